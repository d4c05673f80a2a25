//! Volunteers that bring their own LeRobot datasets (`fedvla join --dataset`), beside one on a server shard, in one
//! run of the real `fedvla serve`: datasets that do not fit are refused naming what differs; the run agrees its
//! normalisation statistics by federated statistics (equal to the pooled data's), learns, and keeps no frame,
//! state or action of the own datasets in its run directory or its logs.

use std::collections::HashMap;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use fedvla_aggregator::config::ComputeDevice;
use fedvla_aggregator::records::{DataSource, MetricsLine, read_metrics};
use fedvla_aggregator::run_dir::NORM_STATS_FILE;
use fedvla_data::{CameraSpec, ClientShard, DatasetSpec, DatasetWriter, Episode, FeatureStats, Frame, LeRobotDataset};
use fedvla_federation::{
    Capabilities, ClientMessage, ClientSummary, DataReport, ErrorCode, FeatureMoments, NormalizationStats, OwnDataset,
    PROTOCOL_VERSION, ServerMessage, StatsSource,
};
use fedvla_learner::examples::dataset_signature;
use fedvla_server::native_client::{Volunteer, VolunteerData, simulated_identity, volunteer};
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};
use futures_util::{SinkExt, StreamExt};
use tokio_tungstenite::tungstenite::Message;

const IMAGE_SIZE: u32 = 32;

/// Records `episodes` expert episodes of the sim from `seed`.
fn recorded(dir: &Path, name: &str, seed: u64, episodes: usize) -> PathBuf {
    let root = dir.join(name);
    let options = GenDataOptions { episodes, seed, image_size: IMAGE_SIZE, ..GenDataOptions::default() };
    generate_dataset(&root, &options, |_| {}).unwrap();
    root
}

/// An SO-100-like dataset that does not fit the run: `joints` state and action entries, these cameras.
fn unfit(dir: &Path, name: &str, joints: usize, cameras: &[String]) -> PathBuf {
    let root = dir.join(name);
    let cameras: Vec<CameraSpec> = cameras
        .iter()
        .map(|c| CameraSpec::new(c.trim_start_matches("observation.images."), IMAGE_SIZE, IMAGE_SIZE))
        .collect();
    let mut spec = DatasetSpec::so100(cameras.clone());
    spec.joint_names = (0..joints).map(|j| format!("joint_{j}.pos")).collect();
    let mut writer = DatasetWriter::create(&root, spec).unwrap();
    for e in 0..2 {
        let frames = (0..8)
            .map(|f| Frame {
                state: vec![f as f32; joints],
                action: vec![f as f32 + 0.5; joints],
                images: (0..cameras.len())
                    .map(|c| fedvla_data::synthetic::image(IMAGE_SIZE, IMAGE_SIZE, e, f, c))
                    .collect(),
            })
            .collect();
        writer.add_episode(&Episode { task: "put the cube in the bowl".into(), frames }).unwrap();
    }
    writer.finish().unwrap();
    root
}

/// Runs volunteer `name` on `data` on its own thread (trainer futures are not Send), as `fedvla join` does.
fn join(addr: &str, name: &str, data: Option<PathBuf>) -> std::thread::JoinHandle<Result<ClientSummary, String>> {
    let (addr, name) = (addr.to_owned(), name.to_owned());
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        runtime.block_on(async {
            let data = match &data {
                Some(path) => VolunteerData::Own(path),
                None => VolunteerData::Shard(Some(0)),
            };
            let identity = simulated_identity(&name);
            let v = Volunteer {
                server: &addr,
                ca_cert: None,
                name: &name,
                identity: &identity,
                data,
                auth_token: None,
                attack: None,
                device: ComputeDevice::Cpu,
            };
            volunteer(v, |_| {}).await.map_err(|e| e.to_string())
        })
    })
}

