// Input files and pasted text -> poses for POST /lift. Values pass through as they are: the service,
// not the page, judges them and words the error. Only the layout of each file kind is read here.
//
// parse*() return {poses, frames, people, labels, allFrames, trackIds, fps, temporal, numberedBy, format,
// threshold, request, note}:
// poses are /lift pose objects ({keypoints, confidence?, format?}); frames[i] is pose i's frame number
// and people[i] its index in that frame; allFrames every frame number of the input in order (a frame
// may have no person); labels (per pose) its name in the file's own identifiers (COCO: image and
// annotation ids), else null; trackIds (per pose), fps and temporal what the input gives, else null;
// request: the request-level fields of a POST /lift body that its poses default to (image_size,
// intrinsics); numberedBy: what the frame numbers are where they may be unrelated images' ("image
// ids", "file names", "image names"), else null (repnet.io.poses.Poses.numbered_by).

import { FORMAT_BY_COUNT, InputError, parseDetector, parseYoloTxt, wholebodyTriples } from "./detectors.js";

export { InputError };

const isNumber = (v) => typeof v === "number";
const isRow = (v) => Array.isArray(v) && v.length >= 2 && v.length <= 3;

// Rows of [x, y] / [x, y, c] / null. With a third value on every row it is the confidence.
function poseFromRows(rows, format = null) {
  const found = rows.filter((r) => r !== null);
  if (found.length && found.every((r) => Array.isArray(r) && r.length === 3)) {
    return withFormat({
      keypoints: rows.map((r) => (r === null ? null : [r[0], r[1]])),
      confidence: rows.map((r) => (r === null ? 0 : r[2])),
    }, format);
  }
  return withFormat({ keypoints: rows }, format);
}

function withFormat(pose, format) {
  if (typeof format === "string" && format) pose.format = format;
  return pose;
}

// Flat x, y, c triples (OpenPose, COCO). cIsFlag: COCO's 0/1/2 visibility, not a confidence.
function poseFromTriples(flat, format, cIsFlag) {
  if (!Array.isArray(flat) || flat.length % 3 !== 0) {
    throw new InputError(`expected x, y, c triples, got ${Array.isArray(flat) ? flat.length + " values" : typeof flat}`);
  }
  const keypoints = [];
  const confidence = [];
  for (let i = 0; i < flat.length; i += 3) {
    const c = flat[i + 2];
    keypoints.push(c === 0 ? null : [flat[i], flat[i + 1]]);
    confidence.push(cIsFlag ? (c === 0 ? 0 : 1) : c);
  }
  const pose = { keypoints };
  if (!cIsFlag) pose.confidence = confidence;
  return withFormat(pose, format);
}

// Fill in what an input does not give: each pose its own frame, nothing tracked.
function withFrames(parsed) {
  const frames = parsed.frames ?? parsed.poses.map((_, i) => i);
  return {
    trackIds: null, fps: null, temporal: null, labels: null, numberedBy: null, people: parsed.poses.map(() => 0),
    allFrames: [...new Set(frames)].sort((a, b) => a - b), ...parsed, frames,
  };
}

// OpenPose's models by joint count (repnet.io.poses OPENPOSE_FORMATS): COCO 18, BODY_25.
const OPENPOSE_FORMATS = { 18: "coco18", 25: "body25" };

// OpenPose frames: every person of every frame; numbers: each frame's number.
function openPoseFrames(frames, numbers = frames.map((_, i) => i)) {
  const poses = [];
  const at = [];
  const people = [];
  frames.forEach((frame, f) => {
    const found = Array.isArray(frame.people) ? frame.people : [];
    found.forEach((person, k) => {
      const flat = person.pose_keypoints_2d;
      poses.push(poseFromTriples(flat, Array.isArray(flat) ? OPENPOSE_FORMATS[flat.length / 3] ?? null : null, false));
      at.push(numbers[f]);
      people.push(k);
    });
  });
  const crowded = frames.filter((f) => Array.isArray(f.people) && f.people.length > 1).length;
  const empty = frames.filter((f) => !Array.isArray(f.people) || !f.people.length).length;
  const notes = [`OpenPose: ${frames.length} frame${frames.length === 1 ? "" : "s"}`];
  if (crowded) notes.push(`${crowded} with several people`);
  if (empty) notes.push(`${empty} without a person`);
  const format = poses.find((p) => p.format)?.format ?? "body25";
  return withFrames({ poses, frames: at, people, allFrames: [...new Set(numbers)].sort((a, b) => a - b), format, note: notes.join(", ") });
}

