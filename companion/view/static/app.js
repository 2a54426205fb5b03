// companion view: follows /ws (health as JSON text, the preview as binary JPEG) and sends control
// requests to /api/control. Plain JS, no library, nothing from outside this server.
"use strict";

const REGIONS = ["up_left", "up", "up_right", "left", "center", "right", "down_left", "down", "down_right"];
const KIND_COLOUR = { clear: "#2e9e44", avoid: "#e89a00", brake: "#d93025" };
const STATE_COLOUR = {
  engaged: "#2e9e44", override: "#2e9e44", engaging: "#e89a00", paused: "#e89a00",
  degraded: "#d93025", failsafe: "#d93025", passive: "#5a6675", disengaged: "#5a6675", finished: "#5a6675",
};
const $ = (id) => document.getElementById(id);
const TOKEN_KEY = "companion-view-token";

// The view's token arrives once in the address `companion view` printed (?token=...). Kept in this
// tab's sessionStorage and sent as "Authorization: Bearer" with each command; dropped from the address
// bar and the history. The server never puts it in a page.
function takeToken() {
  const url = new URL(location.href);
  const given = url.searchParams.get("token");
  if (given) {
    try { sessionStorage.setItem(TOKEN_KEY, given); } catch (err) { view.token = given; }
    url.searchParams.delete("token");
    history.replaceState(null, "", url.pathname + url.search + url.hash);
  }
  try { return sessionStorage.getItem(TOKEN_KEY) || view.token || null; } catch (err) { return view.token || null; }
}

const view = {
  ws: null, lastMessageMs: 0, retryMs: 500, timeline: [], windowS: 60, thresholds: null,
  control: false, health: null, previewUrl: null, previewCount: 0, viewStatus: null, token: null,
};

function fmt(x, digits = 2, unit = "") {
  return (typeof x === "number" && isFinite(x)) ? x.toFixed(digits) + unit : "–";
}
function signed(x, digits = 2) {
  if (typeof x !== "number" || !isFinite(x)) return "–";
  const text = Math.abs(x).toFixed(digits);
  return (Number(text) === 0 ? " " : x > 0 ? "+" : "−") + text;
}

// ------------------------------------------------------------------------------------------ regions
function buildRegions() {
  const box = $("regions");
  for (const name of REGIONS) {
    const cell = document.createElement("div");
    cell.className = "region";
    cell.innerHTML = '<div class="name"></div><div class="value">–</div>' +
      '<div class="bar"><div class="fill"></div><div class="mark near"></div><div class="mark far"></div></div>';
    cell.querySelector(".name").textContent = name.replace("_", " ");
    cell.dataset.region = name;
    cell.dataset.depth = "";
    box.appendChild(cell);
  }
}

function scaleMaxM() {
  const far = view.thresholds ? view.thresholds.far_m : 2.25;
  return Math.max(5, Math.ceil(far * 2));
}

function updateRegions(h) {
  const r = (h && h.regions_m) || {};
  const near = view.thresholds ? view.thresholds.near_m : null;
  const far = view.thresholds ? view.thresholds.far_m : null;
  const max = scaleMaxM();
  for (const cell of $("regions").children) {
    const d = r[cell.dataset.region];
    const known = typeof d === "number" && isFinite(d);
    cell.dataset.depth = known ? String(d) : "unknown";
    cell.querySelector(".value").textContent = known ? d.toFixed(2) + " m" : "? (near)";
    const fill = cell.querySelector(".fill");
    fill.style.width = (known ? Math.min(d, max) / max * 100 : 100) + "%";
    let cls = "unknown";
    if (known) cls = (near !== null && d <= near) ? "near" : (far !== null && d >= far) ? "far" : "mid";
    fill.className = "fill " + cls;
    const nm = cell.querySelector(".mark.near"), fm = cell.querySelector(".mark.far");
    nm.hidden = fm.hidden = near === null;
    if (near !== null) {
      nm.style.left = (near / max * 100) + "%";
      fm.style.left = (far / max * 100) + "%";
    }
  }
  $("thresholds").textContent = view.thresholds
    ? `near ≤ ${fmt(near)} m, far ≥ ${fmt(far)} m, bars to ${max} m` : "near – / far –";
}

