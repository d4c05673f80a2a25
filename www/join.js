// The join page: consent, the Join button, the volunteer's key (a random seed kept in IndexedDB, one per name),
// an optional own dataset folder (www/dataset.js), live status drawn from the wasm volunteer's reports, and
// automatic reconnection (with the cached downloads, a reconnect costs only the WebSocket handshake).
import init, { run_volunteer } from "./pkg/fedvla_client_wasm.js";
import { folderFromInput, pickFolder } from "./dataset.js";

const $ = (id) => document.getElementById(id);
const RECONNECT_MIN_MS = 1000;
const RECONNECT_MAX_MS = 15000;

// A stable random name per browser, so a reload rejoins as the same volunteer.
function volunteerName() {
  const params = new URLSearchParams(location.search);
  if (params.get("name")) return params.get("name");
  let name = localStorage.getItem("fedvla-name");
  if (!name) {
    name = "browser-" + Math.random().toString(36).slice(2, 8);
    localStorage.setItem("fedvla-name", name);
  }
  return name;
}

// The WebGPU adapter in words, and its storage buffer limit (0 without an adapter) for the volunteer to check
// against the model's largest tensor.
async function describeWebGpu() {
  if (!navigator.gpu) return ["WebGPU not available in this browser", 0];
  try {
    const adapter = await navigator.gpu.requestAdapter();
    if (!adapter) return ["WebGPU refused an adapter", 0];
    const info = adapter.info || {};
    const what = [info.vendor, info.architecture, info.description].filter(Boolean).join(" ") || "unnamed adapter";
    const limit = adapter.limits.maxStorageBufferBindingSize;
    return [`WebGPU adapter present (${what}${adapter.isFallbackAdapter ? ", software fallback" : ""}, storage buffers up to ${fmtBytes(limit)})`, limit];
  } catch (e) {
    return ["WebGPU refused: " + e, 0];
  }
}

// The 32-byte seed of this browser's key pair for `name`, made (from the browser's CSPRNG) and stored on first use.
// The server binds the name, the shard and the volunteer's state to the key: without it, the name is another's.
function volunteerSeed(name) {
  return new Promise((resolve, reject) => {
    const open = indexedDB.open("fedvla", 1);
    open.onupgradeneeded = () => open.result.createObjectStore("keys");
    open.onerror = () => reject(open.error);
    open.onsuccess = () => {
      const store = () => open.result.transaction("keys", "readwrite").objectStore("keys");
      const get = store().get(name);
      get.onerror = () => reject(get.error);
      get.onsuccess = () => {
        if (get.result) return resolve(get.result);
        const seed = crypto.getRandomValues(new Uint8Array(32));
        const put = store().add(seed, name);
        put.onerror = () => reject(put.error);
        put.onsuccess = () => resolve(seed);
      };
    };
  });
}

const fmtBytes = (n) => n >= 1 << 20 ? (n / (1 << 20)).toFixed(1) + " MiB" : n >= 1024 ? (n / 1024).toFixed(1) + " KiB" : n + " B";

const state = { contributions: 0, up: 0, down: 0, gpu: "", reconnectDelay: RECONNECT_MIN_MS, dataset: null };

// The volunteer's wasm memory: the most it has held at once (it never shrinks), against wasm32's 4 GiB.
function showMemory(bytes) {
  $("memory").textContent = `${fmtBytes(bytes)} of wasm32's 4096 MiB`;
  $("memory").dataset.bytes = bytes;
}

