//! Tenancy through real `sylva serve` processes: each managed key sees only its own records,
//! on every route openapi.yaml lists with a path parameter (so a new route without the
//! ownership check fails here), on SQLite and on PostgreSQL; admin keys; per-key idempotency;
//! revocation seen by two API processes at once; expiry; per-key webhook secret rotation.

mod common;

use std::time::Duration;

use common::*;
use reqwest::{Client, Method, StatusCode};
use serde_json::{Value, json};

/// (METHOD, path) of every operation in openapi.yaml whose path has a parameter.
fn operations_with_path_parameters() -> Vec<(String, String)> {
    openapi_operations()
        .into_iter()
        .filter(|(_, p)| p.contains('{'))
        .collect()
}

/// `path` with its parameters filled: `{id}` by `id`, a part index 0, an artifact name.
fn fill(path: &str, id: &str) -> String {
    path.replace("{id}", id)
        .replace("{n}", "0")
        .replace("{name}", "ingest/report.json")
}

/// `method url` as `c`, with a body for PUT and POST: the status and the JSON answer (null
/// when there is none).
async fn try_route(c: &Client, method: &str, url: &str) -> (StatusCode, Value) {
    let m = Method::from_bytes(method.as_bytes()).expect("method");
    let mut req = c.request(m, url);
    if method == "PUT" {
        req = req.body(vec![0u8; 16]);
    } else if method == "POST" {
        req = req.header("content-type", "application/json").body("{}");
    }
    let r = send(req).await;
    let status = r.status();
    let text = r.text().await.unwrap_or_default();
    (status, serde_json::from_str(&text).unwrap_or(Value::Null))
}

/// The parts of a problem document that must not tell another key's record from a missing
/// one: everything but the request id, with the record's id written as `ID`.
fn comparable(problem: &Value, id: &str) -> Value {
    let mut p = problem.clone();
    if let Some(o) = p.as_object_mut() {
        o.remove("request_id");
        o.remove("instance");
        for v in o.values_mut() {
            if let Some(s) = v.as_str() {
                *v = Value::String(s.replace(id, "ID"));
            }
        }
    }
    p
}

