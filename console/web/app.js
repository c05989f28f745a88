// The FaStage console: one page, its views chosen by the address's #fragment, fed by the console's event stream
// (/api/events) and its JSON API. Plain ES module, nothing fetched from elsewhere.

const $ = (id) => document.getElementById(id);
const state = { me: null, status: null, take: null, summary: null, alarms: { active: [], history: [] }, events: null,
  ledgerLost: [], previewTimer: null };

// Text for HTML: names, reasons and messages come from the stage and its users, not from this page.
function esc(text) {
  return String(text ?? '').replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' })[c]);
}

function enumName(value, prefix) { return String(value || '').replace(prefix, ''); }
function ms(unixMs) { return unixMs ? new Date(Number(unixMs)).toLocaleTimeString() : ''; }
function toast(text) {
  const t = $('toast');
  t.textContent = text;
  t.hidden = false;
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => { t.hidden = true; }, 6000);
}

async function api(path, options = {}) {
  const init = { credentials: 'same-origin', ...options };
  if (init.method === 'POST') init.headers = { 'Content-Type': 'application/json', 'X-FaStage': '1', ...(init.headers || {}) };
  const res = await fetch(path, init);
  if (res.status === 401) { showLogin(); throw new Error('log in first'); }
  const type = res.headers.get('Content-Type') || '';
  const body = type.startsWith('application/json') ? await res.json() : await res.text();
  if (!res.ok) throw new Error(body.error || res.statusText);
  return body;
}

async function command(path, body = {}, confirmText = null) {
  if (confirmText && !window.confirm(confirmText)) return null;
  try {
    return await api(path, { method: 'POST', body: JSON.stringify(body) });
  } catch (e) {
    toast(`${path.replace('/api/', '')}: ${e.message}`);
    return null;
  }
}

// ---- login ----
function showLogin() {
  $('login').hidden = false;
  $('pages').hidden = true;
  if (state.events) { state.events.close(); state.events = null; }
}

async function start() {
  try {
    state.me = await api('/api/me');
  } catch (e) {
    return;
  }
  $('login').hidden = true;
  $('pages').hidden = false;
  $('who').textContent = `${state.me.user} (${state.me.role})`;
  document.body.dataset.role = state.me.role;
  for (const b of document.querySelectorAll('button.operator')) b.disabled = state.me.role !== 'operator';
  follow();
  refreshAlarms();
  refreshLog();
  route();
}

$('login-form').addEventListener('submit', async (ev) => {
  ev.preventDefault();
  $('login-error').textContent = '';
  const res = await fetch('/api/login', { method: 'POST', credentials: 'same-origin',
    headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify({ user: $('login-user').value, password: $('login-password').value }) });
  if (!res.ok) {
    $('login-error').textContent = (await res.json()).error || 'refused';
    return;
  }
  $('login-password').value = '';
  start();
});
$('logout').addEventListener('click', async () => {
  await fetch('/api/logout', { method: 'POST', credentials: 'same-origin' });
  showLogin();
});

// ---- the event stream ----
// An event's JSON; an event that is not JSON is the console's fault, and says which.
function data(e) {
  try {
    return JSON.parse(e.data);
  } catch (err) {
    throw new Error(`the console sent a ${e.type} event that is not JSON: ${String(e.data).slice(0, 120)}`);
  }
}

function follow() {
  if (state.events) state.events.close();
  const es = new EventSource('/api/events');
  state.events = es;
  es.addEventListener('status', (e) => renderStatus(data(e)));
  es.addEventListener('take', (e) => onTakeEvent(data(e)));
  es.addEventListener('alarm', (e) => onAlarm(data(e)));
  es.addEventListener('log', (e) => appendLog(data(e)));
  es.addEventListener('message', (e) => toast(data(e).text));
  es.addEventListener('link', (e) => renderLink(data(e)));
  es.addEventListener('resync', () => { refreshAlarms(); refreshLog(); });
  es.onerror = () => { $('link').textContent = 'console unreachable'; $('link').className = 'pill bad'; };
  es.onopen = () => renderLink({ connected: true });
}

