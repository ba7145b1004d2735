// The alignment card (the latest frame, zoomable, with the ball's expected outline and a
// histogram; the test shot; jog and home) and the daemon's log. Uses app.js's api, $, el,
// showMessage and session.
"use strict";

const FRAME_PERIOD_MS = 1000;
const LOG_PERIOD_MS = 2000;
const MAX_ZOOM = 32;
const CHANNEL_COLOURS = { R: "#d43c3c", G: "#2e9e48", B: "#3c6fd4" };

// --- the viewer: the frame on a canvas, zoomed and panned ---------------------------------
const view = { image: null, summary: null, serial: null, loading: null, scale: 1, ox: 0, oy: 0, fitted: false };

function viewerCanvas() {
  const canvas = $("viewer");
  const width = Math.max(200, Math.round(canvas.clientWidth));
  const height = Math.round(width * 0.62);
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  return canvas;
}

function fitView() {
  const canvas = viewerCanvas();
  if (!view.image) return;
  const w = view.image.naturalWidth, h = view.image.naturalHeight;
  view.scale = Math.min(canvas.width / w, canvas.height / h);
  view.ox = (canvas.width - w * view.scale) / 2;
  view.oy = (canvas.height - h * view.scale) / 2;
  drawView();
}

// Zoom by ``factor`` keeping the frame's point under (cx, cy) (canvas pixels) where it is.
function zoomAt(factor, cx, cy) {
  if (!view.image) return;
  const canvas = viewerCanvas();
  if (cx === undefined) { cx = canvas.width / 2; cy = canvas.height / 2; }
  const fit = Math.min(canvas.width / view.image.naturalWidth, canvas.height / view.image.naturalHeight);
  const scale = Math.min(MAX_ZOOM, Math.max(fit / 2, view.scale * factor));
  view.ox = cx - (cx - view.ox) * (scale / view.scale);
  view.oy = cy - (cy - view.oy) * (scale / view.scale);
  view.scale = scale;
  drawView();
}

function drawView() {
  const canvas = viewerCanvas();
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#000";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!view.image) return;
  const w = view.image.naturalWidth, h = view.image.naturalHeight;
  ctx.imageSmoothingEnabled = view.scale < 1;  // zoomed in: the sensor's pixels, square
  ctx.drawImage(view.image, view.ox, view.oy, w * view.scale, h * view.scale);
  const outline = view.summary && view.summary.ball_outline_px;
  if (outline && $("show-outline").checked) {
    // A pixel (col, row) has its centre at (col + 0.5, row + 0.5) of the image drawn.
    ctx.beginPath();
    outline.forEach(([c, r], k) => {
      const x = view.ox + (c + 0.5) * view.scale, y = view.oy + (r + 0.5) * view.scale;
      if (k === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.closePath();
    ctx.lineWidth = 1.5;
    ctx.setLineDash([6, 4]);
    ctx.strokeStyle = "#00e5ff";
    ctx.stroke();
    ctx.setLineDash([]);
  }
  $("zoom-level").textContent = `zoom ${view.scale >= 1 ? view.scale.toFixed(1) : view.scale.toFixed(2)}×`;
}

function wireViewer() {
  const canvas = $("viewer");
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const box = canvas.getBoundingClientRect();
    const sx = canvas.width / box.width;
    zoomAt(e.deltaY < 0 ? 1.25 : 0.8, (e.clientX - box.left) * sx, (e.clientY - box.top) * sx);
  }, { passive: false });
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, ox: view.ox, oy: view.oy };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    const box = canvas.getBoundingClientRect();
    const sx = canvas.width / box.width;
    if (drag) {
      view.ox = drag.ox + (e.clientX - drag.x) * sx;
      view.oy = drag.oy + (e.clientY - drag.y) * sx;
      drawView();
    }
    if (view.image) {
      const col = Math.floor(((e.clientX - box.left) * sx - view.ox) / view.scale);
      const row = Math.floor(((e.clientY - box.top) * sx - view.oy) / view.scale);
      const inside = col >= 0 && row >= 0 && col < view.image.naturalWidth && row < view.image.naturalHeight;
      $("cursor-px").textContent = inside ? `col ${col}, row ${row}` : "";
    }
  });
  const end = () => { drag = null; };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  canvas.addEventListener("dblclick", fitView);
  $("zoom-in").addEventListener("click", () => zoomAt(1.5));
  $("zoom-out").addEventListener("click", () => zoomAt(1 / 1.5));
  $("zoom-fit").addEventListener("click", fitView);
  $("zoom-1").addEventListener("click", () => zoomAt(1 / view.scale));
  $("show-outline").addEventListener("change", drawView);
  window.addEventListener("resize", () => (view.fitted ? fitView() : drawView()));
}

