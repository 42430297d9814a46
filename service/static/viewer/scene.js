// Pose math and the two trajectory drawings (top-down and 3D), on plain 2D canvases.
// Poses are camera-to-world 4x4 matrices as 16 row-major numbers (OpenCV camera: x right, y down, z forward).

export const position = (p) => [p[3], p[7], p[11]];

function scaleOf(p) {
  return Math.hypot(p[0], p[4], p[8]) || 1;
}

// The camera's viewing direction in the world (third column of R).
export function forward(p) {
  const s = scaleOf(p);
  return [p[2] / s, p[6] / s, p[10] / s];
}

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];

// --------------------------------------------------------------------------------------- top-down (x, z)

function fitBounds(points, width, height, margin) {
  let minX = Infinity, maxX = -Infinity, minZ = Infinity, maxZ = -Infinity;
  for (const [x, , z] of points) {
    minX = Math.min(minX, x); maxX = Math.max(maxX, x);
    minZ = Math.min(minZ, z); maxZ = Math.max(maxZ, z);
  }
  const span = Math.max(maxX - minX, maxZ - minZ, 1e-3);
  const scale = Math.min(width - 2 * margin, height - 2 * margin) / span;
  const cx = (minX + maxX) / 2, cz = (minZ + maxZ) / 2;
  return ([x, , z]) => [width / 2 + (x - cx) * scale, height / 2 + (z - cz) * scale];
}

function clear(ctx, canvas) {
  ctx.fillStyle = "#0b0e11";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
}

function dot(ctx, [x, y], radius, color) {
  ctx.fillStyle = color;
  ctx.beginPath();
  ctx.arc(x, y, radius, 0, 2 * Math.PI);
  ctx.fill();
}

function polyline(ctx, points, color, width) {
  if (points.length < 2) return;
  ctx.strokeStyle = color;
  ctx.lineWidth = width;
  ctx.beginPath();
  ctx.moveTo(...points[0]);
  for (const q of points.slice(1)) ctx.lineTo(...q);
  ctx.stroke();
}

// Returns the number of poses drawn.
export function drawTopDown(canvas, poses, keyframes, loops) {
  const ctx = canvas.getContext("2d");
  clear(ctx, canvas);
  if (!poses.length) {
    ctx.fillStyle = "#8a96a3";
    ctx.fillText("no poses yet", 12, 20);
    return 0;
  }
  const points = poses.map(position);
  const toCanvas = fitBounds(points, canvas.width, canvas.height, 24);
  polyline(ctx, points.map(toCanvas), "#4fc3f7", 2);
  for (const k of keyframes) dot(ctx, toCanvas(position(k)), 3, "#ffd54f");
  for (const l of loops) {
    ctx.strokeStyle = "#ff5252";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc(...toCanvas(l.position), 8, 0, 2 * Math.PI);
    ctx.stroke();
  }
  dot(ctx, toCanvas(points[0]), 5, "#66bb6a");
  const last = poses[poses.length - 1];
  const head = toCanvas(position(last));
  const f = forward(last);
  const dir = Math.atan2(f[2], f[0]);
  ctx.fillStyle = "#4fc3f7";
  ctx.beginPath();
  ctx.moveTo(head[0] + 12 * Math.cos(dir), head[1] + 12 * Math.sin(dir));
  ctx.lineTo(head[0] + 6 * Math.cos(dir + 2.4), head[1] + 6 * Math.sin(dir + 2.4));
  ctx.lineTo(head[0] + 6 * Math.cos(dir - 2.4), head[1] + 6 * Math.sin(dir - 2.4));
  ctx.fill();
  return poses.length;
}

// --------------------------------------------------------------------------------------------- 3D orbit

