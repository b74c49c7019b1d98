// The viewer of one session: server-rendered images of a camera the user flies, redrawn after each
// fold (fold events over SSE), with the input cameras as frustums, a scrubber and snap buttons.
import { download, formatAge, formatBytes, json, request, subscribe, withToken } from "./api.js";
import * as cam from "./camera.js";

const params = new URLSearchParams(location.search);
const badParams = [];
// a whole number from the page's query, within [low, high]; else the default, and the page says so
function countParam(name, fallback, low, high) {
  if (!params.has(name)) return fallback;
  const value = Number(params.get(name));  // digits only: Number() would take 1e3 and 0x10 too
  if (/^[0-9]+$/.test(params.get(name)) && value >= low && value <= high) return value;
  badParams.push(`?${name}=${params.get(name)}: expected a whole number from ${low} to ${high}; ${fallback} used`);
  return fallback;
}
let WIDTH = countParam("width", 512, 16, 4096);  // full-quality view size (pixels; `fitSize` may shrink it)
let HEIGHT = countParam("height", 384, 16, 4096);
const LOW = 0.5;  // size factor of the images asked for while the pose moves
// ... and their level of detail: the best-supported N Gaussians (rendering time grows with N)
const PREVIEW_GAUSSIANS = countParam("preview_gaussians", 60000, 1, 1e9);
const REST_MS = 180;  // the pose counts as resting this long after its last change
const SEND_GAP_MS = 40;  // while a picture is out, a newer pose is asked for at most this often
// ... and at most this many are out: one rendering, one waiting that a newer one replaces; more would
// wait in the browser for a connection (six per host), out of the service's reach, and be rendered
// one after another once they got there, each of a pose already left behind
const MAX_INFLIGHT = 2;
// while frames stream in, the picture follows them at most this often: each picture is a render the
// service's cores make instead of folds (a stream's own frames come first, the viewer's last)
const FOLD_GAP_MS = 400;
// ... and while they come faster than that, those pictures are previews (as for a moving pose), with
// a full one at most this often and as soon as the stream pauses: a full picture costs the service
// several previews' time, all of it taken from the stream's folds
const STREAM_FULL_GAP_MS = 2000;
// fold events at most this often (seconds, the stream's `?every=`): the page draws a few times a
// second, and each event of a 30 Hz stream would cost the browser a wake-up and a parse
const EVENT_EVERY_S = 0.2;
// no fold event for this long: the stream has paused for FOLD_GAP_MS (a fold's event may come up to
// an interval after it)
const PAUSE_MS = FOLD_GAP_MS + 1000 * EVENT_EVERY_S;
// this page among the service's viewers: its waiting picture is replaced by its newer ones only
const VIEWER_ID = Math.random().toString(36).slice(2, 12);
const ORBIT_RAD_PER_PX = 0.006;
const FLY_SPEED = 0.6;  // orbit distances per second
const MAX_FRUSTUMS = 20;  // frustums drawn by default: more hide the picture under a wireframe
const sessionId = decodeURIComponent(location.pathname.split("/")[2]);
const $ = (id) => document.getElementById(id);

const view = $("view"), overlay = $("overlay"), stage = $("stage");
function setSize(width, height) {
  WIDTH = width;
  HEIGHT = height;
  for (const c of [view, overlay]) { c.width = WIDTH; c.height = HEIGHT; }
  stage.style.aspectRatio = `${WIDTH} / ${HEIGHT}`;
  stage.style.width = `min(100cqw, calc(100cqh * ${WIDTH} / ${HEIGHT}))`;
}
setSize(WIDTH, HEIGHT);

// The view's size within the largest picture the service renders (`/v1/viewer/info`): a larger
// ?width= and ?height= would be refused at every full picture, so they are scaled down, and the page
// says so.
function fitSize(most) {
  if (WIDTH * HEIGHT <= most) return;
  const s = Math.sqrt(most / (WIDTH * HEIGHT));
  const w = Math.max(16, Math.floor(WIDTH * s)), h = Math.max(16, Math.floor(HEIGHT * s));
  badParams.push(`?width=${WIDTH}&height=${HEIGHT}: above the largest picture the service renders ` +
                 `(${most} pixels); ${w}x${h} used`);
  setSize(w, h);
  Object.assign(state, { width: w, height: h, K: cam.viewIntrinsics(null, w, h) });
}

