// The page: read an input, POST it to /lift (same origin only), show the answer, step through frames.
// Every value from a file or the API reaches the document through textContent, never as HTML.

import { chooseMode, liftRequests, stillsReason } from "./lift.js";
import { showSkipped, showWarnings, slotOf } from "./notes.js";
import { InputError, parseFiles, parseJson, parseText } from "./parse.js";
import { assignTracks } from "./track.js";
import { cameraFields, drawTrajectory, rootsOf } from "./trajectory.js";
import { View3D, draw2d, sideOf } from "./view.js";
import "./live.js";  // the live mode: a video or the webcam, detected here, lifted causally

const $ = (id) => document.getElementById(id);
const SLOTS = ["example", "file", "paste", "format", "threshold", "temporal", "rate", "intrinsics", "height", "image-size"];
const NUMBERS = ["num-model", "num-scale", "num-rotation", "num-error", "num-plausibility", "num-imputed", "num-derived", "num-track", "num-root"];
// poses: what was sent, results: their answers, tracks: each pose's track, frames: the input's frame
// numbers in order, byFrame: frame number -> its poses, shown: the track the player follows ("": the
// first person of each frame).
const state = {
  model: null, formats: {}, examples: [], poses: [], results: [], tracks: null, frames: [], byFrame: new Map(),
  shown: "", temporal: "off", index: 0, timer: null, lifts: 0, last: null,
};
const view3d = new View3D($("view3d"));

function text(id, value) {
  $(id).textContent = value;
}

function clearErrors() {
  for (const slot of SLOTS) text(`${slot}-error`, "");
  text("status", "");
  $("format-warnings").replaceChildren();
  $("skipped").replaceChildren();
}

// An error leaves nothing of an earlier lift on screen: views, numbers and player are emptied.
function clearResult() {
  pause();
  Object.assign(state, { poses: [], results: [], tracks: null, frames: [], byFrame: new Map(), shown: "" });
  $("player").hidden = true;
  draw2d($("view2d"), null);
  view3d.setPose(null);
  for (const id of NUMBERS) text(id, "—");
}

function addError(slot, message) {
  clearResult();
  const line = document.createElement("span");
  line.textContent = message;
  $(`${slot}-error`).append(line);
}

