// The Flash-Mono web viewer: session and saved-map lists, a session's live trajectory (top-down and 3D), loop
// closures, a rendered view from a camera the user moves, a saved map with its sessions' trajectories, the splat view
// (opened on an overview of the whole map) and the map download. Query parameters: ?session=ID or ?map=ID (a saved
// map); the API key may come as #api_key=KEY (or ?api_key=KEY): it is moved to sessionStorage and removed from the
// address bar at once, so it stays out of the history, bookmarks and Referer headers, and is forgotten when the tab
// closes.

import { Api } from "./api.js";
import { boundsOf, unionBounds } from "./bounds.js";
import { mapEntry, mapFacts, sessionEntry } from "./entries.js";
import { EventFeed } from "./events.js";
import { PagedList } from "./lists.js";
import { MapSessions, drawLegend, latestPose, mapLayers } from "./map_view.js";
import { MOVE_KEYS, ServerView } from "./render_view.js";
import { OrbitView, drawTopDown, position } from "./scene.js";

const POLL_TRAJECTORY_MS = 1000;
const MAP_REFRESH_MIN_MS = 2000; // a streaming session's map is fetched again at most this often
const POLL_SESSIONS_MS = 4000;
const POLL_MAP_MS = 3000; // an open map: new versions, sessions created in it, their trajectories

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
  mapId: params.get("map"), // a saved map open instead of a session
  map: null, // its record, and its sessions as map_view.js loads them
  mapSessions: [],
  poses: [],
  keyframes: [],
  loops: [], // {revision, position}
  revision: null,
  splats: null, // the SplatView, once WebGL and the renderer loaded
  mapFormat: "spz",
  mapKey: null, // what the shown map reflects: revision, keyframes and status of the session
  mapLoading: false,
  mapFetchedAt: 0,
  overviewPlaced: false, // the splat view shows the whole map (or path) once for what is open
  splatsShown: false, // whether the splats of what is open are loaded (the overview frames them then, once)
};
const sessionsInMap = new MapSessions(state.api);
// What tests and curious users can read: how much has been drawn and rendered.
window.viewerState = { posesDrawn: 0, renders: 0, lastError: null, loopClosures: 0, mapDownloads: 0, lastMap: null,
  splat: { ready: false, error: null, fps: 0, frames: 0, firstSplatFrameMs: null, maps: 0, map: null,
    history: [], overview: null },
  events: [], livePoses: 0, map: null };

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

function sessionMatches(s) {
  const text = $("session-filter").value.trim().toLowerCase();
  const status = $("status-filter").value;
  if (status && s.status !== status) return false;
  return !text || [s.name, s.id, s.device_id].some((v) => v && v.toLowerCase().includes(text));
}

// The fleet (each session's status, frames, keyframes, last pose time, tracking state while live, a link to its
// view) and the saved maps, a page at a time.
const sessionList = new PagedList({
  list: $("sessions"), more: $("more-sessions"), matches: sessionMatches,
  entry: (s) => sessionEntry(s, selectSession), onError: (err) => setStatus(`sessions: ${err.message}`, true),
  fetchPage: async (limit, cursor) => {
    const status = $("status-filter").value;
    const page = await state.api.sessions(limit, cursor, status ? { status } : {});
    return { items: page.sessions, next: page.next_cursor };
  },
});
const mapList = new PagedList({
  list: $("maps"), more: $("more-maps"), entry: (m) => mapEntry(m, openMap),
  onError: (err) => setStatus(`maps: ${err.message}`, true),
  fetchPage: async (limit, cursor) => {
    const page = await state.api.maps(limit, cursor);
    return { items: page.maps, next: page.next_cursor };
  },
});

function drawSessions() {
  window.viewerState.sessionsShown = sessionList.draw();
}

