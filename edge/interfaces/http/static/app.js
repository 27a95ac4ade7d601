// vtzero operator page: plain JavaScript, no build step, nothing loaded from elsewhere.
// Data: /healthz (polled), /v1/events and /v1/tactile (server-sent events), /v1/episodes.
// /healthz's keys are Health's and an episode's press keys PressSummary's (edge/runtime/
// state.py; the list carries webui.LISTED_PRESS): tests/runtime/test_state.py checks them.
"use strict";

const UI = { "X-Vtzero-UI": "1" };
const $ = (id) => document.getElementById(id);
// frames: received; draws: frames drawn (times: when, for the rate over the last 2 s).
const stats = { frames: 0, draws: 0, times: [], lastSeq: null };
// For tests and curious operators: window.vtzero.fps() is the live view's frame rate.
window.vtzero = { stats, fps: () => fps() };

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k === "text") node.textContent = v;
    else node.setAttribute(k, v);
  }
  for (const c of children) if (c != null) node.append(c);
  return node;
}

async function call(path, body, method) {
  const opts = { credentials: "same-origin", headers: { ...UI } };
  if (method) opts.method = method;
  if (body !== undefined) {
    opts.method = method || "POST";
    opts.headers["Content-Type"] = "application/json";
    opts.body = JSON.stringify(body);
  }
  const resp = await fetch(path, opts);
  let data = null;
  try { data = await resp.json(); } catch (e) { data = null; }
  if (resp.status === 401) location.href = "/login";
  return { status: resp.status, data };
}

// --- health and state -------------------------------------------------------------------
function showState(state, episode) {
  $("state").textContent = state || "–";
  $("running").textContent = episode ? `episode ${episode}` : "";
}

async function pollHealth() {
  try {
    const { status, data } = await call("/healthz");
    const h = $("health");
    if (!data) throw new Error(`HTTP ${status}`);
    h.textContent = data.ok ? "healthy" : "not ready";
    h.className = "badge " + (data.ok ? "ok" : "bad");
    const why = [];
    if (!data.ready) why.push("starting");
    if (data.sensor_error) why.push(`sensor: ${data.sensor_error}`);
    else if (!data.sensor_fresh) why.push(`tactile stream stale (last frame ${data.last_frame_age_s ?? "?"} s ago)`);
    if (data.bus_error) why.push(`bus: ${data.bus_error}`);
    if (data.store_error) why.push(`store: ${data.store_error}`);
    if (data.vlm_error) why.push(data.vlm_error);
    $("health-detail").textContent = (why.join("; ") || "sensor fresh, bus and store fine") +
      ` · v${data.version}`;
    // Taught references another model embedded: kept, never used (absent from an older daemon).
    const stale = data.stale_references || 0;
    $("health-warning").textContent = stale
      ? `${stale} taught reference(s) not used, another model embedded them ` +
        `(${data.stale_reference_labels.join(", ")}): teach them again or fold them into a build`
      : "";
    showState(data.state, data.episode);
  } catch (e) {
    $("health").textContent = "unreachable";
    $("health").className = "badge bad";
    $("health-detail").textContent = String(e);
  }
}

function followEvents() {
  const events = new EventSource("/v1/events");
  const onState = (e) => { const d = JSON.parse(e.data); showState(d.state, d.episode); };
  events.addEventListener("hello", onState);
  events.addEventListener("state", onState);
  for (const kind of ["episode", "tactile", "result"]) {
    events.addEventListener(kind, () => refreshEpisodes());
  }
  events.addEventListener("teach", (e) => onTeach(JSON.parse(e.data)));
  // A recognition of several presses: the operator's cue before the next.
  events.addEventListener("press_again", (e) => say(JSON.parse(e.data).message));
}

// --- the live view ----------------------------------------------------------------------
// Micro-units of normal load for the brightest colour: adapts to the peak, never below
// MIN_SCALE (about one taxel's load when a press crosses x_th = 0.004).
const MIN_SCALE = 1000;
let fullScale = MIN_SCALE;

function fps() {
  const now = performance.now();
  while (stats.times.length && now - stats.times[0] > 2000) stats.times.shift();
  if (stats.times.length < 2) return 0;
  return (stats.times.length - 1) / ((stats.times[stats.times.length - 1] - stats.times[0]) / 1000);
}

