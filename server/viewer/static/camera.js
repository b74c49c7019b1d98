// Camera math of the viewer, pure functions on plain arrays. Poses are camera-to-world in OpenCV
// axes (x right, y down, z forward); a pose is {R: 3x3 rows, p: [3]} where R's columns are the
// camera's right, down and forward directions in world coordinates.

export const add = (a, b) => a.map((x, i) => x + b[i]);
export const sub = (a, b) => a.map((x, i) => x - b[i]);
export const scale = (a, s) => a.map((x) => x * s);
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
export const norm = (a) => Math.hypot(a[0], a[1], a[2]);
export const unit = (a) => scale(a, 1 / (norm(a) || 1));

export const column = (R, j) => [R[0][j], R[1][j], R[2][j]];
const fromColumns = (a, b, c) => [0, 1, 2].map((i) => [a[i], b[i], c[i]]);
const matmul = (A, B) => A.map((row) => [0, 1, 2].map((j) => row[0] * B[0][j] + row[1] * B[1][j] + row[2] * B[2][j]));
const apply = (A, v) => A.map((row) => dot(row, v));

// Rotation by `angle` radians about the unit `axis` (Rodrigues).
export function rotation(axis, angle) {
  const [x, y, z] = unit(axis);
  const c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [
    [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
    [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
    [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
  ];
}

// 16 row-major numbers <-> {R, p}
export function fromMatrix(m) {
  return { R: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]], p: [m[3], m[7], m[11]] };
}

export function toMatrix({ R, p }) {
  return [...R[0], p[0], ...R[1], p[1], ...R[2], p[2], 0, 0, 0, 1];
}

// Re-orthonormalise R (drift of many small rotations), keeping its forward axis.
function orthonormal(R) {
  const f = unit(column(R, 2));
  const r = unit(sub(column(R, 0), scale(f, dot(column(R, 0), f))));
  return fromColumns(r, cross(f, r), f);
}

// Orbit about the target `distance` ahead: `yaw` about the world `up`, `pitch` about the camera's
// right axis (radians). The target stays where it is.
export function orbit(pose, distance, up, yaw, pitch) {
  const target = add(pose.p, scale(column(pose.R, 2), distance));
  let Q = rotation(up, yaw);
  Q = matmul(rotation(apply(Q, column(pose.R, 0)), pitch), Q);
  const R = orthonormal(matmul(Q, pose.R));
  return { R, p: add(target, apply(Q, sub(pose.p, target))) };
}

// Move the camera along its own right / down / forward axes by [dx, dy, dz] metres.
export function translate(pose, [dx, dy, dz]) {
  const { R, p } = pose;
  return { R, p: add(p, add(add(scale(column(R, 0), dx), scale(column(R, 1), dy)), scale(column(R, 2), dz))) };
}

// Move along the world `up` by `d` metres (fly up/down whatever the camera's tilt).
export function lift(pose, up, d) {
  return { R: pose.R, p: add(pose.p, scale(unit(up), d)) };
}

// Dolly toward the target: the new orbit distance is distance * factor, the target is kept.
export function zoom(pose, distance, factor) {
  return { pose: translate(pose, [0, 0, distance * (1 - factor)]), distance: distance * factor };
}

// Pixel of world point X in a camera {pose, K: [fx, fy, cx, cy]}, or null behind the camera.
export function project(pose, K, X) {
  const d = sub(X, pose.p);
  const x = dot(column(pose.R, 0), d), y = dot(column(pose.R, 1), d), z = dot(column(pose.R, 2), d);
  if (z <= 1e-4) return null;
  return [K[0] * x / z + K[2], K[1] * y / z + K[3]];
}

// The five world points of an input camera's frustum: centre and the image corners at depth `depth`.
export function frustum(camera, depth) {
  const pose = fromMatrix(camera.c2w);
  const [fx, fy, cx, cy] = camera.K;
  const corners = [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]];
  const lifted = corners.map(([u, v]) => {
    const ray = [(u - cx) / fx * depth, (v - cy) / fy * depth, depth];
    return add(pose.p, apply(pose.R, ray));
  });
  return [pose.p, ...lifted];
}

// Intrinsics of a width x height view with the field of view of an input camera (or ~60 degrees),
// its principal point where the camera has it (relative to the image's middle, at the view's scale;
// pixel centres on integers, as canonical_core.resample has them): a view snapped to an input
// camera then draws what that camera saw.
export function viewIntrinsics(camera, width, height) {
  if (!camera) return [0.85 * width, 0.85 * width, width / 2, height / 2];
  const s = width / camera.width;
  const [fx, fy, cx, cy] = camera.K;
  return [fx * s, fy * s, (cx + 0.5) * s - 0.5, height / 2 + (cy + 0.5 - camera.height / 2) * s - 0.5];
}
