//! The browser volunteer in a real headless Chromium (Debian's, driven by chromedriver), against a real
//! `fedvla` server on loopback with the tiny SmolVLA on sim-recorded episodes, beside a native volunteer.
//! The browser trains on its CPU fallback (burn flex in wasm): headless Chromium without flags offers no WebGPU.
//!
//! Skipped with a message when Chromium, chromedriver or the built wasm (www/pkg) are missing, unless
//! FEDVLA_REQUIRE_BROWSER=1 (tests/run.sh), which makes that a failure.

mod webdriver;

use std::path::{Path, PathBuf};
use std::time::Duration;

use burn::tensor::Device;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::run_dir::{METRICS_FILE, RunDir};
use fedvla_app::server::{self, ServerHandle};
use fedvla_federation::{Admission, ClientOptions, Introduction, run_client};
use fedvla_learner::volunteer::smolvla_volunteer;
use fedvla_server::native_client::{admitted, simulated_identity};
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::server_parts;
use serde_json::Value;
use webdriver::{Browser, missing_prerequisite, www_dir};

const OPERATOR_TOKEN: &str = "operator-secret";

/// Where the tests leave their screenshots (PNG).
fn screenshot_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("browser-screenshots")
}

async fn start_server(tmp: &Path, overrides: &str) -> (ServerHandle, RunDir) {
    let data = tmp.join("so100");
    generate_dataset(&data, &GenDataOptions { episodes: 6, seed: 0, image_size: 32, ..Default::default() }, |_| {})
        .unwrap();
    let cfg = RunConfig::default()
        .with_overrides(&format!(
            "workload=smolvla model-size=tiny dataset={} output-dir={} num-clients=2 min-clients=2 min-fit=2 \
             local-steps=6 batch-size=4 lr=0.001 eval-every=1 rollout-episodes=0 client-rollout-episodes=1 rollout-max-frames=30 \
             max-frame-bytes=65536 operator-token={OPERATOR_TOKEN} www-dir={} {overrides}",
            data.display(),
            tmp.join("out").display(),
            www_dir().display(),
        ))
        .unwrap();
    let run_dir = RunDir::create(&tmp.join("out"), &cfg).unwrap();
    let workload = SmolVlaWorkload::prepare(&cfg, &run_dir.path().join("shards")).unwrap();
    let parts = server_parts(&workload, cfg, run_dir.clone()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    (server::start(parts, listener).unwrap(), run_dir)
}

/// A native volunteer on its own thread (trainers are not Send), downloading its setup as `fedvla join` does.
fn native_volunteer(addr: std::net::SocketAddr) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap().block_on(async move {
            let intro = Introduction { name: "native-0".into(), auth_token: None, shard: None, own_dataset: false };
            let (mut transport, Admission { session, setup, .. }) =
                admitted(&format!("ws://{addr}"), None, &simulated_identity("native-0"), &intro).await.unwrap();
            let mut trainer = smolvla_volunteer(&transport, &setup, "native-0", &Device::flex().autodiff(), "cpu-flex")
                .await
                .unwrap();
            let options = ClientOptions { session, data: None };
            run_client(&mut transport, &mut trainer, &options, |_| {}).await.unwrap();
        })
    })
}

/// A fresh Chromium (with `chromium_args`) on the join page as volunteer `name`, with its own `dataset` folder
/// given to the page's directory input (as a volunteer's file dialog would) when there is one, consent given and
/// Join pressed.
async fn volunteer_page(handle: &ServerHandle, name: &str, chromium_args: &[&str], dataset: Option<&Path>) -> Browser {
    let browser = Browser::launch(chromium_args).await;
    browser.goto(&format!("http://{}/?name={name}", handle.addr())).await;
    if let Some(folder) = dataset {
        browser.type_into("#dataset-input", &folder.display().to_string()).await;
    }
    browser.click("#consent").await;
    browser.click("#join").await;
    browser
}