// ------------------------------------------------------------------------------------------ command
function drawStick(h) {
  const c = $("stick"), g = c.getContext("2d");
  const w = c.width, r = w / 2 - 8;
  g.clearRect(0, 0, w, w);
  g.strokeStyle = "#c7ccd3"; g.lineWidth = 1;
  g.beginPath(); g.arc(w / 2, w / 2, r, 0, 2 * Math.PI); g.stroke();
  g.beginPath(); g.moveTo(w / 2, 8); g.lineTo(w / 2, w - 8); g.moveTo(8, w / 2); g.lineTo(w - 8, w / 2); g.stroke();
  g.fillStyle = "#5c6470"; g.font = "10px sans-serif";
  g.fillText("up", w / 2 + 3, 16); g.fillText("right", w - 32, w / 2 - 4);
  const kind = h && h.decision ? h.decision.kind : null;
  if (!h || typeof h.yaw !== "number" || typeof h.pitch !== "number") return;
  const x = w / 2 + h.yaw * r, y = w / 2 - h.pitch * r;
  g.strokeStyle = g.fillStyle = KIND_COLOUR[kind] || "#8a8f98"; g.lineWidth = 3;
  g.beginPath(); g.moveTo(w / 2, w / 2); g.lineTo(x, y); g.stroke();
  g.beginPath(); g.arc(x, y, kind === "brake" ? 9 : 6, 0, 2 * Math.PI); g.fill();
}

// ------------------------------------------------------------------------------------------ timeline
function timelinePoint(h) {
  const d = h.decision || {}, sp = h.setpoint || {}, r = h.regions_m || {};
  const num = (x) => (typeof x === "number" && isFinite(x)) ? x : null;
  return { t: num(h.time_s), state: h.state, kind: d.kind || null, yaw: num(h.yaw), pitch: num(h.pitch),
           fwd: num(sp.forward_m_s), yaw_rate: num(sp.yaw_rate_deg_s), center: num(r.center) };
}

function addTimeline(p) {
  const tl = view.timeline;
  if (p.t === null) return;
  if (tl.length && p.t < tl[tl.length - 1].t) tl.length = 0; // a restarted service
  tl.push(p);
  while (tl.length && p.t - tl[0].t > view.windowS) tl.shift();
}

