//! What a stranger's input cannot do to the server: own or wrap the aggregate with example claims, end the run
//! with an update that breaks the aggregate, hold sockets open, grow its memory, upload files nobody asked for,
//! swap volunteers' shards across a restart, take another volunteer's name, shard or state, download anything
//! without a session (or another's shard with one), or join a closed federation without an admitted key.

mod common;

use std::time::Duration;

use common::*;
use fedvla_aggregator::config::ComputeDevice;
use fedvla_aggregator::registry::Registry;
use fedvla_aggregator::registry::VOLUNTEERS_FILE;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_federation::{AggregateError, ErrorCode, FedAvg, Identity, ServerMessage, TrainOutput, aggregate};
use fedvla_server::native_client::{Volunteer, VolunteerData};
use fedvla_workloads::linreg;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The weight of shard `k`'s updates: what the server knows the shard holds.
fn weight(k: usize) -> u64 {
    linreg::train_examples(k) as u64
}

#[tokio::test]
async fn example_claims_neither_wrap_nor_own_the_aggregate() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    // Two clients claim 2^63 examples each: summed in a u64 that wraps to 0 ("zero examples") and used to end the
    // run. A third trains normally.
    let (mut a, _, _) = RawClient::join_shard(&handle, "client-0", Some(0)).await;
    let (mut b, _, _) = RawClient::join_shard(&handle, "client-1", Some(1)).await;
    let (normal, recorded) = spawn_client(&handle, 2, None);
    let round = a.task().await.round;
    b.task().await;
    let (ua, ub) = (linreg_head(1.0, 0.5), linreg_head(-2.0, 1.5));
    a.upload(round, &ua, 1 << 63).await;
    b.upload(round, &ub, 1 << 63).await;

    let status = handle.finish().await.unwrap();
    normal.await.unwrap().unwrap();
    assert_eq!(status.completed_rounds, 1);
    assert_eq!(status.corrected_claims, 2);
    let normal_update = recorded.lock().unwrap()[0].1.clone();
    assert_eq!(normal_update.examples, weight(2), "an honest claim is the shard's size");
    let expected = weighted_mean(&[
        TrainOutput { update: ua, examples: weight(0), train_loss: 1.0 },
        TrainOutput { update: ub, examples: weight(1), train_loss: 1.0 },
        normal_update,
    ]);
    assert_close(&run_dir.load_model(1).unwrap(), &expected, 1e-6);
    let line = &metrics(run_dir.path())[1];
    let client = |name: &str| line["clients"].as_array().unwrap().iter().find(|c| c["name"] == name).unwrap().clone();
    assert_eq!(client("client-0")["examples"], weight(0));
    assert_eq!(client("client-0")["claimed_examples"], 1u64 << 63);
}

#[tokio::test]
async fn a_lone_client_claiming_zero_examples_still_closes_the_round() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 min-clients=1 min-fit=1");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut c, _, _) = RawClient::join_shard(&handle, "zero", Some(1)).await;
    let round = c.task().await.round;
    let update = linreg_head(0.5, -0.5);
    c.upload(round, &update, 0).await;
    let status = handle.finish().await.unwrap();
    assert_eq!((status.completed_rounds, status.skipped_rounds, status.corrected_claims), (1, 0, 1));
    assert_eq!(run_dir.load_model(1).unwrap(), update);
}

/// An update whose values are near f32's largest: finite, but averaged in, the held-out evaluation of the aggregate
/// would overflow.
fn overflowing_update() -> fedvla_federation::NamedTensors {
    linreg_head(f32::MAX / 2.0, f32::MAX / 2.0)
}