/// Joins with `dataset`'s signature and moments as a volunteer that skipped its own check would: the server's
/// refusal.
fn raw_join(port: u16, name: &str, dataset: &Path) -> (ErrorCode, String) {
    let d = LeRobotDataset::open(dataset).unwrap();
    let signature = dataset_signature(d.info());
    let moments = ["observation.state", "action"]
        .into_iter()
        .map(|f| {
            let rows = rows(&d, f);
            (f.to_owned(), FeatureMoments::of_rows(rows[0].len(), rows.iter().map(Vec::as_slice)))
        })
        .collect();
    let join = ClientMessage::Join {
        capabilities: Capabilities { backend: "test".into(), memory_bytes: 0 },
        data: Some(DataReport { own: Some(OwnDataset { signature, train_examples: d.len() as u64 }), moments }),
    };
    let identity = simulated_identity(name);
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://127.0.0.1:{port}/ws")).await.unwrap();
        loop {
            match ws.next().await {
                Some(Ok(Message::Text(text))) => match serde_json::from_str(text.as_str()).unwrap() {
                    ServerMessage::Challenge { nonce } => {
                        let identify = ClientMessage::Identify {
                            protocol_version: PROTOCOL_VERSION,
                            auth_token: None,
                            name: name.into(),
                            public_key: identity.public_key_hex(),
                            signature: identity.prove(&nonce, name),
                            shard: None,
                            own_dataset: true,
                        };
                        ws.send(Message::text(serde_json::to_string(&identify).unwrap())).await.unwrap();
                    }
                    ServerMessage::Admitted { .. } => {
                        ws.send(Message::text(serde_json::to_string(&join).unwrap())).await.unwrap();
                    }
                    ServerMessage::Error { code, message } => return (code, message),
                    other => panic!("expected a refusal, got {other:?}"),
                },
                Some(Ok(_)) => {}
                other => panic!("closed without a refusal: {other:?}"),
            }
        }
    })
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Every state and action row of `dataset`.
fn rows(dataset: &LeRobotDataset, feature: &str) -> Vec<Vec<f32>> {
    (0..dataset.len()).map(|i| dataset.vector(feature, i).unwrap().to_vec()).collect()
}

fn le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn f64_le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| f64::from(*v).to_le_bytes()).collect()
}

/// Every file under `dir`, with its bytes.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(files(&path));
        } else {
            let bytes = std::fs::read(&path).unwrap();
            out.push((path, bytes));
        }
    }
    out
}

