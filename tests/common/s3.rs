//! A throwaway S3-compatible server for tests, on loopback, with one fresh bucket per test.
//!
//! The server is moto's (`moto_server`, from PyPI: MinIO binaries cannot be fetched here);
//! scripts/test installs it into a virtual environment at `target/test-venv`. The first test
//! that asks for a bucket starts one server on a free port of 127.0.0.1; a watchdog process
//! stops it once the test process has exited, however it ended. Every test gets its own
//! bucket. `SYLVA_TEST_MOTO` overrides the search: the path of `moto_server`, or `none` to
//! skip the S3 cases. Where it is absent, [`bucket`] prints why and returns `None`.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A running test server.
pub struct Server {
    port: u16,
}

/// One bucket of the test server, with what a `sylva` process needs to reach it.
pub struct TestBucket {
    /// `s3://bucket/prefix` for `--store`.
    pub url: String,
    /// The bucket's name.
    pub bucket: String,
    /// `AWS_*` variables for the `sylva` process (endpoint, dummy credentials, plain HTTP).
    pub env: Vec<(String, String)>,
    port: u16,
}

impl TestBucket {
    /// Keys of every object in the bucket (one page of ListObjectsV2 is enough for tests).
    pub fn keys(&self) -> Vec<String> {
        let body =
            request(self.port, "GET", &format!("/{}?list-type=2", self.bucket)).unwrap_or_default();
        body.split("<Key>")
            .skip(1)
            .filter_map(|s| s.split("</Key>").next())
            .map(str::to_string)
            .collect()
    }
}

/// A fresh bucket on the test server, or `None` (with the reason printed) where moto's
/// server is not installed. Panics when it is installed but does not start.
pub fn bucket() -> Option<TestBucket> {
    static SERVER: OnceLock<Result<Server, String>> = OnceLock::new();
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let server = match SERVER.get_or_init(start) {
        Ok(s) => s,
        Err(why) if why.starts_with("skip: ") => {
            sylva::testing::skip("s3", &why[6..]);
            return None;
        }
        Err(why) => panic!("the test S3 server did not start: {why}"),
    };
    let name = format!(
        "sylva-test-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::SeqCst)
    );
    let made = request(server.port, "PUT", &format!("/{name}"));
    if let Err(e) = made {
        panic!("cannot create the test bucket {name}: {e}");
    }
    let endpoint = format!("http://127.0.0.1:{}", server.port);
    Some(TestBucket {
        url: format!("s3://{name}/sylva"),
        bucket: name,
        env: [
            ("AWS_ENDPOINT_URL", endpoint.as_str()),
            ("AWS_ALLOW_HTTP", "true"),
            ("AWS_ACCESS_KEY_ID", "test"),
            ("AWS_SECRET_ACCESS_KEY", "test"),
            ("AWS_REGION", "us-east-1"),
        ]
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect(),
        port: server.port,
    })
}

/// `moto_server` (see [`super::test_tool`]); an `Err` starting "skip: " where there is none.
fn find_moto() -> Result<PathBuf, String> {
    super::test_tool("SYLVA_TEST_MOTO", "moto_server").map_err(|why| format!("skip: {why}"))
}

fn free_port() -> Result<u16, String> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

fn start() -> Result<Server, String> {
    let bin = find_moto()?;
    let port = free_port()?;
    let log = std::env::temp_dir().join(format!("sylva-test-moto-{}.log", std::process::id()));
    // The server runs under a shell that stops it once this test process is gone.
    let script = r#"
        "$2" -H 127.0.0.1 -p "$3" >"$4" 2>&1 &
        server=$!
        while [ -d "/proc/$1" ] && [ -d "/proc/$server" ]; do sleep 1; done
        kill "$server" 2>/dev/null
    "#;
    Command::new("sh")
        .arg("-c")
        .arg(script)
        .arg("sylva-test-moto")
        .arg(std::process::id().to_string())
        .arg(&bin)
        .arg(port.to_string())
        .arg(&log)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("cannot run {}: {e}", bin.display()))?;
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if request(port, "GET", "/").is_ok() {
            return Ok(Server { port });
        }
        if Instant::now() > deadline {
            return Err(format!(
                "{} did not answer on port {port} within 60 s; its log:\n{}",
                bin.display(),
                std::fs::read_to_string(&log).unwrap_or_default()
            ));
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// One plain HTTP/1.1 request without a body; the body of a 2xx answer, else an error.
fn request(port: u16, method: &str, path: &str) -> Result<String, String> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    s.set_read_timeout(Some(Duration::from_secs(30)))
        .map_err(|e| e.to_string())?;
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .map_err(|e| e.to_string())?;
    let mut text = String::new();
    s.read_to_string(&mut text).map_err(|e| e.to_string())?;
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse::<u16>().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map(|(_, b)| b).unwrap_or("");
    if (200..300).contains(&status) {
        Ok(body.to_string())
    } else {
        Err(format!("{method} {path}: HTTP {status}: {body}"))
    }
}
