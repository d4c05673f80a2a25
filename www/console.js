// The operator console: logs in with the operator token, renders the server's snapshot (run, settings, clients,
// metrics charts, round timeline, video gallery) and keeps it live from the server-sent event stream. Client
// table changes are applied from the events themselves; anything about rounds re-reads the snapshot.

const TOKEN_KEY = "fedvla-operator-token";
const SVG_NS = "http://www.w3.org/2000/svg";
/// Round events often come in bursts (a round closes, the next starts): one snapshot read covers them.
const REFRESH_DELAY_MS = 250;

const $ = (selector) => document.querySelector(selector);

const session = {
  token: null,
  events: null,
  snapshot: null,
  refreshTimer: null,
};

// ---- Talking to the server ----

async function api(path, { method = "GET", body } = {}) {
  const response = await fetch(path, {
    method,
    headers: {
      Authorization: `Bearer ${session.token}`,
      ...(body === undefined ? {} : { "Content-Type": "application/json" }),
    },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const data = await response.json().catch(() => ({ error: `${response.status} ${response.statusText}` }));
  return { ok: response.ok, status: response.status, data };
}

/// A console URL with the token in the query, for elements that cannot send headers (video, links).
function withToken(url) {
  return `${url}?token=${encodeURIComponent(session.token)}`;
}

async function login(token) {
  session.token = token;
  let reply;
  try {
    reply = await api("/console/api/snapshot");
  } catch (e) {
    showLoginError(`The server cannot be reached: ${e.message}`);
    return;
  }
  if (!reply.ok) {
    sessionStorage.removeItem(TOKEN_KEY);
    showLoginError(reply.data.error || `${reply.status}`);
    return;
  }
  sessionStorage.setItem(TOKEN_KEY, token);
  $("#login").hidden = true;
  $("#login-error").hidden = true;
  $("#console").hidden = false;
  $("#logout-button").hidden = false;
  render(reply.data);
  openEvents();
}

function logout() {
  sessionStorage.removeItem(TOKEN_KEY);
  if (session.events) session.events.close();
  session.events = null;
  session.token = null;
  $("#console").hidden = true;
  $("#logout-button").hidden = true;
  $("#login").hidden = false;
  $("#connection-status").textContent = "";
}

function showLoginError(message) {
  $("#login").hidden = false;
  $("#console").hidden = true;
  const error = $("#login-error");
  error.textContent = message;
  error.hidden = false;
}

function openEvents() {
  if (session.events) session.events.close();
  const events = new EventSource(withToken("/console/api/events"));
  session.events = events;
  events.onopen = () => {
    $("#connection-status").textContent = "live";
    // Whatever happened while the stream was down.
    scheduleRefresh();
  };
  events.onmessage = (message) => onEvent(JSON.parse(message.data));
  events.onerror = () => {
    if (events.readyState === EventSource.CLOSED) {
      // Refused outright (the server restarted with another token?): the snapshot says why.
      $("#connection-status").textContent = "disconnected";
      checkStillAuthorized();
    } else {
      $("#connection-status").textContent = "reconnecting…";
    }
  };
}

async function checkStillAuthorized() {
  try {
    const reply = await api("/console/api/snapshot");
    if (reply.status === 401) {
      logout();
      showLoginError(reply.data.error);
    }
  } catch {
    // The server is down; the status line says so.
  }
}

function onEvent(event) {
  switch (event.type) {
    case "client_joined":
    case "client_state":
    case "client_left":
      upsertClientRow(event.client);
      break;
    case "run_state":
      if (session.snapshot) {
        session.snapshot.run.state = event.state;
        renderRun(session.snapshot.run);
      }
      scheduleRefresh();
      break;
    default:
      // round_started, round_closed, settings_changed, video_stored, resync, and whatever comes later.
      scheduleRefresh();
  }
}

function scheduleRefresh() {
  if (session.refreshTimer !== null) return;
  session.refreshTimer = setTimeout(async () => {
    session.refreshTimer = null;
    try {
      const reply = await api("/console/api/snapshot");
      if (reply.ok) {
        render(reply.data);
      } else if (reply.status === 401) {
        logout();
        showLoginError(reply.data.error);
      }
    } catch {
      $("#connection-status").textContent = "server unreachable";
    }
  }, REFRESH_DELAY_MS);
}

// ---- Rendering ----

function render(snapshot) {
  session.snapshot = snapshot;
  renderRun(snapshot.run);
  renderSettings(snapshot.settings, snapshot.pending_settings);
  const rows = $("#clients tbody");
  rows.replaceChildren();
  snapshot.clients.forEach(upsertClientRow);
  renderCharts(snapshot);
  renderTasks(snapshot.metrics);
  renderTimeline(snapshot);
  renderGallery(snapshot.gallery);
}

function renderRun(run) {
  $("#run-state").textContent = run.state.replaceAll("_", " ");
  const current = run.current_round === null ? "" : `; round ${run.current_round} in progress`;
  $("#run-round").textContent = `${run.completed_rounds} of ${run.num_server_rounds} completed${current}`;
  $("#run-connected").textContent = `${run.connected} (rounds need ${run.min_clients})`;
  $("#run-retried").textContent = String(run.retried_rounds);
  const rejections = Object.entries(run.rejections).map(([code, n]) => `${code}: ${n}`);
  $("#run-rejections").textContent = rejections.length ? rejections.join(", ") : "none";
  const allowed = {
    start: run.state === "waiting_for_start",
    pause: run.state === "running" || run.state === "waiting_for_start",
    resume: run.state === "paused",
    stop: run.state !== "stopping" && run.state !== "finished",
  };
  for (const [action, enabled] of Object.entries(allowed)) {
    $(`#btn-${action}`).disabled = !enabled;
  }
}

function renderSettings(settings, pending) {
  const form = $("#settings-form");
  for (const [key, value] of Object.entries(settings)) {
    const input = form.elements.namedItem(key);
    // The operator may be typing into it.
    if (input && document.activeElement !== input && !input.dataset.edited) input.value = String(value);
  }
  const waiting = Object.entries(pending).map(([key, value]) => `${key} = ${value}`);
  $("#settings-pending").textContent = waiting.length ? `Waiting for the next round: ${waiting.join(", ")}` : "";
}

/// What a client trains on: the server's shard (its example count verified) or its own data (a claim).
function dataSource(data) {
  if (!data) return "";
  if (data.kind === "shard") return `shard ${data.index} (${data.examples} examples)`;
  const capped = data.weight < data.claimed_examples ? `, weighed as ${data.weight}` : "";
  return `own dataset (${data.claimed_examples} examples claimed${capped})`;
}

function upsertClientRow(client) {
  const body = $("#clients tbody");
  let row = body.querySelector(`tr[data-client-id="${client.id}"]`);
  if (!row) {
    row = document.createElement("tr");
    row.dataset.clientId = String(client.id);
    body.append(row);
  }
  const cells = [
    String(client.id),
    client.name,
    client.backend,
    dataSource(client.data),
    client.state,
    new Date(client.last_seen_ms).toLocaleTimeString(),
    String(client.updates_accepted),
    formatBytes(client.bytes_up),
    formatBytes(client.bytes_down),
  ].map((text) => {
    const cell = document.createElement("td");
    cell.textContent = text;
    return cell;
  });
  cells[4].className = `state-${client.state}`;
  row.replaceChildren(...cells);
}

/// Rounds with a metrics line, merged with the attempts this server ran (a round in flight has no line yet).
function renderTimeline(snapshot) {
  const rounds = new Map();
  for (const line of snapshot.metrics) {
    rounds.set(line.round, { round: line.round, line, attempts: [] });
  }
  for (const attempt of snapshot.timeline) {
    if (!rounds.has(attempt.round)) rounds.set(attempt.round, { round: attempt.round, line: null, attempts: [] });
    rounds.get(attempt.round).attempts.push(attempt);
  }
  const checkpoints = new Set(snapshot.checkpoints);
  const rows = [...rounds.values()].sort((a, b) => b.round - a.round).map(({ round, line, attempts }) => {
    const last = attempts[attempts.length - 1];
    const outcome = line ? (round === 0 ? "initial evaluation" : "closed") : last.outcome;
    const updates = line ? line.clients.filter((c) => c.accepted).length : last.updates;
    const row = document.createElement("tr");
    row.dataset.round = String(round);
    row.className = `outcome-${outcome.replaceAll(" ", "-")}`;
    const texts = [
      String(round),
      outcome,
      String(line ? (line.attempt ?? 0) + 1 : attempts.length),
      updates === null || updates === undefined ? "-" : String(updates),
      line && line.seconds !== undefined ? line.seconds.toFixed(1) : "-",
      formatNumber(line?.global?.heldout_loss),
      line?.settings ? Object.entries(line.settings).map(([k, v]) => `${k} = ${v}`).join(", ") : "",
    ];
    for (const text of texts) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.append(cell);
    }
    const checkpointCell = document.createElement("td");
    if (checkpoints.has(round)) {
      const link = document.createElement("a");
      link.className = "checkpoint";
      link.dataset.round = String(round);
      link.href = withToken(`/console/api/checkpoint/${round}`);
      link.download = `fedvla_round_${round}_policy.tar`;
      link.textContent = "LeRobot policy (.tar)";
      checkpointCell.append(link);
    }
    row.append(checkpointCell);
    return row;
  });
  $("#timeline tbody").replaceChildren(...rows);
}

// ---- Charts ----

const CHART = { width: 360, height: 180, left: 44, right: 10, top: 10, bottom: 24 };

function mean(values) {
  return values.reduce((sum, v) => sum + v, 0) / values.length;
}

function renderCharts(snapshot) {
  const lines = snapshot.metrics;
  const trainLoss = lines
    .map((line) => ({ round: line.round, losses: line.clients.map((c) => c.train_loss).filter(isNumber) }))
    .filter((p) => p.losses.length)
    .map((p) => ({ round: p.round, value: mean(p.losses) }));
  const global = (key) =>
    lines.filter((line) => isNumber(line.global?.[key])).map((line) => ({ round: line.round, value: line.global[key] }));
  drawChart($("#chart-train-loss"), [{ className: "global", points: trainLoss }]);
  drawChart($("#chart-heldout-loss"), [{ className: "global", points: global("heldout_loss") }]);
  drawChart($("#chart-action-mse"), [{ className: "global", points: global("action_mse") }]);
  drawChart($("#chart-success"), successSeries(snapshot.gallery), { min: 0, max: 1 });
}

/// Success rates by the model they measured: the server films round N's global model, a client the model its
/// round started from (`model_version` in its results).
function successSeries(gallery) {
  const server = [];
  const clients = [];
  for (const round of gallery) {
    const rate = round.global?.results?.success_rate;
    if (isNumber(rate)) server.push({ round: round.round, value: rate });
    for (const client of round.clients) {
      const results = client.results;
      if (isNumber(results?.success_rate)) {
        clients.push({ round: results.model_version ?? round.round, value: results.success_rate, label: `client ${client.client_id}` });
      }
    }
  }
  return [
    { className: "global", points: server, line: true },
    { className: "client", points: clients, line: false },
  ];
}

/// The last evaluated round's figures per task (`global.heldout_by_task`, `global.success_by_task`) and its
/// language checks, in the sim (`global.language_check`) and on the held-out rows (`global.heldout_language`);
/// hidden for a run of one task whose instruction does not decide the goal, whose lines carry none.
function renderTasks(lines) {
  const last = (key) => [...lines].reverse().find((line) => line.global?.[key])?.global?.[key];
  const heldOut = last("heldout_by_task") ?? [];
  const success = last("success_by_task") ?? [];
  const check = last("language_check");
  const heldOutLanguage = last("heldout_language");
  const names = [...new Set([...heldOut.map((t) => t.task), ...success.map((t) => t.task)])];
  $("#tasks").hidden = names.length === 0 && !check && !heldOutLanguage;
  $("#task-figures").hidden = names.length === 0;
  const rows = names.map((name) => {
    const h = heldOut.find((t) => t.task === name);
    const s = success.find((t) => t.task === name);
    const row = document.createElement("tr");
    const texts = [
      name,
      formatNumber(h?.heldout_loss),
      formatNumber(h?.action_mse),
      h ? String(h.heldout_examples) : "-",
      s ? `${s.successes}/${s.episodes}` : "-",
    ];
    for (const text of texts) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.append(cell);
    }
    return row;
  });
  $("#task-figures tbody").replaceChildren(...rows);
  const interval = (i) => `[${i.ci95_low.toFixed(2)}, ${i.ci95_high.toFixed(2)}]`;
  $("#language-check").textContent = check
    ? `Language check (${check.task}): told the right goal ${check.right_successes}/${check.episodes} ` +
      `${interval(check.right)}, told another goal ${check.wrong_successes}/${check.episodes} ` +
      `${interval(check.wrong)} (Wilson 95%).`
    : "";
  const l = heldOutLanguage;
  $("#heldout-language").textContent = l
    ? `Held-out language check (${l.task}, ${l.heldout_examples} rows): loss told the right goal ` +
      `${formatNumber(l.loss_told_right)}, told another goal ${formatNumber(l.loss_told_another)} ` +
      `(${formatPercentChange(l.loss_told_right, l.loss_told_another)}; a policy that ignores the instruction: 0%).`
    : "";
}