function drawTimeline() {
  const c = $("timeline"), dpr = window.devicePixelRatio || 1;
  const cssW = c.clientWidth || 960, cssH = c.clientHeight || 170;
  if (c.width !== Math.round(cssW * dpr)) { c.width = Math.round(cssW * dpr); c.height = Math.round(cssH * dpr); }
  const g = c.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, cssW, cssH);
  const tl = view.timeline, left = 34, right = cssW - 6, top = 4, band = 12;
  const plotTop = top + 2 * band + 8, plotBottom = cssH - 16;
  const tEnd = tl.length ? tl[tl.length - 1].t : 0, tStart = tEnd - view.windowS;
  const X = (t) => left + (t - tStart) / view.windowS * (right - left);
  g.font = "10px sans-serif"; g.fillStyle = "#5c6470";
  g.fillText("state", 0, top + 10); g.fillText("decision", 0, top + band + 10);
  // grid: every 10 s
  g.strokeStyle = "#e3e6ea"; g.lineWidth = 1;
  for (let s = 0; s <= view.windowS; s += 10) {
    const x = X(tStart + s);
    g.beginPath(); g.moveTo(x, plotTop); g.lineTo(x, plotBottom); g.stroke();
    g.fillText(s === view.windowS ? "now" : `-${view.windowS - s}s`, x - 10, cssH - 4);
  }
  const mid = (plotTop + plotBottom) / 2, half = (plotBottom - plotTop) / 2;
  g.strokeStyle = "#b9bfc7"; g.beginPath(); g.moveTo(left, mid); g.lineTo(right, mid); g.stroke();
  g.fillText("+1", 14, plotTop + 8); g.fillText("-1", 16, plotBottom);
  for (let i = 0; i < tl.length; i++) {
    const p = tl[i], x0 = X(p.t), x1 = i + 1 < tl.length ? X(tl[i + 1].t) : right;
    g.fillStyle = STATE_COLOUR[p.state] || "#8a8f98"; g.fillRect(x0, top, Math.max(1, x1 - x0), band - 2);
    if (p.kind) { g.fillStyle = KIND_COLOUR[p.kind] || "#8a8f98"; g.fillRect(x0, top + band, Math.max(1, x1 - x0), band - 2); }
  }
  // state changes: a tick and the new state's name
  g.fillStyle = "#15181d";
  let lastLabelX = -1e9;
  for (let i = 1; i < tl.length; i++) {
    if (tl[i].state !== tl[i - 1].state) {
      const x = X(tl[i].t);
      g.fillRect(x, top, 1, plotBottom - top);
      if (x - lastLabelX > 60) {
        const w = g.measureText(tl[i].state).width;
        g.fillText(tl[i].state, x + 2 + w > right ? x - w - 2 : x + 2, plotTop + 10);
        lastLabelX = x;
      }
    }
  }
  const maxFwd = Math.max(0.5, ...tl.map((p) => Math.abs(p.fwd || 0)));
  const line = (key, colour, scale) => {
    g.strokeStyle = colour; g.lineWidth = 1.6; g.beginPath();
    let pen = false;
    for (const p of tl) {
      const v = p[key];
      if (v === null || v === undefined) { pen = false; continue; }
      const y = mid - Math.max(-1, Math.min(1, v / scale)) * half;
      if (pen) g.lineTo(X(p.t), y); else { g.moveTo(X(p.t), y); pen = true; }
    }
    g.stroke();
  };
  line("fwd", "#111", maxFwd);
  line("yaw", "#1f5fd1", 1);
  line("pitch", "#9b2fc9", 1);
}

// ------------------------------------------------------------------------------------------ health
function setText(id, text) { $(id).textContent = text; }

function applyHealth(h) {
  view.health = h;
  if (!h) return;
  const st = $("state");
  st.textContent = h.state || "?";
  st.dataset.state = h.state || "";
  st.dataset.seq = String(h.seq);
  st.className = "state state-" + (h.state || "unknown");
  setText("reason", h.reason || "");
  // The rig check's lines (health's rig), in the words process/eval/run print: shown while the rig
  // cannot measure down to where "near" is full, or measures badly.
  const rig = $("rig"), rigLines = (h.rig && Array.isArray(h.rig.lines)) ? h.rig.lines : [];
  rig.hidden = rigLines.length === 0;
  if (rigLines.length) rig.textContent = rigLines.join("\n");
  updateRegions(h);
  drawStick(h);
  const d = h.decision || {};
  setText("decision", d.kind ? d.kind.toUpperCase() + (typeof d.speed_fraction === "number" ? ` (speed ${fmt(d.speed_fraction)})` : "") : "–");
  // the pilot's words; the controller's reason (rules, memberships) on hover, for tuning
  setText("decision-reason", d.words || d.reason || "");
  $("decision-reason").title = d.words ? (d.reason || "") : "";
  setText("yaw", signed(h.yaw) + (typeof h.yaw === "number" ? (h.yaw > 0.02 ? "  right" : h.yaw < -0.02 ? "  left" : "") : ""));
  setText("pitch", signed(h.pitch) + (typeof h.pitch === "number" ? (h.pitch > 0.02 ? "  up" : h.pitch < -0.02 ? "  down" : "") : ""));
  const sp = h.setpoint || {};
  setText("sp-forward", fmt(sp.forward_m_s, 2, " m/s"));
  setText("sp-right", fmt(sp.right_m_s, 2, " m/s"));
  setText("sp-down", fmt(sp.down_m_s, 2, " m/s"));
  setText("sp-yaw-rate", fmt(sp.yaw_rate_deg_s, 1, " °/s"));
  setText("fps", fmt(h.fps, 1));
  setText("frame-age", fmt(h.frame_age_ms, 0, " ms"));
  const lat = h.frame_to_setpoint_ms || {};
  setText("latency", lat.last === null || lat.last === undefined ? "– (not engaged)"
    : `${fmt(lat.last, 1)} ms (median ${fmt(lat.median, 1)}, p99 ${fmt(lat.p99, 1)})`);
  setText("dropped", `${h.dropped_frames ?? "–"} of ${h.camera && h.camera.frames !== undefined ? h.camera.frames : "–"}`);
  const cam = h.camera || {};
  setText("camera", `${cam.source ?? "–"} ${cam.status ?? ""} ${fmt(cam.fps, 0, " fps")}` + (cam.reconnects ? `, ${cam.reconnects} reconnects` : ""));
  const v = h.vehicle || {};
  setText("vehicle", `${v.link ?? "–"}, ${v.flight_mode ?? "–"}, ${v.armed ? "armed" : "disarmed"}`);
  const p = h.planner;
  setText("planner", p ? `${p.mode}: ${p.reason}` + (p.limited_by && p.limited_by.length ? `; limited by ${p.limited_by.join(", ")}` : "")
    : "– (not flying)");
  setText("last-error", h.last_error || "none");
  $("last-error").className = h.last_error ? "err" : "";
  updateButtons();
}