// COCO image ids as frame numbers: an integer id is its frame, a text id the last number in it;
// else the ids in order (repnet.io.pose_file); with what they are ({numbers, numberedBy}).
function imageFrames(ids) {
  const numbers = ids.map((id) => (Number.isInteger(id) ? id : (typeof id === "string" ? lastNumber(id) : null)));
  if (numbers.every((n) => n !== null)) return { numbers, numberedBy: "image ids" };
  const order = [...new Set(ids.map(String))].sort();
  return { numbers: ids.map((id) => order.indexOf(String(id))), numberedBy: "image names" };
}

// The last run of digits in a name (OpenPose: video_000000000012_keypoints.json), or null.
export function lastNumber(name) {
  const digits = String(name).replace(/\.[^.]*$/, "").match(/\d+/g);
  return digits ? Number(digits[digits.length - 1]) : null;
}

// COCO results or annotations, AlphaPose results, COCO-WholeBody annotations (parts joined): the format
// by joint count (17 coco17, 26 halpe26, 133 wholebody133).
function cocoPoses(items, note) {
  const triples = items.filter((a) => a && Array.isArray(a.keypoints)).map((a) => ({ ...a, keypoints: wholebodyTriples(a) }));
  const { numbers: frameOf, numberedBy } = imageFrames(triples.map((a, k) => a.image_id ?? k));
  const order = triples.map((a, k) => [frameOf[k], k]).sort((x, y) => x[0] - y[0] || x[1] - y[1]).map((x) => x[1]);
  // Ground-truth files flag each joint 0 (not labelled), 1 or 2; detector results give a score.
  const flags = triples.every((a) => a.keypoints.every((v, i) => i % 3 !== 2 || [0, 1, 2].includes(v)));
  const format = FORMAT_BY_COUNT[(triples[0]?.keypoints.length ?? 0) / 3] ?? null;
  const poses = order.map((k) => poseFromTriples(triples[k].keypoints, format, flags));
  const frames = order.map((k) => frameOf[k]);
  const people = frames.map((f, i) => frames.slice(0, i).filter((g) => g === f).length);
  const labels = order.map((k) => `image_id ${triples[k].image_id ?? k}${triples[k].id !== undefined ? `, id ${triples[k].id}` : ""}`);
  const by = triples.some((a) => a.image_id !== undefined) ? numberedBy : null;  // else the file's order
  return withFrames({ poses, frames, people, labels, numberedBy: by, format, note: `${note}: ${poses.length} poses` });
}

// The tracks, frame numbers and temporal fields a POST /lift body or repnet lift output gives.
function givenTracks(items, poses) {
  const trackIds = items.map((p) => (p && typeof p === "object" && p.track_id !== undefined ? p.track_id : null));
  if (!trackIds.some((t) => t !== null)) return { poses };
  const frames = items.map((p, i) => (Number.isInteger(p?.frame) ? p.frame : i));
  const bare = poses.map((p) => {
    const pose = { ...p };
    delete pose.track_id;
    delete pose.frame;
    return pose;
  });
  return { poses: bare, trackIds, frames };
}

// Is `v` a list of poses (each a list of rows) rather than one pose?
function isPoseList(v) {
  return Array.isArray(v) && v.length > 0 && Array.isArray(v[0]) &&
    v[0].some((row) => Array.isArray(row));
}

const rate = (data) => (typeof data?.fps === "number" && data.fps > 0 ? data.fps : null);

