//! Each bound on what connections send refuses at its limit with its own code, is counted in the console's
//! snapshot, and leaves the server serving everyone else: joins per address per minute, messages per second,
//! rollout videos per round and their size, and the memory held for uploads in flight (an update waits for room,
//! up to a round's deadline; a video does not). (The connection cap and the timeouts are trust.rs's; oversized
//! frames and updates, faults.rs's.)

mod common;

use std::net::Ipv4Addr;

use common::*;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_app::server::ServerHandle;
use fedvla_federation::codec::encode_payload;
use fedvla_federation::{ClientMessage, ErrorCode, ServerMessage};
use fedvla_workloads::linreg;
use serde_json::Value;

/// The console's snapshot, as an operator reads it.
async fn snapshot(handle: &ServerHandle) -> Value {
    let token = format!("Bearer {}", handle.operator_token());
    let (status, body) = http(handle, "GET", "/console/api/snapshot", &[("authorization", &token)], Vec::new()).await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// How many refusals of `code` the console shows.
async fn refusals(handle: &ServerHandle, code: ErrorCode) -> u64 {
    snapshot(handle).await["run"]["rejections"][code.as_str()].as_u64().unwrap_or(0)
}

fn expect_error(message: Option<ServerMessage>, code: ErrorCode) {
    match message {
        Some(ServerMessage::Error { code: got, .. }) if got == code => {}
        other => panic!("expected {}, got {other:?}", code.as_str()),
    }
}

#[tokio::test]
async fn joins_past_the_per_address_limit_are_refused_and_other_addresses_still_join() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("joins-per-address-per-minute=3 min-clients=5");
    let handle = start(cfg.clone(), RunDir::create(base.path(), &cfg).unwrap()).await;
    let mut joined = Vec::new();
    for name in ["a", "b", "c"] {
        joined.push(RawClient::join(&handle, name).await.0);
    }
    let mut fourth = RawClient::connect(&handle).await;
    expect_error(fourth.identify(&simulated_identity("d"), "d", None).await, ErrorCode::JoinRateLimited);
    assert_eq!(fourth.recv().await, None, "closed after the refusal");

    let mut elsewhere = RawClient::connect_from(&handle, Ipv4Addr::new(127, 0, 0, 2)).await;
    let admitted = elsewhere.identify(&simulated_identity("e"), "e", None).await;
    assert!(matches!(admitted, Some(ServerMessage::Admitted { .. })), "another address is admitted: {admitted:?}");
    assert!(matches!(elsewhere.join_admitted().await, Some(ServerMessage::Welcome { .. })), "and joins");
    wait_status(&handle, |s| s.connected == 4).await;
    assert_eq!(refusals(&handle, ErrorCode::JoinRateLimited).await, 1);
    handle.kill().await;
}

#[tokio::test]
async fn a_connection_flooding_messages_is_closed_and_the_others_stay() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("max-messages-per-second=5 min-clients=5");
    let handle = start(cfg.clone(), RunDir::create(base.path(), &cfg).unwrap()).await;
    let (mut calm, _) = RawClient::join(&handle, "calm").await;
    let (mut flood, _) = RawClient::join(&handle, "flood").await;
    for _ in 0..3 {
        calm.send(&ClientMessage::Heartbeat).await;
    }
    // A burst of five passes; the rest of a burst of fifty does not.
    for _ in 0..50 {
        flood.send(&ClientMessage::Heartbeat).await;
    }
    expect_error(flood.recv().await, ErrorCode::MessageRateLimited);
    assert_eq!(flood.recv().await, None, "closed after the refusal");
    let status = wait_status(&handle, |s| s.connected == 1).await;
    assert_eq!(status.rejections.get(&ErrorCode::MessageRateLimited), Some(&1));
    assert_eq!(refusals(&handle, ErrorCode::MessageRateLimited).await, 1);
    let (_late, _) = RawClient::join(&handle, "late").await;
    wait_status(&handle, |s| s.connected == 2).await;
    handle.kill().await;
}

#[tokio::test]
async fn rollout_videos_are_bounded_in_number_and_size() {
    let err = RunConfig::default().with_overrides("client-rollout-episodes=3 max-rollout-videos=2").unwrap_err();
    assert!(err.to_string().contains("max-rollout-videos (2)"), "{err}");

    let base = tempfile::tempdir().unwrap();
    let cfg = config(
        "num-server-rounds=1 min-clients=1 min-fit=1 client-rollout-episodes=2 max-rollout-videos=2 \
         max-video-bytes=1000",
    );
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut c, client_id, session) = RawClient::join_shard(&handle, "filmer", Some(0)).await;
    let auth = format!("Bearer {session}");
    let post = async |round: u64, file: &str, len: usize| {
        http(&handle, "POST", &format!("/rollout/{round}/{file}"), &[("authorization", &auth)], vec![1; len]).await
    };
    let round = c.task().await.round;
    let (status, body) = post(round, "big.webm", 1001).await;
    assert_eq!(status, 413, "{body}");
    for file in ["a.webm", "b.webm"] {
        let (status, body) = post(round, file, 1000).await;
        assert_eq!(status, 201, "{body}");
    }
    assert_eq!(post(round, "c.webm", 10).await.0, 403, "two videos asked, two taken");
    assert_eq!(post(round + 1, "d.webm", 10).await.0, 403, "a round that asked for none");
    for (code, n) in [(ErrorCode::VideoTooLarge, 1), (ErrorCode::TooManyVideos, 1), (ErrorCode::UnrequestedVideo, 1)] {
        assert_eq!(refusals(&handle, code).await, n, "{}", code.as_str());
    }
    c.upload(round, &linreg_head(0.1, 0.1), linreg::train_examples(0) as u64).await;
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 1);
    let dir = run_dir.client_eval_dir(round, client_id);
    assert!(dir.join("a.webm").exists() && dir.join("b.webm").exists());
    assert!(!dir.join("big.webm").exists() && !dir.join("c.webm").exists());
}

