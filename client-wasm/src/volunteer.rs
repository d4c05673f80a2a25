//! `run_volunteer`, the page's entry point: prove the volunteer's key over the WebSocket (the page keeps its seed
//! in IndexedDB), download what the admission offers with its session (cached by version), build the SmolVLA
//! trainer on the shard the server assigns or on the volunteer's own dataset folder ([`crate::own_dataset`]), join
//! and run the shared round loop until the run finishes or the connection drops (the page then reconnects).

use burn::tensor::Device;
use fedvla_federation::identity::SEED_BYTES;
use fedvla_federation::{
    Admission, BoxError, Capabilities, ClientEvent, ClientOptions, EvalOutput, Identity, Introduction, LocalTrainer,
    NamedTensors, OwnDataset, RolloutOutput, RolloutRequest, RoundTask, TrainOutput, identify, run_client,
};
use fedvla_learner::SmolVlaTrainer;
use fedvla_learner::rollout::Episode;
use fedvla_learner::trainer::rollout_episode;
use fedvla_learner::volunteer::{Fetch, policy_config, smolvla_volunteer, smolvla_volunteer_on};
use serde_json::json;
use wasm_bindgen::prelude::*;
use web_sys::HtmlCanvasElement;

use crate::browser::{js_error, now_seconds, sleep_ms, wasm_memory_bytes, yield_to_page};
use crate::download::{Source, cached, fetch_with_progress};
use crate::film::{CanvasView, Recorder};
use crate::own_dataset::{PickedFolder, pack_picked_folder};
use crate::status::StatusSink;
use crate::transport::BrowserTransport;

thread_local! {
    /// The page's WebGPU device, or why there is none: burn's wgpu runtime can be initialised only once.
    static WEBGPU: std::cell::RefCell<Option<Result<Device, String>>> = const { std::cell::RefCell::new(None) };
}

/// The page's WebGPU adapter as a burn device. The runtime asks the adapter for its own limits (storage buffer
/// sizes included), not WebGPU's defaults.
pub async fn webgpu_device() -> Result<Device, String> {
    if let Some(known) = WEBGPU.with_borrow(Clone::clone) {
        return known;
    }
    let result = Device::wgpu_options().init_async().await.map_err(|e| e.to_string());
    WEBGPU.with_borrow_mut(|slot| *slot = Some(result.clone()));
    result
}

/// The training device (WebGPU when the browser gives an adapter whose storage buffers hold the model's largest
/// tensor, `largest_tensor_bytes`, against the adapter's `max_buffer_bytes` limit; else burn's CPU backend in
/// wasm), with the name the server's client table and the page show.
async fn training_device(status: &StatusSink, max_buffer_bytes: f64, largest_tensor_bytes: usize) -> (Device, String) {
    let gpu = if max_buffer_bytes > 0.0 && (largest_tensor_bytes as f64) > max_buffer_bytes {
        Err(format!(
            "the model's largest tensor ({:.0} MB) exceeds this adapter's storage buffer limit ({:.0} MB)",
            largest_tensor_bytes as f64 / 1e6,
            max_buffer_bytes / 1e6
        ))
    } else {
        webgpu_device().await
    };
    match gpu {
        Ok(device) => (device.autodiff(), "webgpu".to_owned()),
        Err(reason) => {
            status.send("fallback", json!({ "reason": reason }));
            (Device::flex().autodiff(), "wasm-cpu (burn flex)".to_owned())
        }
    }
}

/// Rollout frames per second (the sim's control rate) and each camera's size on the canvas and in the video.
const ROLLOUT_FPS: f64 = 30.0;
const ROLLOUT_VIEW_SIZE: usize = 128;

fn boxed(e: JsValue) -> BoxError {
    e.as_string()
        .or_else(|| js_sys::Error::from(e).message().as_string())
        .unwrap_or_else(|| "JavaScript error".into())
        .into()
}