function renderLink(link) {
  $('link').textContent = link.connected ? 'controller up' : `controller unreachable: ${link.error || ''}`;
  $('link').className = `pill ${link.connected ? 'ok' : 'bad'}`;
}

// ---- the stage at a glance ----
function deviceLine(d) {
  if (!d) return '';
  if (d.light) {
    const l = d.light;
    const mode = enumName(l.mode, 'LIGHT_MODE_');
    const parts = [`<span class="${mode === 'BLACKOUT' ? 'dark' : ''}">${mode}</span>`];
    if (l.temperature_c) parts.push(`${Number(l.temperature_c).toFixed(1)} °C`);
    parts.push(`duty ${(Number(l.max_channel_duty || 0) * 100).toFixed(0)} %`);
    parts.push(`thermal ${(Number(l.max_thermal_load || 0) * 100).toFixed(0)} %`);
    if (l.faults && l.faults.length) parts.push(`faults: ${esc(l.faults.join('; '))}`);
    return parts.join(' · ');
  }
  if (d.camera) {
    const c = d.camera;
    const parts = [c.link_up ? 'camera linked' : `camera link down ${esc(c.link_detail)}`];
    parts.push(`${c.frames_completed} frames, ${c.frames_dropped} dropped`);
    if (c.take_id) parts.push(`take ${c.take_frames_received}/${c.take_frames_expected}, lost ${c.take_frames_lost}`);
    return parts.join(' · ');
  }
  return d.error ? `device: ${esc(d.error)}` : '';
}

function renderStatus(s) {
  if (!s || !s.nodes) return;
  state.status = s;
  $('stage-name').textContent = s.stage_name || s.stage_id || '';
  const session = enumName(s.session_state, 'SESSION_STATE_');
  $('session').textContent = session + (s.current_take_id ? ` ${s.current_take_id}` : '');
  $('session').dataset.state = session;
  $('stage-summary').textContent = `${s.nodes_up}/${s.nodes_total} nodes up · timing ${s.timing_errors} errors, ` +
    `${s.timing_warnings} warnings`;
  const banner = $('estop-banner');
  banner.hidden = !s.estop_latched;
  banner.textContent = s.estop_latched ? `Emergency stop latched: ${s.estop_reason}. Every light node is dark; ` +
    'an operator resets it on the Take page.' : '';
  document.body.dataset.estop = s.estop_latched ? 'latched' : 'clear';
  const devices = Object.fromEntries((s.devices || []).map((d) => [d.id, d]));
  const html = s.nodes.map((n) => {
    const link = enumName(n.state, 'NODE_STATE_').toLowerCase();
    const kind = enumName(n.kind, 'NODE_KIND_').toLowerCase();
    const role = n.camera_role && n.camera_role !== 'CAMERA_ROLE_UNSPECIFIED' ? ` ${enumName(n.camera_role, 'CAMERA_ROLE_').toLowerCase()}` : '';
    const clock = n.clock && n.clock.measured ? `clock ${(Number(n.clock.offset_ns) / 1000).toFixed(1)} ± ` +
      `${(Number(n.clock.uncertainty_ns) / 1000).toFixed(1)} µs${n.clock.flagged ? ' FLAGGED' : ''}` : 'clock not measured';
    const rtt = n.rtt_ns ? `rtt ${(Number(n.rtt_ns) / 1e6).toFixed(2)} ms` : '';
    const d = devices[n.id];
    const dark = d && d.light && d.light.mode === 'LIGHT_MODE_BLACKOUT' ? 'dark' : '';
    return `<div class="card link-${link}" data-node="${esc(n.id)}" data-link="${link}" data-light="${dark}">
      <h3>${esc(n.id)} <small>${kind}${role}</small></h3>
      <div>link ${link.toUpperCase()}${n.reason ? `: ${esc(n.reason)}` : ''}</div>
      <div>${clock} ${rtt}</div>
      <div class="device">${deviceLine(d)}</div></div>`;
  }).join('');
  $('nodes').innerHTML = html;
  fillCameraChoices(s);
  renderLedgerLive();
}

