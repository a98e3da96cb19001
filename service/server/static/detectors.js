// Detector files as their tools write them (repnet.io.detectors reads the same layouts, to the same
// poses): MMPose inferencer predictions, Ultralytics YOLO-pose summaries and label files, MediaPipe
// PoseLandmarker results, and the format of a COCO-style list by its joint count.

export class InputError extends Error {}

// COCO-style keypoint lists by joint count: COCO-17, Halpe-26 (AlphaPose), COCO-WholeBody.
export const FORMAT_BY_COUNT = { 17: "coco17", 26: "halpe26", 133: "wholebody133" };
// COCO-WholeBody's parts in the order of its 133 joints: body, feet, face, left hand, right hand.
const WHOLEBODY_PARTS = ["keypoints", "foot_kpts", "face_kpts", "lefthand_kpts", "righthand_kpts"];
const YOLO_JOINTS = 17;

const isNumber = (v) => typeof v === "number" && Number.isFinite(v);
const isObject = (v) => v !== null && typeof v === "object" && !Array.isArray(v);
const formatOf = (count) => FORMAT_BY_COUNT[count] ?? null;

function withFormat(pose, format) {
  if (format) pose.format = format;
  return pose;
}

// A COCO-WholeBody annotation's flat x, y, v values (its parts joined), else the item's keypoints.
export function wholebodyTriples(item) {
  if (!WHOLEBODY_PARTS.slice(1).some((part) => part in item)) return item.keypoints;
  return WHOLEBODY_PARTS.flatMap((part) => {
    if (!Array.isArray(item[part])) throw new InputError(`${part}: a COCO-WholeBody annotation has all of ${WHOLEBODY_PARTS.join(", ")}, as lists`);
    return item[part];
  });
}

function numbers(values, where) {
  if (!Array.isArray(values) || !values.every(isNumber)) throw new InputError(`${where}: expected a list of numbers`);
  return values;
}

function located(poses, frames, people, labels, format, note, extra = {}) {
  return { poses, frames, people, labels, format, note, ...extra };
}

// ---- MMPose: MMPoseInferencer(..., pred_out_dir=...): a video's [{frame_id, instances}], an image's instances ----

const isInstance = (i) => isObject(i) && Array.isArray(i.keypoints) && "keypoint_scores" in i;

function isMmpose(data) {
  if (!Array.isArray(data) || !data.length) return false;
  return data.every((f) => isObject(f) && "frame_id" in f && "instances" in f) || data.every(isInstance);
}

function mmposePose(item, where) {
  if (!isInstance(item)) throw new InputError(`${where}: expected an instance {keypoints: [[x, y], ...], keypoint_scores}`);
  if (!item.keypoints.every((r) => Array.isArray(r) && r.length === 2 && r.every(isNumber))) {
    throw new InputError(`${where}.keypoints: expected [x, y] rows (MMPose 2D)`);
  }
  const scores = numbers(item.keypoint_scores, `${where}.keypoint_scores`);
  if (scores.length !== item.keypoints.length) throw new InputError(`${where}.keypoint_scores: expected ${item.keypoints.length} scores, got ${scores.length}`);
  // RTMPose's scores are SimCC maxima and pass 1 (mmpose issues 2755, 3122): above 1 is read as sure.
  return { keypoints: item.keypoints, confidence: scores.map((v) => Math.min(v, 1)) };
}

function readMmpose(data) {
  const video = data.every((f) => isObject(f) && "frame_id" in f);
  const frames = video ? data : [{ frame_id: 0, instances: data }];
  const poses = [], at = [], people = [], labels = [];
  frames.forEach((frame, f) => {
    const number = frame.frame_id;
    if (!Number.isInteger(number) || number < 0) throw new InputError(`[${f}].frame_id: expected a frame number >= 0`);
    if (!Array.isArray(frame.instances)) throw new InputError(`[${f}].instances: expected a list`);
    frame.instances.forEach((item, k) => {
      poses.push(mmposePose(item, video ? `[${f}].instances[${k}]` : `[${k}]`));
      at.push(number);
      people.push(k);
      labels.push(video ? `frame_id ${number}, instance ${k}` : `instance ${k}`);
    });
  });
  if (!poses.length) throw new InputError("MMPose predictions: no instances in any frame");
  const format = formatOf(poses[0].keypoints.length);
  return located(poses.map((p) => withFormat(p, format)), at, people, labels, format, `MMPose: ${poses.length} instances`);
}

// ---- Ultralytics YOLO-pose: Results.summary() / to_json() (one image's list, or a list of them) ----

const isYoloItem = (i) => isObject(i) && isObject(i.box) && isObject(i.keypoints);

function isYoloSummary(data) {
  if (!Array.isArray(data) || !data.length) return false;
  if (data.every(Array.isArray)) return data.some((f) => f.length) && data.every((f) => f.every(isYoloItem));
  return data.every(isYoloItem);
}