/// Joins the federation served at `origin` as `name` with the key pair of the 32-byte `seed` (the page keeps it in
/// IndexedDB), drawing rollouts on `canvas` and reporting every change to `on_status` (one JSON string per
/// call). `max_buffer_bytes` is the WebGPU adapter's `maxStorageBufferBindingSize` (0 when the page found no
/// adapter). `dataset` is the volunteer's own LeRobot dataset folder as www/dataset.js gives it (`{name, paths,
/// sizes, read, decode}`), or null to train on the shard the server assigns. Resolves with the run's summary when
/// the server finishes the run; rejects with a message when anything fails (the page shows it and reconnects).
#[wasm_bindgen]
pub async fn run_volunteer(
    origin: String,
    name: String,
    seed: Vec<u8>,
    canvas: HtmlCanvasElement,
    max_buffer_bytes: f64,
    on_status: js_sys::Function,
    dataset: JsValue,
) -> Result<JsValue, JsValue> {
    let status = StatusSink::new(on_status);
    let started = now_seconds();
    let seed: [u8; SEED_BYTES] =
        seed.try_into().map_err(|s: Vec<u8>| js_error(format!("a key seed of {} bytes, not {SEED_BYTES}", s.len())))?;
    let identity = Identity::from_seed(seed);
    status.send("identity", json!({ "public_key": identity.public_key_hex() }));
    let mut transport = BrowserTransport::connect(&origin).map_err(|e| js_error(format!("{e}")))?;
    status.send("stage", json!({ "stage": "identifying" }));
    let folder = if dataset.is_null() || dataset.is_undefined() {
        None
    } else {
        Some(PickedFolder::from_js(&dataset).map_err(|e| js_error(format!("{e}")))?)
    };
    let intro = Introduction { name, auth_token: None, shard: None, own_dataset: folder.is_some() };
    let admission = identify(&mut transport, &identity, &intro).await.map_err(|e| js_error(format!("{e}")))?;
    let (mut trainer, own) =
        prepare(&origin, &intro.name, &admission, folder.as_ref(), canvas, max_buffer_bytes, started, &status)
            .await
            .map_err(|e| js_error(format!("{e}")))?;
    let data = Some(trainer.inner.examples().data_report(own));
    let options = ClientOptions { session: admission.session, data };
    let sink = status.clone();
    let summary = run_client(&mut transport, &mut trainer, &options, move |event| report(&sink, event))
        .await
        .map_err(|e| js_error(format!("{e}")))?;
    let summary = json!({
        "client_id": summary.client_id,
        "rounds_trained": summary.rounds_trained,
        "bytes_up": summary.bytes_up,
        "bytes_down": summary.bytes_down,
    });
    status.send("finished", summary.clone());
    Ok(JsValue::from_str(&summary.to_string()))
}

/// Downloads the frozen weights, the shard (or, with the volunteer's own `folder`, the run's tokenizer to pack it
/// with) and the global model the admission's setup names, with its session, and builds the trainer (the shared
/// start-up, over the page's fetch). With a folder, also what the server is told of it.
#[allow(clippy::too_many_arguments)]
async fn prepare(
    origin: &str,
    name: &str,
    admission: &Admission,
    folder: Option<&PickedFolder>,
    canvas: HtmlCanvasElement,
    max_buffer_bytes: f64,
    started: f64,
    status: &StatusSink,
) -> Result<(BrowserTrainer, Option<OwnDataset>), BoxError> {
    let (setup, session) = (&admission.setup, admission.session.as_str());
    let fetch = PageFetch { origin, session, status };
    // The key keeps a returning volunteer on its shard (and so on its cached copy of it).
    status.send(
        "setup",
        json!({ "shard": setup.shard_index, "shards": setup.shard_count, "model_version": setup.model_version,
                "own_dataset": folder.is_some() }),
    );
    let largest_tensor = policy_config(setup)?.param_specs().iter().map(|p| p.numel() * 4).max().unwrap_or(0);
    let (device, backend) = training_device(status, max_buffer_bytes, largest_tensor).await;
    status.send("device", json!({ "backend": backend }));
    let (inner, own) = match folder {
        None => (smolvla_volunteer(&fetch, setup, name, &device, &backend).await?, None),
        Some(folder) => {
            let packed = pack_picked_folder(folder, &fetch, setup, name, status).await?;
            let inner = smolvla_volunteer_on(&fetch, setup, name, packed.shard, &device, &backend).await?;
            let train_examples = inner.examples().train_examples();
            status.send("dataset_packed", json!({ "train_examples": train_examples }));
            (inner, Some(OwnDataset { signature: packed.signature, train_examples }))
        }
    };
    let view = CanvasView::new(canvas, ROLLOUT_VIEW_SIZE).map_err(boxed)?;
    Ok((BrowserTrainer { inner, status: status.clone(), view, started, first_step_reported: false }, own))
}

/// Downloads from the page's server with the admission's session, with progress on the page, kept in the Cache
/// API under their content key.
struct PageFetch<'a> {
    origin: &'a str,
    session: &'a str,
    status: &'a StatusSink,
}

impl Fetch for PageFetch<'_> {
    async fn get(&self, path: &str, what: &str, cache_key: Option<&str>) -> Result<Vec<u8>, BoxError> {
        let url = format!("{}{path}", self.origin.trim_end_matches('/'));
        let Some(key) = cache_key else {
            return fetch_with_progress(&url, self.session, |_, _| {}).await.map_err(boxed);
        };
        let (bytes, source) = cached(&url, key, self.session, |received, total| {
            self.status.send("download", json!({ "what": what, "received": received, "total": total }));
        })
        .await
        .map_err(boxed)?;
        self.status
            .send("downloaded", json!({ "what": what, "bytes": bytes.len(), "cached": source == Source::Cache }));
        // Building the model takes a moment: let the page show the download first.
        yield_to_page().await;
        Ok(bytes)
    }
}

