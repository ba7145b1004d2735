// The technician's page: plain JavaScript against the daemon's REST API, no build step.
"use strict";

const TOKEN_KEY = "mirrorgonio.token";
const FINAL = ["complete", "aborted", "failed", "interrupted"];
const ACTIVE = ["queued", "running", "paused"];
const STATUS_PERIOD_MS = 2000;
const POLL_PERIOD_MS = 1000;

const $ = (id) => document.getElementById(id);

// --- talking to the daemon ---------------------------------------------------------------
class ApiError extends Error {
  constructor(status, detail) {
    super(status ? `${detail} (HTTP ${status})` : detail);
    this.status = status;
  }
}

// FastAPI's ``detail``: a string, or a list of validation errors with ``loc`` and ``msg``.
function describeDetail(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => {
      const loc = (d.loc || []).filter((p) => p !== "body").join(".");
      return loc ? `${loc}: ${d.msg}` : String(d.msg);
    }).join("; ");
  }
  return JSON.stringify(detail);
}

// ``accept`` lists the error statuses whose JSON body is still an answer (503 of /health).
// Every request carries the token (it guards reads too); every request that changes something
// is sent as JSON, body or none (the daemon refuses anything else: docs/daemon.md, "Security").
async function api(method, path, body, accept = []) {
  const headers = {};
  const token = $("token").value.trim();
  if (token) headers.Authorization = `Bearer ${token}`;
  if (method !== "GET") headers["Content-Type"] = "application/json";
  let resp;
  try {
    resp = await fetch(path, {
      method, headers, cache: "no-store",
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (err) {
    throw new ApiError(0, `the daemon does not answer (${err.message})`);
  }
  const text = await resp.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!resp.ok && !accept.includes(resp.status)) {
    const detail = data && data.detail !== undefined ? describeDetail(data.detail) : (resp.statusText || "error");
    throw new ApiError(resp.status, detail);
  }
  return data;
}

// ``about`` names what the message is about, for hideMessage once that is settled.
function showMessage(text, kind = "error", about = "") {
  const box = $("message");
  box.textContent = text;
  box.className = `message ${kind}`;
  box.setAttribute("role", kind === "error" ? "alert" : "status");
  box.dataset.about = about;
  box.hidden = false;
}

function hideMessage(about) {
  if ($("message").dataset.about === about) $("message").hidden = true;
}

// The browser's own requests (the event stream, the preview image, downloads, the report in a
// tab) cannot carry the token: a session cookie set for it by POST /session stands in for it,
// for reads only. ``session`` settles when the cookie matches the token field.
let session = Promise.resolve();
let sessionSeq = 0;

function openSession() {
  const seq = ++sessionSeq;
  const token = $("token").value.trim();
  session = (token ? api("POST", "/session") : api("DELETE", "/session"))
    .then(() => {
      if (seq !== sessionSeq) return;
      loadPresets();
      refreshRuns();
    })
    .catch(() => { /* a token being typed, or a wrong one: the reads say so */ });
  return session;
}

// --- formatting --------------------------------------------------------------------------
function plural(n, noun) { return `${n} ${noun}${n === 1 ? "" : "s"}`; }

function fmtPercent(p) { return `${Math.round((p || 0) * 10) / 10} %`; }

function fmtDuration(s) {
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  const mm = String(m).padStart(h ? 2 : 1, "0"), ss = String(sec).padStart(2, "0");
  return h ? `${h}:${mm}:${ss}` : `${mm}:${ss}`;
}

function fmtTime(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
}

function setBadge(el, text, cls) {
  el.textContent = text;
  el.className = `badge ${cls}`;
}

function el(tag, props = {}, ...children) {
  const node = document.createElement(tag);
  Object.assign(node, props);
  for (const child of children) node.append(child);
  return node;
}

// --- device status, every 2 s --------------------------------------------------------------
// The health needs no token; the devices do, while tokens guard reads.
async function refreshStatus() {
  try {
    await showStatus();
  } finally {
    setTimeout(refreshStatus, STATUS_PERIOD_MS);
  }
}

async function showStatus() {
  const [health, devices] = await Promise.allSettled([api("GET", "/health", undefined, [503]), api("GET", "/devices")]);
  if (health.status === "fulfilled") {
    renderHealth(health.value);
    const active = health.value.active_run;
    // Follow whatever run the daemon is busy with once ours has ended.
    if (active && active !== followed && (!current || !ACTIVE.includes(current.state))) follow(active);
  } else {
    setBadge($("health-status"), "unreachable", "badge-unreachable");
    $("health-summary").textContent = health.reason.message;
  }
  if (devices.status === "fulfilled") {
    renderDevices(devices.value);
    $("devices-updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
  } else {
    $("devices-updated").textContent = `cannot read the devices: ${devices.reason.message}`;
  }
}

function renderHealth(h) {
  setBadge($("health-status"), h.status, `badge-${h.status}`);
  $("rig-name").textContent = `of rig ${h.rig}`;
  let active = h.active_run ? `active run ${h.active_run}` : "no active run";
  if (h.queued_runs) active += `, ${h.queued_runs} queued${h.queue_held ? " (the queue is held)" : ""}`;
  $("health-summary").textContent = `${h.reasons.length ? h.reasons.join("; ") : "devices ready"} · ${active} · v${h.version}`;
  $("health-reasons").replaceChildren(...h.reasons.map((r) => el("li", { textContent: r })));
}

function renderDevices(d) {
  const arm = d.arm, cam = d.camera;
  $("arm-connected").textContent = arm.connected ? "connected" : `not connected: ${arm.error || "?"}`;
  $("arm-connected").className = arm.connected ? "good" : "bad";
  $("arm-identity").textContent = arm.identity;
  if (arm.position) {
    const p = arm.position, mm = (v) => (v * 1000).toFixed(2), deg = (v) => v.toFixed(2);
    $("arm-position").textContent =
      `x ${mm(p.x)}  y ${mm(p.y)}  z ${mm(p.z)} mm\nrx ${deg(p.rx)}  ry ${deg(p.ry)}  rz ${deg(p.rz)} °`;
    $("arm-position").style.whiteSpace = "pre";
  } else {
    $("arm-position").textContent = "—";
  }
  const status = [];
  if (arm.moving !== null && arm.moving !== undefined) status.push(arm.moving ? "moving" : "still");
  if (arm.in_position !== null && arm.in_position !== undefined) status.push(arm.in_position ? "in position" : "not in position");
  $("arm-status").textContent = status.join(", ") || "—";
  const alarm = arm.alarm_code ? `0x${arm.alarm_code.toString(16).padStart(4, "0")}: ${arm.alarm_text || ""}` : "none";
  $("arm-alarm").textContent = arm.connected ? alarm : "—";
  $("arm-alarm").className = arm.alarm_code ? "bad" : "";
  $("camera-connected").textContent = cam.connected ? "connected" : `not connected: ${cam.error || "?"}`;
  $("camera-connected").className = cam.connected ? "good" : "bad";
  $("camera-identity").textContent = cam.identity;
}

// --- presets and the start form --------------------------------------------------------------
let presets = {};

async function loadPresets() {
  try {
    const data = await api("GET", "/presets");
    presets = data.presets;
    const select = $("preset");
    const chosen = select.value;
    select.replaceChildren(...Object.entries(presets).map(([name, p]) =>
      el("option", { value: name, textContent: presetLabel(name, p), disabled: !p.valid })));
    if (chosen && presets[chosen]) select.value = chosen;
    if (!$("exposures").value && data.default_bracket && data.default_bracket.exposures_s) {
      $("exposures").value = data.default_bracket.exposures_s.join(", ");
    }
    showPresetInfo();
    hideMessage("presets");
  } catch (err) {
    showMessage(`Cannot read the presets — ${err.message}`, "error", "presets");
  }
}

// The positions a run of the preset takes: all of them, or the first N the form asks for.
function presetPositions(p) {
  const count = Number($("count").value.trim());
  return Number.isInteger(count) && count > 0 && count < p.positions
    ? `${count} of its ${p.positions} positions` : `${p.positions} positions`;
}

function presetLabel(name, p) { return p.valid ? `${name} (${presetPositions(p)})` : `${name} (invalid)`; }

function showPresetInfo() {
  for (const option of $("preset").options) {
    const p = presets[option.value];
    if (p) option.textContent = presetLabel(option.value, p);
  }
  const p = presets[$("preset").value];
  $("preset-info").textContent = !p ? "" : p.valid ? `${p.schedule.kind}: ${presetPositions(p)}` : p.error;
}

function bracketMode() { return $("bracket-auto").checked ? "auto" : "fixed"; }

function showBracketFields() {
  const auto = bracketMode() === "auto";
  $("exposures-label").hidden = auto;
  $("snr-label").hidden = !auto;
}

// Numbers where they parse; anything else goes as typed, for the daemon to explain.
function parseExposures(text) {
  return text.split(/[\s,;]+/).filter(Boolean).map((s) => {
    const n = Number(s);
    return Number.isFinite(n) ? n : s;
  });
}

function runRequest() {
  const body = {
    preset: $("preset").value,
    operator: $("operator").value,
    light_source: $("light-source").value,
    notes: $("notes").value,
  };
  const count = $("count").value.trim();
  if (count) body.count = Number(count);
  if (bracketMode() === "fixed") {
    body.bracket = { mode: "fixed", exposures_s: parseExposures($("exposures").value) };
  } else {
    body.bracket = { mode: "auto" };
    const snr = $("target-snr").value.trim();
    if (snr) body.bracket.target_snr = Number(snr);
  }
  return body;
}

async function startRun(event) {
  event.preventDefault();
  const button = $("start");
  button.disabled = true;
  try {
    const run = await api("POST", "/runs", runRequest());
    if (run.state === "queued") {
      // It waits its turn: the page goes on showing the run in progress.
      showMessage(`Run ${run.id} queued: position ${run.queue_position}, ${plural(run.n_positions, "position")}; `
        + "it starts when the runs ahead of it have completed.", "info");
    } else {
      showMessage(`Run ${run.id} started: ${run.n_positions} positions.`, "info");
      follow(run.id, run);
    }
    refreshRuns();
  } catch (err) {
    showMessage(`Start refused: ${err.message}`);
  } finally {
    button.disabled = false;
  }
}

// --- the followed run: server-sent events, polling as the fallback -------------------------
let followed = null;   // id of the run shown
let current = null;    // its last RunStatus
let source = null;     // its EventSource
let pollTimer = null;
let resultsKey = null; // the job whose figures the results card shows

function stopFollowing() {
  if (source) { source.close(); source = null; }
  if (pollTimer) { clearInterval(pollTimer); pollTimer = null; }
}

async function follow(id, initial) {
  stopFollowing();
  followed = id;
  current = null;
  resultsKey = null;
  if (initial) render(initial);
  markSelected();
  const run = await fetchFollowed();
  if (run && followed === id && ACTIVE.includes(run.state)) openEvents(id);
}

async function fetchFollowed() {
  const id = followed;
  if (!id) return null;
  try {
    const run = await api("GET", `/runs/${encodeURIComponent(id)}`);
    if (followed === id) render(run);
    return run;
  } catch (err) {
    $("follow-mode").textContent = `cannot read the run: ${err.message}`;
    return null;
  }
}

async function openEvents(id) {
  if (!window.EventSource) { startPolling(id); return; }
  await session;  // the stream reads with the session cookie
  if (followed !== id || source) return;
  const es = new EventSource(`/runs/${encodeURIComponent(id)}/events`);
  source = es;
  es.addEventListener("progress", (e) => {
    if (followed !== id) return;
    $("follow-mode").textContent = "live";
    try { render(JSON.parse(e.data)); } catch { /* a malformed event: polling will catch up */ }
  });
  // The stream ends when the run does; any other end (or failure) falls back to polling.
  es.onerror = () => {
    es.close();
    if (source === es) source = null;
    if (followed === id && !(current && FINAL.includes(current.state))) startPolling(id);
  };
}

function startPolling(id) {
  if (pollTimer || followed !== id) return;
  $("follow-mode").textContent = "polling";
  pollTimer = setInterval(async () => {
    const run = await fetchFollowed();
    if (followed !== id || (run && FINAL.includes(run.state))) {
      clearInterval(pollTimer);
      pollTimer = null;
      if (followed === id) $("follow-mode").textContent = "";
    }
  }, POLL_PERIOD_MS);
}

function render(run) {
  const previous = current;
  current = run;
  $("run-id").textContent = run.id;
  $("progress").value = run.percent_done;
  $("progress").textContent = fmtPercent(run.percent_done);
  $("percent").textContent = fmtPercent(run.percent_done);
  setBadge($("state"), run.state, `state-${run.state}`);
  $("positions").textContent = `${run.positions_done} of ${run.n_positions} positions · preset ${run.preset || "—"}`;
  $("current").textContent = run.current_position === null ? "—" : fmtPosition(run.current_position, run.n_positions);
  if (run.state === "running" && run.eta_s !== null) {
    const end = new Date(Date.now() + run.eta_s * 1000);
    $("eta").textContent = `ETA ${fmtDuration(run.eta_s)} (about ${end.toLocaleTimeString()})`;
  } else if (run.finished_utc) {
    $("eta").textContent = `finished ${fmtTime(run.finished_utc)}`;
  } else {
    $("eta").textContent = "—";
  }
  $("run-exposures").textContent = run.exposures_per_position ?? "—";
  // What the run does now; while it waits for the operator (to switch the lights), what to do.
  $("step").textContent = run.step || "—";
  $("step").className = run.step && run.state === "paused" ? "attention" : "";
  $("last-error").textContent = run.last_error || "none";
  $("last-error").className = run.last_error ? "bad" : "";
  $("pause").disabled = run.state !== "running";
  $("resume").disabled = !["paused", "interrupted", "failed"].includes(run.state);
  $("abort").disabled = !["queued", "running", "paused", "interrupted"].includes(run.state);
  if (!previous || previous.state !== run.state || (FINAL.includes(run.state) && previous.percent_done !== run.percent_done)) {
    refreshRuns();
  }
}

// Positions are counted from 1 on the page, as "position 12 of 12" (the API's
// current_position is the 0-based index in the schedule).
function fmtPosition(index, count) { return `position ${index + 1} of ${count}`; }

async function control(action) {
  const id = followed;
  if (!id) return;
  if (action === "abort" && !window.confirm(`Abort run ${id}? The frames taken are kept.`)) return;
  try {
    const run = await api("POST", `/runs/${encodeURIComponent(id)}/${action}`);
    showMessage(`Run ${id}: ${action} → ${run.state}.`, "info");
    if (action === "resume") follow(id, run); else render(run);
  } catch (err) {
    showMessage(`${action} refused: ${err.message}`);
  }
}

async function stopArm() {
  try {
    await api("POST", "/arm/stop");
    showMessage("Arm stopped. A running run pauses; resume it to re-take the interrupted position.", "info");
    fetchFollowed();
  } catch (err) {
    showMessage(`Stop arm refused: ${err.message}`);
  }
}

// --- the list of runs -------------------------------------------------------------------------
let runsLoading = false;

async function refreshRuns() {
  if (runsLoading) return;
  runsLoading = true;
  try {
    const lab = $("all-rigs").checked ? "&rig=all" : "";
    const [runs, jobs, queue] = await Promise.all(
      [api("GET", `/runs?limit=50${lab}`), api("GET", `/jobs?limit=200${lab}`), api("GET", "/queue")]);
    renderQueue(queue);
    const latestJob = {};
    for (const job of jobs) {
      if (!latestJob[job.run_id] || job.created_utc > latestJob[job.run_id].created_utc) latestJob[job.run_id] = job;
    }
    renderRuns(runs, latestJob);
    renderJobs(jobs);
    showResults(jobs);
    // At first the run in progress, else the newest that is not waiting in the queue.
    const first = runs.find((r) => r.state === "running" || r.state === "paused") || runs.find((r) => r.state !== "queued") || runs[0];
    if (!followed && first) follow(first.id);
  } catch (err) {
    $("runs").replaceChildren(el("tr", {}, el("td", { colSpan: 7, className: "bad", textContent: err.message })));
    $("jobs").replaceChildren(el("tr", {}, el("td", { colSpan: 6, className: "bad", textContent: err.message })));
  } finally {
    runsLoading = false;
  }
}

function renderRuns(runs, latestJob) {
  if (!runs.length) {
    $("runs").replaceChildren(el("tr", {}, el("td", { colSpan: 7, className: "muted", textContent: "no runs yet" })));
    return;
  }
  $("runs").replaceChildren(...runs.map((run) => {
    const view = el("a", { href: `#${run.id}`, className: "run-link", textContent: run.id, title: "show this run" });
    view.addEventListener("click", (e) => { e.preventDefault(); follow(run.id); });
    const state = el("span", { className: `badge state-${run.state}`,
      textContent: run.state === "queued" ? `queued #${run.queue_position}` : run.state });
    // A run removed from the queue ended without starting: it has no file.
    const hasFile = FINAL.includes(run.state) && run.started_utc;
    const file = hasFile
      ? el("a", { href: run.file_url, className: "download", textContent: "download .h5", download: "" })
      : el("span", { className: "muted", textContent:
          run.state === "queued" ? "not yet taken" : FINAL.includes(run.state) ? "none: never started" : "being written" });
    const job = latestJob[run.id];
    // Another rig's run is shown, not changed: its own daemon has its file and takes its jobs.
    const process = el("button", { type: "button", className: "small process", textContent: "process",
      disabled: !hasFile || run.read_only, title: run.read_only ? `rig ${run.rig}'s run: process it from its own daemon` : "" });
    process.addEventListener("click", () => processRun(run.id));
    const jobText = job ? ` ${job.state}${job.state === "running" ? ` ${Math.round(job.progress * 100)} %` : ""}${job.error ? `: ${job.error}` : ""}` : "";
    const row = el("tr", {},
      el("td", {}, view, ...(run.read_only ? [" ", el("span", { className: "badge rig", textContent: run.rig })] : [])),
      el("td", { textContent: run.preset || "—" }),
      el("td", {}, state),
      el("td", { className: "num percent-cell", textContent: `${fmtPercent(run.percent_done)} (${run.positions_done} of ${run.n_positions})` }),
      el("td", { className: "small", textContent: fmtTime(run.created_utc) }),
      el("td", {}, file),
      el("td", {}, process, el("span", { className: "small job-state", textContent: jobText, title: job ? job.id : "" }),
        ...(job ? [" ", resultLinks(job, ["report", "ies", "tm25"])] : [])),
    );
    row.dataset.runId = run.id;
    return row;
  }));
  markSelected();
}

// --- the queue of runs -----------------------------------------------------------------------
// The runs waiting, the next first: each moves up or down (PUT /queue with the new order) or
// leaves the queue (DELETE /queue/{id}); a held queue says why, and starts again on request.
let queued = [];

function renderQueue(queue) {
  queued = queue.runs.map((run) => run.id);
  const n = queue.runs.length;
  $("queue-summary").textContent = n ? `${plural(n, "run")} waiting` : "no run waiting";
  $("queue-held").hidden = !queue.held;
  $("queue-held").textContent = queue.held ? `Held: ${queue.held}` : "";
  $("queue-start").hidden = !(queue.held && n);
  $("queue").replaceChildren(...queue.runs.map((run, k) => {
    const up = el("button", { type: "button", className: "small up", textContent: "↑", title: "start it earlier", disabled: k === 0 });
    const down = el("button", { type: "button", className: "small down", textContent: "↓", title: "start it later", disabled: k === n - 1 });
    const remove = el("button", { type: "button", className: "small remove danger", textContent: "remove", title: "take it out of the queue" });
    up.addEventListener("click", () => moveQueued(run.id, -1));
    down.addEventListener("click", () => moveQueued(run.id, 1));
    remove.addEventListener("click", () => removeQueued(run.id));
    const item = el("li", {}, el("span", { className: "queue-run" },
      el("span", { className: "mono small", textContent: run.id }),
      el("span", { className: "small", textContent: `${run.preset || "—"}, ${plural(run.n_positions, "position")}` }),
      up, down, remove));
    item.dataset.runId = run.id;
    return item;
  }));
}

async function queueAction(method, path, body, said) {
  try {
    const answer = await api(method, path, body);
    showMessage(said(answer), "info");
  } catch (err) {
    showMessage(`Queue: ${err.message}`);
  }
  refreshRuns();
}

function moveQueued(id, step) {
  const order = queued.slice();
  const k = order.indexOf(id);
  if (k < 0 || k + step < 0 || k + step >= order.length) return;
  [order[k], order[k + step]] = [order[k + step], order[k]];
  queueAction("PUT", "/queue", { run_ids: order }, (q) => `Queue: ${q.runs.map((r) => r.id).join(", ")}.`);
}

function removeQueued(id) {
  queueAction("DELETE", `/queue/${encodeURIComponent(id)}`, undefined, (run) => `Run ${run.id} removed from the queue.`);
}

function startQueue() {
  queueAction("POST", "/queue/start", undefined, (q) =>
    q.held ? `The queue is held again: ${q.held}` : "The queue runs on: its next run starts when the rig is free.");
}

// --- processing jobs ------------------------------------------------------------------------
// The result files a job recorded, as the daemon serves them (GET /jobs/{id}/artifacts/{kind}).
const ARTIFACT_LABELS = {
  report: "report", ies: "IES", tm25: "ray file (TM-25)", ldt: "LDT", light_model: "light model (JSON)", results: "results (.zip)",
};

function resultLinks(job, kinds = Object.keys(ARTIFACT_LABELS)) {
  const span = el("span", { className: "results small" });
  for (const kind of kinds) {
    const url = (job.artifacts || {})[kind];
    if (!url) continue;
    const link = el("a", { href: url, className: `artifact artifact-${kind}`, textContent: ARTIFACT_LABELS[kind] || kind });
    if (kind === "report") link.target = "_blank"; else link.download = "";
    span.append(link);
  }
  return span;
}

// The figures of the report of the followed run's latest completed job: the light's polar
// plots and the other figures the report draws, without opening it.
async function showResults(jobs) {
  const job = jobs.filter((j) => j.run_id === followed && j.state === "complete" && (j.artifacts || {}).report)
    .sort((a, b) => (a.created_utc < b.created_utc ? 1 : -1))[0];
  const key = job ? job.id : `none:${followed}`;
  if (key === resultsKey) return;
  resultsKey = key;
  $("results-of").textContent = job ? `of run ${job.run_id}, job ${job.id}` : "of the run shown, once a job completes";
  if (!job) {
    $("figures").replaceChildren(el("p", { className: "muted small", textContent: "no completed job for this run yet" }));
    return;
  }
  try {
    const [figures, photometry] = await Promise.all([
      api("GET", `/jobs/${encodeURIComponent(job.id)}/figures`),
      api("GET", `/jobs/${encodeURIComponent(job.id)}/photometry`).catch(() => null),  // an older light model: none
    ]);
    if (resultsKey !== key) return;
    await session;  // the images read with the session cookie
    $("figures").replaceChildren(...(photometry ? [photometryTable(photometry)] : []),
      ...figures.map((f) => el("figure", { className: "result-figure" },
      el("a", { href: f.url, target: "_blank", title: "open the figure alone" }, el("img", { src: f.url, alt: f.alt, loading: "lazy" })),
      el("figcaption", { className: "small", textContent: f.caption }))),
    el("p", { className: "small" }, resultLinks(job)));
  } catch (err) {
    resultsKey = null;
    $("figures").replaceChildren(el("p", { className: "bad small", textContent: `cannot read the report's figures: ${err.message}` }));
  }
}

// The whole light's photometric summary, as a lighting engineer reads it first.
function photometryTable(p) {
  const num = (x, digits = 3) => Number(x).toPrecision(digits);
  const planes = (angles) => Object.entries(angles).map(([plane, deg]) => `${num(deg)}° (${plane})`).join(", ");
  const beyond = (flag) => (flag ? " (beyond the measured θ: extrapolated)" : "");
  const rows = [
    ["total flux", `${num(p.total_flux, 4)} ${p.flux_units}`],
    ["beyond the measured θ", `${num(p.flux_beyond_measured_percent)} % of the flux (θ measured to ${num(p.measured_theta_max_deg)}°; the files hold ${p.extrapolation === "none" ? "the measured range only" : "the fits' extrapolation"})`],
    ["peak intensity", `${num(p.peak_intensity, 4)} ${p.intensity_units} at γ ${num(p.peak_gamma_deg)}°, C ${num(p.peak_c_deg)}°`],
    ["beam angle (50 %)", planes(p.beam_angle_deg) + beyond(p.beam_angle_beyond_measured)],
    ["field angle (10 %)", planes(p.field_angle_deg) + beyond(p.field_angle_beyond_measured)],
  ];
  if (p.near_field_difference_percent != null) {
    rows.push([`at ${num(p.near_field_distance_m * 100)} cm`, `the sources against one point source: ${num(p.near_field_difference_percent)} % of the peak illuminance at most`]);
  }
  return el("table", { id: "photometry", className: "photometry small" },
    el("caption", { textContent: "The whole light" }),
    ...rows.map(([name, value]) => el("tr", {}, el("th", { textContent: name }), el("td", { textContent: value }))));
}

function renderJobs(jobs) {
  if (!jobs.length) {
    $("jobs").replaceChildren(el("tr", {}, el("td", { colSpan: 6, className: "muted", textContent: "no processing jobs yet" })));
    return;
  }
  $("jobs").replaceChildren(...jobs.map((job) => {
    const run = el("a", { href: `#${job.run_id}`, className: "run-link", textContent: job.run_id, title: "show this run" });
    run.addEventListener("click", (e) => { e.preventDefault(); follow(job.run_id); });
    const progress = el("progress", { className: "job-progress", max: 100, value: Math.round(job.progress * 100) });
    const note = job.error || job.message || "";
    const row = el("tr", {},
      el("td", { className: "mono small", textContent: job.id, title: `steps ${job.steps}${describeOptions(job.options)}${job.claimed_by ? `, worker ${job.claimed_by}` : ""}` }),
      el("td", {}, run),
      el("td", {}, el("span", { className: `badge state-${job.state} job-badge`, textContent: job.state })),
      el("td", { className: "num" }, progress, ` ${Math.round(job.progress * 100)} %`),
      el("td", { className: `small job-note${job.error ? " bad" : ""}`, textContent: note }),
      el("td", {}, resultLinks(job)),
    );
    row.dataset.jobId = job.id;
    return row;
  }));
}

function markSelected() {
  for (const row of $("runs").querySelectorAll("tr[data-run-id]")) {
    row.classList.toggle("selected", row.dataset.runId === followed);
  }
}

// The options of the next job (JobRequest): only those that differ from the worker's defaults.
function jobRequest() {
  const body = { steps: "hdr,sources" };
  if ($("fit-aperture").value !== "auto") body.fit_aperture = $("fit-aperture").value;
  if ($("fit-sensor-distance").checked) body.fit_sensor_distance = "always";
  if ($("fit-model").value !== "gaussian") body.fit = $("fit-model").value;
  if ($("extrapolation").value !== "fitted") body.extrapolation = $("extrapolation").value;
  if ($("ignore-corrupt").checked) body.ignore_corrupt = true;
  return body;
}

function describeOptions(options) {
  const parts = [];
  const said = { always: "aperture fitted", never: "aperture as described", auto: "aperture fitted where searched" };
  if (options && options.fit_aperture) parts.push(said[options.fit_aperture] || `aperture ${options.fit_aperture}`);
  if (options && options.fit_sensor_distance && options.fit_sensor_distance !== "never") parts.push("sensor distance fitted");
  if (options && options.fit) parts.push(`${options.fit} fits`);
  if (options && options.extrapolation) {
    parts.push(options.extrapolation === "none" ? "measured range only" : "fitted extrapolation");
  }
  if (options && options.ignore_corrupt) parts.push("positions with a corrupt frame skipped");
  return parts.length ? `, ${parts.join(", ")}` : "";
}

async function processRun(id) {
  try {
    const job = await api("POST", `/runs/${encodeURIComponent(id)}/process`, jobRequest());
    showMessage(`Job ${job.id} queued for run ${id} (steps ${job.steps}${describeOptions(job.options)}).`, "info");
    refreshRuns();
  } catch (err) {
    showMessage(`Process refused: ${err.message}`);
  }
}

// --- wiring ---------------------------------------------------------------------------------
function init() {
  const token = $("token");
  token.value = localStorage.getItem(TOKEN_KEY) || "";
  token.addEventListener("input", () => {
    localStorage.setItem(TOKEN_KEY, token.value.trim());
    openSession();
  });
  $("start-form").addEventListener("submit", startRun);
  $("preset").addEventListener("change", showPresetInfo);
  $("all-rigs").addEventListener("change", refreshRuns);
  for (const radio of document.querySelectorAll("input[name=bracket]")) radio.addEventListener("change", showBracketFields);
  $("pause").addEventListener("click", () => control("pause"));
  $("resume").addEventListener("click", () => control("resume"));
  $("abort").addEventListener("click", () => control("abort"));
  $("stop-arm").addEventListener("click", stopArm);
  $("queue-start").addEventListener("click", startQueue);
  $("count").addEventListener("input", showPresetInfo);
  initAlign();
  showBracketFields();
  refreshStatus();
  if (token.value) openSession(); else { loadPresets(); refreshRuns(); }
  setInterval(refreshRuns, STATUS_PERIOD_MS);
}

document.addEventListener("DOMContentLoaded", init);
