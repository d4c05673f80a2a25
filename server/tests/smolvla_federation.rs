//! The federation on the real workload: the tiny SmolVLA trained by 3 native clients over loopback
//! WebSockets on episodes the SO-100 sim recorded. Aggregation exactness, wire bytes (trainable
//! tensors only), metrics, LeRobot export and seed determinism.

mod common;

use std::path::Path;
use std::sync::{Arc, Mutex};

use burn::tensor::Device;
use fedvla_aggregator::config::{ComputeDevice, RunConfig};
use fedvla_aggregator::records::RolloutResults;
use fedvla_aggregator::run_dir::{RunDir, TRAINABLE_FILE};
use fedvla_app::server;
use fedvla_data::LeRobotDataset;
use fedvla_federation::RolloutOutput;
use fedvla_federation::codec::HEADER_LEN;
use fedvla_federation::protocol::RolloutRequest;
use fedvla_federation::{
    Admission, BoxError, Capabilities, ClientOptions, ClientSummary, EvalOutput, Introduction, LocalTrainer,
    NamedTensors, RoundTask, TrainOutput, routes, run_client,
};
use fedvla_learner::ShardExamples;
use fedvla_learner::volunteer::{fetch_shard, smolvla_volunteer};
use fedvla_policy::PolicyDir;
use fedvla_server::native_client::{admitted, simulated_identity};
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};
use fedvla_workloads::sim_eval::FilmedRollouts;
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::{Workload, server_parts};

use common::{heldout_loss, metrics_lines};

/// Records every update it sends; hangs from round `hang_from_round` on (a client stuck mid-round).
struct Recording {
    inner: FilmedRollouts,
    updates: Arc<Mutex<Vec<(u64, TrainOutput)>>>,
    hang_from_round: Option<u64>,
}

impl LocalTrainer for Recording {
    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }
    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_global(global)
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_correction(correction)
    }
    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        if self.hang_from_round.is_some_and(|r| task.round >= r) {
            std::future::pending::<()>().await;
        }
        let out = self.inner.train(task).await?;
        self.updates.lock().unwrap().push((task.round, out.clone()));
        Ok(out)
    }
    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        self.inner.evaluate().await
    }
    async fn rollout(&mut self, request: &RolloutRequest) -> Result<Vec<RolloutOutput>, BoxError> {
        self.inner.rollout(request).await
    }
}

fn dataset(dir: &Path) -> std::path::PathBuf {
    dataset_of(dir, 7)
}

fn dataset_of(dir: &Path, episodes: usize) -> std::path::PathBuf {
    let root = dir.join("so100");
    generate_dataset(&root, &GenDataOptions { episodes, seed: 0, image_size: 32, ..Default::default() }, |_| {})
        .unwrap();
    root
}

/// LeRobot's switches (the backbone frozen), so that the wire carries only the expert's part; FedAvg, whose
/// example-weighted mean the tests check.
fn config(dataset: &Path, out: &Path, seed: u64) -> RunConfig {
    RunConfig::default()
        .with_overrides(&format!(
            "workload=smolvla model-size=tiny dataset={} output-dir={} num-clients=3 min-clients=3 min-fit=3 \
             strategy=fedavg num-server-rounds=2 eval-every=1 local-steps=3 batch-size=4 lr=0.001 seed={seed} \
             max-frame-bytes=65536 round-deadline-ms=120000 rollout-episodes=1 train-expert-only=true \
             freeze-vision-encoder=true",
            dataset.display(),
            out.display()
        ))
        .unwrap()
}

struct Run {
    dir: std::path::PathBuf,
    updates: Vec<Vec<(u64, TrainOutput)>>,
    initial: NamedTensors,
    cfg: RunConfig,
}

async fn run(dataset: &Path, out: &Path, seed: u64) -> Run {
    run_with(config(dataset, out, seed)).await
}

