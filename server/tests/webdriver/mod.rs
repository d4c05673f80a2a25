//! A headless Debian Chromium driven by chromedriver over the W3C WebDriver protocol (plain HTTP/JSON), for the
//! browser tests: open pages, click, run scripts, wait for conditions, take screenshots, read the page's errors.

#![allow(dead_code)] // each test binary uses its own subset

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fedvla_server::native_client::{Dialer, http_request};
use hyper::body::Bytes;
use serde_json::{Value, json};

/// The pages `fedvla serve` serves, with the wasm volunteer built into www/pkg by client-wasm/build.sh.
pub fn www_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../www")
}

/// Why browser tests cannot run here, if they cannot. With `FEDVLA_REQUIRE_BROWSER=1` (tests/run.sh sets it)
/// a missing piece is a failure instead of a skip.
pub fn missing_prerequisite() -> Option<String> {
    let missing = if !Path::new(&chromedriver()).exists() {
        Some(format!("chromedriver not found at {} (Debian package chromium-driver)", chromedriver()))
    } else if !Path::new(&chromium()).exists() {
        Some(format!("chromium not found at {} (Debian package chromium)", chromium()))
    } else if !www_dir().join("pkg/fedvla_client_wasm_bg.wasm").exists() {
        Some(format!("the wasm volunteer is not built into {}/pkg (run client-wasm/build.sh)", www_dir().display()))
    } else {
        None
    };
    if let Some(why) = &missing
        && std::env::var("FEDVLA_REQUIRE_BROWSER").is_ok_and(|v| v == "1")
    {
        panic!("FEDVLA_REQUIRE_BROWSER=1 but {why}");
    }
    missing
}

fn chromedriver() -> String {
    std::env::var("CHROMEDRIVER").unwrap_or_else(|_| "/usr/bin/chromedriver".into())
}

fn chromium() -> String {
    std::env::var("CHROME_BIN").unwrap_or_else(|_| "/usr/bin/chromium".into())
}

