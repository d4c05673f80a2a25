//! A base-size round in the browser (issue 11, point 5): a real headless Chromium joins a real `fedvla` server on
//! loopback whose model is `smolvla_base`-shaped (the rehearsal's seeded random bf16 checkpoint, 450 M parameters)
//! and trains one local step at batch 1 on its CPU fallback (burn flex in wasm: headless Chromium without flags
//! offers no WebGPU, and the 189 MB token embedding exceeds WebGPU's default 128 MiB storage binding anyway), within
//! wasm32's 4 GiB. It prints what it measured: the step's time, the volunteer's wasm memory (the most it held at
//! once) and the renderer's peak RSS.
//!
//! Ignored in `cargo test` (about 6 minutes and 7 GB on 2 cores); run by hand, as the README says:
//!   cargo test --release -p fedvla-server --test browser_base -- --ignored --nocapture

mod webdriver;

use std::path::Path;
use std::time::{Duration, Instant};

use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::MetricsLine;
use fedvla_aggregator::run_dir::{METRICS_FILE, RunDir};
use fedvla_app::server;
use fedvla_server::rehearsal::{write_checkpoint, write_dataset};
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::server_parts;
use webdriver::{Browser, missing_prerequisite, www_dir};

/// wasm32's address space: everything the volunteer holds at once must fit.
const WASM32_BYTES: f64 = 4.0 * 1024.0 * 1024.0 * 1024.0;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
#[ignore = "a base-size round in Chromium: about 6 minutes and 7 GB on 2 cores; run by hand (README)"]
async fn a_browser_trains_a_step_of_the_base_model_on_its_cpu_fallback_within_wasm32() {
    if let Some(why) = missing_prerequisite() {
        eprintln!("SKIPPED: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (policy, data) = (tmp.path().join("policy"), tmp.path().join("data"));
    let tokenizer = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/fixtures/smolvla-tiny-a/vlm");
    write_checkpoint(&policy, 0, &tokenizer).unwrap();
    write_dataset(&data, 8, 4).unwrap();
    let out = tmp.path().join("out");
    let cfg = RunConfig::default()
        .with_overrides(&format!(
            "workload=smolvla model-size=base init-policy={} dataset={} output-dir={} num-clients=1 min-clients=1 \
             min-fit=1 num-server-rounds=1 local-steps=1 batch-size=1 rollout-episodes=0 client-rollout-episodes=0 \
             round-deadline-ms=3600000 www-dir={}",
            policy.display(),
            data.display(),
            out.display(),
            www_dir().display(),
        ))
        .unwrap();
    let run_dir = RunDir::create(&out, &cfg).unwrap();
    let workload = SmolVlaWorkload::prepare(&cfg, &run_dir.path().join("shards")).unwrap();
    let parts = server_parts(&workload, cfg, run_dir.clone()).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let handle = server::start(parts, listener).unwrap();

    let browser = Browser::launch(&[]).await;
    let joined = Instant::now();
    browser.goto(&format!("http://{}/?name=browser-base", handle.addr())).await;
    browser.click("#consent").await;
    browser.click("#join").await;
    let device = browser
        .wait_for("the device line", Duration::from_secs(600), "return document.getElementById('device').textContent.includes('wasm') && document.getElementById('device').textContent")
        .await;
    eprintln!("browser device: {device}");
    // Polled rather than awaited: a volunteer that fails (out of wasm memory, say) shows why on the page and tries
    // again, and the round would only close at its hour-long deadline.
    let status = handle.status();
    let mut last_stage = String::new();
    while status.borrow().completed_rounds < 1 {
        assert!(joined.elapsed() < Duration::from_secs(3600), "round 1 not completed within an hour");
        let message = browser.eval("return document.getElementById('message').className === 'error' && document.getElementById('message').textContent").await;
        if let Some(message) = message.as_str() {
            panic!("the volunteer stopped: {message}; page errors: {:?}", browser.page_errors().await);
        }
        let stage = browser.eval("return document.getElementById('stage').textContent").await;
        let stage = stage.as_str().unwrap_or_default().to_owned();
        if stage != last_stage {
            eprintln!("{:>5.0} s: {stage}", joined.elapsed().as_secs_f64());
            last_stage = stage;
        }
        tokio::time::sleep(Duration::from_secs(5)).await;
    }
    let round_seconds = joined.elapsed().as_secs_f64();

    let line = std::fs::read_to_string(run_dir.path().join(METRICS_FILE))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<MetricsLine>(l).unwrap())
        .find(|l| l.round == 1)
        .expect("a metrics line for round 1");
    let record = line.clients.iter().find(|c| c.name == "browser-base").expect("the browser's record in round 1");
    assert!(record.accepted, "the browser's base-size update was not accepted: {record:?}");
    assert!(record.train_loss.is_some_and(f64::is_finite), "{record:?}");
    let page = |id: &str| format!("return document.getElementById('{id}').textContent");
    let step = browser.eval(&page("step")).await;
    let first_step = browser.eval(&page("first-step")).await;
    let memory = browser.eval("return Number(document.getElementById('memory').dataset.bytes)").await;
    let memory = memory.as_f64().expect("the page shows the volunteer's wasm memory");
    let renderer_kb = browser.renderer_peak_rss_kb();
    eprintln!(
        "base-size browser round: local step {step}; first step after joining {first_step}; wasm memory {:.0} MiB \
         of 4096; renderer peak RSS {renderer_kb:?} kB; {:.0} s from joining to the round's close; update {} bytes",
        memory / (1024.0 * 1024.0),
        round_seconds,
        record.update_bytes.unwrap_or(0),
    );
    assert!(memory > 0.0 && memory <= WASM32_BYTES, "wasm memory {memory} bytes");
    browser.quit().await;
}