/// `after` against `before`, as a signed percentage.
function formatPercentChange(before, after) {
  if (!isNumber(before) || !isNumber(after) || before === 0) return "-";
  const change = (100 * (after - before)) / before;
  return `${change >= 0 ? "+" : ""}${change.toFixed(1)}%`;
}

function isNumber(value) {
  return typeof value === "number" && Number.isFinite(value);
}

function svg(tag, attributes = {}, text) {
  const element = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attributes)) element.setAttribute(name, String(value));
  if (text !== undefined) element.textContent = text;
  return element;
}

/// One line per series (points joined in round order) and one `g[data-round]` marker per round holding every
/// series' point of that round, with a tooltip.
function drawChart(chart, series, range = {}) {
  const points = series.flatMap((s) => s.points);
  chart.replaceChildren();
  const { width, height, left, right, top, bottom } = CHART;
  chart.append(svg("line", { class: "axis", x1: left, y1: height - bottom, x2: width - right, y2: height - bottom }));
  chart.append(svg("line", { class: "axis", x1: left, y1: top, x2: left, y2: height - bottom }));
  if (!points.length) {
    chart.append(svg("text", { class: "empty", x: width / 2, y: height / 2, "text-anchor": "middle" }, "no data yet"));
    return;
  }
  const rounds = points.map((p) => p.round);
  const values = points.map((p) => p.value);
  const [x0, x1] = [Math.min(...rounds), Math.max(...rounds)];
  let [y0, y1] = [range.min ?? Math.min(0, ...values), range.max ?? Math.max(...values)];
  if (y1 === y0) y1 = y0 + 1;
  const x = (round) => left + (x1 === x0 ? 0.5 : (round - x0) / (x1 - x0)) * (width - left - right);
  const y = (value) => height - bottom - ((value - y0) / (y1 - y0)) * (height - top - bottom);

  chart.append(svg("text", { class: "label", x: left - 4, y: top + 8, "text-anchor": "end" }, formatNumber(y1)));
  chart.append(svg("text", { class: "label", x: left - 4, y: height - bottom, "text-anchor": "end" }, formatNumber(y0)));
  chart.append(svg("text", { class: "label", x: x(x0), y: height - 8, "text-anchor": "middle" }, `round ${x0}`));
  if (x1 !== x0) chart.append(svg("text", { class: "label", x: x(x1), y: height - 8, "text-anchor": "middle" }, `${x1}`));

  for (const s of series) {
    if (s.line === false || s.points.length < 2) continue;
    const path = [...s.points].sort((a, b) => a.round - b.round).map((p) => `${x(p.round)},${y(p.value)}`);
    chart.append(svg("polyline", { class: "line", points: path.join(" ") }));
  }
  for (const round of [...new Set(rounds)].sort((a, b) => a - b)) {
    const marker = svg("g", { class: "point", "data-round": round });
    const tips = [];
    for (const s of series) {
      for (const p of s.points.filter((p) => p.round === round)) {
        marker.append(svg("circle", { class: s.className, cx: x(p.round), cy: y(p.value), r: s.className === "client" ? 2.5 : 3.5 }));
        tips.push(`${p.label ?? "round " + round}: ${formatNumber(p.value)}`);
      }
    }
    marker.append(svg("title", {}, tips.join("\n")));
    chart.append(marker);
  }
}