function show(kind, s) {
  switch (kind) {
    case "identity": $("public-key").textContent = s.public_key; break;
    case "stage": $("stage").textContent = s.stage; break;
    case "setup":
      $("stage").textContent = s.own_dataset ? "training on your own dataset" : `assigned shard ${s.shard} of ${s.shards}`;
      break;
    case "dataset_read":
      {
        $("dataset-status").hidden = false;
        const item = document.createElement("li");
        item.textContent = `${s.path}: ${fmtBytes(s.bytes)}`;
        $("dataset-reads").append(item);
      }
      break;
    case "dataset_plan":
      $("dataset-plan").textContent = `training on ${s.episodes} of ${s.of} episodes (${s.frames} frames, ` +
        `${fmtBytes(s.bytes)} of examples in memory, within the ${fmtBytes(s.budget_bytes)} budget)`;
      break;
    case "dataset_decoded": $("stage").textContent = `decoded ${s.frames} frames of ${s.path}`; break;
    case "dataset_packed": $("stage").textContent = `your dataset: ${s.train_examples} training examples built in memory`; break;
    case "download":
      $("stage").textContent = `downloading ${s.what}`;
      $("progress").max = s.total || 1;
      $("progress").value = s.total ? s.received : 0;
      break;
    case "downloaded":
      state.down += s.cached ? 0 : s.bytes;
      $("bytes").textContent = `${fmtBytes(state.up)} / ${fmtBytes(state.down)}`;
      $("stage").textContent = `${s.what}: ${fmtBytes(s.bytes)}${s.cached ? " (from the browser cache)" : ""}`;
      {
        const item = document.createElement("li");
        item.textContent = `${s.what}: ${fmtBytes(s.bytes)}, ${s.cached ? "from the browser cache" : "downloaded"}`;
        item.dataset.cached = s.cached;
        $("downloads").append(item);
      }
      break;
    case "device": $("device").textContent = `${s.backend}; ${state.gpu}`; break;
    case "fallback": state.gpu += ` (training on the CPU instead: ${s.reason})`; break;
    case "joined":
      state.reconnectDelay = RECONNECT_MIN_MS;
      $("connection").textContent = `joined as client ${s.client_id}`; $("stage").textContent = "waiting for a round"; break;
    case "task": $("round").textContent = s.round; $("stage").textContent = "round task received"; break;
    case "step":
      $("step").textContent = `${s.step} / ${s.steps} (${(s.step_seconds * 1000).toFixed(0)} ms/step)`;
      $("loss").textContent = s.loss.toFixed(4);
      $("progress").max = s.steps;
      $("progress").value = s.step;
      $("stage").textContent = "training";
      showMemory(s.wasm_memory_bytes);
      if (s.first_step_seconds !== undefined) $("first-step").textContent = `${s.first_step_seconds.toFixed(1)} s (downloads, model build and the step)`;
      break;
    case "trained": $("loss").textContent = `${s.train_loss.toFixed(4)} (round mean)`; $("stage").textContent = "uploading the update"; break;
    case "uploaded":
      state.contributions += 1;
      state.up = s.total_up;
      $("contributions").textContent = state.contributions;
      $("bytes").textContent = `${fmtBytes(s.total_up)} / ${fmtBytes(state.down + s.total_down)}`;
      $("stage").textContent = `update of round ${s.round} sent (${fmtBytes(s.bytes)})`;
      showMemory(s.wasm_memory_bytes);
      break;
    case "rollout":
      $("stage").textContent = `sim rollout ${s.episode + 1} of ${s.episodes}`;
      $("rollout-status").textContent = `episode ${s.episode + 1}: frame ${s.frame} of at most ${s.max_frames}`;
      break;
    case "rolled_out":
      $("rollout-status").textContent = `episode ${s.episode + 1}: ${s.success ? "success" : "no success"} after ${s.length} frames, video ${fmtBytes(s.video_bytes)} uploaded`;
      break;
    case "round_closed": $("stage").textContent = `round ${s.round} ${s.accepted ? "closed" : "will be retried"}; waiting for the next`; break;
    case "refused": $("message").textContent = `the server refused: ${s.code}: ${s.message}`; break;
    case "finished": $("stage").textContent = `run finished: ${s.rounds_trained} rounds trained`; break;
  }
}

async function volunteer() {
  $("status").hidden = false;
  const [gpu, maxBuffer] = await describeWebGpu();
  state.gpu = gpu;
  $("device").textContent = state.gpu;
  await init();
  const name = volunteerName();
  const seed = await volunteerSeed(name);
  for (;;) {
    $("connection").textContent = "connecting";
    $("message").textContent = "";
    $("message").className = "";
    try {
      // Each connection reads the folder afresh: the page keeps none of it between them.
      $("dataset-reads").replaceChildren();
      await run_volunteer(location.origin, name, seed, $("rollout"), maxBuffer, (json) => {
        const status = JSON.parse(json);
        show(status.kind, status);
      }, state.dataset);
      $("connection").textContent = "run finished; thank you";
      return;
    } catch (e) {
      // Expected when the server restarts: say so and try again, backing off.
      $("connection").textContent = "disconnected; reconnecting";
      $("message").textContent = String(e && e.message ? e.message : e);
      $("message").className = "error";
      console.warn("volunteer stopped:", e);
      await new Promise((resolve) => setTimeout(resolve, state.reconnectDelay));
      state.reconnectDelay = Math.min(state.reconnectDelay * 2, RECONNECT_MAX_MS);
    }
  }
}

function chooseDataset(folder) {
  state.dataset = folder;
  $("dataset-choice").textContent = folder
    ? `Chosen: ${folder.name} (${folder.paths.length} files listed, none read yet); you train on it instead of a shard.`
    : "No folder chosen: you train on a shard the server sends.";
}

function join() {
  $("join").disabled = true;
  $("consent").disabled = true;
  $("pick-dataset").disabled = true;
  $("dataset-input").disabled = true;
  localStorage.setItem("fedvla-consent", "given");
  volunteer();
}

$("volunteer-name").textContent = "as " + volunteerName();
$("consent").addEventListener("change", () => { $("join").disabled = !$("consent").checked; });
$("join").addEventListener("click", join);
$("dataset-input").addEventListener("change", () => chooseDataset(folderFromInput($("dataset-input").files)));
if (window.showDirectoryPicker) {
  $("pick-dataset").hidden = false;
  $("dataset-input-label").textContent = "or with the file dialog:";
  $("pick-dataset").addEventListener("click", async () => {
    try {
      chooseDataset(await pickFolder());
    } catch (e) {
      // Closing the picker is a choice, not an error.
      if (e.name !== "AbortError") $("dataset-choice").textContent = `could not open the folder: ${e}`;
    }
  });
}
// A volunteer who already agreed rejoins by itself after a reload.
if (localStorage.getItem("fedvla-consent") === "given") {
  $("consent").checked = true;
  join();
}