const NOT_ASKED = { version: -1, full: false, at: -Infinity };
// Everything a test (or the console) may want to read is on window.viewer.
const state = {
  id: sessionId, width: WIDTH, height: HEIGHT,
  pose: { R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], p: [0, 0, 0] }, distance: 1, up: [0, -1, 0],
  K: cam.viewIntrinsics(null, WIDTH, HEIGHT),
  mode: "rgb", cameras: [], selected: -1, frames: 0, voxels: 0, labelDim: 0,
  streamOpened: false,  // the fold events' first state came: a later one is a reconnect
  version: 0, changedAt: 0, foldDrawnAt: -Infinity,  // foldDrawnAt: when a fold last asked for a picture
  foldSeenAt: -Infinity, foldGap: Infinity,  // the last fold event; ms from the fold before
  // when a full picture was last asked for: the page's opening counts as one, so a page opened on a
  // running stream starts with previews (sooner on screen, and a few times cheaper for the service)
  fullAskedAt: performance.now(),
  inflight: 0, asked: NOT_ASKED, superseded: 0,  // requests out; the newest one asked; answers superseded by a newer one
  drawn: { version: -1, full: false, mode: null, frames: 0, headers: {} },
  frustums: { chosen: [], drawn: 0 },  // input cameras given a frustum; how many were in front of the view
  status: "connecting…",
  images: 0, info: null, timing: {}, history: [],  // history: timings of the last HISTORY images
};
const HISTORY = 500;
window.viewer = state;

// -- the image loop ---------------------------------------------------------------------------
// moving: a pose change under the user's hand (previews until it rests); otherwise (a fold, a mode,
// a snap) the full picture is asked for at once.
function changed(moving = true) {
  state.version += 1;
  state.changedAt = moving ? performance.now() : -Infinity;
  drawFrustums();
  pump();
}

// Whether frames stream in: the last two folds came less than FOLD_GAP_MS apart, the latest one's
// event less than PAUSE_MS ago.
function streaming() {
  return state.foldGap < FOLD_GAP_MS && performance.now() - state.foldSeenAt < PAUSE_MS;
}

// Whether a full picture may be asked for now, as far as the stream goes: while frames stream in,
// one every STREAM_FULL_GAP_MS.
function fullDue() {
  return !streaming() || performance.now() - state.fullAskedAt >= STREAM_FULL_GAP_MS;
}

function imageUrl(full) {
  const w = full ? WIDTH : Math.round(WIDTH * LOW), h = full ? HEIGHT : Math.round(HEIGHT * LOW);
  const s = w / WIDTH;
  const K = [state.K[0] * s, state.K[1] * s, state.K[2] * s, state.K[3] * s];
  const mode = state.mode === "composited" ? "rgb" : state.mode;
  const q = new URLSearchParams({
    pose: cam.toMatrix(state.pose).map((x) => x.toPrecision(9)).join(","),
    K: K.map((x) => x.toPrecision(9)).join(","), width: w, height: h, mode,
    format: full || mode === "labels" ? "png" : "jpeg", quality: 70,
  });
  if (state.mode === "composited") q.set("colour", "composited");
  if (!full) q.set("max_gaussians", PREVIEW_GAUSSIANS);
  // previews keep the colour scale of the last full depth picture, so colours do not flicker
  if (!full && mode === "depth" && state.depthRange) q.set("depth_range", state.depthRange);
  return `/v1/sessions/${encodeURIComponent(sessionId)}/image?${q}`;
}

