// The page of horizon-bake (GET /): upload, parameters, progress, the list of bakes, downloads,
// and the WebGL2 viewer (viewer.js). Plain ES modules, no bundler, no dependency.
//
// The HTTP client (API key, problem+json, the event stream read with fetch) is api.js, the
// height-map header probe and the PNG height range are probe.js; this module is the page
// itself. `window.__horizon` is a small hook for the browser test and for automation (read the
// canvas, set the light).

import { Viewer, decodeImage, fromAngles, DEFAULTS } from './viewer.js';
import { api, apiJson, blobUrl, readEvents, fetchResult, getApiKey, setApiKey } from './api.js';
import { probe, sniffType, pngRange } from './probe.js';

// ---------------------------------------------------------------------------------------------
// The page

const $ = (id) => document.getElementById(id);

function readConfig() {
  const fallback = { version: '?', auth_required: false, max_body_bytes: 0, max_dim: 0, max_texels: 0 };
  try {
    return { ...fallback, ...JSON.parse($('config').textContent) };
  } catch {
    return fallback; // the file opened without the server's substitution
  }
}

const config = readConfig();

const DEFAULT_PARAMS = {
  method: 'lengyel',
  radius: '16',
  min_elevation_deg: '5',
  bins: '32',
  reduce: 'average',
  height_scale: '8',
  channel: 'luma',
  edge: 'wrap',
  y_axis: 'up',
  encoding: 'linear',
  outputs: 'horizon',
  fourier_terms: '5',
  fourier_range: 'standard',
};
const FIELDS = Object.keys(DEFAULT_PARAMS);
/**
 * A DEM's defaults (SPEC §2): a line of sight to the map's edge, which the server resolves
 * (`sweep`, or `exact` where `sweep` cannot run); the form shows them and sends neither.
 */
const DEM_PARAMS = { ...DEFAULT_PARAMS, method: 'sweep', radius: 'unlimited' };

/** The defaults of what the form holds: a DEM's when the DEM box is ticked. */
function defaultsNow() {
  return $('p-dem').checked ? DEM_PARAMS : DEFAULT_PARAMS;
}

const UNIT_SYMBOLS = { metre: 'm', foot: 'ft', us_survey_foot: 'US ft' };

/** A number as a person writes it: 0.005, not 0.004999999999999976; 200, not 200.00000000000097. */
function fmtNum(x) {
  const n = Number(x);
  return Number.isFinite(n) ? String(Number(n.toPrecision(10))) : String(x);
}

/** A cell size with its unit's symbol: "30 m". */
function fmtCell(g) {
  return `${fmtNum(g.cell_size)} ${UNIT_SYMBOLS[g.units] || g.units || 'map units'}`;
}
const TERMINAL = new Set(['succeeded', 'failed', 'canceled']);
const CUBE_SIZE = DEFAULTS.cubeSize;

const state = {
  file: null,
  fileInfo: null,     // the dropped file's header (imageinfo)
  bake: null,          // the bake resource shown
  watch: null,         // AbortController of the event stream
  viewer: null,
  viewerError: '',
  loadToken: 0,
  loadedId: null,      // id whose textures the viewer holds
  cube: null,          // decoded cube faces (shared by every bake)
  light: { azimuth: DEFAULTS.azimuth, elevation: DEFAULTS.elevation, hardness: DEFAULTS.hardness },
  progressLog: [],
  previewTimer: 0,
  previewAbort: null,
  previewUrl: '',
  previewFor: '',
  retryTimer: 0,
  range: null,         // {min, max} of the chosen PNG's normalised heights
  terrainFor: '',      // id whose SVF the terrain panel shows
  surfaceFor: '',      // id whose maps the surface panel shows
  size: undefined,     // render size (longer side) in `display` resolution, else native
};

// --- formatting ---------------------------------------------------------------------------

function fmtBytes(n) {
  if (!Number.isFinite(n) || n <= 0) return '—';
  const u = ['B', 'KiB', 'MiB', 'GiB'];
  let i = 0;
  while (n >= 1024 && i < u.length - 1) {
    n /= 1024;
    i++;
  }
  return `${n.toFixed(i ? 1 : 0)} ${u[i]}`;
}

const fmtDeg = (v) => `${Number(v.toFixed(2))}°`;

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === 'class') e.className = v;
    else if (k === 'text') e.textContent = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children) e.append(c);
  return e;
}

// --- errors -------------------------------------------------------------------------------

function clearErrors() {
  $('error').hidden = true;
  $('error').textContent = '';
  for (const f of [...FIELDS]) {
    const e = $(`err-${f}`);
    if (e) e.textContent = '';
  }
  for (const i of document.querySelectorAll('#params [aria-invalid]')) i.removeAttribute('aria-invalid');
}

/** Shows an API error: code and detail in the alert, and next to the field it names. */
function showError(err, context) {
  const box = $('error');
  box.textContent = '';
  const code = err.code || 'error';
  const msg = err.detail || err.message || String(err);
  box.append(el('strong', { text: context ? `${context}: ` : '' }), el('code', { class: 'code', text: code }),
    ' — ', el('span', { class: 'detail', text: msg }));
  if (err.status === 401) {
    box.append(el('br'), 'Enter the server\'s API key at the top right.');
  }
  if (err.retryAfter !== null && err.retryAfter !== undefined && err.status === 429) {
    box.append(el('br'), el('span', { class: 'retry', text: `Retry-After: ${err.retryAfter} s` }));
  }
  box.hidden = false;
  if (err.field) {
    const slot = $(`err-${err.field}`);
    if (slot) {
      slot.textContent = msg;
      const input = err.field === 'outputs' ? $('p-out-horizon')
        : err.field === 'radius' ? ($('p-radius-mode').value === 'texels' ? $('p-radius') : $('p-radius-mode'))
          : $(`p-${err.field}`);
      if (input) {
        input.setAttribute('aria-invalid', 'true');
        input.focus({ preventScroll: true });
      }
    }
  }
}

// --- API key --------------------------------------------------------------------------------

function showKeyState() {
  const has = !!getApiKey();
  $('api-key').placeholder = config.auth_required ? 'required by this server' : 'not needed';
  $('key-state').textContent = has ? 'key saved' : config.auth_required ? 'needs a key' : '';
}

$('api-key').value = getApiKey();
$('key-form').addEventListener('submit', (ev) => {
  ev.preventDefault();
  setApiKey($('api-key').value.trim());
  showKeyState();
  clearErrors();
  refreshRecent();
  route();
});

// --- parameters ---------------------------------------------------------------------------