#[tokio::test]
async fn an_update_no_model_holds_is_dropped_as_it_arrives_and_the_rest_aggregated() {
    let base = tempfile::tempdir().unwrap();
    // The strategy's check alone: the norm screen would leave this update out before any aggregate.
    let cfg = config("num-server-rounds=1 min-clients=3 min-fit=2 update-norm-factor=0");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let good: Vec<_> = (0..2).map(|shard| spawn_client(&handle, shard, None)).collect();
    let (mut attacker, attacker_id, _) = RawClient::join_shard(&handle, "client-2", Some(2)).await;
    let round = attacker.task().await.round;
    attacker.upload(round, &overflowing_update(), weight(2)).await;

    let status = handle.finish().await.unwrap();
    assert_eq!((status.completed_rounds, status.skipped_rounds), (1, 0));
    assert_eq!(status.rejections.get(&ErrorCode::DroppedUpdate), Some(&1));
    let mut updates = Vec::new();
    for (task, recorded) in good {
        task.await.unwrap().unwrap();
        updates.push(recorded.lock().unwrap()[0].1.clone());
    }
    // The premise: its values are beyond what FedAvg's exact sum takes (and would overflow the evaluation).
    let mut with_attacker: Vec<_> = updates.iter().map(|u| (u.update.clone(), u.examples)).collect();
    with_attacker.push((overflowing_update(), weight(2)));
    let refused = aggregate(&FedAvg, &linreg::initial_model(0), with_attacker.iter().map(|(t, n)| (t, *n)));
    assert!(matches!(refused, Err(AggregateError::OutOfRange { index: 2, .. })), "{refused:?}");

    assert_close(&run_dir.load_model(1).unwrap(), &weighted_mean(&updates), 1e-6);
    let line = &metrics(run_dir.path())[1];
    let attacker_record =
        line["clients"].as_array().unwrap().iter().find(|c| c["client_id"] == attacker_id).unwrap().clone();
    assert_eq!(attacker_record["accepted"], false);
    assert!(attacker_record["dropped"].as_str().unwrap().contains("beyond"), "{attacker_record}");
    assert!(line["global"]["heldout_loss"].as_f64().unwrap().is_finite());
    assert_eq!(line["rejections"]["dropped_update"], 1);
}

#[tokio::test]
async fn a_round_with_no_usable_aggregate_is_skipped_and_the_run_goes_on() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=2 min-clients=1 min-fit=1");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut attacker, _, _) = RawClient::join_shard(&handle, "attacker", Some(0)).await;
    let round = attacker.task().await.round;
    attacker.upload(round, &overflowing_update(), weight(0)).await;
    // Round 1 closes, skipped; the attacker leaves and an honest client takes round 2.
    loop {
        if let Some(ServerMessage::RoundClosed { round: 1, .. }) = attacker.recv().await {
            break;
        }
    }
    drop(attacker);
    let (honest, recorded) = spawn_client(&handle, 1, None);
    let status = handle.finish().await.unwrap();
    honest.await.unwrap().unwrap();
    assert_eq!((status.completed_rounds, status.skipped_rounds), (2, 1));
    let lines = metrics(run_dir.path());
    assert!(lines[1]["skipped"].as_str().unwrap().contains("fewer than min-fit"), "{}", lines[1]);
    assert!(lines[1]["clients"][0]["dropped"].as_str().unwrap().contains("beyond"), "{}", lines[1]);
    assert_eq!(run_dir.load_model(1).unwrap(), linreg::initial_model(0), "a skipped round keeps the model");
    let (round, update) = recorded.lock().unwrap()[0].clone();
    assert_eq!(round, 2);
    assert_eq!(run_dir.load_model(2).unwrap(), update.update);
}

/// Whether the server closed `socket` within `within`: reads return end-of-file or an error.
async fn closed_within(socket: &mut TcpStream, within: Duration) -> bool {
    let mut buf = [0u8; 256];
    loop {
        match tokio::time::timeout(within, socket.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0) | Err(_)) => return true,
            // A 408 or similar before the close is fine.
            Ok(Ok(_)) => {}
        }
    }
}

#[tokio::test]
async fn slow_heads_silent_sockets_and_one_socket_too_many_are_closed() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("max-connections=4 header-read-timeout-ms=300 idle-timeout-ms=1000");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir).await;
    let mut half_heads = Vec::new();
    for _ in 0..2 {
        let mut s = TcpStream::connect(handle.addr()).await.unwrap();
        s.write_all(b"GET /api/volunteer HTTP/1.1\r\nHost: x\r\n").await.unwrap();
        half_heads.push(s);
    }
    let mut silent = Vec::new();
    for _ in 0..2 {
        silent.push(TcpStream::connect(handle.addr()).await.unwrap());
    }
    // The cap is reached: a fifth socket is accepted and closed at once.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut fifth = TcpStream::connect(handle.addr()).await.unwrap();
    assert!(closed_within(&mut fifth, Duration::from_millis(500)).await, "a socket over the cap is closed at once");
    for s in &mut half_heads {
        assert!(closed_within(s, Duration::from_secs(2)).await, "a half-sent head times out");
    }
    for s in &mut silent {
        assert!(closed_within(s, Duration::from_secs(2)).await, "a silent socket times out");
    }
    // The server serves others all along and after.
    let token = format!("Bearer {}", handle.operator_token());
    let (status, body) = http(&handle, "GET", "/console/api/snapshot", &[("authorization", &token)], Vec::new()).await;
    assert_eq!(status, 200, "{body}");
    let snapshot: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert!(snapshot["run"]["refused_connections"].as_u64().unwrap() >= 1, "{}", snapshot["run"]);
    handle.kill().await;
}

