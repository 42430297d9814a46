// An open saved map's sessions: each one's trajectory where its poses are in the map's world, a colour each, and a
// legend that lists them all (those not drawn marked, with why).

const PALETTE = ["#4fc3f7", "#ffb74d", "#ba68c8", "#81c784", "#f06292", "#fff176", "#4db6ac", "#9575cd", "#e57373",
  "#aed581"];

// Whether a session's poses are in the map's world, and why, from what the API says: the map's entry of the session
// ({id, role, map_mode}), its record (null when unreadable, `unreadable` saying why) and the map's versions.
//   built: the map was saved from the session, so the map's world is the session's;
//   used, and made a version (extend): a version is made only by a session that relocalized;
//   used, tracking_state "tracking": the worker reports "not_relocalized" for a session tracked but never found in
//   the map, so "tracking" means found, its poses revised into the map's world;
//   used, "lost" or "initializing": the record does not say whether it was found before, so it is not drawn.
export function placement(entry, record, versions, unreadable = null) {
  if (!record) return { drawn: false, note: unreadable || "deleted" };
  if (entry.role === "built") return { drawn: true, note: "built the map" };
  const made = versions.find((v) => v.session_id === entry.id);
  if (made) return { drawn: true, note: `relocalized, made version ${made.version}` };
  const state = record.tracking_state;
  if (state === "tracking") return { drawn: true, note: "relocalized" };
  if (state === "not_relocalized") return { drawn: false, note: "never relocalized: its poses are in its own world" };
  if (!state) return { drawn: false, note: "no poses yet" };
  return { drawn: false, note: `${state}, not known to have relocalized` };
}

// Loads a map and its sessions' trajectories (kept while a session's record says they did not change).
export class MapSessions {
  constructor(api) {
    this.api = api;
    this.trajectories = new Map(); // session id -> {key, poses, keyframes}
  }

  // {map, sessions: [{id, role, map_mode, status, name, drawn, note, color, poses, keyframes}]}, oldest first.
  async load(mapId) {
    const map = await this.api.savedMap(mapId);
    const sessions = await Promise.all(map.sessions.map((entry, i) =>
      this.session(entry, map.versions, PALETTE[i % PALETTE.length])));
    return { map, sessions };
  }

  async session(entry, versions, color) {
    let record = null, unreadable = null;
    try {
      record = await this.api.session(entry.id);
    } catch (err) {
      if (err.status !== 403 && err.status !== 404) throw err;
      unreadable = err.status === 404 ? "deleted" : "not readable with this API key";
    }
    const place = placement(entry, record, versions, unreadable);
    const out = { ...entry, name: record ? record.name : null, color, ...place, poses: [], keyframes: [] };
    return place.drawn ? { ...out, ...await this.trajectory(record) } : out;
  }

  async trajectory(record) {
    const key = `${record.revision}|${record.frames_processed}|${record.tracking_state}|${record.status}`;
    const known = this.trajectories.get(record.id);
    if (known && known.key === key) return known;
    const [all, keyframes] = await Promise.all([this.api.trajectory(record.id, "all"),
      this.api.trajectory(record.id, "keyframes")]);
    const got = { key, poses: all.poses.map((p) => p.pose), keyframes: keyframes.poses.map((p) => p.pose) };
    this.trajectories.set(record.id, got);
    return got;
  }
}

// The splat view's overlay: the drawn sessions, each in its colour.
export function mapLayers(sessions) {
  return sessions.filter((s) => s.drawn).map((s) => ({ id: s.id, poses: s.poses, keyframes: s.keyframes,
    color: s.color, keyframeColor: s.color }));
}

// The newest pose of the newest session drawn; null without one.
export function latestPose(sessions) {
  const drawn = sessions.filter((s) => s.drawn && s.poses.length);
  return drawn.length ? drawn[drawn.length - 1].poses.at(-1) : null;
}

export function drawLegend(list, sessions) {
  list.replaceChildren(...sessions.map((s) => {
    const li = document.createElement("li");
    li.dataset.id = s.id;
    li.dataset.drawn = String(s.drawn);
    li.classList.toggle("off-map", !s.drawn);
    const swatch = document.createElement("i");
    swatch.style.borderColor = s.color;
    if (s.drawn) swatch.style.background = s.color;
    const mode = s.map_mode ? ` (${s.map_mode})` : "";
    const shown = s.drawn ? `${s.poses.length} poses, ${s.note}` : `not drawn: ${s.note}`;
    li.append(swatch, `${s.name || s.id} · ${s.role}${mode} · ${s.status || "deleted"} · ${shown}`);
    return li;
  }));
}