export function parseJson(data) {
  if (Array.isArray(data) && data.length && data.every((f) => f && typeof f === "object" && "people" in f)) {
    return openPoseFrames(data);
  }
  const found = data && typeof data === "object" && "people" in data ? null : parseDetector(data);
  if (found) return withFrames(found);
  if (data && typeof data === "object" && !Array.isArray(data)) {
    if ("people" in data) return openPoseFrames([data]);
    if (Array.isArray(data.annotations)) return cocoPoses(data.annotations, "COCO annotations");
    if (Array.isArray(data.poses) && data.poses.some((p) => p && typeof p === "object" && "input" in p)) {
      const poses = data.poses.map((p) => withFormat({ ...(p.input ?? {}) }, null));
      for (const pose of poses) if (pose.confidence === null) delete pose.confidence;
      const given = givenTracks(data.poses, poses);
      const people = data.poses.map((p) => (Number.isInteger(p?.person) ? p.person : 0));
      const temporal = typeof data.temporal === "string" ? data.temporal : null;
      return withFrames({ ...given, people, fps: rate(data), temporal, format: data.format ?? null, note: `repnet lift output: ${poses.length} poses` });
    }
    if ("poses" in data) {  // a POST /lift body, sent as it is
      // A body whose poses are not a list goes to the service whole, for it to say what is wrong.
      const body = Array.isArray(data.poses) ? null : data;
      const given = body ? { poses: [] } : givenTracks(data.poses, data.poses);
      const temporal = typeof data.temporal === "string" ? data.temporal : null;
      // The body's defaults for its poses (image_size, intrinsics) go with every request, as curl sends them.
      const request = Object.fromEntries(["image_size", "intrinsics"].filter((k) => k in data).map((k) => [k, data[k]]));
      return withFrames({ ...given, fps: rate(data), temporal, format: data.format ?? null, threshold: data.confidence_threshold, body, request, note: "POST /lift body" });
    }
    if ("keypoints" in data) {
      if (isPoseList(data.keypoints)) {
        const poses = data.keypoints.map((rows) => poseFromRows(rows));
        return withFrames({ poses, fps: rate(data), format: data.format ?? null, note: `${poses.length} poses` });
      }
      const pose = { ...data };
      delete pose.confidence_threshold;
      delete pose.fps;
      return withFrames({ poses: [pose], format: null, threshold: data.confidence_threshold, note: "one pose" });
    }
  }
  if (Array.isArray(data) && data.length && data.every((a) => a && typeof a === "object" && Array.isArray(a.keypoints) && a.keypoints.every(isNumber))) {
    return cocoPoses(data, "COCO results");
  }
  if (isPoseList(data)) {
    const poses = data.map((rows) => poseFromRows(rows));
    return withFrames({ poses, format: null, note: `${poses.length} poses` });
  }
  if (Array.isArray(data) && data.length && data.some((r) => isRow(r) || r === null)) {
    return withFrames({ poses: [poseFromRows(data)], format: null, note: "one pose" });
  }
  throw new InputError("expected a pose ([[x, y], …]), a list of poses, a POST /lift body, OpenPose, COCO, AlphaPose, MMPose, YOLO, MediaPipe or repnet lift JSON");
}

export function parseText(text) {
  let data;
  try {
    data = JSON.parse(text);
  } catch (err) {
    throw new InputError(`not JSON: ${err.message}`);
  }
  return parseJson(data);
}

// Several OpenPose files are the frames of one video, numbered by the last number in their names
// (OpenPose numbers them), else in file-name order.
// maxBytes: the most an NPZ's arrays may hold once inflated (its size as a file says little).
export async function parseFiles(files, maxBytes = Infinity) {
  const sorted = [...files].sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
  if (sorted.length === 1 && sorted[0].name.toLowerCase().endsWith(".npz")) {
    return parseNpz(new Uint8Array(await sorted[0].arrayBuffer()), maxBytes);
  }
  const numbers = sorted.map((f) => lastNumber(f.name));
  const parts = [];
  for (const file of sorted) {
    if (file.name.toLowerCase().endsWith(".npz")) throw new InputError(`${file.name}: pick an NPZ file on its own`);
    if (file.name.toLowerCase().endsWith(".txt")) {
      parts.push(parseYoloTxt(await file.text(), file.name));
      continue;
    }
    let data;
    try {
      data = JSON.parse(await file.text());
    } catch (err) {
      throw new InputError(`${file.name}: not JSON: ${err.message}`);
    }
    if (sorted.length === 1) return parseJson(data);
    parts.push(data && typeof data === "object" && "people" in data ? { openpose: data } : parseJson(data));
  }
  if (!parts.some((p) => p.openpose || p.poses.length)) throw new InputError(`${sorted.map((f) => f.name).join(", ")}: no poses`);
  if (sorted.length === 1) return withFrames(parts[0]);
  const numbered = numbers.every((n) => n !== null);
  const numberedBy = numbered ? "file names" : null;  // unrelated images or a clip: cli.lift's stills rule
  if (parts.every((p) => p.openpose)) {
    return { ...openPoseFrames(parts.map((p) => p.openpose), numbered ? numbers : undefined), numberedBy };
  }
  return { ...frameFiles(parts, sorted, numbers), numberedBy };
}

