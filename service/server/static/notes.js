// What the page says about a lift besides its answer: the field an API error belongs next to, the
// service's warnings, and the poses of a file the service did not lift. Text only (textContent).

// The field an API error names -> the page field it belongs next to.
export function slotOf(field, source) {
  if (field === "format" || /\.format$/.test(field)) return "format";
  if (field === "confidence_threshold") return "threshold";
  if (field === "temporal") return "temporal";
  if (field === "fps") return "rate";
  if (/(^|\.)intrinsics(\.|$)/.test(field)) return "intrinsics";
  if (/(^|\.)person_height_m$/.test(field)) return "height";
  if (/(^|\.)image_size$/.test(field)) return "image-size";
  return source;
}

// The service's warnings, each once, as items of `list`.
export function showWarnings(list, warnings) {
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

// An error item's field within its pose ("keypoints[3]"), without the request's "poses[k]."
const fieldIn = (item) => String(item.field ?? "").replace(/^poses\[\d+\]\.?/, "");

// A skipped pose named by its place in the input (poses[i], its frame and person) and why.
function skippedText(at, item, parsed) {
  const field = fieldIn(item);
  const who = parsed.labels?.[at] ?? `frame ${parsed.frames[at]}, person ${parsed.people[at] ?? 0}`;
  return `poses[${at}] (${who}): ${field ? `${field}: ` : ""}${item.reason ?? item.message}`;
}

// The poses a lift skipped ({at, item}), as items of `list`, each named and with why.
export function showSkipped(list, skipped, parsed) {
  list.replaceChildren();
  const shown = skipped.slice(0, 20);
  for (const { at, item } of shown) {
    const entry = document.createElement("li");
    entry.textContent = `skipped ${skippedText(at, item, parsed)}`;
    list.append(entry);
  }
  if (skipped.length > shown.length) {
    const more = document.createElement("li");
    more.textContent = `and ${skipped.length - shown.length} more`;
    list.append(more);
  }
}
