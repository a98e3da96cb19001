// Canvas drawing: the 2D input with its reprojection, and the 3D skeleton under an orbit camera.
// Coordinates: input pixels (x right, y down); pose_3d in mm, template frame (x to the image right,
// y down, z away from the camera, the subject facing it).

export const COLOURS = {
  background: "#12161c", grid: "#3b4452", left: "#2f7df6", right: "#f0483e", centre: "#b4bcc6",
  reprojection: "#f2f2f2", imputed: "#ffb020", derived: "#42d392", detector: "#6b7480",
};

export function sideOf(name) {
  return name.startsWith("left_") ? "left" : name.startsWith("right_") ? "right" : "centre";
}

function clear(ctx, canvas) {
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = COLOURS.background;
  ctx.fillRect(0, 0, canvas.width, canvas.height);
}

// frame: {input: per model joint [x, y] or null, reprojection, imputed, derived, detector: other
// detector points, parents, sides}
export function draw2d(canvas, frame) {
  const ctx = canvas.getContext("2d");
  clear(ctx, canvas);
  if (!frame) return;
  const points = [...frame.input.filter(Boolean), ...frame.reprojection, ...frame.detector];
  const xs = points.map((p) => p[0]);
  const ys = points.map((p) => p[1]);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const margin = 28;
  const scale = Math.min((canvas.width - 2 * margin) / Math.max(x1 - x0, 1), (canvas.height - 2 * margin) / Math.max(y1 - y0, 1));
  const at = (p) => [canvas.width / 2 + (p[0] - (x0 + x1) / 2) * scale, canvas.height / 2 + (p[1] - (y0 + y1) / 2) * scale];
  const line = (a, b, colour, width, dash) => {
    ctx.strokeStyle = colour;
    ctx.lineWidth = width;
    ctx.setLineDash(dash);
    ctx.beginPath();
    ctx.moveTo(...at(a));
    ctx.lineTo(...at(b));
    ctx.stroke();
  };
  ctx.lineCap = "round";
  for (const p of frame.detector) dot(ctx, at(p), 2.5, COLOURS.detector);
  frame.parents.forEach((parent, j) => {
    if (parent < 0) return;
    const [a, b] = [frame.input[parent], frame.input[j]];
    if (a && b) line(a, b, COLOURS[frame.sides[j]], 4, []);
  });
  frame.parents.forEach((parent, j) => {
    if (parent >= 0) line(frame.reprojection[parent], frame.reprojection[j], COLOURS.reprojection, 1.5, [6, 4]);
  });
  ctx.setLineDash([]);
  frame.input.forEach((p, j) => {
    if (!p) return;
    if (frame.derived[j]) diamond(ctx, at(p), 6, COLOURS.derived);
    else dot(ctx, at(p), 3.5, COLOURS[frame.sides[j]]);
  });
  frame.reprojection.forEach((p, j) => {
    if (frame.imputed[j]) ring(ctx, at(p), 7, COLOURS.imputed, 2.5);
    else ring(ctx, at(p), 3, COLOURS.reprojection, 1);
  });
}

function dot(ctx, [x, y], r, colour) {
  ctx.fillStyle = colour;
  ctx.beginPath();
  ctx.arc(x, y, r, 0, 2 * Math.PI);
  ctx.fill();
}

function ring(ctx, [x, y], r, colour, width) {
  ctx.strokeStyle = colour;
  ctx.lineWidth = width;
  ctx.beginPath();
  ctx.arc(x, y, r, 0, 2 * Math.PI);
  ctx.stroke();
}

function diamond(ctx, [x, y], r, colour) {
  ctx.strokeStyle = colour;
  ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(x, y - r);
  ctx.lineTo(x + r, y);
  ctx.lineTo(x, y + r);
  ctx.lineTo(x - r, y);
  ctx.closePath();
  ctx.stroke();
}

const matmul = (a, b) => a.map((row) => [0, 1, 2].map((j) => row[0] * b[0][j] + row[1] * b[1][j] + row[2] * b[2][j]));
const IDENTITY = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
const DISTANCE_MM = 4000;  // the orbit camera's distance from the pose's centre
export const VIEWS = { front: [0, 0.25], side: [Math.PI / 2, 0.25], camera: [0, 0] };

