// Live view of a think server: a stream of views (each with the samples not seen yet), redrawn
// with Plotly.react. Read-only: it only ever sends GET requests.
"use strict";

const history = { t: [], reward: [], q_chosen: [], thinks_per_s: [], stored: [], resets: [] };
const clientHistory = {};  // client -> { t, jitter_p99_ms, overruns, reward, q }
let seq = 0;
const plotConfig = { displayModeBar: false, responsive: true };
const margin = { l: 55, r: 55, t: 35, b: 40 };
let revision = 0;  // the curves' arrays grow in place: Plotly.react redraws when this changes

function fmt(value, digits = 0) {
  if (value === null || value === undefined) return "-";
  return Number(value).toLocaleString(undefined, { maximumFractionDigits: digits, minimumFractionDigits: digits });
}

function take(samples) {
  for (const s of samples) {
    seq = Math.max(seq, s.seq);
    for (const key of Object.keys(history)) history[key].push(s[key]);
    for (const [client, c] of Object.entries(s.clients)) {
      const h = clientHistory[client] ||= { t: [], jitter_p99_ms: [], overruns: [], reward: [], q: [] };
      h.t.push(s.t);
      for (const key of ["jitter_p99_ms", "overruns", "reward", "q"]) h[key].push(c[key]);
    }
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
  for (const [client, h] of Object.entries(clientHistory)) {
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
  const reasons = Object.keys(rejected);
  Plotly.react("chart-rejected", [{ type: "bar", x: reasons, y: reasons.map((r) => rejected[r]) }],
    { title: { text: "frames rejected, by reason", font: { size: 14 } }, margin,
      yaxis: { title: { text: "frames" }, rangemode: "tozero" } }, plotConfig);
}

function drawClientTable(clients) {
  const body = document.querySelector("#clients tbody");
  body.replaceChildren();
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
}

let cameraShown = "";

function drawCamera(cameras) {
  const clients = Object.keys(cameras).sort();
  if (clients.length === 0) return;
  const client = clients[0];
  const shown = `${client}:${cameras[client]}`;
  if (shown === cameraShown) return;  // fetch a picture only when a new one has arrived
  cameraShown = shown;
  document.getElementById("camera-panel").hidden = false;
  document.getElementById("camera-client").textContent = client;
  document.getElementById("camera-tick").textContent = cameras[client];
  document.getElementById("camera").src = `/api/camera/${encodeURIComponent(client)}.png?tick=${cameras[client]}`;
}

function show(view) {
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
  drawClientTable(view.clients);
  drawCamera(view.cameras);
}

// One server-sent-events stream per page: the server pushes the view update_hz times a second.
// After an error the page starts afresh: a restarted server numbers its samples from 1 again and
// sends back the history it keeps.
function connect() {
  for (const key of Object.keys(history)) history[key].length = 0;
  for (const client of Object.keys(clientHistory)) delete clientHistory[client];
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