// Several files of poses as the frames of one video (repnet.io.pose_file.load_frames): every pose of a
// file has the file's number (else its place), people by their place in the file, labels from the file.
function frameFiles(parts, files, numbers) {
  const at = numbers.map((n, f) => n ?? f);
  const flat = parts.map((p, f) => {
    if (p.body || Object.keys(p.request ?? {}).length) throw new InputError(`${files[f].name}: pick a POST /lift body on its own`);
    return p.openpose ? openPoseFrames([p.openpose]) : p;
  });
  const poses = flat.flatMap((p) => p.poses);
  const frames = flat.flatMap((p, f) => p.poses.map(() => at[f]));
  const people = flat.flatMap((p) => p.poses.map((_, k) => k));
  const labels = flat.flatMap((p, f) => (files[f].name.endsWith(".txt") ? p.labels : p.poses.map(() => files[f].name)));
  const normalised = flat.find((p) => p.normalised)?.normalised;
  const format = flat.find((p) => p.format)?.format ?? null;
  return withFrames({ poses, frames, people, labels, format, normalised, note: `${files.length} files: ${poses.length} poses` });
}

// ---- NPZ: a zip archive (stored or deflated, zip64 sizes as numpy writes them) of .npy arrays ----

// An entry inflated, stopped as soon as it passes the size its zip directory declares.
async function inflate(bytes, declared, name) {
  const reader = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate-raw")).getReader();
  const out = new Uint8Array(declared);
  let filled = 0;
  for (let part = await reader.read(); !part.done; part = await reader.read()) {
    if (filled + part.value.length > declared) {
      await reader.cancel();
      throw new InputError(`${name}: inflates to more than the ${declared} bytes its zip entry declares`);
    }
    out.set(part.value, filled);
    filled += part.value.length;
  }
  return out.subarray(0, filled);
}

// The zip's entries, each inflated only while all declared sizes together are at most maxBytes.
async function unzip(bytes, maxBytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  let end = bytes.length - 22;
  while (end >= 0 && view.getUint32(end, true) !== 0x06054b50) end -= 1;
  if (end < 0) throw new InputError("not an NPZ file (no zip directory)");
  const count = view.getUint16(end + 10, true);
  let at = view.getUint32(end + 16, true);
  const entries = {};
  let total = 0;
  for (let i = 0; i < count; i += 1) {
    if (view.getUint32(at, true) !== 0x02014b50) throw new InputError("damaged NPZ file");
    const method = view.getUint16(at + 10, true);
    let size = view.getUint32(at + 20, true);
    let rawSize = view.getUint32(at + 24, true);
    let offset = view.getUint32(at + 42, true);
    const nameLength = view.getUint16(at + 28, true);
    const extraLength = view.getUint16(at + 30, true);
    const commentLength = view.getUint16(at + 32, true);
    const name = new TextDecoder().decode(bytes.subarray(at + 46, at + 46 + nameLength));
    let extra = at + 46 + nameLength;
    const extraEnd = extra + extraLength;
    while (extra + 4 <= extraEnd) {  // zip64: the 64-bit values of the fields set to 0xFFFFFFFF
      const id = view.getUint16(extra, true);
      let field = extra + 4;
      if (id === 1) {
        if (rawSize === 0xffffffff) { rawSize = Number(view.getBigUint64(field, true)); field += 8; }
        if (size === 0xffffffff) { size = Number(view.getBigUint64(field, true)); field += 8; }
        if (offset === 0xffffffff) offset = Number(view.getBigUint64(field, true));
      }
      extra += 4 + view.getUint16(extra + 2, true);
    }
    const start = offset + 30 + view.getUint16(offset + 26, true) + view.getUint16(offset + 28, true);
    const data = bytes.subarray(start, start + size);
    if (method !== 0 && method !== 8) throw new InputError(`${name}: unsupported zip compression ${method}`);
    total += method === 8 ? rawSize : size;
    if (total > maxBytes) {
      throw new InputError(`its arrays hold ${total} bytes or more once inflated, more than the ${maxBytes} this page reads`);
    }
    entries[name.replace(/\.npy$/, "")] = method === 8 ? await inflate(data, rawSize, name) : data;
    at += 46 + nameLength + extraLength + commentLength;
  }
  return entries;
}

