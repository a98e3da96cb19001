// Where the person stands: the camera fields a lift is sent with (intrinsics, the person's height) and
// the root trajectory they give (root_camera_m of each frame), drawn from above.

import { COLOURS } from "./view.js";

// The request fields of the page's camera inputs: {extra} to send, or {error: {slot, message}}. The
// height goes as typed (the service names a bad one); intrinsics must be four numbers.
export function cameraFields(intrinsicsText, heightText) {
  const extra = {};
  const typed = intrinsicsText.trim();
  if (typed) {
    const values = typed.split(/[\s,]+/).map(Number);
    if (values.length !== 4 || !values.every(Number.isFinite) || values[0] <= 0 || values[1] <= 0) {
      return { error: { slot: "intrinsics", message: `expected fx, fy, cx, cy: 4 numbers in px, fx and fy > 0, got "${typed.slice(0, 60)}"` } };
    }
    extra.intrinsics = { focal_px: values.slice(0, 2), principal_point_px: values.slice(2) };
  }
  const height = heightText.trim();
  if (height) extra.person_height_m = Number.isFinite(Number(height)) ? Number(height) : height;
  return { extra };
}

// The followed person's root per frame: [x, y, z] m in the camera frame, or null.
export function rootsOf(results, poseAt, count) {
  const roots = [];
  for (let k = 0; k < count; k += 1) {
    const at = poseAt(k);
    const root = at === null ? null : results[at]?.root_camera_m;
    roots.push(Array.isArray(root) && root.length === 3 ? root : null);
  }
  return roots;
}

// The trajectory seen from above: x to the right, depth z away from the camera (up the canvas), the
// camera at the bottom; the path over all frames, the current frame's root marked. Square metres.
export function drawTrajectory(canvas, roots, current) {
  const ctx = canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = COLOURS.background;
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const known = roots.filter(Boolean);
  if (!known.length) return;
  const xs = known.map((r) => r[0]);
  const zs = known.map((r) => r[2]);
  const [x0, x1, z0, z1] = [Math.min(...xs), Math.max(...xs), Math.min(...zs), Math.max(...zs)];
  const span = Math.max(x1 - x0, z1 - z0, 1);  // at least a metre across
  const margin = 34;
  const scale = Math.min(canvas.width, canvas.height - 18) / (span * 1.25) ;
  const at = (r) => [canvas.width / 2 + (r[0] - (x0 + x1) / 2) * scale,
    (canvas.height - 18) / 2 - (r[2] - (z0 + z1) / 2) * scale];
  grid(ctx, canvas, at, scale, margin);
  ctx.strokeStyle = COLOURS.centre;
  ctx.lineWidth = 2;
  ctx.beginPath();
  let open = false;
  for (const r of roots) {  // a frame without a root breaks the path
    if (!r) { open = false; continue; }
    if (open) ctx.lineTo(...at(r)); else ctx.moveTo(...at(r));
    open = true;
  }
  ctx.stroke();
  for (const r of known) {
    ctx.fillStyle = COLOURS.detector;
    ctx.beginPath();
    ctx.arc(...at(r), 2, 0, 2 * Math.PI);
    ctx.fill();
  }
  const now = roots[current];
  if (now) {
    ctx.fillStyle = COLOURS.imputed;
    ctx.beginPath();
    ctx.arc(...at(now), 6, 0, 2 * Math.PI);
    ctx.fill();
  }
  ctx.fillStyle = COLOURS.detector;
  ctx.font = "12px system-ui, sans-serif";
  ctx.fillText(`x ${x0.toFixed(2)} to ${x1.toFixed(2)} m, depth ${z0.toFixed(2)} to ${z1.toFixed(2)} m (camera below)`, 8, canvas.height - 6);
}

// Lines every half metre (every metre when the span is wide), labelled with their depth.
function grid(ctx, canvas, at, scale, margin) {
  const step = scale > 60 ? 0.5 : 1;
  ctx.strokeStyle = COLOURS.grid;
  ctx.lineWidth = 1;
  ctx.fillStyle = COLOURS.detector;
  ctx.font = "11px system-ui, sans-serif";
  const origin = at([0, 0, 0]);
  const first = Math.floor(-origin[0] / scale / step) * step;
  for (let x = first; origin[0] + x * scale < canvas.width; x += step) {
    const px = origin[0] + x * scale;
    ctx.beginPath(); ctx.moveTo(px, 0); ctx.lineTo(px, canvas.height - 18); ctx.stroke();
  }
  const near = Math.floor(-(origin[1] - (canvas.height - 18)) / scale / step) * step;
  for (let z = near; origin[1] - z * scale > 0; z += step) {
    const py = origin[1] - z * scale;
    if (py > canvas.height - 18) continue;
    ctx.beginPath(); ctx.moveTo(0, py); ctx.lineTo(canvas.width, py); ctx.stroke();
    if (py > margin / 2) ctx.fillText(`${z.toFixed(1)} m`, 4, py - 3);
  }
}
