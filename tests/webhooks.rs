//! Webhooks through the real server: signed deliveries to a receiver on loopback that fails
//! at first, retried with growing gaps and delivered once; pending deliveries surviving a
//! SIGKILL; private targets refused at submission and again at delivery time; per-key secret
//! rotation with a grace period.

mod common;

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode as AxumStatus};
use common::*;
use hmac::{Hmac, KeyInit, Mac};
use reqwest::{Client, StatusCode};
use serde_json::{Value, json};
use sha2::Sha256;

/// One request the receiver got.
#[derive(Debug, Clone)]
struct Hit {
    at: Instant,
    headers: HeaderMap,
    body: Bytes,
    answered: u16,
}

impl Hit {
    fn header(&self, name: &str) -> &str {
        self.headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
    }
}

/// A webhook receiver on 127.0.0.1: records every request; answers 500 to the first
/// `fail_first`, 503 while `down`, 204 otherwise.
#[derive(Clone, Default)]
struct Receiver {
    hits: Arc<Mutex<Vec<Hit>>>,
    fail_first: Arc<AtomicUsize>,
    down: Arc<AtomicBool>,
}

async fn receive(State(r): State<Receiver>, headers: HeaderMap, body: Bytes) -> AxumStatus {
    let failing = r
        .fail_first
        .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
        .is_ok();
    let status = if failing {
        AxumStatus::INTERNAL_SERVER_ERROR
    } else if r.down.load(Ordering::SeqCst) {
        AxumStatus::SERVICE_UNAVAILABLE
    } else {
        AxumStatus::NO_CONTENT
    };
    r.hits.lock().expect("hits").push(Hit {
        at: Instant::now(),
        headers,
        body,
        answered: status.as_u16(),
    });
    status
}

impl Receiver {
    /// Starts a receiver; returns it and its URL.
    async fn start(fail_first: usize) -> (Receiver, String) {
        let r = Receiver::default();
        r.fail_first.store(fail_first, Ordering::SeqCst);
        let app = axum::Router::new()
            .route("/hook", axum::routing::post(receive))
            .with_state(r.clone());
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind receiver");
        let addr = listener.local_addr().expect("addr");
        tokio::spawn(async move {
            let _ = axum::serve(listener, app).await;
        });
        (r, format!("http://{addr}/hook"))
    }

    fn hits(&self) -> Vec<Hit> {
        self.hits.lock().expect("hits").clone()
    }

    /// Waits until `done(hits)` holds.
    async fn wait(&self, what: &str, timeout: Duration, done: impl Fn(&[Hit]) -> bool) {
        poll_until(timeout, 20, async || {
            let hits = self.hits();
            if done(&hits) {
                return Ok(());
            }
            Err(format!("waiting for {what}: {hits:?}"))
        })
        .await;
    }
}

/// Checks a `Sylva-Signature` the way a receiver would, with nothing from Sylva's code:
/// HMAC-SHA256 keyed with the secret's bytes over `<t>.<body>`, compared in constant time.
fn signature_verifies(secret: &str, hit: &Hit) -> bool {
    let header = hit.header("sylva-signature");
    let Some(t) = header
        .split(',')
        .find_map(|p| p.strip_prefix("t="))
        .and_then(|t| t.parse::<i64>().ok())
    else {
        return false;
    };
    let Some(sig) = header
        .split(',')
        .find_map(|p| p.strip_prefix("v1="))
        .and_then(|s| hex::decode(s).ok())
    else {
        return false;
    };
    let mut mac = Hmac::<Sha256>::new_from_slice(secret.as_bytes()).expect("key");
    mac.update(format!("{t}.").as_bytes());
    mac.update(&hit.body);
    mac.verify_slice(&sig).is_ok()
}

/// Sends `req`, asserting a 2xx answer; its JSON body.
async fn ok_json(req: reqwest::RequestBuilder) -> Value {
    let r = send(req).await.error_for_status().expect("2xx");
    r.json().await.expect("json")
}

/// The webhook secret of `token` (none: the anonymous owner's).
async fn secret(c: &Client, base: &str, token: &str) -> String {
    let v = ok_json(
        c.get(format!("{base}/v1/webhooks/secret"))
            .bearer_auth(token),
    )
    .await;
    assert_eq!(v["algorithm"], "HMAC-SHA256");
    v["secret"].as_str().expect("secret").to_string()
}

/// The webhook and deliveries of `job`.
async fn deliveries(c: &Client, base: &str, job: &str) -> Value {
    ok_json(c.get(format!("{base}/v1/jobs/{job}/webhooks"))).await
}