/// What the server answers `name` identifying with its name's simulated key, asking for `shard`.
async fn admission(handle: &fedvla_app::server::ServerHandle, name: &str, shard: Option<u32>) -> Option<ServerMessage> {
    RawClient::connect(handle).await.identify(&simulated_identity(name), name, shard).await
}

fn expect_refusal(answer: Option<ServerMessage>, code: ErrorCode, says: &str) {
    match answer {
        Some(ServerMessage::Error { code: got, message }) if got == code => {
            assert!(message.contains(says), "{message:?} should say {says:?}");
        }
        other => panic!("expected {}, got {other:?}", code.as_str()),
    }
}

#[tokio::test]
async fn names_are_bounded_and_the_registry_forgets_the_oldest() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("max-volunteer-names=2");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let long = "n".repeat(65);
    expect_refusal(admission(&handle, &long, None).await, ErrorCode::InvalidName, "65 bytes");
    expect_refusal(admission(&handle, "x", Some(9)).await, ErrorCode::UnknownShard, "no shard 9");
    let mut c = RawClient::connect(&handle).await;
    expect_refusal(c.identify(&simulated_identity(&long), &long, None).await, ErrorCode::InvalidName, "65 bytes");
    assert_eq!(c.recv().await, None, "closed after an invalid name");

    for name in ["a", "b", "c"] {
        assert!(matches!(admission(&handle, name, None).await, Some(ServerMessage::Admitted { .. })), "{name}");
    }
    let registry: Registry =
        serde_json::from_slice(&std::fs::read(run_dir.path().join(VOLUNTEERS_FILE)).unwrap()).unwrap();
    let mut names: Vec<&str> = registry.volunteers.values().map(|b| b.name.as_str()).collect();
    names.sort_unstable();
    assert_eq!(names, ["b", "c"], "at most two keys, the first bound forgotten");
    handle.kill().await;
}

#[tokio::test]
async fn rollout_videos_are_taken_only_for_the_rollouts_a_round_asked_for() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 min-clients=1 min-fit=1 client-rollout-episodes=1");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let (mut c, client_id, session) = RawClient::join_shard(&handle, "filmer", Some(0)).await;
    let auth = format!("Bearer {session}");
    let post = async |round: u64, file: &str| {
        http(&handle, "POST", &format!("/rollout/{round}/{file}"), &[("authorization", &auth)], vec![1; 64]).await
    };
    let task = c.task().await;
    assert_eq!(task.rollout.as_ref().map(|r| r.episodes), Some(1));
    assert_eq!(post(task.round + 4, "e.webm").await.0, 403, "a round that asked for nothing");
    let (status, body) = post(task.round, "e.webm").await;
    assert_eq!(status, 201, "{body}");
    let (status, body) = post(task.round, "f.webm").await;
    assert_eq!(status, 403, "one episode asked, one video taken: {body}");
    c.upload(task.round, &linreg_head(0.1, 0.1), weight(0)).await;
    handle.finish().await.unwrap();
    assert!(run_dir.client_eval_dir(task.round, client_id).join("e.webm").exists());
    assert!(!run_dir.client_eval_dir(task.round, client_id).join("f.webm").exists());
}