export class OrbitView {
  constructor(canvas) {
    this.canvas = canvas;
    this.yaw = 0.6;
    this.pitch = 0.5;
    this.zoom = 1.0;
    this.data = { poses: [], keyframes: [], loops: [] };
    let drag = null;
    canvas.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; });
    window.addEventListener("mouseup", () => { drag = null; });
    window.addEventListener("mousemove", (e) => {
      if (!drag) return;
      this.yaw += (e.clientX - drag[0]) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      this.draw();
    });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom *= e.deltaY > 0 ? 0.9 : 1.1;
      this.draw();
    }, { passive: false });
  }

  update(poses, keyframes, loops) {
    this.data = { poses, keyframes, loops };
    return this.draw();
  }

  // World -> canvas: orbit around the centroid; world "up" is -y (the OpenCV camera's y points down).
  projector(points) {
    const n = points.length;
    const centre = points.reduce((a, p) => [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n], [0, 0, 0]);
    const radius = Math.max(1e-3, ...points.map((p) => Math.hypot(...sub(p, centre))));
    const distance = 3 * radius / this.zoom;
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw), cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const focal = Math.min(this.canvas.width, this.canvas.height) * 1.2;
    return {
      radius, centre,
      project: (p) => {
        const [dx, dy, dz] = sub(p, centre);
        const x1 = cy * dx - sy * dz, z1 = sy * dx + cy * dz; // yaw about the vertical
        const y1 = -dy;
        const y2 = cp * y1 - sp * z1, z2 = sp * y1 + cp * z1; // pitch
        const depth = Math.max(1e-3, distance + z2);
        return [this.canvas.width / 2 + focal * x1 / depth, this.canvas.height / 2 - focal * y2 / depth];
      },
    };
  }

  draw() {
    const { canvas } = this;
    const ctx = canvas.getContext("2d");
    clear(ctx, canvas);
    const { poses, keyframes, loops } = this.data;
    if (!poses.length) return 0;
    const points = poses.map(position);
    const { project, radius, centre } = this.projector(points);
    const floor = Math.max(...points.map((p) => p[1])) + 0.1 * radius; // below the cameras (y is down)
    ctx.strokeStyle = "#1f2a33";
    ctx.lineWidth = 1;
    for (let i = -4; i <= 4; i++) {
      const a = (i / 4) * 1.5 * radius;
      const b = 1.5 * radius;
      polyline(ctx, [project([centre[0] + a, floor, centre[2] - b]), project([centre[0] + a, floor, centre[2] + b])],
        "#1f2a33", 1);
      polyline(ctx, [project([centre[0] - b, floor, centre[2] + a]), project([centre[0] + b, floor, centre[2] + a])],
        "#1f2a33", 1);
    }
    polyline(ctx, points.map(project), "#4fc3f7", 2);
    for (const k of keyframes) {
      const c = position(k), f = forward(k), len = 0.12 * radius;
      polyline(ctx, [project(c), project([c[0] + f[0] * len, c[1] + f[1] * len, c[2] + f[2] * len])], "#ffd54f", 1);
      dot(ctx, project(c), 2.5, "#ffd54f");
    }
    for (const l of loops) {
      ctx.strokeStyle = "#ff5252";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(...project(l.position), 7, 0, 2 * Math.PI);
      ctx.stroke();
    }
    dot(ctx, project(points[0]), 4, "#66bb6a");
    dot(ctx, project(points[points.length - 1]), 5, "#4fc3f7");
    return poses.length;
  }
}

// ---------------------------------------------------------------------------------------- virtual camera

// A camera-to-world rigid pose the user moves in its own frame (x right, y down, z forward).
export class VirtualCamera {
  constructor() {
    this.R = [1, 0, 0, 0, 1, 0, 0, 0, 1]; // row-major 3x3
    this.t = [0, 0, 0];
  }

  setFromPose(p) {
    const s = scaleOf(p);
    this.R = [p[0] / s, p[1] / s, p[2] / s, p[4] / s, p[5] / s, p[6] / s, p[8] / s, p[9] / s, p[10] / s];
    this.t = [p[3], p[7], p[11]];
  }

  pose() {
    const [r, t] = [this.R, this.t];
    return [r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1], r[6], r[7], r[8], t[2], 0, 0, 0, 1];
  }

  translate(local) { // a step expressed in the camera frame
    const r = this.R;
    for (let i = 0; i < 3; i++) this.t[i] += r[3 * i] * local[0] + r[3 * i + 1] * local[1] + r[3 * i + 2] * local[2];
  }

  rotate(axis, angle) { // R <- R * rotation about the camera's own x or y axis
    const c = Math.cos(angle), s = Math.sin(angle);
    const m = axis === "x" ? [1, 0, 0, 0, c, -s, 0, s, c] : [c, 0, s, 0, 1, 0, -s, 0, c];
    const r = this.R, out = new Array(9).fill(0);
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) {
        for (let k = 0; k < 3; k++) out[3 * i + j] += r[3 * i + k] * m[3 * k + j];
      }
    }
    this.R = out;
  }
}