// The newest pose is asked for as soon as it changes (at most one request per SEND_GAP_MS while
// others are out, and at most MAX_INFLIGHT out), even while an older picture is on its way: the
// service renders viewer pictures last, one of this page's at a time, and answers a request that
// still waits when a newer one of this page (VIEWER_ID) arrives with 204 (superseded). So what it
// renders next is always the newest pose, and a moving view costs one waiting picture, not a queue
// of stale ones. A response that arrives after a newer picture was drawn is dropped, so the view
// never goes back in time. An empty session has nothing to draw: no request until its first fold,
// which then gets one at once.
function pump() {
  showText();
  if (!state.info || !state.frames || state.deleted) return;
  const { version, frames } = state;
  if (state.failed === version) return;  // asked and refused: wait for the next change
  const resting = performance.now() - state.changedAt >= REST_MS && fullDue();
  if (state.drawn.version === version && (state.drawn.full || !resting)) {
    if (!state.drawn.full) setTimeout(pump, REST_MS);
    return;
  }
  const full = resting;
  if (state.asked.version === version && (state.asked.full || !full)) return;  // its answer pumps again
  if (state.inflight >= MAX_INFLIGHT) return;  // an answer pumps again
  const wait = state.asked.at + SEND_GAP_MS - performance.now();
  if (state.inflight && wait > 0) {
    clearTimeout(state.sendTimer);
    state.sendTimer = setTimeout(pump, wait);
    return;
  }
  const mode = state.mode;
  const t0 = performance.now();
  state.asked = { version, full, at: t0 };
  if (full) state.fullAskedAt = t0;
  state.inflight += 1;
  request(imageUrl(full), { headers: { "X-Canonical-Viewer": VIEWER_ID } })
    .then(async (response) => {
      if (response.status === 204) { state.superseded += 1; return; }  // a newer request of ours replaced it
      const blob = await response.blob();
      const t1 = performance.now();
      const bitmap = await createImageBitmap(blob);
      if (version < state.drawn.version || (version === state.drawn.version && state.drawn.full && !full)) return;
      const ctx = view.getContext("2d");
      ctx.imageSmoothingEnabled = !full;
      ctx.drawImage(bitmap, 0, 0, WIDTH, HEIGHT);
      state.images += 1;
      state.timing = { ...serverTiming(response.headers.get("Server-Timing")), fetch: t1 - t0,
                       decode: performance.now() - t1, bytes: blob.size, full, at: performance.now() };
      state.history.push(state.timing);
      if (state.history.length > HISTORY) state.history.shift();
      state.drawn = { version, full, mode, frames, url: response.url, headers: Object.fromEntries(response.headers) };
      view.dataset.version = version;
      view.dataset.full = full;
      showStatus();  // "rendering…" ends with the picture, not a text interval later
      showReading(mode, response.headers);
      const centre = Number(response.headers.get("X-Canonical-Centre-Depth"));
      if (state.retarget && full && centre > 0) { state.distance = centre; state.retarget = false; drawFrustums(); }
      $("timing").textContent = `${full ? "full" : "preview"} ${bitmap.width}×${bitmap.height} · ` +
        `render ${state.timing.render?.toFixed(0)} ms · encode ${state.timing.encode?.toFixed(0)} ms · ` +
        `round trip ${state.timing.fetch.toFixed(0)} ms · ${(blob.size / 1024).toFixed(0)} KiB`;
      $("error").hidden = true;
    })
    .catch((error) => {
      showError(error);
      state.failed = version;
      if (error.status === 429) setTimeout(() => { state.failed = null; pump(); }, 1000);  // busy: try again
    })
    .finally(() => {
      state.inflight -= 1;
      if (state.asked.version === version && state.asked.full === full) state.asked = NOT_ASKED;  // answered
      pump();
    });
  showText();
}

// The line over the view says what it waits for: the service, the first frame, or a picture of
// the latest fold.
function showStatus() {
  const n = state.frames;
  let text = "connecting…";
  if (state.deleted) return;  // the deletion's text stays
  if (state.info && !n) text = "waiting for the first frame";
  else if (state.info) {
    const folded = `${n} frame${n === 1 ? "" : "s"} folded`;
    text = state.drawn.frames < n ? `${folded} · rendering…` : folded;
  }
  if (text !== state.status) $("status").textContent = state.status = text;
}

function serverTiming(text) {
  const out = {};
  for (const part of (text || "").split(",")) {
    const m = part.trim().match(/^(\w+);dur=([\d.]+)/);
    if (m) out[m[1]] = Number(m[2]);
  }
  return out;
}

function showError(error) {
  if (error.status === 404 && error.message.startsWith("session_id:")) { sessionGone(error.message); return; }
  if (state.deleted) return;  // what the page says of the session's end stays
  $("error").textContent = error.message;
  $("error").hidden = false;
}

