//! Stragglers, dropped clients and bad input: the server refuses with a clear error, counts it, and carries on.

mod common;

use std::time::{Duration, Instant};

use common::*;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_federation::codec::{encode_payload, encode_update};
use fedvla_federation::{
    ClientMessage, ErrorCode, NamedTensors, PROTOCOL_VERSION, RoundMetrics, ServerMessage, TrainOutput,
};
use fedvla_workloads::linreg::{self, BIAS, FEATURES, WEIGHT};

#[tokio::test]
async fn straggler_and_dropped_clients_do_not_stall_the_round() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 num-clients=5 min-clients=5 min-fit=2 round-deadline-ms=1500");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let good: Vec<_> = (0..2).map(|shard| spawn_client(&handle, shard, None)).collect();
    let (straggler, _) = spawn_client(&handle, 2, Some(1));
    // A client that takes its task and disconnects without answering.
    // Its own shard asked for: one dealt round-robin could be one the clients above ask for (shard_taken).
    let (mut dropper, _, _) = RawClient::join_shard(&handle, "client-3", Some(3)).await;
    // A client that uploads its update, then disconnects before the round closes: its update still counts, with
    // the weight of its shard, not the 10 examples it claims.
    let (mut leaver, _, _) = RawClient::join_shard(&handle, "client-4", Some(4)).await;
    let started = Instant::now();
    assert!(matches!(dropper.recv().await, Some(ServerMessage::RoundTask(_))));
    drop(dropper);
    let Some(ServerMessage::RoundTask(task)) = leaver.recv().await else { panic!("task") };
    let leaver_update = TrainOutput {
        update: head(vec![0.25; FEATURES], vec![-0.5]),
        examples: linreg::train_examples(4) as u64,
        train_loss: 1.0,
    };
    let payload = encode_payload(&leaver_update.update);
    leaver
        .send(&ClientMessage::UpdateHeader {
            round: task.round,
            examples: 10,
            train_loss: 1.0,
            payload_bytes: payload.len() as u64,
        })
        .await;
    for frame in encode_update(&leaver_update.update, task.round, 64) {
        leaver.send_binary(frame).await;
    }
    leaver
        .send(&ClientMessage::Metrics(RoundMetrics {
            round: task.round,
            examples: 10,
            train_loss: 1.0,
            seconds: 0.0,
            bytes_up: 0,
            bytes_down: 0,
            download_bytes: 0,
        }))
        .await;
    drop(leaver);

    let status = handle.finish().await.unwrap();
    let elapsed = started.elapsed();
    assert_eq!(status.completed_rounds, 1);
    assert_eq!(status.corrected_claims, 1, "the leaver's claim of 10 examples was corrected");
    assert!(elapsed >= Duration::from_millis(1400), "closed at the deadline, not before: {elapsed:?}");
    assert!(elapsed < Duration::from_secs(8), "closed at the deadline, not after: {elapsed:?}");
    straggler.abort();

    let mut updates: Vec<TrainOutput> = Vec::new();
    for (task, rec) in good {
        task.await.unwrap().unwrap();
        updates.extend(rec.lock().unwrap().iter().map(|(_, u)| u.clone()));
    }
    assert_eq!(updates.len(), 2);
    updates.push(leaver_update);
    assert_close(&run_dir.load_model(1).unwrap(), &weighted_mean(&updates), 1e-6);
    let line = &metrics_lines(run_dir.path())[1];
    let accepted: Vec<&str> = line.clients.iter().filter(|c| c.accepted).map(|c| c.name.as_str()).collect();
    assert_eq!(accepted, ["client-0", "client-1", "client-4"]);
}

#[tokio::test]
async fn too_few_updates_retry_the_round() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 min-clients=2 min-fit=2 round-deadline-ms=300");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    // Only one real client at first: with a straggler the round cannot reach min-fit and is retried.
    let (straggler, _) = spawn_client(&handle, 2, Some(1));
    let (first, _) = spawn_client(&handle, 0, None);
    wait_status(&handle, |s| s.retried_rounds >= 1).await;
    straggler.abort();
    let (second, _) = spawn_client(&handle, 1, None);
    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 1);
    first.await.unwrap().unwrap();
    second.await.unwrap().unwrap();
    let lines = metrics_lines(run_dir.path());
    assert_eq!(lines.len(), 2, "a retried attempt is not a round");
    assert!(lines[1].attempt.expect("the closing attempt recorded") >= 1);
}

