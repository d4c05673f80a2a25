//! Full runs over loopback WebSockets: aggregation, wire bytes, metrics, determinism.

mod common;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::{RunDir, TRAINABLE_FILE};
use fedvla_federation::codec::{HEADER_LEN, model_deltas_len, payload_len};
use fedvla_federation::protocol::INT8_BLOCK;
use fedvla_federation::{TrainOutput, UpdateEncoding};
use fedvla_workloads::linreg;
use tokio::sync::Semaphore;

#[tokio::test]
async fn three_clients_two_rounds() {
    let base = tempfile::tempdir().unwrap();
    let cfg = config("");
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let dir = run_dir.path().to_owned();
    let handle = start(cfg.clone(), run_dir.clone()).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 2);
    assert!(status.rejections.is_empty(), "{:?}", status.rejections);
    let mut recorded = Vec::new();
    for (task, rec) in clients {
        let summary = task.await.unwrap().unwrap();
        assert_eq!(summary.rounds_trained, 2);
        recorded.push(rec);
    }

    // The global model of each round is the example-weighted mean of that round's updates.
    for round in 1..=2 {
        let updates: Vec<TrainOutput> = recorded
            .iter()
            .flat_map(|r| {
                r.lock().unwrap().iter().filter(|(r, _)| *r == round).map(|(_, u)| u.clone()).collect::<Vec<_>>()
            })
            .collect();
        assert_eq!(updates.len(), 3);
        assert_ne!(updates[0].examples, updates[1].examples, "unequal weights make the test meaningful");
        assert_close(&run_dir.load_model(round).unwrap(), &weighted_mean(&updates), 1e-6);
        // Each client's record holds the norm of its change from the model the round started from.
        let start = run_dir.load_model(round - 1).unwrap();
        let sorted = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v
        };
        let sent = sorted(updates.iter().map(|u| u.update.distance(&start).unwrap()).collect());
        let line = &read_metrics(&dir).unwrap()[round as usize];
        let recorded = sorted(line.clients.iter().map(|c| c.update_norm.expect("an accepted update's norm")).collect());
        assert_eq!(recorded, sent);
        assert!(sent.iter().all(|n| *n > 0.0));
    }

    // Only the trainable head crosses the wire: payload (names, shapes, f32 values) plus one header per frame.
    let spec = linreg::initial_model(0).spec();
    let payload: usize = 1
        + 4
        + spec.iter().map(|(n, s)| 4 + n.len() + 4 + 8 * s.len() + 4 * s.iter().product::<usize>()).sum::<usize>();
    let frames = payload.div_ceil(cfg.max_frame_bytes - HEADER_LEN);
    assert!(frames > 1, "the test should exercise chunking");
    let expected_bytes = (payload + frames * HEADER_LEN) as u64;
    let frozen_bytes = (linreg::FEATURES * linreg::INPUTS * 4) as u64;
    assert!(expected_bytes < spec.byte_size() as u64 + frozen_bytes);

    let lines = metrics_lines(&dir);
    assert_eq!(lines.iter().map(|l| l.round).collect::<Vec<_>>(), [0, 1, 2]);
    assert!(lines[0].clients.is_empty());
    for line in &lines[1..] {
        let clients = &line.clients;
        assert_eq!(clients.len(), 3);
        for c in clients {
            assert_eq!(c.update_bytes, Some(expected_bytes), "{c:?}");
            assert!(c.train_loss.expect("train loss recorded") > 0.0);
            assert!(c.examples.expect("examples recorded") >= 48);
            assert!(c.seconds.is_some());
            assert!(c.bytes_up.expect("bytes up recorded") >= expected_bytes);
            assert!(c.bytes_down.expect("bytes down recorded") > 0);
            assert!(c.eval_loss.is_some());
        }
    }
    // Held-out loss of the global model falls.
    let loss = |i: usize| heldout_loss(&lines[i]);
    assert!(loss(2) < loss(1) && loss(1) < loss(0), "{} {} {}", loss(0), loss(1), loss(2));
    assert!(dir.join("global_model/round_0").join(TRAINABLE_FILE).exists());
    assert!(dir.join("config.toml").exists());
}