async fn run_with(cfg: RunConfig) -> Run {
    let out = cfg.output_dir.clone();
    let out = Path::new(&out);
    let run_dir = RunDir::create(out, &cfg).unwrap();
    let workload = SmolVlaWorkload::prepare(&cfg, &run_dir.path().join("shards")).unwrap();
    let initial = workload.initial_model().unwrap();
    let parts = server_parts(&workload, cfg.clone(), run_dir.clone()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let handle = server::start(parts, listener).unwrap();
    let clients = spawn_clients(handle.addr(), cfg.num_clients, None);
    let status = handle.finish().await.unwrap();
    assert_eq!(status.completed_rounds, 2);
    assert!(status.rejections.is_empty(), "{:?}", status.rejections);
    let updates = clients
        .into_iter()
        .map(|(thread, updates)| {
            assert_eq!(thread.join().unwrap().rounds_trained, 2);
            Arc::try_unwrap(updates).unwrap().into_inner().unwrap()
        })
        .collect();
    Run { dir: run_dir.path().to_owned(), updates, initial, cfg }
}

type Updates = Arc<Mutex<Vec<(u64, TrainOutput)>>>;

/// `count` native volunteers on their own threads (trainer futures are not Send, the browser's are not either),
/// each downloading its setup, shard and weights over HTTP as `fedvla join` does, recording their updates.
fn spawn_clients(
    addr: std::net::SocketAddr,
    count: usize,
    hang_from_round: Option<u64>,
) -> Vec<(std::thread::JoinHandle<ClientSummary>, Updates)> {
    (0..u32::try_from(count).unwrap())
        .map(|shard| {
            let updates = Updates::default();
            let recorded = updates.clone();
            let thread = std::thread::spawn(move || {
                tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap().block_on(async move {
                    let name = format!("client-{shard}");
                    let intro =
                        Introduction { name: name.clone(), auth_token: None, shard: Some(shard), own_dataset: false };
                    let (mut transport, Admission { session, setup, .. }) =
                        admitted(&format!("ws://{addr}"), None, &simulated_identity(&name), &intro).await.unwrap();
                    let device = Device::flex().autodiff();
                    let inner = FilmedRollouts(
                        smolvla_volunteer(&transport, &setup, &name, &device, "cpu-flex").await.unwrap(),
                    );
                    let mut trainer = Recording { inner, updates: recorded, hang_from_round };
                    let options = ClientOptions { session, data: None };
                    run_client(&mut transport, &mut trainer, &options, |_| {}).await.unwrap()
                })
            });
            (thread, updates)
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn smolvla_three_clients_two_rounds_on_sim_data() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    assert_eq!(LeRobotDataset::open(&data).unwrap().episodes().len(), 7);
    let first = run(&data, &tmp.path().join("a"), 3).await;

    // Each round's global model is the example-weighted mean of that round's three updates.
    for round in 1..=2u64 {
        let updates: Vec<&TrainOutput> =
            first.updates.iter().flatten().filter(|(r, _)| *r == round).map(|(_, u)| u).collect();
        assert_eq!(updates.len(), 3);
        let total: f64 = updates.iter().map(|u| u.examples as f64).sum();
        let global = NamedTensors::from_safetensors(
            &std::fs::read(first.dir.join(format!("global_model/round_{round}")).join(TRAINABLE_FILE)).unwrap(),
        )
        .unwrap();
        for (name, t) in global.iter() {
            for (i, v) in t.values.iter().enumerate() {
                let mean: f64 = updates
                    .iter()
                    .map(|u| u.update.get(name).unwrap().values[i] as f64 * u.examples as f64)
                    .sum::<f64>()
                    / total;
                assert!((*v as f64 - mean).abs() <= 1e-6, "{name}[{i}]: {v} vs {mean}");
            }
        }
    }

    // Only the trainable tensors cross the wire: each upload is their payload plus frame headers,
    // far below the frozen part.
    let spec = first.initial.spec();
    // The encoding byte, the tensor count, then per tensor its name, rank, dimensions and f32 values.
    let payload: usize = 1
        + 4
        + spec.iter().map(|(n, s)| 4 + n.len() + 4 + 8 * s.len() + 4 * s.iter().product::<usize>()).sum::<usize>();
    let frames = payload.div_ceil(first.cfg.max_frame_bytes - HEADER_LEN);
    let lines = metrics_lines(&first.dir);
    assert_eq!(lines.iter().map(|l| l.round).collect::<Vec<_>>(), [0, 1, 2]);
    let cfg = fedvla_policy::SmolVlaConfig::tiny();
    let frozen: usize = cfg.param_specs().iter().filter(|s| !s.trainable).map(|s| s.numel() * 4).sum();
    for (round, line) in lines.iter().enumerate().skip(1) {
        assert!(heldout_loss(line).is_finite());
        for c in &line.clients {
            let update = c.update_bytes.expect("update bytes recorded");
            assert_eq!(update, (payload + frames * HEADER_LEN) as u64, "{c:?}");
            // bytes_up counts every round so far: one update each, a few small JSON messages, and the rollout
            // videos uploaded in the rounds so far.
            let up = c.bytes_up.expect("bytes up recorded");
            let client = c.client_id;
            let videos: u64 = (1..=round as u64)
                .filter_map(|r| std::fs::read_dir(first.dir.join(format!("evaluate/round_{r}/client_{client}"))).ok())
                .flatten()
                .map(|f| f.unwrap().path())
                .filter(|p| p.extension().is_some_and(|e| e == "mp4"))
                .map(|p| std::fs::metadata(p).unwrap().len())
                .sum();
            assert!(up >= round as u64 * update + videos && up < round as u64 * (update + 4096) + videos, "{c:?}");
            assert!(update < frozen as u64);
        }
    }
    assert!(heldout_loss(&lines[0]).is_finite(), "round 0 evaluates the initial model");

    // Every round's global model is also a LeRobot policy directory.
    let policy = PolicyDir::load(&first.dir.join("global_model/round_2/policy")).unwrap();
    assert!(policy.stats.is_some() && policy.vlm_dir.is_some());
    // ... and is rolled out in the sim, filmed.
    let rollouts = first.dir.join("global_model/round_2/rollouts");
    let results: RolloutResults =
        serde_json::from_str(&std::fs::read_to_string(rollouts.join("results.json")).unwrap()).unwrap();
    assert_eq!(results.episodes.len(), 1);
    assert!(std::fs::metadata(rollouts.join("episode_0.mp4")).unwrap().len() > 1000);
    // Native volunteers film their own rollouts too: every client's evaluation in round 1 holds its MP4, on
    // layouts of its own.
    let mut seeds = std::collections::BTreeSet::new();
    for client in std::fs::read_dir(first.dir.join("evaluate/round_1")).unwrap() {
        let dir = client.unwrap().path();
        let results: RolloutResults =
            serde_json::from_str(&std::fs::read_to_string(dir.join("results.json")).unwrap()).unwrap();
        for episode in &results.episodes {
            let video = episode.video.as_ref().unwrap_or_else(|| panic!("{}: episode without video", dir.display()));
            assert!(std::fs::metadata(dir.join(video)).unwrap().len() > 1000, "{}", dir.display());
            seeds.insert(episode.seed);
        }
    }
    assert_eq!(seeds.len(), 3, "three clients, three distinct layouts");

    // The same seed gives a byte-identical global model; another seed does not.
    let model = |run: &Run| std::fs::read(run.dir.join("global_model/round_2").join(TRAINABLE_FILE)).unwrap();
    let again = run(&data, &tmp.path().join("b"), 3).await;
    assert_eq!(model(&first), model(&again), "same seed, same global model");
    let other = run(&data, &tmp.path().join("c"), 4).await;
    assert_ne!(model(&first), model(&other), "another seed, another global model");
}

/// SCAFFOLD on the real workload: every client downloads its correction each round over HTTP (with its session)
/// and its trainer applies it; round 1's corrections are zero (its clients train as FedAvg's), from round 2 on
/// they move the clients' steps, and the server keeps its variate and one per shard with the round.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scaffold_corrects_the_clients_of_the_tiny_smolvla() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let with = |strategy: &str, out: &str| {
        config(&data, &tmp.path().join(out), 3).with_overrides(&format!("strategy={strategy}")).unwrap()
    };
    let scaffold = run_with(with("scaffold", "scaffold")).await;
    let fedavg = run_with(with("fedavg", "fedavg")).await;
    let round = |run: &Run, round: u64| -> Vec<NamedTensors> {
        run.updates.iter().flat_map(|u| u.iter().filter(|(r, _)| *r == round).map(|(_, o)| o.update.clone())).collect()
    };
    assert_eq!(round(&scaffold, 1), round(&fedavg, 1), "round 1's corrections are zero");
    assert_ne!(round(&scaffold, 2), round(&fedavg, 2), "round 2's corrections move the clients' steps");
    let loss = |run: &Run, i: usize| heldout_loss(&metrics_lines(&run.dir)[i]);
    // Six steps from random weights move the held-out loss little either way: the corrections steer the clients,
    // they do not derail them.
    let (ours, theirs) = (loss(&scaffold, 2), loss(&fedavg, 2));
    assert!(ours.is_finite() && (ours - theirs).abs() < 0.1 * theirs, "scaffold {ours}, fedavg {theirs}");
    // The strategy's state went to disk with the round: the server's variate and one per client (by shard).
    let (run_dir, _) = RunDir::open(&scaffold.dir).unwrap();
    let state = run_dir.load_strategy_state(2).unwrap();
    let trainable = scaffold.initial.len();
    assert_eq!(state.len(), 4 * trainable, "c and the 3 clients' c_i");
    for shard in 0..3 {
        assert!(state.iter().any(|(name, _)| name.starts_with(&format!("client/{shard}/"))), "shard {shard}");
    }
}

/// Every strategy, and both wrappers (update clipping, client-level DP with fixed and adaptive clipping), federates
/// the tiny SmolVLA over loopback: the real model's tensors go through each rule as the volunteers' wire brings
/// them, every update is accepted, and every round's global model moves, stays finite and evaluates to a finite
/// held-out loss. (What each rule computes is checked by hand in its unit tests, and on a least-squares
/// workload whose loss must fall in `federation.rs`.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_strategy_federates_the_tiny_smolvla() {
    let tmp = tempfile::tempdir().unwrap();
    // The server holds 2 of 16 out, leaving 2 (one trained, one held out) for each of Bulyan's 7 clients.
    let data = dataset_of(tmp.path(), 16);
    let five = "num-clients=5 min-clients=5 min-fit=5 krum-f=1";
    let seven = "num-clients=7 min-clients=7 min-fit=7 krum-f=1";
    for (index, (strategy, extra)) in [
        ("fedavg", "clip-update-norm=0.5"),
        ("fedprox", "proximal-mu=0.1"),
        ("fedavgm", "server-momentum=0.5"),
        ("fedadagrad", "server-lr=0.01"),
        ("fedyogi", "server-lr=0.01"),
        ("fedadam", "server-lr=0.01"),
        ("median", ""),
        ("trimmed-mean", ""),
        ("krum", five),
        ("multi-krum", five),
        ("bulyan", seven),
        ("qfedavg", ""),
        ("scaffold", ""),
        ("fedavg", "dp-noise-multiplier=0.5 dp-clip-norm=0.1"),
        (
            "fedadam",
            "server-lr=0.01 dp-noise-multiplier=0.5 dp-clip-norm=0.1 dp-clip-quantile=0.5 dp-clip-count-stddev=1",
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = config(&data, &tmp.path().join(format!("run_{index}")), 3)
            .with_overrides(&format!("strategy={strategy} {extra} rollout-episodes=0 client-rollout-episodes=0"))
            .unwrap();
        let run = run_with(cfg).await;
        let lines = metrics_lines(&run.dir);
        let mut previous = run.initial.clone();
        for round in 1..=2 {
            let global = NamedTensors::from_safetensors(
                &std::fs::read(run.dir.join(format!("global_model/round_{round}")).join(TRAINABLE_FILE)).unwrap(),
            )
            .unwrap();
            assert!(global.iter().all(|(_, t)| t.values.iter().all(|v| v.is_finite())), "{strategy} {extra}");
            assert_ne!(global, previous, "{strategy} {extra}: round {round} moved nothing");
            let loss = lines[round].global.as_ref().and_then(|g| g.eval.as_ref()).expect("evaluated").heldout_loss;
            assert!(loss.is_finite(), "{strategy} {extra}: round {round}'s held-out loss {loss}");
            assert_eq!(lines[round].privacy.is_some(), extra.contains("dp-"), "{strategy} {extra}");
            previous = global;
        }
        assert_eq!(run.updates.len(), run.cfg.num_clients, "{strategy} {extra}");
        assert!(run.updates.iter().all(|u| u.len() == 2), "{strategy} {extra}: every client trained both rounds");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_shards_download_over_http_with_size_and_checksum() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let cfg = config(&data, &tmp.path().join("out"), 0);
    let run_dir = RunDir::create(&tmp.path().join("out"), &cfg).unwrap();
    let workload = SmolVlaWorkload::prepare(&cfg, &run_dir.path().join("shards")).unwrap();
    let parts = server_parts(&workload, cfg, run_dir).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let handle = server::start(parts, listener).unwrap();
    let url = format!("ws://{}", handle.addr());
    // Shards are bound round-robin to volunteer keys, and a returning key keeps its shard.
    let mut assigned = Vec::new();
    let mut transports = Vec::new();
    for name in ["ann", "bob", "cy", "dee", "bob", "ann"] {
        let intro = Introduction { name: name.into(), auth_token: None, shard: None, own_dataset: false };
        let (transport, admission) = admitted(&url, None, &simulated_identity(name), &intro).await.unwrap();
        assigned.push(admission.setup.shard_index);
        transports.push(transport);
    }
    assert_eq!(assigned, [0, 1, 2, 0, 1, 0]);
    // Each downloads its own shard, checked against its manifest; another's is refused (403).
    for (index, transport) in transports.iter().take(3).enumerate() {
        let (manifest, bytes) =
            fetch_shard(transport, &routes::shard(index as u32), &routes::shard_manifest(index as u32)).await.unwrap();
        assert_eq!(bytes.len() as u64, manifest.file_bytes);
        assert_eq!(
            bytes,
            std::fs::read(&workload.volunteer_offer().unwrap().shards[index].file.as_ref().unwrap()).unwrap()
        );
        let shard = fedvla_data::ClientShard::from_bytes(Path::new(&manifest.file), &bytes).unwrap();
        assert_eq!(shard.manifest.client_index, index);
    }
    let another = fetch_shard(&transports[0], &routes::shard(1), &routes::shard_manifest(1)).await.unwrap_err();
    assert!(another.to_string().contains("403"), "{another}");
    handle.kill().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_killed_after_round_one_resumes_round_two_on_the_real_workload() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let out = tmp.path().join("out");
    let cfg = config(&data, &out, 5);
    let run_dir = RunDir::create(&out, &cfg).unwrap();
    let dir = run_dir.path().to_owned();
    let start = |cfg: RunConfig, run_dir: RunDir| async move {
        let workload = SmolVlaWorkload::prepare(&cfg, &run_dir.path().join("shards")).unwrap();
        let parts = server_parts(&workload, cfg, run_dir).unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        server::start(parts, listener).unwrap()
    };
    let rounds = || metrics_lines(&dir).iter().map(|l| l.round).collect::<Vec<_>>();

    // First life: the clients hang in round 2, so the kill lands while round 2 is in flight. Their threads stay
    // parked on the hang; the test does not wait for them.
    let handle = start(cfg, run_dir).await;
    let _stuck = spawn_clients(handle.addr(), 3, Some(2));
    let mut status = handle.status();
    status.wait_for(|s| s.completed_rounds == 1).await.unwrap();
    handle.kill().await;
    assert_eq!(rounds(), [0, 1]);
    let round_one = std::fs::read(dir.join("global_model/round_1").join(TRAINABLE_FILE)).unwrap();

    // Second life, as `fedvla serve --resume` does it: the run directory's config and models.
    let (run_dir, cfg) = RunDir::open(&dir).unwrap();
    let handle = start(cfg, run_dir.clone()).await;
    assert_eq!(handle.status().borrow().completed_rounds, 1);
    let clients = spawn_clients(handle.addr(), 3, None);
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 2);
    let mut updates = Vec::new();
    for (thread, recorded) in clients {
        assert_eq!(thread.join().unwrap().rounds_trained, 1, "resumed clients train round 2 only");
        updates.extend(recorded.lock().unwrap().drain(..).map(|(round, u)| {
            assert_eq!(round, 2);
            u
        }));
    }
    assert_eq!(rounds(), [0, 1, 2], "no round lost or counted twice");
    assert_eq!(std::fs::read(dir.join("global_model/round_1").join(TRAINABLE_FILE)).unwrap(), round_one);
    let global = run_dir.load_model(2).unwrap();
    let total: f64 = updates.iter().map(|u| u.examples as f64).sum();
    for (name, t) in global.iter() {
        for (i, v) in t.values.iter().enumerate() {
            let mean: f64 =
                updates.iter().map(|u| u.update.get(name).unwrap().values[i] as f64 * u.examples as f64).sum::<f64>()
                    / total;
            assert!((*v as f64 - mean).abs() <= 1e-6, "{name}[{i}]: {v} vs {mean}");
        }
    }
    assert!(PolicyDir::load(&dir.join("global_model/round_2/policy")).is_ok());
}

/// A label-shuffling attacker's batches (`attack=label-shuffle`): every training row keeps its frames and state
/// but is labelled with another training row's action chunk, a permutation of them all; held-out rows keep theirs.
#[test]
fn shuffled_labels_permute_the_training_actions_and_spare_the_held_out_rows() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let cfg = config(&data, &tmp.path().join("out"), 0);
    let workload = SmolVlaWorkload::prepare(&cfg, &tmp.path().join("shards")).unwrap();
    let policy = workload.policy_config();
    let shard = || {
        let shard = fedvla_data::ClientShard::read(&tmp.path().join("shards/client_0.safetensors")).unwrap();
        ShardExamples::new(shard, policy).unwrap()
    };
    let (honest, mut poisoned) = (shard(), shard());
    poisoned.shuffle_labels(7);
    let chunks = |examples: &ShardExamples, rows: &[usize]| -> Vec<Vec<u32>> {
        let batch = examples.batch(rows, policy.chunk_size).unwrap();
        let actions = batch.actions.unwrap();
        actions.data.chunks(actions.data.len() / rows.len()).map(|c| c.iter().map(|v| v.to_bits()).collect()).collect()
    };
    let rows = &honest.train_rows;
    let (mut before, mut after) = (chunks(&honest, rows), chunks(&poisoned, rows));
    assert_ne!(before, after, "the labels moved");
    let states = |e: &ShardExamples| e.batch(rows, policy.chunk_size).unwrap().state;
    assert_eq!(states(&honest).data, states(&poisoned).data, "the observations stayed");
    before.sort();
    after.sort();
    assert_eq!(before, after, "a permutation of the training rows' own action chunks");
    let held_out = &honest.held_out_rows;
    assert!(!held_out.is_empty());
    assert_eq!(chunks(&honest, held_out), chunks(&poisoned, held_out));
}

