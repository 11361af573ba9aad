//! `sylva bench load` runs end to end: the in-process API on SQLite answers the clients and
//! the table comes out. A smoke test of the benchmark, not a timing assertion.

mod common;

use common::{bench, table_row};

#[test]
fn bench_load_prints_a_table_with_requests_on_sqlite() {
    let (stdout, stderr) = bench(&[
        "load",
        "--database",
        "sqlite",
        "--clients",
        "2",
        "--seconds",
        "1",
        "--jobs",
        "20",
    ]);
    let row = table_row(
        &stdout,
        "| database | clients | requests | requests/s | p50 ms | p99 ms | errors |",
        "|---|---|---|---|---|---|---|",
    );
    assert_eq!(row[0], "sqlite");
    assert_eq!(row[1], "2");
    let requests: u64 = row[2].parse().expect("requests");
    assert!(requests > 0, "no request answered: {stdout}");
    assert_eq!(row[6], "0", "errors: {stdout}\n{stderr}");
}