async function refreshLists() {
  const [sessions, maps] = await Promise.all([
    sessionList.refresh().catch((err) => setStatus(`sessions: ${err.message}`, true)),
    mapList.refresh().catch((err) => setStatus(`maps: ${err.message}`, true)),
  ]);
  window.viewerState.sessionsShown = sessions ?? 0;
  window.viewerState.mapsShown = maps ?? 0;
  if (!state.sessionId && !state.mapId && sessions !== undefined) {
    setStatus(sessions || maps ? "pick a session or a map" : "no sessions yet");
  }
}

// What is open: the address, the lists' selection, the page's mode (a map hides the session-only views).
function show(kind, id) {
  const url = new URL(window.location.href);
  url.searchParams.delete(kind === "map" ? "session" : "map");
  url.searchParams.set(kind, id);
  window.history.replaceState(null, "", url);
  sessionList.select(kind === "session" ? id : null);
  mapList.select(kind === "map" ? id : null);
  document.body.dataset.mode = kind;
  $("download-map").disabled = false;
  Object.assign(state, { mapKey: null, overviewPlaced: false, splatsShown: false });
  if (state.splats) state.splats.clear(); // not the last one's map under this one's path
  Object.assign(window.viewerState.splat, { map: null, mapError: null, overview: null });
}

function selectSession(id) {
  Object.assign(state, { sessionId: id, session: null, poses: [], keyframes: [], loops: [], revision: null,
    mapId: null, map: null, mapSessions: [] });
  serverView.open(id);
  show("session", id);
  window.viewerState.events = [];
  feed.open(id, state.api.apiKey);
  pollSession();
}