// ---- Videos ----

/// Adds what is new and leaves what is there, so videos being watched keep playing.
function renderGallery(gallery) {
  const container = $("#gallery");
  for (const round of [...gallery].sort((a, b) => b.round - a.round)) {
    const groups = [];
    if (round.global?.videos.length) groups.push({ key: "server", title: "Server: global model", set: round.global });
    for (const client of round.clients) {
      if (client.videos.length) {
        const model = client.results?.model_version;
        const title = `Client ${client.client_id}` + (model === undefined ? "" : `: model of round ${model}`);
        groups.push({ key: `client-${client.client_id}`, title, set: client });
      }
    }
    if (!groups.length) continue;
    let section = container.querySelector(`section[data-round="${round.round}"]`);
    if (!section) {
      section = document.createElement("section");
      section.dataset.round = String(round.round);
      section.append(Object.assign(document.createElement("h3"), { textContent: `Round ${round.round}` }));
      const later = [...container.children].find((s) => Number(s.dataset.round) < round.round);
      container.insertBefore(section, later ?? null);
    }
    for (const group of groups) {
      let block = section.querySelector(`div[data-group="${group.key}"]`);
      if (!block) {
        block = document.createElement("div");
        block.dataset.group = group.key;
        block.append(document.createElement("h4"), Object.assign(document.createElement("div"), { className: "videos" }));
        section.append(block);
      }
      const rate = group.set.results?.success_rate;
      block.querySelector("h4").textContent = group.title + (isNumber(rate) ? `, success ${Math.round(rate * 100)}%` : "");
      const videos = block.querySelector(".videos");
      for (const url of group.set.videos) {
        if ([...videos.children].some((video) => video.dataset.url === url)) continue;
        const video = document.createElement("video");
        video.controls = true;
        video.preload = "metadata";
        video.muted = true;
        video.dataset.url = url;
        video.src = withToken(url);
        videos.append(video);
      }
    }
  }
}