#[test]
fn own_datasets_federate_beside_a_shard_and_never_leave_their_machines() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = std::fs::canonicalize(tmp.path()).unwrap();
    let server_data = recorded(&dir, "server-data", 0, 6);
    let own = [recorded(&dir, "own-a", 5_000, 5), recorded(&dir, "own-b", 7_000, 5)];
    let cameras = LeRobotDataset::open(&server_data).unwrap().camera_keys();
    let seven_joints = unfit(&dir, "seven-joints", 7, &cameras);
    let one_camera = unfit(&dir, "one-camera", 6, &cameras[..1]);

    let out = dir.join("outputs");
    let port = free_port();
    let overrides = format!(
        "workload=smolvla model-size=tiny dataset={} output-dir={} listen=127.0.0.1:{port} num-clients=1 \
         min-clients=3 min-fit=3 num-server-rounds=3 eval-every=1 local-steps=8 batch-size=4 lr=0.001 seed=3 \
         rollout-episodes=0 client-rollout-episodes=0 train-expert-only=true freeze-vision-encoder=true \
         federated-stats=true round-deadline-ms=300000",
        server_data.display(),
        out.display()
    );
    let log = std::fs::File::create(dir.join("serve.log")).unwrap();
    let mut server = Command::new(env!("CARGO_BIN_EXE_fedvla"))
        .args(["serve", "--run-config", &overrides])
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let addr = format!("ws://127.0.0.1:{port}");
    let started = std::time::Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(server.try_wait().unwrap().is_none(), "fedvla serve exited: see {}", dir.join("serve.log").display());
        assert!(started.elapsed() < Duration::from_secs(600), "the server never listened");
        std::thread::sleep(Duration::from_millis(200));
    }

    // Datasets that do not fit are refused, each naming what differs: by the volunteer before it decodes anything,
    // and by the server, whatever a volunteer claims; the server carries on.
    let seven = "action dimension: this dataset has 7, the run's has 6";
    let lacks = format!("this dataset lacks [{:?}]", cameras[1]);
    for (name, path, difference) in [("seven", &seven_joints, seven), ("one-eyed", &one_camera, lacks.as_str())] {
        let refusal = join(&addr, name, Some(path.clone())).join().unwrap().unwrap_err();
        assert!(refusal.contains(difference), "{refusal}");
        let (code, message) = raw_join(port, name, path);
        assert_eq!(code, ErrorCode::IncompatibleDataset, "{message}");
        assert!(message.contains(difference), "{message}");
    }

    let volunteers = [
        join(&addr, "own-a", Some(own[0].clone())),
        join(&addr, "own-b", Some(own[1].clone())),
        join(&addr, "shard-0", None),
    ];
    let server_log = || std::fs::read_to_string(dir.join("serve.log")).unwrap();
    for v in volunteers {
        match v.join().unwrap() {
            Ok(summary) => assert_eq!(summary.rounds_trained, 3),
            Err(e) => panic!("{e}\nthe server's output:\n{}", server_log()),
        }
    }
    assert!(server.wait().unwrap().success(), "see {}", dir.join("serve.log").display());
    let run = std::fs::read_dir(&out).unwrap().next().unwrap().unwrap().path();

    // Who brought what: the shard's examples are the server's count, the own datasets' a claim.
    let lines: Vec<MetricsLine> = read_metrics(&run).unwrap();
    let last = lines.last().unwrap();
    assert_eq!(last.round, 3);
    let mut sources: Vec<DataSource> = last.clients.iter().filter_map(|c| c.data).collect();
    sources.sort_by_key(|d| matches!(d, DataSource::Shard { .. }));
    assert!(matches!(
        sources[..],
        [DataSource::Own { .. }, DataSource::Own { .. }, DataSource::Shard { index: 0, .. }]
    ));
    for client in &last.clients {
        assert!(client.accepted && client.eval_loss.is_some_and(f64::is_finite), "{client:?}");
        assert_eq!(client.examples, client.data.map(DataSource::weight));
    }
    // It learns: the server's held-out loss falls from the initial model.
    let loss = |line: &MetricsLine| line.global.as_ref().and_then(|g| g.eval.as_ref()).unwrap().heldout_loss;
    assert!(loss(last) < loss(&lines[0]), "held-out loss {} -> {}", loss(&lines[0]), loss(last));

    // Federated statistics equal the statistics of the pooled data: the own datasets and the shard's episodes.
    let agreed: NormalizationStats =
        serde_json::from_slice(&std::fs::read(run.join(NORM_STATS_FILE)).unwrap()).unwrap();
    assert_eq!((agreed.source, agreed.clients), (StatsSource::Federated, 3));
    let shard = ClientShard::read(&run.join("shards/client_0.safetensors")).unwrap();
    let own_sets: Vec<LeRobotDataset> = own.iter().map(|p| LeRobotDataset::open(p).unwrap()).collect();
    for (feature, shard_values) in [("observation.state", &shard.state), ("action", &shard.action)] {
        let mut pooled: Vec<Vec<f64>> =
            shard_values.chunks(6).map(|r| r.iter().map(|&v| f64::from(v)).collect()).collect();
        for d in &own_sets {
            pooled.extend(rows(d, feature).iter().map(|r| r.iter().map(|&v| f64::from(v)).collect::<Vec<_>>()));
        }
        let expected = FeatureStats::from_rows(&pooled, 6);
        let got = &agreed.features[feature];
        assert_eq!(got.count, expected.count, "{feature}");
        for (name, a, b) in [
            ("mean", &got.mean, &expected.mean),
            ("std", &got.std, &expected.std),
            ("min", &got.min, &expected.min),
            ("max", &got.max, &expected.max),
        ] {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() <= 1e-9 * y.abs().max(1.0), "{feature} {name}: {x} against pooled {y}");
            }
        }
    }

    // Nothing of the own datasets reached the server: no state or action row (as f32 or f64 bytes, or as the
    // text of its first values), no frame, no byte run of their parquet or video files, in any file of the run
    // directory or the server's output.
    // Rows the server's own dataset also has (every episode starts from the arm's rest pose) prove nothing.
    let server_set = LeRobotDataset::open(&server_data).unwrap();
    let server_rows: std::collections::HashSet<Vec<u8>> =
        ["observation.state", "action"].iter().flat_map(|f| rows(&server_set, f)).map(|row| le_bytes(&row)).collect();
    let mut scan = Scan::default();
    for (d, root) in own_sets.iter().zip(&own) {
        let name = root.file_name().unwrap().to_string_lossy().into_owned();
        for feature in ["observation.state", "action"] {
            for (i, row) in rows(d, feature).iter().enumerate() {
                if server_rows.contains(&le_bytes(row)) {
                    continue;
                }
                scan.add(format!("{name} {feature} row {i} (f32)"), le_bytes(row));
                scan.add(format!("{name} {feature} row {i} (f64)"), f64_le_bytes(row));
                let text = format!("{},{}", f64::from(row[0]), f64::from(row[1]));
                scan.add(format!("{name} {feature} row {i} (text {text})"), text.into_bytes());
            }
        }
        for episode in d.episodes() {
            for camera in d.camera_keys() {
                let frames = d.camera_frames(&camera, episode, &[episode.dataset_from_index + 3]).unwrap();
                let what = format!("{name} episode {} {camera} frame 3", episode.episode_index);
                scan.add(what, frames[0].data.clone());
            }
        }
        let stored =
            files(root).into_iter().filter(|(p, _)| p.extension().is_some_and(|e| e == "parquet" || e == "mp4"));
        for (path, bytes) in stored {
            let middle = bytes.len() / 2;
            let run = bytes[middle..(middle + 256).min(bytes.len())].to_vec();
            scan.add(format!("{} bytes {middle}..", path.display()), run);
        }
    }
    assert!(scan.needles.len() > 1000, "{} needles", scan.needles.len());
    let mut haystacks = files(&run);
    haystacks.push((dir.join("serve.log"), std::fs::read(dir.join("serve.log")).unwrap()));
    // The scan finds what it looks for, planted anywhere.
    for (_, bytes, _) in scan.needles.iter().step_by(97) {
        let mut planted = haystacks[0].1.clone();
        planted.splice(planted.len() / 3..planted.len() / 3, bytes.iter().copied());
        assert!(scan.find_in(&planted).is_some());
    }
    for (path, haystack) in &haystacks {
        if let Some(what) = scan.find_in(haystack) {
            panic!("{} holds {what}", path.display());
        }
    }
}

