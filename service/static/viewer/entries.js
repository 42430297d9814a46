// The entries of the session and map lists, and the facts of a map (its list entry, and the bar of an open map).

const LIVE = new Set(["created", "streaming", "finishing"]); // statuses whose tracking state is worth showing
const SCALES = { metric: "metric", up_to_scale: "up to scale" };

export const isLive = (session) => LIVE.has(session.status);

function ago(iso) {
  const s = Math.max(0, (Date.now() - Date.parse(iso)) / 1000);
  if (s < 90) return `${Math.round(s)} s ago`;
  return s < 5400 ? `${Math.round(s / 60)} min ago` : `${Math.round(s / 3600)} h ago`;
}

const plural = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;

function span(className, text) {
  const el = document.createElement("span");
  el.className = className;
  el.textContent = text;
  return el;
}

// An <li> for the record `id`, titled, that opens it when clicked (the link too, without leaving the page).
function entry(id, title, href, linkText, open) {
  const li = document.createElement("li");
  li.dataset.id = id;
  const link = document.createElement("a");
  link.href = href;
  link.textContent = linkText;
  link.addEventListener("click", (e) => { e.preventDefault(); e.stopPropagation(); open(id); });
  li.append(span("title", title), link);
  li.addEventListener("click", () => open(id));
  return li;
}

// A session: its status, frames, keyframes, last pose time and device; its tracking state only while it is live
// (a finished session is not "tracking").
export function sessionEntry(s, open) {
  const live = isLive(s);
  const li = entry(s.id, s.name || s.id, `/viewer?session=${encodeURIComponent(s.id)}`, live ? "live view" : "view",
    open);
  li.dataset.status = s.status;
  const meta = span("meta", "");
  meta.append(span(`status status-${s.status}`, s.status), ` · ${s.frames_processed} frames · ${s.keyframes} `
    + `keyframes · last pose ${s.frames_processed ? ago(s.updated_at) : "–"} · ${s.device_id || "no device"}`);
  li.append(meta);
  const tracking = live ? s.tracking_state || (s.frames_processed ? null : "waiting") : null;
  if (tracking) li.append(span(`meta tracking-${tracking}`, `tracking: ${tracking}`));
  return li;
}

export function megabytes(bytes) {
  return `${(bytes / 1e6).toFixed(bytes < 1e7 ? 2 : 1)} MB`;
}

// What a saved map holds: version, keyframes, surfels, package size, scale, the sessions that built it.
export function mapFacts(m) {
  const meta = m.meta;
  return [`v${m.latest_version}`, plural(meta.keyframes, "keyframe"), `${meta.surfels.toLocaleString("en")} surfels`,
    megabytes(m.size_bytes), SCALES[meta.scale] || meta.scale, `built by ${plural(meta.sessions.length, "session")}`]
    .join(" · ");
}

export function mapEntry(m, open) {
  const li = entry(m.id, m.name || m.id, `/viewer?map=${encodeURIComponent(m.id)}`, "view", open);
  li.dataset.status = m.status;
  li.append(span("meta", mapFacts(m)));
  return li;
}
