// A session's or a saved map's map as Gaussian splats in WebGL (Spark on three.js, vendored under ./vendor), with
// trajectories, keyframe frustums and loop closures in the same scene (overlay.js), orbit and fly controls (mouse,
// keyboard, touch), an overview from outside the map, and a camera that can be put exactly at a tracked pose with
// the session's intrinsics (the server renders the same view).
//
// The scene is in the map's world frame (OpenCV: x right, y down, z forward); a three.js camera looks down its -z
// with y up, so its world matrix is the pose times diag(1, -1, -1).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkControls, SparkRenderer, SplatFileType, SplatMesh } from "@sparkjsdev/spark";
import { quantileBounds } from "./bounds.js";
import { drawLayers } from "./overlay.js";

const GL_FROM_CV = new THREE.Matrix4().makeScale(1, -1, -1);
// SPZ stores right-up-back axes (its specification); the map's world is right-down-forward: a half turn about x.
const SPZ_TO_WORLD = new THREE.Quaternion(1, 0, 0, 0);
const FILE_TYPES = { spz: SplatFileType.SPZ, splat: SplatFileType.SPLAT, ply: SplatFileType.PLY };
const NEAR = 0.01;
const FAR = 1000;
// An overview looks at the map's centre from behind and above where the first camera stood (it looked along +z,
// with -y up) and a little to its right.
const OVERVIEW_FROM = new THREE.Vector3(0.35, -0.75, -1).normalize();
const OVERVIEW_MARGIN = 1.1; // the bounding sphere fills the narrower side of the view less this

// A three.js object's pose from a camera-to-world similarity (16 row-major numbers; the scale is dropped).
function cameraMatrix(pose) {
  const m = new THREE.Matrix4().set(...pose);
  const s = Math.cbrt(Math.abs(m.determinant())) || 1;
  const e = m.elements; // column-major
  for (const i of [0, 1, 2, 4, 5, 6, 8, 9, 10]) e[i] /= s;
  return m.multiply(GL_FROM_CV);
}

// The OpenGL projection of a pinhole camera K (pixels, OpenCV convention) for a width x height image.
export function pinholeProjection(k, width, height, near = NEAR, far = FAR) {
  return new THREE.Matrix4().set(
    2 * k.fx / width, 0, 1 - 2 * k.cx / width, 0,
    0, 2 * k.fy / height, 2 * k.cy / height - 1, 0,
    0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, -1, 0,
  );
}

export class SplatView {
  constructor(canvas, { onFrame = () => {} } = {}) {
    this.canvas = canvas;
    this.onFrame = onFrame;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(1);
    this.renderer.setClearColor(0x000000, 1);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(60, canvas.width / canvas.height, NEAR, FAR);
    this.camera.up.set(0, -1, 0); // orbit about the world's vertical: -y, the first camera's up (OpenCV world)
    this.spark = new SparkRenderer({ renderer: this.renderer, enable2DGS: true });
    this.scene.add(this.spark);
    this.intrinsics = null; // pinhole of the session's camera (scaled to the canvas), else a 60-degree view
    this.mesh = null;
    this.layers = []; // what the overlay draws: [{id, poses, color}]
    this.touched = false; // whether the user moved the camera since the last overview
    this.loaded = null; // {format, bytes, splats, revision, ms}
    this.overlay = new THREE.Group();
    this.scene.add(this.overlay);
    this.frames = 0;
    this.fps = 0;
    this.firstSplatFrameAt = null;
    this.fpsWindow = { start: performance.now(), frames: 0 };
    this.orbit = new OrbitControls(this.camera, canvas);
    this.orbit.enableDamping = false;
    this.orbit.listenToKeyEvents(canvas);
    this.fly = new SparkControls({ canvas });
    this.setMode("orbit");
    canvas.tabIndex = 0;
    // Spark's keyboard movement listens on the whole document: only while this canvas has the focus.
    canvas.addEventListener("focus", () => { this.fly.fpsMovement.enable = this.mode === "fly"; });
    canvas.addEventListener("blur", () => { this.fly.fpsMovement.enable = false; });
    canvas.addEventListener("pointerdown", () => canvas.focus());
    const touch = () => { this.touched = true; };
    for (const event of ["pointerdown", "wheel", "keydown"]) canvas.addEventListener(event, touch);
    this.renderer.setAnimationLoop(() => this.frame());
  }

