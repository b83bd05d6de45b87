// Live view of a think server: a stream of views (each with the samples not seen yet), redrawn
// with Plotly.react. Read-only: it only ever sends GET requests.
"use strict";

const history = { t: [], reward: [], q_chosen: [], thinks_per_s: [], stored: [], resets: [] };
// client -> { t, jitter_p99_ms, overruns, reward, q }: a Map, never a plain object, since client
// ids come from the network and may be "__proto__", "constructor" or any other property's name.
const clientHistory = new Map();
let seq = 0;
let kept = 2400;  // samples kept per curve: the server's history length (sent in the view)
const plotConfig = { displayModeBar: false, responsive: true };
const margin = { l: 55, r: 55, t: 35, b: 40 };
let revision = 0;  // the curves' arrays grow in place: Plotly.react redraws when this changes

function fmt(value, digits = 0) {
  if (value === null || value === undefined) return "-";
  return Number(value).toLocaleString(undefined, { maximumFractionDigits: digits, minimumFractionDigits: digits });
}

const CLIENT_KEYS = ["jitter_p99_ms", "overruns", "reward", "q"];

function take(samples) {
  for (const s of samples) {
    seq = Math.max(seq, s.seq);
    for (const key of Object.keys(history)) history[key].push(s[key]);
    for (const [client, c] of Object.entries(s.clients || {})) {
      let h = clientHistory.get(client);
      if (h === undefined) {
        h = { t: [], jitter_p99_ms: [], overruns: [], reward: [], q: [] };
        clientHistory.set(client, h);
      }
      h.t.push(s.t);
      for (const key of CLIENT_KEYS) h[key].push(Object.hasOwn(c, key) ? c[key] : null);
    }
  }
  trim();
}

// Keep what the server keeps: the oldest samples go, and clients none of whose samples are left.
function trim() {
  const excess = history.t.length - kept;
  if (excess > 0) for (const key of Object.keys(history)) history[key].splice(0, excess);
  const oldest = history.t.length > 0 ? history.t[0] : -Infinity;
  for (const [client, h] of clientHistory) {
    let n = 0;
    while (n < h.t.length && !(h.t[n] >= oldest)) n += 1;
    if (n === h.t.length) clientHistory.delete(client);
    else if (n > 0) for (const key of ["t", ...CLIENT_KEYS]) h[key].splice(0, n);
  }
}

function drawLearning() {
  Plotly.react("chart-learning", [
    { x: history.t, y: history.reward, name: "reward (mean raw)", mode: "lines" },
    { x: history.t, y: history.q_chosen, name: "Q of chosen actions", mode: "lines", yaxis: "y2" },
  ], { datarevision: revision, title: { text: "reward and Q of chosen actions", font: { size: 14 } }, margin,
       xaxis: { title: { text: "s" } }, yaxis: { title: { text: "reward" } },
       yaxis2: { title: { text: "Q" }, overlaying: "y", side: "right", showgrid: false, zeroline: false },
       legend: { orientation: "h", y: -0.25 } }, plotConfig);
}

function drawThinking() {
  Plotly.react("chart-thinking", [
    { x: history.t, y: history.thinks_per_s, name: "thinks/s", mode: "lines" },
    { x: history.t, y: history.stored, name: "experiences stored", mode: "lines", yaxis: "y2" },
    { x: history.t, y: history.resets, name: "divergence resets", mode: "lines", yaxis: "y2",
      line: { dash: "dot" } },
  ], { datarevision: revision, title: { text: "thinking", font: { size: 14 } }, margin, xaxis: { title: { text: "s" } },
       yaxis: { title: { text: "thinks/s" } }, yaxis2: { title: { text: "experiences, resets" }, overlaying: "y", side: "right", showgrid: false, zeroline: false },
       legend: { orientation: "h", y: -0.25 } }, plotConfig);
}

function drawClients() {
  const traces = [];
  for (const [client, h] of clientHistory) {
    traces.push({ x: h.t, y: h.jitter_p99_ms, name: `${client} jitter p99 (ms)`, mode: "lines" });
    traces.push({ x: h.t, y: h.overruns, name: `${client} overruns`, mode: "lines", yaxis: "y2",
                  line: { dash: "dot" } });
  }
  Plotly.react("chart-clients", traces, {
    datarevision: revision, title: { text: "clients' control ticks", font: { size: 14 } }, margin, xaxis: { title: { text: "s" } },
    yaxis: { title: { text: "ms" } }, yaxis2: { title: { text: "overruns" }, overlaying: "y", side: "right", showgrid: false, zeroline: false, rangemode: "tozero" },
    legend: { orientation: "h", y: -0.25 } }, plotConfig);
}

function float32(base64) {
  const bytes = Uint8Array.from(atob(base64), (c) => c.charCodeAt(0));
  return Array.from(new Float32Array(bytes.buffer));
}

function linspace([low, high, n]) {
  return Array.from({ length: n }, (_, i) => low + (high - low) * i / (n - 1));
}