function syncForm() {
  const mode = $('p-radius-mode').value;
  $('p-radius').disabled = mode !== 'texels';
  $('p-min_elevation_deg').disabled = mode !== 'auto';
  $('p-reduce').disabled = $('p-method').value === 'lengyel';
  const fourier = $('p-out-fourier').checked;
  $('p-fourier_terms').disabled = !fourier;
  $('p-fourier_range').disabled = !fourier;
  // A DEM's defaults come from the file (SPEC §2): the page sends no height_scale or edge, so
  // the server resolves them (cell size, 1/cell size, none).
  const dem = $('p-dem').checked;
  $('p-height_scale').disabled = dem;
  $('p-edge').disabled = dem;
}

/** Shows the DEM row of the form, ticked, for a TIFF (a DEM until the server says otherwise). */
function showDemRow(show, checked) {
  for (const e of document.querySelectorAll('.dem-row')) e.hidden = !show;
  const was = $('p-dem').checked;
  $('p-dem').checked = show && checked;
  if ($('p-dem').checked !== was) showKindDefaults(was);
  syncForm();
}

/**
 * The method, radius and terrain outputs of the kind of input the form now holds (a DEM or a
 * plain image), where they still show the other kind's defaults (a choice the user made stays).
 */
function showKindDefaults(wasDem) {
  const [from, to] = wasDem ? [DEM_PARAMS, DEFAULT_PARAMS] : [DEFAULT_PARAMS, DEM_PARAMS];
  const sel = $('p-method');
  if (sel.value === from.method && [...sel.options].some((o) => o.value === to.method)) {
    sel.value = to.method;
  }
  const mode = $('p-radius-mode');
  const radius = mode.value === 'texels' ? $('p-radius').value.trim() : mode.value;
  if (radius === from.radius) {
    if (to.radius === 'unlimited' || to.radius === 'auto') {
      mode.value = to.radius;
    } else {
      mode.value = 'texels';
      $('p-radius').value = to.radius;
    }
  }
  // A DEM is baked for its terrain products (angles, svf) by default in the form.
  $('p-out-terrain').checked = !wasDem;
}

/** The form's parameters as strings, only the enabled fields. */
function formParams() {
  const p = {};
  for (const f of FIELDS) {
    const input = $(`p-${f}`);
    if (f === 'radius') {
      const mode = $('p-radius-mode').value;
      p.radius = mode === 'texels' ? $('p-radius').value.trim() : mode;
    } else if (f === 'outputs') {
      p.outputs = [['horizon', 'p-out-horizon'], ['fourier', 'p-out-fourier'], ['angles,svf', 'p-out-terrain'],
        ['normal,ao,bent_normal', 'p-out-surface']]
        .filter(([, id]) => $(id).checked).map(([n]) => n).join(',');
    } else if (input && !input.disabled) {
      p[f] = String(input.value).trim();
    }
  }
  return p;
}

/** The query string of the non-default parameters. */
function paramQuery(p) {
  const q = new URLSearchParams();
  const d = defaultsNow();
  for (const f of FIELDS) {
    if (p[f] !== undefined && p[f] !== d[f]) q.set(f, p[f]);
  }
  const s = q.toString();
  return s ? `?${s}` : '';
}

function resetForm() {
  $('p-dem').checked = !$('dem-l').hidden;
  const d = defaultsNow();
  $('p-method').value = d.method;
  $('p-radius-mode').value = d.radius === 'unlimited' ? 'unlimited' : 'texels';
  $('p-radius').value = DEFAULT_PARAMS.radius;
  for (const f of ['min_elevation_deg', 'bins', 'reduce', 'height_scale', 'channel', 'edge', 'y_axis',
    'encoding', 'fourier_terms', 'fourier_range']) {
    $(`p-${f}`).value = DEFAULT_PARAMS[f];
  }
  $('p-out-horizon').checked = true;
  $('p-out-fourier').checked = false;
  $('p-out-terrain').checked = $('p-dem').checked;
  $('p-out-surface').checked = false;
  syncForm();
  clearErrors();
}

/** Puts a bake's resolved parameters into the form, so Bake re-runs what is shown. */
function loadForm(p) {
  if (!p || !p.method) return;
  const sel = $('p-method');
  if (![...sel.options].some((o) => o.value === p.method)) {
    sel.append(el('option', { value: p.method, text: METHOD_LABELS[p.method] || p.method }));
  }
  sel.value = p.method;
  const r = String(p.radius ?? DEFAULT_PARAMS.radius);
  if (r === 'auto' || r === 'unlimited') {
    $('p-radius-mode').value = r;
  } else {
    $('p-radius-mode').value = 'texels';
    $('p-radius').value = r;
  }
  for (const f of ['min_elevation_deg', 'bins', 'reduce', 'height_scale', 'channel', 'edge', 'y_axis',
    'encoding', 'fourier_terms', 'fourier_range']) {
    const input = $(`p-${f}`);
    if (input && p[f] !== undefined && p[f] !== null) input.value = String(p[f]);
  }
  const outs = outputsOf(p);
  $('p-out-horizon').checked = outs.includes('horizon');
  $('p-out-fourier').checked = outs.includes('fourier');
  $('p-out-terrain').checked = outs.includes('angles') || outs.includes('svf');
  $('p-out-surface').checked = SURFACE_MAPS.some((m) => outs.includes(m));
  syncForm();
  clearErrors();
  showRelief();
}

for (const id of ['p-radius-mode', 'p-method', 'p-out-fourier', 'p-out-horizon', 'p-dem']) {
  $(id).addEventListener('change', syncForm);
}
// Ticking or unticking "DEM" by hand shows that kind's defaults too.
$('p-dem').addEventListener('change', () => {
  showKindDefaults(!$('p-dem').checked);
  syncForm();
});
$('reset').addEventListener('click', resetForm);

// The kernels this server offers, when its configuration lists them (else the form's own).
const METHOD_LABELS = {
  lengyel: 'lengyel (Max/Lengyel splat)',
  exact: 'exact (line of sight)',
  march: 'march (fast, finite radius)',
  sweep: 'sweep (fast, any radius)',
};
if (Array.isArray(config.methods) && config.methods.length) {
  const sel = $('p-method');
  sel.textContent = '';
  for (const m of config.methods) sel.append(el('option', { value: m, text: METHOD_LABELS[m] || m }));
  sel.value = config.methods.includes(DEFAULT_PARAMS.method) ? DEFAULT_PARAMS.method : config.methods[0];
}
syncForm();

// --- the file -----------------------------------------------------------------------------

function showLimits() {
  const parts = [];
  if (config.max_dim) parts.push(`each side ≤ ${config.max_dim} texels`);
  if (config.max_texels) parts.push(`≤ ${config.max_texels.toLocaleString('en')} texels`);
  if (config.max_body_bytes) parts.push(`≤ ${fmtBytes(config.max_body_bytes)} per upload`);
  $('limits').textContent = parts.length ? `Server limits: ${parts.join(', ')}.` : '';
}