/// The held-out language check: on pick-colour data every held-out row is evaluated again told another cube's
/// colour, from the same frames, noise and times; told its own, the loss is about the evaluation's, and told
/// another it differs (the instruction's tokens reach the action expert). Data of a task the instruction does not decide
/// has no such check.
#[test]
fn the_held_out_evaluation_tells_pick_colour_rows_another_colour() {
    use fedvla_sim::TaskKind;
    let evaluate = |task: TaskKind| {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("so100");
        let options = GenDataOptions { episodes: 12, seed: 0, image_size: 32, tasks: vec![task], ..Default::default() };
        generate_dataset(&data, &options, |_| {}).unwrap();
        let workload =
            SmolVlaWorkload::prepare(&config(&data, &tmp.path().join("out"), 0), &tmp.path().join("shards")).unwrap();
        // Every colour is asked for somewhere, so that every held-out row's other colour has its token ids.
        let recorded = LeRobotDataset::open(&data).unwrap().tasks().to_vec();
        assert!(task.instructions().iter().all(|i| recorded.contains(i)), "{recorded:?}");
        workload.evaluator().unwrap().evaluate(&workload.initial_model().unwrap()).unwrap()
    };
    let metrics = evaluate(TaskKind::PickColour);
    let language = metrics.heldout_language.as_ref().unwrap_or_else(|| panic!("{metrics:?}"));
    assert_eq!(language.task, "pick-colour");
    assert_eq!(language.heldout_examples, metrics.heldout_examples, "{metrics:?}");
    // Told its own instruction, each row's loss is its share of the evaluation's (which LeRobot's loss also takes
    // over padded steps past an episode's end, where a row's own figure does not).
    assert!((language.loss_told_right - metrics.heldout_loss).abs() < 0.01 * metrics.heldout_loss, "{metrics:?}");
    assert!(language.loss_told_another.is_finite() && language.loss_told_another != language.loss_told_right);
    assert_eq!(evaluate(TaskKind::CubeInBowl).heldout_language, None);
}