function colour(v) {
  // 0 -> dark blue, 0.5 -> teal/green, 1 -> yellow/white; negative -> purple.
  const t = Math.max(-1, Math.min(1, v));
  if (t < 0) return `rgb(${Math.round(90 * -t + 20)},20,${Math.round(60 + 100 * -t)})`;
  const stops = [[20, 24, 60], [22, 120, 140], [90, 190, 90], [250, 220, 60], [255, 250, 220]];
  const x = t * (stops.length - 1);
  const i = Math.min(stops.length - 2, Math.floor(x));
  const f = x - i;
  const c = stops[i].map((a, k) => Math.round(a + f * (stops[i + 1][k] - a)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

// The pad's grid as [sensor] gives it (rows x cols, row-major from the top left); a frame
// from an older daemon names none: 4 x 4.
function drawPad(canvas, pad, rows = 4, cols = 4) {
  const ctx = canvas.getContext("2d");
  const cell = canvas.width / cols;
  const h = Math.round(cell * rows);
  if (canvas.height !== h) canvas.height = h;
  canvas.parentElement.hidden = !pad;
  ctx.fillStyle = "#111";
  ctx.fillRect(0, 0, canvas.width, h);
  if (!pad) return;
  const shearScale = fullScale * 0.5;
  for (let i = 0; i < rows * cols; i++) {
    const r = Math.floor(i / cols), c = i % cols;
    const x0 = c * cell, y0 = r * cell;
    ctx.fillStyle = colour(pad.z[i] / fullScale);
    ctx.fillRect(x0 + 2, y0 + 2, cell - 4, cell - 4);
    // Shear as an arrow from the taxel's centre.
    const cx = x0 + cell / 2, cy = y0 + cell / 2;
    let dx = pad.x[i] / shearScale, dy = pad.y[i] / shearScale;
    const len = Math.hypot(dx, dy);
    if (len > 1) { dx /= len; dy /= len; }
    const ex = cx + dx * cell * 0.45, ey = cy + dy * cell * 0.45;
    ctx.strokeStyle = "#fff"; ctx.fillStyle = "#fff"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(cx, cy, 2.5, 0, 2 * Math.PI); ctx.fill();
    if (Math.hypot(ex - cx, ey - cy) > 4) {  // (shorter: noise, not drawn)
      ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(ex, ey); ctx.stroke();
      const a = Math.atan2(ey - cy, ex - cx);
      ctx.beginPath();
      ctx.moveTo(ex, ey);
      ctx.lineTo(ex - 8 * Math.cos(a - 0.45), ey - 8 * Math.sin(a - 0.45));
      ctx.lineTo(ex - 8 * Math.cos(a + 0.45), ey - 8 * Math.sin(a + 0.45));
      ctx.closePath(); ctx.fill();
    }
  }
}

// Each frame is drawn as it arrives (waiting for an animation frame would merge two frames
// that arrive in one display interval); the numbers under the pads change 5 times a second.
let lastText = 0;

function drawFrame(f) {
  let peak = 0;
  for (const p of f.pads) for (const z of p.z) peak = Math.max(peak, Math.abs(z));
  fullScale = Math.max(MIN_SCALE, peak * 1.1, fullScale * 0.995);
  drawPad($("pad0"), f.pads[0], f.rows, f.cols);
  drawPad($("pad1"), f.pads[1], f.rows, f.cols);
  stats.draws++;
  const now = performance.now();
  stats.times.push(now);
  if (now - lastText < 200) return;
  lastText = now;
  $("norm").textContent = f.norm.toFixed(5);
  $("xth").textContent = f.x_th;
  $("norm-meter").value = Math.min(2, f.norm / f.x_th);
  $("scale").textContent = (fullScale / 1e6).toExponential(1);
  $("age").textContent = f.age_s > 0.5 ? `STALE: last frame ${f.age_s.toFixed(1)} s ago` : `frame ${f.seq}`;
  $("fps").textContent = `${fps().toFixed(1)} frames/s`;
}

function followTactile() {
  const source = new EventSource("/v1/tactile");
  source.onmessage = (e) => {
    const f = JSON.parse(e.data);
    stats.frames++;
    stats.lastSeq = f.seq;
    drawFrame(f);
  };
}

// --- recognize and abort ----------------------------------------------------------------
function say(text, bad = false) {
  const m = $("control-msg");
  m.textContent = text;
  m.className = bad ? "error" : "muted";
}

async function recognize(ev) {
  ev.preventDefault();
  const candidates = $("candidates").value.split(/[,\n]/).map((s) => s.trim()).filter(Boolean);
  localStorage.setItem("vtzero.candidates", $("candidates").value);
  // 1..5 presses fused into one question, or "auto" (a second only where the first is unsure).
  const chosen = $("presses").value;
  const presses = chosen === "auto" ? "auto" : Number(chosen);
  const { status, data } = await call("/v1/recognize", { candidates, presses });
  const of = presses === 1 ? "" : ` (${presses === "auto" ? "auto" : presses} presses)`;
  if (status === 202 || status === 200) say(`episode ${data.id}: ${data.status}${of}`);
  else if (status === 409) say(`busy: ${data.error}`, true);
  else say(`refused (${status}): ${data ? data.error : "no answer"}`, true);
}

async function abort() {
  const { data } = await call("/v1/abort", {});
  say(data && data.aborted ? "abort requested: the gripper opens" : "no press to abort");
}

// --- episodes ---------------------------------------------------------------------------
const traces = new Map();
let refreshing = false;
let again = false;

function drawTrace(canvas, tr) {
  const dpr = window.devicePixelRatio || 1;
  const W = canvas.clientWidth || 260, H = canvas.clientHeight || 120;
  canvas.width = W * dpr; canvas.height = H * dpr;
  const ctx = canvas.getContext("2d");
  ctx.scale(dpr, dpr);
  const pad = { l: 8, r: 8, t: 14, b: 16 };
  const t0 = Math.min(tr.t[0], tr.window[0]), t1 = Math.max(tr.t[tr.t.length - 1], tr.window[1]);
  const ymax = Math.max(tr.peak, tr.x_th) * 1.15;
  const X = (t) => pad.l + (t - t0) / (t1 - t0) * (W - pad.l - pad.r);
  const Y = (v) => H - pad.b - v / ymax * (H - pad.t - pad.b);
  ctx.clearRect(0, 0, W, H);
  // The model's crop window.
  ctx.fillStyle = "rgba(47,111,223,0.12)";
  ctx.fillRect(X(tr.window[0]), pad.t, X(tr.window[1]) - X(tr.window[0]), H - pad.t - pad.b);
  ctx.font = "10px system-ui, sans-serif";
  ctx.fillStyle = "#2f6fdf";
  ctx.fillText("crop", X(tr.window[0]) + 3, pad.t + 10);
  // x_th.
  ctx.strokeStyle = "#c2362b"; ctx.setLineDash([4, 3]); ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(pad.l, Y(tr.x_th)); ctx.lineTo(W - pad.r, Y(tr.x_th)); ctx.stroke();
  ctx.fillStyle = "#c2362b"; ctx.fillText("x_th", W - pad.r - 24, Y(tr.x_th) - 3);
  // t_cross (dotted) and t_stop.
  if (tr.t_cross != null) {
    ctx.strokeStyle = "#a86100"; ctx.setLineDash([2, 2]);
    ctx.beginPath(); ctx.moveTo(X(tr.t_cross), pad.t); ctx.lineTo(X(tr.t_cross), H - pad.b); ctx.stroke();
  }
  ctx.setLineDash([]); ctx.strokeStyle = "#1d232b";
  ctx.beginPath(); ctx.moveTo(X(0), pad.t); ctx.lineTo(X(0), H - pad.b); ctx.stroke();
  ctx.fillStyle = "#1d232b"; ctx.fillText("t_stop", X(0) + 3, H - 4);
  // The norm.
  ctx.strokeStyle = "#18794e"; ctx.lineWidth = 1.5;
  ctx.beginPath();
  tr.t.forEach((t, i) => (i ? ctx.lineTo(X(t), Y(tr.norm[i])) : ctx.moveTo(X(t), Y(tr.norm[i]))));
  ctx.stroke();
  ctx.fillStyle = "#69717d";
  ctx.fillText(`peak norm ${tr.peak.toFixed(4)} · ${tr.frames} frames`, pad.l, pad.t - 3);
  canvas.dataset.points = String(tr.t.length);
}

async function traceOf(ep) {
  if (!traces.has(ep.id)) {
    const { status, data } = await call(ep.trace);
    if (status !== 200) return null;
    traces.set(ep.id, data);
  }
  return traces.get(ep.id);
}

function card(ep) {
  const when = ep.created ? new Date(ep.created * 1000).toLocaleTimeString() : "";
  const photo = ep.image
    ? el("img", { src: ep.image, alt: `photo of episode ${ep.id}`, class: "photo" })
    : el("div", { class: "noimg", text: "no photo" });
  const canvas = el("canvas", { class: "trace", "data-episode": ep.id });
  const result = ep.label
    ? el("div", { class: "label", text: ep.label })
    : ep.status === "pressed"
      ? el("div", { class: "muted", text: "pressed to teach: no question asked" })
      : el("div", { class: "error", text: ep.error || (ep.status === "pending" ? "waiting for the VLM" : ep.status) });
  // The VLM's reason ([vlm] ask_reason) as text, never markup: it is the server's words.
  const reason = ep.reason ? el("div", { class: "reason", text: `why: ${ep.reason}` }) : null;
  const topk = el("ol", { class: "topk" },
    ...(ep.topk || []).map((t) => el("li", { text: `${t.label} (${t.distance.toFixed(3)})` })));
  // The nearest reference's distance as a percentile of the references' own: past the
  // configured one, a touch like none the robot knows.
  const familiarity = ep.familiarity == null ? null : el("div", {
    class: ep.unfamiliar ? "error familiarity" : "muted familiarity",
    text: `familiarity: percentile ${ep.familiarity.toFixed(0)}` + (ep.unfamiliar ? " · unfamiliar: like no reference" : "") });
  const tm = ep.timings || {};
  const fmt = (k) => (tm[k] != null ? `${k.replace("_s", "")} ${(tm[k] * 1000).toFixed(0)} ms` : null);
  const timings = el("div", { class: "timings",
    text: ["press_s", "encode_s", "vlm_s"].map(fmt).filter(Boolean).join(" · ") +
      (ep.press && ep.press.stop_latency_ms != null ? ` · stop latency ${ep.press.stop_latency_ms.toFixed(2)} ms` : "") +
      (ep.presses ? ` · ${ep.presses.length} presses fused (${ep.fusion})` : "") });
  const node = el("div", { class: "episode", id: `ep-${ep.id}`, "data-status": ep.status,
                           "data-presses": ep.presses ? ep.presses.length : 1 },
    el("div", { class: "head" }, el("span", { class: `badge ${ep.status}`, text: ep.status }),
       el("span", { class: "id", text: ep.id }), el("span", { class: "muted", text: when })),
    photo,
    el("div", {}, result, reason, el("div", { class: "muted", text: "touch: similar to" }), topk,
       familiarity, timings, pressList(ep)),
    el("div", { class: "info" }, ep.trace ? canvas : el("div", { class: "muted", text: "no press recording" }),
       thisWas(ep)));
  if (ep.trace) traceOf(ep).then((tr) => tr && drawTrace(canvas, tr));
  return node;
}

// A recognition of several presses: each as it went (its nearest class, familiarity and
// subsampling offsets' agreement), before the fused top-k above.
function pressList(ep) {
  if (!ep.presses) return null;
  const pct = (v) => (v == null ? "–" : v.toFixed(0));
  return el("details", { class: "presses" },
    el("summary", { text: `each press (fused by ${ep.fusion})` }),
    el("ol", {}, ...ep.presses.map((p) => {
      const near = p.topk && p.topk.length ? `${p.topk[0].label} (${p.topk[0].distance.toFixed(3)})` : "–";
      return el("li", { class: p.result === "ok" ? "" : "error",
        text: `${p.result}` + (p.press_s != null ? ` · ${p.press_s.toFixed(1)} s` : "") +
          (p.topk ? ` · nearest ${near} · familiarity ${pct(p.familiarity)}` : "") +
          (p.unfamiliar ? " · unfamiliar" : "") +
          (p.agreement != null ? ` · offsets agree ${(p.agreement * 100).toFixed(0)} %` : "") });
    })));
}

async function refreshEpisodes() {
  // One request at a time; an event during it asks for one more pass after it.
  if (refreshing) { again = true; return; }
  refreshing = true;
  try {
    do {
      again = false;
      const { status, data } = await call("/v1/episodes?limit=8");
      if (status !== 200) break;
      const list = $("episodes");
      const key = JSON.stringify(data.episodes.map((e) => [e.id, e.status, e.updated]));
      if (list.dataset.key !== key) {
        list.dataset.key = key;
        list.replaceChildren(...data.episodes.map(card));
      }
      $("episodes-note").textContent = data.episodes.length ? "" : "none yet";
    } while (again);
  } catch (e) {
    $("episodes-note").textContent = `cannot list episodes: ${e}`;
  } finally {
    refreshing = false;
  }
}

// --- teaching ---------------------------------------------------------------------------
// POST /v1/teach (the robot presses the object, asking between presses to move it), the
// progress from the "teach" events, GET/DELETE /v1/references, and "this was..." on each
// episode (POST /v1/episodes/{id}/teach).
function sayTeach(text, kind = "muted") {
  const m = $("teach-msg");
  m.textContent = text;
  m.className = kind;
}

async function teach(ev) {
  ev.preventDefault();
  const body = { label: $("teach-label").value.trim(), presses: Number($("teach-presses").value),
                 append: $("teach-append").checked };
  const description = $("teach-description").value.trim();
  if (description) body.description = description;
  const { status, data } = await call("/v1/teach", body);
  if (status === 202) sayTeach(`teaching ${data.label}: ${data.presses} press(es)`);
  else sayTeach(`refused (${status}): ${data ? data.error : "no answer"}`, "error");
}

function onTeach(e) {
  if (e.step === "pressing") sayTeach(`${e.label}: press ${e.press} of ${e.presses}…`);
  else if (e.step === "move") sayTeach(e.message, "move");
  else if (e.step === "taught") sayTeach(`${e.label}: press ${e.press} of ${e.presses} taught (reference ${e.reference})`);
  else if (e.step === "done") sayTeach(`taught ${e.label}: ${e.presses} presses`, "ok");
  else if (e.step === "failed") sayTeach(`teaching ${e.label} stopped: ${e.message}`, "error");
  if (e.step !== "pressing" && e.step !== "move") refreshReferences();
}

async function refreshReferences() {
  const { status, data } = await call("/v1/references");
  if (status !== 200) {
    $("references-note").textContent = data ? data.error : `HTTP ${status}`;
    return;
  }
  $("references").replaceChildren(...data.references.map((r) => {
    const remove = el("button", { type: "button", class: "danger", text: "remove",
                                  title: `DELETE /v1/references/${r.id}` });
    remove.addEventListener("click", async () => {
      const answer = await call(`/v1/references/${encodeURIComponent(r.id)}`, undefined, "DELETE");
      if (answer.status !== 200) sayTeach(`not removed: ${answer.data ? answer.data.error : answer.status}`, "error");
      refreshReferences();
    });
    return el("li", { class: r.stale ? "stale" : "", "data-id": r.id },
      el("b", { text: r.label }), el("span", { class: "desc",
        text: `${r.description} · ${r.source}${r.episode ? ` · episode ${r.episode}` : ""}` +
          (r.stale ? " · another model embedded it: not used" : "") }), remove);
  }));
  $("references-note").textContent = data.references.length ? `${data.references.length}` : "none yet";
}

// "This was...": the episode's press taught as what its object really was.
function thisWas(ep) {
  if (!ep.trace || ep.status === "running" || ep.status === "pending") return null;
  const label = el("input", { placeholder: "label", "aria-label": "what it was" });
  const description = el("input", { placeholder: "description (a new label)", "aria-label": "its description" });
  const button = el("button", { type: "button", text: "teach" });
  const msg = el("span", { class: "muted" });
  button.addEventListener("click", async () => {
    const body = { label: label.value.trim() };
    if (description.value.trim()) body.description = description.value.trim();
    const { status, data } = await call(`/v1/episodes/${encodeURIComponent(ep.id)}/teach`, body);
    msg.textContent = status === 200 ? `taught as ${data.label} (reference ${data.id})`
      : `refused (${status}): ${data ? data.error : "no answer"}`;
    msg.className = status === 200 ? "muted" : "error";
    if (status === 200) refreshReferences();
  });
  // An unfamiliar touch (like no reference) is offered open: teaching it is the likely fix.
  return el("details", { class: "this-was", ...(ep.unfamiliar ? { open: "" } : {}) },
            el("summary", { text: ep.unfamiliar ? "unfamiliar: this was…" : "this was…" }),
            label, description, button, el("div", {}, msg));
}

// --- start ------------------------------------------------------------------------------
$("candidates").value = localStorage.getItem("vtzero.candidates") || "";
$("recognize-form").addEventListener("submit", recognize);
$("abort").addEventListener("click", abort);
$("tare").addEventListener("click", () => call("/v1/tactile/tare", {}));
$("teach-form").addEventListener("submit", teach);
refreshReferences();
pollHealth();
setInterval(pollHealth, 1000);
followEvents();
followTactile();
refreshEpisodes();
setInterval(refreshEpisodes, 5000);