// The session is gone, whichever of the page's requests or its event stream learns it first: a page
// that showed it says it was deleted; one that never found it (a stale link) says there is no such
// session. Nothing more is asked for.
function sessionGone(message) {
  const shown = state.info !== null;
  state.deleted = true;
  $("status").textContent = state.status = shown ? "deleted" : "no such session";
  $("live").textContent = "gone";
  $("error").textContent = shown ? "this session was deleted" : message;
  $("error").hidden = false;
}

// Scale bar (depth) and legend (labels) for the picture just drawn.
function showReading(mode, headers) {
  const range = headers.get("X-Canonical-Depth-Range");
  $("scale").hidden = mode !== "depth" || !range;
  if (mode === "depth" && range) {
    if (state.drawn.full) state.depthRange = range;
    const [near, far] = range.split(",").map(Number);
    $("near").textContent = `${near.toFixed(2)} m`;
    $("far").textContent = `${far.toFixed(2)} m`;
  }
  const labels = headers.get("X-Canonical-Labels");
  const legend = $("legend");
  legend.hidden = mode !== "labels";
  if (mode === "labels") {
    const ids = labels ? labels.split(",").map(Number) : [];
    legend.replaceChildren(...ids.map((k) => {
      const li = document.createElement("li");
      li.dataset.label = k;
      const swatch = document.createElement("span");
      const [r, g, b] = state.info.label_palette[1 + (k % 255)];  // as the pictures: labels past 254 take the colours of those 255 below them
      swatch.style.background = `rgb(${r},${g},${b})`;
      li.append(swatch, `label ${k}`);
      return li;
    }));
  }
}

function drawScaleBar() {
  const bar = $("scale-bar"), ctx = bar.getContext("2d");
  const lut = state.info.depth_colormap;
  lut.forEach(([r, g, b], i) => {
    ctx.fillStyle = `rgb(${r},${g},${b})`;
    ctx.fillRect(i * bar.width / lut.length, 0, bar.width / lut.length + 1, bar.height);
  });
}

// -- input cameras -------------------------------------------------------------------------------
// The input cameras that get a frustum: "some" (the default) is at most MAX_FRUSTUMS: one less
// spread evenly over the track, the first and the latest among them, and the selected one.
function frustumIndices(n, selected, choice) {
  if (choice === "none") return [];
  if (choice === "all" || n <= MAX_FRUSTUMS) return [...Array(n).keys()];
  const spread = MAX_FRUSTUMS - 1;
  const picks = new Set(Array.from({ length: spread }, (_, i) => Math.round(i * (n - 1) / (spread - 1))));
  if (selected >= 0 && selected < n) picks.add(selected);
  return [...picks].sort((a, b) => a - b);
}

function drawFrustums() {
  const ctx = overlay.getContext("2d");
  ctx.clearRect(0, 0, WIDTH, HEIGHT);
  const chosen = frustumIndices(state.cameras.length, state.selected, $("frustums").value);
  state.frustums = { chosen, drawn: 0 };
  const depth = Math.max(0.02, 0.08 * state.distance);
  for (const k of chosen) {
    const pts = cam.frustum(state.cameras[k], depth).map((X) => cam.project(state.pose, state.K, X));
    if (pts.some((p) => p === null)) continue;  // behind the view
    ctx.strokeStyle = k === state.selected ? "rgba(240,192,72,0.95)" : "rgba(120,200,255,0.55)";
    ctx.lineWidth = k === state.selected ? 2 : 1;
    ctx.beginPath();
    for (let i = 1; i <= 4; i++) { ctx.moveTo(...pts[0]); ctx.lineTo(...pts[i]); }
    ctx.moveTo(...pts[1]);
    for (const i of [2, 3, 4, 1]) ctx.lineTo(...pts[i]);
    ctx.stroke();
    state.frustums.drawn += 1;
  }
}

function updateScrubber() {
  const n = state.cameras.length;
  const scrub = $("scrub");
  scrub.max = Math.max(0, n - 1);
  scrub.disabled = n === 0;
  if (state.selected >= 0) scrub.value = state.selected;
  $("camera-k").textContent = n ? `camera ${state.selected + 1} / ${n}` : "no input cameras";
}

