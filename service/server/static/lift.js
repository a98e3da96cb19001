// The /lift requests of an input: poses lifted alone in batches within the service's limits, or a
// sequence's tracked people lifted temporally, a long clip cut with the context its windows read.

import { reach, splitClip } from "./track.js";

export const bytes = (text) => new Blob([text]).size;

// The temporal mode of a lift: the one asked, else offline for a sequence and off for one frame;
// a default the service has no model for falls back to causal, then off ({mode, note}).
export function chooseMode(asked, sequence, model) {
  const have = (model.temporal ?? []).map((t) => t.mode);
  let mode = asked || (sequence ? "offline" : "off");
  if (!asked && mode !== "off" && !have.includes(mode)) {
    const fallback = have.includes("causal") ? "causal" : "off";
    return { mode: fallback, note: `no ${mode} temporal model on this service: temporal ${fallback}` };
  }
  return { mode, note: "" };
}

// Why frames numbered so are unrelated still images rather than a clip, or null for a clip: ids with
// no number, or numbers of which fewer than half follow the previous one by 1 (repnet.cli.lift.stills_reason).
export function stillsReason(numberedBy, frames) {
  const distinct = [...new Set(frames)].sort((a, b) => a - b);
  if (numberedBy === null || numberedBy === undefined || distinct.length < 2) return null;
  if (numberedBy === "image names") return "image ids not numbered";
  const ones = distinct.slice(1).filter((f, i) => f - distinct[i] === 1).length;
  return 2 * ones >= distinct.length - 1 ? null : `${numberedBy} not consecutive`;
}

// Each pose as it is sent: with its track and frame number when it has a track.
function items(poses, trackIds, frames) {
  return poses.map((pose, i) => (trackIds && trackIds[i] !== null && trackIds[i] !== undefined
    ? { ...pose, track_id: trackIds[i], frame: frames[i] } : pose));
}

// Requests of at most max_request_poses (and 256) poses and max_body_bytes bytes, in order.
function* batches(sent, extra, limits) {
  let start = 0;
  while (start < sent.length) {
    let size = Math.min(limits.max_request_poses, 256, sent.length - start);
    let body = JSON.stringify({ ...extra, poses: sent.slice(start, start + size) });
    while (bytes(body) > limits.max_body_bytes && size > 1) {
      size = Math.ceil(size / 2);
      body = JSON.stringify({ ...extra, poses: sent.slice(start, start + size) });
    }
    const send = Array.from({ length: size }, (_, k) => start + k);
    yield { send, keep: send.map(() => true), body };
    start += size;
  }
}

// The requests ({send, keep, body}: the poses' positions, which answers are kept) of `poses`.
// temporal: {mode, fps}; trackIds and frames: per pose, or trackIds null for poses lifted alone.
export function liftRequests(poses, trackIds, frames, temporal, extra, model) {
  const sent = items(poses, trackIds, frames);
  if (temporal.mode === "off") return [...batches(sent, extra, model.limits)];
  const contract = (model.temporal ?? []).find((t) => t.mode === temporal.mode);
  const body = { ...extra, temporal: temporal.mode, fps: temporal.fps };
  if (!contract) return [{ send: sent.map((_, i) => i), keep: sent.map(() => true), body: JSON.stringify({ ...body, poses: sent }) }];
  const widest = Math.max(...sent.map((p) => bytes(JSON.stringify(p))));
  const most = Math.min(model.limits.max_temporal_poses ?? 0, Math.floor((model.limits.max_body_bytes - model.rules.envelope_bytes) / (widest + 2)));
  const parts = splitClip(trackIds ?? sent.map(() => null), frames, reach(contract, temporal.fps), most);
  return parts.map((part) => ({ ...part, body: JSON.stringify({ ...body, poses: part.send.map((i) => sent[i]) }) }));
}