// --- the frame's figures beside it ---------------------------------------------------------
function fmtExposure(s) {
  if (s >= 1) return `${s.toPrecision(3).replace(/\.?0+$/, "")} s`;
  return `1/${Math.round(1 / s)} s (${s.toPrecision(3).replace(/\.?0+$/, "")} s)`;
}

function showSummary(s) {
  $("frame-exposure").textContent = fmtExposure(s.exposure_s);
  $("frame-peak").textContent = `${Math.round(s.peak_dn)} DN of ${Math.round(s.white_level_dn - s.black_level_dn)} above black`;
  const share = s.saturated_share * 100;
  $("frame-saturated").textContent = s.saturated_pixels
    ? `${s.saturated_pixels} photosites (${share < 0.01 ? share.toExponential(1) : share.toFixed(2)} %)`
    : "none";
  $("frame-saturated").className = s.saturated_pixels ? "bad" : "good";
  $("frame-scale").textContent = `log: black at ${s.scale.low_dn} DN above black, white at ${Math.round(s.scale.high_dn)} DN`;
  const what = s.run_id ? `run ${s.run_id}` : "test shot";
  $("frame-caption").textContent =
    `${what}, ${s.width} × ${s.height}, exposure ${fmtExposure(s.exposure_s)}, taken ${new Date(s.captured_utc).toLocaleTimeString()}`
    + (s.ball_outline_px ? "" : " (the rig's sensor differs from the frame's: no outline)");
  drawHistogram(s);
}

// Each channel's counts on log-spaced bins (x: DN above black, log; y: photosites, log).
function drawHistogram(s) {
  const canvas = $("histogram");
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height, pad = 18;
  ctx.clearRect(0, 0, W, H);
  ctx.fillStyle = "#fafbfc";
  ctx.fillRect(0, 0, W, H);
  const edges = s.histogram.edges_dn;
  const lx = (v) => pad + (W - 2 * pad) * Math.log10(v) / Math.log10(edges[edges.length - 1]);
  let top = 1;
  for (const ch of Object.values(s.histogram.channels)) top = Math.max(top, ...ch.counts);
  const ly = (n) => H - pad - (H - 2 * pad) * (n > 0 ? Math.log10(n + 1) / Math.log10(top + 1) : 0);
  ctx.strokeStyle = "#c4cad1";
  ctx.fillStyle = "#68717d";
  ctx.font = "10px sans-serif";
  for (let d = 1; d <= edges[edges.length - 1]; d *= 10) {
    ctx.beginPath(); ctx.moveTo(lx(d), pad); ctx.lineTo(lx(d), H - pad); ctx.stroke();
    ctx.fillText(`${d}`, lx(d) + 2, H - 5);
  }
  ctx.fillText("DN above black", W - 90, 12);
  const sat = 0.98 * edges[edges.length - 1];
  ctx.strokeStyle = "#e000e0";
  ctx.beginPath(); ctx.moveTo(lx(sat), pad); ctx.lineTo(lx(sat), H - pad); ctx.stroke();
  for (const [name, ch] of Object.entries(s.histogram.channels)) {
    ctx.strokeStyle = CHANNEL_COLOURS[name] || "#333";
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    ch.counts.forEach((n, k) => {
      const x0 = lx(edges[k]), x1 = lx(edges[k + 1]), y = ly(n);
      if (k === 0) ctx.moveTo(x0, y); else ctx.lineTo(x0, y);
      ctx.lineTo(x1, y);
    });
    ctx.stroke();
    ctx.lineWidth = 1;
  }
}

// --- following the latest frame ------------------------------------------------------------
async function refreshFrame() {
  try {
    const summary = await api("GET", "/preview/frame", undefined, [404]);
    if (summary && summary.serial !== undefined && summary.serial !== view.serial && view.loading !== summary.serial) {
      await loadFrame(summary);
    }
  } catch { /* the status line and the runs say what is wrong */ }
}

async function loadFrame(summary) {
  view.loading = summary.serial;
  await session;  // the image reads with the session cookie
  const image = new Image();
  image.decoding = "async";
  const loaded = new Promise((resolve, reject) => { image.onload = resolve; image.onerror = reject; });
  image.src = `/preview/frame.png?serial=${summary.serial}`;
  try {
    await loaded;
  } catch {
    view.loading = null;
    return;
  }
  const first = !view.image || view.image.naturalWidth !== image.naturalWidth;
  view.image = image;
  view.summary = summary;
  view.serial = summary.serial;
  view.loading = null;
  $("viewer").dataset.serial = String(summary.serial);
  showSummary(summary);
  if (first) { view.fitted = true; fitView(); } else drawView();
}

