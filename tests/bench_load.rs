//! `sylva bench load` runs end to end: the in-process API on SQLite answers the clients and
//! the table comes out. A smoke test of the benchmark, not a timing assertion.

use std::process::Command;

#[test]
fn bench_load_prints_a_table_with_requests_on_sqlite() {
    let out = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args(["bench", "load", "--database", "sqlite", "--clients", "2"])
        .args(["--seconds", "1", "--jobs", "20"])
        // Authentication off, whatever the environment says.
        .env_remove("SYLVA_TOKEN")
        .output()
        .expect("run sylva bench load");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "exit {}:\n{stdout}\n{stderr}",
        out.status
    );
    let mut lines = stdout.lines();
    assert_eq!(
        lines.next(),
        Some("| database | clients | requests | requests/s | p50 ms | p99 ms | errors |"),
        "{stdout}"
    );
    assert_eq!(lines.next(), Some("|---|---|---|---|---|---|---|"));
    let row: Vec<&str> = lines
        .next()
        .expect("one row")
        .split('|')
        .map(str::trim)
        .filter(|c| !c.is_empty())
        .collect();
    assert_eq!(row[0], "sqlite");
    assert_eq!(row[1], "2");
    let requests: u64 = row[2].parse().expect("requests");
    assert!(requests > 0, "no request answered: {stdout}");
    assert_eq!(row[6], "0", "errors: {stdout}\n{stderr}");
}
