// orbitct console: every page talks to the REST API with the session cookie and its CSRF token.
// No framework and no build step; data is put into the page as text (never as HTML), so API content cannot inject markup.
'use strict';

const $ = (sel, root = document) => root.querySelector(sel);
const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));
const CSRF = (document.querySelector('meta[name="csrf-token"]') || {}).content || '';
const FINAL = ['complete', 'aborted', 'failed', 'interrupted', 'succeeded', 'cancelled'];

class ApiError extends Error {
  constructor(message, status) { super(message); this.status = status; }
}

/** Call the REST API; JSON in and out (or the raw response with raw: true); errors become ApiError with the API's message. */
async function api(method, path, body, { raw = false, signIn = true } = {}) {
  const options = { method, headers: {}, credentials: 'same-origin' };
  if (method !== 'GET') options.headers['X-CSRF-Token'] = CSRF;
  if (body instanceof Blob) { options.headers['Content-Type'] = 'application/octet-stream'; options.body = body; }  // a file, as is
  else if (body !== undefined) { options.headers['Content-Type'] = 'application/json'; options.body = JSON.stringify(body); }
  let response;
  try { response = await fetch(path, options); } catch (exc) { throw new ApiError('the service does not answer (' + exc.message + ')', 0); }
  if (response.status === 401 && signIn && document.body.dataset.page !== 'sign-in') {
    location.assign('/sign-in?next=' + encodeURIComponent(location.pathname));
    throw new ApiError('signed out: sign in again', 401);
  }
  if (!response.ok) {
    let message = response.status + ' ' + response.statusText;
    try {
      const e = await response.json();
      message = e.message || message;
      const extra = (e.details || []).filter((d) => !message.includes(d.reason)).map((d) => d.field + ': ' + d.reason);
      if (extra.length) message += ' (' + extra.join('; ') + ')';
    } catch (_) { /* not JSON */ }
    throw new ApiError(message, response.status);
  }
  if (raw) return response;
  if (response.status === 204) return null;
  return (response.headers.get('content-type') || '').includes('json') ? response.json() : response.text();
}

/** An element with attributes and children (strings become text nodes). */
function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === 'class') node.className = v; else if (k === 'text') node.textContent = v;
    else if (k.startsWith('on')) node.addEventListener(k.slice(2), v); else node.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) node.append(c instanceof Node ? c : String(c));
  return node;
}

