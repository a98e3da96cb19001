// The live mode: a video file or the webcam, its person detected in 2D in the browser by the vendored
// MediaPipe PoseLandmarker (vendor/mediapipe/, lite model, WebAssembly on the CPU) and lifted by this
// service as one causal track: each frame is a POST /lift of the track's last frames (the causal
// model's window), whose last answer is the frame's 3D pose, drawn at once. Frames that arrive while
// one is in hand are skipped.

import { bytes } from "./lift.js";
import { reach } from "./track.js";
import { View3D, sideOf } from "./view.js";

const $ = (id) => document.getElementById(id);
const VENDOR = "/ui/vendor/mediapipe/";
const TRACK = "live";
const KEPT = 200;  // latencies kept for the p50/p95 shown

const live = { pose: null, model: null, running: false, source: null, sent: [], latencies: [], parts: [], drawn: 0, start: 0 };
const view = new View3D($("live3d"));

// The vendored detector (MediaPipe Tasks' PoseLandmarker), loaded once on demand: its ES module, then its
// WebAssembly build and the lite model, all from this service. It runs on the CPU (XNNPACK in WebAssembly
// SIMD), in VIDEO mode: the person found in one frame is tracked into the next without the detector model.
async function loadDetector() {
  if (live.pose) return live.pose;
  const { PoseLandmarker } = await import(`${VENDOR}vision_bundle.mjs`);
  const fileset = { wasmLoaderPath: `${VENDOR}vision_wasm_internal.js`, wasmBinaryPath: `${VENDOR}vision_wasm_internal.wasm` };
  live.pose = await PoseLandmarker.createFromOptions(fileset, {
    baseOptions: { modelAssetPath: `${VENDOR}pose_landmarker_lite.task`, delegate: "CPU" },
    runningMode: "VIDEO",
    numPoses: 1,
    minPoseDetectionConfidence: 0.5,
    minPosePresenceConfidence: 0.5,
    minTrackingConfidence: 0.5,
  });
  return live.pose;
}

// The detector's landmarks of one video frame (grabbed at `time`, ms): 33 normalised {x, y, z, visibility}, or null.
function detect(pose, video, time) {
  return pose.detectForVideo(video, time).landmarks[0] ?? null;
}

const round = (value, scale) => Math.round(value * scale) / scale;

const percentile = (values, q) => {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
};

function status(message) {
  $("live-status").textContent = message;
}

// One frame: detect, lift the causal window ending at it, draw; its latency from the frame's grab.
async function step(video, fps, window) {
  const grabbed = performance.now();
  const frame = live.source === "camera" ? Math.round((grabbed - live.start) / 1000 * fps) : Math.round(video.currentTime * fps);
  if (live.sent.length && frame <= live.sent[live.sent.length - 1].frame) return;
  const landmarks = detect(live.pose, video, grabbed);
  const detected = performance.now();
  if (!live.running) return;
  if (!landmarks) {
    status("no person in view");
    return;
  }
  // x, y to 1e-5 of the image (well under a pixel), so that a window of every frame fits the body limit
  const keypoints = landmarks.map((l) => [round(l.x, 1e5), round(l.y, 1e5), round(l.z, 1e4), round(l.visibility, 1e3)]);
  live.sent.push({ keypoints, track_id: TRACK, frame });
  live.sent = live.sent.filter((p) => p.frame >= frame - window);
  const body = { format: "mediapipe33", image_size: [video.videoWidth, video.videoHeight], temporal: "causal", fps, poses: live.sent };
  // a service with a smaller body limit than the window needs gets the newest poses that fit
  let text = JSON.stringify(body);
  while (live.sent.length > 1 && bytes(text) > live.model.limits.max_body_bytes) {
    live.sent = live.sent.slice(1);
    body.poses = live.sent;
    text = JSON.stringify(body);
  }
  const response = await fetch("/lift", { method: "POST", headers: { "Content-Type": "application/json" }, body: text });
  const answer = await response.json();
  if (!response.ok) throw new Error(`/lift answered ${response.status}: ${JSON.stringify(answer.detail)}`);
  const lifted = performance.now();
  if (!live.running) return;
  const result = answer.poses[answer.poses.length - 1];
  const { parents, joints } = live.model;
  view.setPose({ points: result.pose_3d, rotation: result.rotation, parents, sides: joints.map(sideOf), imputed: result.imputed });
  const took = performance.now() - grabbed;
  live.latencies = [...live.latencies.slice(1 - KEPT), took];
  live.parts = [...live.parts.slice(1 - KEPT), [detected - grabbed, lifted - detected, performance.now() - lifted]];
  live.drawn += 1;
  const [p50, p95] = [percentile(live.latencies, 0.5), percentile(live.latencies, 0.95)];
  document.body.dataset.liveDrawn = String(live.drawn);
  const parts = [0, 1, 2].map((k) => percentile(live.parts.map((p) => p[k]), 0.5));
  document.body.dataset.liveLatency = JSON.stringify({ p50, p95, n: live.latencies.length, detect: parts[0], lift: parts[1], draw: parts[2] });
  status(`frame ${frame}: ${live.drawn} poses drawn; camera frame to drawn 3D pose p50 ${p50.toFixed(0)} ms, p95 ${p95.toFixed(0)} ms (last ${live.latencies.length}; median detection ${parts[0].toFixed(0)}, lift ${parts[1].toFixed(0)}, draw ${parts[2].toFixed(0)} ms)`);
}

async function run(video, fps) {
  const contract = (live.model.temporal ?? []).find((t) => t.mode === "causal");
  if (!contract) throw new Error("this service has no causal temporal model");
  const [window] = reach(contract, fps);
  while (live.running && !video.ended) {
    await step(video, fps, window);
    await new Promise((resolve) => requestAnimationFrame(resolve));
  }
}

async function start(source, setUp) {
  stop();
  live.running = true;
  live.source = source;
  live.sent = [];
  live.latencies = [];
  live.parts = [];
  live.drawn = 0;
  const video = $("live-video");
  try {
    status("loading the pose detector…");
    live.model ??= await (await fetch("/v1/model")).json();
    await loadDetector();
    const fps = await setUp(video);
    await video.play();
    live.start = performance.now();
    status("running…");
    await run(video, fps);
  } catch (err) {
    status(`live mode stopped: ${err.message}`);
    live.running = false;
  }
}

function stop() {
  live.running = false;
  const video = $("live-video");
  if (video.srcObject) video.srcObject.getTracks().forEach((t) => t.stop());
  video.srcObject = null;
  video.pause();
}

$("live-camera").addEventListener("click", () => start("camera", async (video) => {
  const stream = await navigator.mediaDevices.getUserMedia({ video: { width: 640, height: 480 }, audio: false });
  video.srcObject = stream;
  return stream.getVideoTracks()[0].getSettings().frameRate || 30;
}));
$("live-file").addEventListener("change", () => {
  const file = $("live-file").files[0];
  if (!file) return;
  start("file", async (video) => {
    video.src = URL.createObjectURL(file);
    await new Promise((resolve) => { video.onloadeddata = resolve; });
    return Number($("live-fps").value) || 30;
  });
});
$("live-stop").addEventListener("click", () => {
  stop();
  status("stopped");
});
