// The Flash-Mono web viewer: session list, live trajectory (top-down and 3D), loop closures, a rendered view from
// a camera the user moves, and the map download. Query parameters: ?session=ID; the API key may come as #api_key=KEY
// (or ?api_key=KEY): it is moved to sessionStorage and removed from the address bar at once, so it stays out of the
// history, bookmarks and Referer headers, and is forgotten when the tab closes.

import { Api } from "./api.js";
import { EventFeed } from "./events.js";
import { MOVE_KEYS, ServerView } from "./render_view.js";
import { OrbitView, drawTopDown, position } from "./scene.js";

const POLL_TRAJECTORY_MS = 1000;
const MAP_REFRESH_MIN_MS = 2000; // a streaming session's map is fetched again at most this often
const POLL_SESSIONS_MS = 4000;

const $ = (id) => document.getElementById(id);
const KEY_STORE = "flashmono.apiKey";
const params = new URLSearchParams(window.location.search);
const hashParams = new URLSearchParams(window.location.hash.slice(1));
const urlKey = hashParams.get("api_key") || params.get("api_key");
if (urlKey) {
  sessionStorage.setItem(KEY_STORE, urlKey);
  params.delete("api_key");
  const query = params.toString();
  history.replaceState(null, "", window.location.pathname + (query ? `?${query}` : ""));
}
localStorage.removeItem(KEY_STORE); // older viewers kept the key there for good
const state = {
  api: new Api(urlKey || sessionStorage.getItem(KEY_STORE) || ""),
  sessionId: params.get("session"),
  session: null,
  poses: [],
  keyframes: [],
  loops: [], // {revision, position}
  revision: null,
  splats: null, // the SplatView, once WebGL and the renderer loaded
  mapFormat: "spz",
  mapKey: null, // what the shown map reflects: revision, keyframes and status of the session
  mapLoading: false,
  mapFetchedAt: 0,
  splatPosePlaced: false,
  sessionList: [],
};
// What tests and curious users can read: how much has been drawn and rendered.
window.viewerState = { posesDrawn: 0, renders: 0, lastError: null, loopClosures: 0, mapDownloads: 0, lastMap: null,
  splat: { ready: false, error: null, fps: 0, frames: 0, firstSplatFrameMs: null, maps: 0, map: null,
    history: [] },
  events: [], livePoses: 0 };

const orbit = new OrbitView($("view3d"));
const serverView = new ServerView(state.api, $("render"), {
  onRendered: () => {
    window.viewerState.renders += 1;
    document.body.dataset.renders = String(window.viewerState.renders);
  },
  onError: (err) => setStatus(`render: ${err.message}`, true),
});
const feed = new EventFeed($("events"), $("tracking-state"), {
  onPose: () => { window.viewerState.livePoses += 1; },
  onEvent: (message) => {
    window.viewerState.events.push(message);
    if (message.type === "loop_closed") state.mapFetchedAt = 0; // the corrected map as soon as the revision shows
  },
});

function setStatus(text, isError = false) {
  const el = $("status");
  el.textContent = text;
  el.classList.toggle("error", isError);
  if (isError) window.viewerState.lastError = text;
}

// ----------------------------------------------------------------------------------------------- sessions

function ago(iso) {
  const s = Math.max(0, (Date.now() - Date.parse(iso)) / 1000);
  return s < 90 ? `${Math.round(s)} s ago` : s < 5400 ? `${Math.round(s / 60)} min ago` : `${Math.round(s / 3600)} h ago`;
}

const LIVE = new Set(["created", "streaming", "finishing", "abandoned"]);

function sessionMatches(s) {
  const text = $("session-filter").value.trim().toLowerCase();
  const status = $("status-filter").value;
  if (status && s.status !== status) return false;
  return !text || [s.name, s.id, s.device_id].some((v) => v && v.toLowerCase().includes(text));
}

// The fleet: each session's status, frames, keyframes, last pose time, tracking state, and a link to its live view.
function drawSessions() {
  const list = $("sessions");
  list.replaceChildren();
  const shown = state.sessionList.filter(sessionMatches);
  for (const s of shown) {
    const li = document.createElement("li");
    li.dataset.id = s.id;
    li.dataset.status = s.status;
    li.classList.toggle("selected", s.id === state.sessionId);
    const title = document.createElement("span");
    title.textContent = s.name || s.id;
    const link = document.createElement("a");
    link.href = `/viewer?session=${encodeURIComponent(s.id)}`;
    link.textContent = "live view";
    link.addEventListener("click", (e) => { e.preventDefault(); e.stopPropagation(); selectSession(s.id); });
    const meta = document.createElement("span");
    meta.className = "meta";
    meta.textContent = `${s.status} · ${s.frames_processed} frames · ${s.keyframes} keyframes · last pose `
      + `${s.frames_processed ? ago(s.updated_at) : "–"} · ${s.device_id || "no device"}`;
    const trackingState = s.tracking_state || (LIVE.has(s.status) && !s.frames_processed ? "waiting" : null);
    const tracking = document.createElement("span");
    tracking.className = `meta tracking-${trackingState || "none"}`;
    tracking.textContent = trackingState ? `tracking: ${trackingState}` : "";
    li.append(title, link, meta, tracking);
    li.addEventListener("click", () => selectSession(s.id));
    list.append(li);
  }
  window.viewerState.sessionsShown = shown.length;
}