function applyViewStatus(s) {
  view.viewStatus = s;
  if (!s) return;
  const banner = $("banner");
  if (s.health_age_s === null) { banner.hidden = false; banner.textContent = `No running service: no health message from ${s.health_endpoint || "its health socket"} yet. Start it (companion run); this page follows it once it runs.`; }
  else if (s.health_age_s > 2) { banner.hidden = false; banner.textContent = `No health message from the service for ${s.health_age_s.toFixed(0)} s: the service may have stopped.`; }
  else banner.hidden = true;
  const age = s.preview_age_s;
  const failing = view.health && view.health.preview ? view.health.preview.failing : null;
  let info = age === null ? "no picture yet (the service draws one only while someone watches; the first takes a few seconds)"
    : `${fmt(s.preview_fps, 1)} pictures/s, newest ${fmt(age * 1000, 0)} ms ago` + (s.preview_encode_ms ? `, drawn in ${fmt(s.preview_encode_ms, 1)} ms` : "");
  if (failing) info = `no new picture: ${failing}` + (age === null ? "" : ` (the last one ${fmt(age, 0)} s ago)`);
  setText("preview-info", info);
  $("preview-info").className = failing ? "err" : "";
}

// ------------------------------------------------------------------------------------------ preview
function showPreview(data) {
  const url = URL.createObjectURL(new Blob([data], { type: "image/jpeg" }));
  const img = $("preview"), old = view.previewUrl;
  view.previewUrl = url;
  view.previewCount += 1;
  img.dataset.count = String(view.previewCount);
  img.onload = () => { if (old) URL.revokeObjectURL(old); };
  img.src = url;
}

// ------------------------------------------------------------------------------------------ control
function updateButtons() {
  const h = view.health || {};
  for (const b of document.querySelectorAll(".btn")) {
    b.disabled = !view.control;
    b.title = view.control ? "" : "this view has no control socket (read-only or a simulation)";
  }
  const msg = $("control-message");
  if (!view.control) { msg.textContent = "Read-only: this view has no control socket."; msg.dataset.readonly = "1"; }
  else if (!view.token) {
    for (const b of document.querySelectorAll(".btn")) { b.disabled = true; b.title = "commanding needs the view's token"; }
    msg.textContent = "Watching only: to command, open the address `companion view` printed (…/?token=…)."; msg.dataset.readonly = "1";
  } else if (msg.dataset.readonly) { msg.textContent = "Engage and Resume ask for a second tap."; delete msg.dataset.readonly; }
  $("engage").dataset.ready = (h.vehicle && h.vehicle.armed && !h.engaged) ? "1" : "0";
}