#[tokio::test]
async fn shards_and_client_ids_survive_a_restart() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let shard_of = async |handle: &fedvla_app::server::ServerHandle, name: &str| -> u32 {
        match admission(handle, name, None).await {
            Some(ServerMessage::Admitted { setup, .. }) => setup.shard_index,
            other => panic!("expected the admission of {name}, got {other:?}"),
        }
    };
    let handle = start(cfg.clone(), run_dir.clone()).await;
    let mut before = Vec::new();
    for name in ["x", "y", "z"] {
        before.push(shard_of(&handle, name).await);
    }
    assert_eq!(before, [0, 1, 2]);
    let (_c, first_id) = RawClient::join(&handle, "w").await;
    handle.kill().await;

    let (run_dir, cfg) = RunDir::open(run_dir.path()).unwrap();
    let handle = start(cfg, run_dir).await;
    // Asked in the other order, each key gets its shard back.
    for (name, shard) in [("z", 2), ("y", 1), ("x", 0)] {
        assert_eq!(shard_of(&handle, name).await, shard, "{name}");
    }
    let (_c, second_id) = RawClient::join(&handle, "w").await;
    assert!(second_id > first_id, "client ids are never handed out twice: {first_id} then {second_id}");
    handle.kill().await;
}

/// Another key using a volunteer's name is refused (`name_taken`), and asking for its shard under another name too
/// (`shard_taken`): it gets neither the shard nor the strategy state, which follows the shard bound to a key. With
/// a session of its own it cannot download that shard (403); the volunteer, with its key, keeps name and shard,
/// across a restart too.
#[tokio::test]
async fn a_second_volunteer_using_anothers_name_gets_neither_its_shard_nor_its_state() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let alice = simulated_identity("alice");
    let mallory = Identity::from_seed([0x66; 32]);
    let mut a = RawClient::connect(&handle).await;
    let Some(ServerMessage::Admitted { session: alice_session, setup, .. }) =
        a.identify(&alice, "alice", Some(1)).await
    else {
        panic!("alice is admitted")
    };
    assert_eq!(setup.shard_index, 1);

    let mut m = RawClient::connect(&handle).await;
    expect_refusal(m.identify(&mallory, "alice", None).await, ErrorCode::NameTaken, "belongs to another key");
    assert_eq!(m.recv().await, None, "closed after the refusal");
    let mut m = RawClient::connect(&handle).await;
    expect_refusal(m.identify(&mallory, "mallory", Some(1)).await, ErrorCode::ShardTaken, "shard 1");
    // A signature for another challenge (a replayed one) proves nothing.
    let mut m = RawClient::connect(&handle).await;
    m.challenge().await;
    let replayed = identify_message(&alice, "00", "alice", None, fedvla_federation::PROTOCOL_VERSION);
    m.send(&replayed).await;
    expect_refusal(m.recv().await, ErrorCode::Unauthorized, "identity not proven");

    let mut m = RawClient::connect(&handle).await;
    let Some(ServerMessage::Admitted { session: mallory_session, setup, .. }) =
        m.identify(&mallory, "mallory", None).await
    else {
        panic!("mallory is admitted under a name of its own")
    };
    assert_ne!(setup.shard_index, 1, "round-robin never hands out a shard asked for by name");
    let bearer = |session: &str| format!("Bearer {session}");
    for path in ["/shard/1", "/shard/1/manifest"] {
        let (status, body) =
            http(&handle, "GET", path, &[("authorization", &bearer(&mallory_session))], Vec::new()).await;
        assert_eq!(status, 403, "{path} with another key's session: {body}");
        // linreg's shards are generated from their index, not files: alice passes the check and hears so.
        let (status, body) =
            http(&handle, "GET", path, &[("authorization", &bearer(&alice_session))], Vec::new()).await;
        assert_eq!(status, 404, "{path} with its key's session: {body}");
    }
    handle.kill().await;

    let (run_dir, cfg) = RunDir::open(run_dir.path()).unwrap();
    let handle = start(cfg, run_dir).await;
    expect_refusal(admission_as(&handle, &mallory, "alice").await, ErrorCode::NameTaken, "alice");
    match admission_as(&handle, &alice, "alice").await {
        Some(ServerMessage::Admitted { setup, .. }) => assert_eq!(setup.shard_index, 1, "alice keeps her shard"),
        other => panic!("alice is admitted again, got {other:?}"),
    }
    handle.kill().await;
}

async fn admission_as(
    handle: &fedvla_app::server::ServerHandle,
    identity: &Identity,
    name: &str,
) -> Option<ServerMessage> {
    RawClient::connect(handle).await.identify(identity, name, None).await
}