// ---- Formatting ----

function formatBytes(bytes) {
  if (bytes < 1024) return `${bytes} B`;
  const units = ["KiB", "MiB", "GiB"];
  let value = bytes / 1024;
  let unit = 0;
  while (value >= 1024 && unit < units.length - 1) {
    value /= 1024;
    unit += 1;
  }
  return `${value.toFixed(1)} ${units[unit]}`;
}

function formatNumber(value) {
  return isNumber(value) ? Number(value.toPrecision(4)).toString() : "-";
}

function setMessage(selector, text, className) {
  const element = $(selector);
  element.textContent = text;
  element.className = className;
}

// ---- Operator actions ----

async function sendControl(action) {
  try {
    const reply = await api("/console/api/control", { method: "POST", body: { action } });
    if (reply.ok) {
      setMessage("#control-message", `${action}: the run is now ${reply.data.state.replaceAll("_", " ")}`, "ok");
      scheduleRefresh();
    } else {
      setMessage("#control-message", reply.data.error, "error");
    }
  } catch (e) {
    setMessage("#control-message", `The server cannot be reached: ${e.message}`, "error");
  }
}

/// Sends only the settings the operator changed.
async function applySettings(event) {
  event.preventDefault();
  const form = $("#settings-form");
  const current = session.snapshot?.settings ?? {};
  const change = {};
  for (const input of form.querySelectorAll("input")) {
    const value = Number(input.value);
    if (input.value.trim() === "" || !Number.isFinite(value)) {
      setMessage("#settings-message", `${input.name}: not a number`, "error");
      return;
    }
    if (value !== current[input.name]) change[input.name] = value;
  }
  if (!Object.keys(change).length) {
    setMessage("#settings-message", "Nothing changed.", "muted");
    return;
  }
  try {
    const reply = await api("/console/api/settings", { method: "POST", body: change });
    if (reply.ok) {
      for (const input of form.querySelectorAll("input")) delete input.dataset.edited;
      const applied = Object.entries(change).map(([key, value]) => `${key} = ${value}`);
      setMessage("#settings-message", `Applies from the next round's tasks: ${applied.join(", ")}`, "ok");
      scheduleRefresh();
    } else {
      setMessage("#settings-message", reply.data.error, "error");
    }
  } catch (e) {
    setMessage("#settings-message", `The server cannot be reached: ${e.message}`, "error");
  }
}

// ---- Start ----

$("#login-form").addEventListener("submit", (event) => {
  event.preventDefault();
  login($("#token-input").value.trim());
});
$("#logout-button").addEventListener("click", logout);
for (const button of document.querySelectorAll(".controls button")) {
  button.addEventListener("click", () => sendControl(button.dataset.action));
}
$("#settings-form").addEventListener("submit", applySettings);
$("#settings-form").addEventListener("input", (event) => {
  event.target.dataset.edited = "true";
});

const saved = sessionStorage.getItem(TOKEN_KEY);
if (saved) login(saved);
