//! openapi.yaml is the contract: every routed path is in it, every path in it is routed.

mod common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::*;
use serde_json::json;
use sylva::api::ROUTES;

fn routed_operations() -> BTreeSet<(String, String)> {
    ROUTES
        .iter()
        .map(|(m, p)| (m.to_string(), p.replace("{*", "{")))
        .collect()
}

#[test]
fn every_routed_path_is_in_openapi_and_every_openapi_path_is_routed() {
    let spec = openapi_operations();
    let routed = routed_operations();
    assert!(spec.len() > 20, "parsed too few operations: {spec:?}");
    let undocumented: Vec<_> = routed.difference(&spec).collect();
    let unrouted: Vec<_> = spec.difference(&routed).collect();
    assert!(
        undocumented.is_empty(),
        "routed but not in openapi.yaml: {undocumented:?}"
    );
    assert!(
        unrouted.is_empty(),
        "in openapi.yaml but not routed: {unrouted:?}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn every_listed_route_reaches_a_handler() {
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = serve(&dir.path().join("data"), &["--workers", "0"]);
    let c = client();
    let upload = open_upload(&c, &srv.base, "lidar", "a.las", 10).await;
    let upload_id = upload["id"].as_str().expect("id");
    for (method, path) in ROUTES {
        if *method == "HEAD" {
            let url = path.replace("{id}", upload_id);
            let r = send(c.head(format!("{}{url}", srv.base))).await;
            assert_eq!(r.status(), reqwest::StatusCode::OK, "HEAD {path}");
            continue;
        }
        let url = path
            .replace("{id}", "0123456789abcdef0123456789abcdef")
            .replace("{n}", "0")
            .replace("{*name}", "ingest/report.json");
        let r = c
            .request(
                sylva::api::route_method(method),
                format!("{}{url}", srv.base),
            )
            .header("content-type", "application/json")
            .body(if *method == "GET" || *method == "HEAD" {
                ""
            } else {
                "{}"
            })
            .send()
            .await
            .expect("request");
        let status = r.status();
        assert_ne!(
            status,
            reqwest::StatusCode::METHOD_NOT_ALLOWED,
            "{method} {path}"
        );
        let body = r.text().await.expect("body");
        assert!(
            !body.contains("no-such-route"),
            "{method} {path} → {status} {body}"
        );
    }
    // The served contract is the file in the repository.
    let served = send(c.get(format!("{}/openapi.yaml", srv.base))).await;
    assert_eq!(served.headers()["content-type"], "application/yaml");
    let served = served.text().await.expect("text");
    let file = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml"))
        .expect("read");
    assert_eq!(served, file);
}

/// Examples per operation and phase (schemathesis `--max-examples`): enough for each check to
/// see every operation many times, small enough for two to three minutes on two cores.
/// `SYLVA_TEST_FUZZ_EXAMPLES` overrides it (to search harder by hand).
const FUZZ_EXAMPLES: &str = "200";

/// Fixed seed, so a failure can be replayed with the command the test prints.
/// `SYLVA_TEST_FUZZ_SEED` overrides it (to search elsewhere by hand).
const FUZZ_SEED: &str = "20240701";

/// Longest the whole schemathesis run may take before the test gives up on it.
const FUZZ_DEADLINE: Duration = Duration::from_secs(15 * 60);

/// Where schemathesis is: `SYLVA_TEST_SCHEMATHESIS` (its path, or `none` to skip), else the
/// test virtual environment that scripts/test makes (target/test-venv), else `PATH`.
fn schemathesis() -> Result<PathBuf, String> {
    test_tool("SYLVA_TEST_SCHEMATHESIS", "schemathesis")
}

/// Real resources for the fuzzer to find through the listings and links: completed uploads
/// and an open one, a canceled job and, newest (first in `GET /v1/jobs`, which the links
/// follow), a job that succeeded and has artifacts. Queued jobs appear when the fuzzer retries.
async fn seed_resources(data: &Path, base: &str, key: &str) {
    let c = keyed_client(key);
    let fx = fixture();
    let inputs = upload_inputs(&c, base, &fx).await;
    let open = json!({ "kind": "field_dbh", "filename": "open.csv", "size": 100 });
    let r = send(c.post(format!("{base}/v1/uploads")).json(&open)).await;
    r.error_for_status().expect("201");
    let body = job_until(&inputs, "ingest");
    let id = submit(&c, base, &body).await;
    let r = send(c.post(format!("{base}/v1/jobs/{id}/cancel"))).await;
    assert_eq!(r.status(), reqwest::StatusCode::ACCEPTED);
    // One job runs (ingest only, no GPU) on a worker of its own, which then stops: the server
    // under test has none, so nothing heavy runs while it is fuzzed.
    let mut w = worker(data, &["--poll-ms", "50"]);
    let id = submit(&c, base, &body).await;
    let (job, _) = wait_job(&c, base, &id, Duration::from_secs(180), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert!(
        job["artifacts"].as_array().is_some_and(|a| !a.is_empty()),
        "{job}"
    );
    w.kill();
}

/// schemathesis (PyPI) against the live server's /openapi.yaml with auth on and every
/// default check: status codes, content types, headers and bodies as documented, negative
/// data rejected, a missing token refused, unsupported methods answered 405 with `Allow`,
/// deleted resources gone. Skips, saying why, where schemathesis is not installed.
#[tokio::test(flavor = "multi_thread")]
async fn schemathesis_finds_no_contract_violation() {
    let exe = match schemathesis() {
        Ok(exe) => exe,
        Err(why) => {
            sylva::testing::skip("schemathesis", &format!("contract fuzzing: {why}"));
            return;
        }
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    // No workers: nothing heavy runs while the API is fuzzed. Small, fixed limits: the answers
    // must not depend on the free space of the machine the test runs on.
    // A managed key, as a cloud backend would hold (`sylva keys create`).
    let key = Db::sqlite().create_key(&data, "fuzzer", &[]);
    let srv = serve(
        &data,
        &[
            "--workers",
            "0",
            "--max-upload-bytes",
            "67108864",
            "--min-free-bytes",
            "0",
        ],
    );
    seed_resources(&data, &srv.base, &key).await;

    let seed = std::env::var("SYLVA_TEST_FUZZ_SEED").unwrap_or(FUZZ_SEED.into());
    let examples = std::env::var("SYLVA_TEST_FUZZ_EXAMPLES").unwrap_or(FUZZ_EXAMPLES.into());
    let auth = format!("Authorization: Bearer {key}");
    let schema = format!("{}/openapi.yaml", srv.base);
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/schemathesis.toml");
    let args = [
        "--config-file",
        config,
        "run",
        schema.as_str(),
        "--header",
        auth.as_str(),
        "--seed",
        seed.as_str(),
        "--max-examples",
        examples.as_str(),
        "--workers",
        "1",
        "--request-timeout",
        "20",
        "--generation-database",
        "none",
        "--no-color",
    ];
    let started = Instant::now();
    let out_path = dir.path().join("schemathesis.out");
    let out = std::fs::File::create(&out_path).expect("output file");
    let mut child = std::process::Command::new(&exe)
        .args(args)
        .current_dir(dir.path())
        .stdout(out.try_clone().expect("clone"))
        .stderr(out)
        .spawn()
        .unwrap_or_else(|e| panic!("could not run {}: {e}", exe.display()));
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break Some(s);
        }
        if started.elapsed() > FUZZ_DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    let output = std::fs::read_to_string(&out_path).unwrap_or_default();
    // Its warnings (operations it could not reach) and summary, also when it passes.
    let summary = output
        .find("=== WARNINGS ===")
        .or_else(|| output.find("=== SUMMARY ==="))
        .map(|at| &output[at..])
        .unwrap_or_default();
    eprintln!(
        "schemathesis ran {:.0} s: {} {}\n{summary}",
        started.elapsed().as_secs_f64(),
        exe.display(),
        args.join(" ")
    );
    assert!(
        status.is_some_and(|s| s.success()),
        "schemathesis found contract violations ({status:?}):\n{output}\n\nserver log:\n{}",
        srv.stderr_text()
    );
    // A run that tested nothing would also exit 0.
    assert!(
        output.contains("passed") && !output.contains("No operations"),
        "schemathesis tested nothing:\n{output}"
    );
}