/// A server whose upload budget holds exactly one update of `payload` bytes (or one video of that size), with
/// `first` holding it (its update header in, its frames not sent), and `second` sampled beside it.
struct BudgetTaken {
    handle: ServerHandle,
    run_dir: RunDir,
    first: RawClient,
    second: RawClient,
    round: u64,
    _base: tempfile::TempDir,
}

async fn budget_taken(payload: usize, overrides: &str) -> BudgetTaken {
    let base = tempfile::tempdir().unwrap();
    let cfg = config(&format!(
        "num-server-rounds=1 min-clients=2 min-fit=1 client-rollout-episodes=1 max-video-bytes={payload} \
         max-upload-memory-bytes={payload} {overrides}"
    ));
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut first, first_id, _) = RawClient::join_shard(&handle, "first", Some(0)).await;
    let (mut second, _, session) = RawClient::join_shard(&handle, "second", Some(1)).await;
    let round = first.task().await.round;
    second.task().await;
    let examples = linreg::train_examples(0) as u64;
    first.send(&ClientMessage::UpdateHeader { round, examples, train_loss: 1.0, payload_bytes: payload as u64 }).await;
    // The header is in once the console shows the client uploading: the budget is taken.
    loop {
        let clients = snapshot(&handle).await["clients"].clone();
        let row = clients.as_array().unwrap().iter().find(|c| c["id"] == first_id).cloned().unwrap();
        if row["state"] == "uploading" {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let auth = format!("Bearer {session}");
    let (status, body) =
        http(&handle, "POST", &format!("/rollout/{round}/v.webm"), &[("authorization", &auth)], vec![1; payload]).await;
    assert_eq!(status, 503, "a video does not wait for room: {body}");
    assert_eq!(refusals(&handle, ErrorCode::UploadBudget).await, 1);
    BudgetTaken { handle, run_dir, first, second, round, _base: base }
}

#[tokio::test]
async fn an_update_past_the_memory_budget_waits_until_the_one_in_flight_is_taken() {
    let update = linreg_head(0.2, -0.2);
    let payload = encode_payload(&update).len();
    let cfg = config(&format!("max-upload-memory-bytes={} max-video-bytes=1", payload - 1));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let other = tempfile::tempdir().unwrap();
    let err = fedvla_app::server::start(parts(cfg.clone(), RunDir::create(other.path(), &cfg).unwrap()), listener)
        .err()
        .expect("a budget below one update refuses to start");
    assert!(err.to_string().contains("cannot hold one update"), "{err}");

    let BudgetTaken { handle, run_dir, mut first, mut second, round, _base } = budget_taken(payload, "").await;
    // The second update waits for room (its frames unread in the socket) instead of being refused ...
    let other_update = linreg_head(0.3, 0.3);
    second.upload(round, &other_update, linreg::train_examples(1) as u64).await;
    // ... until the first's frames are in and the coordinator has taken it.
    for frame in fedvla_federation::codec::encode_update(&update, round, 64) {
        first.send_binary(frame).await;
    }
    let metrics = fedvla_federation::RoundMetrics {
        round,
        examples: 1,
        train_loss: 1.0,
        seconds: 0.0,
        bytes_up: 0,
        bytes_down: 0,
        download_bytes: 0,
    };
    first.send(&ClientMessage::Metrics(metrics)).await;
    let status = handle.finish().await.unwrap();
    // The update waited: the run refused none (the video's refusal is the app's, counted on the console).
    assert_eq!((status.completed_rounds, status.rejections.get(&ErrorCode::UploadBudget)), (1, None));
    let line = fedvla_aggregator::records::read_metrics(run_dir.path()).unwrap().pop().unwrap();
    assert_eq!(line.clients.iter().filter(|c| c.accepted).count(), 2, "both updates aggregated: {:?}", line.clients);
    let (w0, w1) = (linreg::train_examples(0) as f32, linreg::train_examples(1) as f32);
    let expected = update.zip_map(&other_update, |a, b| (a * w0 + b * w1) / (w0 + w1)).unwrap();
    let model = run_dir.load_model(1).unwrap();
    let diff = model.zip_map(&expected, |a, b| (a - b).abs()).unwrap();
    assert!(diff.iter().flat_map(|(_, t)| &t.values).all(|d| *d < 1e-6), "{model:?} against {expected:?}");
}

#[tokio::test]
async fn an_update_that_finds_no_room_within_a_rounds_deadline_is_refused() {
    let update = linreg_head(0.2, -0.2);
    let payload = encode_payload(&update).len();
    // `first` stays connected, holding the budget: its leaving would end its reservation.
    let BudgetTaken { handle, first: _first, mut second, round, .. } =
        budget_taken(payload, "round-deadline-ms=300").await;
    second.upload(round, &linreg_head(0.3, 0.3), linreg::train_examples(1) as u64).await;
    expect_error(second.recv().await, ErrorCode::UploadBudget);
    assert_eq!(refusals(&handle, ErrorCode::UploadBudget).await, 2, "the video and the update");
    handle.kill().await;
}