// Put the view at input camera k: its pose, its field of view, the orbit target at the depth of
// the scene's middle (kept from before, or 1 m).
function snapTo(k) {
  const c = state.cameras[k];
  if (!c) return;
  state.selected = k;
  state.pose = cam.fromMatrix(c.c2w);
  state.up = cam.scale(cam.column(state.pose.R, 1), -1);
  state.K = cam.viewIntrinsics(c, WIDTH, HEIGHT);
  state.retarget = true;  // orbit about what the next picture shows in its middle
  updateScrubber();
  changed(false);
}

// -- stats -------------------------------------------------------------------------------------
// The session's figures once its folds pause (no event for PAUSE_MS), not while frames stream in:
// the service counts the Gaussians by decoding the scene, which during a stream takes the cores of
// its folds.
let statsTimer = null;
function refreshStats() {
  clearTimeout(statsTimer);
  statsTimer = setTimeout(async () => {
    try {
      const s = await json(`/v1/sessions/${encodeURIComponent(sessionId)}`);
      state.voxels = s.voxels;
      setFrames(s.frames);
      $("gaussians").textContent = s.gaussians;
      $("memory").textContent = formatBytes(s.memory_bytes);
      const limit = s.inconsistent_depth_below;
      $("near-limit").textContent = limit == null ? "–" : `${limit.toFixed(2)} m`;
      setLabels(s.label_dim);
    } catch (error) { showError(error); }
  }, PAUSE_MS);
}

// The fold counts, the last fold's age and the status line; while frames stream in, written at most
// every TEXT_GAP_MS (the latest state always): at 30 frames/s, text written at every fold costs the
// browser a layout and a paint per fold, more than the pictures do.
const TEXT_GAP_MS = 250;
let textTimer = null, textAt = -Infinity;
function showText() {
  if (textTimer !== null) return;  // the timer writes the latest state
  const wait = textAt + TEXT_GAP_MS - performance.now();
  if (streaming() && wait > 0) { textTimer = setTimeout(() => { textTimer = null; showText(); }, wait); return; }
  textAt = performance.now();
  const texts = { frames: state.frames, voxels: state.voxels, "last-fold": formatAge(state.lastFold) };
  for (const [id, text] of Object.entries(texts)) {
    if ($(id).textContent !== String(text)) $(id).textContent = text;  // an unchanged text is not rewritten
  }
  showStatus();
}

function setFrames(n) {
  state.frames = n;
  if (!n) view.getContext("2d").clearRect(0, 0, WIDTH, HEIGHT);  // every frame removed: nothing to show
  showText();
}

// The input cameras read again and the picture redrawn, the view where it is.
function refreshTrack() {
  json(`${base}/cameras`).then((track) => {
    state.cameras = track.cameras;
    state.selected = Math.min(state.selected, state.cameras.length - 1);
    state.failed = null;  // a picture refused before (the service down) is asked for again
    updateScrubber();
    changed(false);
  }).catch(showError);
}

function setLabels(labelDim) {
  state.labelDim = labelDim;
  $("mode").querySelector("option[value=labels]").disabled = labelDim === 0;
  if (labelDim === 0 && state.mode === "labels") {  // its labels removed: every label picture would be refused
    $("mode").value = state.mode = "rgb";
    $("legend").hidden = true;
    changed(false);
  }
}