  // "orbit", "fly", or "still" (no controls: the camera stays exactly where setPose put it).
  setMode(mode) {
    this.mode = mode;
    this.orbit.enabled = mode === "orbit";
    this.fly.pointerControls.enable = mode === "fly";
    this.fly.fpsMovement.enable = mode === "fly" && document.activeElement === this.canvas;
    if (mode === "orbit") this.retarget();
  }

  // The orbit centre: in front of the camera, at the distance of the map's (or the path's) centre.
  retarget(centre = this.sceneCentre()) {
    const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(this.camera.quaternion);
    const distance = centre ? Math.max(0.2, centre.clone().sub(this.camera.position).dot(forward)) : 1;
    this.orbit.target.copy(this.camera.position).addScaledVector(forward, distance);
    this.orbit.update();
  }

  sceneCentre() {
    const box = new THREE.Box3().setFromObject(this.overlay);
    if (this.mesh && this.mesh.getBoundingBox) {
      try { box.union(this.mesh.getBoundingBox()); } catch (_) { /* not ready */ }
    }
    return box.isEmpty() ? null : box.getCenter(new THREE.Vector3());
  }

  setIntrinsics(k) {
    this.intrinsics = k;
  }

  // The drawing buffer's size in pixels (the CSS size is left to the page).
  resize(width, height) {
    this.renderer.setSize(width, height, false);
  }

  // Put the camera at a tracked pose (camera-to-world, 16 row-major floats).
  setPose(pose) {
    cameraMatrix(pose).decompose(this.camera.position, this.camera.quaternion, new THREE.Vector3());
    this.camera.updateMatrixWorld(true);
    if (this.mode === "orbit") this.retarget();
  }

  // The camera as a camera-to-world pose in the map's frame (what the server's /render takes).
  pose() {
    this.camera.updateMatrixWorld(true);
    const m = this.camera.matrixWorld.clone().multiply(GL_FROM_CV);
    const e = m.elements;
    return [e[0], e[4], e[8], e[12], e[1], e[5], e[9], e[13], e[2], e[6], e[10], e[14], 0, 0, 0, 1];
  }

  // The pinhole of the current view at the canvas size (for the server's render of the same view).
  viewIntrinsics() {
    const { width, height } = this.canvas;
    if (this.intrinsics) {
      const sx = width / this.intrinsics.width, sy = height / this.intrinsics.height;
      return { width, height, fx: this.intrinsics.fx * sx, fy: this.intrinsics.fy * sy, cx: this.intrinsics.cx * sx,
        cy: this.intrinsics.cy * sy };
    }
    const f = 0.5 * height / Math.tan(THREE.MathUtils.degToRad(30));
    return { width, height, fx: f, fy: f, cx: width / 2, cy: height / 2 };
  }

  // Replace the map by `bytes` in `format` (spz, splat or ply); the old map stays on screen until the new is ready.
  async loadMap(bytes, format, revision = null) {
    const t0 = performance.now();
    const mesh = new SplatMesh({ fileBytes: bytes, fileType: FILE_TYPES[format] });
    if (format === "spz") mesh.quaternion.copy(SPZ_TO_WORLD);
    await mesh.initialized;
    this.scene.add(mesh);
    if (this.mesh) {
      this.scene.remove(this.mesh);
      this.mesh.dispose();
    }
    const firstMap = !this.mesh;
    this.mesh = mesh;
    const splats = mesh.packedSplats ? mesh.packedSplats.numSplats : (mesh.numSplats ?? null);
    this.loaded = { format, bytes: bytes.byteLength, splats, revision, ms: performance.now() - t0 };
    if (firstMap && this.mode === "orbit") this.retarget();
    return this.loaded;
  }

