// pma view: the page. Everything comes from this server; nothing is fetched elsewhere.
//
// Frames are progressive: a small preview sized so that it takes about PREVIEW_MS (from the
// last full frame's time), then the full size once the view has not changed. At most one
// request is in flight; a change while the full frame renders aborts it (the server stops
// that frame at its next chunk because a newer request arrived).
'use strict';

const PREVIEW_MS = 150;
const RUN_POLL_MS = 2000;

const $ = (id) => document.getElementById(id);

// window.pmaView is what tests and curious users can read.
const V = (window.pmaView = {
  info: null,
  previews: 0,
  fullFrames: 0,
  lastStats: null,
  lastFullStats: null,
  timing: { firstPreviewMs: null, firstFullMs: null },
  // The first frames drawn: stage, size, server ms, page time (ms since navigation).
  history: [],
  run: null,
  errors: [],
  // True once the full frame of the current view is on the page and nothing is in flight.
  settled: () => current === null && fullSeq === seq,
});

const S = {
  pose: 0,
  cam: -1, // dataset camera index, or -1 for a free camera
  eye: [0, 0, 3],
  target: [0, 0, 0],
  fov: 30,
  w: 256,
  h: 256,
  switches: {},
  playing: false,
  fps: 10,
};

let seq = 0; // bumped by every view change
let fullSeq = -1; // the view whose full frame is shown
let current = null; // the request in flight: {stage, ctrl}
let lastFullMs = null;
let lastCheckpoint = null;