export class View3D {
  constructor(canvas) {
    this.canvas = canvas;
    this.pose = null;
    this.base = IDENTITY;  // the camera view starts from the pose's own rotation R
    this.zoom = 1;
    [this.yaw, this.pitch] = VIEWS.front;
    let last = null;
    canvas.addEventListener("pointerdown", (e) => {
      last = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!last) return;
      this.yaw += (e.clientX - last[0]) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + (e.clientY - last[1]) * 0.01));
      last = [e.clientX, e.clientY];
      this.draw();
    });
    const stop = () => { last = null; };
    canvas.addEventListener("pointerup", stop);
    canvas.addEventListener("pointercancel", stop);
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom = Math.max(0.3, Math.min(6, this.zoom * Math.exp(-e.deltaY * 0.001)));
      this.draw();
    }, { passive: false });
  }

  // pose: {points: (J, 3) mm, rotation: 3x3, parents, sides, imputed}
  setPose(pose) {
    this.pose = pose;
    if (pose && this.mode === "camera") this.base = pose.rotation;
    this.draw();
  }

  setView(name) {
    this.mode = name;
    [this.yaw, this.pitch] = VIEWS[name];
    this.base = name === "camera" && this.pose ? this.pose.rotation : IDENTITY;
    this.zoom = 1;
    this.draw();
  }

  draw() {
    const { canvas } = this;
    const ctx = canvas.getContext("2d");
    clear(ctx, canvas);
    if (!this.pose) return;
    const pts = this.pose.points;
    const lo = [0, 1, 2].map((k) => Math.min(...pts.map((p) => p[k])));
    const hi = [0, 1, 2].map((k) => Math.max(...pts.map((p) => p[k])));
    const centre = lo.map((v, k) => (v + hi[k]) / 2);
    const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 500);
    const [cy, sy, cp, sp] = [Math.cos(this.yaw), Math.sin(this.yaw), Math.cos(this.pitch), Math.sin(this.pitch)];
    const yaw = [[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]];
    const pitch = [[1, 0, 0], [0, cp, -sp], [0, sp, cp]];
    const m = matmul(matmul(pitch, yaw), this.base);
    const f = this.zoom * 0.8 * canvas.height * DISTANCE_MM / extent;
    const project = (p) => {
      const d = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
      const v = m.map((row) => row[0] * d[0] + row[1] * d[1] + row[2] * d[2]);
      const depth = Math.max(DISTANCE_MM + v[2], 50);
      return [canvas.width / 2 + f * v[0] / depth, canvas.height / 2 + f * v[1] / depth, v[2]];
    };
    this.drawGrid(ctx, project, centre, hi[1]);
    const bones = this.pose.parents.map((parent, j) => [parent, j]).filter(([parent]) => parent >= 0)
      .map(([parent, j]) => [project(pts[parent]), project(pts[j]), j])
      .sort((a, b) => (b[0][2] + b[1][2]) - (a[0][2] + a[1][2]));  // far bones first
    ctx.lineCap = "round";
    for (const [a, b, j] of bones) {
      ctx.strokeStyle = COLOURS[this.pose.sides[j]];
      ctx.lineWidth = 6;
      ctx.beginPath();
      ctx.moveTo(a[0], a[1]);
      ctx.lineTo(b[0], b[1]);
      ctx.stroke();
    }
    pts.forEach((p, j) => {
      const [x, y] = project(p);
      if (this.pose.imputed[j]) ring(ctx, [x, y], 8, COLOURS.imputed, 2.5);
      dot(ctx, [x, y], 4, COLOURS[this.pose.sides[j]]);
    });
  }

  // A 2 m x 2 m grid on the ground (the lowest joint's height, y down), centred under the pose.
  drawGrid(ctx, project, centre, ground) {
    ctx.strokeStyle = COLOURS.grid;
    ctx.lineWidth = 1;
    ctx.setLineDash([]);
    for (let k = -1000; k <= 1000; k += 250) {
      for (const [a, b] of [[[k, -1000], [k, 1000]], [[-1000, k], [1000, k]]]) {
        const p = project([centre[0] + a[0], ground, centre[2] + a[1]]);
        const q = project([centre[0] + b[0], ground, centre[2] + b[1]]);
        ctx.beginPath();
        ctx.moveTo(p[0], p[1]);
        ctx.lineTo(q[0], q[1]);
        ctx.stroke();
      }
    }
  }
}
