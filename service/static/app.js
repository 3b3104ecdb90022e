// flyscan status page: live status (server-sent events), last scans, latest frame, last cloud.
"use strict";

const FRAME_PERIOD_MS = 500;     // reload of the latest frame while the page is visible
const FRAME_RETRY_MS = 1000;     // after a failed frame (no frame yet, service away)
const STALE_MS = 3000;           // no status event for this long: the link is shown as lost
const SCAN_ROWS = 20;            // newest scans shown
const TERMINAL = new Set(["done", "failed"]);
const TOKEN_KEY = "flyscan.token";

const $ = (id) => document.getElementById(id);

function setText(el, text) {
  text = String(text);
  if (el.textContent !== text) el.textContent = text;
}

function fmtInt(n) {
  return typeof n === "number" && Number.isFinite(n) ? n.toLocaleString("en-US") : "\u2013";
}

function fmtNum(n, digits) {
  return typeof n === "number" && Number.isFinite(n) ? n.toFixed(digits) : "\u2013";
}

// ---- live status ---------------------------------------------------------------------------

let lastStatusAt = 0;
let scansKey = null;

function pill(el, text, level) {
  setText(el, text);
  el.className = "pill " + level;
}

function applyStatus(s) {
  lastStatusAt = Date.now();
  setLink(true, "live");

  const state = $("state");
  setText(state, s.state);
  if (state.dataset.state !== s.state) state.dataset.state = s.state;
  const fault = $("fault-reason");
  const showFault = s.state === "fault";
  fault.hidden = !showFault;
  setText(fault, showFault ? (s.fault_reason || "no reason given") : "");

  const cam = s.camera || {};
  pill($("camera-state"), cam.state || "unknown",
       cam.state === "streaming" ? "ok" : cam.state === "stalled" ? "warn" : "bad");
  setText($("camera-error"), cam.error || "");
  setText($("fps"), fmtNum(s.fps, 1));
  setText($("frames-dropped"), fmtInt(s.frames_dropped));
  setText($("exposure-us"), fmtNum(cam.exposure_us, 0));
  setText($("exposure-gain"), fmtNum(cam.gain, 2));
  setText($("exposure-mode"), cam.exposure_mode || "fixed");
  const q = s.queue || {};
  setText($("queue-depth"), fmtInt(q.depth));
  setText($("queue-capacity"), fmtInt(q.capacity));
  setText($("queue-overflows"), fmtInt(q.overflows));
  $("queue-overflows").classList.toggle("nonzero", q.overflows > 0);
  const z = s.zmq || {};
  setText($("zmq-sent"), fmtInt(z.sent));
  setText($("zmq-dropped"), fmtInt(z.dropped));
  $("zmq-dropped").classList.toggle("nonzero", z.dropped > 0);
  const robot = s.robot || {};
  pill($("robot"), robot.connected ? "connected" : "not connected", robot.connected ? "ok" : "bad");
  setText($("robot-detail"), robotDetail(robot, s));
  setText($("scans-done"), fmtInt(s.scans_done));
  setText($("scans-failed"), fmtInt(s.scans_failed));
  setText($("current-scan"), s.current_scan_id || "\u2013");
  setText($("mode"), (s.simulated ? "Simulated cell. " : "") +
          (z.endpoint ? "ZeroMQ on " + z.endpoint : "ZeroMQ not bound"));

  // The scans list changes when a scan is armed, moves on, or finishes.
  const key = [s.last_scan_id, s.current_scan_id, s.state, s.scans_done, s.scans_failed].join("|");
  if (key !== scansKey) {
    scansKey = key;
    refreshScans();
  }
}

function setLink(live, text) {
  const link = $("link");
  const value = String(live);
  if (link.dataset.live !== value) link.dataset.live = value;
  setText(link, text);
}

function connectEvents() {
  const events = new EventSource("/events");
  events.addEventListener("status", (e) => {
    try {
      applyStatus(JSON.parse(e.data));
    } catch (err) {
      console.error("bad status event", err);
    }
  });
  events.onerror = () => setLink(false, "connection lost, retrying\u2026");
  setInterval(() => {
    if (lastStatusAt && Date.now() - lastStatusAt > STALE_MS) {
      setLink(false, "no update for " + Math.round((Date.now() - lastStatusAt) / 1000) + " s");
    }
  }, 1000);
}

// ---- scans ---------------------------------------------------------------------------------

let scansBusy = false;
let scansAgain = false;
let scansPoll = null;
const seenScans = new Set();
let firstScans = true;

async function refreshScans() {
  if (scansBusy) { scansAgain = true; return; }
  scansBusy = true;
  clearTimeout(scansPoll);
  try {
    const r = await fetch("/scans", { cache: "no-store" });
    if (!r.ok) throw new Error("GET /scans: " + r.status);
    const scans = (await r.json()).scans || [];
    renderScans(scans);
    showCloud(scans.find((s) => s.state === "done"));
    // A scan in progress moves on without the run state always telling: look again soon.
    if (scans.some((s) => !TERMINAL.has(s.state))) scansPoll = setTimeout(refreshScans, 1000);
  } catch (err) {
    console.error(err);
    scansPoll = setTimeout(refreshScans, 2000);
  } finally {
    scansBusy = false;
    if (scansAgain) { scansAgain = false; refreshScans(); }
  }
}