// ---- previews ----
function fillCameraChoices(s) {
  const select = $('preview-camera');
  // High-speed cameras first: they see every pattern, the full-on ones whose frames make the previews among them.
  const cameraNodes = s.nodes.filter((n) => n.kind === 'NODE_KIND_CAMERA');
  const cameras = [...cameraNodes.filter((n) => n.camera_role === 'CAMERA_ROLE_HIGH_SPEED'),
    ...cameraNodes.filter((n) => n.camera_role !== 'CAMERA_ROLE_HIGH_SPEED')].map((n) => n.id);
  if (select.options.length === cameras.length) return;
  const chosen = select.value;
  select.innerHTML = cameras.map((c) => `<option>${esc(c)}</option>`).join('');
  if (cameras.includes(chosen)) select.value = chosen;
}

async function refreshPreview() {
  const camera = $('preview-camera').value;
  if (!camera) return;
  let p;
  try {
    p = await api(`/api/preview?camera=${encodeURIComponent(camera)}`);
  } catch (e) {
    $('preview-info').textContent = e.message;
    return;
  }
  const img = new Image();
  img.onload = () => drawPreview(img, p);
  img.src = `data:image/png;base64,${p.png}`;
}

function drawPreview(img, p) {
  const canvas = $('preview-canvas');
  canvas.width = img.width;
  canvas.height = img.height;
  // Small previews drawn larger, by a whole factor (pixels stay square and sharp).
  canvas.style.width = `${Math.max(1, Math.min(8, Math.floor(720 / img.width))) * img.width}px`;
  const ctx = canvas.getContext('2d');
  ctx.drawImage(img, 0, 0);
  const raw = ctx.getImageData(0, 0, img.width, img.height);
  state.previewRaw = raw;
  // Auto-stretch: the 0.5th to 99.5th percentile of luminance onto 0..255.
  const hist = new Array(256).fill(0);
  for (let i = 0; i < raw.data.length; i += 4) {
    hist[Math.round(0.2126 * raw.data[i] + 0.7152 * raw.data[i + 1] + 0.0722 * raw.data[i + 2])] += 1;
  }
  const total = raw.data.length / 4;
  let lo = 0, hi = 255, seen = 0;
  for (let v = 0; v < 256; v++) { seen += hist[v]; if (seen >= 0.005 * total) { lo = v; break; } }
  seen = 0;
  for (let v = 255; v >= 0; v--) { seen += hist[v]; if (seen >= 0.005 * total) { hi = v; break; } }
  if (hi <= lo) hi = lo + 1;
  const out = ctx.createImageData(img.width, img.height);
  const k = 255 / (hi - lo);
  for (let i = 0; i < raw.data.length; i += 4) {
    for (let c = 0; c < 3; c++) out.data[i + c] = Math.max(0, Math.min(255, (raw.data[i + c] - lo) * k));
    out.data[i + 3] = 255;
  }
  ctx.putImageData(out, 0, 0);
  const h = $('preview-histogram').getContext('2d');
  h.clearRect(0, 0, 256, 100);
  const peak = Math.max(...hist.slice(1, 255), 1);
  h.fillStyle = '#8ab4f8';
  for (let v = 0; v < 256; v++) h.fillRect(v, 100 - Math.min(100, (hist[v] / peak) * 100), 1, 100);
  h.fillStyle = '#e0a100';
  h.fillRect(lo, 0, 1, 100);
  h.fillRect(hi, 0, 1, 100);
  $('preview-stretch').textContent = `stretched ${lo}..${hi} to 0..255`;
  const f = p.frame || {};
  $('preview-info').textContent = `${p.width}x${p.height} · frame ${f.frame_id ?? ''} · slot ${f.slot ?? ''}`;
  canvas.dataset.loaded = $('preview-camera').value;
}