/// An update for the running round from a client the round did not sample, and a second update from a sampled
/// one, are refused with their own codes; the round aggregates the first updates as if neither had been sent.
#[tokio::test]
async fn unrequested_and_duplicate_updates_are_refused_with_their_own_codes() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 num-clients=3 min-clients=2 min-fit=2 round-deadline-ms=20000");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut first, _, _) = RawClient::join_shard(&handle, "client-0", Some(0)).await;
    let (mut second, _, _) = RawClient::join_shard(&handle, "client-1", Some(1)).await;
    for c in [&mut first, &mut second] {
        assert!(matches!(c.recv().await, Some(ServerMessage::RoundTask(_))));
    }
    // Joined after the round sampled its clients.
    let (mut late, _, _) = RawClient::join_shard(&handle, "client-2", Some(2)).await;
    late.upload(1, &linreg_head(9.0, 0.0), 1).await;
    expect_error(late.recv().await, ErrorCode::UnrequestedUpdate, "not sampled");
    first.upload(1, &linreg_head(0.5, 0.0), 1).await;
    first.upload(1, &linreg_head(9.0, 0.0), 1).await;
    expect_error(first.recv().await, ErrorCode::DuplicateUpdate, "second update");
    second.upload(1, &linreg_head(1.5, 0.0), 1).await;

    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 1);
    assert_eq!(status.rejections.get(&ErrorCode::UnrequestedUpdate), Some(&1));
    assert_eq!(status.rejections.get(&ErrorCode::DuplicateUpdate), Some(&1));
    // The shard-weighted mean of 0.5 and 1.5: neither 9.0 went in.
    let model = run_dir.load_model(1).unwrap();
    let weights = &model.get(WEIGHT).unwrap().values;
    assert!(weights.iter().all(|w| (0.5..=1.5).contains(w)), "{weights:?}");
}

fn head(weight: Vec<f32>, bias: Vec<f32>) -> NamedTensors {
    let mut t = NamedTensors::new();
    t.insert(WEIGHT, vec![1, FEATURES], weight).unwrap();
    t.insert(BIAS, vec![bias.len()], bias).unwrap();
    t
}

/// Announces and sends an update; returns the server's answer.
async fn upload(c: &mut RawClient, tensors: &NamedTensors) -> Option<ServerMessage> {
    let payload = encode_payload(tensors);
    c.send(&ClientMessage::UpdateHeader {
        round: 1,
        examples: 10,
        train_loss: 0.5,
        payload_bytes: payload.len() as u64,
    })
    .await;
    for frame in encode_update(tensors, 1, 64) {
        c.send_binary(frame).await;
    }
    c.recv().await
}

fn expect_error(reply: Option<ServerMessage>, code: ErrorCode, needle: &str) {
    match reply {
        Some(ServerMessage::Error { code: got, message }) => {
            assert_eq!(got, code, "{message}");
            assert!(message.contains(needle), "`{message}` should mention `{needle}`");
        }
        other => panic!("expected {code:?} error, got {other:?}"),
    }
}