/// `keep-optimizer-state`: a client that keeps its AdamW moments trains a round differently from one whose task
/// asks for a fresh optimizer, from the same global model after the same first round (one that kept them: a task
/// that does not keep its moments drops them as it ends); each is reproducible.
#[test]
fn a_client_keeps_its_optimizer_moments_across_rounds_only_when_its_task_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let data = dataset(tmp.path());
    let cfg = config(&data, &tmp.path().join("out"), 0);
    let workload = SmolVlaWorkload::prepare_centralized(&cfg, &tmp.path().join("shards")).unwrap();
    let global = workload.initial_model().unwrap();
    let task = |round: u64, keep_optimizer_state: bool| RoundTask {
        round,
        model_version: round - 1,
        local_steps: 3,
        batch_size: 4,
        lr: 1e-3,
        lr_schedule: None,
        seed: round,
        strategy: fedvla_federation::StrategyParams::plain("fedavg"),
        keep_optimizer_state,
        opening_frames: None,
        deadline_ms: 60_000,
        eval_request: false,
        rollout: None,
        update_encoding: fedvla_federation::UpdateEncoding::F32,
        model_deltas: None,
    };
    let rounds = |first_keeps: bool, second_keeps: bool| {
        let mut trainer = workload.centralized_trainer(ComputeDevice::Cpu).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        trainer.set_global(&global).unwrap();
        rt.block_on(trainer.train(&task(1, first_keeps))).unwrap();
        trainer.set_global(&global).unwrap();
        rt.block_on(trainer.train(&task(2, second_keeps))).unwrap().update
    };
    let (kept, reset) = (rounds(true, true), rounds(true, false));
    assert_ne!(kept, reset, "the first round's moments must shape the kept optimizer's steps");
    assert_eq!(rounds(true, true), kept);
    assert_eq!(rounds(true, false), reset);
    assert_eq!(rounds(false, true), reset, "a first round that did not keep its moments dropped them");
}