/** The map's relief in texels at the form's height scale, with a warning when it is useless. */
function showRelief() {
  const out = $('relief');
  const r = state.range;
  const info = state.fileInfo;
  if (!r || !info) {
    out.textContent = state.file && info && info.format !== 'png'
      ? 'Relief: shown for PNG maps before the bake (this one is measured by the bake).' : '';
    out.className = 'muted';
    delete out.dataset.texels;
    return;
  }
  const scale = Number($('p-height_scale').value);
  const span = r.max - r.min;
  const texels = span * (Number.isFinite(scale) ? scale : 0);
  const size = Math.max(info.width, info.height);
  out.dataset.texels = String(texels);
  let text = `Relief: ${texels.toPrecision(3)} texels (heights ${r.min.toFixed(4)}–${r.max.toFixed(4)} × height scale ${scale}).`;
  out.className = 'muted';
  if (texels < 1) {
    const want = span > 0 ? Math.ceil(16 / span) : null;
    text += ` Below 1 texel the bake is flat: nothing casts a shadow.${want ? ` A height scale of about ${want} gives 16 texels.` : ''}`;
    out.className = 'warn';
  } else if (texels > size) {
    text += ` That is more than the map's size (${size} texels): the relief is a field of cliffs; lower the height scale.`;
    out.className = 'warn';
  }
  out.textContent = text;
}

async function measureRelief() {
  state.range = null;
  const file = state.file;
  if (file && state.fileInfo && state.fileInfo.format === 'png') {
    try {
      const channel = $('p-channel').value;
      const range = await pngRange(await file.arrayBuffer(), channel);
      if (file === state.file) state.range = range;
    } catch {
      state.range = null;
    }
  }
  showRelief();
}

$('p-height_scale').addEventListener('input', showRelief);
$('p-channel').addEventListener('change', measureRelief);

/**
 * A TIFF (by its magic number or its name) may be a GeoTIFF DEM: the form then sends no
 * height_scale or edge, and the server resolves the DEM defaults (SPEC §2); the CRS and cell
 * size shown are the server's, once the bake resource answers.
 */
function showFileDem(file, h) {
  const tiffFile = (h && h.format === 'tiff') || (!h && /\.tiff?$/i.test(file.name));
  showDemRow(tiffFile, tiffFile);
  const out = $('dem-info');
  out.hidden = !tiffFile;
  delete out.dataset.epsg;
  delete out.dataset.cellSize;
  if (!tiffFile) return;
  out.textContent = h && h.geoKeys
    ? `DEM: defaults from the file (GeoTIFF${h.pixelScale ? `, ${h.pixelScale} map units per cell` : ''}); the CRS and cell size show once the server has it.`
    : 'DEM: defaults from the file, if it is a GeoTIFF (the server decides).';
}

async function chooseFile(file) {
  state.file = file;
  state.range = null;
  const info = $('file-info');
  info.className = 'muted';
  info.textContent = `${file.name} — ${fmtBytes(file.size)}…`;
  try {
    // The header is read in slices: a TIFF's directory may be anywhere in a large file.
    const h = await probe((off, len) => file.slice(off, off + len).arrayBuffer());
    state.fileInfo = h;
    const depth = h.bitDepth ? `${h.bitDepth}-bit${h.float ? ' float' : ''}` : '';
    const over = [];
    if (config.max_dim && (h.width > config.max_dim || h.height > config.max_dim)) {
      over.push(`a side exceeds ${config.max_dim}`);
    }
    if (config.max_texels && h.width * h.height > config.max_texels) {
      over.push(`more than ${config.max_texels} texels`);
    }
    if (config.max_body_bytes && file.size > config.max_body_bytes) {
      over.push(`larger than ${fmtBytes(config.max_body_bytes)}`);
    }
    info.textContent = `${file.name}: ${h.width} × ${h.height}, ${h.format.toUpperCase()} ${h.color} ${depth}, ${fmtBytes(file.size)}`;
    info.dataset.width = h.width;
    info.dataset.height = h.height;
    showFileDem(file, h);
    if (over.length) {
      info.className = 'err';
      info.textContent += ` — over the server's limits (${over.join('; ')}): it will be refused.`;
    }
  } catch (e) {
    state.fileInfo = null;
    showFileDem(file, null);
    info.className = 'err';
    info.textContent = `${file.name} (${fmtBytes(file.size)}): ${e.message}; the server will refuse it.`;
  }
  await measureRelief();
}

const drop = $('drop');
drop.addEventListener('dragover', (ev) => {
  ev.preventDefault();
  drop.classList.add('over');
});
drop.addEventListener('dragleave', () => drop.classList.remove('over'));
drop.addEventListener('drop', (ev) => {
  ev.preventDefault();
  drop.classList.remove('over');
  const f = ev.dataTransfer && ev.dataTransfer.files[0];
  if (f) chooseFile(f);
});
drop.addEventListener('keydown', (ev) => {
  if (ev.key === 'Enter' || ev.key === ' ') {
    ev.preventDefault();
    $('file').click();
  }
});
$('file').addEventListener('change', () => {
  const f = $('file').files[0];
  if (f) chooseFile(f);
});

// --- submit, progress, cancel --------------------------------------------------------------

async function submit(ev) {
  ev.preventDefault();
  clearErrors();
  if (!state.file) {
    showError({ code: 'no_file', detail: 'choose a height map first' });
    return;
  }
  const head = new Uint8Array(await state.file.slice(0, 16).arrayBuffer());
  const type = sniffType(head) || 'application/octet-stream';
  const url = `/v1/bakes${paramQuery(formParams())}`;
  $('bake').disabled = true;
  $('status').textContent = 'Uploading…';
  try {
    const { status, body } = await apiJson(url, { method: 'POST', body: state.file, headers: { 'Content-Type': type } });
    $('status').textContent = status === 200 ? 'Identical bake found: showing it.' : 'Accepted.';
    state.progressLog.push({ fraction: body.progress.fraction, stage: body.progress.stage, status: body.status });
    openResource(body);
    refreshRecent();
  } catch (e) {
    $('status').textContent = '';
    showError(e, 'upload');
    if (e.status === 429) retryCountdown(e.retryAfter || 1);
  } finally {
    if (!state.retryTimer) $('bake').disabled = false;
  }
}

function retryCountdown(secs) {
  clearInterval(state.retryTimer);
  let left = Math.max(1, Math.ceil(secs));
  const btn = $('bake');
  btn.disabled = true;
  const tick = () => {
    if (left <= 0) {
      clearInterval(state.retryTimer);
      state.retryTimer = 0;
      btn.disabled = false;
      btn.textContent = 'Bake';
      return;
    }
    btn.textContent = `Retry in ${left} s`;
    $('status').textContent = `Queue full: retry after ${left} s.`;
    left--;
  };
  tick();
  state.retryTimer = setInterval(tick, 1000);
}

$('params').addEventListener('submit', submit);

/** Shows `status` for bake `id` in the recent list (running, canceled, …) as it changes. */
function markRecent(id, status) {
  for (const li of document.querySelectorAll('#recent li')) {
    if (li.dataset.id !== id) continue;
    const st = li.querySelector('.st');
    if (st && st.textContent !== status) {
      st.textContent = status;
      st.className = `st ${status}`;
    }
  }
}