#[tokio::test]
async fn bad_clients_are_refused_counted_and_the_server_carries_on() {
    let base = tempfile::tempdir().unwrap();
    // Shards 3 and 4 for the bad clients: the good ones ask for 0 to 2, which a key holding them would refuse.
    let cfg = config("num-server-rounds=1 num-clients=5");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let good_weight = linreg::initial_model(0).get(WEIGHT).unwrap().values.clone();

    // Wrong protocol version on identify: refused and disconnected.
    let mut c = RawClient::connect(&handle).await;
    let nonce = c.challenge().await;
    c.send(&identify_message(&simulated_identity("old"), &nonce, "old", None, PROTOCOL_VERSION + 1)).await;
    expect_error(c.recv().await, ErrorCode::ProtocolVersion, &format!("protocol version {}", PROTOCOL_VERSION + 1));
    assert_eq!(c.recv().await, None, "connection closed after a fatal error");

    // Non-fatal errors, one connection.
    let (mut c, _, _) = RawClient::join_shard(&handle, "bad", Some(3)).await;
    c.send_text("{\"type\":\"metrics\", \"round\": \"one\"}".into()).await;
    expect_error(c.recv().await, ErrorCode::MalformedMessage, "bad control message");

    c.send(&ClientMessage::UpdateHeader { round: 1, examples: 1, train_loss: 0.0, payload_bytes: 12 }).await;
    c.send_binary(b"definitely not a frame".to_vec()).await;
    expect_error(c.recv().await, ErrorCode::MalformedFrame, "magic");

    // The rest of a refused update is dropped silently; after a control message a stray frame is an error.
    c.send_binary(vec![0; 8]).await;
    c.send(&ClientMessage::Heartbeat).await;
    c.send_binary(vec![0; 8]).await;
    expect_error(c.recv().await, ErrorCode::UnexpectedMessage, "without an update header");

    let missing = {
        let mut t = NamedTensors::new();
        t.insert(WEIGHT, vec![1, FEATURES], good_weight.clone()).unwrap();
        t
    };
    expect_error(upload(&mut c, &missing).await, ErrorCode::MissingTensor, BIAS);

    let mut extra = head(good_weight.clone(), vec![0.0]);
    extra.insert("vision.frozen", vec![2], vec![0.0; 2]).unwrap();
    expect_error(upload(&mut c, &extra).await, ErrorCode::UnexpectedTensor, "vision.frozen");

    let misshaped = head(good_weight.clone(), vec![0.0, 0.0]);
    expect_error(upload(&mut c, &misshaped).await, ErrorCode::ShapeMismatch, "expected [1]");

    let mut nan_weight = good_weight.clone();
    nan_weight[5] = f32::NAN;
    expect_error(upload(&mut c, &head(nan_weight, vec![0.0])).await, ErrorCode::NonFinite, "index 5");

    c.send(&ClientMessage::UpdateHeader { round: 1, examples: 1, train_loss: 0.0, payload_bytes: 1 << 30 }).await;
    expect_error(c.recv().await, ErrorCode::Oversized, "1073741824");

    let frames = encode_update(&head(good_weight.clone(), vec![0.0]), 1, 1 << 16);
    let payload_bytes = (frames[0].len() - fedvla_federation::codec::HEADER_LEN) as u64;
    c.send(&ClientMessage::UpdateHeader { round: 1, examples: 1, train_loss: 0.0, payload_bytes }).await;
    c.send_binary(frames[0].clone()).await;
    expect_error(c.recv().await, ErrorCode::Oversized, "frame limit");

    let mut frames = encode_update(&head(good_weight.clone(), vec![0.0]), 1, 64);
    frames[0][4..6].copy_from_slice(&(PROTOCOL_VERSION + 1).to_le_bytes());
    let payload_bytes = encode_payload(&head(good_weight.clone(), vec![0.0])).len() as u64;
    c.send(&ClientMessage::UpdateHeader { round: 1, examples: 1, train_loss: 0.0, payload_bytes }).await;
    c.send_binary(frames[0].clone()).await;
    expect_error(c.recv().await, ErrorCode::ProtocolVersion, "protocol version");
    assert_eq!(c.recv().await, None, "connection closed after a fatal error");

    // A valid update outside any round is refused as stale, not aggregated.
    let (mut c, _, _) = RawClient::join_shard(&handle, "early", Some(4)).await;
    expect_error(upload(&mut c, &head(good_weight, vec![0.0])).await, ErrorCode::StaleRound, "not expected");
    drop(c);

    let status = wait_status(&handle, |s| s.connected == 0 && s.rejections.values().sum::<u64>() == 12).await;
    let count = |code| status.rejections.get(&code).copied().unwrap_or(0);
    assert_eq!(count(ErrorCode::ProtocolVersion), 2);
    assert_eq!(count(ErrorCode::Oversized), 2);
    for code in [
        ErrorCode::MalformedMessage,
        ErrorCode::MalformedFrame,
        ErrorCode::UnexpectedMessage,
        ErrorCode::MissingTensor,
        ErrorCode::UnexpectedTensor,
        ErrorCode::ShapeMismatch,
        ErrorCode::NonFinite,
        ErrorCode::StaleRound,
    ] {
        assert_eq!(count(code), 1, "{code:?}");
    }

    // The server carries on: a normal round with three good clients.
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 1);
    for (task, _) in clients {
        task.await.unwrap().unwrap();
    }
    let line = &metrics_lines(run_dir.path())[1];
    assert_eq!(line.rejections.get("non_finite"), Some(&1), "{line:?}");
    assert_eq!(line.rejections.get("protocol_version"), Some(&2), "{line:?}");
}
