// The server's render of a session's map (GET /v1/sessions/{id}/render) from a camera the user moves with buttons
// and keys: the exact reference of what the splat view draws in the page.

import { boundsOf } from "./bounds.js";
import { VirtualCamera, position } from "./scene.js";

const RENDER_MAX_WIDTH = 320;
const RENDER_DELAY_MS = 120; // moves within this are rendered once

const MOVES = {
  forward: (c, s) => c.translate([0, 0, s]), back: (c, s) => c.translate([0, 0, -s]),
  left: (c, s) => c.translate([-s, 0, 0]), right: (c, s) => c.translate([s, 0, 0]),
  up: (c, s) => c.translate([0, -s, 0]), down: (c, s) => c.translate([0, s, 0]),
  "yaw-left": (c) => c.rotate("y", -0.1), "yaw-right": (c) => c.rotate("y", 0.1),
  "pitch-up": (c) => c.rotate("x", 0.1), "pitch-down": (c) => c.rotate("x", -0.1),
};
export const MOVE_KEYS = { w: "forward", s: "back", a: "left", d: "right", q: "up", e: "down", ArrowLeft: "yaw-left",
  ArrowRight: "yaw-right", ArrowUp: "pitch-up", ArrowDown: "pitch-down" };

// The session's pinhole scaled to at most RENDER_MAX_WIDTH pixels wide (a guess of 80% focal without one).
function renderCamera(k) {
  const width = k && k.width ? k.width : 320;
  const height = k && k.height ? k.height : 240;
  const scale = Math.min(1, RENDER_MAX_WIDTH / width);
  const fx = k ? k.fx : 0.8 * width, fy = k ? k.fy : 0.8 * width;
  const cx = k ? k.cx : width / 2, cy = k ? k.cy : height / 2;
  return { width: Math.round(width * scale), height: Math.round(height * scale), fx: fx * scale, fy: fy * scale,
    cx: cx * scale, cy: cy * scale };
}

// A step 5% of the path's longest side.
function stepSize(poses) {
  if (poses.length < 2) return 0.05;
  const { min, max } = boundsOf(poses.map(position));
  return Math.max(0.01, 0.05 * Math.max(...max.map((v, i) => v - min[i])));
}

export class ServerView {
  // onRendered() after each image shown; onError(err) when a render fails.
  constructor(api, img, { onRendered = () => {}, onError = () => {} } = {}) {
    Object.assign(this, { api, img, onRendered, onError });
    this.camera = new VirtualCamera();
    this.kind = "color";
    this.open(null);
    this.rendering = false;
    this.queued = false;
    this.timer = null;
    this.url = null;
  }

  // A session (null: none): the camera goes to its newest pose once it has one.
  open(sessionId) {
    Object.assign(this, { sessionId, session: null, poses: [], placed: false });
  }

  // The session's record and trajectory, at each poll.
  follow(session, poses) {
    Object.assign(this, { session, poses });
    if (!this.placed && poses.length) this.placeAt(poses[poses.length - 1]);
  }

  placeAt(pose, now = false) {
    this.camera.setFromPose(pose);
    this.placed = true;
    if (now) this.renderNow();
    else this.schedule();
  }

  setKind(kind) {
    this.kind = kind;
    this.schedule();
  }

  move(name) {
    if (!this.placed) return;
    MOVES[name](this.camera, stepSize(this.poses));
    this.schedule();
  }

  schedule() {
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.renderNow(), RENDER_DELAY_MS);
  }

  async renderNow() {
    if (!this.sessionId || !this.placed) return;
    if (this.rendering) {
      this.queued = true;
      return;
    }
    this.rendering = true;
    try {
      const k = this.session && this.session.intrinsics;
      const blob = await this.api.render(this.sessionId, this.camera.pose(), renderCamera(k), this.kind);
      if (this.url) URL.revokeObjectURL(this.url);
      this.url = URL.createObjectURL(blob);
      this.img.src = this.url;
      this.onRendered();
    } catch (err) {
      this.onError(err);
    } finally {
      this.rendering = false;
      if (this.queued) {
        this.queued = false;
        this.schedule();
      }
    }
  }
}