// --- the test shot ---------------------------------------------------------------------------
async function testShot() {
  const button = $("test-shot");
  button.disabled = true;
  try {
    const text = $("shot-exposures").value.trim();
    const body = text ? { exposures_s: parseExposures(text) } : {};
    const shot = await api("POST", "/preview/shot", body);
    $("shot-frames").replaceChildren(
      el("tr", {}, el("th", { textContent: "exposure" }), el("th", { textContent: "peak DN" }), el("th", { textContent: "saturated" })),
      ...shot.frames.map((f) => el("tr", {},
        el("td", { textContent: fmtExposure(f.exposure_s) }),
        el("td", { className: "num", textContent: Math.round(f.peak_dn) }),
        el("td", { className: f.saturated_pixels ? "num bad" : "num", textContent: f.saturated_pixels }))));
    showMessage(`Test shot: ${shot.frames.length} frames; the preview shows the last (${fmtExposure(shot.frames[shot.frames.length - 1].exposure_s)}).`, "info");
    await refreshFrame();
  } catch (err) {
    showMessage(`Test shot refused: ${err.message}`);
  } finally {
    button.disabled = false;
  }
}

// --- jog and home ------------------------------------------------------------------------------
const JOG_AXES = [["x", "mm"], ["y", "mm"], ["z", "mm"], ["rx", "deg"], ["ry", "deg"], ["rz", "deg"]];

function buildJog() {
  $("jog").replaceChildren(...JOG_AXES.map(([axis, unit]) => {
    const minus = el("button", { type: "button", className: "small jog-button", textContent: `${axis} −`, title: `jog ${axis} by minus the step` });
    const plus = el("button", { type: "button", className: "small jog-button", textContent: `${axis} +`, title: `jog ${axis} by the step` });
    minus.dataset.axis = plus.dataset.axis = axis;
    minus.dataset.sign = "-1";
    plus.dataset.sign = "1";
    minus.addEventListener("click", () => jog(axis, -1, unit));
    plus.addEventListener("click", () => jog(axis, 1, unit));
    return el("span", { className: "jog-axis" }, minus, plus);
  }));
}

async function armMove(path, body, what) {
  const buttons = [...document.querySelectorAll(".jog-button"), $("home")];
  for (const b of buttons) b.disabled = true;
  try {
    const moved = await api("POST", path, body);
    const p = moved.position;
    const two = (v) => (Math.round(v * 100) / 100 + 0).toFixed(2);  // + 0: no "-0.00"
    showMessage(`${moved.moved}: the arm is at x ${two(p.x * 1000)} y ${two(p.y * 1000)} z ${two(p.z * 1000)} mm, `
      + `rx ${two(p.rx)} ry ${two(p.ry)} rz ${two(p.rz)} °.`, "info", "arm");
  } catch (err) {
    showMessage(`${what} refused: ${err.message}`, "error", "arm");
  } finally {
    for (const b of buttons) b.disabled = false;
  }
}

function jog(axis, sign, unit) {
  const step = Number($(unit === "mm" ? "jog-mm" : "jog-deg").value);
  armMove("/arm/jog", { axis, step: sign * step }, `Jog ${axis}`);
}

// --- the daemon's log ---------------------------------------------------------------------------
let logSeq = 0;

async function refreshLog() {
  try {
    const lines = await api("GET", `/log?after=${logSeq}`);
    if (!lines || !lines.length) return;
    const box = $("log");
    const atEnd = box.scrollTop + box.clientHeight >= box.scrollHeight - 4;
    for (const line of lines) {
      const time = new Date(line.time_utc).toLocaleTimeString();
      box.append(el("span", { className: `log-line log-${line.level.toLowerCase()}`, textContent: `${time} ${line.level.padEnd(7)} ${line.message}\n` }));
      logSeq = Math.max(logSeq, line.seq);
    }
    while (box.childNodes.length > 500) box.firstChild.remove();
    if (atEnd) box.scrollTop = box.scrollHeight;
  } catch { /* a token being typed: the next poll catches up */ }
}

function initAlign() {
  wireViewer();
  buildJog();
  $("test-shot").addEventListener("click", testShot);
  $("home").addEventListener("click", () => armMove("/arm/home", undefined, "Home"));
  drawView();
  const every = (f, ms) => { const tick = async () => { try { await f(); } finally { setTimeout(tick, ms); } }; tick(); };
  every(refreshFrame, FRAME_PERIOD_MS);
  every(refreshLog, LOG_PERIOD_MS);
}