async fn tenancy_matrix(db: Db) {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let alice_key = db.create_key(&data, "alice", &[]);
    let bob_key = db.create_key(&data, "bob", &[]);
    let root_key = db.create_key(&data, "root", &["--admin"]);
    // No workers: alice's job stays queued, so every route finds it as it was.
    let srv = db.serve(&data, &["--workers", "0"]);
    let base = srv.base.clone();
    let (alice, bob, root) = (
        keyed_client(&alice_key),
        keyed_client(&bob_key),
        keyed_client(&root_key),
    );
    let (s, _) = status_of(&client(), &format!("{base}/v1/jobs")).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED, "keys exist: auth is on");

    let inputs = upload_inputs(&alice, &base, &fx).await;
    let upload = inputs["lidar"].as_str().expect("upload id").to_string();
    let job = create_job(&alice, &base, &json!({ "inputs": inputs })).await;
    let job_id = id_of(&job);
    let alice_info: Value = get_json(&alice, &format!("{base}/v1/info")).await;
    let alice_owner = alice_info["caller"]["owner"]
        .as_str()
        .expect("owner")
        .to_string();
    assert!(alice_owner.starts_with("key_"), "{alice_info}");
    assert_eq!(job["owner"], alice_owner.as_str());

    let ops = operations_with_path_parameters();
    assert!(
        ops.len() >= 15,
        "openapi.yaml lists {} such operations",
        ops.len()
    );
    let missing = "0198aaaabbbbccccddddeeeeffff0000";
    for (method, path) in &ops {
        let id = if path.starts_with("/v1/uploads/") {
            &upload
        } else if path.starts_with("/v1/keys/") {
            &alice_owner
        } else {
            &job_id
        };
        let (status, body) = try_route(&bob, method, &format!("{base}{}", fill(path, id))).await;
        assert_eq!(
            status,
            StatusCode::NOT_FOUND,
            "{method} {path}: another key's record must answer 404, got {status}: {body}"
        );
        let (m_status, m_body) =
            try_route(&bob, method, &format!("{base}{}", fill(path, missing))).await;
        assert_eq!(m_status, StatusCode::NOT_FOUND, "{method} {path} (missing)");
        if method != "HEAD" {
            assert_eq!(
                comparable(&body, id),
                comparable(&m_body, missing),
                "{method} {path}: another key's record must answer exactly as a missing one"
            );
        }
    }

    // Nothing bob tried touched alice's records.
    let seen = get_job(&alice, &base, &job_id).await;
    assert_eq!(seen["state"], "queued", "{seen}");
    let u = get_json(&alice, &format!("{base}/v1/uploads/{upload}")).await;
    assert_eq!(u["state"], "complete", "{u}");
    assert_eq!(u["owner"], alice_owner.as_str());

    // Lists: bob's is empty, the admin's shows alice's job with its owner.
    let listed = get_json(&bob, &format!("{base}/v1/jobs")).await;
    assert_eq!(listed["jobs"].as_array().map(Vec::len), Some(0), "{listed}");
    let all = get_json(&root, &format!("{base}/v1/jobs")).await;
    assert!(
        all["jobs"].as_array().is_some_and(|j| j
            .iter()
            .any(|j| j["id"] == job_id.as_str() && j["owner"] == alice_owner.as_str())),
        "{all}"
    );
    // The admin reads and manages alice's records.
    for path in [
        format!("/v1/jobs/{job_id}/log"),
        format!("/v1/uploads/{upload}"),
    ] {
        let (s, _) = status_of(&root, &format!("{base}{path}")).await;
        assert_eq!(s, StatusCode::OK, "{path}");
    }

    // Bob cannot use alice's upload as a job input: the same answer as a missing upload.
    let with_lidar = |lidar: &str| {
        let inputs = json!({ "lidar": lidar, "colmap": inputs["colmap"] });
        bob.post(format!("{base}/v1/jobs"))
            .json(&json!({ "inputs": inputs }))
    };
    let theirs = send(with_lidar(&upload)).await;
    let theirs_status = theirs.status();
    let theirs_body: Value = theirs.json().await.expect("json");
    assert!(theirs_status.is_client_error(), "{theirs_body}");
    let none = send(with_lidar(missing)).await;
    assert_eq!(none.status(), theirs_status);
    let none_body: Value = none.json().await.expect("json");
    assert_eq!(
        comparable(&theirs_body, &upload),
        comparable(&none_body, missing)
    );

    // Idempotency keys are per key: the same value gives bob a job of his own.
    let bob_inputs = upload_inputs(&bob, &base, &fx).await;
    let post = |c: &Client, inputs: &Value| {
        c.post(format!("{base}/v1/jobs"))
            .header("idempotency-key", "nightly-plot-7")
            .json(&json!({ "inputs": inputs }))
    };
    let a = send_json(post(&alice, &inputs)).await;
    let b = send(post(&bob, &bob_inputs)).await;
    assert_eq!(b.status(), StatusCode::ACCEPTED);
    let b: Value = b.json().await.expect("json");
    assert_ne!(a["id"], b["id"], "bob was given alice's job: {b}");
    let a2 = send_json(post(&alice, &inputs)).await;
    assert_eq!(a["id"], a2["id"], "alice's replay gives her job back");

    // Keys over HTTP: admin keys only.
    let keys = format!("{base}/v1/keys");
    let new_key = |c: &Client, key: Value| c.post(&keys).json(&key);
    for c in [&alice, &bob] {
        send_problem(c.get(&keys), StatusCode::FORBIDDEN).await;
        let sneaky = new_key(c, json!({ "name": "sneaky", "admin": true }));
        send_problem(sneaky, StatusCode::FORBIDDEN).await;
    }
    let made = send(new_key(&root, json!({ "name": "carol", "quota_jobs": 2 }))).await;
    assert_eq!(made.status(), StatusCode::CREATED);
    let made: Value = made.json().await.expect("json");
    let carol_key = made["key"].as_str().expect("key").to_string();
    let carol_id = id_of(&made);
    assert_eq!(made["quota_jobs"], 2);
    let (s, _) = status_of(&keyed_client(&carol_key), &format!("{base}/v1/jobs")).await;
    assert_eq!(s, StatusCode::OK, "a key made over HTTP works at once");
    let listed = get_json(&root, &format!("{base}/v1/keys")).await;
    let text = listed.to_string();
    assert!(text.contains("carol") && text.contains("alice"), "{listed}");
    assert!(
        !text.contains(&carol_key[6..]),
        "a listed key shows its key"
    );
    let again = new_key(&root, json!({ "name": "carol" }));
    send_problem(again, StatusCode::CONFLICT).await;
    let carol = format!("{keys}/{carol_id}");
    send_problem(bob.delete(&carol), StatusCode::NOT_FOUND).await;
    assert_eq!(send(root.delete(&carol)).await.status(), StatusCode::OK);
    let (s, _) = status_of(&keyed_client(&carol_key), &format!("{base}/v1/jobs")).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED, "revoked over HTTP");

    // Keys never reach the log.
    let log = srv.stderr_text();
    for key in [&alice_key, &bob_key, &root_key, &carol_key] {
        assert!(!log.contains(&key[6..]), "a key reached the server log");
    }
}