function showProgress(fraction, stage, status) {
  const f = Math.max(0, Math.min(1, Number(fraction) || 0));
  $('progress').value = f;
  $('progress').dataset.stage = stage;
  $('progress-text').textContent = `${(f * 100).toFixed(1)}% ${stage}`;
  $('status').textContent = status;
  $('cancel').disabled = TERMINAL.has(status);
  state.progressLog.push({ fraction: f, stage, status });
}

/** Follows a bake's event stream until it ends, reconnecting when the stream breaks. */
async function watch(id) {
  if (state.watch) state.watch.abort();
  const ctrl = new AbortController();
  state.watch = ctrl;
  let finished = false;
  for (let attempt = 0; !finished && !ctrl.signal.aborted; attempt++) {
    try {
      await readEvents(`/v1/bakes/${encodeURIComponent(id)}/events`, (name, data) => {
        if (ctrl.signal.aborted) return;
        if (name === 'progress') {
          showProgress(data.progress.fraction, data.progress.stage, data.status);
          markRecent(id, data.status);
        } else if (name === 'encoding') {
          const items = (data.encoding || []).map((e) => `${e.result} ${(e.fraction * 100).toFixed(0)}%`);
          $('status').textContent = `encoding ${items.join(', ')}`;
        } else if (name === 'done') {
          finished = true;
          showBake(data);
          refreshRecent();
        } else if (name === 'deleted') {
          finished = true;
          $('status').textContent = `bake ${id} was deleted`;
          $('cancel').disabled = true;
          refreshRecent();
        }
      }, ctrl.signal);
    } catch (e) {
      if (ctrl.signal.aborted) return;
      if (e.status === 404 || e.status === 401) {
        showError(e, 'events');
        return;
      }
    }
    if (finished || ctrl.signal.aborted) break;
    // The stream ended without a final event: ask for the resource, then listen again.
    try {
      const { body } = await apiJson(`/v1/bakes/${encodeURIComponent(id)}`, { signal: ctrl.signal });
      if (TERMINAL.has(body.status)) {
        finished = true;
        showBake(body);
        break;
      }
    } catch (e) {
      if (ctrl.signal.aborted) return;
    }
    await new Promise((r) => setTimeout(r, Math.min(5000, 500 * (attempt + 1))));
  }
  if (state.watch === ctrl) state.watch = null;
}

$('cancel').addEventListener('click', async () => {
  const b = state.bake;
  if (!b) return;
  try {
    const res = await api(`/v1/bakes/${encodeURIComponent(b.id)}`, { method: 'DELETE' });
    $('status').textContent = res.status === 202 ? 'Cancel requested…' : res.status === 204 ? 'Deleted.' : 'Canceled.';
    if (res.status === 200) showBake(await res.json());
  } catch (e) {
    showError(e, 'cancel');
  }
});

// --- one bake: metadata, downloads, viewer --------------------------------------------------

function openResource(res) {
  if (location.hash.slice(1) !== res.id) history.replaceState(null, '', `#${res.id}`);
  showBake(res);
  if (!TERMINAL.has(res.status)) watch(res.id);
}

async function openBake(id) {
  try {
    const { body } = await apiJson(`/v1/bakes/${encodeURIComponent(id)}`);
    openResource(body);
  } catch (e) {
    showError(e, `bake ${id}`);
  }
}

function route() {
  const id = decodeURIComponent(location.hash.slice(1));
  if (id && (!state.bake || state.bake.id !== id || state.loadedId !== id)) openBake(id);
}

window.addEventListener('hashchange', route);

function showMeta(res) {
  const meta = $('meta');
  meta.textContent = '';
  const row = (k, v) => meta.append(el('dt', { text: k }), el('dd', { text: v }));
  const p = res.params || {};
  const i = res.input || {};
  row('id', res.id);
  row('status', res.status + (res.error ? ` — ${res.error.code || ''} ${res.error.detail || res.error.message || JSON.stringify(res.error)}` : ''));
  if (i.width) {
    const kind = [i.format, i.color, i.bit_depth ? `${i.bit_depth}-bit${i.float ? ' float' : ''}` : '']
      .filter(Boolean).join(' ');
    row('input', `${i.width} × ${i.height}${kind ? ` ${kind}` : ''}, ${fmtBytes(i.bytes)}`);
  }
  row('method', `${p.method || '?'}, bins ${p.bins ?? '?'}, reduce ${p.reduce ?? '?'}`);
  const rr = p.resolved_radius;
  row('radius', rr ? `${rr.texels} texels (asked: ${p.radius}) — ${rr.reason}` : String(p.radius ?? '?'));
  row('surface', `height_scale ${fmtNum(p.height_scale)}, channel ${p.channel}, edge ${p.edge}, y_axis ${p.y_axis}`);
  row('encoding', `${p.encoding}, outputs ${outputsOf(p).join(', ')}`);
  const g = res.georeferencing;
  if (g) {
    row('CRS', `${crsName(g)} (${g.model})`);
    row('cell size', g.cell_size ? fmtCell(g) : '—');
  }
  if (res.timings_ms) {
    row('timings', Object.entries(res.timings_ms).map(([k, v]) => `${k} ${Number(v).toFixed(1)} ms`).join(', '));
  }
  row('created', res.created_at || '—');
  if (res.finished_at) row('finished', res.finished_at);
}

function outputsOf(p) {
  const o = p.outputs;
  if (typeof o === 'string') return o.split(',');
  if (Array.isArray(o)) return o;
  if (o && typeof o === 'object') return Object.entries(o).filter(([, v]) => v).map(([k]) => k);
  return ['horizon'];
}

function currentLightQuery(shading) {
  const l = state.light;
  const q = new URLSearchParams({ shading, azimuth: String(l.azimuth), elevation: String(l.elevation),
    hardness: String(l.hardness) });
  return q.toString();
}