$('preview-canvas').addEventListener('mousemove', (ev) => {
  const raw = state.previewRaw;
  if (!raw) return;
  const r = ev.target.getBoundingClientRect();
  const x = Math.floor((ev.clientX - r.left) * raw.width / r.width);
  const y = Math.floor((ev.clientY - r.top) * raw.height / r.height);
  if (x < 0 || y < 0 || x >= raw.width || y >= raw.height) return;
  const i = (y * raw.width + x) * 4;
  $('preview-pixel').textContent = `(${x}, ${y}): R ${raw.data[i]} G ${raw.data[i + 1]} B ${raw.data[i + 2]}`;
});
$('preview-refresh').addEventListener('click', refreshPreview);
$('preview-camera').addEventListener('change', refreshPreview);

// ---- the take: controls and the ledger grid ----
const BINS = 60;

function onTakeEvent(e) {
  if (!state.take || state.take.id !== e.take_id) {
    state.take = { id: e.take_id };
    state.summary = null;
    state.ledgerLost = [];
    $('take-outcome').textContent = '';
  }
  $('take-id').textContent = e.take_id || '';
  if (e.progress) {
    const p = e.progress;
    state.take.progress = p;
    $('take-progress').textContent = `${enumName(p.phase, 'CAPTURE_PHASE_')}: ${p.frames_received}/${p.frames_expected} ` +
      `received, ${p.frames_written} written, ${p.frames_lost} lost · ${Number(p.elapsed_s).toFixed(1)} s` +
      (p.waiting_for ? ` · waiting for ${p.waiting_for}` : '');
  }
  if (e.message) toast(e.message);
  if (e.summary) {
    state.summary = e.summary;
    const outcome = enumName(e.summary.outcome, 'TAKE_OUTCOME_');
    $('take-outcome').textContent = `${outcome}: ${e.summary.total.stored}/${e.summary.total.expected} stored` +
      (e.summary.hint ? ` · ${e.summary.hint}` : '');
    $('take-outcome').dataset.outcome = outcome;
    api(`/api/ledger?take=${encodeURIComponent(e.take_id)}&lost_only=true&page_size=10000`).then((page) => {
      state.ledgerLost = page.entries || [];
      renderLedgerFinal();
    }).catch((err) => toast(err.message));
    renderLedgerFinal();
  }
  renderLedgerLive();
}

function ledgerRow(camera, cells) {
  return `<div class="row" data-camera="${esc(camera)}"><span class="label">${esc(camera)}</span>${cells.join('')}</div>`;
}

// While the take runs: each camera's frames received of those expected, from its device's counters.
function renderLedgerLive() {
  if (!state.take || state.summary || !state.status) return;
  const rows = (state.status.devices || []).filter((d) => d.camera && d.camera.take_id === state.take.id).map((d) => {
    const c = d.camera;
    const filled = c.take_frames_expected > 0 ? Math.floor(BINS * c.take_frames_received / c.take_frames_expected) : 0;
    const cells = Array.from({ length: BINS }, (_, i) => `<span class="cell ${i < filled ? 'stored' : 'pending'}"></span>`);
    return ledgerRow(d.id, cells);
  });
  if (rows.length) $('ledger').innerHTML = rows.join('');
  $('ledger').dataset.complete = 'false';
}

// Once the take has ended: each camera's slots, the lost ones red with their reasons (the ledger).
function renderLedgerFinal() {
  const s = state.summary;
  if (!s) return;
  const slots = Math.max(1, Number(s.slots));
  const rows = (s.cameras || []).map((cam) => {
    const lost = state.ledgerLost.filter((e) => e.camera_id === cam.camera_id);
    const cells = Array.from({ length: BINS }, (_, i) => {
      const inBin = lost.filter((e) => Math.floor(Number(e.slot) * BINS / slots) === i);
      const paused = (s.paused || []).some((r) => Number(r.first) <= (i * slots) / BINS && (i * slots) / BINS < Number(r.end));
      if (inBin.length) {
        const why = inBin.slice(0, 8).map((e) => `slot ${e.slot}: ${enumName(e.reason, 'LOSS_REASON_')}` +
          (e.detail ? ` (${e.detail})` : '')).join('\n') + (inBin.length > 8 ? `\n… ${inBin.length - 8} more` : '');
        return `<span class="cell lost" title="${esc(why)}"></span>`;
      }
      return `<span class="cell ${paused ? 'paused' : 'stored'}"></span>`;
    });
    return ledgerRow(cam.camera_id, cells);
  });
  $('ledger').innerHTML = rows.join('');
  $('ledger').dataset.complete = 'true';
}