function fmtTriple(v, digits) {
  return v.map((x) => fmtNum(x, digits)).join(", ");
}

function fmtMisplacement(m) {
  if (m === null || m === undefined) return "\u2013";
  if (Array.isArray(m) && m.length === 6 && m.every((x) => typeof x === "number")) {
    return "t " + fmtTriple(m.slice(0, 3), 2) + " mm\nr " + fmtTriple(m.slice(3), 2) + "\u00b0";
  }
  if (Array.isArray(m) && m.length === 4 && m.every(Array.isArray)) {   // 4x4 transform
    return "t " + fmtTriple(m.slice(0, 3).map((row) => row[3]), 2) + " mm";
  }
  if (typeof m === "object" && !Array.isArray(m)) {
    return Object.entries(m).map(([k, v]) =>
      k + " " + (Array.isArray(v) ? fmtTriple(v.flat(), 2) : typeof v === "number" ? fmtNum(v, 2) : String(v))
    ).join("\n");
  }
  return String(m);
}

// The verdict first (act, or why not), then the misplacement; or why there is no pose.
function fmtPose(p) {
  if (p.refused) return "no pose: " + p.refused;
  const verdict = p.act ? "act" : "do not act: " + (p.act_reasons || p.flags || []).join("; ");
  return verdict + "\n" + fmtMisplacement(p.misplacement);
}

function cell(tr, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  tr.appendChild(td);
  return td;
}

function renderScans(scans) {
  const tbody = $("scans");
  const rows = [];
  for (const s of scans.slice(0, SCAN_ROWS)) {
    const tr = document.createElement("tr");
    tr.dataset.scanId = s.scan_id;
    if (!firstScans && !seenScans.has(s.scan_id)) tr.className = "fresh";
    seenScans.add(s.scan_id);
    const cc = s.cross_check || null;
    const pose = s.pose || null;
    const latency = (s.latency_ms || {}).last_frame_to_zmq;
    cell(tr, s.scan_id, "mono");
    const st = cell(tr, s.state, "st");
    st.dataset.state = s.state;
    cell(tr, s.reason || "", "reason");
    cell(tr, fmtInt(s.points), "num points");
    cell(tr, fmtInt(s.frames), "num");
    cell(tr, fmtInt(s.frames_dropped), "num");
    cell(tr, cc ? fmtNum(cc.rms_mm, 3) + " / " + fmtNum(cc.max_mm, 3) : "\u2013", "num");
    const flagged = cc && typeof cc.flagged === "boolean" ? cc.flagged : null;
    const flagCell = cell(tr, flagged === null ? "\u2013" : flagged ? "yes" : "no", flagged ? "flag-yes" : "");
    if (cc && cc.reason) flagCell.title = cc.reason;
    const poseCell = cell(tr, pose ? fmtPose(pose) : "\u2013", "mono misplacement");
    if (pose && (pose.refused || !pose.act)) poseCell.classList.add("flag-yes");
    cell(tr, fmtNum(latency, 1), "num");
    rows.push(tr);
  }
  firstScans = false;
  if (rows.length === 0) {
    const tr = document.createElement("tr");
    tr.className = "empty";
    const td = cell(tr, "No scans yet.");
    td.colSpan = 10;
    rows.push(tr);
  }
  tbody.replaceChildren(...rows);
}

let cloudId = null;

function showCloud(scan) {
  const img = $("cloud");
  const screen = $("cloud-screen");
  if (!scan) {
    setText($("cloud-note"), "none yet");
    return;
  }
  if (scan.scan_id === cloudId) return;
  cloudId = scan.scan_id;
  setText($("cloud-note"), scan.scan_id + " (loading)");
  img.onload = () => {
    screen.dataset.empty = "false";
    setText($("cloud-note"), scan.scan_id + ", " + fmtInt(scan.points) + " points");
  };
  img.onerror = () => {
    screen.dataset.empty = "true";
    setText($("cloud-placeholder"), "No cloud for scan " + scan.scan_id);
    setText($("cloud-note"), scan.scan_id + ": no cloud");
  };
  img.src = "/scans/" + encodeURIComponent(scan.scan_id) + "/preview.png";
  showDeviation(scan);
}

function showDeviation(scan) {
  // the inspection's picture: only for a scan registered to a model
  const panel = $("deviation-panel");
  const img = $("deviation");
  img.onload = () => {
    panel.hidden = false;
    const inspection = scan.inspection;
    setText($("deviation-note"), !inspection ? scan.scan_id
      : inspection.conforms ? "conforms"
      : "fails: " + (inspection.failing || []).join(", ").replaceAll("_", " "));
  };
  img.onerror = () => { panel.hidden = true; };
  img.src = "/scans/" + encodeURIComponent(scan.scan_id) + "/deviation.png";
}

// ---- latest frame --------------------------------------------------------------------------

