//! openapi.yaml is the contract: every routed path is in it, every path in it is routed.

mod common;

use std::collections::BTreeSet;

use common::*;
use sylva::api::ROUTES;

/// (METHOD, path) pairs of openapi.yaml's `paths`.
fn openapi_operations() -> BTreeSet<(String, String)> {
    let text = sylva::api::service::OPENAPI_YAML;
    let mut ops = BTreeSet::new();
    let mut in_paths = false;
    let mut path = None;
    for line in text.lines() {
        if !line.starts_with(' ') && !line.is_empty() {
            in_paths = line.starts_with("paths:");
            continue;
        }
        if !in_paths {
            continue;
        }
        if let Some(p) = line.strip_prefix("  /").and_then(|l| l.strip_suffix(':')) {
            path = Some(format!("/{p}"));
        } else if let Some(m) = line.strip_prefix("    ").and_then(|l| l.strip_suffix(':'))
            && ["get", "put", "post", "delete", "head", "patch", "options"].contains(&m)
            && let Some(p) = &path
        {
            ops.insert((m.to_uppercase(), p.clone()));
        }
    }
    ops
}

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
    let upload: serde_json::Value = c
        .post(format!("{}/v1/uploads", srv.base))
        .json(&serde_json::json!({ "kind": "lidar", "filename": "a.las", "size": 10 }))
        .send()
        .await
        .expect("create upload")
        .json()
        .await
        .expect("json");
    let upload_id = upload["id"].as_str().expect("id");
    for (method, path) in ROUTES {
        if *method == "HEAD" {
            let url = path.replace("{id}", upload_id);
            let r = c
                .head(format!("{}{url}", srv.base))
                .send()
                .await
                .expect("head");
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
    let served = c
        .get(format!("{}/openapi.yaml", srv.base))
        .send()
        .await
        .expect("get");
    assert_eq!(served.headers()["content-type"], "application/yaml");
    let served = served.text().await.expect("text");
    let file = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/openapi.yaml"))
        .expect("read");
    assert_eq!(served, file);
}
