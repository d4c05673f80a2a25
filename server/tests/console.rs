//! The operator console over loopback: the token guard, the snapshot, live events, pause/resume/stop, settings
//! changes reaching the next round's tasks, downloads, and the static pages.

mod common;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_app::server::ServerHandle;
use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use hyper::{HeaderMap, StatusCode};
use hyper_util::rt::TokioIo;
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio::sync::{Semaphore, mpsc};

const TOKEN: &str = "operator-secret";

struct Reply {
    status: StatusCode,
    headers: HeaderMap,
    body: Vec<u8>,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&self.body)))
    }

    fn header(&self, name: &str) -> &str {
        self.headers.get(name).map_or("", |v| v.to_str().unwrap())
    }

    /// The JSON error message of a refusal with `status`.
    fn error(&self, status: StatusCode) -> String {
        assert_eq!(self.status, status, "{}", String::from_utf8_lossy(&self.body));
        self.json()["error"].as_str().expect("a JSON error").to_owned()
    }
}

/// Sends one request over a fresh connection; `token` goes in `Authorization: Bearer`.
async fn request(handle: &ServerHandle, method: &str, path: &str, token: Option<&str>, body: &str) -> Reply {
    request_with(handle, method, path, token, &[], body).await
}

async fn request_with(
    handle: &ServerHandle,
    method: &str,
    path: &str,
    token: Option<&str>,
    headers: &[(&str, &str)],
    body: &str,
) -> Reply {
    let response = send(handle, method, path, token, headers, body).await;
    let (parts, body) = response.into_parts();
    let body = body.collect().await.unwrap().to_bytes().to_vec();
    Reply { status: parts.status, headers: parts.headers, body }
}

async fn send(
    handle: &ServerHandle,
    method: &str,
    path: &str,
    token: Option<&str>,
    headers: &[(&str, &str)],
    body: &str,
) -> hyper::Response<hyper::body::Incoming> {
    let stream = TcpStream::connect(handle.addr()).await.unwrap();
    let (mut sender, conn) = hyper::client::conn::http1::handshake(TokioIo::new(stream)).await.unwrap();
    tokio::spawn(conn);
    let mut builder = hyper::Request::builder().method(method).uri(path).header("host", handle.addr().to_string());
    if let Some(token) = token {
        builder = builder.header("authorization", format!("Bearer {token}"));
    }
    for (name, value) in headers {
        builder = builder.header(*name, *value);
    }
    let request = builder.body(Full::new(Bytes::from(body.to_owned()))).unwrap();
    tokio::time::timeout(Duration::from_secs(10), sender.send_request(request))
        .await
        .expect("response within 10 s")
        .unwrap()
}

/// The console's event stream, each `data:` line parsed.
async fn subscribe(handle: &ServerHandle) -> mpsc::UnboundedReceiver<Value> {
    let response = send(handle, "GET", &format!("/console/api/events?token={TOKEN}"), None, &[], "").await;
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "text/event-stream");
    let (tx, rx) = mpsc::unbounded_channel();
    let mut body = response.into_body();
    tokio::spawn(async move {
        let mut text = String::new();
        while let Some(Ok(frame)) = body.frame().await {
            let Ok(data) = frame.into_data() else { continue };
            text.push_str(std::str::from_utf8(&data).unwrap());
            while let Some(end) = text.find("\n\n") {
                let message: String = text.drain(..end + 2).collect();
                for line in message.lines().filter_map(|l| l.strip_prefix("data: ")) {
                    tx.send(serde_json::from_str(line).unwrap()).ok();
                }
            }
        }
    });
    rx
}

/// The next event of `kind` (at most 20 s away), skipping others.
async fn next_event(events: &mut mpsc::UnboundedReceiver<Value>, kind: &str) -> Value {
    next_matching(events, kind, |_| true).await
}

/// The next event of `kind` that `pred` accepts, skipping others.
async fn next_matching(
    events: &mut mpsc::UnboundedReceiver<Value>,
    kind: &str,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            let event = events.recv().await.expect("event stream open");
            if event["type"] == kind && pred(&event) {
                return event;
            }
        }
    })
    .await
    .unwrap_or_else(|_| panic!("no such `{kind}` event within 20 s"))
}