function openMap(id) {
  feed.close();
  Object.assign(state, { mapId: id, map: null, mapSessions: [], sessionId: null, session: null, poses: [],
    keyframes: [], loops: [] });
  serverView.open(null);
  show("map", id);
  $("map-legend").replaceChildren();
  pollMap();
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
    setStatus(`${session.status} · ${poses.length} poses`);
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

// ------------------------------------------------------------------------------------------------ saved map

async function pollMap() {
  const id = state.mapId;
  if (!id) return;
  try {
    const { map, sessions } = await sessionsInMap.load(id);
    if (id !== state.mapId) return; // the user switched meanwhile
    Object.assign(state, { map, mapSessions: sessions });
    $("session-title").textContent = `map ${map.name} (${map.id})`;
    $("session-stats").textContent = `${mapFacts(map)} · sessions in it: ${sessions.length}`;
    drawLegend($("map-legend"), sessions);
    const drawn = sessions.filter((s) => s.drawn);
    window.viewerState.map = { id, version: map.latest_version, bounds: map.meta.bounds,
      sessions: sessions.map((s) => ({ id: s.id, role: s.role, status: s.status, drawn: s.drawn, note: s.note,
        color: s.color, poses: s.poses.length })) };
    updateMapSplats();
    setStatus(`map · ${drawn.length} of ${sessions.length} sessions drawn`);
  } catch (err) {
    setStatus(`map ${id}: ${err.message}`, true);
  }
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
  if (!state.overviewPlaced && state.poses.length) placeOverview(); // the path until the map comes
  const key = `${session.revision}|${session.keyframes}|${session.status}|${state.mapFormat}`;
  const due = performance.now() - state.mapFetchedAt >= MAP_REFRESH_MIN_MS;
  // not while the session finishes: such a request waits out the final refinement, and the finished map follows
  const finishing = session.status === "finishing";
  if (session.keyframes > 0 && key !== state.mapKey && due && !state.mapLoading && !finishing) {
    loadSplatMap("sessions", session.id, key);
  }
}

// An open saved map: its sessions' trajectories (those in its world) and its splats, loaded again for a new version.
function updateMapSplats() {
  const view = state.splats;
  if (!view || !state.map) return;
  view.setIntrinsics(state.map.meta.camera);
  view.setTrajectories(mapLayers(state.mapSessions));
  if (!state.overviewPlaced) placeOverview();
  const key = `${state.map.id}|v${state.map.latest_version}|${state.mapFormat}`;
  if (key !== state.mapKey && !state.mapLoading) loadSplatMap("maps", state.map.id, key);
}

const openId = () => state.sessionId || state.mapId;

function updateOpenSplats() {
  if (state.map) updateMapSplats();
  else if (state.session) updateSplats(state.session);
}

// The box an overview frames: a map's metadata bounds; a session's path with its loaded splats.
function overviewBounds() {
  const path = state.map ? state.mapSessions.flatMap((s) => s.poses) : state.poses;
  const pathBounds = boundsOf(path.map(position));
  if (state.map) return state.map.meta.bounds || pathBounds;
  return unionBounds(pathBounds, state.splatsShown ? state.splats.splatBounds() : null);
}

// The splat view on the whole map (or path), from outside it, looking at its centre.
function placeOverview() {
  const bounds = state.splats && overviewBounds();
  if (!bounds) return;
  window.viewerState.splat.overview = { bounds, ...state.splats.overview(bounds) };
  state.overviewPlaced = true;
}

// The map file of a session or a saved map (`kind`: "sessions" or "maps") into the splat view.
async function loadSplatMap(kind, id, key) {
  state.mapLoading = true;
  state.mapFetchedAt = performance.now();
  const format = state.mapFormat;
  try {
    const t0 = performance.now();
    const bytes = new Uint8Array(await (await state.api.map(id, format, kind)).arrayBuffer());
    const fetchMs = performance.now() - t0;
    if (id !== openId()) return;
    const loaded = await state.splats.loadMap(bytes, format, key);
    if (id !== openId()) return;
    state.mapKey = key;
    const first = !state.splatsShown;
    state.splatsShown = true;
    if (first && !state.splats.touched) placeOverview(); // again, now with the splats' extent
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

// The newest tracked pose: the session's, or that of the newest session drawn in the open map.
function newestPose() {
  return state.map ? latestPose(state.mapSessions) : state.poses.at(-1) || null;
}

// The exact reference: the server renders the splat view's camera (pose and pinhole) as a PNG.
function exactServerView() {
  if (!state.splats || !state.sessionId) return;
  serverView.placeAt(state.splats.pose(), true);
  $("render").scrollIntoView({ block: "nearest" });
}

// ----------------------------------------------------------------------------------------------- download

async function downloadMap() {
  const id = openId();
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
    const blob = await (await state.api.map(id, format, state.mapId ? "maps" : "sessions")).blob();
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
    button.disabled = !openId();
  }
}

// ------------------------------------------------------------------------------------------------- wiring

function init() {
  const keyInput = $("api-key");
  keyInput.value = state.api.apiKey;
  keyInput.addEventListener("change", () => {
    state.api.apiKey = keyInput.value.trim();
    sessionStorage.setItem(KEY_STORE, state.api.apiKey);
    refreshLists();
  });
  $("refresh-sessions").addEventListener("click", refreshLists);
  $("refresh-maps").addEventListener("click", refreshLists);
  $("session-filter").addEventListener("input", drawSessions);
  $("status-filter").addEventListener("change", () => { // at once among those loaded, then from the API
    drawSessions();
    sessionList.reset().then(drawSessions, (err) => setStatus(`sessions: ${err.message}`, true));
  });
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
    updateOpenSplats();
  });
  $("splat-overlay").addEventListener("change", (e) => state.splats && state.splats.showOverlay(e.target.checked));
  $("splat-to-pose").addEventListener("click", () => {
    const pose = newestPose();
    if (state.splats && pose) state.splats.setPose(pose);
  });
  $("splat-overview").addEventListener("click", placeOverview);
  $("splat-exact").addEventListener("click", exactServerView);
  startSplatView().then(updateOpenSplats);
  refreshLists();
  if (state.mapId) openMap(state.mapId);
  else if (state.sessionId) selectSession(state.sessionId);
  setInterval(refreshLists, POLL_SESSIONS_MS);
  setInterval(pollSession, POLL_TRAJECTORY_MS);
  setInterval(pollMap, POLL_MAP_MS);
  drawTrajectory();
}

init();