function drawSurface(surface) {
  if (!surface) {
    Plotly.react("chart-surface", [], { title: { text: "action-value surface: no state yet", font: { size: 14 } },
                                        margin }, plotConfig);
    return;
  }
  const d = surface.dims;
  const axes = surface.axes.map(linspace);
  const flat = float32(surface.q_f32);
  const q = d.length === 1 ? flat
    : Array.from({ length: surface.shape[0] }, (_, j) => flat.slice(j * surface.shape[1], (j + 1) * surface.shape[1]));
  const actions = float32(surface.wire_action_f32);
  const values = float32(surface.wire_value_f32);
  const width = actions.length / surface.n_wires;  // action variables per wire
  const wire = (i, k) => actions[i * width + k];
  const best = surface.best;
  const markerColour = values.map((_, i) => (i === best ? "crimson" : "black"));
  const title = `Q(x, u) of ${surface.client}'s newest state, wires marked`;
  if (d.length === 1) {
    Plotly.react("chart-surface", [
      { x: axes[0], y: q, name: "Q(x, u)", mode: "lines" },
      { x: values.map((_, i) => wire(i, d[0])), y: values, name: "wires (best in red)", mode: "markers",
        marker: { size: 9, color: markerColour } },
    ], { title: { text: title, font: { size: 14 } }, margin, xaxis: { title: { text: `action ${d[0]}` } },
         yaxis: { title: { text: "Q" } }, legend: { orientation: "h", y: -0.25 } }, plotConfig);
  } else {
    Plotly.react("chart-surface", [
      { type: "heatmap", x: axes[0], y: axes[1], z: q, colorscale: "Viridis", colorbar: { title: { text: "Q" } } },
      { x: values.map((_, i) => wire(i, d[0])), y: values.map((_, i) => wire(i, d[1])), mode: "markers",
        name: "wires", text: values.map((v) => `value ${v.toFixed(3)}`),
        marker: { size: 10, color: markerColour, line: { color: "white", width: 1.5 } } },
    ], { title: { text: `${title} (other actions at the best wire)`, font: { size: 13 } }, margin,
         xaxis: { title: { text: `action ${d[0]}` } }, yaxis: { title: { text: `action ${d[1]}` } },
         showlegend: false }, plotConfig);
  }
}

function drawRejected(rejected) {
  const entries = Object.entries(rejected);  // own properties only (reasons are the network's strings)
  Plotly.react("chart-rejected", [{ type: "bar", x: entries.map(([r]) => r), y: entries.map(([, n]) => n) }],
    { title: { text: "frames rejected, by reason", font: { size: 14 } }, margin,
      yaxis: { title: { text: "frames" }, rangemode: "tozero" } }, plotConfig);
}

function drawClientTable(clients, heard) {
  const body = document.querySelector("#clients tbody");
  body.replaceChildren();
  const listed = Object.keys(clients).length;
  for (const [client, c] of Object.entries(clients)) {
    const m = c.metrics;
    const row = document.createElement("tr");
    for (const text of [client, c.following || "-", c.weights_version, fmt(m["client/tick_jitter_ms_p99"], 2),
                        fmt(m["client/overruns"]), fmt(m["client/reward_mean"], 3), fmt(m["client/q_mean"], 3)]) {
      const cell = document.createElement("td");
      cell.textContent = text;
      row.appendChild(cell);
    }
    body.appendChild(row);
  }
  if (heard > listed) {  // the server lists the most recently heard only
    const row = document.createElement("tr");
    const cell = document.createElement("td");
    cell.colSpan = 7;
    cell.textContent = `${heard - listed} more clients heard, not listed`;
    row.appendChild(cell);
    body.appendChild(row);
  }
}

let cameraShown = "";

// The picture of the client whose picture arrived last (the view names it), else the first by name.
function drawCamera(cameras, newest) {
  const ticks = new Map(Object.entries(cameras));  // own properties only: client ids are the network's
  if (ticks.size === 0) return;
  const client = ticks.has(newest) ? newest : [...ticks.keys()].sort()[0];
  const tick = ticks.get(client);
  const shown = `${client}:${tick}`;
  if (shown === cameraShown) return;  // fetch a picture only when a new one has arrived
  cameraShown = shown;
  document.getElementById("camera-panel").hidden = false;
  document.getElementById("camera-client").textContent = client;
  document.getElementById("camera-tick").textContent = tick;
  document.getElementById("camera").src = `/api/camera/${encodeURIComponent(client)}.png?tick=${encodeURIComponent(tick)}`;
}

function show(view) {
  if (Number.isInteger(view.history) && view.history > 0) kept = view.history;
  take(view.samples);
  revision += 1;
  const f = view.figures;
  document.getElementById("server").textContent = `${view.server} (incarnation ${view.incarnation})`;
  document.getElementById("controller").textContent = view.controller;
  document.getElementById("version").textContent = view.weights_version;
  document.getElementById("thinks").textContent = fmt(f["think/thinks_per_s"]);
  document.getElementById("stored").textContent = fmt(f["store/experiences"]);
  document.getElementById("resets").textContent = fmt(f["learn/divergence_resets"]);
  document.getElementById("rejected").textContent = fmt(Object.values(view.rejected).reduce((a, b) => a + b, 0));
  document.getElementById("samples").textContent = history.t.length;
  const cpu = view.cpu.process_s > 0 ? (100 * view.cpu.dashboard_s / view.cpu.process_s) : null;
  document.getElementById("cpu").textContent = cpu === null ? "-" : `${fmt(cpu, 2)}% of the server's`;
  document.getElementById("learner").textContent = view.learner || "waiting for a client's config";
  drawLearning();
  drawThinking();
  drawClients();
  drawSurface(view.surface);
  drawRejected(view.rejected);
  drawClientTable(view.clients, view.clients_heard);
  drawCamera(view.cameras, view.camera);
}

// One server-sent-events stream per page: the server pushes the view update_hz times a second.
// After an error the page starts afresh: a restarted server numbers its samples from 1 again and
// sends back the history it keeps.
function connect() {
  for (const key of Object.keys(history)) history[key].length = 0;
  clientHistory.clear();
  seq = 0;
  const source = new EventSource("/api/stream");
  source.onmessage = (event) => {
    show(JSON.parse(event.data));
    document.getElementById("status").textContent = `live, updated ${new Date().toLocaleTimeString()}`;
  };
  source.onerror = () => {
    source.close();
    document.getElementById("status").textContent = "server not answering; reconnecting";
    setTimeout(connect, 1000);
  };
}

connect();