// ---------------------------------------------------------------- small vector helpers
const sub = (a, b) => a.map((v, i) => v - b[i]);
const add = (a, b) => a.map((v, i) => v + b[i]);
const mul = (a, s) => a.map((v) => v * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => mul(a, 1 / (norm(a) || 1));
// Rotate v about the unit axis k by angle t (Rodrigues).
function rotate(v, k, t) {
  const c = Math.cos(t), s = Math.sin(t);
  return add(add(mul(v, c), mul(cross(k, v), s)), mul(k, dot(k, v) * (1 - c)));
}

// ---------------------------------------------------------------- status and stats
function status(text, bad) {
  const el = $('status');
  el.textContent = text;
  el.classList.toggle('error', !!bad);
  if (bad) V.errors.push(text);
}

const fmt = (n) => (n >= 1e6 ? (n / 1e6).toFixed(2) + ' M' : n >= 1e4 ? (n / 1e3).toFixed(1) + ' k' : String(Math.round(n)));

function showStats(st, stage) {
  $('st-size').textContent = `${st.width}×${st.height} (${stage})`;
  $('st-ms').textContent = st.ms.toFixed(0);
  $('st-rays').textContent = fmt(st.rays);
  $('st-rps').textContent = fmt(st.rays_per_s);
  $('st-samples').textContent = fmt(st.samples);
  const t = V.timing;
  $('st-first').textContent =
    (t.firstPreviewMs === null ? '–' : (t.firstPreviewMs / 1000).toFixed(2) + ' s') +
    ' / ' + (t.firstFullMs === null ? '–' : (t.firstFullMs / 1000).toFixed(2) + ' s');
  if (st.reload_error) status('newest checkpoint not loaded: ' + st.reload_error, true);
}

function showGroundTruth(st) {
  const fig = $('gt-fig');
  if (st.image === null || st.image === undefined) {
    fig.hidden = true;
    return;
  }
  const src = `/api/gt?image=${st.image}`;
  if ($('gt').getAttribute('src') !== src) $('gt').src = src;
  fig.hidden = false;
  const s = st.scores || {};
  const f = (v, d) => (v === null || v === undefined ? 'n/a' : v.toFixed(d));
  $('scores').textContent = `image ${st.image} · PSNR ${f(s.psnr, 2)} dB · SSIM ${f(s.ssim, 3)} · LPIPS ${f(s.lpips, 3)}`;
}

// ---------------------------------------------------------------- rendering
function previewFactor() {
  if (lastFullMs === null) return 4;
  return Math.min(16, Math.max(1, Math.ceil(Math.sqrt(lastFullMs / PREVIEW_MS))));
}

function frameQuery(k) {
  const w = Math.max(1, Math.round(S.w / k));
  const h = Math.max(1, Math.round(S.h / k));
  const p = new URLSearchParams({ pose: S.pose, w, h });
  if (S.cam >= 0) {
    p.set('cam', S.cam);
    if (k === 1) p.set('score', 1);
  } else {
    p.set('eye', S.eye.map((v) => v.toFixed(5)).join(','));
    p.set('target', S.target.map((v) => v.toFixed(5)).join(','));
    p.set('fov', S.fov.toFixed(3));
  }
  for (const [id, on] of Object.entries(S.switches)) p.set(id, on ? 1 : 0);
  return p.toString();
}

// A frame, or null when it was superseded, aborted or refused.
async function fetchFrame(k, signal) {
  let res;
  try {
    res = await fetch('/api/render?' + frameQuery(k), { signal, cache: 'no-store' });
  } catch (e) {
    if (e.name !== 'AbortError') status('server unreachable: ' + e.message, true);
    return null;
  }
  if (res.status === 409) return null;
  if (!res.ok) {
    let msg = res.statusText;
    try { msg = (await res.json()).error; } catch (e) { /* keep the status text */ }
    status(`render refused (${res.status}): ${msg}`, true);
    return null;
  }
  const stats = JSON.parse(res.headers.get('x-pma-stats') || '{}');
  const bitmap = await createImageBitmap(await res.blob());
  return { stats, bitmap };
}

function draw(frame, stage) {
  const c = $('render');
  if (c.width !== S.w || c.height !== S.h) {
    c.width = S.w;
    c.height = S.h;
  }
  const g = c.getContext('2d');
  g.imageSmoothingEnabled = true;
  g.drawImage(frame.bitmap, 0, 0, c.width, c.height);
  V.lastStats = frame.stats;
  const now = performance.now();
  if (V.history.length < 100) {
    V.history.push({ stage, width: frame.stats.width, height: frame.stats.height, ms: frame.stats.ms, at: now });
  }
  if (stage === 'preview') {
    V.previews++;
    if (V.timing.firstPreviewMs === null) V.timing.firstPreviewMs = now;
  } else {
    V.fullFrames++;
    V.lastFullStats = frame.stats;
    lastFullMs = frame.stats.ms;
    if (V.timing.firstFullMs === null) V.timing.firstFullMs = now;
    if (V.timing.firstPreviewMs === null) V.timing.firstPreviewMs = now;
  }
  $('stage').textContent = stage === 'preview' ? '(preview)' : '';
  showStats(frame.stats, stage);
  if (stage === 'full') showGroundTruth(frame.stats);
  else $('gt-fig').hidden = true;
  if (!$('status').classList.contains('error')) status('ready');
}

// The view changed: render it.
function request() {
  seq++;
  if (current && current.stage === 'full') {
    current.ctrl.abort();
    current = null;
  }
  if (!current) runStage(previewFactor() > 1 ? 'preview' : 'full');
}

async function runStage(stage) {
  const mine = seq;
  const ctrl = new AbortController();
  const me = { stage, ctrl };
  current = me;
  const frame = await fetchFrame(stage === 'preview' ? previewFactor() : 1, ctrl.signal);
  if (current !== me) return; // aborted for a newer view, which is already on its way
  current = null;
  // A preview of a view that just changed still shows where the drag is going.
  if (frame && (stage === 'preview' || mine === seq)) {
    draw(frame, stage);
    if (stage === 'full') fullSeq = mine;
  }
  if (mine !== seq) runStage(previewFactor() > 1 ? 'preview' : 'full');
  else if (stage === 'preview' && !S.playing) runStage('full');
}

// ---------------------------------------------------------------- pose and playback
function poseLabel() {
  const i = V.info;
  const kind = { dataset: 'dataset pose', motion: 'motion frame', rest: 'rest pose' }[i.pose_kind];
  $('pose-label').textContent = i.pose_kind === 'rest' ? kind : `${kind} ${S.pose} / ${i.poses - 1}`;
}

function setPose(p) {
  S.pose = Math.max(0, Math.min(V.info.poses - 1, p));
  $('pose').value = S.pose;
  poseLabel();
  request();
}

let playTimer = null;
let played = { t: 0, n: 0 };
function setPlaying(on) {
  S.playing = on && V.info.poses > 1;
  $('play').textContent = S.playing ? 'Pause' : 'Play';
  clearInterval(playTimer);
  playTimer = null;
  $('play-rate').textContent = '';
  if (S.playing) {
    played = { t: performance.now(), n: 0 };
    playTimer = setInterval(() => {
      // Drop the tick while a preview is still on its way: the motion keeps its pace.
      if (current && current.stage === 'preview') return;
      setPose((S.pose + 1) % V.info.poses);
      played.n++;
      const s = (performance.now() - played.t) / 1000;
      if (s > 1) $('play-rate').textContent = `${(played.n / s).toFixed(1)} fps shown`;
    }, 1000 / S.fps);
  } else {
    request();
  }
}

// ---------------------------------------------------------------- camera
function setCamera(c) {
  const info = V.info;
  const vc = c >= 0 ? info.cameras[c] : info.start;
  S.cam = c;
  S.eye = vc.eye.slice();
  S.target = vc.target.slice();
  S.fov = vc.fov_deg;
  $('camera').value = String(c);
  request();
}

function toFree() {
  if (S.cam >= 0) {
    S.cam = -1;
    $('camera').value = '-1';
  }
}

function orbit(dx, dy) {
  const up = V.info.head; // the image's up is the head direction
  let off = sub(S.eye, S.target);
  off = rotate(off, unit(up), -dx * 0.01);
  const right = unit(cross(up, off));
  const turned = rotate(off, right, dy * 0.01);
  // Stay away from the poles: the view must not look along the up axis.
  const cosUp = dot(unit(turned), unit(up));
  if (Math.abs(cosUp) < 0.98) off = turned;
  S.eye = add(S.target, off);
}

function pan(dx, dy) {
  const up = V.info.head;
  const off = sub(S.eye, S.target);
  const dist = norm(off);
  const fwd = unit(mul(off, -1));
  const right = unit(cross(fwd, up));
  const camUp = cross(right, fwd);
  const k = (2 * dist * Math.tan((S.fov * Math.PI) / 360)) / $('render').clientHeight;
  const move = add(mul(right, -dx * k), mul(camUp, dy * k));
  S.eye = add(S.eye, move);
  S.target = add(S.target, move);
}

function zoom(delta) {
  const off = sub(S.eye, S.target);
  const d = Math.min(100, Math.max(0.2, norm(off) * Math.exp(delta * 0.001)));
  S.eye = add(S.target, mul(unit(off), d));
}

function wireMouse() {
  const c = $('render');
  let drag = null;
  c.addEventListener('contextmenu', (e) => e.preventDefault());
  c.addEventListener('pointerdown', (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
    c.setPointerCapture(e.pointerId);
  });
  c.addEventListener('pointermove', (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (dx === 0 && dy === 0) return;
    drag.x = e.clientX;
    drag.y = e.clientY;
    toFree();
    if (drag.pan) pan(dx, dy);
    else orbit(dx, dy);
    request();
  });
  const end = () => { drag = null; };
  c.addEventListener('pointerup', end);
  c.addEventListener('pointercancel', end);
  c.addEventListener('wheel', (e) => {
    e.preventDefault();
    toFree();
    zoom(e.deltaY);
    request();
  }, { passive: false });
}

// ---------------------------------------------------------------- sizes and switches
function fillSizes() {
  const info = V.info, base = [info.start.width, info.start.height];
  const sel = $('size');
  for (const k of [0.5, 1, 2, 4]) {
    const w = Math.round(base[0] * k), h = Math.round(base[1] * k);
    if (w < 8 || h < 8 || w > info.max_side || h > info.max_side) continue;
    const o = document.createElement('option');
    o.value = `${w}x${h}`;
    o.textContent = `${w}×${h}` + (k === 1 ? (info.cameras.length ? ' (dataset)' : '') : '');
    if (k === 1) o.selected = true;
    sel.append(o);
  }
  sel.addEventListener('change', () => {
    const [w, h] = sel.value.split('x').map(Number);
    // Time grows with the pixels: the next preview is sized from the last frame's time.
    if (lastFullMs !== null) lastFullMs *= (w * h) / (S.w * S.h);
    [S.w, S.h] = [w, h];
    request();
  });
  [S.w, S.h] = base;
}

function fillSwitches() {
  const box = $('switches');
  for (const sw of V.info.switches) {
    S.switches[sw.id] = sw.on;
    const label = document.createElement('label');
    label.className = 'switch';
    const input = document.createElement('input');
    input.type = 'checkbox';
    input.id = 'switch-' + sw.id;
    input.checked = sw.on;
    input.addEventListener('change', () => {
      S.switches[sw.id] = input.checked;
      lastFullMs = null;
      request();
    });
    const help = document.createElement('small');
    help.textContent = sw.help;
    label.append(input, ' ' + sw.label, help);
    box.append(label);
  }
}

// ---------------------------------------------------------------- training run
function plot(canvas, pts, title, logY) {
  const g = canvas.getContext('2d');
  const W = canvas.width, H = canvas.height, L = 48, R = 10, T = 22, B = 24;
  g.clearRect(0, 0, W, H);
  g.fillStyle = '#9aa0ab';
  g.font = '12px system-ui, sans-serif';
  g.fillText(title, L, 14);
  if (pts.length === 0) {
    g.fillText('no data yet', L, H / 2);
    return;
  }
  const ty = (v) => (logY ? Math.log10(Math.max(v, 1e-12)) : v);
  const xs = pts.map((p) => p[0]), ys = pts.map((p) => ty(p[1]));
  let x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  if (x1 === x0) x1 = x0 + 1;
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  const px = (x) => L + ((x - x0) / (x1 - x0)) * (W - L - R);
  const py = (y) => H - B - ((y - y0) / (y1 - y0)) * (H - T - B);
  g.strokeStyle = '#444';
  g.strokeRect(L, T, W - L - R, H - T - B);
  const lab = (y) => (logY ? Number(Math.pow(10, y).toPrecision(2)).toString() : y.toFixed(1));
  g.fillText(lab(y1), 2, T + 8);
  g.fillText(lab(y0), 2, H - B);
  g.fillText(String(x0), L, H - 6);
  const xl = 'iteration ' + x1;
  g.fillText(xl, W - R - g.measureText(xl).width, H - 6);
  g.strokeStyle = '#6cb6ff';
  g.lineWidth = 1.5;
  g.beginPath();
  pts.forEach((p, i) => {
    const X = px(p[0]), Y = py(ty(p[1]));
    if (i === 0) g.moveTo(X, Y); else g.lineTo(X, Y);
  });
  g.stroke();
  if (pts.length < 40) {
    g.fillStyle = '#6cb6ff';
    for (const p of pts) g.fillRect(px(p[0]) - 2, py(ty(p[1])) - 2, 4, 4);
  }
}

async function pollRun() {
  try {
    const res = await fetch('/api/run', { cache: 'no-store' });
    if (res.ok) {
      const run = await res.json();
      V.run = run;
      const ck = run.checkpoint ? `${run.checkpoint.modified_ms}/${run.checkpoint.bytes}` : null;
      if (lastCheckpoint !== null && ck !== null && ck !== lastCheckpoint) request();
      if (ck !== null) lastCheckpoint = ck;
      if (V.info.run) {
        plot($('loss-plot'), run.loss, 'training loss (log scale)', true);
        plot($('psnr-plot'), run.eval_psnr, 'held-out PSNR (dB)', false);
        const when = run.checkpoint ? new Date(run.checkpoint.modified_ms).toLocaleTimeString() : 'none yet';
        const it = run.last_iter === null ? 'no log rows yet' : `iteration ${run.last_iter}`;
        const wall = run.wall_s === null ? '' : ` · ${(run.wall_s / 60).toFixed(1)} min of training`;
        const ver = V.lastStats ? ` (model v${V.lastStats.model_version} shown)` : '';
        $('run-status').textContent = `${it}${wall} · newest checkpoint ${when}${ver}` +
          (run.log_error ? ' · ' + run.log_error : '');
      }
    }
  } catch (e) {
    status('server unreachable: ' + e.message, true);
  }
  setTimeout(pollRun, RUN_POLL_MS);
}

// ---------------------------------------------------------------- start
async function main() {
  const res = await fetch('/api/info', { cache: 'no-store' });
  const info = (V.info = await res.json());
  $('model').textContent = `${info.model}${info.run ? ' (run directory)' : ''} · ${info.device}`;
  document.title = `pma view · ${info.model}`;
  const slider = $('pose');
  slider.max = String(info.poses - 1);
  slider.disabled = info.poses < 2;
  slider.addEventListener('input', () => setPose(Number(slider.value)));
  $('play').disabled = info.poses < 2;
  $('play').addEventListener('click', () => setPlaying(!S.playing));
  $('fps').addEventListener('change', () => {
    S.fps = Math.max(1, Math.min(60, Number($('fps').value) || 10));
    if (S.playing) setPlaying(true);
  });
  const camSel = $('camera');
  const free = document.createElement('option');
  free.value = '-1';
  free.textContent = 'free camera';
  camSel.append(free);
  info.cameras.forEach((_, c) => {
    const o = document.createElement('option');
    o.value = String(c);
    o.textContent = `dataset camera ${c}`;
    camSel.append(o);
  });
  camSel.addEventListener('change', () => setCamera(Number(camSel.value)));
  $('reset').addEventListener('click', () => setCamera(S.cam >= 0 ? S.cam : info.cameras.length ? 0 : -1));
  $('run').hidden = !info.run;
  fillSizes();
  fillSwitches();
  wireMouse();
  poseLabel();
  setCamera(info.cameras.length ? 0 : -1);
  pollRun();
}

main().catch((e) => status('cannot start: ' + e.message, true));
