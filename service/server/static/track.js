// Sequences on the page: people followed from frame to frame, and temporal requests cut with context.
// The same rules as repnet.client.tracker (assignTracks) and repnet.core.contract + repnet.client.chunks
// (reach, splitClip); tests/service/test_page.py checks that they give the same answers.

const MIN_SHARED = 4;  // joints visible in both poses
const GATE = 0.5;  // body sizes a person may move between consecutive frames
const GATE_PER_S = 2.0;  // and more per second since the track was last seen

// Python's round(): halves to even, as the service rounds max_gap_s * fps.
function roundHalfEven(x) {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

// A pose's points: per joint [x, y] or null (missing).
function pointsOf(pose) {
  const rows = Array.isArray(pose?.keypoints) ? pose.keypoints : [];
  return rows.map((r) => (Array.isArray(r) && Number.isFinite(r[0]) && Number.isFinite(r[1]) ? [r[0], r[1]] : null));
}

// The spread of the visible joints (geometry.visible_spread): the body size the model normalises by.
function spread(points) {
  const seen = points.filter(Boolean);
  if (!seen.length) return 0;
  const mean = [0, 1].map((c) => seen.reduce((s, p) => s + p[c], 0) / seen.length);
  const sum = seen.reduce((s, p) => s + (p[0] - mean[0]) ** 2 + (p[1] - mean[1]) ** 2, 0);
  return Math.sqrt(sum / (2 * seen.length));
}

function cost(track, points, size) {
  let shared = 0;
  let total = 0;
  points.forEach((p, j) => {
    const q = track.points[j];
    if (p && q) {
      shared += 1;
      total += Math.hypot(p[0] - q[0], p[1] - q[1]);
    }
  });
  const scale = (size + track.size) / 2;
  return shared >= MIN_SHARED && scale > 0 ? total / shared / scale : Infinity;
}

// The track number of each pose (0, 1, … in order of appearance): frames[i] its frame number; a
// track not seen for longer than maxGapS (the service's, GET /v1/model rules.max_gap_s) ends.
export function assignTracks(frames, poses, fps, maxGapS) {
  const points = poses.map(pointsOf);
  const sizes = points.map(spread);
  const out = new Array(poses.length).fill(-1);
  const longestGap = roundHalfEven(maxGapS * fps);
  let tracks = [];
  let made = 0;
  for (const frame of [...new Set(frames)].sort((a, b) => a - b)) {
    const here = frames.map((f, i) => (f === frame ? i : -1)).filter((i) => i >= 0);
    tracks = tracks.filter((t) => frame - t.frame - 1 <= longestGap);
    const pairs = [];
    tracks.forEach((track, r) => here.forEach((pose, c) => {
      const value = cost(track, points[pose], sizes[pose]);
      if (value <= GATE + GATE_PER_S * (frame - track.frame) / fps) pairs.push([value, r, c]);
    }));
    pairs.sort((a, b) => a[0] - b[0] || a[1] - b[1] || a[2] - b[2]);
    const taken = new Map();
    const usedRows = new Set();
    for (const [, r, c] of pairs) {
      if (usedRows.has(r) || taken.has(c)) continue;
      usedRows.add(r);
      taken.set(c, tracks[r]);
    }
    here.forEach((pose, c) => {
      let track = taken.get(c);
      if (!track) {
        track = { number: made };
        made += 1;
        tracks.push(track);
      }
      Object.assign(track, { frame, points: points[pose], size: sizes[pose] });
      out[pose] = track.number;
    });
  }
  return out;
}

// [before, after]: the frames a temporal model's window reads around a frame (Contract.reach).
export function reach(contract, fps) {
  const q = Math.max(1, Math.ceil(fps / contract.max_fps - 1e-9));
  const span = (contract.window - 1) / contract.grid_fps * (fps / q);
  if (contract.mode === "causal") return [q * Math.ceil(span - 1e-6), 0];
  return [q * Math.ceil(span / 2 - 1e-6), q * Math.ceil(span / 2 - 1e-6)];
}

const searchsorted = (values, x, right) => {
  let [lo, hi] = [0, values.length];
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (right ? values[mid] <= x : values[mid] < x) lo = mid + 1;
    else hi = mid;
  }
  return lo;
};

// One track's increasing frame numbers cut into parts of at most maxPoses: [first context, first
// kept, last kept, last context] indexes (repnet.client.chunks.runs).
function runs(frames, [before, after], maxPoses) {
  const n = frames.length;
  const left = frames.map((f) => Math.max(searchsorted(frames, f - before, true) - 1, 0));
  const right = frames.map((f) => Math.min(searchsorted(frames, f + after, false), n - 1));
  const found = [];
  for (let start = 0; start < n;) {
    const first = left[start];
    const stop = searchsorted(right, first + maxPoses - 1, true) - 1;
    if (stop < start) throw new Error(`a request of ${maxPoses} poses cannot hold one frame's context (${before} frames before, ${after} after)`);
    found.push([first, start, stop, right[stop]]);
    start = stop + 1;
  }
  return found;
}

// The requests of a clip ({send, keep}: positions in the clip, in order, and whether each answer is
// kept): whole tracks packed in order, a longer track cut with its context (repnet.client.chunks).
export function splitClip(trackIds, frames, span, maxPoses) {
  const groups = new Map();
  trackIds.forEach((track, i) => {
    const key = track === null || track === undefined ? `pose ${i}` : `track ${track}`;
    if (!groups.has(key)) groups.set(key, []);
    groups.get(key).push(i);
  });
  const units = [];
  for (const members of groups.values()) {
    const mine = members.map((i, k) => [frames[i], k, i]).sort((a, b) => a[0] - b[0] || a[1] - b[1]).map((m) => m[2]);
    if (mine.length <= maxPoses) {
      units.push({ send: mine, keep: mine.map(() => true) });
      continue;
    }
    for (const [first, start, stop, last] of runs(mine.map((i) => frames[i]), span, maxPoses)) {
      const send = mine.slice(first, last + 1);
      units.push({ send, keep: send.map((_, k) => k + first >= start && k + first <= stop) });
    }
  }
  const parts = [];
  let size = maxPoses;
  for (const unit of units) {
    if (size + unit.send.length > maxPoses) {
      parts.push([]);
      size = 0;
    }
    parts[parts.length - 1].push(unit);
    size += unit.send.length;
  }
  return parts.map((members) => {
    const pairs = members.flatMap((u) => u.send.map((s, k) => [s, u.keep[k]])).sort((a, b) => a[0] - b[0]);
    return { send: pairs.map((p) => p[0]), keep: pairs.map((p) => p[1]) };
  });
}
