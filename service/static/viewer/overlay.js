// The lines drawn over the splats: each trajectory as a path, its keyframes as camera frustums and its loop closures
// as spheres, in the map's world frame (poses: camera-to-world, 16 row-major numbers, OpenCV camera).

import * as THREE from "three";

export const PATH_COLOR = 0x4fc3f7;
export const KEYFRAME_COLOR = 0xffd54f;
const LOOP_COLOR = 0xff5252;
const DEFAULT_K = { width: 4, height: 3, fx: 3.2, fy: 3.2, cx: 2, cy: 1.5 };

function frustumSegments(pose, k, size) {
  // apex and the four image corners at depth `size`, in the camera frame, then to the world
  const m = new THREE.Matrix4().set(...pose);
  const s = Math.cbrt(Math.abs(m.determinant())) || 1;
  const corners = [[0, 0], [k.width, 0], [k.width, k.height], [0, k.height]].map(([u, v]) =>
    new THREE.Vector3(((u - k.cx) / k.fx) * size * s, ((v - k.cy) / k.fy) * size * s, size * s).applyMatrix4(m));
  const apex = new THREE.Vector3(0, 0, 0).applyMatrix4(m);
  const out = [];
  for (let i = 0; i < 4; i++) out.push(apex, corners[i], corners[i], corners[(i + 1) % 4]);
  return out;
}

function clearGroup(group) {
  for (const child of [...group.children]) {
    group.remove(child);
    child.geometry.dispose();
    child.material.dispose();
  }
}

const centresOf = (poses) => poses.map((p) => new THREE.Vector3(p[3], p[7], p[11]));

// Replace what `group` shows by `layers`: [{poses, keyframes, loops, color, keyframeColor}] (colours as 0xRRGGBB;
// a session's path blue and keyframes yellow by default). Frustums are sized by the extent of all the paths.
export function drawLayers(group, layers, intrinsics) {
  clearGroup(group);
  const all = layers.flatMap((layer) => centresOf(layer.poses));
  if (!all.length) return;
  const extent = new THREE.Box3().setFromPoints(all).getSize(new THREE.Vector3()).length();
  const size = Math.max(0.02, 0.06 * extent);
  const k = intrinsics || DEFAULT_K;
  for (const { poses, keyframes = [], loops = [], color = PATH_COLOR, keyframeColor = KEYFRAME_COLOR } of layers) {
    if (!poses.length) continue;
    group.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(centresOf(poses)),
      new THREE.LineBasicMaterial({ color })));
    const segments = keyframes.flatMap((pose) => frustumSegments(pose, k, size));
    if (segments.length) {
      group.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(segments),
        new THREE.LineBasicMaterial({ color: keyframeColor })));
    }
    for (const loop of loops) {
      const marker = new THREE.Mesh(new THREE.SphereGeometry(size * 0.3, 12, 8),
        new THREE.MeshBasicMaterial({ color: LOOP_COLOR }));
      marker.position.set(...loop.position);
      group.add(marker);
    }
  }
}
