// Axis-aligned boxes {min: [x, y, z], max: [x, y, z]} in the map's world: what an overview frames.

// The box of `points` ([x, y, z] each); null for none.
export function boundsOf(points) {
  if (!points.length) return null;
  const min = [Infinity, Infinity, Infinity], max = [-Infinity, -Infinity, -Infinity];
  for (const p of points) {
    for (let i = 0; i < 3; i++) {
      min[i] = Math.min(min[i], p[i]);
      max[i] = Math.max(max[i], p[i]);
    }
  }
  return { min, max };
}

// The smallest box holding every box given (nulls skipped); null when none is given.
export function unionBounds(...boxes) {
  const present = boxes.filter(Boolean);
  if (!present.length) return null;
  return boundsOf(present.flatMap((b) => [b.min, b.max]));
}

// The box from the `lo` to the `hi` quantile on each axis of points given as flat x, y, z triples (as the map's
// metadata bounds its surfels: 1st to 99th percentile, so that a few stray splats do not make the box); null for none.
export function quantileBounds(flat, lo = 0.01, hi = 0.99) {
  const n = Math.floor(flat.length / 3);
  if (!n) return null;
  const min = [], max = [];
  for (let axis = 0; axis < 3; axis++) {
    const values = new Float64Array(n);
    for (let i = 0; i < n; i++) values[i] = flat[3 * i + axis];
    values.sort();
    min.push(values[Math.floor(lo * (n - 1))]);
    max.push(values[Math.ceil(hi * (n - 1))]);
  }
  return { min, max };
}