/// How far an encoding may move one value `d` of a client's delta whose tensor's values are `all` (point 3 of
/// the compression issue): f16 and bf16 round to nearest, int8 to its block's absmax / 254, and top-k drops at
/// most values no larger than the smallest it keeps.
fn encoding_error_bound(encoding: UpdateEncoding, all: &[f32], index: usize) -> f32 {
    let d = all[index].abs();
    match encoding {
        UpdateEncoding::F32 => 0.0,
        UpdateEncoding::F16 => d * 2f32.powi(-11) + 6e-8,
        UpdateEncoding::Bf16 => d * 2f32.powi(-8),
        UpdateEncoding::Int8 => {
            let block = &all[index / INT8_BLOCK * INT8_BLOCK..all.len().min((index / INT8_BLOCK + 1) * INT8_BLOCK)];
            block.iter().fold(0f32, |m, v| m.max(v.abs())) / 254.0
        }
        UpdateEncoding::Topk { fraction } => {
            let mut magnitudes: Vec<f32> = all.iter().map(|v| v.abs()).collect();
            magnitudes.sort_by(|a, b| b.total_cmp(a));
            magnitudes[UpdateEncoding::topk_count(fraction, all.len()) - 1]
        }
    }
}

/// Each update encoding over loopback: the global model after round 1 is the example-weighted mean of what the
/// clients trained, within the encoding's bound of every value (twice over for a compressed encoding: the clients'
/// updates, then the server's of the global change, which volunteers download as deltas); every update's bytes in
/// `metrics.jsonl` are the encoding's payload in frames; and a compressed run still learns.
#[tokio::test]
async fn every_update_encoding_aggregates_within_its_bound() {
    let spec = linreg::initial_model(0).spec();
    let f32_bytes = payload_len(&spec, UpdateEncoding::F32);
    for name in ["f32", "f16", "bf16", "int8", "topk"] {
        let base = tempfile::tempdir().unwrap();
        let cfg = config(&format!("update-encoding={name} topk-fraction=0.3 max-frame-bytes=4096"));
        let encoding = cfg.encoding();
        let run_dir = RunDir::create(base.path(), &cfg).unwrap();
        let handle = start(cfg.clone(), run_dir.clone()).await;
        let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
        let status = handle.finish().await.unwrap();
        assert_eq!(status.completed_rounds, 2, "{name}");
        assert!(status.rejections.is_empty(), "{name}: {:?}", status.rejections);
        let mut round_one = Vec::new();
        for (task, rec) in clients {
            task.await.unwrap().unwrap();
            round_one.extend(rec.lock().unwrap().iter().filter(|(r, _)| *r == 1).map(|(_, u)| u.clone()));
        }
        let global = run_dir.load_model(0).unwrap();
        let aggregate = run_dir.load_model(1).unwrap();
        // The server's encoding of the global change: as the clients' for f16, bf16 and int8 (bounded here on the
        // change as encoded, within 0.1% of the change itself), exact to an ulp for top-k, none for f32.
        let served = match encoding {
            UpdateEncoding::F32 | UpdateEncoding::Topk { .. } => UpdateEncoding::F32,
            lossy => lossy,
        };
        let exact = weighted_mean(&round_one);
        let total: f32 = round_one.iter().map(|u| u.examples as f32).sum();
        for (tensor, t) in exact.iter() {
            let deltas: Vec<Vec<f32>> = round_one
                .iter()
                .map(|u| {
                    u.update
                        .get(tensor)
                        .unwrap()
                        .values
                        .iter()
                        .zip(&global.get(tensor).unwrap().values)
                        .map(|(u, g)| u - g)
                        .collect()
                })
                .collect();
            let change: Vec<f32> = aggregate
                .get(tensor)
                .unwrap()
                .values
                .iter()
                .zip(&global.get(tensor).unwrap().values)
                .map(|(a, g)| a - g)
                .collect();
            for (i, want) in t.values.iter().enumerate() {
                let bound: f32 = round_one
                    .iter()
                    .zip(&deltas)
                    .map(|(u, d)| u.examples as f32 / total * encoding_error_bound(encoding, d, i))
                    .sum::<f32>()
                    + encoding_error_bound(served, &change, i)
                    + want.abs() * f32::EPSILON;
                let got = aggregate.get(tensor).unwrap().values[i];
                assert!(
                    (got - want).abs() <= bound * 1.001 + 1e-6,
                    "{name}: {tensor}[{i}] {got} against {want} (bound {bound})"
                );
            }
        }
        let payload = payload_len(&spec, encoding);
        let expected = (payload + payload.div_ceil(cfg.max_frame_bytes - HEADER_LEN) * HEADER_LEN) as u64;
        let lines = read_metrics(run_dir.path()).unwrap();
        for line in &lines[1..] {
            assert!(line.clients.iter().all(|c| c.update_bytes == Some(expected)), "{name}: {:?}", line.clients);
        }
        if encoding != UpdateEncoding::F32 {
            assert!(payload < f32_bytes, "{name}: a payload of {payload} bytes against f32's {f32_bytes}");
        }
        let loss = |i: usize| lines[i].global.as_ref().and_then(|g| g.eval.as_ref()).unwrap().heldout_loss;
        assert!(loss(2) < loss(0), "{name}: held-out loss {} -> {}", loss(0), loss(2));
    }
}