function onEvent(name, data) {
  if (name === "state" || name === "corrected") {
    const missed = !state.frames && data.frames > 0;  // folds between the track's answer and the stream
    // a stream opened again (the service restarted, the connection dropped), or poses corrected and
    // frames removed: what the page shows may be stale
    const stale = name === "corrected" || state.streamOpened;
    state.streamOpened = true;
    state.voxels = data.voxels;
    setFrames(data.frames);
    setLabels(data.label_dim);
    if (missed) json(`${base}/cameras`).then(showTrack).catch(showError);
    else if (stale) refreshTrack();
    if (name === "corrected") refreshStats();  // its Gaussians and memory changed too
    return;
  }
  if (name === "recoloured") {  // colours solved in the background: the picture shown is older
    changed(false);
    refreshStats();
    return;
  }
  if (name === "deleted") {  // nothing more to ask for: no picture, and the status says why
    sessionGone();
    return;
  }
  if (name !== "fold") return;
  // one event stands for the folds of the last EVENT_EVERY_S (`?every=`): the latest fold's counts,
  // every camera of them, and the latest advice among them
  if (data.warned) {  // the stream's latest advice stays up until newer advice replaces it
    $("warning").textContent = `frame ${data.warned.frame_index}: ${data.warned.warnings.join(" · ")}`;
    $("warning").hidden = false;
  }
  state.frames = data.frames;
  state.voxels = data.voxels;
  // the service's clocks of the latest fold and the one before (the track's latest, for the first
  // event after the page opened on a stream): the gap the stream has, not the one events come with
  const before = data.previous_time ?? state.lastFold;
  state.foldGap = before == null ? Infinity : 1000 * (data.time - before);
  state.lastFold = data.time;
  state.foldSeenAt = performance.now();
  showText();
  for (const camera of data.cameras) {
    if (!state.cameras.some((c) => c.frame_index === camera.frame_index)) state.cameras.push(camera);
  }
  followFolds();
  refreshStats();
}

// The picture after a fold: at once for the first fold and after a pause, else at most once per
// FOLD_GAP_MS, always ending on the latest fold (a timer takes the folds that came meanwhile).
let foldTimer = null;
function followFolds() {
  const wait = state.foldDrawnAt + FOLD_GAP_MS - performance.now();
  if (wait > 0) {
    if (foldTimer === null) foldTimer = setTimeout(() => { foldTimer = null; followFolds(); }, wait);
    return;
  }
  state.foldDrawnAt = performance.now();
  if ($("follow").checked || state.selected < 0) snapTo(state.cameras.length - 1);
  else { updateScrubber(); changed(false); }
}

// -- navigation -----------------------------------------------------------------------------------
const pointers = new Map();
let gesture = null;

// W A S D need the keyboard: the view takes it on load and when the pointer comes over it, unless
// the user is typing in a field (the token form).
const TYPING = new Set(["text", "password", "search", "email", "url", "tel", "number"]);
function focusView() {
  const a = document.activeElement;
  const typing = a && (a.isContentEditable || a.tagName === "TEXTAREA" || (a.tagName === "INPUT" && TYPING.has(a.type)));
  if (!typing) view.focus({ preventScroll: true, focusVisible: false });  // the outline marks a Tab's focus only
}
stage.addEventListener("pointerenter", focusView);

stage.addEventListener("pointerdown", (e) => {
  stage.setPointerCapture(e.pointerId);
  view.focus({ preventScroll: true, focusVisible: false });
  pointers.set(e.pointerId, [e.clientX, e.clientY]);
  gesture = { pan: e.button === 2 || e.shiftKey };
});

stage.addEventListener("pointermove", (e) => {
  if (!pointers.has(e.pointerId)) return;
  const before = [...pointers.values()];
  const last = pointers.get(e.pointerId);
  pointers.set(e.pointerId, [e.clientX, e.clientY]);
  const px = WIDTH / stage.clientWidth;  // screen pixels -> view pixels
  if (pointers.size >= 2) {
    const after = [...pointers.values()];
    const spread = (p) => Math.hypot(p[0][0] - p[1][0], p[0][1] - p[1][1]);
    const mid = (p) => [(p[0][0] + p[1][0]) / 2, (p[0][1] + p[1][1]) / 2];
    const [m0, m1] = [mid(before), mid(after)];
    pan((m1[0] - m0[0]) * px, (m1[1] - m0[1]) * px);
    if (spread(before) > 0 && spread(after) > 0) zoomBy(spread(before) / spread(after));
    return;
  }
  const dx = (e.clientX - last[0]) * px, dy = (e.clientY - last[1]) * px;
  if (gesture?.pan) pan(dx, dy);
  else {
    state.pose = cam.orbit(state.pose, state.distance, state.up, -dx * ORBIT_RAD_PER_PX, -dy * ORBIT_RAD_PER_PX);
    changed();
  }
});

for (const type of ["pointerup", "pointercancel"]) {
  stage.addEventListener(type, (e) => { pointers.delete(e.pointerId); if (!pointers.size) gesture = null; });
}
stage.addEventListener("contextmenu", (e) => e.preventDefault());
stage.addEventListener("wheel", (e) => {
  e.preventDefault();
  zoomBy(Math.exp(e.deltaY * 0.0015));
}, { passive: false });