function showDownloads(res) {
  const ul = $('downloads');
  ul.textContent = '';
  const add = (label, href, type, filename) => {
    ul.append(el('li', {}, el('a', { class: 'dl', href, download: filename, 'data-type': type, text: label })));
  };
  const base = `/v1/bakes/${encodeURIComponent(res.id)}`;
  add('bake.json (resource)', base, 'application/json', `bake_${res.id}.json`);
  if (res.status !== 'succeeded') return;
  const links = res.links || {};
  if (links.horizon_0) {
    for (const layer of [0, 1]) {
      add(`horizon_${layer}.png (8-bit)`, `${base}/horizon/${layer}?format=png8`, 'image/png', `horizon_${layer}.png`);
      add(`horizon_${layer}.png (16-bit)`, `${base}/horizon/${layer}?format=png16`, 'image/png', `horizon_${layer}_16.png`);
      add(`horizon_${layer}.exr`, `${base}/horizon/${layer}?format=exr`, 'image/x-exr', `horizon_${layer}.exr`);
    }
    add('horizon.ktx2', `${base}/horizon.ktx2`, 'image/ktx2', 'horizon.ktx2');
    add('horizon.dds', `${base}/horizon.dds`, 'image/vnd-ms.dds', 'horizon.dds');
  }
  for (const k of [0, 1, 2]) {
    if (links[`fourier_${k}`]) add(`fourier_${k}.png`, `${base}/fourier/${k}`, 'image/png', `fourier_${k}.png`);
  }
  for (let f = 0; f < 6; f++) {
    add(`cube_${f}.png (${['+X', '−X', '+Y', '−Y', '+Z', '−Z'][f]})`, `/v1/cubemap/${f}?size=${CUBE_SIZE}`, 'image/png', `cube_${f}.png`);
  }
  add('cubemap.ktx2', `/v1/cubemap.ktx2?size=${CUBE_SIZE}`, 'image/ktx2', 'cubemap.ktx2');
  add('cubemap.dds', `/v1/cubemap.dds?size=${CUBE_SIZE}`, 'image/vnd-ms.dds', 'cubemap.dds');
  add('heights (f32 LE)', `${base}/heights`, 'application/octet-stream', `heights_${res.id}.f32`);
  const shading = links.horizon_0 ? 'horizon' : 'fourier';
  const prev = el('a', { class: 'dl', id: 'dl-preview', href: `${base}/preview?${currentLightQuery(shading)}`,
    download: `preview_${res.id}.png`, 'data-type': 'image/png', text: 'CPU preview at this light' });
  ul.append(el('li', {}, prev));
}

// Downloads cannot send headers, and a format the bake did not encode answers 202 while it is
// encoded: fetch the file (following the 202s, shown in the status line) and hand the browser a
// blob.
$('downloads').addEventListener('click', async (ev) => {
  const a = ev.target.closest('a.dl');
  if (!a) return;
  ev.preventDefault();
  try {
    const path = a.getAttribute('href');
    const res = await fetchResult(path, (body) => {
      const pct = body.progress ? ` ${(body.progress.fraction * 100).toFixed(0)}%` : '';
      $('status').textContent = `encoding ${body.result || path}${pct}…`;
    });
    const url = URL.createObjectURL(await res.blob());
    const tmp = el('a', { href: url, download: a.getAttribute('download') });
    document.body.append(tmp);
    tmp.click();
    tmp.remove();
    setTimeout(() => URL.revokeObjectURL(url), 30000);
  } catch (e) {
    showError(e, 'download');
  }
});

function showBake(res) {
  const changed = !state.bake || state.bake.id !== res.id;
  state.bake = res;
  $('bake-id').textContent = `#${res.id}`;
  showMeta(res);
  showDownloads(res);
  if (TERMINAL.has(res.status)) {
    // A canceled or failed bake keeps the fraction it reached (the resource keeps it too).
    showProgress(res.status === 'succeeded' ? 1 : res.progress.fraction, res.status === 'succeeded' ? 'done' : res.status, res.status);
  } else {
    showProgress(res.progress.fraction, res.progress.stage, res.status);
  }
  for (const li of document.querySelectorAll('#recent li')) {
    li.classList.toggle('current', li.dataset.id === res.id);
  }
  markRecent(res.id, res.status);
  // Opened by #id, from the list, or just submitted: the form shows what this bake used.
  if (changed) loadForm(res.params);
  if (res.status === 'succeeded' && (changed || state.loadedId !== res.id)) loadViewer(res);
  showDem(res);
  showTerrain(res);
  showSurface(res);
  if (res.status === 'failed' && res.error) {
    showError({ code: res.error.code || 'failed', detail: res.error.detail || res.error.message || JSON.stringify(res.error) }, `bake ${res.id} failed`);
  }
}

// --- DEM and terrain products -----------------------------------------------------------------

function crsName(g) {
  if (g.epsg) return `EPSG:${g.epsg}`;
  return g.citation || 'unknown CRS';
}

/** The CRS, cell size and resolved DEM defaults of a bake's input, from its resource. */
function showDem(res) {
  const out = $('dem-info');
  const g = res.georeferencing;
  const p = res.params || {};
  if (!g) {
    if (res.input && res.input.format === 'tiff' && !out.hidden) {
      out.textContent = 'TIFF without georeferencing: the plain-image defaults apply.';
      delete out.dataset.epsg;
      delete out.dataset.cellSize;
    } else {
      out.hidden = true;
    }
    return;
  }
  out.hidden = false;
  out.dataset.epsg = g.epsg ? String(g.epsg) : '';
  out.dataset.cellSize = g.cell_size ? String(g.cell_size) : '';
  const cell = g.cell_size ? `cell size ${fmtCell(g)}` : 'no cell size';
  out.textContent = `DEM: ${crsName(g)} (${g.model}), ${cell}; height_scale ${fmtNum(p.height_scale)}, edge ${p.edge}; ${p.method}, radius ${p.radius}.`;
  // A DEM bake opened by #id: re-baking it keeps the file's defaults.
  if ($('dem-l').hidden) showDemRow(true, true);
}

/** The terrain panel of a succeeded bake: its SVF (when baked) and the shadow of a sun. */
function showTerrain(res) {
  const sec = $('terrain');
  if (res.status !== 'succeeded') {
    sec.hidden = true;
    return;
  }
  sec.hidden = false;
  const p = res.params || {};
  const hasSvf = outputsOf(p).includes('svf');
  $('show-svf').disabled = !hasSvf;
  $('sun-azimuth').title = `degrees, counted ${p.azimuth_from === 'north_cw' ? 'clockwise from north' : 'counter-clockwise from east'} (the bake's azimuth_from)`;
  if (state.terrainFor !== res.id) {
    state.terrainFor = res.id;
    for (const id of ['svf', 'shadow']) {
      $(`${id}-fig`).hidden = true;
      const img = $(`${id}-image`);
      if (img.src.startsWith('blob:')) URL.revokeObjectURL(img.src);
      img.removeAttribute('src');
      delete img.dataset.query;
    }
    $('terrain-note').textContent = hasSvf ? ''
      : 'No sky-view factor in this bake: tick “terrain products” and bake again. The shadow works for any bake.';
    if (hasSvf) showTerrainImage('svf', 'format=png', `sky-view factor (${p.svf_model || 'radiative'}): black 0, white 1; clear = nodata`);
  }
}

const SURFACE_MAPS = ['normal', 'ao', 'bent_normal'];

/** The surface-map panel of a succeeded bake: each of normal, ao, bent_normal it computed,
 * as the server's PNG (SPEC §3.8), with what its channels hold. */