/// Downloads of the global model over loopback, in each update encoding: two of three volunteers a round (so some
/// hold a model more than one version old), four rounds. Every model a volunteer trained from is the server's of
/// that version bit for bit; the first download is the whole model, and each later one, of a compressed run, the
/// chain of deltas since the version the volunteer held (f16, bf16, int8: the encoding's payload a round, while
/// the chain is shorter than the model), smaller than the whole model after one round; an f32 run's are whole.
#[tokio::test]
async fn volunteers_download_deltas_and_hold_the_servers_model_bit_for_bit() {
    let spec = linreg::initial_model(0).spec();
    for name in ["f32", "f16", "bf16", "int8", "topk"] {
        let base = tempfile::tempdir().unwrap();
        let cfg =
            config(&format!("update-encoding={name} topk-fraction=0.1 num-server-rounds=4 fraction-fit=0.5 min-fit=2"));
        let encoding = cfg.encoding();
        let run_dir = RunDir::create(base.path(), &cfg).unwrap();
        let handle = start(cfg.clone(), run_dir.clone()).await;
        let mut clients = Vec::new();
        for shard in 0..3 {
            let (trainer, _) = TestTrainer::new(shard, None);
            let (tasks, globals) = (trainer.tasks(), trainer.globals());
            clients.push((format!("client-{shard}"), spawn_trainer(&handle, shard, trainer), tasks, globals));
        }
        let status = handle.finish().await.unwrap();
        assert_eq!(status.completed_rounds, 4, "{name}");
        assert!(status.rejections.is_empty(), "{name}: {:?}", status.rejections);
        let lines = read_metrics(run_dir.path()).unwrap();
        let whole = |version: u64| run_dir.load_model(version).unwrap().to_safetensors().unwrap().len() as u64;
        let mut deltas_downloaded = 0;
        for (client, task, tasks, globals) in clients {
            task.await.unwrap().unwrap();
            let (tasks, globals) = (tasks.lock().unwrap().clone(), globals.lock().unwrap().clone());
            assert_eq!(tasks.len(), globals.len(), "{name}: one global model a task");
            assert!(tasks.len() >= 2, "{name}: {client} trained {} rounds", tasks.len());
            let mut held = None;
            for (task, model) in tasks.iter().zip(&globals) {
                let server = run_dir.load_model(task.model_version).unwrap();
                assert_eq!(model.checksum(), server.checksum(), "{name}: {client}, version {}", task.model_version);
                assert_eq!(model, &server, "{name}: {client}, version {}", task.model_version);
                let record = lines[task.round as usize].clients.iter().find(|c| c.name == client).unwrap();
                let downloaded = record.download_bytes.expect("the client reported its download");
                let full = whole(task.model_version);
                let expected = match (held, encoding) {
                    (Some(held), _) if held == task.model_version => Some(0),
                    (None, _) | (_, UpdateEncoding::F32) => Some(full),
                    (Some(held), UpdateEncoding::Topk { .. }) => {
                        assert!(
                            downloaded <= full,
                            "{name}: {client} downloaded {downloaded} bytes, the model is {full}"
                        );
                        (task.model_version == held + 1).then(|| {
                            assert!(downloaded < full, "{name}: {client}'s delta of {downloaded} bytes, model {full}");
                            downloaded
                        })
                    }
                    (Some(held), lossy) => {
                        let steps = (task.model_version - held) as usize;
                        let chain = model_deltas_len(steps, steps * payload_len(&spec, lossy)) as u64;
                        Some(if chain < full { chain } else { full })
                    }
                };
                if let Some(expected) = expected {
                    assert_eq!(downloaded, expected, "{name}: {client}, version {} held {held:?}", task.model_version);
                }
                deltas_downloaded += usize::from(held.is_some() && downloaded < full);
                held = Some(task.model_version);
            }
        }
        match encoding {
            UpdateEncoding::F32 => assert_eq!(deltas_downloaded, 0, "f32 runs serve whole models"),
            _ => assert!(deltas_downloaded >= 3, "{name}: {deltas_downloaded} downloads of deltas"),
        }
        let loss = |i: usize| lines[i].global.as_ref().and_then(|g| g.eval.as_ref()).unwrap().heldout_loss;
        assert!(loss(4) < loss(0), "{name}: held-out loss {} -> {}", loss(0), loss(4));
    }
}