async function refreshSessions() {
  try {
    const { sessions } = await state.api.sessions(200);
    state.sessionList = sessions;
    drawSessions();
    if (!state.sessionId) setStatus(sessions.length ? "pick a session" : "no sessions yet");
  } catch (err) {
    setStatus(`sessions: ${err.message}`, true);
  }
}

function selectSession(id) {
  Object.assign(state, { sessionId: id, session: null, poses: [], keyframes: [], loops: [], revision: null,
    mapKey: null, splatPosePlaced: false });
  serverView.open(id);
  const url = new URL(window.location.href);
  url.searchParams.set("session", id);
  window.history.replaceState(null, "", url);
  for (const li of $("sessions").children) li.classList.toggle("selected", li.dataset.id === id);
  $("download-map").disabled = false;
  window.viewerState.events = [];
  feed.open(id, state.api.apiKey);
  pollSession();
}

// --------------------------------------------------------------------------------------------- trajectory

async function pollSession() {
  const id = state.sessionId;
  if (!id) return;
  try {
    const [session, all, keyframes] = await Promise.all([
      state.api.session(id), state.api.trajectory(id, "all"), state.api.trajectory(id, "keyframes"),
    ]);
    if (id !== state.sessionId) return; // the user switched meanwhile
    state.session = session;
    const poses = all.poses.map((p) => p.pose);
    if (state.revision !== null && all.revision > state.revision && poses.length) {
      // A loop closure rewrote the trajectory since the last poll: mark where the camera was.
      state.loops.push({ revision: all.revision, position: position(poses[poses.length - 1]) });
    }
    state.revision = all.revision;
    state.poses = poses;
    state.keyframes = keyframes.poses.map((p) => p.pose);
    window.viewerState.loopClosures = state.loops.length;
    $("session-title").textContent = session.name ? `${session.name} (${session.id})` : session.id;
    $("session-stats").textContent = `${session.status} · ${session.frames_processed}/${session.frames_received} `
      + `frames · ${session.keyframes} keyframes · revision ${all.revision}`;
    drawTrajectory();
    updateSplats(session);
    serverView.follow(session, poses);
    setStatus(`live · ${poses.length} poses`);
  } catch (err) {
    setStatus(`session ${id}: ${err.message}`, true);
  }
}

function drawTrajectory() {
  const drawn = drawTopDown($("topdown"), state.poses, state.keyframes, state.loops);
  orbit.update(state.poses, state.keyframes, state.loops);
  window.viewerState.posesDrawn = drawn;
  document.body.dataset.posesDrawn = String(drawn);
}

// ------------------------------------------------------------------------------------------- splat view

async function startSplatView() {
  const info = $("splat-info");
  try {
    const { SplatView } = await import("./splats.js");
    state.splats = new SplatView($("splats"), {
      onFrame: (view) => {
        const s = window.viewerState.splat;
        s.frames = view.frames;
        s.fps = view.fps;
        if (view.firstSplatFrameAt !== null && s.firstSplatFrameMs === null) s.firstSplatFrameMs = view.firstSplatFrameAt;
      },
    });
    window.splatView = state.splats; // for tests and the curious: pose(), setPose(), readSplats()
    window.viewerState.splat.ready = true;
    info.textContent = "renderer ready";
    setInterval(showSplatInfo, 1000);
  } catch (err) {
    window.viewerState.splat.error = String(err && err.message ? err.message : err);
    info.textContent = `splat view unavailable (WebGL2 needed): ${window.viewerState.splat.error}`;
  }
}

function showSplatInfo() {
  const s = window.viewerState.splat;
  if (s.mapError) return;
  const m = s.map;
  $("splat-info").textContent = m
    ? `${m.splats ?? "?"} splats · ${m.format} ${(m.bytes / 1e6).toFixed(2)} MB · ${s.fps.toFixed(1)} frames/s`
    : `no map yet · ${s.fps.toFixed(1)} frames/s`;
  document.body.dataset.splatFps = s.fps.toFixed(1);
}

// Called on every poll: trajectory and frustums in the 3D scene, and the map again when the session's map changed
// (a new keyframe, a loop closure's revision, the final refinement once finished).
function updateSplats(session) {
  const view = state.splats;
  if (!view) return;
  const k = session.estimated_intrinsics || session.intrinsics;
  if (k) view.setIntrinsics(k);
  view.setTrajectory(state.poses, state.keyframes, state.loops);
  if (!state.splatPosePlaced && state.poses.length) {
    view.setPose(state.poses[state.poses.length - 1]);
    state.splatPosePlaced = true;
  }
  const key = `${session.revision}|${session.keyframes}|${session.status}|${state.mapFormat}`;
  const due = performance.now() - state.mapFetchedAt >= MAP_REFRESH_MIN_MS;
  // not while the session finishes: such a request waits out the final refinement, and the finished map follows
  const finishing = session.status === "finishing";
  if (session.keyframes > 0 && key !== state.mapKey && due && !state.mapLoading && !finishing) {
    loadSplatMap(session.id, key);
  }
}

