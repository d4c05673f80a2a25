// Runs bench_training for each configuration in turn and adds a row per result; `#bench-status` says "done"
// at the end (the measuring script waits for it).
import init, { bench_training } from "./pkg/fedvla_client_wasm.js";

const params = new URLSearchParams(location.search);
const runs = [
  ["tiny", 8, 6, false],
  ["small", 8, 4, false],
];
if (params.get("webgpu") === "1") runs.push(["tiny", 1, 3, true], ["small", 1, 2, true]);

async function bench() {
  document.getElementById("run").disabled = true;
  await init();
  const status = document.getElementById("bench-status");
  for (const [model, batch, steps, webgpu] of runs) {
    status.textContent = `running ${model} on ${webgpu ? "WebGPU" : "the CPU"}...`;
    try {
      const r = JSON.parse(await bench_training(model, batch, steps, webgpu));
      const row = document.createElement("tr");
      for (const cell of [r.model, r.backend, r.batch, `${r.first_step_ms.toFixed(0)} ms`, `${r.median_step_ms.toFixed(0)} ms`, r.samples_per_s.toFixed(1)]) {
        const td = document.createElement("td");
        td.textContent = cell;
        row.append(td);
      }
      document.querySelector("#results tbody").append(row);
    } catch (e) {
      status.textContent = `${model} on ${webgpu ? "WebGPU" : "the CPU"} failed: ${e}`;
      console.warn(e);
    }
  }
  status.textContent = "done";
}

document.getElementById("run").addEventListener("click", bench);
if (params.get("autorun") === "1") bench();