/// The final global model of a 3-client run whose clients finish each round's training in `order`: each client
/// trains only once the previous one's update is trained and on its way.
async fn model_with_arrivals(order: [usize; 3], overrides: &str) -> Vec<u8> {
    let base = tempfile::tempdir().unwrap();
    let cfg = config(overrides);
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg.clone(), run_dir.clone()).await;
    let gates: Vec<Arc<Semaphore>> = (0..3).map(|_| Arc::new(Semaphore::new(0))).collect();
    let mut recorded = Vec::new();
    for (shard, gate) in gates.iter().enumerate() {
        let (trainer, rec) = TestTrainer::new(shard, None);
        spawn_trainer(&handle, shard, trainer.gated(Arc::clone(gate)));
        recorded.push(rec);
    }
    for round in 1..=cfg.num_server_rounds {
        for &k in &order {
            gates[k].add_permits(1);
            while !recorded[k].lock().unwrap().iter().any(|(r, _)| *r == round) {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            // Loopback delivers a few hundred bytes well within this: the next client starts after it arrived.
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    assert_eq!(handle.finish().await.unwrap().completed_rounds, cfg.num_server_rounds);
    std::fs::read(run_dir.model_dir(cfg.num_server_rounds).join(TRAINABLE_FILE)).unwrap()
}

/// The aggregate does not depend on the order updates arrive in (it folds them in the order of the clients'
/// names), with exact and with compressed updates: the same seed gives byte-identical global models.
#[tokio::test]
async fn arrival_order_does_not_change_the_aggregate() {
    for overrides in ["", "update-encoding=int8", "strategy=fedadam server-lr=0.05"] {
        let forward = model_with_arrivals([0, 1, 2], overrides).await;
        let backward = model_with_arrivals([2, 1, 0], overrides).await;
        assert_eq!(forward, backward, "{overrides}: clients arriving in another order changed the model");
    }
}

async fn final_model(seed: u64) -> Vec<u8> {
    let base = tempfile::tempdir().unwrap();
    // Two of three clients sampled per round: the seed drives sampling, initial model and local shuffling.
    let cfg = config(&format!("seed={seed} fraction-fit=0.5 min-fit=2"));
    let run_dir = RunDir::create(base.path(), &cfg).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    let clients: Vec<_> = (0..3).map(|shard| spawn_client(&handle, shard, None)).collect();
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 2);
    for (task, _) in clients {
        task.await.unwrap().unwrap();
    }
    std::fs::read(run_dir.model_dir(2).join(TRAINABLE_FILE)).unwrap()
}

#[tokio::test]
async fn same_seed_same_model_other_seed_differs() {
    let a = final_model(7).await;
    let b = final_model(7).await;
    let c = final_model(8).await;
    assert_eq!(a, b, "same seed must give a byte-identical global model");
    assert_ne!(a, c, "another seed must give another model");
}

/// Every strategy of the configuration runs a federation over loopback to its last round: the clients get the
/// strategy's parameters in each task, the global models stay finite, and the server's held-out loss falls.
#[tokio::test]
async fn every_strategy_runs_a_federation_and_the_held_out_loss_falls() {
    let five = "num-clients=5 min-clients=5 min-fit=5";
    for (strategy, extra) in [
        ("fedavg", ""),
        ("fedavg", "clip-update-norm=0.5"),
        ("fedavg", "clip-update-norm=0.5 clip-update-quantile=0.5"),
        ("fedprox", ""),
        ("fedavgm", ""),
        ("fedadagrad", ""),
        ("fedyogi", ""),
        ("fedadam", ""),
        ("median", ""),
        ("trimmed-mean", ""),
        ("krum", five),
        ("multi-krum", five),
        ("bulyan", "num-clients=7 min-clients=7 min-fit=7"),
        ("qfedavg", ""),
        ("scaffold", ""),
        ("fedavg", "dp-noise-multiplier=0.1 dp-clip-norm=0.5"),
        ("fedadam", "dp-noise-multiplier=0.1 dp-clip-norm=0.5 dp-clip-quantile=0.5 dp-clip-count-stddev=1"),
    ] {
        let base = tempfile::tempdir().unwrap();
        // The adaptive optimizers take per-coordinate steps of about server-lr: small ones for a least-squares fit.
        let lr = if strategy.starts_with("fedad") || strategy == "fedyogi" { 0.05 } else { 1.0 };
        let cfg = config(&format!(
            "num-server-rounds=3 strategy={strategy} server-lr={lr} server-momentum=0.5 proximal-mu=0.1 {extra}"
        ));
        let clients = cfg.num_clients;
        let run_dir = RunDir::create(base.path(), &cfg).unwrap();
        let handle = start(cfg.clone(), run_dir.clone()).await;
        let clients: Vec<_> = (0..clients)
            .map(|shard| {
                let trainer = TestTrainer::new(shard, None).0;
                let tasks = trainer.tasks();
                (spawn_trainer(&handle, shard, trainer), tasks)
            })
            .collect();
        let status = handle.finish().await.unwrap();
        assert_eq!(status.completed_rounds, 3, "{strategy}");
        for (task, tasks) in clients {
            task.await.unwrap().unwrap();
            let tasks = tasks.lock().unwrap();
            assert!(tasks.iter().all(|t| t.strategy.name == strategy), "{strategy}: {:?}", tasks[0].strategy);
            let mu = if strategy == "fedprox" { 0.1 } else { 0.0 };
            assert!(tasks.iter().all(|t| t.strategy.proximal_mu == mu), "{strategy}");
            assert!(tasks.iter().all(|t| t.strategy.control_variates == (strategy == "scaffold")), "{strategy}");
        }
        let lines = fedvla_aggregator::records::read_metrics(run_dir.path()).unwrap();
        let loss = |i: usize| lines[i].global.as_ref().and_then(|g| g.eval.as_ref()).expect("evaluated").heldout_loss;
        assert!(loss(3).is_finite() && loss(3) < loss(0), "{strategy}: held-out loss {} -> {}", loss(0), loss(3));
        // DP-FedAvg reports the privacy each round has spent: nothing before round 1, more with every round.
        let epsilon = |i: usize| lines[i].privacy.map(|p| p.spent.epsilon);
        if extra.contains("dp-") {
            assert_eq!(epsilon(0), Some(0.0), "{strategy} {extra}");
            assert!(epsilon(1) > Some(0.0) && epsilon(3) > epsilon(1), "{strategy} {extra}: {:?}", epsilon(3));
        } else {
            assert_eq!(epsilon(3), None, "{strategy} {extra}");
        }
    }
}
