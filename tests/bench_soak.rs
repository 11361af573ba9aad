//! `sylva bench soak` runs end to end with a handful of jobs: real `sylva serve` and
//! `sylva worker` processes, seeded cancels, one SIGKILL of the server half-way, and a table
//! in which every job is accounted for and nothing is lost. A smoke test of the benchmark, not
//! a timing assertion.

mod common;

use common::{bench, table_row};

#[test]
fn bench_soak_runs_jobs_across_a_sigkill_and_loses_nothing() {
    let (stdout, stderr) = bench(&[
        "soak",
        "--jobs",
        "6",
        "--workers",
        "2",
        "--seed",
        "1",
        "--cancel-share",
        "0.5",
        "--pollers",
        "2",
    ]);
    let row = table_row(
        &stdout,
        "| jobs | workers | succeeded | canceled | failed | lost | jobs/hour | requests | p50 ms | p99 ms | unanswered | restart |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    );
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