function showSurface(res) {
  const sec = $('surface');
  const p = res.params || {};
  const maps = SURFACE_MAPS.filter((m) => outputsOf(p).includes(m));
  if (res.status !== 'succeeded' || !maps.length) {
    sec.hidden = true;
    return;
  }
  sec.hidden = false;
  if (state.surfaceFor === res.id) return;
  state.surfaceFor = res.id;
  for (const id of SURFACE_MAPS) {
    $(`${id}-fig`).hidden = true;
    const img = $(`${id}-image`);
    if (img.src.startsWith('blob:')) URL.revokeObjectURL(img.src);
    img.removeAttribute('src');
  }
  const conv = p.normal_convention || 'opengl';
  $('surface-note').textContent = `normal_convention ${conv} (${conv === 'directx' ? 'Y−: Unreal' : 'Y+: Godot, Blender, Unity'}), from ${p.method === 'lengyel' ? 'its 8 channel directions (lengyel: coarse)' : `every one of its ${p.bins} bins`}; holes are black.`;
  const captions = {
    normal: 'normal map: (n + 1) / 2, flat = (128, 128, 255)',
    ao: 'ambient occlusion: white open and flat, darker under the horizons',
    bent_normal: `bent normal: (b + 1) / 2 (${p.bent_normal_encoding || 'rgb'})`,
  };
  for (const m of maps) showTerrainImage(m, '', captions[m]);
}

/** Loads a server image (`svf` or `shadow` rendering, or a surface map) of the current bake
 * into its figure. */
async function showTerrainImage(kind, query, caption) {
  const bake = state.bake;
  if (!bake) return;
  const img = $(`${kind}-image`);
  $(`${kind}-caption`).textContent = `${caption} — loading…`;
  try {
    const url = await blobUrl(`/v1/bakes/${encodeURIComponent(bake.id)}/${kind}?${query}`);
    if (!state.bake || state.bake.id !== bake.id) {
      URL.revokeObjectURL(url);
      return;
    }
    await new Promise((resolve, reject) => {
      img.addEventListener('load', resolve, { once: true });
      img.addEventListener('error', () => reject(new Error(`the ${kind} image did not decode`)), { once: true });
      const old = img.src;
      img.src = url;
      if (old.startsWith('blob:')) URL.revokeObjectURL(old);
    });
    img.dataset.query = query;
    $(`${kind}-fig`).hidden = false;
    $(`${kind}-caption`).textContent = caption;
  } catch (e) {
    $(`${kind}-caption`).textContent = '';
    showError(e, kind);
  }
}

$('show-svf').addEventListener('click', () => {
  const p = (state.bake && state.bake.params) || {};
  showTerrainImage('svf', 'format=png', `sky-view factor (${p.svf_model || 'radiative'}): black 0, white 1; clear = nodata`);
});

$('show-shadow').addEventListener('click', () => {
  clearErrors();
  const az = Number($('sun-azimuth').value);
  const elev = Number($('sun-elevation').value);
  if ($('sun-azimuth').value.trim() === '' || !Number.isFinite(az)) {
    showError({ code: 'invalid_parameter', field: null, detail: 'sun azimuth: give a number of degrees' }, 'shadow');
    return;
  }
  if ($('sun-elevation').value.trim() === '' || !Number.isFinite(elev) || elev < -90 || elev > 90) {
    showError({ code: 'invalid_parameter', field: null, detail: 'sun elevation: give degrees between -90 and 90' }, 'shadow');
    return;
  }
  const q = new URLSearchParams({ sun_azimuth: String(az), sun_elevation: String(elev), format: 'png' });
  showTerrainImage('shadow', q.toString(), `sun shadow at azimuth ${az}°, elevation ${elev}°: white lit, black shadowed; clear = nodata`);
});

// --- recent bakes ---------------------------------------------------------------------------

async function refreshRecent() {
  const ol = $('recent');
  let items = [];
  try {
    let url = '/v1/bakes?limit=1000';
    for (let page = 0; url && page < 10; page++) {
      const { body } = await apiJson(url);
      items = items.concat(body.items);
      url = body.next ? body.next.href : null;
    }
  } catch (e) {
    ol.textContent = '';
    ol.append(el('li', { class: 'muted', text: e.status === 401 ? 'needs the API key' : `cannot list: ${e.message}` }));
    return;
  }
  ol.textContent = '';
  const recent = items.slice(-40).reverse();
  if (!recent.length) ol.append(el('li', { class: 'muted', text: 'no bakes yet' }));
  for (const b of recent) {
    const i = b.input || {};
    const p = b.params || {};
    const li = el('li', { 'data-id': b.id, class: state.bake && state.bake.id === b.id ? 'current' : '' },
      el('a', { href: `#${b.id}`, class: 'mono', text: b.id.slice(0, 14) }),
      el('span', { class: `st ${b.status}`, text: b.status }),
      el('span', { class: 'muted', text: `${i.width || '?'}×${i.height || '?'} ${p.method || ''} r=${p.resolved_radius ? p.resolved_radius.texels : p.radius}` }));
    ol.append(li);
  }
}

$('refresh').addEventListener('click', refreshRecent);

// --- the viewer -----------------------------------------------------------------------------

function setupViewer() {
  try {
    state.viewer = Viewer.create($('canvas'));
  } catch (e) {
    state.viewer = null;
    state.viewerError = e.message;
  }
  if (state.viewer) {
    $('renderer').textContent = `WebGL2: ${state.viewer.rendererName()}`;
  } else {
    $('renderer').textContent = 'no WebGL2';
    $('viewer-note').textContent = `WebGL2 is not available${state.viewerError ? ` (${state.viewerError})` : ''}: showing the server's CPU preview instead.`;
    $('canvas').hidden = true;
    $('cpu-fig').hidden = false;
    $('layout').disabled = true;
    $('debug').disabled = true;
  }
}

async function fetchImage(path) {
  const res = await api(path);
  return decodeImage(await res.blob());
}

async function loadCube() {
  if (!state.cube) {
    state.cube = Promise.all([0, 1, 2, 3, 4, 5].map((f) => fetchImage(`/v1/cubemap/${f}?size=${CUBE_SIZE}`)));
  }
  try {
    return await state.cube;
  } catch (e) {
    state.cube = null;
    throw e;
  }
}

