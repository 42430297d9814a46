// The capture page: a phone's browser streams its (rear) camera to a new session over the same WebSocket contract
// as every client (binary msgpack frames, JSON acks and results; openapi.yaml x-websocket), and shows the live map.
//
// Flow control, as the contract says: at most WINDOW frames on the wire without their immediate answer (ack or
// error) and at most MAX_AT_SERVER acked frames without their result (pose or error). A camera tick that finds either
// full sends nothing (the image is dropped at the source, no seq is spent). On `backpressure` the sender rewinds to
// `resend_from`, backs off exponentially while refusals go on, and sends its newest image under that seq.

import { encode } from "@msgpack/msgpack";
import { Api } from "./api.js";

const WINDOW = 4;
const MAX_AT_SERVER = 8;
const JPEG_QUALITY = 0.85;
const MAP_POLL_MS = 2000;
const KEY_STORE = "flashmono.apiKey";
const $ = (id) => document.getElementById(id);

const hash = new URLSearchParams(window.location.hash.slice(1));
if (hash.get("api_key")) {
  sessionStorage.setItem(KEY_STORE, hash.get("api_key"));
  history.replaceState(null, "", window.location.pathname + window.location.search);
}
const api = new Api(sessionStorage.getItem(KEY_STORE) || "");

// What tests and curious users can read.
const counters = { sent: 0, acked: 0, results: 0, poses: 0, refused: 0, dropped: 0, backpressure: 0, events: [],
  sessionId: null, finished: false, error: null, camera: null };
window.captureState = counters;

const capture = {
  ws: null, stream: null, timer: null, canvas: document.createElement("canvas"), nextSeq: 0,
  awaitingAnswer: new Set(), awaitingResult: new Set(), pausedUntil: 0, backoffMs: 100, busy: false,
  splats: null, mapKey: null, mapTimer: null,
};

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").classList.toggle("error", isError);
  if (isError) counters.error = text;
}

function showCounters() {
  const c = counters;
  $("counters").textContent = `sent ${c.sent} · acked ${c.acked} · poses ${c.poses} · skipped ${c.skipped || 0} · on the wire `
    + `${capture.awaitingAnswer.size} · at the server ${capture.awaitingResult.size} · dropped at the camera `
    + `${c.dropped} · backpressure ${c.backpressure}`;
}

function chosenSize() {
  const [width, height] = $("size").value.split("x").map(Number);
  return { width, height };
}

async function start() {
  $("start").disabled = true;
  try {
    api.apiKey = $("api-key").value.trim();
    sessionStorage.setItem(KEY_STORE, api.apiKey);
    const { width, height } = chosenSize();
    capture.stream = await navigator.mediaDevices.getUserMedia({
      audio: false, video: { facingMode: { ideal: "environment" }, width: { ideal: width }, height: { ideal: height } },
    });
    const video = $("video");
    video.srcObject = capture.stream;
    await video.play();
    const settings = capture.stream.getVideoTracks()[0].getSettings();
    counters.camera = { label: capture.stream.getVideoTracks()[0].label, width: settings.width,
      height: settings.height, facingMode: settings.facingMode || null };
    capture.canvas.width = width;
    capture.canvas.height = height;
    const focal = Number($("focal").value);
    // a live camera: the tracker may skip frames that fell behind a newer one (each gets a `skipped` result);
    // no preset unless the user picks one: the server chooses for this camera and its machine (`auto`)
    const body = { name: $("name").value || "phone capture", device_id: "browser", skip_frames: true,
      frame_rate: Math.max(1, Math.min(30, Number($("fps").value) || 5)) };
    if ($("preset").value) body.preset = $("preset").value;
    if (focal > 0) body.intrinsics = { width, height, fx: focal, fy: focal, cx: width / 2, cy: height / 2 };
    const session = await api.createSession(body);
    counters.sessionId = session.id;
    $("viewer-link").href = `/viewer?session=${encodeURIComponent(session.id)}`;
    openStream(session.id);
    startSplats(session.id);
  } catch (err) {
    setStatus(`start: ${err.message || err}`, true);
    stopCamera();
    $("start").disabled = false;
  }
}

function openStream(id) {
  const scheme = window.location.protocol === "https:" ? "wss" : "ws";
  const query = api.apiKey ? `?api_key=${encodeURIComponent(api.apiKey)}` : "";
  const ws = new WebSocket(`${scheme}://${window.location.host}/v1/sessions/${encodeURIComponent(id)}/stream${query}`);
  ws.binaryType = "arraybuffer";
  capture.ws = ws;
  ws.addEventListener("open", () => {
    setStatus(`streaming to ${id}`);
    $("stop").disabled = false;
    const fps = Math.max(1, Math.min(30, Number($("fps").value) || 5));
    capture.timer = setInterval(tick, 1000 / fps);
  });
  ws.addEventListener("message", (e) => onMessage(JSON.parse(e.data)));
  ws.addEventListener("close", (e) => {
    clearInterval(capture.timer);
    if (!counters.finished) setStatus(`stream closed (${e.code}) ${e.reason || ""}`, e.code !== 1000);
  });
}

