// A session's live feed (WS /v1/sessions/{id}/events): tracking events and loop closures as they happen, the newest
// first in a short list, and the tracking state they tell.

const EVENT_TYPES = new Set(["tracking_lost", "relocalized", "initialized", "loop_closed", "finished", "error"]);
const MAX_EVENTS_SHOWN = 12;
const TRACKING = { tracking_lost: ["lost", "lost"], relocalized: ["tracking", "ok"], initialized: ["tracking", "ok"],
  finished: ["finished", ""] }; // event -> [text, class] of the tracking state

export class EventFeed {
  // onPose() for each live pose, onEvent(message) for each event shown.
  constructor(list, trackingLabel, { onPose = () => {}, onEvent = () => {} } = {}) {
    Object.assign(this, { list, trackingLabel, onPose, onEvent });
    this.ws = null;
  }

  open(sessionId, apiKey) {
    this.close();
    this.list.replaceChildren();
    this.trackingLabel.textContent = "tracking: –";
    this.trackingLabel.className = "";
    const scheme = window.location.protocol === "https:" ? "wss" : "ws";
    const query = apiKey ? `?api_key=${encodeURIComponent(apiKey)}` : "";
    const ws = new WebSocket(`${scheme}://${window.location.host}/v1/sessions/${encodeURIComponent(sessionId)}`
      + `/events${query}`);
    this.ws = ws;
    ws.addEventListener("message", (e) => {
      if (ws !== this.ws) return; // another session opened since
      let message;
      try { message = JSON.parse(e.data); } catch (_) { return; }
      if (message.type === "pose") this.onPose(message);
      else if (EVENT_TYPES.has(message.type)) this.show(message);
    });
  }

  close() {
    if (this.ws) this.ws.close();
    this.ws = null;
  }

  show(message) {
    const li = document.createElement("li");
    li.className = message.type;
    const at = message.seq !== undefined ? ` @${message.seq}` : "";
    li.textContent = `${message.type.replace("_", " ")}${at}`;
    this.list.prepend(li);
    while (this.list.children.length > MAX_EVENTS_SHOWN) this.list.lastChild.remove();
    const tracking = TRACKING[message.type];
    if (tracking) {
      this.trackingLabel.textContent = `tracking: ${tracking[0]}`;
      this.trackingLabel.className = tracking[1];
    }
    this.onEvent(message);
  }
}