async function loadViewer(res) {
  const token = ++state.loadToken;
  state.loadedId = null;
  const v = state.viewer;
  const p = res.params || {};
  const outs = outputsOf(p);
  const hasHorizon = !!(res.links && res.links.horizon_0);
  const hasFourier = !!(res.links && res.links.fourier_0);
  for (const opt of $('shading').options) {
    if (opt.value === 'horizon' || opt.value === 'difference') opt.disabled = !hasHorizon;
    if (opt.value === 'fourier') opt.disabled = !hasFourier;
  }
  if ($('shading').selectedOptions[0].disabled) $('shading').value = hasHorizon ? 'horizon' : 'fourier';
  for (const opt of $('layout').options) {
    if (opt.value === 'tiled') opt.disabled = p.edge !== 'wrap';
  }
  if ($('layout').value === 'tiled' && p.edge !== 'wrap') $('layout').value = 'single';
  if (!v) {
    update();
    return;
  }
  $('viewer-note').textContent = 'Loading the baked layers…';
  try {
    const base = `/v1/bakes/${encodeURIComponent(res.id)}`;
    const hres = await api(`${base}/heights`);
    const w = Number(hres.headers.get('x-width')) || res.input.width;
    const h = Number(hres.headers.get('x-height')) || res.input.height;
    const buf = await hres.arrayBuffer();
    if (buf.byteLength !== w * h * 4) throw new Error(`heights: ${buf.byteLength} bytes for ${w}×${h}`);
    const max = v.maxTextureSize();
    if (w > max || h > max) throw new Error(`the map (${w}×${h}) exceeds this GPU's texture size ${max}`);
    const heights = new Float32Array(w * h);
    const dv = new DataView(buf);
    for (let k = 0; k < w * h; k++) heights[k] = dv.getFloat32(k * 4, true);
    const terms = Number(p.fourier_terms) || 5;
    const [layers, fourier, cube] = await Promise.all([
      hasHorizon ? Promise.all([fetchImage(`${base}/horizon/0`), fetchImage(`${base}/horizon/1`)]) : null,
      hasFourier ? Promise.all([fetchImage(`${base}/fourier/0`), fetchImage(`${base}/fourier/1`),
        terms >= 7 && res.links.fourier_2 ? fetchImage(`${base}/fourier/2`) : null]) : null,
      loadCube(),
    ]);
    if (token !== state.loadToken) return;
    v.setMap({ width: w, height: h, heights, edge: p.edge, yAxis: p.y_axis, encoding: p.encoding });
    if (layers) v.setLayers(layers[0], layers[1]);
    if (fourier) v.setFourier(fourier[0], fourier[1], fourier[2], terms, p.fourier_range);
    v.setCube(cube);
    state.loadedId = res.id;
    $('viewer-note').textContent = `${w} × ${h}, ${outs.join(' + ')}; GPU decodes the layers with the cube map (${CUBE_SIZE}² per face).`;
    update();
  } catch (e) {
    if (token !== state.loadToken) return;
    $('viewer-note').textContent = `The viewer could not load this bake: ${e.message}`;
    showError(e, 'viewer');
  }
}

function debugOptions() {
  const d = $('debug').value;
  if (d === 'layer0' || d === 'layer1') return { mode: 'layer', layer: Number(d[5]) };
  if (d.startsWith('ch')) return { mode: 'channel', channel: Number(d.slice(2)) };
  return { mode: d };
}

function viewOptions(extra = {}) {
  const l = state.light;
  const sh = $('shading').value;
  return {
    light: fromAngles(l.azimuth, l.elevation),
    hardness: l.hardness,
    // raytraced/difference are server images: beside them the GPU shows its own decode
    shading: sh === 'fourier' || sh === 'none' ? sh : state.viewer && !state.viewer.hasLayers ? 'fourier' : 'horizon',
    tiled: $('layout').value === 'tiled',
    ...debugOptions(),
    ...extra,
  };
}

function displaySize(w, h) {
  const zoom = $('zoom').value;
  if (zoom !== 'fit') return [w * Number(zoom), h * Number(zoom)];
  const stage = $('stage').getBoundingClientRect();
  const side = $('layout').value === 'side' ? 2 : 1;
  const maxW = Math.max(64, (stage.width - (side - 1) * 10) / side);
  const maxH = Math.max(128, window.innerHeight * 0.72);
  const s = Math.min(maxW / w, maxH / h);
  return [Math.max(1, Math.floor(w * s)), Math.max(1, Math.floor(h * s))];
}

function showLight() {
  const l = state.light;
  $('light').textContent = `azimuth ${fmtDeg(l.azimuth)}, elevation ${fmtDeg(l.elevation)}, hardness ${l.hardness}`;
  $('azimuth').value = ((l.azimuth + 180) % 360 + 360) % 360 - 180;
  $('elevation').value = l.elevation;
  $('hardness').value = l.hardness;
  $('azimuth-v').textContent = fmtDeg(l.azimuth);
  $('elevation-v').textContent = fmtDeg(l.elevation);
  $('hardness-v').textContent = String(l.hardness);
  const prev = $('dl-preview');
  if (prev && state.bake) {
    const shading = state.bake.links && state.bake.links.horizon_0 ? 'horizon' : 'fourier';
    prev.href = `/v1/bakes/${encodeURIComponent(state.bake.id)}/preview?${currentLightQuery(shading)}`;
  }
}

/** The sun marker: centre = overhead, the image's edge = the horizon. */
function placeSun(cssW, cssH) {
  const sun = $('sun');
  const l = state.light;
  const up = !state.bake || (state.bake.params || {}).y_axis !== 'down';
  const r = Math.max(0, Math.min(1, 1 - l.elevation / 90));
  const a = (l.azimuth * Math.PI) / 180;
  const dx = r * Math.cos(a);
  const dy = r * Math.sin(a) * (up ? -1 : 1);
  sun.style.left = `${cssW / 2 + (dx * cssW) / 2}px`;
  sun.style.top = `${cssH / 2 + (dy * cssH) / 2}px`;
  sun.hidden = debugOptions().mode !== 'shaded';
}

function update() {
  showLight();
  const v = state.viewer;
  const bake = state.bake;
  const layout = $('layout').value;
  const sh = $('shading').value;
  const serverOnly = sh === 'raytraced' || sh === 'difference';
  const ready = v && state.loadedId && bake && state.loadedId === bake.id;
  const k = layout === 'tiled' ? 2 : 1;
  const mw = bake && bake.input && bake.input.width ? bake.input.width : 256;
  const mh = bake && bake.input && bake.input.height ? bake.input.height : 256;
  const [cw, ch] = displaySize(mw * k, mh * k);
  // "display" renders at the shown size (textures filtered as the preview's `size=` does).
  state.size = $('resolution').value === 'display'
    ? Math.max(1, Math.min(4096, Math.round(Math.max(cw, ch) / k))) : undefined;
  if (ready) v.draw(viewOptions({ size: state.size }));
  for (const e of [$('canvas'), $('overlay'), $('server-image'), $('cpu-image')]) {
    e.style.width = `${cw}px`;
    e.style.height = `${ch}px`;
  }
  const cmpShading = serverOnly ? sh : viewOptions().shading;
  const wantCpu = !v || serverOnly || ((layout === 'split' || layout === 'side') && debugOptions().mode === 'shaded');
  // Server-only shadings (raytraced, difference) replace the canvas, except side by side,
  // where they stand beside the GPU's horizon decode.
  const side = layout === 'side' && debugOptions().mode === 'shaded';
  $('server-image').hidden = !(v && serverOnly && !side);
  $('canvas').style.visibility = v && serverOnly && !side ? 'hidden' : '';
  $('overlay').hidden = !(v && !serverOnly && layout === 'split' && debugOptions().mode === 'shaded');
  $('split-line').hidden = $('overlay').hidden;
  $('split').hidden = $('overlay').hidden;
  $('cpu-fig').hidden = !(!v || side);
  $('cpu-caption').textContent = serverOnly ? `${sh} (server)` : `CPU preview, ${cmpShading} (server)`;
  $('legend').textContent = sh === 'difference'
    ? 'difference (server): grey = horizon map and ray tracing agree; red = the map shadows a lit texel; blue = it lights a shadowed one.'
    : sh === 'raytraced' ? 'raytraced (server): ground-truth shadows, exact horizon to the edge of the map.' : '';
  if (!$('overlay').hidden) {
    const pct = Number($('split').value);
    $('overlay').style.clipPath = `inset(0 0 0 ${pct}%)`;
    $('split-line').style.left = `${(pct / 100) * cw}px`;
  }
  placeSun(cw, ch);
  if (wantCpu && bake && bake.status === 'succeeded' && layout !== 'tiled') schedulePreview(cmpShading);
}