fn metrics(run_dir: &RunDir) -> Vec<Value> {
    std::fs::read_to_string(run_dir.path().join(METRICS_FILE))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The metrics record of `name` in round `round`.
fn client_record(run_dir: &RunDir, round: u64, name: &str) -> Value {
    let lines = metrics(run_dir);
    let line =
        lines.iter().find(|l| l["round"] == round).unwrap_or_else(|| panic!("no metrics line for round {round}"));
    line["clients"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .cloned()
        .unwrap_or_else(|| panic!("round {round} has no record of {name}: {line}"))
}

async fn wait_rounds(handle: &ServerHandle, rounds: u64) {
    let mut status = handle.status();
    tokio::time::timeout(Duration::from_secs(300), status.wait_for(|s| s.completed_rounds >= rounds))
        .await
        .unwrap_or_else(|_| panic!("round {rounds} not completed within 300 s"))
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_browser_trains_a_round_beside_a_native_client_uploads_its_rollout_and_the_console_shows_it() {
    if let Some(why) = missing_prerequisite() {
        eprintln!("SKIPPED: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (handle, run_dir) = start_server(tmp.path(), "num-server-rounds=1 round-deadline-ms=240000").await;
    let base = format!("http://{}", handle.addr());
    let native = native_volunteer(handle.addr());

    let browser = volunteer_page(&handle, "browser-e2e", &[], None).await;
    let device = browser.wait_for("the device line", Duration::from_secs(120), "return document.getElementById('device').textContent.includes('wasm') && document.getElementById('device').textContent").await;
    eprintln!("browser device: {device}");
    browser
        .wait_for("training or a rollout in round 1", Duration::from_secs(240), "return document.getElementById('round').textContent === '1' && ['training', 'sim rollout'].some(s => document.getElementById('stage').textContent.startsWith(s))")
        .await;
    browser.screenshot(&screenshot_dir().join("join-page-mid-round.png")).await;
    wait_rounds(&handle, 1).await;
    native.join().unwrap();

    // The browser's update was aggregated, and its rollout video and results are filed under its client id.
    let record = client_record(&run_dir, 1, "browser-e2e");
    assert_eq!(record["accepted"], true, "{record}");
    assert!(record["train_loss"].as_f64().is_some_and(f64::is_finite), "{record}");
    assert_eq!(client_record(&run_dir, 1, "native-0")["accepted"], true);
    let rollout = &record["rollout"];
    assert_eq!(rollout["episodes"].as_array().map(Vec::len), Some(1), "{record}");
    assert_eq!(rollout["episodes"][0]["video"], "episode_0.webm", "{record}");
    let client_dir = run_dir.path().join(format!("evaluate/round_1/client_{}", record["client_id"]));
    let video = std::fs::read(client_dir.join("episode_0.webm")).expect("the browser's rollout video is stored");
    assert!(
        video.len() > 1000 && video.starts_with(&[0x1a, 0x45, 0xdf, 0xa3]),
        "a WebM (EBML) file, got {} bytes",
        video.len()
    );
    let results: Value = serde_json::from_slice(&std::fs::read(client_dir.join("results.json")).unwrap()).unwrap();
    assert_eq!(results["model_version"], 0);
    let timing = browser.eval("return document.getElementById('step').textContent + '; first step after ' + document.getElementById('first-step').textContent").await;
    eprintln!("browser training: {timing}");
    let errors = browser.page_errors().await;
    assert!(errors.is_empty(), "JavaScript errors on the join page: {errors:?}");

    // The operator logs in and finds the round in the charts and its video in the gallery.
    browser.goto(&format!("{base}/console")).await;
    browser.type_into("#token-input", OPERATOR_TOKEN).await;
    browser.click("#login-button").await;
    browser
        .wait_for(
            "round 1 in the held-out loss chart",
            Duration::from_secs(30),
            "return !!document.querySelector('#chart-heldout-loss [data-round=\"1\"]')",
        )
        .await;
    browser
        .wait_for(
            "round 1 in the train loss chart",
            Duration::from_secs(30),
            "return !!document.querySelector('#chart-train-loss [data-round=\"1\"]')",
        )
        .await;
    browser
        .wait_for(
            "the browser's video in the gallery",
            Duration::from_secs(30),
            "return !!document.querySelector('#gallery section[data-round=\"1\"] video[src*=\"episode_0.webm\"]')",
        )
        .await;
    browser.screenshot(&screenshot_dir().join("console-after-round.png")).await;
    let errors = browser.page_errors().await;
    assert!(errors.is_empty(), "JavaScript errors on the console: {errors:?}");
    browser.quit().await;
    handle.finish().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_browser_reloaded_mid_round_does_not_stall_the_round_and_rejoins() {
    if let Some(why) = missing_prerequisite() {
        eprintln!("SKIPPED: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    // min-fit 1: the round the browser walks out of closes with the native update alone.
    let (handle, run_dir) = start_server(
        tmp.path(),
        "num-server-rounds=2 min-fit=1 local-steps=40 client-rollout-episodes=0 round-deadline-ms=240000",
    )
    .await;
    let native = native_volunteer(handle.addr());
    let browser = volunteer_page(&handle, "browser-reload", &[], None).await;
    browser
        .wait_for("training in round 1", Duration::from_secs(240), "return document.getElementById('round').textContent === '1' && document.getElementById('stage').textContent === 'training'")
        .await;
    browser.refresh().await;
    wait_rounds(&handle, 1).await;
    let walked_out = client_record(&run_dir, 1, "browser-reload");
    assert_eq!(walked_out["accepted"], false, "the reloaded page's round-1 update never came: {walked_out}");
    assert_eq!(client_record(&run_dir, 1, "native-0")["accepted"], true);
    // Round 2 needs two connected clients: it runs only because the reloaded page rejoined by itself, and the
    // rejoined page took the frozen weights and its shard from the browser's cache.
    wait_rounds(&handle, 2).await;
    let downloads =
        browser.eval("return [...document.querySelectorAll('#downloads li')].map(li => li.textContent)").await;
    for what in ["frozen weights", "shard"] {
        assert!(
            downloads
                .as_array()
                .unwrap()
                .iter()
                .any(|d| d.as_str().unwrap().starts_with(what)
                    && d.as_str().unwrap().ends_with("from the browser cache")),
            "{what} not from the cache after the reload: {downloads}"
        );
    }
    native.join().unwrap();
    assert_eq!(client_record(&run_dir, 2, "browser-reload")["accepted"], true);
    let errors = browser.page_errors().await;
    assert!(errors.is_empty(), "JavaScript errors on the join page: {errors:?}");
    browser.quit().await;
    handle.finish().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_browser_with_a_webgpu_adapter_trains_its_round_on_it() {
    if let Some(why) = missing_prerequisite() {
        eprintln!("SKIPPED: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    // SwiftShader takes seconds per step: one step of the tiny model at batch 1, the browser alone.
    let overrides = "num-server-rounds=1 min-clients=1 min-fit=1 local-steps=1 batch-size=1 client-rollout-episodes=0 \
                     round-deadline-ms=290000";
    let (handle, run_dir) = start_server(tmp.path(), overrides).await;
    let browser = volunteer_page(&handle, "browser-webgpu", &["--enable-unsafe-webgpu"], None).await;
    let device = browser
        .wait_for("the device line", Duration::from_secs(120), "return document.getElementById('device').textContent.startsWith('webgpu') && document.getElementById('device').textContent")
        .await;
    eprintln!("browser device: {device}");
    wait_rounds(&handle, 1).await;
    let record = client_record(&run_dir, 1, "browser-webgpu");
    assert_eq!(record["accepted"], true, "{record}");
    assert!(record["train_loss"].as_f64().is_some_and(f64::is_finite), "{record}");
    let errors = browser.page_errors().await;
    assert!(errors.is_empty(), "JavaScript errors on the join page: {errors:?}");
    browser.quit().await;
    handle.finish().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_browser_trains_a_round_on_its_own_dataset_folder_read_and_decoded_in_the_page() {
    if let Some(why) = missing_prerequisite() {
        eprintln!("SKIPPED: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (handle, run_dir) = start_server(
        tmp.path(),
        "num-server-rounds=1 client-rollout-episodes=0 federated-stats=true round-deadline-ms=240000",
    )
    .await;
    // The volunteer's own recordings (H.264 mp4, as `fedvla gen-data` writes them), beside files of its own that the
    // policy does not need.
    let folder = tmp.path().join("my-recordings");
    generate_dataset(
        &folder,
        &GenDataOptions { episodes: 4, seed: 5_000, image_size: 32, ..Default::default() },
        |_| {},
    )
    .unwrap();
    std::fs::write(folder.join("notes.txt"), "not for the policy").unwrap();
    std::fs::write(folder.join("meta/private.json"), "{}").unwrap();
    let native = native_volunteer(handle.addr());

    let browser = volunteer_page(&handle, "browser-own", &[], Some(&folder)).await;
    let chosen = browser.eval("return document.getElementById('dataset-choice').textContent").await;
    assert!(chosen.as_str().unwrap().starts_with("Chosen: my-recordings"), "{chosen}");
    browser
        .wait_for("the own dataset's examples", Duration::from_secs(240), "return document.getElementById('stage').textContent.startsWith('your dataset:') || ['training', 'waiting'].some(s => document.getElementById('stage').textContent.startsWith(s))")
        .await;
    wait_rounds(&handle, 1).await;
    native.join().unwrap();
    browser
        .wait_for(
            "the page counting its contribution",
            Duration::from_secs(30),
            "return document.getElementById('contributions').textContent === '1'",
        )
        .await;
    browser.screenshot(&screenshot_dir().join("join-page-own-dataset-after-round.png")).await;

    // Its update was aggregated, weighed as an own dataset of its three training episodes (one of four held out).
    let record = client_record(&run_dir, 1, "browser-own");
    assert_eq!(record["accepted"], true, "{record}");
    assert!(record["train_loss"].as_f64().is_some_and(f64::is_finite), "{record}");
    assert_eq!(record["data"]["kind"], "own", "{record}");
    let own = fedvla_data::LeRobotDataset::open(&folder).unwrap();
    let train_frames: usize = own.episodes().iter().map(|e| e.length).sum::<usize>();
    let claimed = record["data"]["claimed_examples"].as_u64().unwrap() as usize;
    assert!(claimed > 0 && claimed < train_frames, "claimed {claimed} of {train_frames} frames: {record}");
    assert_eq!(client_record(&run_dir, 1, "native-0")["accepted"], true);

    // The page read exactly what the policy needs, and said so.
    let reads = browser
        .eval("return [...document.querySelectorAll('#dataset-reads li')].map(li => li.textContent.split(':')[0])")
        .await;
    let reads: Vec<&str> = reads.as_array().unwrap().iter().map(|r| r.as_str().unwrap()).collect();
    assert_eq!(
        reads,
        [
            "meta/info.json",
            "meta/tasks.parquet",
            "meta/episodes/chunk-000/file-000.parquet",
            "meta/stats.json",
            "data/chunk-000/file-000.parquet",
            "videos/observation.images.top/chunk-000/file-000.mp4",
            "videos/observation.images.wrist/chunk-000/file-000.mp4",
        ]
    );
    let plan = browser.eval("return document.getElementById('dataset-plan').textContent").await;
    assert!(plan.as_str().unwrap().starts_with("training on 4 of 4 episodes"), "{plan}");
    let errors = browser.page_errors().await;
    assert!(errors.is_empty(), "JavaScript errors on the join page: {errors:?}");
    browser.quit().await;
    handle.finish().await.unwrap();
}