/// A federation on a dataset of all four sim tasks, each task whole on one client (`partitioning = "by-task"`):
/// every evaluated round's metrics line carries the held-out loss and action MSE per task and the sim success per
/// task, the rollouts (the server's and the clients') cycle through the tasks each told its own instruction, and
/// the pick-colour episodes are rolled out again told another colour (the language check, both rates recorded).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_multi_task_federation_reports_every_task_and_the_language_check() {
    use fedvla_sim::{Arrangement, TaskKind};
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("so100");
    let options =
        GenDataOptions { episodes: 20, seed: 0, image_size: 32, tasks: TaskKind::ALL.to_vec(), ..Default::default() };
    generate_dataset(&data, &options, |_| {}).unwrap();
    let cfg = config(&data, &tmp.path().join("run"), 3)
        .with_overrides("partitioning=by-task rollout-episodes=4 client-rollout-episodes=4 max-rollout-videos=4 rollout-max-frames=20")
        .unwrap();

    // The volunteers' token table holds every instruction of the four tasks, the pick-colour ones told apart.
    let workload = SmolVlaWorkload::prepare(&cfg, &tmp.path().join("shards")).unwrap();
    let offer = workload.volunteer_offer().unwrap();
    let names: Vec<&str> = TaskKind::ALL.iter().map(|t| t.name()).collect();
    assert_eq!(offer.rollout_tasks.tasks, names);
    let picks: std::collections::BTreeSet<&Vec<u32>> = offer
        .rollout_tasks
        .instructions
        .iter()
        .filter(|i| TaskKind::PickColour.instructions().contains(&i.instruction))
        .map(|i| &i.ids)
        .collect();
    assert!(picks.len() >= 2, "right and wrong colours tokenise apart: {picks:?}");

    let run = run_with(cfg).await;
    let lines = metrics_lines(&run.dir);
    for line in &lines {
        let global = line.global.as_ref().unwrap_or_else(|| panic!("round {} has no global figures", line.round));
        let eval = global.eval.as_ref().unwrap_or_else(|| panic!("no held-out evaluation: {global:?}"));
        let by_task = &eval.heldout_by_task;
        assert!(by_task.len() >= 2, "{global:?}");
        let rows: u64 = by_task.iter().map(|t| t.heldout_examples).sum();
        assert_eq!(rows, eval.heldout_examples);
        for task in by_task {
            assert!(names.contains(&task.task.as_str()), "{task:?}");
            assert!(task.heldout_loss.is_finite() && task.action_mse.is_some());
        }
        let sim = global.sim.as_ref().unwrap_or_else(|| panic!("no sim figures: {global:?}"));
        let success: Vec<&str> = sim.success_by_task.iter().map(|t| t.task.as_str()).collect();
        assert_eq!(success, names, "{global:?}");
        let check = sim.language_check.as_ref().unwrap_or_else(|| panic!("no language check: {global:?}"));
        assert_eq!((check.task.as_str(), check.episodes), ("pick-colour", 1), "{global:?}");
        for rate in [&check.right, &check.wrong] {
            assert!(rate.ci95_low <= rate.ci95_high);
        }
    }

    // The server's rollouts: episode k on the k-th task; the pick-colour one told another colour on its seed.
    let results: RolloutResults = serde_json::from_str(
        &std::fs::read_to_string(run.dir.join("global_model/round_2/rollouts/results.json")).unwrap(),
    )
    .unwrap();
    let tasks: Vec<Option<&str>> = results.episodes.iter().map(|e| e.task.as_deref()).collect();
    assert_eq!(tasks, names.iter().map(|n| Some(*n)).collect::<Vec<_>>());
    let [wrong] = results.told_wrong.as_slice() else { panic!("{:?}", results.told_wrong) };
    let right = Arrangement::from_seed(TaskKind::PickColour, wrong.seed).instruction();
    assert_ne!(wrong.instruction, right);
    assert!(TaskKind::PickColour.instructions().contains(&wrong.instruction));
    let check = results.language_check.as_ref().unwrap();
    assert_eq!(check.right_successes, u64::from(results.episodes[3].success));
    assert_eq!(check.wrong_successes, u64::from(wrong.success));

    // The clients' rollouts cycle through the tasks too.
    for client in std::fs::read_dir(run.dir.join("evaluate/round_1")).unwrap() {
        let dir = client.unwrap().path();
        let results: RolloutResults =
            serde_json::from_str(&std::fs::read_to_string(dir.join("results.json")).unwrap()).unwrap();
        let tasks: Vec<Option<&str>> = results.episodes.iter().map(|e| e.task.as_deref()).collect();
        assert_eq!(tasks, names.iter().map(|n| Some(*n)).collect::<Vec<_>>(), "{}", dir.display());
    }
}

