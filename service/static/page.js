// The page: read an input, POST it to /lift (same origin only), show the answer, step through frames.
// Every value from a file or the API reaches the document through textContent, never as HTML.

import { InputError, parseFiles, parseJson, parseText } from "./parse.js";
import { View3D, draw2d, sideOf } from "./view.js";

const $ = (id) => document.getElementById(id);
const SLOTS = ["example", "file", "paste", "format", "threshold"];
const state = { model: null, formats: {}, examples: [], frames: [], results: [], index: 0, timer: null, lifts: 0, last: null };
const view3d = new View3D($("view3d"));

function text(id, value) {
  $(id).textContent = value;
}

function clearErrors() {
  for (const slot of SLOTS) text(`${slot}-error`, "");
  text("status", "");
  $("format-warnings").replaceChildren();
}

function addError(slot, message) {
  const line = document.createElement("span");
  line.textContent = message;
  $(`${slot}-error`).append(line);
}

// The field an API error names -> the page field it belongs next to.
function slotOf(field, source) {
  if (field === "format" || /\.format$/.test(field)) return "format";
  if (field === "confidence_threshold") return "threshold";
  return source;
}

function showApiError(status, detail, first, source) {
  if (!Array.isArray(detail)) {
    addError(source, `${status}: ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
    return;
  }
  for (const item of detail) {
    const where = first > 0 && Number.isInteger(item.pose) ? ` (frame ${first + item.pose + 1})` : "";
    addError(slotOf(String(item.field ?? ""), source), `${item.message ?? item.reason ?? JSON.stringify(item)}${where}`);
  }
}

function showWarnings(warnings) {
  const list = $("format-warnings");
  const seen = new Set();
  for (const w of warnings) {
    const message = typeof w === "string" ? w : (w?.message ?? w?.reason ?? JSON.stringify(w));
    if (seen.has(message)) continue;
    seen.add(message);
    const item = document.createElement("li");
    item.textContent = message;
    list.append(item);
  }
}

function tooLarge(bytes, what) {
  const limit = state.model.limits.max_body_bytes;
  return bytes > limit ? `${what} has ${bytes} bytes, more than the ${limit}-byte limit of a /lift body` : null;
}

// Requests of at most max_request_poses poses and max_body_bytes bytes, in frame order.
function* requests(poses, extra) {
  const limits = state.model.limits;
  let start = 0;
  while (start < poses.length) {
    let size = Math.min(limits.max_request_poses, 256, poses.length - start);
    let body = JSON.stringify({ ...extra, poses: poses.slice(start, start + size) });
    while (new Blob([body]).size > limits.max_body_bytes && size > 1) {
      size = Math.ceil(size / 2);
      body = JSON.stringify({ ...extra, poses: poses.slice(start, start + size) });
    }
    yield { first: start, count: size, body };
    start += size;
  }
}

async function lift(parsed, source) {
  clearErrors();
  pause();
  const chosen = $("format").value;
  const thresholdText = $("threshold").value.trim();
  const threshold = thresholdText === "" ? parsed.threshold
    : (Number.isFinite(Number(thresholdText)) ? Number(thresholdText) : thresholdText);
  const extra = { format: chosen || parsed.format || "h36m17" };
  if (threshold !== undefined && threshold !== null) extra.confidence_threshold = threshold;
  const frames = parsed.poses.map((p) => (p && chosen && typeof p === "object" ? { ...p, format: undefined } : p));
  const sent = frames.map((p, i) => [p, i]).filter(([p]) => p !== null);
  const batches = parsed.body ? [{ first: 0, count: 0, body: JSON.stringify({ ...parsed.body, ...extra }) }]
    : [...requests(sent.map(([p]) => p), extra)];
  if (!batches.length) {
    addError(source, "no pose to lift");
    return;
  }
  text("status", "lifting…");
  document.body.dataset.busy = "true";
  const results = new Array(frames.length).fill(null);
  const warnings = [];
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
        showApiError(response.status, reply.detail, batch.first, source);
        text("status", `the service answered ${response.status}`);
        return;
      }
      if (Array.isArray(reply.warnings)) warnings.push(...reply.warnings);
      reply.poses.forEach((pose, k) => {
        if (Array.isArray(pose.warnings)) warnings.push(...pose.warnings);
        results[sent[batch.first + k][1]] = { ...pose, model_id: reply.model_id };
      });
    }
  } catch (err) {
    addError(source, `the service could not be reached: ${err.message}`);
    return;
  } finally {
    document.body.dataset.busy = "false";
  }
  showWarnings(warnings);
  state.frames = frames.map((p) => (p ? { ...p, format: p.format || extra.format } : null));
  state.results = results;
  state.lifts += 1;
  const lifted = results.filter(Boolean).length;
  text("status", `lifted ${lifted} pose${lifted === 1 ? "" : "s"} in ${batches.length} request${batches.length === 1 ? "" : "s"} (${parsed.note})`);
  $("player").hidden = frames.length < 2;
  $("frame").max = String(Math.max(frames.length - 1, 0));
  render(0);
  document.body.dataset.lifts = String(state.lifts);
}

// The input's model joints (the mean of each joint's visible sources) and its other detector points.
function inputPoints(frame, result) {
  const fmt = state.formats[frame.format];
  const keypoints = Array.isArray(frame.keypoints) ? frame.keypoints : [];
  const point = (k) => (Array.isArray(keypoints[k]) ? keypoints[k].map(Number) : null);
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
  const [frame, result] = [state.frames[index], state.results[index]];
  $("frame").value = String(index);
  text("frame-label", `frame ${index + 1} / ${state.frames.length}`);
  const { parents } = state.model;
  const sides = state.model.joints.map(sideOf);
  if (!result) {
    draw2d($("view2d"), null);
    view3d.setPose(null);
    for (const id of ["num-scale", "num-rotation", "num-error", "num-plausibility", "num-imputed", "num-derived"]) text(id, "—");
    text("num-model", "no person in this frame");
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
    clearErrors();
    addError(source, err.message);
  }
}

function liftFiles() {
  const files = [...$("file").files];
  if (!files.length) return;
  clearErrors();
  for (const file of files) {
    const tooBig = tooLarge(file.size, `file ${file.name}`);
    if (tooBig) {
      addError("file", tooBig);
      return;
    }
  }
  run("file", () => parseFiles(files));
}

function liftPaste() {
  const pasted = $("paste").value;
  clearErrors();
  const tooBig = tooLarge(new Blob([pasted]).size, "the pasted text");
  if (tooBig) addError("paste", tooBig);
  else run("paste", async () => parseText(pasted));
}

function liftExample() {
  const example = state.examples[Number($("example").value)];
  if (!example) return;
  if (example.fps) $("fps").value = String(example.fps);
  run("example", async () => parseJson(example.data));
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
  text("model-line", `model ${m.model_id} (${m.skeleton}), ${m.joints.length} joints; plausibility: ${m.plausibility ? "given" : "not given by this model"}`);
  state.examples = await (await fetch("/ui/examples.json")).json();
  state.examples.forEach((example, i) => {
    const option = document.createElement("option");
    option.value = String(i);
    option.textContent = example.name;
    $("example").append(option);
  });
  $("example").addEventListener("change", liftExample);
  for (const id of ["format", "threshold"]) {  // lift the last input again with the new setting
    $(id).addEventListener("change", () => { if (state.last) lift(state.last.parsed, state.last.source); });
  }
  $("file").addEventListener("change", liftFiles);
  $("lift-paste").addEventListener("click", liftPaste);
  $("prev").addEventListener("click", () => { pause(); step(-1); });
  $("next").addEventListener("click", () => { pause(); step(1); });
  $("play").addEventListener("click", play);
  $("fps").addEventListener("change", () => { if (state.timer) { pause(); play(); } });
  $("frame").addEventListener("input", () => { pause(); render(Number($("frame").value)); });
  for (const name of ["front", "side", "camera"]) $(`view-${name}`).addEventListener("click", () => view3d.setView(name));
  view3d.draw();
  draw2d($("view2d"), null);
  document.body.dataset.ready = "true";
}

start().catch((err) => {
  text("status", `the page could not start: ${err.message}`);
});