pub struct Browser {
    driver: Child,
    /// chromedriver's own HTTP endpoint.
    driver_address: Dialer,
    session: String,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts chromedriver and a fresh headless Chromium profile. `extra_args` are added to Chromium's flags.
    pub async fn launch(extra_args: &[&str]) -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let driver = Command::new(chromedriver())
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let driver_address = Dialer::plain(&format!("127.0.0.1:{port}"));
        let profile = tempfile::tempdir().unwrap();
        let started = Instant::now();
        while http_request(&driver_address, hyper::Request::get("/status"), Bytes::new()).await.is_err() {
            assert!(started.elapsed() < Duration::from_secs(20), "chromedriver did not answer within 20 s");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // No network here: Chromium's background services would only log failures.
        let mut args: Vec<String> = [
            "--headless=new",
            "--no-sandbox",
            "--disable-dev-shm-usage",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-quic",
            "--no-first-run",
            "--window-size=1100,1300",
        ]
        .map(String::from)
        .to_vec();
        args.push(format!("--user-data-dir={}", profile.path().display()));
        args.extend(extra_args.iter().map(|a| a.to_string()));
        let capabilities = json!({ "capabilities": { "alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": { "binary": chromium(), "args": args },
            "goog:loggingPrefs": { "browser": "ALL" },
        }}});
        let mut browser = Self { driver, driver_address, session: String::new(), _profile: profile };
        let created = browser.command("POST", "/session", capabilities).await;
        browser.session = created["sessionId"].as_str().expect("a session id").to_owned();
        browser
    }

    /// One WebDriver command; returns its `value`.
    async fn command(&self, method: &str, path: &str, body: Value) -> Value {
        let request = hyper::Request::builder().method(method).uri(path).header("content-type", "application/json");
        let body = if body.is_null() { Bytes::new() } else { Bytes::from(body.to_string()) };
        let reply = http_request(&self.driver_address, request, body)
            .await
            .unwrap_or_else(|e| panic!("WebDriver {method} {path}: {e}"));
        let reply: Value = serde_json::from_slice(&reply).expect("WebDriver JSON");
        reply["value"].clone()
    }

    async fn session_command(&self, method: &str, path: &str, body: Value) -> Value {
        self.command(method, &format!("/session/{}{path}", self.session), body).await
    }

    pub async fn goto(&self, url: &str) {
        self.session_command("POST", "/url", json!({ "url": url })).await;
    }

    pub async fn refresh(&self) {
        self.session_command("POST", "/refresh", json!({})).await;
    }

    /// Runs `body` as a function body in the page and returns what it returns.
    pub async fn eval(&self, body: &str) -> Value {
        self.session_command("POST", "/execute/sync", json!({ "script": body, "args": [] })).await
    }

    /// The WebDriver id of the first element matching `css`.
    async fn element(&self, css: &str) -> String {
        let element = self.session_command("POST", "/element", json!({ "using": "css selector", "value": css })).await;
        let id = element.as_object().and_then(|o| o.values().next()).and_then(Value::as_str);
        id.unwrap_or_else(|| panic!("no element {css}: {element}")).to_owned()
    }

    pub async fn click(&self, css: &str) {
        let id = self.element(css).await;
        self.session_command("POST", &format!("/element/{id}/click"), json!({})).await;
    }

    pub async fn type_into(&self, css: &str, text: &str) {
        let id = self.element(css).await;
        self.session_command("POST", &format!("/element/{id}/value"), json!({ "text": text })).await;
    }

    /// Polls `condition` (a function body returning a truthy value when satisfied) until it holds; returns its value.
    pub async fn wait_for(&self, what: &str, timeout: Duration, condition: &str) -> Value {
        let started = Instant::now();
        loop {
            let value = self.eval(condition).await;
            if !matches!(value, Value::Null | Value::Bool(false)) && value != json!("") && value != json!(0) {
                return value;
            }
            if started.elapsed() > timeout {
                let page = self.eval("return document.body ? document.body.innerText : ''").await;
                panic!(
                    "timed out after {timeout:?} waiting for {what}; page text:\n{}\npage errors: {:?}",
                    page.as_str().unwrap_or(""),
                    self.page_errors().await
                );
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Saves a PNG screenshot and checks that it is not blank (its pixels vary).
    pub async fn screenshot(&self, path: &Path) {
        use base64::Engine;
        let encoded = self.session_command("GET", "/screenshot", Value::Null).await;
        let png = base64::engine::general_purpose::STANDARD
            .decode(encoded.as_str().expect("base64 screenshot"))
            .expect("base64");
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, &png).unwrap();
        let image = image::load_from_memory(&png).expect("a PNG").to_luma8();
        let n = image.pixels().len() as f64;
        let mean = image.pixels().map(|p| f64::from(p.0[0])).sum::<f64>() / n;
        let variance = image.pixels().map(|p| (f64::from(p.0[0]) - mean).powi(2)).sum::<f64>() / n;
        assert!(variance > 50.0, "screenshot {} looks blank (luma variance {variance:.1})", path.display());
        eprintln!("screenshot {} ({}x{}, luma variance {variance:.0})", path.display(), image.width(), image.height());
    }

    /// Errors the page recorded (www/errors.js) plus the browser console's SEVERE entries since the last call.
    pub async fn page_errors(&self) -> Vec<String> {
        let mut errors: Vec<String> = match self.eval("return window.__pageErrors || []").await {
            Value::Array(items) => items.iter().map(|v| v.as_str().unwrap_or_default().to_owned()).collect(),
            _ => Vec::new(),
        };
        if let Value::Array(entries) = self.session_command("POST", "/se/log", json!({ "type": "browser" })).await {
            errors.extend(
                entries
                    .iter()
                    .filter(|e| e["level"] == "SEVERE")
                    .map(|e| format!("console: {}", e["message"].as_str().unwrap_or_default())),
            );
        }
        errors
    }

    /// The largest peak RSS (`VmHWM`, kB) of this browser's renderer processes (the pages, the wasm volunteer's
    /// memory included), found among chromedriver's descendants in /proc; None when none can be read.
    pub fn renderer_peak_rss_kb(&self) -> Option<u64> {
        let parent_of = |pid: u32| -> Option<u32> {
            let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
            status.lines().find_map(|l| l.strip_prefix("PPid:")).and_then(|v| v.trim().parse().ok())
        };
        let descends_from_driver = |mut pid: u32| {
            while pid > 1 {
                if pid == self.driver.id() {
                    return true;
                }
                let Some(parent) = parent_of(pid) else { return false };
                pid = parent;
            }
            false
        };
        let peak_rss_kb = |pid: u32| -> Option<u64> {
            let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
            // Chromium rewrites its children's titles: their arguments are separated by spaces there, not NULs.
            let is_renderer = cmdline.split(|&b| b == 0 || b == b' ').any(|arg| arg == b"--type=renderer");
            let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
            let hwm = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
            is_renderer.then(|| hwm.trim().trim_end_matches("kB").trim().parse().ok()).flatten()
        };
        std::fs::read_dir("/proc")
            .ok()?
            .filter_map(|entry| entry.ok()?.file_name().to_str()?.parse::<u32>().ok())
            .filter(|&pid| descends_from_driver(pid))
            .filter_map(peak_rss_kb)
            .max()
    }

    pub async fn quit(mut self) {
        self.session_command("DELETE", "", Value::Null).await;
        self.driver.kill().ok();
        self.driver.wait().ok();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        self.driver.kill().ok();
        self.driver.wait().ok();
    }
}
