//! `sylva bench soak` runs end to end with a handful of jobs: real `sylva serve` and
//! `sylva worker` processes, seeded cancels, one SIGKILL of the server half-way, and a table
//! in which every job is accounted for and nothing is lost. A smoke test of the benchmark, not
//! a timing assertion.

use std::process::Command;

#[test]
fn bench_soak_runs_jobs_across_a_sigkill_and_loses_nothing() {
    let out = Command::new(env!("CARGO_BIN_EXE_sylva"))
        .args([
            "bench",
            "soak",
            "--jobs",
            "6",
            "--workers",
            "2",
            "--seed",
            "1",
        ])
        .args(["--cancel-share", "0.5", "--pollers", "2"])
        // Authentication off, whatever the environment says.
        .env_remove("SYLVA_TOKEN")
        .output()
        .expect("run sylva bench soak");
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
        Some(
            "| jobs | workers | succeeded | canceled | failed | lost | jobs/hour | requests | p50 ms | p99 ms | unanswered | restart |"
        ),
        "{stdout}"
    );
    assert_eq!(
        lines.next(),
        Some("|---|---|---|---|---|---|---|---|---|---|---|---|")
    );
    let row: Vec<&str> = lines
        .next()
        .expect("one row")
        .split('|')
        .map(str::trim)
        .filter(|c| !c.is_empty())
        .collect();
    let num = |i: usize| -> u64 { row[i].parse().expect("a whole number") };
    assert_eq!(num(0), 6, "every job accepted: {stdout}\n{stderr}");
    assert_eq!(row[1], "2");
    assert_eq!(
        num(2) + num(3) + num(4),
        6,
        "every job finished: {stdout}\n{stderr}"
    );
    assert_eq!(num(4), 0, "no job failed: {stdout}\n{stderr}");
    assert_eq!(num(5), 0, "nothing lost: {stdout}\n{stderr}");
    assert!(num(7) > 0, "no request answered: {stdout}");
    assert!(
        row[11].starts_with("serve SIGKILLed"),
        "the server was killed and restarted: {stdout}\n{stderr}"
    );
    assert!(stderr.contains("database integrity: ok"), "{stderr}");
}