/** Fetches the server's CPU preview at the current light (debounced, stale requests aborted). */
function schedulePreview(shading) {
  const query = currentLightQuery(shading) + (state.size ? `&size=${state.size}` : '');
  const key = `${state.bake.id}?${query}`;
  if (key === state.previewFor) return;
  clearTimeout(state.previewTimer);
  state.previewTimer = setTimeout(async () => {
    if (state.previewAbort) state.previewAbort.abort();
    const ctrl = new AbortController();
    state.previewAbort = ctrl;
    try {
      const url = await blobUrl(`/v1/bakes/${encodeURIComponent(state.bake.id)}/preview?${query}`, ctrl.signal);
      if (ctrl.signal.aborted) return;
      if (state.previewUrl) URL.revokeObjectURL(state.previewUrl);
      state.previewUrl = url;
      state.previewFor = key;
      for (const id of ['overlay', 'cpu-image', 'server-image']) $(id).src = url;
    } catch (e) {
      if (!ctrl.signal.aborted) $('viewer-note').textContent = `CPU preview: ${e.code || ''} ${e.message}`;
    }
  }, 150);
}

function setLight(l) {
  if (l.azimuth !== undefined) state.light.azimuth = Number(l.azimuth);
  if (l.elevation !== undefined) state.light.elevation = Math.max(-90, Math.min(90, Number(l.elevation)));
  if (l.hardness !== undefined) state.light.hardness = Number(l.hardness);
  update();
}

for (const id of ['azimuth', 'elevation', 'hardness']) {
  $(id).addEventListener('input', () => setLight({ [id]: Number($(id).value) }));
}
for (const id of ['shading', 'layout', 'debug', 'zoom', 'resolution']) $(id).addEventListener('change', update);
$('split').addEventListener('input', update);
window.addEventListener('resize', update);

// Drag the light: the pointer's offset from the image centre is the light's direction in the
// tangent plane (image up = +y for y_axis=up), its distance the elevation (centre = 90°).
function lightFromPointer(ev, target) {
  const rect = target.getBoundingClientRect();
  const dx = (ev.clientX - (rect.left + rect.width / 2)) / (rect.width / 2);
  const dy = (ev.clientY - (rect.top + rect.height / 2)) / (rect.height / 2);
  const up = !state.bake || (state.bake.params || {}).y_axis !== 'down';
  const tx = dx;
  const ty = up ? -dy : dy;
  const r = Math.min(1, Math.hypot(tx, ty));
  const azimuth = Math.round((Math.atan2(ty, tx) * 180) / Math.PI * 10) / 10;
  const elevation = Math.max(0.5, Math.round(90 * (1 - r) * 10) / 10);
  setLight({ azimuth, elevation });
}

// The GPU image, and the CPU image (the only one without WebGL2), take the drag.
for (const [area, image] of [[$('gpu-wrap'), $('canvas')], [$('cpu-fig'), $('cpu-image')]]) {
  area.addEventListener('pointerdown', (ev) => {
    if (ev.button !== 0) return;
    ev.preventDefault();
    area.setPointerCapture(ev.pointerId);
    area.dataset.dragging = '1';
    lightFromPointer(ev, image);
  });
  area.addEventListener('pointermove', (ev) => {
    if (area.dataset.dragging) lightFromPointer(ev, image);
  });
  for (const t of ['pointerup', 'pointercancel']) {
    area.addEventListener(t, () => delete area.dataset.dragging);
  }
}

// --- copy as curl ---------------------------------------------------------------------------

$('curl').addEventListener('click', async () => {
  const name = state.file ? state.file.name : 'height.png';
  const type = (state.fileInfo && state.fileInfo.type) || 'image/png';
  const q = (s) => `'${String(s).replace(/'/g, "'\\''")}'`;
  const parts = ['curl -sS -X POST', `--data-binary @${q(name)}`, `-H ${q(`Content-Type: ${type}`)}`];
  if (config.auth_required || getApiKey()) parts.push('-H "Authorization: Bearer $HORIZON_API_KEY"');
  parts.push(q(`${location.origin}/v1/bakes${paramQuery(formParams())}`));
  const text = parts.join(' \\\n  ');
  const ta = $('curl-text');
  ta.value = text;
  ta.hidden = false;
  try {
    await navigator.clipboard.writeText(text);
    $('status').textContent = 'curl command copied.';
  } catch {
    ta.select();
    $('status').textContent = 'Copy the curl command from the box.';
  }
});

// --- test and automation hook ---------------------------------------------------------------

function base64(bytes) {
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

window.__horizon = {
  config,
  progressLog: state.progressLog,
  get loadedId() { return state.loadedId; },
  get bake() { return state.bake; },
  get light() { return { ...state.light }; },
  get webgl2() { return !!state.viewer; },
  setLight(l) { setLight(l); return { ...state.light }; },
  /** The visible canvas, RGBA rows from the top, base64. */
  readCanvas() {
    const px = state.viewer.readCanvas();
    return { width: px.width, height: px.height, rgba: base64(px.rgba) };
  },
  /**
   * An off-screen render (defaults: the current light, shading horizon, the native size; `size`
   * = the longer side, as the preview's `size`).
   */
  render(o = {}) {
    const l = { ...state.light, ...o };
    const px = state.viewer.renderPixels(viewOptions({ light: fromAngles(l.azimuth, l.elevation),
      hardness: l.hardness, shading: o.shading || 'horizon', mode: 'shaded', tiled: false,
      size: o.size }));
    return { width: px.width, height: px.height, rgba: base64(px.rgba) };
  },
};

// --- start ----------------------------------------------------------------------------------

$('version').textContent = `v${config.version}`;
showKeyState();
showLimits();
setupViewer();
showLight();
refreshRecent();
route();
