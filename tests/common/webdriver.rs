//! A small W3C WebDriver client over reqwest, driving Debian's headless Chromium through
//! `chromedriver`: enough to open pages, run scripts, click, choose files and take screenshots.
//! (A client crate would bring a second HTTP stack for these dozen requests.)
#![allow(dead_code)]

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64_lite::decode as b64decode;
use serde_json::{Value, json};

/// The W3C key of element references in WebDriver answers.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// Where the browser tests put their screenshots.
pub fn output_dir() -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join("browser");
    std::fs::create_dir_all(&d).expect("screenshot dir");
    d
}

fn find_program(names: &[&str]) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path).chain([
        PathBuf::from("/usr/bin"),
        PathBuf::from("/usr/lib/chromium"),
    ]) {
        for n in names {
            let p = dir.join(n);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// A browser, or `None` (with the reason printed, capability `browser`) where there is none.
pub async fn browser_or_skip(test: &str) -> Option<Browser> {
    match Browser::start().await {
        Ok(b) => Some(b),
        Err(why) => {
            sylva::testing::skip("browser", &format!("{test}: {why}"));
            None
        }
    }
}

/// A headless Chromium session, or the reason there cannot be one here.
pub struct Browser {
    driver: Child,
    url: String,
    session: String,
    http: reqwest::Client,
    _profile: tempfile::TempDir,
}

impl Browser {
    pub async fn start() -> Result<Browser, String> {
        let chromium = find_program(&["chromium", "chromium-browser"])
            .ok_or("chromium is not installed (Debian package `chromium`)")?;
        let driver = find_program(&["chromedriver"])
            .ok_or("chromedriver is not installed (Debian package `chromium-driver`)")?;
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| e.to_string())?
            .port();
        // Its own process group, so that the browsers it starts can be ended with it.
        let child = Command::new(&driver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .process_group(0)
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", driver.display()))?;
        let http = reqwest::Client::builder()
            .timeout(Duration::from_secs(120))
            .build()
            .map_err(|e| e.to_string())?;
        let url = format!("http://127.0.0.1:{port}");
        let profile = tempfile::tempdir().map_err(|e| e.to_string())?;
        let mut browser = Browser {
            driver: child,
            url,
            session: String::new(),
            http,
            _profile: profile,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let ready = browser
                .http
                .get(format!("{}/status", browser.url))
                .send()
                .await
                .ok()
                .map(|r| r.status().is_success())
                .unwrap_or(false);
            if ready {
                break;
            }
            if Instant::now() > deadline {
                return Err("chromedriver did not answer within 30 s".into());
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let caps = json!({ "capabilities": { "alwaysMatch": {
            "browserName": "chrome",
            // WebGL runs in software here and the machine may be busy: generous script and
            // page-load limits (milliseconds) instead of the 30 s defaults.
            "timeouts": { "script": 180_000, "pageLoad": 180_000 },
            "goog:chromeOptions": {
                "binary": chromium,
                "args": [
                    "--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                    "--window-size=1400,1900", "--hide-scrollbars",
                    // WebGL2 on the CPU: Chromium's SwiftShader backend through ANGLE.
                    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                    format!("--user-data-dir={}", browser._profile.path().display()),
                ],
            },
        }}});
        let v = browser.raw("POST", "/session", Some(caps)).await?;
        browser.session = v["sessionId"]
            .as_str()
            .ok_or_else(|| format!("no session: {v}"))?
            .to_string();
        Ok(browser)
    }

    async fn raw(&self, method: &str, path: &str, body: Option<Value>) -> Result<Value, String> {
        let url = format!("{}{path}", self.url);
        let req = match method {
            "GET" => self.http.get(url),
            "DELETE" => self.http.delete(url),
            _ => self.http.post(url).json(&body.unwrap_or(json!({}))),
        };
        let resp = req.send().await.map_err(|e| e.to_string())?;
        let status = resp.status();
        let v: Value = resp.json().await.map_err(|e| e.to_string())?;
        if !status.is_success() {
            return Err(format!(
                "WebDriver {method} {path}: {status} {}",
                v["value"]
            ));
        }
        Ok(v.get("value").cloned().unwrap_or(Value::Null))
    }

    async fn cmd(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let p = format!("/session/{}{path}", self.session);
        match self.raw(method, &p, body).await {
            Ok(v) => v,
            Err(e) => panic!("{e}"),
        }
    }

    /// Sets the window's outer size in CSS pixels.
    pub async fn set_window_size(&self, width: u32, height: u32) {
        self.cmd(
            "POST",
            "/window/rect",
            Some(json!({ "width": width, "height": height })),
        )
        .await;
    }

    pub async fn goto(&self, url: &str) {
        self.cmd("POST", "/url", Some(json!({ "url": url }))).await;
    }

    /// Runs `script` (a function body; `arguments` are `args`) and returns its value; a
    /// returned promise is awaited.
    pub async fn exec(&self, script: &str, args: Value) -> Value {
        self.cmd(
            "POST",
            "/execute/sync",
            Some(json!({ "script": script, "args": args })),
        )
        .await
    }

    /// Runs `script` (a function body) without arguments; its value, as [`Browser::exec`].
    pub async fn eval(&self, script: &str) -> Value {
        self.exec(script, json!([])).await
    }

    /// Polls `script` until it returns something truthy; panics with `what` after
    /// `timeout_secs` seconds.
    pub async fn wait_for(&self, what: &str, script: &str, timeout_secs: u64) -> Value {
        let deadline = Instant::now() + Duration::from_secs(timeout_secs);
        loop {
            let v = self.eval(script).await;
            let truthy = match &v {
                Value::Null => false,
                Value::Bool(b) => *b,
                Value::Number(n) => n.as_f64().is_some_and(|x| x != 0.0),
                Value::String(s) => !s.is_empty(),
                _ => true,
            };
            if truthy {
                return v;
            }
            if Instant::now() > deadline {
                let shot = output_dir().join(format!("timeout-{}.png", what.replace(' ', "_")));
                self.screenshot(&shot).await;
                panic!(
                    "timed out waiting for {what} (screenshot {})",
                    shot.display()
                );
            }
            tokio::time::sleep(Duration::from_millis(150)).await;
        }
    }

    pub async fn find(&self, css: &str) -> String {
        let v = self
            .cmd(
                "POST",
                "/element",
                Some(json!({ "using": "css selector", "value": css })),
            )
            .await;
        match v[ELEMENT].as_str() {
            Some(id) => id.to_string(),
            None => panic!("no element {css}: {v}"),
        }
    }

    pub async fn click(&self, css: &str) {
        let e = self.find(css).await;
        self.cmd("POST", &format!("/element/{e}/click"), None).await;
    }

    /// Types `text` into an element; for `<input type=file>` the text is a file path.
    pub async fn send_keys(&self, css: &str, text: &str) {
        let e = self.find(css).await;
        self.cmd(
            "POST",
            &format!("/element/{e}/value"),
            Some(json!({ "text": text })),
        )
        .await;
    }

    /// Saves a PNG of the window (or of one element) to `path`.
    pub async fn screenshot(&self, path: &Path) {
        let v = self.capture("/screenshot").await;
        save_png(&v, path);
    }

    pub async fn screenshot_element(&self, css: &str, path: &Path) {
        let e = self.find(css).await;
        let v = self.capture(&format!("/element/{e}/screenshot")).await;
        save_png(&v, path);
    }

    /// A screenshot request, tried up to three times: chromedriver gives the renderer only
    /// 10 s to answer, which software WebGL on a busy machine can miss.
    async fn capture(&self, path: &str) -> Value {
        let p = format!("/session/{}{path}", self.session);
        let mut last = String::new();
        for _ in 0..3 {
            match self.raw("GET", &p, None).await {
                Ok(v) => return v,
                Err(e) if e.contains("Timed out receiving message from renderer") => {
                    last = e;
                    tokio::time::sleep(Duration::from_secs(2)).await;
                }
                Err(e) => panic!("{e}"),
            }
        }
        panic!("{last}")
    }
}

fn save_png(v: &Value, path: &Path) {
    let b64 = v.as_str().expect("screenshot base64");
    let png = b64decode(b64).expect("screenshot decodes");
    std::fs::write(path, png).expect("write screenshot");
}

impl Browser {
    /// The browser's profile folder: every Chromium process of this session names it on its
    /// command line.
    pub fn profile_dir(&self) -> &Path {
        self._profile.path()
    }
}

/// Process ids whose command line contains `needle`.
pub fn processes_naming(needle: &str) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline"))
                .map(|c| String::from_utf8_lossy(&c).contains(needle))
                .unwrap_or(false)
        })
        .collect()
}

impl Drop for Browser {
    /// Ends chromedriver and every browser it started, also when a test fails: a killed
    /// chromedriver leaves its Chromium running, so the whole process group goes, then any
    /// process still naming this session's profile folder.
    fn drop(&mut self) {
        let group = format!("-{}", self.driver.id());
        let _ = Command::new("kill").args(["-KILL", "--", &group]).status();
        let _ = self.driver.kill();
        let _ = self.driver.wait();
        let profile = self._profile.path().to_string_lossy().to_string();
        for pid in processes_naming(&profile) {
            let _ = Command::new("kill")
                .args(["-KILL", &pid.to_string()])
                .status();
        }
    }
}

/// Base64 (standard alphabet, padded) without another dependency.
mod base64_lite {
    pub fn decode(s: &str) -> Option<Vec<u8>> {
        let val = |c: u8| -> Option<u32> {
            Some(match c {
                b'A'..=b'Z' => c - b'A',
                b'a'..=b'z' => c - b'a' + 26,
                b'0'..=b'9' => c - b'0' + 52,
                b'+' => 62,
                b'/' => 63,
                _ => return None,
            } as u32)
        };
        let bytes: Vec<u8> = s.bytes().filter(|c| !c.is_ascii_whitespace()).collect();
        let mut out = Vec::with_capacity(bytes.len() / 4 * 3);
        for chunk in bytes.chunks(4) {
            let mut n = 0u32;
            let mut pad = 0;
            for (i, &c) in chunk.iter().enumerate() {
                let v = if c == b'=' {
                    pad += 1;
                    0
                } else {
                    val(c)?
                };
                n |= v << (18 - 6 * i);
            }
            let b = n.to_be_bytes();
            out.extend_from_slice(&b[1..4 - pad]);
        }
        Some(out)
    }

    pub fn encode(data: &[u8]) -> String {
        const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        let mut out = String::with_capacity(data.len().div_ceil(3) * 4);
        for chunk in data.chunks(3) {
            let mut b = [0u8; 3];
            b[..chunk.len()].copy_from_slice(chunk);
            let n = u32::from_be_bytes([0, b[0], b[1], b[2]]);
            for i in 0..4 {
                if i <= chunk.len() {
                    out.push(A[(n >> (18 - 6 * i) & 63) as usize] as char);
                } else {
                    out.push('=');
                }
            }
        }
        out
    }
}

pub use base64_lite::encode as base64_encode;