function disarm(b) { b.classList.remove("armed"); b.textContent = b.dataset.label; delete b.dataset.armedAt; }

async function onButton(ev) {
  const b = ev.currentTarget;
  if (b.dataset.confirm && !b.dataset.armedAt) {
    b.dataset.armedAt = String(Date.now());
    b.classList.add("armed");
    b.textContent = "Tap again to " + b.dataset.label.toLowerCase();
    setTimeout(() => disarm(b), 3000);
    return;
  }
  disarm(b);
  const cmd = b.dataset.cmd, msg = $("control-message");
  msg.className = "small"; msg.textContent = `${cmd}…`;
  try {
    const resp = await fetch("/api/control", {
      method: "POST", credentials: "same-origin",
      headers: { "Content-Type": "application/json", "X-Companion-View": "1", "Authorization": `Bearer ${view.token}` },
      body: JSON.stringify({ cmd }),
    });
    const reply = await resp.json();
    if (reply.ok) { msg.className = "small ok"; msg.textContent = `${cmd}: ${(reply.result && reply.result.message) || "ok"}`; }
    else {
      // the service's message already says "engage refused: ..."; a message of its own gets the prefix
      const text = String((reply.error && reply.error.message) || resp.status);
      msg.className = "small err"; msg.textContent = text.startsWith(`${cmd} refused`) ? text : `${cmd} refused: ${text}`;
    }
  } catch (err) {
    msg.className = "small err"; msg.textContent = `${cmd}: no answer from the view (${err})`;
  }
}

// ------------------------------------------------------------------------------------------ socket
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(`${proto}//${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  view.ws = ws;
  ws.onopen = () => { view.retryMs = 500; setConn(true); };
  ws.onmessage = (ev) => {
    view.lastMessageMs = Date.now();
    if (typeof ev.data !== "string") { showPreview(ev.data); return; }
    const m = JSON.parse(ev.data);
    if (m.type === "hello") {
      view.control = !!m.control; view.windowS = m.timeline_s || 60; view.thresholds = m.thresholds;
      view.timeline = (m.timeline || []).filter((p) => p.t !== null);
      if (m.title) { setText("title", m.title); document.title = m.title + " view"; }
      applyHealth(m.health); applyViewStatus(m.view); updateButtons(); drawTimeline();
    } else if (m.type === "health") {
      addTimeline(timelinePoint(m.health)); applyHealth(m.health); applyViewStatus(m.view);
    } else if (m.type === "thresholds") {
      view.thresholds = { near_m: m.near_m, far_m: m.far_m }; updateRegions(view.health);
    } else if (m.type === "tick") {
      applyViewStatus(m.view);
    }
  };
  ws.onclose = () => {
    setConn(false);
    setTimeout(connect, view.retryMs);
    view.retryMs = Math.min(4000, view.retryMs * 2);
  };
}

function setConn(ok) {
  const c = $("conn");
  c.textContent = ok ? "live" : "reconnecting…";
  c.className = ok ? "conn" : "conn bad";
}

function watchdog() {
  if (view.ws && view.ws.readyState === WebSocket.OPEN && Date.now() - view.lastMessageMs > 3000) {
    setConn(false); $("conn").textContent = "no data for " + ((Date.now() - view.lastMessageMs) / 1000).toFixed(0) + " s";
  }
}

function start() {
  view.token = takeToken();
  buildRegions();
  for (const b of document.querySelectorAll(".btn")) { b.dataset.label = b.textContent; b.addEventListener("click", onButton); }
  updateRegions(null); drawStick(null); drawTimeline(); updateButtons();
  connect();
  setInterval(watchdog, 500);
  let pending = false;
  const redraw = () => { pending = false; drawTimeline(); };
  setInterval(() => { if (!pending) { pending = true; requestAnimationFrame(redraw); } }, 250);
}

document.addEventListener("DOMContentLoaded", start);