// a duration as a person reads it (as the CLI says it): '40 s', '12 min', '3.5 h'
function duration(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

function fmt(v, digits = 3) {
  if (v === null || v === undefined) return '—';
  if (typeof v === 'boolean') return v ? 'yes' : 'no';
  if (typeof v === 'number') return Number.isInteger(v) ? String(v) : String(Number(v.toPrecision(digits)));
  if (Array.isArray(v)) return v.length ? v.map((x) => fmt(x, digits)).join(', ') : 'none';
  if (typeof v === 'object') {
    const entries = Object.entries(v);
    return entries.length ? entries.map(([k, x]) => k + ' ' + fmt(x, digits)).join(', ') : 'none';
  }
  return String(v);
}

function label(key) { return key.replace(/_utc$/, ' (UTC)').replace(/_/g, ' ').replace(/ mm$/, ' (mm)').replace(/ deg$/, ' (deg)').replace(/ px$/, ' (px)').replace(/ s$/, ' (s)'); }

function facts(dl, entries) {
  dl.replaceChildren(...entries.filter(([, v]) => v !== undefined).flatMap(([k, v]) => [el('dt', { text: label(k) }), el('dd', { text: fmt(v) })]));
}

function badge(node, state) { node.textContent = state; node.className = 'badge ' + state; }
// a result's quality verdict: passed (green), passed with warnings (amber), failed (red); never green when failed
function verdictBadge(v) {
  if (!v) return null;
  const said = (v.reasons && v.reasons.length ? v.reasons : v.warnings || []).join('; ');
  return el('span', { class: 'badge verdict ' + v.status, text: v.label, title: said, 'data-verdict': v.status });
}
function stateCell(j) {
  // a job's state, its verdict beside it when the verdict says more than the state does
  const cell = el('td', {}, el('span', { class: 'badge ' + j.state, text: j.state }));
  if (j.verdict && !(j.state === 'succeeded' && j.verdict.status === 'passed')) cell.append(' ', verdictBadge(j.verdict));
  return cell;
}

/** The error slot next to where an action was taken. */
function errorSlot(node) {
  const scope = node.closest('fieldset, form, .actions, .card, section, .latch, main') || document.body;
  return $('.error', scope) || $('main .error');
}

/** Run an action from a button: disabled while it runs, its error shown beside it. */
async function act(button, fn) {
  const slot = errorSlot(button);
  if (slot) slot.textContent = '';
  button.disabled = true;
  try { return await fn(); } catch (exc) { if (slot) slot.textContent = exc.message; else alert(exc.message); return undefined; }
  finally { button.disabled = false; }
}

/** Server-sent events with named handlers; the browser resumes after the last id on reconnect. */
function listen(path, handlers) {
  const source = new EventSource(path, { withCredentials: true });
  for (const [name, fn] of Object.entries(handlers)) source.addEventListener(name, (ev) => fn(JSON.parse(ev.data), ev));
  return source;
}

function every(ms, fn) { fn(); return setInterval(() => { if (!document.hidden) fn(); }, ms); }

// ---------------------------------------------------------------- on every page: stop, latch, sign-out
function initFrame() {
  const stop = $('#estop');
  const press = async () => {
    const notice = $('#stop-result');
    notice.hidden = false;
    notice.textContent = 'Stopping the bench…';
    try {
      // an expired session must not take the page away from a failed stop: the failure stays on screen
      const r = await api('POST', '/stop', { reason: 'emergency stop from the web console' }, { signIn: false });
      notice.textContent = (r.halted ? 'Stopped and verified: ' : 'STOP NOT VERIFIED: ') + r.message
        + (r.scan_aborted ? ' Scan ' + r.scan_aborted + ' aborted.' : '');
      notice.className = r.halted ? 'notice' : 'notice error';
    } catch (exc) {
      notice.textContent = 'The stop request failed: ' + exc.message + '. Use the hardware stop button.';
      notice.className = 'notice error';
    }
    refreshLatch();
  };
  stop.addEventListener('click', press);
  document.addEventListener('keydown', (ev) => { if (ev.key === 'Escape' && !ev.repeat) { ev.preventDefault(); press(); } });
  $('#sign-out').addEventListener('click', async () => {
    try { await api('POST', '/session/sign-out'); } finally { location.assign('/sign-in'); }
  });
  const reset = $('#reset-stop');
  if (reset) {
    reset.addEventListener('click', () => act(reset, async () => {
      await api('POST', '/stop/reset', { note: $('#reset-note').value });
      $('#stop-result').hidden = true;
      await refreshLatch();
    }));
  }
  refreshLatch();
  listen('/stop/events', { stop: refreshLatch, reset: refreshLatch });
}

async function refreshLatch() {
  try {
    const s = await api('GET', '/stop');
    $('#latch').hidden = !s.latched;
    $('#latch-text').textContent = s.latched ? `Since ${s.since_utc} by ${s.by}: ${s.reason}. No motion or X-rays until it is reset.` : '';
    document.body.classList.toggle('latched', s.latched);
    document.dispatchEvent(new Event('latch'));
  } catch (_) { /* the next event or page load tries again */ }
}

// ---------------------------------------------------------------- sign-in
function pageSignIn() {
  const form = $('#sign-in-form');
  form.addEventListener('submit', (ev) => {
    ev.preventDefault();
    act($('button', form), async () => {
      const token = $('#token').value.trim();
      $('#token').value = '';
      await api('POST', '/session', { token });
      location.assign(document.body.dataset.next || '/console/bench');
    });
  });
}

// ---------------------------------------------------------------- bench
async function pageBench() {
  const box = $('#devices');
  let devices;
  try { devices = await api('GET', '/devices'); } catch (exc) { $('#bench-error').textContent = exc.message; box.replaceChildren(); return; }
  box.replaceChildren();
  for (const dev of devices) {
    const card = $('#device-card').content.firstElementChild.cloneNode(true);
    card.dataset.device = dev.name;
    $('.name', card).textContent = dev.name;
    $('.model', card).textContent = `${dev.model} · serial ${dev.serial}${dev.uri ? ' · ' + dev.uri : ''}`;
    const move = $('form.move', card);
    const ref = $('.reference', card);
    if (ref) {
      ref.hidden = dev.axes.length === 0;
      ref.addEventListener('click', () => act(ref, async () => { render(card, await api('POST', `/devices/${dev.name}/reference`)); }));
    }
    if (move && dev.axes.length) {
      move.hidden = false;
      $('.axes', move).replaceChildren(...dev.axes.map((a) => el('label', {},
        `${a.name} (${a.unit}, ${a.low} to ${a.high})`,
        el('input', { type: 'number', step: 'any', min: a.low, max: a.high, name: a.name, 'aria-label': `target of axis ${a.name} in ${a.unit}` }))));
      move.addEventListener('submit', (ev) => {
        ev.preventDefault();
        const targets = {};
        for (const input of $$('input', move)) if (input.value !== '') targets[input.name] = Number(input.value);
        act($('button', move), async () => {
          if (!Object.keys(targets).length) throw new ApiError('enter a target for at least one axis');
          render(card, await api('POST', `/devices/${dev.name}/move`, { targets }));
        });
      });
    }
    const fault = $('.reset-fault', card);
    if (fault) fault.addEventListener('click', () => act(fault, async () => { render(card, await api('POST', `/devices/${dev.name}/reset-fault`)); }));
    box.append(card);
  }
  every(2000, () => devices.forEach(async (dev) => {
    const card = $(`[data-device="${dev.name}"]`, box);
    try { render(card, await api('GET', `/devices/${dev.name}`)); } catch (exc) { $('.error', card).textContent = exc.message; }
  }));
  // the controls that move or switch something are off, with the reason, while the stop is latched or a scan runs
  let busy = null;
  const gate = () => {
    const why = document.body.classList.contains('latched') ? 'the emergency stop is latched: an operator resets it in the red banner first'
      : busy ? `scan "${busy.name || busy.id}" is ${busy.state}: wait for it to end, or abort it on its page` : '';
    $('#bench-gate').hidden = !why;
    $('#bench-gate').textContent = why ? 'Controls are off because ' + why + '.' : '';
    for (const control of $$('.device .reference, .device .reset-fault, .device form.move button, .device form.move input')) {
      control.disabled = Boolean(why);
      control.title = why ? 'Off: ' + why : '';
    }
  };
  document.addEventListener('latch', gate);
  every(2000, async () => {
    try { busy = (await api('GET', '/scans?limit=5')).find((s) => ['queued', 'running', 'paused'].includes(s.state)) || null; } catch (_) { busy = null; }
    gate();
  });

  function render(card, reading) {
    // the named state (red: latched, fault, moving, exposing; green: on target, referenced, ready), then each axis
    // with its unit and soft limits, then the other readings with their units
    const status = $('.status', card);
    status.textContent = reading.status;
    status.className = `status tone-${reading.tone}`;
    $('.why', card).textContent = reading.why;
    const mark = (ok) => el('td', { class: ok ? 'yes' : 'no', text: ok ? '✔' : '✘' });
    const axes = $('table.axes', card);
    axes.hidden = !reading.axes.length;
    card.classList.toggle('has-axes', reading.axes.length > 0);
    $('tbody', axes).replaceChildren(...reading.axes.map((a) => el('tr', {},
      el('th', { text: a.axis }), el('td', { text: a.position }), el('td', { text: a.target }), el('td', { text: a.limits }),
      mark(a.referenced), mark(a.on_target))));
    $('table.state tbody', card).replaceChildren(...reading.readings.map((r) =>
      el('tr', {}, el('th', { text: r.label }), el('td', { text: r.value }))));
    const fault = $('.reset-fault', card);
    if (fault) fault.hidden = reading.status !== 'fault';
  }
}

// ---------------------------------------------------------------- new scan
async function pageScanNew() {
  const form = $('#scan-form');
  const kinds = await api('GET', '/orbits');
  const select = $('#orbit');
  select.replaceChildren(...kinds.map((k) => el('option', { value: k.kind, text: k.kind })));
  const pick = () => {
    const kind = kinds.find((k) => k.kind === select.value);
    $('#orbit-description').textContent = kind.description;
    const props = kind.parameters.properties || {};
    const required = kind.parameters.required || [];
    $('#frames').placeholder = props.n_frames && props.n_frames.default ? `default ${props.n_frames.default}` : "the orbit's default";
    $('#params').replaceChildren(...Object.entries(props).filter(([name]) => name !== 'n_frames').map(([name, p]) => paramInput(name, p, required.includes(name))));
    $('#check-result').hidden = true;
  };
  select.addEventListener('change', pick);
  pick();
  detector();

  const body = () => {
    const params = {};
    for (const input of $$('#params [data-param]')) {
      if (input.type === 'checkbox') { params[input.dataset.param] = input.checked; continue; }
      if (input.value === '') continue;
      params[input.dataset.param] = input.dataset.kind === 'json' ? JSON.parse(input.value) : input.type === 'number' ? Number(input.value) : input.value;
    }
    const frames = $('#frames').value;
    const scan = { name: $('#scan-name').value, orbit: select.value, params, frames: frames === '' ? null : Number(frames),
                   errors: $('#errors').value, seed: Number($('#seed').value || 0), mode: $('#mode').value };
    if ($('#frame-rate').value) scan.frame_rate_hz = Number($('#frame-rate').value);
    if ($('#calibrate-live').checked) {
      scan.calibrate = 'live';
      if ($('#bb-diameter').value) scan.bb_diameter_mm = Number($('#bb-diameter').value);
      scan.abort_on = $$('#abort-on input:checked').map((box) => box.value);
    }
    return scan;
  };
  $('#check').addEventListener('click', (ev) => act(ev.currentTarget, async () => {
    const scan = body();
    const spec = { kind: scan.orbit, params: { ...scan.params, ...(scan.frames ? { n_frames: scan.frames } : {}) } };
    const summary = await api('POST', '/orbits/validate', spec);
    $('#check-result').hidden = false;
    facts($('#orbit-summary'), [['frames', summary.n_frames], ['segments', summary.n_segments], ['rotation_deg', summary.rotation_deg],
      ['tilt_deg', summary.tilt_deg], ['step per frame (rotation, tilt) (deg)', summary.step_deg]]);
    const png = await api('POST', '/orbits/preview', spec, { raw: true });
    const img = $('#preview');
    img.src = URL.createObjectURL(await png.blob());
    img.hidden = false;
    const pf = $('#preflight');
    try {
      const r = await api('POST', '/scans/preflight', scan);
      pf.textContent = '✔ Pre-flight passed: ' + r.message;
      pf.className = 'yes';
    } catch (exc) {
      pf.textContent = '✘ Pre-flight refused: ' + exc.message;
      pf.className = 'no';
    }
  }));
  form.addEventListener('submit', (ev) => {
    ev.preventDefault();
    act($('#start'), async () => {
      const scan = await api('POST', '/scans', body());
      location.assign(`/console/scans/${scan.id}`);
    });
  });

  async function detector() {
    try {
      const devices = await api('GET', '/devices');
      const det = devices.find((d) => /detector|panel/i.test(d.name));
      const xray = devices.find((d) => /xray|generator/i.test(d.name));
      const entries = [];
      if (det) {
        const s = (await api('GET', `/devices/${det.name}`)).state;
        entries.push(['panel', `${det.name} (${det.model})`], ['pixels (rows, columns)', s.shape], ['binning', s.binning]);
      }
      if (xray) {
        const s = (await api('GET', `/devices/${xray.name}`)).state;
        entries.push(['generator', `${xray.name} (${xray.model})`], ['tube voltage (kV)', s.kv], ['tube current (mA)', s.ma],
          ['exposure per frame (ms)', s.exposure_ms]);
      }
      const dl = el('dl', { class: 'facts' });
      facts(dl, entries);
      $('#detector').replaceChildren(dl, el('p', { class: 'help', text: 'Panel size, binning and X-ray technique come from the bench configuration; the frame rate can be set per scan.' }));
    } catch (exc) { $('#detector').textContent = exc.message; }
  }
}

function paramInput(name, p, required) {
  const schema = p.anyOf ? (p.anyOf.find((x) => x.type && x.type !== 'null') || p) : p;
  const id = 'param-' + name;
  const text = label(name) + (p.description ? ` — ${p.description}` : '');
  let input;
  if (schema.type === 'boolean') {
    input = el('input', { id, type: 'checkbox', 'data-param': name });
    input.checked = p.default === true;
    return el('label', { class: 'check', for: id }, input, text);
  }
  if (schema.enum) {
    input = el('select', { id, 'data-param': name }, ...(required ? [] : [el('option', { value: '', text: 'default' })]),
      ...schema.enum.map((v) => el('option', { value: v, text: v, selected: v === p.default })));
  } else if (schema.type === 'number' || schema.type === 'integer') {
    input = el('input', { id, type: 'number', step: schema.type === 'integer' ? 1 : 'any', 'data-param': name, required,
      min: schema.minimum ?? schema.exclusiveMinimum, max: schema.maximum ?? schema.exclusiveMaximum });
    if (p.default !== undefined && p.default !== null) input.value = p.default;
  } else {
    input = el('input', { id, 'data-param': name, 'data-kind': schema.type === 'string' ? 'text' : 'json', required,
      placeholder: schema.type === 'string' ? '' : 'JSON, e.g. [[0, 0], [90, 10]]' });
    if (p.default !== undefined && p.default !== null) input.value = typeof p.default === 'string' ? p.default : JSON.stringify(p.default);
  }
  return el('div', {}, el('label', { for: id, text }), input);
}

// ---------------------------------------------------------------- scans
function calibrationCell(c) {
  // a scan's latest calibration: its verdict once it has one, else the job's state; links to its report
  if (!c) return el('td', { class: 'muted', text: 'none' });
  const mark = c.verdict ? verdictBadge(c.verdict) : el('span', { class: 'badge ' + c.state, text: c.state });
  return el('td', { class: 'calibration' }, c.job_id ? el('a', { href: `/console/calibrations/${c.job_id}`, title: 'the calibration report' }, mark) : mark,
    c.state === 'live' ? el('span', { class: 'muted', text: ' (live)' }) : null);
}

function pageScans() {
  const load = async () => {
    const state = $('#state').value;
    const text = $('#text').value.toLowerCase();
    try {
      const rows = await api('GET', '/scans?limit=200' + (state ? '&state=' + state : ''));
      $('#scan-table tbody').replaceChildren(...rows.filter((s) => !text || (s.name + ' ' + s.id).toLowerCase().includes(text)).map((s) => el('tr', {},
        el('td', {}, el('a', { href: `/console/scans/${s.id}`, text: s.name || '(no name)' })), el('td', {}, el('code', { text: s.id })),
        el('td', { text: s.orbit }), el('td', {}, el('span', { class: 'badge ' + s.state, text: s.state })),
        el('td', { text: frameCount(s, ' / ') }), calibrationCell(s.calibration),
        el('td', { text: s.owner }), el('td', { text: s.created_utc.slice(0, 19).replace('T', ' ') }))));
      if (!$('#scan-table tbody').children.length) $('#scan-table tbody').append(el('tr', {}, el('td', { colspan: 8, class: 'muted', text: 'No scans match.' })));
      $('main > .error').textContent = '';
    } catch (exc) { $('main > .error').textContent = exc.message; }
  };
  $('#state').addEventListener('change', load);
  $('#text').addEventListener('input', load);
  every(3000, load);
}

function frameCount(s, of) {
  // every frame (projections, darks and flats, as the scan counts them) and, once the file says, its projections:
  // the views a calibration and a reconstruction count
  const kinds = (s.summary || {}).frames_by_kind;
  const views = kinds && kinds.projection !== undefined ? ` (${kinds.projection} projections, ${(kinds.dark || 0) + (kinds.flat || 0)} darks and flats)` : '';
  return `${s.frames_done}${of}${s.frames_total}${views}`;
}

// ---------------------------------------------------------------- one scan: live, summary, jobs
async function pageScan() {
  const id = document.body.dataset.scan;
  let scan;
  let events = null;
  let framePoll = null;
  const show = (s) => {
    scan = s;
    $('#scan-name').textContent = s.name || s.id;
    badge($('#scan-state'), s.state);
    scanFacts(s);
    $('#scan-reason').hidden = !s.reason;
    $('#scan-reason').textContent = s.reason;
    const live = !FINAL.includes(s.state);
    $('#live').hidden = !live && !events;
    if (s.progress && Object.keys(s.progress).length) progress(s.progress);
    buttons(s.state);
    if (!live) ended(s);
  };
  const scanFacts = (s) => {
    facts($('#scan-facts'), [['id', s.id], ['orbit', s.orbit], ['owner', s.owner], ['created_utc', s.created_utc],
      ['started_utc', s.started_utc], ['finished_utc', s.finished_utc], ['frames', frameCount(s, ' of ')]]);
    if (s.calibration) $('#scan-facts').append(el('dt', { text: 'calibration' }), el('dd', { id: 'scan-calibration' }, ...calibrationCell(s.calibration).childNodes));
    calibrationNotice(s.calibration);
  };
  const calibrationNotice = (c) => {
    // a failed calibrated geometry: say so where a reconstruction is started, and ask for the override explicitly
    const note = $('#rec-failed-geometry');
    if (!note) return;
    const failed = Boolean(c && c.verdict && c.verdict.status === 'failed');
    note.hidden = !failed;
    if (failed) $('#rec-failed-reasons').textContent = (c.verdict.reasons || []).join('; ');
    if (!failed) $('#rec-accept-failed').checked = false;
  };
  let expected = null;  // how long the scan's frames take in all, once the scan has said so
  const progress = (p) => {
    if (p.stage === 'duration') { expected = p.metrics.expected_s; return; }
    if (p.expected_s) expected = p.expected_s;
    if (scan && p.total) { scan.frames_done = p.done; scan.frames_total = p.total; scanFacts(scan); }
    const bar = $('#scan-progress');
    bar.max = Math.max(p.total || 1, 1);
    bar.value = p.done || 0;
    const m = p.metrics || {};
    const parts = [`${p.stage || 'scan'}: frame ${p.done} of ${p.total}`];
    if (m.rate_fps) parts.push(`${m.rate_fps.toFixed(1)} frames/s`);
    if (m.time_left_s !== undefined && m.time_left_s !== null) parts.push(`${Math.round(m.time_left_s)} s left`);
    if (expected) parts.push(`about ${duration(expected)} in all`);
    if (p.message) parts.push(p.message);
    $('#scan-progress-text').textContent = parts.join(' · ');
  };
  const liveCalibration = (d) => {
    const m = d.metrics || {};
    const parts = [`live calibration: projection ${d.done} of ${d.total}`, `${m.bbs ?? '?'} BBs`];
    if (m.rpe_mm !== undefined) parts.push(`RPE ${m.rpe_mm.toFixed(3)} mm (mean ${m.rpe_mean_mm.toFixed(3)})`);
    if (m.predicted_px !== undefined) parts.push(`predicted error ${m.predicted_px.toFixed(2)} px`);
    return parts.join(' · ');
  };
  const buttons = (state) => {
    if (!$('#pause')) return;
    $('#pause').hidden = state !== 'running';
    $('#resume').hidden = state !== 'paused';
    $('#abort').hidden = FINAL.includes(state);
  };
  const ended = (s) => {
    if (framePoll) { clearInterval(framePoll); framePoll = null; }
    $('#results').hidden = false;
    const summary = s.summary || {};
    facts($('#scan-summary'), Object.entries(summary).filter(([k]) => k !== 'timing').map(([k, v]) => [k, v]));
    $('#download').hidden = s.state === 'running' || s.state === 'queued';
    $('#jobs').hidden = s.state !== 'complete';
    if (s.state === 'complete') jobs();
  };
  if ($('#pause')) {
    $('#pause').addEventListener('click', (ev) => act(ev.currentTarget, async () => show(await api('POST', `/scans/${id}/pause`))));
    $('#resume').addEventListener('click', (ev) => act(ev.currentTarget, async () => show(await api('POST', `/scans/${id}/resume`))));
    $('#abort').addEventListener('click', (ev) => act(ev.currentTarget, async () => {
      if (!confirm('Abort this scan? Axes halt and X-rays go off; the file keeps the frames so far.')) return;
      show(await api('POST', `/scans/${id}/abort`, { reason: 'aborted from the web console' }));
    }));
  }
  try { show(await api('GET', `/scans/${id}`)); } catch (exc) { $('#scan-error').textContent = exc.message; return; }
  if (!FINAL.includes(scan.state)) {
    $('#live').hidden = false;
    events = listen(`/scans/${id}/events`, {
      progress: (p) => progress(p),
      state: (d) => { if (d.state) { badge($('#scan-state'), d.state); buttons(d.state); } },
      warning: (d) => $('#scan-warnings').append(el('li', { text: d.message || JSON.stringify(d) })),
      calibration: (d) => { $('#live-calibration-text').textContent = liveCalibration(d); },
      end: async () => { events.close(); show(await api('GET', `/scans/${id}`)); },
    });
    framePoll = every(1000, latestFrame);
  }

  async function latestFrame() {
    try {
      const f = await api('GET', `/scans/${id}/frames/latest`);
      if (!f || !f.pixels) return;
      const canvas = $('#frame');
      canvas.width = f.width; canvas.height = f.height;
      const ctx = canvas.getContext('2d');
      const img = ctx.createImageData(f.width, f.height);
      const bytes = Uint8Array.from(atob(f.pixels), (c) => c.charCodeAt(0));
      for (let i = 0; i < bytes.length; i++) { img.data[4 * i] = img.data[4 * i + 1] = img.data[4 * i + 2] = bytes[i]; img.data[4 * i + 3] = 255; }
      ctx.putImageData(img, 0, 0);
      ctx.strokeStyle = '#ff3b30'; ctx.lineWidth = 1.5;
      for (const [u, v] of f.bbs || []) { ctx.beginPath(); ctx.arc(u * f.scale, v * f.scale, 5, 0, 2 * Math.PI); ctx.stroke(); }
      $('#frame-caption').textContent = `${f.kind} frame ${f.index}` + (f.bbs ? ` · ${f.bbs.length} BBs detected` : '');
    } catch (_) { /* no frame yet */ }
  }

  async function jobs() {
    const list = await api('GET', `/jobs?scan_id=${id}`);
    const latest = list.find((j) => j.kind === 'calibration');
    if (latest) { scan.calibration = { job_id: latest.id, state: latest.state, verdict: latest.verdict }; scanFacts(scan); }
    $('#scan-jobs tbody').replaceChildren(...list.map((j) => el('tr', {},
      el('td', { text: j.kind }), el('td', {}, el('code', { text: j.id })), stateCell(j),
      el('td', { text: j.progress && j.progress.total ? `${j.progress.stage} ${j.progress.done}/${j.progress.total}` : '' }),
      el('td', { text: fmt(j.params) }),
      el('td', {}, j.kind === 'calibration' ? el('a', { href: `/console/calibrations/${j.id}`, text: 'report' })
        : j.state === 'succeeded' ? el('a', { href: `/console/reconstructions/${j.id}`, text: 'viewer' }) : ''))));
    if (list.some((j) => !FINAL.includes(j.state))) setTimeout(jobs, 1500);
  }
  const cal = $('#calibrate-form');
  if (cal) {
    cal.addEventListener('submit', (ev) => {
      ev.preventDefault();
      act($('#calibrate'), async () => {
        const body = { scan_id: id, method: $('#cal-method').value };
        if ($('#cal-intrinsics').value) body.intrinsics = $('#cal-intrinsics').value;
        await api('POST', '/calibrations', body);
        await jobs();
      });
    });
    $('#reconstruct-form').addEventListener('submit', (ev) => {
      ev.preventDefault();
      act($('#reconstruct'), async () => {
        const algorithm = $('#rec-algorithm').value;
        const body = { scan_id: id, algorithm, geometry: $('#rec-geometry').value, mar: $('#rec-mar').checked, overwrite: $('#rec-overwrite').checked };
        if ($('#rec-accept-failed').checked && body.geometry === 'calibrated') body.accept_failed_geometry = true;
        const n = $('#rec-shape').value;
        if (n) body.shape = [Number(n), Number(n), Number(n)];
        if (algorithm === 'pwls') body.iterations = Number($('#rec-iterations').value);
        await api('POST', '/reconstructions', body);
        await jobs();
      });
    });
  }
}

// ---------------------------------------------------------------- calibration report
async function pageCalibration() {
  const id = document.body.dataset.job;
  const show = async () => {
    let job;
    try { job = await api('GET', `/calibrations/${id}`); } catch (exc) { $('main > .error').textContent = exc.message; return; }
    badge($('#job-state'), job.state);
    facts($('#job-facts'), [['scan', job.scan_id], ['parameters', job.params], ['owner', job.owner], ['started_utc', job.started_utc],
      ['finished_utc', job.finished_utc], ['reason', job.reason || undefined]]);
    if (!FINAL.includes(job.state)) {
      const bar = $('#job-progress');
      bar.hidden = false;
      let expected = null;  // how long the job takes in all, once it has said so
      const source = listen(`/jobs/${id}/events`, {
        progress: (p) => {
          if (p.stage === 'duration') { expected = p.metrics.expected_s; return; }
          bar.max = Math.max(p.total || 1, 1); bar.value = p.done || 0;
          const about = expected || p.expected_s;
          $('#job-progress-text').textContent = `${p.stage} ${p.done} of ${p.total} ${p.message || ''}` + (about ? ` · about ${duration(about)} in all` : '');
        },
        end: () => { source.close(); bar.hidden = true; show(); },
      });
      return;
    }
    if (job.state !== 'succeeded' && !job.verdict) return;  // a report exists once it succeeded or failed its check
    const result = job.result || {};
    const quality = result.quality || {};
    const v = job.verdict || { status: 'failed', label: 'failed', reasons: ['this calibration has no quality verdict'], warnings: [] };
    $('#verdict').hidden = false;
    $('#verdict-badge').replaceChildren(verdictBadge(v));
    const figures = quality.predicted_px_median === undefined ? '' : ` Predicted field-of-view error ${fmt(quality.predicted_px_median)} px (median), ${fmt(quality.predicted_px_max)} px (worst view, frame ${quality.worst_frame}); limit ${fmt(quality.max_predicted_px)} px; centroid noise ${fmt(quality.centroid_noise_px)} px.`;
    const text = v.status === 'failed' ? `Failed: ${v.reasons.join('; ')}. Do not use this geometry: calibrate again, or reconstruct from the nominal geometry.`
      : v.status === 'passed_with_warnings' ? `Passed with warnings: read them below before using this geometry.` : 'Passed.';
    $('#verdict-text').textContent = text + figures + (quality.views ? ` Views: ${fmt(quality.views)}.` : '');
    $('#verdict-text').className = { passed: 'yes', passed_with_warnings: 'warn', failed: 'no' }[v.status];
    $('#cal-warnings').replaceChildren(...(result.warnings || []).map((w) => el('li', { text: w })));
    const rpe = await api('GET', `/calibrations/${id}/rpe`);
    $('#table1').hidden = false;
    $('#table1 > table tbody').replaceChildren(...Object.entries(rpe.table).map(([k, v]) => el('tr', {}, el('th', { text: label(k) }), el('td', { text: fmt(v, 4) }))));
    $('#iterations tbody').replaceChildren(...rpe.iterations.map((it) => el('tr', {}, el('td', { text: it.index }), el('td', { text: fmt(it.rpe_mean_mm, 4) }),
      el('td', { text: fmt(it.rpe_median_mm, 4) }), el('td', { text: fmt(it.rpe_std_mm, 4) }), el('td', { text: fmt(it.reproj_rms_px, 4) }))));
    const files = await api('GET', `/calibrations/${id}/files`);
    $('#figures').hidden = false;
    $('#figures .figures').replaceChildren(...files.filter((f) => f.endsWith('.png')).map((f) => el('figure', {},
      el('img', { src: `/calibrations/${id}/files/${encodeURIComponent(f)}`, alt: f.replace(/[_.]/g, ' ') }), el('figcaption', { text: f }))));
    $('#figures .files').replaceChildren(...files.map((f) => el('li', {}, el('a', { href: `/calibrations/${id}/files/${encodeURIComponent(f)}`, download: f, text: f }))));
  };
  show();
}

// ---------------------------------------------------------------- jobs
function pageJobs() {
  const mayCancel = (document.body.dataset.may || '').split(' ').includes('analysis');
  const load = async () => {
    try {
      const list = await api('GET', '/jobs?limit=200');
      $('#job-table tbody').replaceChildren(...list.map((j) => el('tr', {},
        el('td', { text: j.kind }), el('td', {}, el('code', { text: j.id })), el('td', {}, el('a', { href: `/console/scans/${j.scan_id}`, text: j.scan_id })),
        (() => { const cell = stateCell(j); if (j.reason) cell.append(el('div', { class: 'muted', text: j.reason })); return cell; })(),
        el('td', { text: j.progress && j.progress.total ? `${j.progress.stage} ${j.progress.done}/${j.progress.total}` : '' }),
        el('td', { text: j.owner }), el('td', { text: j.created_utc.slice(0, 19).replace('T', ' ') }),
        el('td', {},
          el('button', { type: 'button', text: 'Log', onclick: () => showLog(j.id) }),
          j.kind === 'calibration' ? el('a', { href: `/console/calibrations/${j.id}`, text: 'report' }) : null,
          j.kind === 'reconstruction' && j.state === 'succeeded' ? el('a', { href: `/console/reconstructions/${j.id}`, text: 'viewer' }) : null,
          mayCancel && !FINAL.includes(j.state) ? el('button', { type: 'button', class: 'danger', text: 'Cancel',
            onclick: (ev) => act(ev.currentTarget, async () => { await api('POST', `/jobs/${j.id}/cancel`); load(); }) }) : null))));
      if (!list.length) $('#job-table tbody').append(el('tr', {}, el('td', { colspan: 8, class: 'muted', text: 'No jobs yet.' })));
      $('main > .error').textContent = '';
    } catch (exc) { $('main > .error').textContent = exc.message; }
  };
  const showLog = async (jobId) => {
    const box = $('#job-log');
    box.hidden = false;
    $('.id', box).textContent = jobId;
    const lines = await api('GET', `/jobs/${jobId}/log`);
    $('pre', box).textContent = lines.map((l) => `${l.utc || ''} ${l.level || ''} ${l.message || JSON.stringify(l)}`).join('\n') || '(empty)';
  };
  every(2000, load);
}

// ---------------------------------------------------------------- BB plans
function pagePlans() {
  const sleep = (ms) => new Promise((resolve) => { setTimeout(resolve, ms); });
  /** The plan once it is no longer being made (plans are made one at a time in the background). */
  let shown = null;  // the plan last asked for: an earlier one still being polled gives way
  const made = async (id) => {
    for (;;) {
      const plan = await api('GET', `/plans/bbs/${id}`);
      if (plan.state !== 'planning' || shown !== id) return plan;
      const progress = $('#plan-progress');
      progress.hidden = false;
      $('.id', progress).textContent = id;
      $('#plan-since').textContent = new Date(plan.created).toLocaleTimeString();
      const step = plan.progress;
      $('#plan-step').textContent = (step ? `${{ count: 'BB counts', prepare: 'preparing' }[step.stage] || 'search'}: ${step.done} of ${step.total} (${step.message})`
        : 'waiting for its turn') + (plan.expected_s ? `; expected to take about ${duration(plan.expected_s)} in all` : '');
      await sleep(1000);
    }
  };
  const show = async (id) => {
    shown = id;
    const plan = await made(id);
    if (shown !== id) return;
    $('#plan-progress').hidden = true;
    if (plan.state !== 'done') throw new ApiError(`plan ${id} ${plan.state}: ${plan.reason}`, 0);
    const box = $('#plan-result');
    box.hidden = false;
    $('.id', box).textContent = id;
    const p = plan.predicted;
    const own = plan.experiment_placement;
    const shape = plan.surface.kind === 'ellipsoid' ? `ellipsoid ${plan.surface.a_mm} × ${plan.surface.b_mm} × ${plan.surface.c_mm} mm`
      : `elliptic cylinder ${plan.surface.a_mm} × ${plan.surface.b_mm} mm`;
    const surface = plan.surface.kind === 'outline' ? `outline of ${plan.surface.source}` : shape;
    const entries = [['experiment', plan.experiment], ['surface', surface], ['orbit', `${plan.orbit} (${plan.views} views)`],
      ['BBs', plan.bbs.length], ['motion errors expected', plan.motion_errors ? plan.motion_errors.profile : 'none'],
      ['predicted error px', `median ${fmt(p.predicted_px_median)}, worst ${fmt(p.predicted_px_max)}`],
      ['usable BBs per view', `at least ${p.bbs_min}, median ${fmt(p.bbs_median)}`], ['under determined views', p.under_determined],
      ['the experiment\'s own placement', `${own.bbs} BBs: worst ${fmt(own.predicted.predicted_px_max)} px, ${own.predicted.under_determined} under-determined`]];
    if (plan.hand_spiral) {
      const h = plan.hand_spiral;
      entries.push(['a hand-made spiral', `${h.bbs} BBs: median ${fmt(h.predicted.predicted_px_median)}, worst ${fmt(h.predicted.predicted_px_max)} px, ${h.predicted.under_determined} under-determined`]);
    }
    if (plan.count_suggestion) {
      const c = plan.count_suggestion;
      entries.push(['fewest BBs for target', c.n_bbs === null ? `${c.target_px} px not reached` : `${c.n_bbs} for ${c.target_px} px`]);
    }
    facts($('#plan-facts'), entries);
    $('#plan-warnings').replaceChildren(...(plan.warnings || []).map((w) => el('li', { class: 'error', text: w })));
    $('#plan-picture').src = `/plans/bbs/${id}/picture`;
    $('#plan-bbs-table tbody').replaceChildren(...plan.bbs.map((b) => el('tr', {}, el('td', { text: b.number }),
      el('td', { text: fmt(b.angle_deg, 4) }), el('td', { text: fmt(b.height_mm, 4) }), ...b.xyz_mm.map((v) => el('td', { text: fmt(v, 4) })))));
    const { id: _, state: __, ...body } = plan;
    $('#plan-json').href = URL.createObjectURL(new Blob([JSON.stringify(body, null, 1)], { type: 'application/json' }));
    $('#plan-json').download = `bb-plan-${id}.json`;
    document.body.dataset.plan = id;
  };
  const load = async () => {
    const slot = $('#plan-table').closest('section').querySelector('.error');
    try {
      const list = await api('GET', '/plans/bbs');
      $('#plan-table tbody').replaceChildren(...list.map((p) => el('tr', {},
        el('td', {}, el('a', { href: `?plan=${p.id}`, text: p.id, onclick: (ev) => { ev.preventDefault(); history.replaceState(null, '', `?plan=${p.id}`); show(p.id).catch((exc) => { slot.textContent = exc.message; }); } })),
        el('td', { title: p.reason || '' }, el('span', { class: `badge ${p.state}`, text: p.state })),
        el('td', { text: p.experiment }), el('td', { text: p.orbit }), el('td', { text: p.views }), el('td', { text: fmt(p.bbs) }),
        el('td', { text: fmt(p.predicted_px_max) }), el('td', { text: fmt(p.under_determined) }))));
      if (!list.length) $('#plan-table tbody').append(el('tr', {}, el('td', { colspan: 8, class: 'muted', text: 'No plans yet.' })));
      slot.textContent = '';
    } catch (exc) { slot.textContent = exc.message; }
  };
  const form = $('#plan-form');
  if (form) {
    const meshOption = (m) => el('option', { value: `mesh:${m.id}`, text: `mesh ${m.name} (${m.id})` });
    Promise.all([api('GET', '/surfaces'), api('GET', '/reconstructions?limit=100')]).then(([meshes, jobs]) => {
      $('#plan-surface').append(...meshes.map(meshOption), ...jobs.filter((j) => j.state === 'succeeded').map((j) => el('option', {
        value: `reconstruction:${j.id}`, text: `reconstruction ${j.id} of scan ${j.scan_id} (${j.params.algorithm}, ${j.params.geometry || 'nominal'} geometry)` })));
    }).catch((exc) => { $('.error', form).textContent = exc.message; });
    $('#plan-mesh').addEventListener('change', () => act($('#plan-make'), async () => {
      const file = $('#plan-mesh').files[0];
      if (!file) return;
      const answer = await api('POST', `/surfaces?name=${encodeURIComponent(file.name)}`, file);
      $('#plan-surface').append(meshOption(answer));
      $('#plan-surface').value = `mesh:${answer.id}`;
    }));
    form.addEventListener('submit', (ev) => {
      ev.preventDefault();
      act($('#plan-make'), async () => {
        const number = (sel) => ($(sel).value === '' ? undefined : Number($(sel).value));
        const keepOut = $('#plan-keep-out').value.split('\n').map((l) => l.trim()).filter(Boolean).map((line) => {
          const m = line.match(/^(-?[\d.]+):(-?[\d.]+),(-?[\d.]+):(-?[\d.]+)$/);
          if (!m) throw new ApiError(`keep-out "${line}": expected FROM_DEG:TO_DEG,ZMIN_MM:ZMAX_MM (e.g. 300:60,-20:10)`, 0);
          const turn = (deg) => ((deg % 360) + 360) % 360;
          const whole = Number(m[2]) - Number(m[1]) >= 360;  // 0:360, the whole turn
          return { angle_from_deg: whole ? 0 : turn(Number(m[1])), angle_to_deg: whole ? 360 : turn(Number(m[2])),
            z_min_mm: Number(m[3]), z_max_mm: Number(m[4]) };
        });
        const [kind, surfaceId] = $('#plan-surface').value.split(':');
        const surface = kind === 'mesh' ? { surface_id: surfaceId } : kind === 'reconstruction' ? { surface_reconstruction_id: surfaceId } : {};
        const shape = $('#plan-shape').value.trim();
        if (shape) surface.surface_shape = shape;
        $('#plan-make').textContent = 'Planning…';
        try {
          const queued = await api('POST', '/plans/bbs', { experiment: $('#plan-experiment').value, frames: number('#plan-frames'),
            bbs: number('#plan-bbs'), target_px: number('#plan-target'), keep_out: keepOut, detector_px: number('#plan-detector'), errors: $('#plan-errors').value,
            noise_px: number('#plan-noise'), surface_threshold_per_mm: number('#plan-surface-threshold'), ...surface });
          history.replaceState(null, '', `?plan=${queued.id}`);
          await load();
          await show(queued.id);
          await load();
        } finally { $('#plan-make').textContent = 'Plan'; }
      });
    });
  }
  const cancel = $('#plan-cancel');
  if (cancel) {
    cancel.addEventListener('click', () => act(cancel, async () => {
      await api('POST', `/plans/bbs/${$('#plan-progress .id').textContent}/cancel`);
    }));
  }
  const wanted = new URLSearchParams(location.search).get('plan');
  if (wanted && /^[0-9a-f]{12}$/.test(wanted)) show(wanted).catch((exc) => { $('#plan-table').closest('section').querySelector('.error').textContent = exc.message; });
  every(5000, load);
}

// ---------------------------------------------------------------- volume viewer
async function pageViewer() {
  const id = document.body.dataset.job;
  let job;
  try { job = await api('GET', `/reconstructions/${id}`); } catch (exc) { $('main > .error').textContent = exc.message; return; }
  $('#download-nifti').href = `/reconstructions/${id}/volume?format=nifti`;
  $('#download-npy').href = `/reconstructions/${id}/volume?format=npy`;
  $('#to-scan').href = `/console/scans/${job.scan_id}`;
  const others = (await api('GET', `/reconstructions?scan_id=${job.scan_id}`)).filter((j) => j.id !== id && j.state === 'succeeded');
  const compare = $('#compare');
  compare.append(...others.map((j) => el('option', { value: j.id, text: `${j.result.name || j.id} (${j.params.geometry})` })));
  const wanted = document.body.dataset.compare || (others.find((j) => j.params.geometry !== job.params.geometry && j.params.algorithm === job.params.algorithm) || {}).id || '';
  compare.value = wanted;
  const caption = (j) => `${j.result.name || j.id}: ${j.params.algorithm.toUpperCase()}, ${j.params.geometry} geometry, ${fmt(j.result.shape)} voxels of ${fmt(j.result.voxel_mm)} mm`;
  $('#caption-a').textContent = caption(job);
  verdictNote(job, $('#verdict-a'));
  const gl = document.createElement('canvas').getContext('webgl2');
  if (!window.niivue || !gl) { fallback(job, others.find((j) => j.id === compare.value)); return; }

  const NV = window.niivue.Niivue;
  const make = async (canvas) => {
    // the slice views carry our own labelled scale bar (niivue's ruler is an unlabelled 10 cm, cut by small fields)
    const nv = new NV({ isRuler: false, isColorbar: true, backColor: [0, 0, 0, 1], show3Dcrosshair: true, crosshairWidth: 1.5, crosshairWidthUnit: 'mm',
      fontMinPx: 16, fontSizeScaling: 0.5, fontColor: [0.9, 0.9, 0.9, 1],
      crosshairColor: [1, 0.8, 0, 0.6], rulerColor: [1, 1, 1, 0.9], loadingText: 'loading the volume...' });
    await nv.attachToCanvas(canvas);
    return nv;
  };
  const a = await make($('#gl-a'));
  let b = null;
  // a compared volume is resampled by the server onto this one's grid: the same voxels, side by side
  const load = async (nv, j, pane, onto) => {
    const grid = onto ? `&grid_of=${onto.id}` : '';
    await nv.loadVolumes([{ url: `/reconstructions/${j.id}/volume?format=nifti${grid}`, name: `${j.id}.nii.gz`, colormap: 'gray' }]);
    const h = nv.volumes[0].hdr;
    pane.dataset.grid = `${h.dims.slice(1, 4).join(' x ')} voxels of ${h.pixDims.slice(1, 4).map((v) => +v.toPrecision(4)).join(' x ')} mm`;
  };
  await load(a, job, $('#gl-a').closest('figure'));
  const vol = a.volumes[0];
  $('#wmin').value = vol.cal_min.toPrecision(4);
  $('#wmax').value = vol.cal_max.toPrecision(4);
  const viewers = () => [a, b].filter(Boolean);
  const window_ = () => {
    const lo = Number($('#wmin').value); const hi = Number($('#wmax').value);
    if (!(hi > lo)) { $('main > .error').textContent = 'the window needs "to" above "from"'; return; }
    $('main > .error').textContent = '';
    for (const nv of viewers()) { nv.volumes[0].cal_min = lo; nv.volumes[0].cal_max = hi; nv.updateGLVolume(); }
  };
  const view = () => {
    const type = { axial: 0, coronal: 1, sagittal: 2, multi: 3, '3d': 4 }[$('#view').value];
    for (const nv of viewers()) nv.setSliceType(type);
  };
  const pair = async () => {
    const other = others.find((j) => j.id === compare.value);
    $('#pane-b').hidden = !other;
    if (!other) { b = null; a.broadcastTo([]); return; }
    if (!b) b = await make($('#gl-b'));
    const same = ['voxel_mm', 'shape', 'origin_mm'].every((k) => fmt(other.result[k]) === fmt(job.result[k]));
    $('#caption-b').textContent = caption(other) + (same ? '' : `, resampled onto the first volume's grid (${fmt(job.result.shape)} voxels of ${fmt(job.result.voxel_mm)} mm)`);
    verdictNote(other, $('#verdict-b'));
    await load(b, other, $('#pane-b'), same ? null : job);
    a.broadcastTo(b, { '2d': true, '3d': true });
    b.broadcastTo(a, { '2d': true, '3d': true });
    window_(); view();
  };
  $('#wmin').addEventListener('change', window_);
  $('#wmax').addEventListener('change', window_);
  $('#view').addEventListener('change', view);
  compare.addEventListener('change', pair);
  $('#auto-window').addEventListener('click', () => {
    $('#wmin').value = vol.robust_min !== undefined ? vol.robust_min.toPrecision(4) : vol.global_min.toPrecision(4);
    $('#wmax').value = vol.robust_max !== undefined ? vol.robust_max.toPrecision(4) : vol.global_max.toPrecision(4);
    window_();
  });
  view();
  await pair();
  const bars = () => { scaleBar(a, $('#scale-a')); if (b) scaleBar(b, $('#scale-b')); };
  bars();
  setInterval(bars, 500);  // follows zoom, resizing and the view
  document.body.dataset.viewerReady = 'yes';
}

function scaleBar(nv, node) {
  // a round length (1, 2 or 5 x 10^k mm) about a fifth of the slice's width, drawn to scale and labelled in mm
  const tile = (nv.screenSlices || []).find((s) => s.axCorSag !== 4 && s.fovMM && s.fovMM.length > 1);
  if (!tile || !(tile.fovMM[0] > 0)) { node.hidden = true; return; }
  const cssPerMm = tile.leftTopWidthHeight[2] / tile.fovMM[0] * (nv.canvas.clientWidth / nv.canvas.width);
  const want = tile.fovMM[0] / 5;
  const base = 10 ** Math.floor(Math.log10(want));
  const mm = [5, 2, 1].map((m) => m * base).find((v) => v <= want);
  node.hidden = false;
  $('.bar', node).style.width = `${(mm * cssPerMm).toFixed(1)}px`;
  $('.label', node).textContent = `${+mm.toPrecision(3)} mm`;
  node.dataset.mm = String(mm);
}

function verdictNote(j, node) {
  // beside each volume: its verdict, and the override when it was made from a failed geometry
  const v = j.verdict;
  node.hidden = !v || v.status === 'passed';
  if (node.hidden) return;
  node.replaceChildren(verdictBadge(v), ' ', (v.reasons.length ? v.reasons : v.warnings).join('; '));
  // made from a failed geometry by override: drawn as a failure would be, whatever else it says
  node.className = 'notice verdict-note ' + (j.result.geometry_override ? 'failed' : v.status);
}

function fallback(job, other) {
  const note = $('#viewer-fallback');
  note.hidden = false;
  note.textContent = (window.niivue ? 'This browser has no WebGL2, so the 3-D viewer cannot run'
    : 'The 3-D viewer\'s library is not installed on this server (python -m orbitct_app.console.assets)')
    + '; the middle slices are shown as pictures (window: 1st to 99.5th percentile of the first volume'
    + (other ? ', the second volume resampled onto its grid' : '') + ').';
  const pictures = (j, fig, onto) => {
    const verdict = $('p[role=status]', fig);  // the volume's verdict stays with its pictures
    const query = onto ? `?grid_of=${encodeURIComponent(onto.id)}` : '';
    const caption = (j.result.name || j.id) + (onto ? `, resampled onto ${onto.result.name || onto.id}'s grid` : '');
    fig.replaceChildren(el('figcaption', { text: caption }), verdict,
      ...['axial', 'coronal', 'sagittal'].map((axis) => el('img', { src: `/reconstructions/${j.id}/slices/${axis}${query}`, alt: `${axis} slice of ${j.id}` })));
    verdictNote(j, verdict);
  };
  pictures(job, $('#gl-a').closest('figure'));
  if (other) { $('#pane-b').hidden = false; pictures(other, $('#pane-b'), job); }
  document.body.dataset.viewerReady = 'fallback';
}

// ---------------------------------------------------------------- people (operators)
function pagePeople() {
  const me = document.body.dataset.user;
  const load = async () => {
    try {
      const list = await api('GET', '/people');
      $('#people-table tbody').replaceChildren(...list.map((p) => el('tr', { 'data-person': p.name },
        el('td', { text: p.name }), el('td', { text: p.roles.join(', ') }), el('td', {}, el('code', { text: p.hash_prefix })),
        el('td', {}, p.name === me ? el('span', { class: 'muted', text: 'you' }) : el('button', { type: 'button', class: 'danger', text: 'Remove',
          onclick: (ev) => act(ev.currentTarget, async () => {
            if (!confirm(`Remove ${p.name}? Their token stops working at once.`)) return;
            await api('DELETE', `/people/${encodeURIComponent(p.name)}`);
            await load();
          }) })))));
      if (!list.length) $('#people-table tbody').append(el('tr', {}, el('td', { colspan: 4, class: 'muted', text: 'Nobody in the tokens file yet.' })));
      $('main > .error').textContent = '';
    } catch (exc) { $('main > .error').textContent = exc.message; }
  };
  $('#person-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    act($('#add-person'), async () => {
      const roles = Array.from(document.querySelectorAll('#person-form input[name=role]:checked')).map((i) => i.value);
      if (!roles.length) throw new ApiError('choose at least one role', 0);
      const made = await api('POST', '/people', { name: $('#person-name').value, roles });
      $('#new-token').hidden = false;
      $('#new-token .name').textContent = `${made.name} (${made.roles.join(', ')})`;
      $('#new-token .token').textContent = made.token;
      $('#person-form').reset();
      await load();
    });
  });
  load();
}

// ---------------------------------------------------------------- start
const PAGES = { 'sign-in': pageSignIn, bench: pageBench, 'scan-new': pageScanNew, scans: pageScans, scan: pageScan,
  calibration: pageCalibration, jobs: pageJobs, viewer: pageViewer, plans: pagePlans, people: pagePeople };
document.addEventListener('DOMContentLoaded', () => {
  const page = document.body.dataset.page;
  if (page !== 'sign-in') initFrame();
  const run = PAGES[page];
  if (run) Promise.resolve(run()).catch((exc) => { const slot = $('main .error'); if (slot) slot.textContent = exc.message; });
});