/// `opening-frames`: a pass of local steps draws the first frames of each pick-colour episode `repeat` times, and
/// every other row (later pick-colour frames, cube-in-bowl's opening ones) once; without it, each row once.
#[test]
fn opening_frames_of_instruction_decides_episodes_are_drawn_more_often() {
    use fedvla_sim::TaskKind;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("so100");
    let tasks = vec![TaskKind::PickColour, TaskKind::CubeInBowl];
    generate_dataset(
        &data,
        &GenDataOptions { episodes: 8, seed: 0, image_size: 32, tasks, ..Default::default() },
        |_| {},
    )
    .unwrap();
    let cfg = config(&data, &tmp.path().join("out"), 0)
        .with_overrides("num-clients=1 min-clients=1 min-fit=1 opening-frames=6 opening-frames-repeat=3")
        .unwrap();
    let opening = cfg.opening_frames();
    assert_eq!(opening, Some(fedvla_federation::OpeningFrames { frames: 6, repeat: 3 }));
    assert!(cfg.with_overrides("opening-frames-repeat=0").is_err());
    assert_eq!(cfg.with_overrides("opening-frames-repeat=1").unwrap().opening_frames(), None);
    let workload = SmolVlaWorkload::prepare(&cfg, &tmp.path().join("shards")).unwrap();
    let shard = fedvla_data::ClientShard::read(&tmp.path().join("shards/client_0.safetensors")).unwrap();
    let examples = ShardExamples::new(shard.clone(), workload.policy_config()).unwrap();
    assert_eq!(examples.training_draws(None), examples.train_rows);
    let draws = examples.training_draws(opening);
    let mut counts = std::collections::BTreeMap::<usize, usize>::new();
    for row in draws {
        *counts.entry(row).or_default() += 1;
    }
    let mut seen = std::collections::BTreeSet::new();
    for &row in &examples.train_rows {
        let task = TaskKind::of_instruction(&shard.manifest.tasks[shard.task_index[row] as usize]).unwrap();
        let opens = shard.frame_index[row] < 6;
        let expected = if task == TaskKind::PickColour && opens { 3 } else { 1 };
        assert_eq!(counts[&row], expected, "row {row}: {task:?}, frame {}", shard.frame_index[row]);
        seen.insert((task.name(), opens));
    }
    assert_eq!(seen.len(), 4, "both tasks' opening and later frames trained on: {seen:?}");
}