/// Polls the job's deliveries until `done` holds; returns them.
async fn wait_deliveries(
    c: &Client,
    base: &str,
    job: &str,
    timeout: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    poll_until(timeout, 50, async || {
        let d = deliveries(c, base, job).await;
        if done(&d) {
            return Ok(d);
        }
        Err(d.to_string())
    })
    .await
}

/// The first delivery of a job's deliveries.
fn first_delivery(d: &Value) -> &Value {
    &d["deliveries"][0]
}

/// Cancels `job`, asserting a 2xx answer.
async fn cancel(c: &Client, base: &str, job: &str) {
    let r = send(c.post(format!("{base}/v1/jobs/{job}/cancel"))).await;
    r.error_for_status().expect("202");
}

/// `flags`, then [`FAST`].
fn fast(flags: &[&'static str]) -> Vec<&'static str> {
    [flags, FAST].concat()
}

/// The body of a job over `inputs` with `webhook`.
fn hooked(inputs: &Value, webhook: Value) -> Value {
    json!({ "inputs": inputs, "webhook": webhook })
}

/// Fast retries for tests: 200 ms doubling up to 2 s, looked for every 50 ms.
const FAST: &[&str] = &[
    "--webhook-allow-private",
    "--webhook-backoff-ms",
    "200",
    "--webhook-backoff-max-ms",
    "2000",
    "--webhook-poll-ms",
    "50",
    "--webhook-timeout-secs",
    "2",
];

async fn deliveries_are_signed_retried_with_growing_gaps_and_delivered_once(db: Db) {
    let fx = fixture();
    let flags = fast(&["--workers", "0", "--token", "alpha,bravo"]);
    let srv = db.serve(&fx.data, &flags);
    let base = srv.base.clone();
    let c = keyed_client("alpha");
    let (receiver, url) = Receiver::start(3).await;

    let inputs = upload_inputs(&c, &base, &fx).await;
    let body =
        json!({ "inputs": inputs, "params": { "until": "ingest" }, "webhook": { "url": url } });
    let job = create_job(&c, &base, &body).await;
    let id = id_of(&job);
    assert_eq!(job["webhook"]["url"], url.as_str());
    assert_eq!(
        job["webhook"]["events"],
        json!(["job.succeeded", "job.failed", "job.canceled"])
    );
    cancel(&c, &base, &id).await;

    receiver
        .wait("four attempts", Duration::from_secs(30), |h| h.len() >= 4)
        .await;
    let d = wait_deliveries(&c, &base, &id, Duration::from_secs(10), |d| {
        first_delivery(d)["state"] == "delivered"
    })
    .await;
    // Nothing more comes once it was acknowledged.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let hits = receiver.hits();
    assert_eq!(
        hits.iter().map(|h| h.answered).collect::<Vec<_>>(),
        [500, 500, 500, 204],
        "{hits:?}"
    );
    assert_eq!(d["deliveries"].as_array().map(Vec::len), Some(1), "{d}");
    let rec = first_delivery(&d);
    assert_eq!(rec["event"], "job.canceled");
    assert_eq!(rec["attempts"], 4);
    assert_eq!(rec["last_status"], 204);
    assert!(rec["next_attempt_at"].is_null() && rec["finished_at"].is_string());

    // Every attempt: the same delivery id, body and event, signed with alpha's secret over
    // a timestamp that is now.
    let alpha = secret(&c, &base, "alpha").await;
    let bravo = secret(&c, &base, "bravo").await;
    assert_ne!(alpha, bravo, "each token has its own secret");
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("clock")
        .as_secs() as i64;
    for (n, h) in hits.iter().enumerate() {
        assert_eq!(h.header("sylva-delivery"), rec["id"].as_str().expect("id"));
        assert_eq!(h.header("sylva-event"), "job.canceled");
        assert_eq!(h.header("sylva-attempt"), (n + 1).to_string());
        assert_eq!(h.header("content-type"), "application/json");
        assert_eq!(h.body, hits[0].body);
        let t: i64 = h.header("sylva-timestamp").parse().expect("timestamp");
        assert!((now - t).abs() < 60, "timestamp {t} is not now ({now})");
        assert!(
            h.header("sylva-signature")
                .starts_with(&format!("t={t},v1=")),
            "{}",
            h.header("sylva-signature")
        );
        assert!(signature_verifies(&alpha, h), "attempt {n} does not verify");
        assert!(
            !signature_verifies(&bravo, h),
            "another token's secret verifies"
        );
    }
    let mut tampered = hits[0].clone();
    tampered.body = Bytes::from(hits[0].body.to_vec().repeat(2));
    assert!(!signature_verifies(&alpha, &tampered));
    let body: Value = serde_json::from_slice(&hits[0].body).expect("json body");
    assert_eq!(body["id"], rec["id"]);
    assert_eq!(body["type"], "job.canceled");
    assert_eq!(body["data"]["job"]["id"], id.as_str());
    assert_eq!(body["data"]["job"]["state"], "canceled");
    assert_eq!(body["data"]["job"]["href"], format!("/v1/jobs/{id}"));

    // Backoff: each gap at least half its nominal delay (200, 400, 800 ms), and growing.
    let gaps: Vec<u128> = hits
        .windows(2)
        .map(|w| (w[1].at - w[0].at).as_millis())
        .collect();
    assert!(
        gaps[0] >= 95 && gaps[1] >= 195 && gaps[2] >= 395,
        "gaps {gaps:?}"
    );
    assert!(gaps[2] > gaps[0], "gaps do not grow: {gaps:?}");
}
on_both_databases!(deliveries_are_signed_retried_with_growing_gaps_and_delivered_once);

async fn pending_deliveries_survive_a_killed_server(db: Db) {
    let fx = fixture();
    let flags = fast(&["--workers", "0"]);
    let mut srv = db.serve(&fx.data, &flags);
    let c = client();
    let (receiver, url) = Receiver::start(0).await;
    receiver.down.store(true, Ordering::SeqCst);
    let inputs = upload_inputs(&c, &srv.base, &fx).await;
    let id = submit(&c, &srv.base, &hooked(&inputs, json!({ "url": url }))).await;
    cancel(&c, &srv.base, &id).await;
    let d = wait_deliveries(&c, &srv.base, &id, Duration::from_secs(20), |d| {
        first_delivery(d)["attempts"].as_i64() >= Some(2)
    })
    .await;
    assert_eq!(first_delivery(&d)["state"], "pending");
    assert_eq!(first_delivery(&d)["last_status"], 503);
    let delivery = first_delivery(&d)["id"].as_str().expect("id").to_string();

    // SIGKILL: no shutdown, the delivery is left pending in the database.
    srv.kill();
    let before = receiver.hits().len();
    assert!(before >= 2 && receiver.hits().iter().all(|h| h.answered == 503));
    receiver.down.store(false, Ordering::SeqCst);

    let srv = db.serve(&fx.data, &flags);
    receiver
        .wait(
            "the delivery after the restart",
            Duration::from_secs(30),
            |h| h.iter().any(|h| h.answered == 204),
        )
        .await;
    let d = wait_deliveries(&c, &srv.base, &id, Duration::from_secs(10), |d| {
        first_delivery(d)["state"] == "delivered"
    })
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let hits = receiver.hits();
    assert_eq!(
        hits.iter().filter(|h| h.answered == 204).count(),
        1,
        "{hits:?}"
    );
    assert!(hits.iter().all(|h| h.header("sylva-delivery") == delivery));
    assert_eq!(d["deliveries"].as_array().map(Vec::len), Some(1));
}
on_both_databases!(pending_deliveries_survive_a_killed_server);

/// Submits a job over `inputs` with `webhook`, asserting a 422 that names a `webhook` field;
/// the problem.
async fn refused(c: &Client, base: &str, inputs: &Value, webhook: Value) -> Value {
    let r = c
        .post(format!("{base}/v1/jobs"))
        .json(&hooked(inputs, webhook));
    let p = send_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(
        p["errors"]
            .as_array()
            .is_some_and(|e| e.iter().any(|e| e["field"]
                .as_str()
                .is_some_and(|f| f.starts_with("webhook")))),
        "{p}"
    );
    p
}

#[tokio::test(flavor = "multi_thread")]
async fn private_and_malformed_targets_are_refused_at_submission() {
    let fx = fixture();
    let srv = serve(&fx.data, &["--workers", "0"]);
    let c = client();
    let inputs = upload_inputs(&c, &srv.base, &fx).await;
    for url in [
        "http://127.0.0.1:9/hook",
        "http://localhost:9/hook",
        "http://[::1]/hook",
        "http://[::ffff:127.0.0.1]/hook",
        "http://10.1.2.3/hook",
        "http://192.168.0.1/hook",
        "http://169.254.169.254/latest/meta-data/",
        "http://[fd00::1]/hook",
        "http://[fe80::1]/hook",
        "http://0.0.0.0/hook",
        "http://224.0.0.1/hook",
    ] {
        let p = refused(&c, &srv.base, &inputs, json!({ "url": url })).await;
        assert!(
            p["detail"]
                .as_str()
                .is_some_and(|d| d.contains("--webhook-allow-private")),
            "{url}: {p}"
        );
    }
    for bad in [
        json!({ "url": "ftp://hooks.example/x" }),
        json!({ "url": "https://user:secret@hooks.example/x" }),
        json!({ "url": format!("https://hooks.example/{}", "a".repeat(3000)) }),
        json!({ "url": "not a url" }),
        json!({ "url": "https://8.8.8.8/x", "events": ["job.exploded"] }),
        json!({ "url": "https://8.8.8.8/x", "events": [] }),
        json!({ "url": "https://8.8.8.8/x", "secret": "mine" }),
        json!({ "events": ["job.failed"] }),
        json!("https://8.8.8.8/x"),
    ] {
        refused(&c, &srv.base, &inputs, bad).await;
    }
    // No job was created by any of them.
    let jobs: Value = get_json(&c, &format!("{}/v1/jobs", srv.base)).await;
    assert_eq!(jobs["jobs"].as_array().map(Vec::len), Some(0), "{jobs}");
    // A public literal address is accepted without any lookup.
    let twice = json!({ "url": "https://8.8.8.8/x", "events": ["job.failed", "job.failed"] });
    let job = create_job(&c, &srv.base, &hooked(&inputs, twice)).await;
    assert_eq!(job["webhook"]["events"], json!(["job.failed"]));

    // The webhook is part of the request an Idempotency-Key stands for.
    let keyed = |hook: &str| {
        c.post(format!("{}/v1/jobs", srv.base))
            .header("Idempotency-Key", "hooked-once")
            .json(&hooked(&inputs, json!({ "url": hook })))
    };
    let first = send_json(keyed("https://8.8.8.8/a")).await;
    let again = send_json(keyed("https://8.8.8.8/a")).await;
    assert_eq!(first["id"], again["id"]);
    send_problem(keyed("https://8.8.8.8/b"), StatusCode::UNPROCESSABLE_ENTITY).await;

    // A one-request multipart submission takes a `webhook` part, checked the same way.
    let form = multipart(&[("lidar", &fx.lidar), ("colmap", &fx.colmap_zip)])
        .text("webhook", r#"{"url": "http://10.0.0.1/hook"}"#);
    let r = c.post(format!("{}/v1/jobs", srv.base)).multipart(form);
    send_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    drop(srv);

    // An allowed network lets its addresses through, and only those.
    let srv = serve(
        &fx.data,
        &["--workers", "0", "--webhook-allow-cidr", "127.0.0.0/8"],
    );
    let allowed = json!({ "url": "http://127.0.0.1:9/hook" });
    create_job(&c, &srv.base, &hooked(&inputs, allowed)).await;
    let outside = json!({ "url": "http://10.1.2.3/hook" });
    refused(&c, &srv.base, &inputs, outside).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_target_no_longer_allowed_is_refused_at_delivery_and_says_why() {
    let fx = fixture();
    let (receiver, url) = Receiver::start(0).await;
    let c = client();
    // Accepted while the server allowed private targets ...
    let flags = fast(&["--workers", "0"]);
    let srv = serve(&fx.data, &flags);
    let inputs = upload_inputs(&c, &srv.base, &fx).await;
    let id = submit(&c, &srv.base, &hooked(&inputs, json!({ "url": url }))).await;
    drop(srv);
    // ... then delivered by a server that does not: the receiver is never contacted.
    let strict: Vec<&str> = flags
        .iter()
        .copied()
        .filter(|f| *f != "--webhook-allow-private")
        .chain(["--webhook-max-attempts", "2"])
        .collect();
    let srv = serve(&fx.data, &strict);
    cancel(&c, &srv.base, &id).await;
    let d = wait_deliveries(&c, &srv.base, &id, Duration::from_secs(20), |d| {
        first_delivery(d)["state"] == "failed"
    })
    .await;
    let rec = first_delivery(&d);
    assert_eq!(rec["attempts"], 2);
    assert!(rec["last_status"].is_null());
    assert!(
        rec["last_error"]
            .as_str()
            .is_some_and(|e| e.contains("refused") && e.contains("loopback")),
        "{rec}"
    );
    assert!(receiver.hits().is_empty(), "{:?}", receiver.hits());
}

#[tokio::test(flavor = "multi_thread")]
async fn a_finished_job_announces_its_stages_and_its_success() {
    let fx = fixture();
    let flags = fast(&[]);
    let srv = serve(&fx.data, &flags);
    let c = client();
    let (receiver, url) = Receiver::start(0).await;
    let inputs = upload_inputs(&c, &srv.base, &fx).await;
    let job = create_job(
        &c,
        &srv.base,
        &json!({
            "inputs": inputs,
            "params": { "until": "ingest" },
            "webhook": { "url": url, "events": ["stage.finished", "job.succeeded"] },
        }),
    )
    .await;
    let id = id_of(&job);
    let (done, _) = wait_job(&c, &srv.base, &id, Duration::from_secs(120), is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    receiver
        .wait("two events", Duration::from_secs(20), |h| h.len() >= 2)
        .await;
    let secret = secret(&c, &srv.base, "").await;
    let mut events: Vec<(String, Value)> = receiver
        .hits()
        .iter()
        .map(|h| {
            assert!(signature_verifies(&secret, h));
            let body: Value = serde_json::from_slice(&h.body).expect("json");
            (h.header("sylva-event").to_string(), body)
        })
        .collect();
    events.sort_by(|a, b| a.0.cmp(&b.0));
    assert_eq!(events.len(), 2, "{events:?}");
    assert_eq!(events[0].0, "job.succeeded");
    assert_eq!(events[0].1["data"]["job"]["state"], "succeeded");
    assert_eq!(events[1].0, "stage.finished");
    assert_eq!(events[1].1["data"]["stage"]["name"], "ingest");
    let d = deliveries(&c, &srv.base, &id).await;
    assert_eq!(d["webhook"]["url"], url.as_str());
}

/// Whether any `v1=` entry of the hit's signature verifies under `secret`.
fn any_signature_verifies(secret: &str, hit: &Hit) -> bool {
    let header = hit.header("sylva-signature");
    let t: Vec<&str> = header.split(',').filter(|p| p.starts_with("t=")).collect();
    header
        .split(',')
        .filter(|p| p.starts_with("v1="))
        .any(|v1| {
            let mut one = hit.clone();
            one.headers.insert(
                "sylva-signature",
                format!("{},{v1}", t.first().copied().unwrap_or(""))
                    .parse()
                    .expect("header"),
            );
            signature_verifies(secret, &one)
        })
}

/// Rotation is per key: alice's new secret leaves bob's alone, and during the grace period a
/// delivery carries the new and the old signature, either of which verifies.
#[tokio::test(flavor = "multi_thread")]
async fn a_rotation_changes_one_keys_secret_and_both_secrets_verify_during_the_grace() {
    let fx = fixture();
    let db = Db::sqlite();
    let alice_key = db.create_key(&fx.data, "alice", &[]);
    let bob_key = db.create_key(&fx.data, "bob", &[]);
    let flags = fast(&["--workers", "0"]);
    let srv = db.serve(&fx.data, &flags);
    let base = srv.base.clone();
    let c = client();
    let old = secret(&c, &base, &alice_key).await;
    let bob_before = secret(&c, &base, &bob_key).await;
    let rotate = c.post(format!("{base}/v1/webhooks/secret/rotate"));
    let rotated = ok_json(rotate.bearer_auth(&alice_key)).await;
    let new = rotated["secret"].as_str().expect("secret").to_string();
    assert_ne!(new, old);
    assert_eq!(rotated["generation"], 1);
    assert_eq!(rotated["previous"]["secret"], old.as_str(), "{rotated}");
    assert_eq!(secret(&c, &base, &alice_key).await, new);
    assert_eq!(
        secret(&c, &base, &bob_key).await,
        bob_before,
        "bob's secret moved"
    );

    let (receiver, url) = Receiver::start(0).await;
    let alice = keyed_client(&alice_key);
    let inputs = upload_inputs(&alice, &base, &fx).await;
    let id = submit(&alice, &base, &hooked(&inputs, json!({ "url": url }))).await;
    cancel(&alice, &base, &id).await;
    receiver
        .wait("one delivery", Duration::from_secs(30), |h| !h.is_empty())
        .await;
    let hit = &receiver.hits()[0];
    assert_eq!(
        hit.header("sylva-signature").matches("v1=").count(),
        2,
        "{}",
        hit.header("sylva-signature")
    );
    assert!(any_signature_verifies(&new, hit));
    assert!(any_signature_verifies(&old, hit));
    assert!(!any_signature_verifies(&bob_before, hit));
}