function readNpy(bytes, name) {
  if (bytes[0] !== 0x93 || String.fromCharCode(...bytes.subarray(1, 6)) !== "NUMPY") {
    throw new InputError(`${name}: not a .npy array`);
  }
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const long = bytes[6] >= 2;
  const headerLength = long ? view.getUint32(8, true) : view.getUint16(8, true);
  const start = (long ? 12 : 10) + headerLength;
  const header = new TextDecoder().decode(bytes.subarray(long ? 12 : 10, start));
  const descr = /'descr':\s*'([^']+)'/.exec(header)?.[1];
  const shape = (/'shape':\s*\(([^)]*)\)/.exec(header)?.[1] ?? "").split(",").filter((s) => s.trim()).map(Number);
  if (/'fortran_order':\s*True/.test(header)) throw new InputError(`${name}: Fortran-ordered arrays are not read`);
  const body = bytes.slice(start);
  const size = shape.reduce((a, b) => a * b, 1);
  const types = { "<f8": Float64Array, "<f4": Float32Array, "<i8": BigInt64Array, "<i4": Int32Array, "|b1": Uint8Array };
  if (descr in types) {
    const values = Array.from(new types[descr](body.buffer, 0, size), Number);
    return { shape, values };
  }
  const text = /^<U(\d+)$/.exec(descr ?? "");
  if (text && size === 1) {
    const chars = new Uint32Array(body.buffer, 0, Number(text[1]));
    return { shape, values: [String.fromCodePoint(...chars.filter((c) => c !== 0))] };
  }
  throw new InputError(`${name}: unsupported dtype ${descr}`);
}

export async function parseNpz(bytes, maxBytes = Infinity) {
  const entries = await unzip(bytes, maxBytes);
  if (!entries.keypoints) throw new InputError(`no 'keypoints' array (has ${Object.keys(entries).join(", ")})`);
  const keypoints = readNpy(entries.keypoints, "keypoints");
  let [n, j, d] = keypoints.shape;
  if (keypoints.shape.length === 2) [n, j, d] = [1, ...keypoints.shape];
  if (![2, 3].includes(d) || keypoints.shape.length > 3) {
    throw new InputError(`keypoints: expected shape (N, J, 2|3), got (${keypoints.shape.join(", ")})`);
  }
  const confidence = entries.confidence ? readNpy(entries.confidence, "confidence").values : null;
  const format = entries.format ? readNpy(entries.format, "format").values[0] : null;
  const poses = [];
  for (let p = 0; p < n; p += 1) {
    const rows = [];
    for (let k = 0; k < j; k += 1) {
      const at = (p * j + k) * d;
      const row = keypoints.values.slice(at, at + d);
      rows.push(row.slice(0, 2).some(Number.isNaN) ? null : row);
    }
    const pose = poseFromRows(rows);
    if (confidence) pose.confidence = confidence.slice(p * j, (p + 1) * j);
    poses.push(pose);
  }
  const fps = entries.fps ? readNpy(entries.fps, "fps").values[0] : null;
  return withFrames({ poses, fps, format, note: `NPZ: ${n} poses` });
}