// Drag the scene with the pointer: metres per view pixel at the orbit target's depth.
function pan(dx, dy) {
  const m = state.distance / state.K[0];
  state.pose = cam.translate(state.pose, [-dx * m, -dy * m, 0]);
  changed();
}

function zoomBy(factor) {
  ({ pose: state.pose, distance: state.distance } = cam.zoom(state.pose, state.distance, factor));
  changed();
}

const keys = new Set();
const FLY = { KeyW: [0, 0, 1], KeyS: [0, 0, -1], KeyA: [-1, 0, 0], KeyD: [1, 0, 0] };
stage.addEventListener("keydown", (e) => {
  if (FLY[e.code] || e.code === "KeyQ" || e.code === "KeyE") {
    e.preventDefault();
    if (!keys.size) requestAnimationFrame(fly);
    keys.add(e.code);
  }
});
stage.addEventListener("keyup", (e) => keys.delete(e.code));
view.addEventListener("blur", () => keys.clear());

let lastFly = null;
function fly(now) {
  if (!keys.size) { lastFly = null; return; }
  const dt = lastFly === null ? 1 / 60 : Math.min(0.1, (now - lastFly) / 1000);
  lastFly = now;
  const step = FLY_SPEED * state.distance * dt;
  for (const code of keys) {
    if (FLY[code]) state.pose = cam.translate(state.pose, cam.scale(FLY[code], step));
    if (code === "KeyE") state.pose = cam.lift(state.pose, state.up, step);
    if (code === "KeyQ") state.pose = cam.lift(state.pose, state.up, -step);
  }
  changed();
  requestAnimationFrame(fly);
}

// -- controls ----------------------------------------------------------------------------------------
$("mode").addEventListener("change", (e) => {
  state.mode = e.target.value;
  state.depthRange = null;
  changed(false);
  focusView();  // the keys fly again: the list would take them as a search for a mode (D: depth)
});
$("scrub").addEventListener("input", (e) => snapTo(Number(e.target.value)));
$("latest").addEventListener("click", () => snapTo(state.cameras.length - 1));
$("frustums").addEventListener("change", drawFrustums);
const base = `/v1/sessions/${encodeURIComponent(sessionId)}`;
// a download refused for its token asks for one, as every other request of the page does
$("ply").addEventListener("click", () => withToken(() => download(`${base}/gaussians.ply`, `${sessionId}.ply`)).catch(showError));
$("splat").addEventListener("click", () => withToken(() => download(`${base}/gaussians.splat`, `${sessionId}.splat`))
  .catch(showError));

// -- start -----------------------------------------------------------------------------------------
// The input cameras and the session's counts (`GET .../cameras`); the view goes to the latest camera.
function showTrack(track) {
  state.cameras = track.cameras;
  state.lastFold = track.last_fold;
  if (track.last_fold_age != null && 1000 * track.last_fold_age < FOLD_GAP_MS) {
    // opened on a running stream: its first pictures are previews, as those of a stream seen running
    state.foldSeenAt = performance.now() - 1000 * track.last_fold_age;
    state.foldGap = 0;
  }
  setFrames(track.frames);
  setLabels(track.label_dim);
  if (state.cameras.length) snapTo(state.cameras.length - 1);
  else { updateScrubber(); changed(false); }
}

async function start() {
  $("title").textContent = sessionId;
  document.title = `CanonicalGS Fusion · ${sessionId.slice(0, 8)}`;
  focusView();
  const [info, track] = await withToken(() => Promise.all([json("/v1/viewer/info"), json(`${base}/cameras`)]));
  fitSize(info.max_picture_pixels);
  if (badParams.length) { $("warning").textContent = badParams.join(" · "); $("warning").hidden = false; }
  state.info = info;
  drawScaleBar();
  showTrack(track);
  focusView();  // again: the token form, where it was asked for, had the keyboard
  subscribe(`${base}/events?every=${EVENT_EVERY_S}`, onEvent, (s) => { $("live").textContent = s; });
  refreshStats();
  setInterval(showText, 5000);  // the last fold's age
}

start().catch(showError);