function readYoloSummary(data) {
  const nested = data.every(Array.isArray);
  const frames = nested ? data : [data];
  const poses = [], at = [], people = [], labels = [], coords = [];
  frames.forEach((items, f) => items.forEach((item, k) => {
    const where = nested ? `[${f}][${k}]` : `[${k}]`;
    const x = numbers(item.keypoints.x, `${where}.keypoints.x`);
    const y = numbers(item.keypoints.y, `${where}.keypoints.y`);
    const seen = item.keypoints.visible;
    const c = seen === undefined || seen === null ? null : numbers(seen, `${where}.keypoints.visible`);
    if (x.length !== y.length || (c && c.length !== x.length) || !x.length) {
      throw new InputError(`${where}.keypoints: x, y and visible must be equally long, non-empty lists`);
    }
    coords.push(...x, ...y, ...numbers(["x1", "y1", "x2", "y2"].map((key) => item.box[key]), `${where}.box`));
    const pose = { keypoints: x.map((v, j) => [v, y[j]]) };
    if (c) pose.confidence = c;
    poses.push(pose);
    at.push(f);
    people.push(k);
    labels.push(nested ? `image ${f}, detection ${k}` : `detection ${k}`);
  }));
  if (!poses.length) throw new InputError("YOLO results: no detections");
  const format = formatOf(poses[0].keypoints.length);
  const unit = coords.every((v) => v >= 0 && v <= 1);  // summary(normalize=True): fractions of the image
  return located(poses.map((p) => withFormat(p, format)), at, people, labels, format, `YOLO: ${poses.length} detections`,
    unit ? { normalised: "YOLO results (summary(normalize=True))" } : {});
}

// A YOLO-pose label file (save_txt): per line `class cx cy w h` and 17 keypoints x y [visibility] in [0, 1],
// then the box confidence (save_conf) and the track id if saved.
export function parseYoloTxt(text, name) {
  const poses = [], labels = [];
  text.split(/\r?\n/).forEach((line, i) => {
    if (!line.trim()) return;
    const values = line.trim().split(/\s+/).map(Number);
    let width = 3;
    let extra = values.length - 5 - 3 * YOLO_JOINTS;
    if (extra < 0 || extra > 2) [width, extra] = [2, values.length - 5 - 2 * YOLO_JOINTS];
    if (!values.every(isNumber)) throw new InputError(`${name}: line ${i + 1}: expected finite numbers`);
    if (extra < 0 || extra > 2) {
      throw new InputError(`${name}: line ${i + 1}: expected class cx cy w h and ${YOLO_JOINTS} keypoints of x y [visibility] (${5 + 2 * YOLO_JOINTS} to ${7 + 3 * YOLO_JOINTS} numbers), got ${values.length} values`);
    }
    const joints = [...Array(YOLO_JOINTS).keys()].map((j) => values.slice(5 + width * j, 5 + width * (j + 1)));
    const pose = withFormat({ keypoints: joints.map((r) => [r[0], r[1]]) }, "coco17");
    if (width === 3) pose.confidence = joints.map((r) => r[2]);
    poses.push(pose);
    labels.push(`${name} line ${i + 1}`);
  });
  return located(poses, poses.map(() => 0), poses.map((_, k) => k), labels, "coco17", `YOLO labels: ${poses.length} poses`,
    { normalised: "YOLO label rows" });
}

// ---- MediaPipe PoseLandmarker (Tasks API) results: Python's pose_landmarks or the JS API's landmarks ----

function resultLandmarks(data) {
  if (!isObject(data)) return null;
  const poses = "pose_landmarks" in data ? data.pose_landmarks : data.landmarks;
  const ok = Array.isArray(poses) && poses.every((p) => Array.isArray(p) && p.every((m) => isObject(m) && "x" in m && "y" in m));
  return ok ? poses : null;
}

const isMediapipe = (data) => (Array.isArray(data) && data.length ? data : [data]).every((r) => resultLandmarks(r) !== null);

// Rows [x, y, z, visibility] normalised to [0, 1] (the service scales them by image_size); world landmarks unread.
function readMediapipe(data) {
  const results = Array.isArray(data) ? data : [data];
  const poses = [], at = [], people = [], labels = [];
  results.forEach((result, f) => resultLandmarks(result).forEach((marks, k) => {
    const seen = marks.some((m) => m.visibility !== undefined && m.visibility !== null);
    const keypoints = marks.map((m, j) => {
      const row = seen ? [m.x, m.y, m.z ?? 0, m.visibility ?? 0] : [m.x, m.y];
      if (!row.every(isNumber)) throw new InputError(`[${f}] pose ${k} landmark ${j}: expected numbers x, y, visibility`);
      return row;
    });
    poses.push({ keypoints, format: "mediapipe33" });
    at.push(f);
    people.push(k);
    labels.push(`result ${f}, pose ${k}`);
  }));
  if (!poses.length) throw new InputError("MediaPipe results: no pose in any result");
  return located(poses, at, people, labels, "mediapipe33", `MediaPipe: ${poses.length} poses`,
    { normalised: "MediaPipe PoseLandmarker landmarks" });
}

// The poses of a detector's JSON file this module reads, or null for any other JSON (parse.js reads it).
export function parseDetector(data) {
  if (isMmpose(data)) return readMmpose(data);
  if (isYoloSummary(data)) return readYoloSummary(data);
  if (isMediapipe(data)) return readMediapipe(data);
  return null;
}