on_both_databases!(tenancy_matrix);

/// GET `url` as `c`: the status and the text of the answer.
async fn status_of(c: &Client, url: &str) -> (StatusCode, String) {
    let r = send(c.get(url)).await;
    let s = r.status();
    (s, r.text().await.unwrap_or_default())
}

/// Two API processes on one database: a revoked key is refused by both on their next request.
async fn revocation_is_seen_by_every_api_process(db: Db) {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let key = db.create_key(&data, "ci", &[]);
    let one = db.serve(&data, &["--workers", "0"]);
    let two = db.serve(&data, &["--workers", "0"]);
    let c = keyed_client(&key);
    for srv in [&one, &two] {
        let (s, body) = status_of(&c, &format!("{}/v1/jobs", srv.base)).await;
        assert_eq!(s, StatusCode::OK, "{body}");
    }
    let listed = db.keys(&data, "list", &[]);
    assert!(
        listed.contains("ci") && listed.contains("active"),
        "{listed}"
    );
    assert!(
        !listed.contains(&key[6..]),
        "the key itself is never listed"
    );
    let revoked = db.keys(&data, "revoke", &["ci"]);
    assert!(revoked.contains("revoked"), "{revoked}");
    for srv in [&one, &two] {
        let (s, body) = status_of(&c, &format!("{}/v1/jobs", srv.base)).await;
        assert_eq!(s, StatusCode::UNAUTHORIZED, "{body}");
        assert!(body.contains("revoked"), "{body}");
    }
    // Refused on the very first request after the revocation: no cache to wait out.
    for srv in [&one, &two] {
        assert!(srv.stderr_text().contains("job database open"));
    }
}

on_both_databases!(revocation_is_seen_by_every_api_process);

#[tokio::test(flavor = "multi_thread")]
async fn an_expired_key_is_refused_and_quotas_are_per_key() {
    let db = Db::sqlite();
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let short = db.create_key(&data, "short", &["--expires", "3s"]);
    let one_job = db.create_key(&data, "one-job", &["--quota-jobs", "1"]);
    let srv = db.serve(&data, &["--workers", "0", "--quota-jobs", "5"]);
    let base = srv.base.clone();
    let (s, _) = status_of(&keyed_client(&short), &format!("{base}/v1/jobs")).await;
    assert_eq!(s, StatusCode::OK);

    // The key's own quota, not the server's 5.
    let c = keyed_client(&one_job);
    let info = get_json(&c, &format!("{base}/v1/info")).await;
    assert_eq!(info["limits"]["quota_jobs"], 1, "{info}");
    assert_eq!(info["caller"]["key"], "one-job");
    let inputs = upload_inputs(&c, &base, &fx).await;
    let body = json!({ "inputs": inputs });
    create_job(&c, &base, &body).await;
    let second = c.post(format!("{base}/v1/jobs")).json(&body);
    send_problem(second, StatusCode::TOO_MANY_REQUESTS).await;

    // Past its expiry the first key is refused, saying why.
    tokio::time::sleep(Duration::from_millis(3200)).await;
    let (s, body) = status_of(&keyed_client(&short), &format!("{base}/v1/jobs")).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED, "{body}");
    assert!(body.contains("expired"), "{body}");
}

#[test]
fn keys_create_refuses_bad_input_clearly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    for (args, says) in [
        (vec!["keys", "create", "--name", " "], "name"),
        (
            vec!["keys", "create", "--name", "x", "--expires", "soon"],
            "RFC 3339",
        ),
        (vec!["keys", "revoke", "nobody"], "no key"),
    ] {
        let err = fails(&mut sylva_command(&args, &data));
        assert!(err.contains(says), "{args:?}: {err}");
    }
    Db::sqlite().create_key(&data, "twice", &[]);
    let err = fails(&mut sylva_command(
        &["keys", "create", "--name", "twice"],
        &data,
    ));
    assert!(err.contains("exists already"), "{err}");
}