async function loadSplatMap(id, key) {
  state.mapLoading = true;
  state.mapFetchedAt = performance.now();
  const format = state.mapFormat;
  try {
    const t0 = performance.now();
    const bytes = new Uint8Array(await (await state.api.map(id, format)).arrayBuffer());
    const fetchMs = performance.now() - t0;
    if (id !== state.sessionId) return;
    const loaded = await state.splats.loadMap(bytes, format, key);
    state.mapKey = key;
    window.viewerState.splat.maps += 1;
    window.viewerState.splat.map = { ...loaded, fetchMs, key, loadedAt: performance.now() };
    window.viewerState.splat.history.push({ splats: loaded.splats, key, bytes: loaded.bytes });
    window.viewerState.splat.mapError = null;
    showSplatInfo();
  } catch (err) {
    // shown beside the view, not as a page error: a session may have no Gaussian map (409: not again until the
    // session changes), or its worker may be busy (503/504: tried again at the next poll)
    if (err.status === 409) state.mapKey = key;
    window.viewerState.splat.mapError = `map (${format}): ${err.message}`;
    $("splat-info").textContent = window.viewerState.splat.mapError;
  } finally {
    state.mapLoading = false;
  }
}

// The exact reference: the server renders the splat view's camera (pose and pinhole) as a PNG.
function exactServerView() {
  if (!state.splats || !state.sessionId) return;
  serverView.placeAt(state.splats.pose(), true);
  $("render").scrollIntoView({ block: "nearest" });
}

// ----------------------------------------------------------------------------------------------- download

async function downloadMap() {
  const id = state.sessionId;
  if (!id) return;
  // The result goes to its own line next to the button: the status line is rewritten by every trajectory poll,
  // which would hide the outcome within a second.
  const button = $("download-map");
  const mapStatus = $("map-status");
  button.disabled = true;
  mapStatus.classList.remove("error");
  mapStatus.textContent = "downloading…";
  try {
    const format = $("download-format").value;
    const blob = await (await state.api.map(id, format)).blob();
    const name = `${id}.${format}`;
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = name;
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 60000);
    window.viewerState.mapDownloads += 1;
    window.viewerState.lastMap = { name, bytes: blob.size };
    mapStatus.textContent = `map downloaded: ${name} (${blob.size} bytes)`;
  } catch (err) {
    mapStatus.textContent = `map: ${err.message}`;
    mapStatus.classList.add("error");
    setStatus(`map: ${err.message}`, true);
  } finally {
    button.disabled = !state.sessionId;
  }
}

// ------------------------------------------------------------------------------------------------- wiring

function init() {
  const keyInput = $("api-key");
  keyInput.value = state.api.apiKey;
  keyInput.addEventListener("change", () => {
    state.api.apiKey = keyInput.value.trim();
    sessionStorage.setItem(KEY_STORE, state.api.apiKey);
    refreshSessions();
  });
  $("refresh-sessions").addEventListener("click", refreshSessions);
  $("session-filter").addEventListener("input", drawSessions);
  $("status-filter").addEventListener("change", drawSessions);
  $("download-map").addEventListener("click", downloadMap);
  $("snap-camera").addEventListener("click", () => {
    if (state.poses.length) serverView.placeAt(state.poses[state.poses.length - 1]);
  });
  $("render-kind").addEventListener("change", (e) => serverView.setKind(e.target.value));
  for (const button of $("camera-controls").querySelectorAll("button")) {
    button.addEventListener("click", () => serverView.move(button.dataset.move));
  }
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target === $("splats")) return; // the splat view's own keys
    const name = MOVE_KEYS[e.key] || MOVE_KEYS[e.key.toLowerCase()];
    if (name) {
      e.preventDefault();
      serverView.move(name);
    }
  });
  $("splat-mode").addEventListener("change", (e) => state.splats && state.splats.setMode(e.target.value));
  $("splat-format").addEventListener("change", (e) => {
    state.mapFormat = e.target.value;
    if (state.session) updateSplats(state.session);
  });
  $("splat-overlay").addEventListener("change", (e) => state.splats && state.splats.showOverlay(e.target.checked));
  $("splat-to-pose").addEventListener("click", () => {
    if (state.splats && state.poses.length) state.splats.setPose(state.poses[state.poses.length - 1]);
  });
  $("splat-exact").addEventListener("click", exactServerView);
  startSplatView().then(() => state.session && updateSplats(state.session));
  refreshSessions();
  if (state.sessionId) selectSession(state.sessionId);
  setInterval(refreshSessions, POLL_SESSIONS_MS);
  setInterval(pollSession, POLL_TRAJECTORY_MS);
  drawTrajectory();
}

init();