/// Bytes that must appear nowhere, each found through the 16 bytes of it that vary most (so that a frame's
/// uniform background does not match every background of the server's own frames).
#[derive(Default)]
struct Scan {
    needles: Vec<(String, Vec<u8>, usize)>,
    by_key: HashMap<[u8; KEY], Vec<usize>>,
}

const KEY: usize = 16;

impl Scan {
    /// Adds `bytes` (at least 16 of them: shorter runs could be anything's).
    fn add(&mut self, what: String, bytes: Vec<u8>) {
        if bytes.len() < KEY {
            return;
        }
        let distinct = |w: &[u8]| w.iter().collect::<std::collections::BTreeSet<_>>().len();
        let at = (0..=bytes.len() - KEY).max_by_key(|&i| (distinct(&bytes[i..i + KEY]), usize::MAX - i)).unwrap();
        let key: [u8; KEY] = bytes[at..at + KEY].try_into().unwrap();
        self.by_key.entry(key).or_default().push(self.needles.len());
        self.needles.push((what, bytes, at));
    }

    /// What of the needles `haystack` holds, if any.
    fn find_in(&self, haystack: &[u8]) -> Option<&str> {
        for (p, window) in haystack.windows(KEY).enumerate() {
            let Some(candidates) = self.by_key.get(window) else { continue };
            for &n in candidates {
                let (what, bytes, at) = &self.needles[n];
                let Some(start) = p.checked_sub(*at) else { continue };
                if haystack.get(start..start + bytes.len()) == Some(bytes.as_slice()) {
                    return Some(what);
                }
            }
        }
        None
    }
}