function takeRequest() {
  const body = { seconds: Number($('take-seconds').value) || 1 };
  if ($('take-name').value) body.name = $('take-name').value;
  return body;
}
$('cmd-arm').addEventListener('click', () => command('/api/arm', takeRequest()));
$('cmd-capture').addEventListener('click', () => command('/api/capture', takeRequest()));
$('cmd-pause').addEventListener('click', () => command('/api/pause'));
$('cmd-resume').addEventListener('click', () => command('/api/resume'));
$('cmd-abort').addEventListener('click', () => command('/api/abort', {}, 'Abort the take? What it recorded is kept.'));
$('cmd-estop-reset').addEventListener('click', () => command('/api/estop/reset', {},
  'Reset the emergency stop? The light nodes may be armed again.'));
$('estop').addEventListener('click', async () => {
  const reply = await command('/api/estop');
  if (reply) toast(reply.all_dark ? `every light node dark in ${Number(reply.elapsed_ms).toFixed(0)} ms` :
    'emergency stop: not every light node confirmed dark');
});

// ---- timing ----
async function refreshTiming() {
  try {
    const report = await api('/api/timing');
    $('timing-summary').textContent = `${report.errors} errors, ${report.warnings} warnings`;
    $('timing-findings').innerHTML = (report.violations || []).map((f) =>
      `<li>${enumName(f.severity, 'SEVERITY_')}: ${esc(f.message)}</li>`).join('');
    $('timing-waveform').innerHTML = `<img alt="one frame's schedule" src="/api/timing.svg?t=${Date.now()}">`;
  } catch (e) {
    $('timing-summary').textContent = e.message;
  }
}

// ---- takes ----
// A take's processing: per stage of its last graph run (done, or its state and units up to date); else the stages with
// results.
function processingCell(t) {
  const stages = t.processing || [];
  if (!stages.length) return esc((t.processed || []).join(', ')) || '—';
  return stages
      .map((p) => {
        const name = enumName(p.stage, 'PROCESSING_STAGE_').toLowerCase();
        const state = enumName(p.state, 'STAGE_PROCESSING_STATE_').toLowerCase();
        const count = `${Number(p.up_to_date || 0)}/${Number(p.units || 0)}`;
        return `<span class="stage-${esc(state)}" title="${esc(state)}: ${count} up to date">${esc(name)} ${
            state === 'done' ? '✓' : `${esc(state)} ${count}`}</span>`;
      })
      .join(', ');
}
// ---- takes ----
async function refreshTakes() {
  try {
    const list = await api('/api/takes');
    $('takes-root').textContent = list.take_root || '';
    $('takes-table').tBodies[0].innerHTML =
        (list.takes || [])
            .slice()
            .reverse()
            .map(
                (t) => `<tr data-take="${esc(t.id)}"><td><a href="#/takes" data-take="${esc(t.id)}">${esc(t.id)}</a></td>` +
                           `<td>${esc(t.name)}</td>` +
                    `<td>${enumName(t.state, 'TAKE_STATE_')}</td><td>${enumName(t.outcome, 'TAKE_OUTCOME_')}</td>` +
                    `<td>${t.frames_stored}/${t.frames_expected}</td><td>${
                           (Number(t.size_bytes) / 1e6).toFixed(1)} MB</td>` +
                    `<td class="processed">${processingCell(t)}</td>` +
                    '<td class="selftest" title="click the take for its self-test"></td></tr>')
            .join('');
  } catch (e) {
    toast(e.message);
  }
}
$('takes-table').addEventListener('click', async (ev) => {
  const id = ev.target.dataset.take;
  if (!id) return;
  const t = await api(`/api/take?id=${encodeURIComponent(id)}`);
  const bad = (t.alignment || []).filter((a) => !a.ok);
  const row = document.querySelector(`tr[data-take="${id}"] .selftest`);
  if (row) row.textContent = (t.alignment || []).length ? (bad.length ? `${bad.length} camera(s) failed` : 'passed') : 'none';
  $('take-detail').textContent = JSON.stringify(t, null, 2);
});