/// A closed federation (`allowed-keys`) admits the keys of its list and refuses any other, with the run's auth
/// token or not.
#[tokio::test]
async fn a_closed_federation_admits_only_the_keys_of_its_allow_list() {
    let base = tempfile::tempdir().unwrap();
    let insider = simulated_identity("insider");
    let list = base.path().join("allowed.txt");
    std::fs::write(&list, format!("# the federation's volunteers\n{}\n\n", insider.public_key_hex().to_uppercase()))
        .unwrap();
    let cfg = config(&format!("allowed-keys={}", list.display()));
    let handle = start(cfg.clone(), RunDir::create(base.path(), &cfg).unwrap()).await;
    expect_refusal(admission(&handle, "outsider", None).await, ErrorCode::Unauthorized, "allow-list");
    assert!(matches!(admission(&handle, "insider", None).await, Some(ServerMessage::Admitted { .. })));
    handle.kill().await;
}

/// A run with an auth token serves nothing without a session: every download and upload route answers 401
/// without one, with the auth token in its place or with a made-up one, and a session (which only an admission with
/// the token gives) opens them; a whole federation of native volunteers holding the token runs to its end.
#[tokio::test]
async fn without_a_session_every_download_route_of_a_run_with_an_auth_token_answers_401() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("num-server-rounds=1 auth-token=s3cret");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let routes = [
        ("GET", "/shard/0"),
        ("GET", "/shard/0/manifest"),
        ("GET", "/model/0"),
        ("GET", "/policy/frozen/0123456789abcdef"),
        ("GET", "/api/tokenizer"),
        ("GET", "/scaffold/1"),
        ("POST", "/rollout/1/e.webm"),
    ];
    let unauthorised = [&[][..], &[("authorization", "Bearer s3cret")][..], &[("authorization", "Bearer 00ff")][..]];
    for (method, path) in routes {
        for headers in unauthorised {
            let (status, body) = http(&handle, method, path, headers, vec![1; 8]).await;
            assert_eq!(status, 401, "{method} {path} {headers:?}: {body}");
        }
    }
    // The identify needs the token; then the session opens the downloads (linreg has no shard files, frozen
    // weights or tokenizer: the server says so, but only to a session's holder).
    let mut c = RawClient::connect(&handle).await;
    expect_refusal(c.identify(&simulated_identity("eve"), "eve", None).await, ErrorCode::Unauthorized, "auth token");
    let mut c = RawClient::connect(&handle).await;
    let nonce = c.challenge().await;
    let ServerMessage::Admitted { session, setup, .. } = ({
        let mut identify =
            identify_message(&simulated_identity("eve"), &nonce, "eve", None, fedvla_federation::PROTOCOL_VERSION);
        if let fedvla_federation::ClientMessage::Identify { auth_token, .. } = &mut identify {
            *auth_token = Some("s3cret".into());
        }
        c.send(&identify).await;
        c.recv().await.unwrap()
    }) else {
        panic!("admitted with the token")
    };
    let auth = format!("Bearer {session}");
    let (status, body) = http(&handle, "GET", "/model/0", &[("authorization", &auth)], Vec::new()).await;
    assert_eq!(status, 200, "{body}");
    let own_shard = format!("/shard/{}/manifest", setup.shard_index);
    let (status, body) = http(&handle, "GET", &own_shard, &[("authorization", &auth)], Vec::new()).await;
    assert_eq!(status, 404, "{own_shard}: {body}");
    drop(c);
    let url = format!("ws://{}", handle.addr());
    let clients: Vec<_> = (0..3)
        .map(|shard| {
            let url = url.clone();
            tokio::spawn(async move {
                let name = format!("client-{shard}");
                let identity = simulated_identity(&name);
                let volunteer = Volunteer {
                    server: &url,
                    ca_cert: None,
                    name: &name,
                    identity: &identity,
                    // Round-robin: eve, admitted above, holds shard 0, which a request would be refused.
                    data: VolunteerData::Shard(None),
                    auth_token: Some("s3cret".into()),
                    attack: None,
                    device: ComputeDevice::Cpu,
                };
                fedvla_server::native_client::volunteer(volunteer, |_| {}).await.map_err(|e| e.to_string())
            })
        })
        .collect();
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 1);
    for client in clients {
        client.await.unwrap().unwrap();
    }
}