/// The shared SmolVLA trainer with the page's progress and an in-page, filmed sim.
struct BrowserTrainer {
    inner: SmolVlaTrainer,
    status: StatusSink,
    view: CanvasView,
    /// When `run_volunteer` started, for the time-to-first-step figure.
    started: f64,
    first_step_reported: bool,
}

impl LocalTrainer for BrowserTrainer {
    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_global(global)
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_correction(correction)
    }

    fn set_norm_stats(&mut self, stats: &fedvla_federation::NormalizationStats) -> Result<(), BoxError> {
        self.inner.set_norm_stats(stats)
    }

    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        let (status, round, started) = (&self.status, task.round, self.started);
        let first_step_reported = &mut self.first_step_reported;
        let mut last = now_seconds();
        self.inner
            .train_with(task, async |p| {
                let now = now_seconds();
                let mut fields = json!({ "round": round, "step": p.step, "steps": p.steps, "loss": p.loss, "step_seconds": now - last,
                                         "wasm_memory_bytes": wasm_memory_bytes() });
                if !*first_step_reported {
                    fields["first_step_seconds"] = json!(now - started);
                    *first_step_reported = true;
                }
                last = now;
                status.send("step", fields);
                yield_to_page().await;
            })
            .await
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        self.status.send("stage", json!({ "stage": "evaluating on the held-out episodes" }));
        yield_to_page().await;
        self.inner.evaluate().await
    }

    /// Each episode drawn on the canvas at the sim's 30 fps and recorded as WebM.
    async fn rollout(&mut self, request: &RolloutRequest) -> Result<Vec<RolloutOutput>, BoxError> {
        let Some(policy) = self.inner.sim_policy()? else { return Ok(Vec::new()) };
        let mut outputs = Vec::new();
        for episode in 0..request.episodes {
            let (task, seed) = (policy.tasks().task_of(episode as usize), request.first_seed + u64::from(episode));
            let mut run = Episode::new(&policy, task, seed, request.max_frames as usize)?;
            self.view.draw(run.scene()).map_err(boxed)?;
            let recorder = Recorder::start(&self.view, ROLLOUT_FPS).map_err(boxed)?;
            let start = now_seconds();
            let mut frame = 0u32;
            while run.step()? {
                frame += 1;
                self.view.draw(run.scene()).map_err(boxed)?;
                if frame % 10 == 0 {
                    self.status.send("rollout", json!({ "episode": episode, "episodes": request.episodes, "frame": frame, "max_frames": request.max_frames }));
                }
                // Real time, so the recording plays at the sim's speed.
                let due = start + f64::from(frame) / ROLLOUT_FPS;
                sleep_ms(((due - now_seconds()) * 1000.0).max(0.0) as i32).await;
            }
            let video = recorder.finish(format!("episode_{episode}.webm")).await.map_err(boxed)?;
            let record = rollout_episode(episode, &run.result());
            self.status.send("rolled_out", json!({ "episode": episode, "task": task.name(), "success": record.success, "length": record.length, "video_bytes": video.bytes.len() }));
            outputs.push(RolloutOutput { episode: record, video: Some(video) });
        }
        Ok(outputs)
    }
}

/// The round loop's events as page status.
fn report(status: &StatusSink, event: ClientEvent) {
    match event {
        ClientEvent::Joined { client_id } => status.send("joined", json!({ "client_id": client_id })),
        ClientEvent::Task { round, local_steps } => {
            status.send("task", json!({ "round": round, "local_steps": local_steps }))
        }
        ClientEvent::Trained { round, examples, train_loss } => {
            status.send("trained", json!({ "round": round, "examples": examples, "train_loss": train_loss }))
        }
        ClientEvent::Uploaded { round, bytes, total_up, total_down } => status.send(
            "uploaded",
            json!({ "round": round, "bytes": bytes, "total_up": total_up, "total_down": total_down,
                    "wasm_memory_bytes": wasm_memory_bytes() }),
        ),
        ClientEvent::RolledOut { round, episodes, successes } => {
            status.send("rollouts", json!({ "round": round, "episodes": episodes, "successes": successes }))
        }
        ClientEvent::RoundClosed { round, accepted } => {
            status.send("round_closed", json!({ "round": round, "accepted": accepted }))
        }
        ClientEvent::Refused { code, message } => {
            status.send("refused", json!({ "code": code.as_str(), "message": message }))
        }
    }
}