async fn snapshot(handle: &ServerHandle) -> Value {
    let reply = request(handle, "GET", "/console/api/snapshot", Some(TOKEN), "").await;
    assert_eq!(reply.status, StatusCode::OK, "{}", String::from_utf8_lossy(&reply.body));
    reply.json()
}

async fn control(handle: &ServerHandle, action: &str) -> Value {
    let reply =
        request(handle, "POST", "/console/api/control", Some(TOKEN), &json!({ "action": action }).to_string()).await;
    assert_eq!(reply.status, StatusCode::OK, "{action}: {}", String::from_utf8_lossy(&reply.body));
    reply.json()["state"].clone()
}

fn console_config(overrides: &str) -> fedvla_aggregator::config::RunConfig {
    config(&format!("operator-token={TOKEN} {overrides}"))
}

#[tokio::test]
async fn every_console_route_wants_the_operator_token() {
    let base = tempfile::tempdir().unwrap();
    let cfg = console_config("");
    let handle = start(cfg.clone(), RunDir::create(base.path(), &cfg).unwrap()).await;
    let routes = [
        ("GET", "/console/api/snapshot", ""),
        ("GET", "/console/api/events", ""),
        ("POST", "/console/api/control", r#"{"action": "pause"}"#),
        ("POST", "/console/api/settings", r#"{"lr": 0.1}"#),
        ("GET", "/console/api/checkpoint/0", ""),
        ("GET", "/console/api/file/config.toml", ""),
    ];
    for (method, path, body) in routes {
        let missing = request(&handle, method, path, None, body).await.error(StatusCode::UNAUTHORIZED);
        assert!(missing.starts_with("missing operator token"), "{path}: {missing}");
        let wrong = request(&handle, method, path, Some("guess"), body).await.error(StatusCode::UNAUTHORIZED);
        assert_eq!(wrong, "wrong operator token", "{path}");
        let wrong_query = format!("{path}?token=guess");
        let wrong = request(&handle, method, &wrong_query, None, body).await.error(StatusCode::UNAUTHORIZED);
        assert_eq!(wrong, "wrong operator token", "{path}");
    }
    assert_eq!(snapshot(&handle).await["run"]["state"], "running", "paused by none of the refused requests");

    // The right token, in the header or the query, opens every route.
    let config_toml = request(&handle, "GET", &format!("/console/api/file/config.toml?token={TOKEN}"), None, "").await;
    assert_eq!(config_toml.status, StatusCode::OK);
    assert_eq!(config_toml.header("content-type"), "text/plain; charset=utf-8");
    assert!(String::from_utf8(config_toml.body).unwrap().contains("num-server-rounds = 2"));
    let outside = request(&handle, "GET", "/console/api/file/../secret", Some(TOKEN), "").await;
    assert!(outside.error(StatusCode::BAD_REQUEST).contains("`../secret` is not a path inside"));
    let outside = request(&handle, "GET", "/console/api/file/%2e%2e/secret", Some(TOKEN), "").await;
    assert_eq!(outside.status, StatusCode::BAD_REQUEST, "percent-encoded dots are dots");
    let missing = request(&handle, "GET", "/console/api/file/global_model/round_9/x.mp4", Some(TOKEN), "").await;
    assert!(missing.error(StatusCode::NOT_FOUND).contains("round_9/x.mp4"));
    let no_checkpoint = request(&handle, "GET", "/console/api/checkpoint/0", Some(TOKEN), "").await;
    let message = no_checkpoint.error(StatusCode::NOT_FOUND);
    assert!(message.starts_with("round 0 has no LeRobot policy directory"), "{message}");
    handle.kill().await;
}

#[tokio::test]
async fn an_empty_operator_token_is_made_up_at_start() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("operator-token=\"\"");
    let handle = start(cfg.clone(), RunDir::create(base.path(), &cfg).unwrap()).await;
    let token = handle.operator_token().to_owned();
    assert_eq!(token.len(), 32, "{token}");
    assert!(token.chars().all(|c| c.is_ascii_hexdigit()), "{token}");
    let reply = request(&handle, "GET", "/console/api/snapshot", Some(&token), "").await;
    assert_eq!(reply.status, StatusCode::OK);
    let empty = request(&handle, "GET", "/console/api/snapshot?token=", None, "").await;
    assert_eq!(empty.error(StatusCode::UNAUTHORIZED), "wrong operator token");
    handle.kill().await;
}

#[tokio::test]
async fn operator_starts_pauses_changes_settings_resumes_and_stops() {
    let base = tempfile::tempdir().unwrap();
    let cfg = console_config("num-server-rounds=5 min-clients=2 min-fit=2 auto-start=false");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let dir = run_dir.path().to_owned();
    let handle = start(cfg, run_dir).await;
    let mut events = subscribe(&handle).await;
    let gate = Arc::new(Semaphore::new(0));
    let mut clients = Vec::new();
    let mut tasks = Vec::new();
    for shard in 0..2 {
        let trainer = TestTrainer::new(shard, None).0.gated(gate.clone());
        tasks.push(trainer.tasks());
        clients.push(spawn_trainer(&handle, shard, trainer));
    }
    for _ in 0..2 {
        let joined = next_event(&mut events, "client_joined").await;
        assert_eq!(joined["client"]["state"], "idle");
        assert_eq!(joined["client"]["backend"], "cpu-f32");
    }
    let rounds_sent = |round: u64| -> Vec<u32> {
        tasks
            .iter()
            .flat_map(|t| t.lock().unwrap().clone())
            .filter(|t| t.round == round)
            .map(|t| t.local_steps)
            .collect()
    };

    // auto-start=false: round 0 (the initial evaluation) ran, round 1 waits for Start.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = snapshot(&handle).await;
    assert_eq!(before["run"]["state"], "waiting_for_start");
    assert_eq!(before["run"]["connected"], 2);
    assert_eq!(before["metrics"].as_array().unwrap().len(), 1, "round 0 only");
    assert!(rounds_sent(1).is_empty(), "no task before Start");

    assert_eq!(control(&handle, "start").await, "running");
    let busy = next_event(&mut events, "client_state").await;
    assert_eq!(busy["client"]["state"], "evaluating", "the task asks for a held-out evaluation first");
    let started = next_event(&mut events, "round_started").await;
    assert_eq!(started["attempt"]["round"], 1);
    assert_eq!(started["attempt"]["sampled"].as_array().unwrap().len(), 2);

    // Pause while round 1 is in flight: it finishes, round 2 does not start.
    assert_eq!(control(&handle, "pause").await, "paused");
    gate.add_permits(2);
    // Round 0 may have closed after the stream opened.
    let closed = next_matching(&mut events, "round_closed", |e| e["round"] != 0).await;
    assert_eq!(closed["round"], 1);
    assert_eq!(closed["outcome"], "closed");
    assert_eq!(closed["metrics"]["round"], 1, "the round-closed event carries the metrics line");
    assert!(closed["metrics"]["global"]["heldout_loss"].as_f64().is_some());
    assert!(closed["metrics"].get("settings").is_none(), "round 1 ran with the configured settings");

    let bad = request(&handle, "POST", "/console/api/settings", Some(TOKEN), r#"{"local-steps": 0}"#).await;
    assert!(bad.error(StatusCode::BAD_REQUEST).contains("local-steps"));
    let bad = request(&handle, "POST", "/console/api/settings", Some(TOKEN), r#"{"lr": "fast"}"#).await;
    assert!(bad.error(StatusCode::BAD_REQUEST).starts_with("bad settings: `lr`: invalid type: string \"fast\""));
    let bad = request(&handle, "POST", "/console/api/settings", Some(TOKEN), r#"{"speed": 2}"#).await;
    assert!(bad.error(StatusCode::BAD_REQUEST).contains("unknown field `speed`"));
    let bad = request(&handle, "POST", "/console/api/settings", Some(TOKEN), "{}").await;
    assert!(bad.error(StatusCode::BAD_REQUEST).contains("none given; settable:"));
    let bad = request(&handle, "POST", "/console/api/control", Some(TOKEN), r#"{"action": "jump"}"#).await;
    assert!(bad.error(StatusCode::BAD_REQUEST).contains("unknown variant `jump`"));
    let changed = request(&handle, "POST", "/console/api/settings", Some(TOKEN), r#"{"local-steps": 7}"#).await;
    assert_eq!(changed.status, StatusCode::OK);
    assert_eq!(changed.json()["settings"]["local-steps"], 7);
    assert_eq!(next_event(&mut events, "settings_changed").await["changed"], json!({ "local-steps": 7 }));

    tokio::time::sleep(Duration::from_millis(300)).await;
    let paused = snapshot(&handle).await;
    assert_eq!(paused["run"]["state"], "paused");
    assert_eq!(paused["run"]["completed_rounds"], 1);
    assert_eq!(paused["pending_settings"], json!({ "local-steps": 7 }));
    assert!(rounds_sent(2).is_empty(), "paused: no round 2 task");
    assert_eq!(rounds_sent(1), [30, 30]);
    let timeline = paused["timeline"].as_array().unwrap();
    assert_eq!(timeline.len(), 1);
    assert_eq!((timeline[0]["outcome"].as_str(), timeline[0]["updates"].as_u64()), (Some("closed"), Some(2)));
    for row in paused["clients"].as_array().unwrap() {
        assert_eq!(row["state"], "idle", "{row}");
        assert_eq!(row["updates_accepted"], 1, "{row}");
        assert!(row["bytes_up"].as_u64().unwrap() > 0, "{row}");
    }

    // Resume: round 2's tasks carry the new local-steps. Stop while it runs: it finishes, then the run ends.
    assert_eq!(control(&handle, "resume").await, "running");
    assert_eq!(next_event(&mut events, "round_started").await["attempt"]["round"], 2);
    assert_eq!(control(&handle, "stop").await, "stopping");
    let refused = request(&handle, "POST", "/console/api/control", Some(TOKEN), r#"{"action": "resume"}"#).await;
    assert!(refused.error(StatusCode::CONFLICT).contains("stopping"));
    gate.add_permits(2);
    assert_eq!(next_event(&mut events, "round_closed").await["metrics"]["settings"], json!({ "local-steps": 7 }));
    assert_eq!(next_event(&mut events, "run_state").await["state"], "finished");
    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 2, "stopped after round 2 of 5");
    assert!(status.finished);
    assert_eq!(rounds_sent(2), [7, 7]);
    for client in clients {
        let summary = client.await.unwrap().expect("clients are told the run finished");
        assert_eq!(summary.rounds_trained, 2);
    }
    let lines = metrics(&dir);
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[2]["settings"], json!({ "local-steps": 7 }));
    let (_, resumed) = RunDir::open(&dir).unwrap();
    assert_eq!(resumed.local_steps, 7, "config.toml carries the operator's settings for a resume");
}

#[tokio::test]
async fn snapshot_gallery_files_and_checkpoints_of_a_finished_run() {
    let base = tempfile::tempdir().unwrap();
    let cfg = console_config("");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let dir = run_dir.path().to_owned();
    let handle = start(cfg, run_dir).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    wait_status(&handle, |s| s.finished).await;

    // What the SmolVLA workload's exporters write, which linreg has none of.
    let policy = dir.join("global_model/round_1/policy");
    std::fs::create_dir_all(policy.join("vlm")).unwrap();
    std::fs::write(policy.join("config.json"), br#"{"type": "smolvla"}"#).unwrap();
    std::fs::write(policy.join("vlm/config.json"), b"{}").unwrap();
    let rollouts = dir.join("global_model/round_2/rollouts");
    std::fs::create_dir_all(&rollouts).unwrap();
    std::fs::write(rollouts.join("episode_0.mp4"), b"not really a video").unwrap();
    std::fs::write(rollouts.join("results.json"), br#"{"success_rate": 0.5}"#).unwrap();

    let snap = snapshot(&handle).await;
    assert_eq!(snap["run"]["state"], "finished");
    assert_eq!(snap["run"]["completed_rounds"], 2);
    let rounds: Vec<u64> = snap["metrics"].as_array().unwrap().iter().map(|l| l["round"].as_u64().unwrap()).collect();
    assert_eq!(rounds, [0, 1, 2]);
    assert_eq!(snap["metrics"], json!(metrics(&dir)), "every metrics line, as written");
    let timeline = snap["timeline"].as_array().unwrap();
    assert_eq!(timeline.iter().map(|a| a["round"].as_u64().unwrap()).collect::<Vec<_>>(), [1, 2]);
    assert!(
        timeline.iter().all(|a| a["outcome"] == "closed" && a["updates"] == 3 && a["closed_ms"].as_u64().is_some())
    );
    let mut names: Vec<&str> =
        snap["clients"].as_array().unwrap().iter().map(|c| c["name"].as_str().unwrap()).collect();
    names.sort();
    assert_eq!(names, ["client-0", "client-1", "client-2"]);
    assert!(
        snap["clients"]
            .as_array()
            .unwrap()
            .iter()
            .all(|c| c["updates_accepted"] == 2 && c["last_seen_ms"].as_u64() > Some(0))
    );
    assert_eq!(snap["settings"]["local-steps"], 30);
    assert_eq!(snap["checkpoints"], json!([1]));
    let round_two =
        snap["gallery"].as_array().unwrap().iter().find(|r| r["round"] == 2).expect("round 2 in the gallery");
    assert_eq!(round_two["global"]["results"]["success_rate"], 0.5);
    let video_url = round_two["global"]["videos"][0].as_str().unwrap();
    assert_eq!(video_url, "/console/api/file/global_model/round_2/rollouts/episode_0.mp4");

    // Videos as a <video> element fetches them: token in the query, byte ranges.
    let video = request(&handle, "GET", &format!("{video_url}?token={TOKEN}"), None, "").await;
    assert_eq!(video.status, StatusCode::OK);
    assert_eq!(video.header("content-type"), "video/mp4");
    assert_eq!(video.header("cache-control"), "no-cache");
    assert_eq!(video.body, b"not really a video");
    let part = request_with(&handle, "GET", video_url, Some(TOKEN), &[("range", "bytes=4-9")], "").await;
    assert_eq!(part.status, StatusCode::PARTIAL_CONTENT);
    assert_eq!(part.header("content-range"), "bytes 4-9/18");
    assert_eq!(part.body, b"really");

    // The checkpoint: the policy directory as a tar archive.
    let tar = request(&handle, "GET", "/console/api/checkpoint/1", Some(TOKEN), "").await;
    assert_eq!(tar.status, StatusCode::OK);
    assert_eq!(tar.header("content-type"), "application/x-tar");
    assert_eq!(tar.header("content-disposition"), "attachment; filename=\"fedvla_round_1_policy.tar\"");
    let mut archive = tar::Archive::new(tar.body.as_slice());
    let mut files = Vec::new();
    for entry in archive.entries().unwrap() {
        let mut entry = entry.unwrap();
        let mut content = String::new();
        std::io::Read::read_to_string(&mut entry, &mut content).unwrap();
        files.push((entry.path().unwrap().display().to_string(), content));
    }
    files.retain(|(_, content)| !content.is_empty());
    files.sort();
    assert_eq!(
        files,
        [
            ("fedvla_round_1_policy/config.json".to_owned(), r#"{"type": "smolvla"}"#.to_owned()),
            ("fedvla_round_1_policy/vlm/config.json".to_owned(), "{}".to_owned()),
        ]
    );

    handle.finish().await.unwrap();
    for (client, _) in clients {
        client.await.unwrap().unwrap();
    }
}

#[tokio::test]
async fn www_dir_pages_with_content_types_and_no_way_out() {
    let base = tempfile::tempdir().unwrap();
    let www = base.path().join("www");
    std::fs::create_dir_all(www.join("pkg")).unwrap();
    let pages = [
        ("index.html", "text/html; charset=utf-8"),
        ("console.html", "text/html; charset=utf-8"),
        ("console.js", "text/javascript; charset=utf-8"),
        ("console.css", "text/css; charset=utf-8"),
        ("pkg/client_bg.wasm", "application/wasm"),
        ("data.json", "application/json"),
        ("logo.svg", "image/svg+xml"),
    ];
    for (name, _) in pages {
        std::fs::write(www.join(name), format!("contents of {name}")).unwrap();
    }
    std::fs::write(base.path().join("secret.txt"), "outside www").unwrap();
    let cfg = config(&format!("www-dir={}", www.display()));
    let handle = start(cfg.clone(), RunDir::create(&base.path().join("runs"), &cfg).unwrap()).await;

    for (path, file) in [("/", "index.html"), ("/console", "console.html")] {
        let page = request(&handle, "GET", path, None, "").await;
        assert_eq!(page.status, StatusCode::OK, "{path}");
        assert_eq!(page.header("content-type"), "text/html; charset=utf-8");
        assert_eq!(page.header("cache-control"), "no-cache");
        assert_eq!(page.body, format!("contents of {file}").as_bytes());
    }
    for (name, content_type) in pages {
        let file = request(&handle, "GET", &format!("/{name}"), None, "").await;
        assert_eq!((file.status, file.header("content-type")), (StatusCode::OK, content_type), "{name}");
        assert_eq!(file.body, format!("contents of {name}").as_bytes());
    }
    let missing = request(&handle, "GET", "/nothing.js", None, "").await;
    assert_eq!(missing.status, StatusCode::NOT_FOUND);
    assert!(String::from_utf8(missing.body).unwrap().contains("nothing.js"));
    for escape in ["/../secret.txt", "/%2e%2e/secret.txt", "/pkg/../../secret.txt"] {
        let refused = request(&handle, "GET", escape, None, "").await;
        assert_eq!(refused.status, StatusCode::BAD_REQUEST, "{escape}");
        assert!(!String::from_utf8(refused.body).unwrap().contains("outside www"));
    }
    // A compressed copy beside a file goes to clients that take gzip, as what it decompresses to.
    let compressed = b"\x1f\x8b pretend gzip of the wasm";
    std::fs::write(www.join("pkg/client_bg.wasm.gz"), compressed).unwrap();
    let gzip = request_with(&handle, "GET", "/pkg/client_bg.wasm", None, &[("accept-encoding", "br, gzip")], "").await;
    assert_eq!((gzip.header("content-encoding"), gzip.header("content-type")), ("gzip", "application/wasm"));
    assert_eq!((gzip.body.as_slice(), gzip.header("vary")), (&compressed[..], "accept-encoding"));
    let plain = request(&handle, "GET", "/pkg/client_bg.wasm", None, "").await;
    assert_eq!(plain.body, b"contents of pkg/client_bg.wasm", "no accept-encoding, no gzip");
    let ranged = request_with(
        &handle,
        "GET",
        "/pkg/client_bg.wasm",
        None,
        &[("accept-encoding", "gzip"), ("range", "bytes=0-7")],
        "",
    )
    .await;
    assert_eq!(ranged.body, b"contents", "a range is of the file itself");
    // The API's own routes are not shadowed by the pages: a model answers as the API does (no session, no model).
    assert_eq!(request(&handle, "GET", "/model/0", None, "").await.status, StatusCode::UNAUTHORIZED);
    handle.kill().await;

    // No www dir at all: pages are 404s naming it, the API works.
    let cfg = console_config(&format!("www-dir={}", base.path().join("absent").display()));
    let handle = start(cfg.clone(), RunDir::create(&base.path().join("runs"), &cfg).unwrap()).await;
    let page = request(&handle, "GET", "/console", None, "").await;
    assert_eq!(page.status, StatusCode::NOT_FOUND);
    let message = String::from_utf8(page.body).unwrap();
    assert!(message.contains("console.html") && message.contains("absent does not exist"), "{message}");
    assert_eq!(snapshot(&handle).await["run"]["state"], "running");
    handle.kill().await;
}