let frameTimer = null;
let frameLoading = false;

function loadFrame() {
  frameTimer = null;
  if (document.hidden) return;
  frameLoading = true;
  $("frame").src = "/frame.png?t=" + Date.now();
}

function scheduleFrame(delay) {
  clearTimeout(frameTimer);
  frameTimer = document.hidden ? null : setTimeout(loadFrame, delay);
}

function setupFrame() {
  const img = $("frame");
  img.addEventListener("load", () => {
    frameLoading = false;
    $("frame-screen").dataset.empty = "false";
    setText($("frame-note"), "");
    scheduleFrame(FRAME_PERIOD_MS);
  });
  img.addEventListener("error", () => {
    frameLoading = false;
    $("frame-screen").dataset.empty = "true";
    setText($("frame-note"), "(no frame yet)");
    scheduleFrame(FRAME_RETRY_MS);
  });
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) { clearTimeout(frameTimer); frameTimer = null; }
    else if (!frameLoading) scheduleFrame(0);
  });
  loadFrame();
}

// ---- arm -----------------------------------------------------------------------------------

function problemText(body, response) {
  const detail = body && body.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) return detail.map((d) => (d && d.msg) || JSON.stringify(d)).join("; ");
  return response.statusText || "request failed";
}

function setupArm() {
  const token = $("token");
  try { token.value = sessionStorage.getItem(TOKEN_KEY) || ""; } catch (err) { /* storage off */ }
  token.addEventListener("input", () => {
    try {
      if (token.value) sessionStorage.setItem(TOKEN_KEY, token.value);
      else sessionStorage.removeItem(TOKEN_KEY);
    } catch (err) { /* storage off */ }
  });

  const button = $("arm");
  const result = $("arm-result");
  $("arm-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    button.disabled = true;
    result.className = "arm-result";
    delete result.dataset.scanId;
    setText(result, "arming\u2026");
    const headers = { "Content-Type": "application/json", "Accept": "application/json" };
    if (token.value.trim()) headers["Authorization"] = "Bearer " + token.value.trim();
    try {
      const r = await fetch("/scans", { method: "POST", headers, body: "{}" });
      const body = await r.json().catch(() => null);
      if (r.ok && body && body.scan_id) {
        result.className = "arm-result ok";
        result.dataset.scanId = body.scan_id;
        setText(result, "Armed scan " + body.scan_id);
        refreshScans();
      } else {
        result.className = "arm-result error";
        setText(result, "Not armed (" + r.status + "): " + problemText(body, r));
      }
    } catch (err) {
      result.className = "arm-result error";
      setText(result, "Not armed: service unreachable (" + err.message + ")");
    } finally {
      button.disabled = false;
    }
  });
}

setupArm();
setupFrame();
connectEvents();
refreshScans();

// The calibration history (GET /calibration/history): every version, its residuals, which is
// active; the residuals' chart of the newest fitted one, drawn by the service once per change.
const CALIBRATION_PERIOD_MS = 10000;

async function refreshCalibrations() {
  try {
    const r = await fetch("/calibration/history", { cache: "no-store" });
    if (!r.ok) throw new Error("GET /calibration/history: " + r.status);
    const history = await r.json();
    const tbody = $("calibrations");
    tbody.replaceChildren();
    for (const v of history.versions.slice().reverse()) {
      const tr = document.createElement("tr");
      tr.dataset.version = v.version;
      const f = v.figures || {};
      cell(tr, "v" + v.version);
      cell(tr, v.source);
      cell(tr, v.created);
      cell(tr, fmtNum(f.views_heldout_px, 4), "num");
      cell(tr, (f.views_per_view_rms_px || []).map((x) => fmtNum(x, 4)).join(" / "), "num");
      cell(tr, fmtNum(f.plane_rms_um, 1), "num");
      cell(tr, fmtNum(f.sphere_centre_rms_um, 1), "num");
      cell(tr, v.active ? "active" : "", "st");
      tbody.appendChild(tr);
    }
    const fitted = history.versions.filter((v) => v.has_report).pop();
    const img = $("residuals");
    const src = fitted ? "/calibration/history/" + fitted.version + "/residuals.png" : null;
    if (src && img.getAttribute("src") !== src) { img.src = src; img.hidden = false; }
  } catch (err) {
    console.error(err);
  }
  setTimeout(refreshCalibrations, CALIBRATION_PERIOD_MS);
}

refreshCalibrations();

// One line on the robot: where it is, how fresh its poses are, and the clocks' offset.
function robotDetail(robot, s) {
  const parts = [];
  if (robot.host) parts.push(robot.host);
  if (typeof robot.last_sample_age_s === "number") parts.push("last pose " + fmtNum(robot.last_sample_age_s, 2) + " s ago");
  if (robot.reconnects) parts.push(fmtInt(robot.reconnects) + " reconnects");
  if (!robot.connected && robot.last_error) parts.push(robot.last_error);
  if (typeof s.clock_offset_s === "number") parts.push("clock offset " + fmtNum(s.clock_offset_s * 1e3, 2) + " ms");
  return parts.join(", ");
}