  // Nothing shown: no map, no trajectories (another session or map is opened).
  clear() {
    if (this.mesh) {
      this.scene.remove(this.mesh);
      this.mesh.dispose();
    }
    this.mesh = null;
    this.loaded = null;
    this.setTrajectories([]);
  }

  // Every splat as Spark decoded it (the browser's reading of the file, for tests): flat arrays.
  readSplats(limit = Infinity) {
    const out = { centers: [], scales: [], quats: [], opacities: [], colors: [] };
    if (!this.mesh) return out;
    this.mesh.updateMatrixWorld(true);
    this.mesh.forEachSplat((i, center, scales, q, opacity, color) => {
      if (i >= limit) return;
      out.centers.push(center.x, center.y, center.z);
      out.scales.push(scales.x, scales.y, scales.z);
      out.quats.push(q.w, q.x, q.y, q.z);
      out.opacities.push(opacity);
      out.colors.push(color.r, color.g, color.b);
    });
    return out;
  }

  // Trajectory (blue), keyframe frustums (yellow), loop closures (red) in the world frame.
  setTrajectory(poses, keyframes, loops) {
    this.setTrajectories([{ poses, keyframes, loops }]);
  }

  // Several trajectories, each its own colours: [{poses, keyframes, loops, color, keyframeColor}] (overlay.js).
  setTrajectories(layers) {
    drawLayers(this.overlay, layers, this.intrinsics);
    this.layers = layers.map((layer) => ({ id: layer.id ?? null, poses: layer.poses.length, color: layer.color }));
  }

  // The box of the loaded map's splat centres in the world (1st to 99th percentile on each axis); null without one.
  splatBounds() {
    if (!this.mesh) return null;
    this.mesh.updateMatrixWorld(true);
    const flat = [];
    const p = new THREE.Vector3();
    this.mesh.forEachSplat((i, center) => {
      p.copy(center).applyMatrix4(this.mesh.matrixWorld);
      flat.push(p.x, p.y, p.z);
    });
    return quantileBounds(flat);
  }

  // The camera outside `bounds` ({min, max}, world), looking at its centre with all of it in view; the orbit turns
  // about that centre. Returns {position, target}.
  overview(bounds) {
    const min = new THREE.Vector3(...bounds.min), max = new THREE.Vector3(...bounds.max);
    const centre = min.clone().add(max).multiplyScalar(0.5);
    const radius = Math.max(0.05, min.distanceTo(max) / 2);
    const k = this.viewIntrinsics();
    const halfAngle = Math.min(Math.atan(k.width / (2 * k.fx)), Math.atan(k.height / (2 * k.fy)));
    this.camera.position.copy(centre).addScaledVector(OVERVIEW_FROM, OVERVIEW_MARGIN * radius / Math.sin(halfAngle));
    this.camera.lookAt(centre);
    this.camera.updateMatrixWorld(true);
    this.orbit.target.copy(centre);
    if (this.mode === "orbit") this.orbit.update();
    this.touched = false;
    return { position: this.camera.position.toArray(), target: centre.toArray() };
  }

  showOverlay(visible) {
    this.overlay.visible = visible;
  }

  frame() {
    const { width, height } = this.canvas;
    if (this.mode === "orbit") this.orbit.update();
    else if (this.mode === "fly") this.fly.update(this.camera);
    const k = this.viewIntrinsics();
    this.camera.projectionMatrix.copy(pinholeProjection(k, width, height));
    this.camera.projectionMatrixInverse.copy(this.camera.projectionMatrix).invert();
    this.renderer.render(this.scene, this.camera);
    this.frames += 1;
    const now = performance.now();
    if (this.mesh && this.firstSplatFrameAt === null) this.firstSplatFrameAt = now;
    this.fpsWindow.frames += 1;
    if (now - this.fpsWindow.start >= 1000) {
      this.fps = (1000 * this.fpsWindow.frames) / (now - this.fpsWindow.start);
      this.fpsWindow = { start: now, frames: 0 };
    }
    this.onFrame(this);
  }
}