async function tick() {
  const ws = capture.ws;
  if (!ws || ws.readyState !== WebSocket.OPEN || capture.busy) return;
  if (performance.now() < capture.pausedUntil || capture.awaitingAnswer.size >= WINDOW
      || capture.awaitingResult.size >= MAX_AT_SERVER) {
    counters.dropped += 1;
    showCounters();
    return;
  }
  capture.busy = true;
  try {
    const { width, height } = capture.canvas;
    capture.canvas.getContext("2d").drawImage($("video"), 0, 0, width, height);
    const blob = await new Promise((resolve) => capture.canvas.toBlob(resolve, "image/jpeg", JPEG_QUALITY));
    const seq = capture.nextSeq++;
    const message = encode({ type: "frame", seq, timestamp: performance.now() / 1000,
      image: new Uint8Array(await blob.arrayBuffer()) });
    capture.awaitingAnswer.add(seq);
    ws.send(message);
    counters.sent += 1;
  } finally {
    capture.busy = false;
    showCounters();
  }
}

function onMessage(m) {
  if (m.type === "ack") {
    capture.awaitingAnswer.delete(m.seq);
    capture.awaitingResult.add(m.seq);
    counters.acked += 1;
    capture.backoffMs = 100;
  } else if (m.type === "pose") {
    capture.awaitingResult.delete(m.seq);
    counters.results += 1;
    counters.poses += 1;
    counters.lastPose = m.pose;
  } else if (m.type === "skipped") { // the tracker, behind, took a newer frame instead: a result all the same
    capture.awaitingResult.delete(m.seq);
    counters.results += 1;
    counters.skipped = (counters.skipped || 0) + 1;
  } else if (m.type === "error" && m.seq !== undefined && capture.awaitingAnswer.has(m.seq)) {
    capture.awaitingAnswer.delete(m.seq);
    counters.refused += 1;
    if (m.code === "backpressure") {
      counters.backpressure += 1;
      // rewind: the newest image goes out next under the refused seq; the refusals of later frames are ignored
      capture.nextSeq = Math.min(capture.nextSeq, m.resend_from ?? m.seq);
      for (const seq of [...capture.awaitingAnswer]) if (seq >= capture.nextSeq) capture.awaitingAnswer.delete(seq);
      capture.pausedUntil = performance.now() + capture.backoffMs;
      capture.backoffMs = Math.min(2000, capture.backoffMs * 2);
    } else {
      showEvent(m);
    }
  } else if (m.type === "error" && m.seq !== undefined) {
    capture.awaitingResult.delete(m.seq); // the worker could not use an acked frame
    counters.results += 1;
    showEvent(m);
  } else if (m.type === "finished") {
    counters.finished = true;
    setStatus(`finished: ${m.frames} frames`);
    stopCamera();
    showEvent(m);
  } else if (["tracking_lost", "relocalized", "initialized", "loop_closed", "error"].includes(m.type)) {
    showEvent(m);
  }
  showCounters();
}

function showEvent(m) {
  counters.events.push(m);
  const li = document.createElement("li");
  li.className = m.type;
  li.textContent = `${m.type}${m.seq !== undefined ? ` @${m.seq}` : ""}${m.message ? `: ${m.message}` : ""}`;
  $("events").prepend(li);
}

function stopCamera() {
  clearInterval(capture.timer);
  if (capture.stream) for (const track of capture.stream.getTracks()) track.stop();
}

function finish() {
  $("stop").disabled = true;
  clearInterval(capture.timer);
  if (capture.ws && capture.ws.readyState === WebSocket.OPEN) {
    capture.ws.send(JSON.stringify({ type: "finish" }));
    setStatus("finishing…");
  }
}

// The live map beside the video: the session's SPZ again whenever its keyframes or revision change.
async function startSplats(id) {
  try {
    const { SplatView } = await import("./splats.js");
    capture.splats = new SplatView($("splats"));
    window.splatView = capture.splats;
  } catch (err) {
    $("splat-info").textContent = `no WebGL2 here: ${err.message}`;
    return;
  }
  capture.mapTimer = setInterval(async () => {
    try {
      const session = await api.session(id);
      const key = `${session.revision}|${session.keyframes}|${session.status}`;
      if (session.keyframes < 1 || key === capture.mapKey) return;
      // a map asked for while the session finishes waits out its final refinement (a timeout on a busy server):
      // the next map worth showing is the finished one
      if (session.status === "finishing") return;
      capture.mapKey = key;
      const k = session.estimated_intrinsics || session.intrinsics;
      if (k) capture.splats.setIntrinsics(k);
      const bytes = new Uint8Array(await (await api.map(id, "spz")).arrayBuffer());
      const loaded = await capture.splats.loadMap(bytes, "spz", key);
      if (counters.lastPose) capture.splats.setPose(counters.lastPose);
      $("splat-info").textContent = `${loaded.splats} splats`;
      counters.mapSplats = loaded.splats;
      if (session.status === "finished") clearInterval(capture.mapTimer);
    } catch (err) {
      $("splat-info").textContent = `map: ${err.message}`;
    }
  }, MAP_POLL_MS);
}

$("api-key").value = api.apiKey;
$("start").addEventListener("click", start);
$("stop").addEventListener("click", finish);
if (!navigator.mediaDevices || !navigator.mediaDevices.getUserMedia) {
  setStatus("this browser gives no camera here (a phone needs https, or localhost)", true);
  $("start").disabled = true;
}
showCounters();