// ---- alarms ----
async function refreshAlarms() {
  try {
    state.alarms = await api('/api/alarms');
  } catch (e) {
    return;
  }
  renderAlarms();
}

function onAlarm(a) {
  state.alarms.active = state.alarms.active.filter((x) => x.id !== a.id);
  if (a.active) state.alarms.active.unshift(a);
  state.alarms.history = [a, ...state.alarms.history.filter((x) => x.id !== a.id)].slice(0, 200);
  renderAlarms();
}

function renderAlarms() {
  const unacked = state.alarms.active.filter((a) => !a.acked_unix_ms).length;
  $('alarm-count').textContent = unacked ? `${unacked} alarm${unacked > 1 ? 's' : ''}` : 'no alarms';
  $('alarm-count').className = `pill ${unacked ? 'bad' : 'ok'}`;
  const operator = state.me && state.me.role === 'operator';
  $('alarms-active').tBodies[0].innerHTML = state.alarms.active.map((a) =>
    `<tr class="active ${a.acked_unix_ms ? 'acked' : ''}" data-alarm="${a.id}" data-key="${esc(a.key)}">` +
    `<td>${ms(a.raised_unix_ms)}</td><td>${esc(a.kind)}</td><td>${esc(a.source)}</td><td>${esc(a.message)}</td>` +
    `<td>${a.acked_unix_ms ? `${esc(a.acked_by)} ${ms(a.acked_unix_ms)}` : ''}</td>` +
    `<td>${!a.acked_unix_ms && operator ? `<button type="button" data-ack="${a.id}">Acknowledge</button>` : ''}</td></tr>`).join('');
  $('alarms-history').tBodies[0].innerHTML = state.alarms.history.map((a) =>
    `<tr data-alarm="${a.id}"><td>${ms(a.raised_unix_ms)}</td><td>${ms(a.cleared_unix_ms)}</td><td>${esc(a.kind)}</td>` +
    `<td>${esc(a.message)}</td><td>${a.acked_unix_ms ? `${esc(a.acked_by)} ${ms(a.acked_unix_ms)}` : ''}</td></tr>`).join('');
}
$('alarms-active').addEventListener('click', async (ev) => {
  const id = ev.target.dataset.ack;
  if (!id) return;
  // The answer is the alarm as acknowledged: shown at once (the event stream brings it to the other pages).
  const alarm = await command('/api/alarms/ack', { id: Number(id) });
  if (alarm) onAlarm(alarm);
});

// ---- log ----
const LOG_LINES = 1000;
async function refreshLog() {
  try {
    const lines = await api('/api/log');
    $('log-lines').textContent = '';
    lines.forEach(appendLog);
  } catch (e) { /* shown by the link state */ }
}
function appendLog(l) {
  const pre = $('log-lines');
  const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
  pre.append(`${l.source}: ${l.line}\n`);
  while (pre.childNodes.length > LOG_LINES) pre.removeChild(pre.firstChild);
  if (atEnd) pre.scrollTop = pre.scrollHeight;
}

// ---- routing ----
function route() {
  const name = (location.hash.replace('#/', '') || 'stage').split('?')[0];
  for (const p of document.querySelectorAll('.page')) p.classList.toggle('current', p.id === `page-${name}`);
  for (const a of document.querySelectorAll('nav a')) a.classList.toggle('current', a.getAttribute('href') === `#/${name}`);
  clearInterval(state.previewTimer);
  if (name === 'previews') {
    refreshPreview();
    state.previewTimer = setInterval(() => { if ($('preview-live').checked) refreshPreview(); }, 1000);
  }
  if (name === 'timing') refreshTiming();
  if (name === 'takes') refreshTakes();
  if (name === 'alarms') refreshAlarms();
}
window.addEventListener('hashchange', route);
start();