// send: the input's position of each pose of the request, to say where a pose the API names is.
function showApiError(status, detail, send, frames, source) {
  if (!Array.isArray(detail)) {
    addError(source, `${status}: ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
    return;
  }
  for (const item of detail) {
    const at = Number.isInteger(item.pose) ? send[item.pose] : undefined;
    const where = at !== undefined && at !== item.pose ? ` (poses[${at}] of the input, frame ${frames[at]})` : "";
    addError(slotOf(String(item.field ?? ""), source), `${item.message ?? item.reason ?? JSON.stringify(item)}${where}`);
  }
}

// The way out of a size limit, as the service words it (repnet.core.errors.SPLIT_HINT).
const SPLIT_HINT = "`repnet lift FILE` and the Python client's LiftClient.lift_batch split a long clip into requests";

function tooLarge(bytes, what) {
  const limit = state.model.limits.max_body_bytes;
  return bytes > limit ? `${what} has ${bytes} bytes, more than the ${limit}-byte limit of a /lift body; ${SPLIT_HINT}` : null;
}

// The frame rate of a lift: the page's field (as typed, for the API to judge), else the input's, else
// the rate clients assume (GET /v1/model's rules.assumed_fps) ({fps, note}).
function frameRate(parsed, mode) {
  const typed = $("rate").value.trim();
  if (typed) return { fps: Number.isFinite(Number(typed)) ? Number(typed) : typed, note: "" };
  if (parsed.fps || mode === "off") return { fps: parsed.fps ?? null, note: "" };
  const assumed = state.model.rules.assumed_fps;
  return { fps: assumed, note: `assuming ${assumed} fps` };
}

// The lifts of `parsed` and what they are sent with: its poses, their tracks, the temporal mode.
function plan(parsed) {
  const chosen = $("format").value;
  const thresholdText = $("threshold").value.trim();
  const threshold = thresholdText === "" ? parsed.threshold
    : (Number.isFinite(Number(thresholdText)) ? Number(thresholdText) : thresholdText);
  const extra = { ...(parsed.request ?? {}), format: chosen || parsed.format || state.model.rules.default_format };
  if (threshold !== undefined && threshold !== null) extra.confidence_threshold = threshold;
  const size = $("image-size").value.trim();  // as typed, for the API to judge; the input's own wins
  if (size && extra.image_size === undefined) extra.image_size = size.split(/[\s,]+/).map((v) => (Number.isFinite(Number(v)) ? Number(v) : v));
  const poses = parsed.poses.map((p) => (p && chosen && typeof p === "object" ? { ...p, format: undefined } : p));
  const asked = $("temporal").value || parsed.temporal || "";
  // Unrelated still images are lifted one by one unless a temporal mode, a frame rate or tracks make them a clip.
  const clip = ["causal", "offline"].includes(asked) || $("rate").value.trim() || parsed.fps || parsed.trackIds !== null;
  const stills = clip ? null : stillsReason(parsed.numberedBy, parsed.allFrames);
  const sequence = parsed.allFrames.length > 1 && stills === null;
  const { mode, note } = chooseMode(asked, sequence, state.model);
  const rate = frameRate(parsed, mode);
  const tracking = parsed.trackIds === null && (sequence || mode !== "off");
  const numeric = typeof rate.fps === "number" && rate.fps > 0 ? rate.fps : state.model.rules.assumed_fps;
  const gap = state.model.rules.max_gap_s;
  const tracks = tracking ? assignTracks(parsed.frames, poses, numeric, gap).map(String) : parsed.trackIds;
  const still = stills && `${parsed.allFrames.length} still images (${stills}): lifted one by one; give a frame rate to treat them as a video`;
  const video = rate.note && parsed.numberedBy ? `${parsed.allFrames.length} frames (${parsed.numberedBy} in sequence): ` : "";
  const notes = [still, note, mode === "off" ? "" : video + rate.note].filter(Boolean);
  return { poses, extra, mode, fps: rate.fps, tracks, notes };
}

async function lift(parsed, source) {
  clearErrors();
  pause();
  const { poses, extra, mode, fps, tracks, notes } = plan(parsed);
  const camera = cameraFields($("intrinsics").value, $("height").value);
  if (camera.error) {
    addError(camera.error.slot, camera.error.message);
    return;
  }
  Object.assign(extra, camera.extra);
  if (parsed.normalised && extra.image_size === undefined) {
    addError("image-size", `${parsed.normalised}: x, y are normalised to [0, 1]; give the image size (width, height in px)`);
    return;
  }
  let batches;
  try {
    // A file's poses that break an input rule are skipped and said, the others lifted (a pasted
    // request body is sent as it is: its own invalid_poses, else refused whole).
    batches = parsed.body ? [{ send: [], keep: [], body: JSON.stringify({ ...parsed.body, ...extra }) }]
      : liftRequests(poses, tracks, parsed.frames, { mode, fps }, { ...extra, invalid_poses: "report" }, state.model);
  } catch (err) {
    addError(source, err.message);
    return;
  }
  if (!batches.length) {
    addError(source, "no pose to lift");
    return;
  }
  text("status", "lifting…");
  document.body.dataset.busy = "true";
  const results = new Array(poses.length).fill(null);
  const warnings = [];
  const skipped = [];  // {at, item}: a pose the service did not lift, and why
  try {
    for (const batch of batches) {
      const tooBig = tooLarge(new Blob([batch.body]).size, "the request");
      if (tooBig) {
        addError(source, tooBig);
        return;
      }
      const response = await fetch("/lift", { method: "POST", headers: { "content-type": "application/json" }, body: batch.body });
      const reply = await response.json().catch(() => ({ detail: response.statusText }));
      if (!response.ok) {
        showApiError(response.status, reply.detail, batch.send, parsed.frames, source);
        text("status", `the service answered ${response.status}`);
        return;
      }
      reply.poses.forEach((pose, k) => {
        if (!batch.keep[k] || pose === null) return;  // context of a cut track, or skipped
        if (Array.isArray(pose.warnings)) warnings.push(...pose.warnings);
        results[batch.send[k]] = { ...pose, model_id: reply.model_id };
      });
      for (const item of reply.errors ?? []) {
        if (batch.keep[item.pose]) skipped.push({ at: batch.send[item.pose], send: batch.send, item });
      }
    }
  } catch (err) {
    addError(source, `the service could not be reached: ${err.message}`);
    return;
  } finally {
    document.body.dataset.busy = "false";
  }
  const lifted = results.filter(Boolean).length;
  if (!lifted && skipped.length) {  // nothing usable: every reason, next to its field
    for (const { send, item } of skipped.slice(0, 20)) showApiError(422, [item], send, parsed.frames, source);
    text("status", "no pose of the input could be lifted");
    return;
  }
  showSkipped($("skipped"), skipped, parsed);
  showWarnings($("format-warnings"), warnings);
  show(parsed, poses.map((p) => ({ ...p, format: p.format || extra.format, image_size: p.image_size ?? extra.image_size })), results, tracks, mode);
  const how = mode === "off" ? "each pose alone" : `temporal ${mode} at ${fps} fps`;
  const counted = tracks ? `, ${new Set(tracks.filter((t) => t !== null)).size} track(s)` : "";
  const said = [parsed.note, ...notes].join("; ");
  const left = skipped.length ? `, skipped ${new Set(skipped.map((s) => s.at)).size}` : "";
  text("status", `lifted ${lifted} pose${lifted === 1 ? "" : "s"}${left} in ${batches.length} request${batches.length === 1 ? "" : "s"}, ${how}${counted} (${said})`);
  if (mode !== "off" && typeof fps === "number") $("fps").value = String(Math.round(fps));
  state.lifts += 1;
  document.body.dataset.temporal = mode;
  document.body.dataset.lifts = String(state.lifts);
}

// Keep a lift's answers for the player: its frames, the tracks to follow, the first frame shown.
function show(parsed, poses, results, tracks, mode) {
  state.poses = poses;
  state.results = results;
  state.tracks = tracks;
  state.temporal = mode;
  state.frames = parsed.allFrames;
  state.byFrame = new Map(state.frames.map((f) => [f, []]));
  parsed.frames.forEach((f, i) => state.byFrame.get(f).push(i));
  for (const list of state.byFrame.values()) list.sort((a, b) => parsed.people[a] - parsed.people[b]);
  const counts = new Map();
  for (const t of tracks ?? []) if (t !== null) counts.set(t, (counts.get(t) ?? 0) + 1);
  const crowded = [...state.byFrame.values()].some((list) => list.length > 1);
  const longest = [...counts].sort((a, b) => b[1] - a[1])[0];
  state.shown = crowded && longest ? longest[0] : "";
  const options = [["", "person 0 of each frame"], ...[...counts].map(([t, n]) => [t, `track ${t} (${n} frame${n === 1 ? "" : "s"})`])];
  const most = Math.max(0, ...[...state.byFrame.values()].map((list) => list.length));
  if (!counts.size) for (let k = 1; k < most; k += 1) options.push([`#${k}`, `person ${k} of each frame`]);
  $("track").replaceChildren(...options.map(([value, label]) => {
    const option = document.createElement("option");
    option.value = value;
    option.textContent = label;
    return option;
  }));
  $("track").value = state.shown;
  const several = counts.size ? counts.size > 1 : most > 1;  // someone else to show
  $("track-field").hidden = !several;
  $("player").hidden = state.frames.length < 2 && !several;
  $("frame").max = String(Math.max(state.frames.length - 1, 0));
  render(0);
}

// The pose the player shows in a frame: the followed track's, or the frame's k-th person ("#k";
// "": the first).
function poseAt(index) {
  const list = state.byFrame.get(state.frames[index]) ?? [];
  if (state.shown === "" || state.shown.startsWith("#")) return list[Number(state.shown.slice(1))] ?? null;
  return list.find((i) => state.tracks?.[i] === state.shown) ?? null;
}

// The input's model joints (the mean of each joint's visible sources) and its other detector points,
// in pixels: normalised x, y (MediaPipe) times the pose's image_size, as the service scales them.
function inputPoints(frame, result) {
  const fmt = state.formats[frame.format];
  const keypoints = Array.isArray(frame.keypoints) ? frame.keypoints : [];
  const size = Array.isArray(frame.image_size) && frame.image_size.length === 2 ? frame.image_size.map(Number) : [1, 1];
  const point = (k) => (Array.isArray(keypoints[k]) ? [0, 1].map((c) => Number(keypoints[k][c]) * size[c]) : null);
  const input = fmt.sources.map((src, j) => {
    const found = src.map(point);
    if (!result.visible[j] || !found.length || found.some((p) => !p)) return null;
    return [0, 1].map((c) => found.reduce((s, p) => s + p[c], 0) / found.length);
  });
  const used = new Set(fmt.sources.flat());
  const detector = keypoints.map((_, k) => (used.has(k) ? null : point(k))).filter((p) => p && p.every(Number.isFinite));
  return { input, detector };
}

function jointList(flags) {
  const names = state.model.joints.filter((_, j) => flags[j]);
  return names.length ? names.join(", ") : "none";
}

function render(index) {
  state.index = index;
  const at = poseAt(index);
  const [frame, result] = at === null ? [null, null] : [state.poses[at], state.results[at]];
  $("frame").value = String(index);
  text("frame-label", `frame ${state.frames[index]} (${index + 1} / ${state.frames.length})`);  // the input's number, as the CLI's
  const { parents } = state.model;
  const sides = state.model.joints.map(sideOf);
  const roots = rootsOf(state.results, poseAt, state.frames.length);
  $("trajectory-figure").hidden = !roots.some(Boolean);
  drawTrajectory($("trajectory"), roots, index);
  if (!result) {
    draw2d($("view2d"), null);
    view3d.setPose(null);
    for (const id of NUMBERS) text(id, "—");
    const who = state.shown.startsWith("#") ? `person ${Number(state.shown.slice(1))}` : `track ${state.shown}`;
    text("num-model", state.shown === "" ? "no person in this frame" : `${who} is not in this frame`);
    return;
  }
  const { input, detector } = inputPoints(frame, result);
  draw2d($("view2d"), { input, detector, reprojection: result.reprojection, imputed: result.imputed, derived: result.derived, parents, sides });
  view3d.setPose({ points: result.pose_3d, rotation: result.rotation, parents, sides, imputed: result.imputed });
  text("num-model", result.model_id);
  text("num-scale", result.scale.toPrecision(5));
  text("num-rotation", result.rotation.map((row) => row.map((v) => v.toFixed(4)).join("  ")).join("\n"));
  text("num-error", result.reprojection_error_px.toFixed(2));
  const p = result.plausibility;
  text("num-plausibility", p === null || p === undefined ? "— (the model has no plausibility output)"
    : `${p.toFixed(3)} (more plausible than ${Math.round(100 * p)} % of real poses)`);
  text("num-imputed", jointList(result.imputed));
  text("num-derived", jointList(result.derived));
  const track = result.track_id === null || result.track_id === undefined ? "none" : result.track_id;
  text("num-track", `${track}, ${result.temporal ? `temporal ${state.temporal}` : "lifted alone"}`);
  const root = result.root_camera_m;
  text("num-root", Array.isArray(root) ? `${root.map((v) => v.toFixed(3)).join(", ")} m (height: ${result.root_height_source})`
    : "— (give the camera intrinsics)");
}

function step(delta) {
  const n = state.frames.length;
  if (n) render((state.index + delta + n) % n);
}

function pause() {
  clearInterval(state.timer);
  state.timer = null;
  text("play", "play");
}

function play() {
  if (state.timer) {
    pause();
    return;
  }
  const fps = Math.max(1, Math.min(120, Number($("fps").value) || 30));
  state.timer = setInterval(() => step(1), 1000 / fps);
  text("play", "pause");
}

async function run(source, read) {
  try {
    const parsed = await read();
    state.last = { parsed, source };
    await lift(parsed, source);
  } catch (err) {
    if (!(err instanceof InputError)) throw err;
    state.last = null;  // a new setting has no input to lift again
    clearErrors();
    addError(source, err.message);
  }
}

// The example list names what is shown: an example, or in its first entry the user's own input.
function markExample(label) {
  $("example-none").textContent = label;
  $("example").value = "";
}

function liftFiles() {
  const files = [...$("file").files];
  if (!files.length) return;
  clearErrors();
  markExample(files.length === 1 ? `(your file: ${files[0].name})` : `(your ${files.length} files)`);
  for (const file of files) {
    const tooBig = tooLarge(file.size, `file ${file.name}`);
    if (tooBig) {
      state.last = null;
      addError("file", tooBig);
      return;
    }
  }
  // An NPZ's arrays, inflated, may hold at most 4x a /lift body: their JSON is about as large.
  run("file", () => parseFiles(files, 4 * state.model.limits.max_body_bytes));
}

function liftPaste() {
  const pasted = $("paste").value;
  clearErrors();
  markExample("(your pasted input)");
  $("file").value = "";
  const tooBig = tooLarge(new Blob([pasted]).size, "the pasted text");
  if (tooBig) {
    state.last = null;
    addError("paste", tooBig);
  } else run("paste", async () => parseText(pasted));
}

function liftExample() {
  const example = state.examples[Number($("example").value)];
  if (!example) return;
  $("file").value = "";  // the file field no longer names what is shown
  $("example-none").textContent = "— pick one —";
  run("example", async () => ({ ...parseJson(example.data), fps: example.fps ?? null }));
}

async function start() {
  state.model = await (await fetch("/v1/model")).json();
  for (const f of state.model.formats) {
    state.formats[f.name] = f;
    const option = document.createElement("option");
    option.value = f.name;
    option.textContent = `${f.name}: ${f.description}`;
    $("format").append(option);
  }
  const m = state.model;
  const temporal = (m.temporal ?? []).map((t) => t.mode).join(" and ") || "none";
  text("model-name", `model ${m.model_id} (${m.skeleton} skeleton, ${m.joints.length} joints) ·`);
  text("model-plausibility", m.plausibility ? "rates how plausible each 3D pose is" : "no plausibility rating (this model has no plausibility output)");
  $("model-plausibility").hidden = false;
  text("model-temporal", `· temporal models: ${temporal}`);
  state.examples = await (await fetch("/ui/examples.json")).json();
  state.examples.forEach((example, i) => {
    const option = document.createElement("option");
    option.value = String(i);
    option.textContent = example.name;
    $("example").append(option);
  });
  $("example").addEventListener("change", liftExample);
  for (const id of ["format", "threshold", "temporal", "rate", "intrinsics", "height", "image-size"]) {  // lift the last input again with the new setting
    $(id).addEventListener("change", () => { if (state.last) lift(state.last.parsed, state.last.source); });
  }
  $("file").addEventListener("change", liftFiles);
  $("lift-paste").addEventListener("click", liftPaste);
  $("prev").addEventListener("click", () => { pause(); step(-1); });
  $("next").addEventListener("click", () => { pause(); step(1); });
  $("play").addEventListener("click", play);
  $("fps").addEventListener("change", () => { if (state.timer) { pause(); play(); } });
  $("track").addEventListener("change", () => { state.shown = $("track").value; render(state.index); });
  $("frame").addEventListener("input", () => { pause(); render(Number($("frame").value)); });
  for (const name of ["front", "side", "camera"]) $(`view-${name}`).addEventListener("click", () => view3d.setView(name));
  view3d.draw();
  draw2d($("view2d"), null);
  document.body.dataset.ready = "true";
}

start().catch((err) => {
  text("status", `the page could not start: ${err.message}`);
});
