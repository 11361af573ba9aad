// Sylva's page: the jobs list (live over server-sent events), the resumable upload form and
// the job page (stages, log, reports, inventory, the 3-D viewer). Plain JavaScript against the
// public API (openapi.yaml); nothing here is private to the page.
'use strict';

const STAGES = ['ingest', 'register', 'anchors', 'segment', 'train', 'dbh', 'export'];
const TERMINAL = new Set(['succeeded', 'failed', 'canceled']);
const $ = (sel) => document.querySelector(sel);

// ------------------------------------------------------------------ small helpers

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v == null) continue;
    if (k === 'class') e.className = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) if (c != null) e.append(c instanceof Node ? c : String(c));
  return e;
}
const SVG_NS = 'http://www.w3.org/2000/svg';
function svg(tag, attrs = {}) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}
function bytes(n) {
  if (n == null) return '';
  const u = ['B', 'kB', 'MB', 'GB', 'TB'];
  let i = 0;
  while (n >= 1000 && i < u.length - 1) { n /= 1000; i++; }
  return `${n.toFixed(i && n < 10 ? 1 : 0)} ${u[i]}`;
}
function duration(s) {
  if (s == null || !isFinite(s)) return '';
  if (s < 1) return `${Math.round(s * 1000)} ms`;
  if (s < 90) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
  if (s < 5400) return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}
function when(ts) { return ts ? new Date(ts).toLocaleString() : ''; }
function num(v) {
  if (typeof v !== 'number' || !isFinite(v)) return String(v);
  if (Number.isInteger(v)) return v.toLocaleString();
  const a = Math.abs(v);
  return a !== 0 && (a < 1e-3 || a >= 1e9) ? v.toExponential(3) : String(+v.toPrecision(4));
}
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
function randomKey() {
  const b = new Uint8Array(16);
  crypto.getRandomValues(b);
  return Array.from(b, (x) => x.toString(16).padStart(2, '0')).join('');
}

// ------------------------------------------------------------------ API and auth

const TOKEN_KEY = 'sylva-token';
/** Who the token is (`GET /v1/info` → caller): an admin key sees every owner's jobs. */
const caller = { owner: '', admin: false, key: null };
const auth = {
  get token() { return sessionStorage.getItem(TOKEN_KEY) || ''; },
  headers() { return this.token ? { Authorization: `Bearer ${this.token}` } : {}; },
  waiting: null,
  /** Shows the token dialog once, however many requests are waiting for it. */
  ask(rejected) {
    if (!this.waiting) {
      this.waiting = new Promise((resolve) => {
        $('#token-error').hidden = !rejected;
        $('#token-dialog').hidden = false;
        $('#token-input').focus();
        $('#token-form').onsubmit = (e) => {
          e.preventDefault();
          sessionStorage.setItem(TOKEN_KEY, $('#token-input').value.trim());
          $('#token-dialog').hidden = true;
          this.waiting = null;
          resolve();
        };
      });
    }
    return this.waiting;
  },
};

/** fetch() on the API with the token; a 401 asks for a token and tries again. */
async function api(path, opts = {}) {
  for (;;) {
    const headers = { ...(opts.headers || {}), ...auth.headers() };
    let body = opts.body;
    if (opts.json !== undefined) { headers['Content-Type'] = 'application/json'; body = JSON.stringify(opts.json); }
    const r = await fetch(path, { ...opts, headers, body });
    if (r.status !== 401) return r;
    await auth.ask(Boolean(auth.token));
  }
}
async function apiJson(path, opts) {
  const r = await api(path, opts);
  if (!r.ok) throw await problem(r);
  return r.json();
}
/** An Error carrying the problem+json detail (and field errors) of a failed answer. */
async function problem(r) {
  let p = null;
  try { p = await r.json(); } catch { /* not JSON */ }
  const detail = (p && (p.detail || p.title)) || `${r.status} ${r.statusText}`;
  const err = new Error(detail);
  err.status = r.status;
  err.problem = p;
  return err;
}
/** Object URL of an artifact fetched with the token (for <img> and downloads). */
async function blobUrl(href) {
  const r = await api(href);
  if (!r.ok) throw await problem(r);
  return URL.createObjectURL(await r.blob());
}
async function download(href, filename) {
  try {
    const url = await blobUrl(href);
    const a = el('a', { href: url, download: filename });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  } catch (e) { alert(`Download failed: ${e.message}`); }
}

/**
 * Server-sent events over fetch (EventSource cannot send the Authorization header; tokens never
 * go in URLs). Reconnects with Last-Event-ID after a dropped connection, so no log line is lost.
 * Returns a function that stops the stream.
 */
function streamEvents(path, onEvent) {
  const ctl = new AbortController();
  let lastId = null, stopped = false;
  (async () => {
    let delay = 1000;
    while (!stopped) {
      try {
        const headers = { Accept: 'text/event-stream' };
        if (lastId != null) headers['Last-Event-ID'] = lastId;
        const r = await api(path, { headers, signal: ctl.signal });
        if (r.status === 404 || r.status === 410) { onEvent('end', { deleted: true }); return; }
        if (!r.ok || !r.body) throw new Error(`events: ${r.status}`);
        delay = 1000;
        const reader = r.body.getReader();
        const dec = new TextDecoder();
        let buf = '';
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buf += dec.decode(value, { stream: true });
          let cut;
          while ((cut = buf.search(/\r?\n\r?\n/)) >= 0) {
            const block = buf.slice(0, cut);
            buf = buf.slice(cut).replace(/^\r?\n\r?\n/, '');
            let type = 'message', data = '';
            for (const line of block.split(/\r?\n/)) {
              if (line.startsWith(':')) continue;
              const i = line.indexOf(':');
              const k = i < 0 ? line : line.slice(0, i);
              const v = i < 0 ? '' : line.slice(i + 1).replace(/^ /, '');
              if (k === 'event') type = v;
              else if (k === 'data') data += (data ? '\n' : '') + v;
              else if (k === 'id') lastId = v;
            }
            let parsed = null;
            try { parsed = data ? JSON.parse(data) : null; } catch { parsed = data; }
            onEvent(type, parsed);
            if (type === 'end') { stopped = true; ctl.abort(); return; }
          }
        }
      } catch (e) {
        if (stopped || e.name === 'AbortError') return;
      }
      await sleep(delay);
      delay = Math.min(delay * 2, 15000);
    }
  })();
  return () => { stopped = true; ctl.abort(); };
}

// ------------------------------------------------------------------ the jobs list

const list = { rows: new Map(), streams: new Map(), timer: null };

function progressCell(p, state) {
  const fill = el('div', { class: `fill ${state === 'failed' ? 'failed' : state === 'succeeded' ? 'done' : ''}` });
  fill.style.width = `${Math.round(p * 100)}%`;
  return el('div', { class: 'progress-cell' }, el('div', { class: 'bar' }, fill), el('span', { class: 'pct' }, `${Math.floor(p * 100)} %`));
}

/** Whose a job is, shown to an admin key (which sees everyone's); others see their own only. */
function ownerNote(j) {
  return caller.admin && j.owner ? ` · owner ${j.owner}` : '';
}

function jobRow(j) {
  const eta = j.eta_seconds != null ? ` · about ${duration(j.eta_seconds)} left` : '';
  const tr = el('tr', { 'data-job': j.id, onclick: () => { location.hash = `#/jobs/${j.id}`; } },
    el('td', {}, el('a', { class: 'id', href: `#/jobs/${j.id}` }, j.id.slice(0, 8) + '…'), el('div', { class: 'hint' }, when(j.created_at) + ownerNote(j))),
    el('td', {}, el('span', { class: `badge ${j.state}`, 'data-state': j.state }, j.state)),
    el('td', {}, j.stage || (j.state === 'succeeded' ? 'done' : '')),
    el('td', {}, progressCell(j.progress, j.state), el('div', { class: 'hint' }, eta)));
  return tr;
}

function updateRow(j) {
  const old = list.rows.get(j.id);
  const tr = jobRow(j);
  if (old && old.isConnected) old.replaceWith(tr);
  else $('#jobs-table tbody').prepend(tr);
  list.rows.set(j.id, tr);
}

/** Live rows: one event stream per unfinished job, a few at a time (browsers cap connections). */
function watchListJobs(jobs) {
  const want = jobs.filter((j) => !TERMINAL.has(j.state)).slice(0, 3).map((j) => j.id);
  for (const [id, stop] of list.streams) if (!want.includes(id)) { stop(); list.streams.delete(id); }
  for (const id of want) {
    if (list.streams.has(id)) continue;
    list.streams.set(id, streamEvents(`/v1/jobs/${id}/events`, (type, data) => {
      if (type === 'job' && data) updateRow(data);
      if (type === 'end') { list.streams.delete(id); refreshList(); }
    }));
  }
  $('#jobs-live').hidden = list.streams.size === 0;
}

async function refreshList() {
  try {
    const d = await apiJson('/v1/jobs?limit=50');
    const tb = $('#jobs-table tbody');
    tb.replaceChildren();
    list.rows.clear();
    for (const j of d.jobs) { const tr = jobRow(j); tb.append(tr); list.rows.set(j.id, tr); }
    $('#jobs-table').hidden = d.jobs.length === 0;
    $('#jobs-note').textContent = d.jobs.length ? '' : 'No jobs yet: upload a plot to start one.';
    watchListJobs(d.jobs);
  } catch (e) {
    $('#jobs-note').textContent = `Could not list jobs: ${e.message}`;
  }
}

function enterList() {
  refreshList();
  clearInterval(list.timer);
  list.timer = setInterval(refreshList, 15000);
}
function leaveList() {
  clearInterval(list.timer);
  for (const stop of list.streams.values()) stop();
  list.streams.clear();
}

// ------------------------------------------------------------------ resumable uploads

/** What the last upload did (tests and curious people read it). */
const uploadStats = { parts: 0, retries: 0, resumedParts: 0, jobs: [] };

const PARALLEL_PARTS = 3;
const PART_TRIES = 6;

/** PUT of one part with upload progress; resolves to the server's answer or rejects on a network error. */
function putPart(uploadId, n, blob, onBytes) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('PUT', `/v1/uploads/${uploadId}/parts/${n}`);
    for (const [k, v] of Object.entries(auth.headers())) xhr.setRequestHeader(k, v);
    xhr.setRequestHeader('Content-Type', 'application/octet-stream');
    xhr.upload.onprogress = (e) => onBytes(e.loaded);
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch { /* empty */ }
      resolve({ status: xhr.status, body });
    };
    xhr.onerror = () => reject(new Error('network error'));
    xhr.ontimeout = () => reject(new Error('timed out'));
    xhr.send(blob);
  });
}

async function sha256Hex(blob) {
  if (!(window.crypto && crypto.subtle)) return null; // only in secure contexts
  const d = await crypto.subtle.digest('SHA-256', await blob.arrayBuffer());
  return Array.from(new Uint8Array(d), (x) => x.toString(16).padStart(2, '0')).join('');
}

/**
 * Uploads `file` as upload `kind` in parts, resuming an earlier attempt at the same file (its
 * upload id is remembered in localStorage), retrying each failed part with backoff, and
 * checking each part's SHA-256 against the server's when the browser can hash.
 */
async function uploadFile(file, kind, ui) {
  const key = `sylva-upload:${kind}:${file.name}:${file.size}:${file.lastModified}`;
  let up = null;
  const saved = localStorage.getItem(key);
  if (saved) {
    const r = await api(`/v1/uploads/${saved}`);
    if (r.ok) up = await r.json();
    if (up && up.state === 'complete') { ui.done(file.size, 'already on the server'); return up.id; }
  }
  if (!up) {
    up = await apiJson('/v1/uploads', { method: 'POST', json: { kind, filename: file.name, size: file.size } });
    localStorage.setItem(key, up.id);
  }
  const ps = up.part_size, total = Math.max(1, Math.ceil(file.size / ps));
  const have = new Set(up.parts_received || []);
  const partLen = (n) => Math.min(file.size, (n + 1) * ps) - n * ps;
  let done = 0;
  for (const n of have) done += partLen(n);
  uploadStats.resumedParts += have.size;
  const inFlight = new Map();
  const report = () => ui.progress(done + [...inFlight.values()].reduce((a, b) => a + b, 0), `${have.size}/${total} parts`);
  report();
  const queue = [];
  for (let n = 0; n < total; n++) if (!have.has(n)) queue.push(n);

  async function sendPart(n) {
    const blob = file.slice(n * ps, n * ps + partLen(n));
    const local = await sha256Hex(blob);
    for (let attempt = 1; ; attempt++) {
      let failure;
      try {
        const r = await putPart(up.id, n, blob, (b) => { inFlight.set(n, b); report(); });
        if (r.status >= 200 && r.status < 300) {
          if (!local || !r.body || r.body.sha256 === local) { inFlight.delete(n); return; }
          failure = 'checksum differs';
        } else if (r.status === 408 || r.status === 429 || r.status >= 500) {
          failure = `server answered ${r.status}`;
        } else {
          const e = new Error((r.body && r.body.detail) || `part ${n}: ${r.status}`);
          e.status = r.status;
          throw e;
        }
      } catch (e) {
        if (e.status) throw e;
        failure = e.message;
      }
      inFlight.delete(n);
      if (attempt >= PART_TRIES) throw new Error(`part ${n} failed ${attempt} times (${failure}); choose the same file again to resume`);
      uploadStats.retries++;
      ui.retry(n, attempt, failure);
      await sleep(Math.min(500 * 2 ** attempt, 15000));
    }
  }
  const workers = Array.from({ length: Math.min(PARALLEL_PARTS, queue.length) }, async () => {
    while (queue.length) {
      const n = queue.shift();
      await sendPart(n);
      have.add(n);
      uploadStats.parts++;
      done += partLen(n);
      report();
    }
  });
  await Promise.all(workers);
  ui.progress(file.size, 'checking…');
  const r = await api(`/v1/uploads/${up.id}/complete`, { method: 'POST' });
  if (!r.ok) {
    const e = await problem(r);
    if (r.status === 422 || r.status === 410) localStorage.removeItem(key);
    const reasons = e.problem && e.problem.errors ? Object.values(e.problem.errors).flat().join('; ') : '';
    throw new Error(`${file.name}: ${e.message}${reasons && !e.message.includes(reasons) ? ` (${reasons})` : ''}`);
  }
  ui.done(file.size, 'checked');
  return up.id;
}

function fileProgressUi(container, file) {
  const fill = el('div', { class: 'fill' });
  const note = el('span', { class: 'muted' });
  const retry = el('div', { class: 'retry' });
  container.append(el('div', { class: 'file-row' },
    el('div', { class: 'name' }, el('span', {}, file.name), note), el('div', { class: 'bar' }, fill), retry));
  const set = (b) => { fill.style.width = `${file.size ? Math.min(100, 100 * b / file.size) : 100}%`; };
  return {
    progress(b, what) { set(b); note.textContent = `${bytes(b)} / ${bytes(file.size)} · ${what}`; },
    retry(n, attempt, why) { retry.textContent = `part ${n} failed (${why}); retry ${attempt} of ${PART_TRIES - 1}…`; },
    done(b, what) { set(b); fill.classList.add('done'); note.textContent = `${bytes(file.size)} · ${what}`; },
  };
}

let jobKey = null; // one Idempotency-Key per plot, kept until its job exists
async function submitPlot(e) {
  e.preventDefault();
  const inputs = [['lidar', '#in-lidar'], ['photos', '#in-photos'], ['colmap', '#in-colmap'], ['control_points', '#in-control'], ['field_dbh', '#in-field']]
    .map(([kind, sel]) => [kind, $(sel).files[0]]).filter(([, f]) => f);
  const status = $('#upload-status'), btn = $('#upload-submit'), box = $('#upload-progress');
  const given = new Set(inputs.map(([kind]) => kind));
  if (given.has('photos') === given.has('colmap')) {
    box.replaceChildren(el('div', { class: 'error' },
      given.has('photos') ? 'Choose photos or a COLMAP project, not both.' : 'Choose the photos (or a COLMAP project).'));
    return;
  }
  btn.disabled = true;
  box.replaceChildren();
  status.textContent = 'Uploading…';
  try {
    const ids = {};
    for (const [kind, file] of inputs) ids[kind] = await uploadFile(file, kind, fileProgressUi(box, file));
    status.textContent = 'Starting the job…';
    const until = $('#in-until').value;
    jobKey = jobKey || randomKey();
    const job = await apiJson('/v1/jobs', {
      method: 'POST', headers: { 'Idempotency-Key': jobKey },
      json: { inputs: ids, params: until ? { until } : {} },
    });
    jobKey = null;
    uploadStats.jobs.push(job.id);
    status.textContent = uploadStats.retries ? `Job started (${uploadStats.retries} part(s) retried).` : 'Job started.';
    $('#upload-form').reset();
    location.hash = `#/jobs/${job.id}`;
  } catch (err) {
    status.textContent = '';
    box.append(el('div', { class: 'error' }, err.message));
  } finally {
    btn.disabled = false;
  }
}

// ------------------------------------------------------------------ the job page

const page = { id: null, job: null, stop: null, viewer: null, tiles: null, artifactsSeen: '', trees: [], stems: [], points: null, sort: null };

function artifact(name) { return page.job && page.job.artifacts.find((a) => a.name === name); }
function artifactEnding(suffix) {
  const all = page.job ? page.job.artifacts.filter((a) => a.name.endsWith(suffix)) : [];
  return all[all.length - 1];
}

function renderHeader(j) {
  $('#job-title').textContent = `Job ${j.id.slice(0, 8)}`;
  $('#job-title').title = j.id;
  const badge = $('#job-state');
  badge.textContent = j.state;
  badge.className = `badge ${j.state}`;
  badge.dataset.state = j.state;
  const bar = $('#job-bar');
  bar.style.width = `${Math.round(j.progress * 100)}%`;
  bar.className = `fill ${j.state === 'failed' ? 'failed' : j.state === 'succeeded' ? 'done' : ''}`;
  const took = j.started_at && j.finished_at ? ` · took ${duration((Date.parse(j.finished_at) - Date.parse(j.started_at)) / 1000)}` : '';
  const eta = j.eta_seconds != null ? ` · about ${duration(j.eta_seconds)} left` : '';
  const until = j.params && j.params.until ? ` · runs until ${j.params.until}` : '';
  $('#job-meta').textContent = `${Math.floor(j.progress * 100)} % · created ${when(j.created_at)}${took}${eta}${until} · attempt ${j.attempt}${ownerNote(j)}`;
  $('#job-cancel').disabled = TERMINAL.has(j.state) || j.state === 'canceling';
  $('#job-retry').disabled = !(j.state === 'failed' || j.state === 'canceled');
  const err = $('#job-error');
  err.hidden = !j.error;
  if (j.error) {
    err.replaceChildren(`${j.error.title || 'Failed'}: ${j.error.detail || ''}`);
    const cands = Array.isArray(j.error.candidates) ? j.error.candidates : [];
    if (cands.length) err.append(candidateTable(cands));
  }
}

/** The alignments a refused automatic registration weighed, best first. */
function candidateTable(cands) {
  const score = (c) => c.on_cloud + c.elevated_on_cloud;
  const pct = (v) => `${(v * 100).toFixed(1)} %`;
  const rows = [...cands].sort((a, b) => score(b) - score(a)).map((c, i) => el('tr', {},
    el('td', {}, String(i + 1)),
    el('td', {}, c.start || 'search'),
    el('td', {}, pct(c.on_cloud)),
    el('td', {}, `${pct(c.elevated_on_cloud)} of ${c.elevated_points}`),
    el('td', {}, `${c.rotation_deg.toFixed(1)}°`),
    el('td', {}, c.scale.toPrecision(4))));
  return el('table', { id: 'job-candidates', class: 'candidates' },
    el('caption', {}, `Candidate alignments weighed (${cands.length})`),
    el('thead', {}, el('tr', {}, ...['#', 'start', 'SfM points on the cloud', 'elevated points on the cloud', 'rotation', 'scale'].map((h) => el('th', {}, h)))),
    el('tbody', {}, ...rows));
}

function renderTimeline(j) {
  const strip = $('#timeline-strip');
  strip.replaceChildren();
  const tb = $('#timeline tbody');
  tb.replaceChildren();
  const total = j.stages.reduce((s, x) => s + (x.duration_seconds || 0), 0);
  for (const s of j.stages) {
    const seg = el('div', { class: `st-${s.state}`, title: `${s.name}: ${s.state} ${duration(s.duration_seconds)}` });
    seg.style.flexGrow = String(s.duration_seconds ? Math.max(s.duration_seconds, total * 0.02) : (s.state === 'running' ? total * 0.1 + 1 : total * 0.02 + 0.2));
    strip.append(seg);
    const dot = el('span', { class: `dot st-${s.state}` });
    const fill = el('div', { class: `fill ${s.state === 'done' ? 'done' : s.state === 'failed' ? 'failed' : ''}` });
    fill.style.width = `${Math.round(s.progress * 100)}%`;
    tb.append(el('tr', { 'data-stage': s.name },
      el('td', {}, dot, s.name),
      el('td', {}, el('span', { class: `badge ${s.state}` }, s.state)),
      el('td', { class: 'wide' }, el('div', { class: 'bar' }, fill)),
      el('td', { class: 'num' }, duration(s.duration_seconds) || (s.state === 'running' ? `${Math.floor(s.progress * 100)} %` : '')),
      el('td', { class: 'hint' }, s.started_at ? new Date(s.started_at).toLocaleTimeString() : '')));
  }
}

function renderArtifacts(j) {
  const ul = $('#artifacts');
  ul.replaceChildren();
  if (!j.artifacts.length) ul.append(el('li', { class: 'muted' }, 'Nothing yet.'));
  for (const a of j.artifacts) {
    const link = el('a', { href: a.href, onclick: (e) => { if (auth.token) { e.preventDefault(); download(a.href, a.name.split('/').pop()); } } }, a.name);
    ul.append(el('li', {}, link, el('span', { class: 'size' }, bytes(a.size))));
  }
}

function appendLog(line) {
  const pre = $('#log');
  const level = (line.level || 'info').toLowerCase();
  const ts = line.ts ? new Date(line.ts).toLocaleTimeString() : '';
  pre.append(el('span', { class: level }, el('span', { class: 'ts' }, `${ts} `), `${line.stage ? `[${line.stage}] ` : ''}${line.message}\n`));
  while (pre.childNodes.length > 5000) pre.firstChild.remove();
  if ($('#log-follow').checked) pre.scrollTop = pre.scrollHeight;
}

/** A nested report as a definition list (numbers rounded); arrays of objects become tables. */
function reportView(obj, skip = []) {
  const dl = el('dl', { class: 'report' });
  const tables = [];
  const walk = (o, prefix) => {
    for (const [k, v] of Object.entries(o)) {
      if (skip.includes(k)) continue;
      const name = prefix ? `${prefix}.${k}` : k;
      if (v && typeof v === 'object' && !Array.isArray(v)) { if (prefix.split('.').length < 2) walk(v, name); continue; }
      if (Array.isArray(v) && v.length && v.every((x) => x && typeof x === 'object' && !Array.isArray(x))) { tables.push([name, v]); continue; }
      let text;
      if (Array.isArray(v)) text = v.length > 6 || v.some((x) => Array.isArray(x)) ? `[${v.length} values]` : v.map(num).join(', ');
      else text = typeof v === 'number' ? num(v) : String(v);
      dl.append(el('dt', {}, name), el('dd', {}, text));
    }
  };
  walk(obj, '');
  const out = el('div', {}, dl);
  for (const [name, rows] of tables) {
    const cols = [...new Set(rows.flatMap((r) => Object.keys(r).filter((k) => typeof r[k] !== 'object' || r[k] === null)))];
    const t = el('table', { class: 'small' }, el('thead', {}, el('tr', {}, ...cols.map((c) => el('th', {}, c)))));
    const tb = el('tbody');
    for (const r of rows.slice(0, 50)) tb.append(el('tr', {}, ...cols.map((c) => el('td', { class: typeof r[c] === 'number' ? 'num' : '' }, r[c] == null ? '' : (typeof r[c] === 'number' ? num(r[c]) : String(r[c]))))));
    t.append(tb);
    out.append(el('h4', {}, name), t);
  }
  return out;
}

async function renderRegistration() {
  const a = artifact('register/report.json');
  if (!a) return;
  const rep = await apiJson(a.href);
  const box = $('#registration');
  const key = el('p', {}, `Method: ${rep.method || '?'}`);
  box.replaceChildren(key, reportView(rep, ['coarse', 'registered_model_frame', 'transform', 'similarity']));
}

async function renderTraining() {
  const evalA = artifact('train/eval.json');
  if (evalA) $('#render-metrics').replaceChildren(reportView(await apiJson(evalA.href)));
  const lossCsv = artifact('train/loss.csv'), lossPng = artifact('train/loss.png');
  if (lossCsv) {
    const r = await api(lossCsv.href);
    if (r.ok) $('#loss').replaceChildren(el('h4', {}, 'Loss'), lossChart(parseCsv(await r.text())));
  } else if (lossPng) {
    $('#loss').replaceChildren(el('h4', {}, 'Loss'), el('img', { src: await blobUrl(lossPng.href), alt: 'training loss' }));
  }
  const renders = page.job.artifacts.filter((a) => a.name.startsWith('train/renders/') && a.name.endsWith('.png'));
  if (!renders.length) return;
  // Pairs: a ground-truth image is named like its render with gt/truth in it.
  const isGt = (n) => /(^|[_\-.])(gt|truth|ground_truth|target)([_\-.]|$)/i.test(n);
  const stem = (n) => n.split('/').pop().replace(/\.png$/, '').replace(/(^|[_\-.])(gt|truth|ground_truth|target|render|pred|rendered)(?=[_\-.]|$)/ig, '').replace(/^[_\-.]+|[_\-.]+$/g, '');
  const groups = new Map();
  for (const a of renders) {
    const k = stem(a.name);
    if (!groups.has(k)) groups.set(k, {});
    groups.get(k)[isGt(a.name) ? 'gt' : 'render'] = a;
  }
  const box = $('#test-views');
  box.replaceChildren();
  for (const [k, g] of groups) {
    const pair = el('div', { class: 'pair' });
    for (const which of ['render', 'gt']) {
      if (g[which]) pair.append(el('img', { src: await blobUrl(g[which].href), alt: `${k} ${which}`, title: g[which].name }));
    }
    box.append(el('figure', {}, pair, el('figcaption', {}, `${k}: render${g.gt ? ' | ground truth' : ''}`)));
  }
  $('#views-card').hidden = false;
}

function parseCsv(text) {
  const lines = text.trim().split(/\r?\n/).filter((l) => l.length);
  const header = (lines.shift() || '').split(',').map((h) => h.trim());
  return { header, rows: lines.map((l) => l.split(',').map((v) => v.trim())) };
}

function lossChart({ header, rows }) {
  const W = 560, H = 220, P = 40;
  const xs = rows.map((r) => Number(r[0]));
  const series = header.slice(1).map((name, i) => ({ name, ys: rows.map((r) => Number(r[i + 1])) }))
    .filter((s) => s.ys.some((y) => isFinite(y)));
  const all = series.flatMap((s) => s.ys.filter((y) => isFinite(y) && y > 0));
  const s = svg('svg', { viewBox: `0 0 ${W} ${H}`, role: 'img', 'aria-label': 'loss curve' });
  if (!all.length || !xs.length) return s;
  const logY = Math.max(...all) / Math.min(...all) > 50;
  const ty = (y) => (logY ? Math.log10(y) : y);
  const y0 = Math.min(...all.map(ty)), y1 = Math.max(...all.map(ty));
  const x0 = Math.min(...xs), x1 = Math.max(...xs);
  const X = (x) => P + (W - P - 10) * (x - x0) / Math.max(x1 - x0, 1e-9);
  const Y = (y) => H - 25 - (H - 35) * (ty(y) - y0) / Math.max(y1 - y0, 1e-9);
  s.append(svg('line', { x1: P, y1: H - 25, x2: W - 10, y2: H - 25, stroke: '#bbb' }), svg('line', { x1: P, y1: 10, x2: P, y2: H - 25, stroke: '#bbb' }));
  const colors = ['#2f6b3a', '#2d6b9a', '#c98a16', '#b3412f'];
  series.forEach((ser, i) => {
    const d = xs.map((x, k) => (isFinite(ser.ys[k]) && ser.ys[k] > 0 ? `${X(x).toFixed(1)},${Y(ser.ys[k]).toFixed(1)}` : null)).filter(Boolean).join(' ');
    s.append(svg('polyline', { points: d, fill: 'none', stroke: colors[i % colors.length], 'stroke-width': 1.5 }));
    const t = svg('text', { x: W - 12, y: 18 + 14 * i, 'text-anchor': 'end', 'font-size': 11, fill: colors[i % colors.length] });
    t.textContent = ser.name;
    s.append(t);
  });
  for (const [txt, x, y, anchor] of [[num(x0), P, H - 8, 'start'], [`${header[0]} ${num(x1)}`, W - 10, H - 8, 'end'],
    [num(logY ? 10 ** y1 : y1), P - 4, 16, 'end'], [num(logY ? 10 ** y0 : y0), P - 4, H - 27, 'end']]) {
    const t = svg('text', { x, y, 'text-anchor': anchor, 'font-size': 10, fill: '#5f6f63' });
    t.textContent = txt;
    s.append(t);
  }
  return s;
}

// ---------------------------------------------------------------- inventory

async function renderInventory() {
  if (!artifactEnding('trees.csv')) return;
  const r = await api(`/v1/jobs/${page.id}/trees.csv`);
  if (!r.ok) return;
  const { header, rows } = parseCsv(await r.text());
  page.trees = rows.map((r) => Object.fromEntries(header.map((h, i) => [h, r[i] ?? ''])));
  page.treeHeader = header;
  drawTrees();
  // The stand figures come from the server (results.plot: LiDAR DBH unless the job asked for
  // the Gaussians', and it says which); the page only formats them.
  const res = await api(`/v1/jobs/${page.id}/results`);
  const results = res.ok ? await res.json() : {};
  const plot = results.plot;
  const f = (v, d = 1) => (v === null || v === undefined ? '—' : Number(v).toFixed(d));
  if (plot) {
    const source = plot.dbh_source === 'gaussians' ? 'Gaussian' : 'LiDAR';
    $('#inventory-summary').textContent = `${plot.stems} trees · ${source} DBH · mean ${f(plot.mean_dbh_cm)} cm · QMD ${f(plot.qmd_cm)} cm`;
    $('#inventory-plot').textContent = `Plot ${f(plot.area_m2, 0)} m² (${plot.area_from}) · ${f(plot.stems_per_ha, 0)} stems/ha · basal area ${f(plot.basal_area_m2_per_ha)} m²/ha · `
      + `height mean ${f(plot.mean_height_m)} m, dominant ${f(plot.dominant_height_m)} m · volume ${f(plot.volume_m3_per_ha)} m³/ha · `
      + `biomass ${f(plot.agb_t_per_ha)} t/ha · carbon ${f(plot.carbon_t_per_ha)} t/ha · CRS ${results.crs || 'unknown'}`;
    $('#inventory-plot').title = Object.values(plot.equations || {}).join('\n');
    $('#inventory-plot').hidden = false;
    $('#dbh-histogram').replaceChildren(dbhHistogram(plot.dbh_classes || []));
    $('#height-dbh').replaceChildren(heightScatter(page.trees, plot.dbh_source === 'gaussians' ? 'dbh_gs_cm' : 'dbh_lidar_cm'));
    $('#inventory-charts').hidden = false;
  } else {
    $('#inventory-summary').textContent = `${page.trees.length} trees`;
  }
  $('#inventory-note').hidden = true;
  $('#trees').hidden = false;
  $('#inventory-downloads').hidden = false;
}

function dbhHistogram(classes) {
  const W = 320, H = 180, P = 28;
  const s = svg('svg', { viewBox: `0 0 ${W} ${H}`, role: 'img', 'aria-label': 'DBH distribution' });
  const top = Math.max(1, ...classes.map((c) => c.stems));
  const bw = (W - 2 * P) / Math.max(1, classes.length);
  classes.forEach((c, i) => {
    const h = ((H - 2 * P) * c.stems) / top;
    const bar = svg('rect', { x: P + i * bw + 1, y: H - P - h, width: Math.max(1, bw - 2), height: h, fill: '#4f7d5c' });
    const t = svg('title', {});
    t.textContent = `${c.from_cm}–${c.to_cm} cm: ${c.stems}`;
    bar.append(t);
    s.append(bar);
    if (i % Math.ceil(classes.length / 8) === 0) {
      const lab = svg('text', { x: P + i * bw, y: H - P + 12, 'font-size': 9, fill: '#5f6f63' });
      lab.textContent = `${c.from_cm}`;
      s.append(lab);
    }
  });
  const ymax = svg('text', { x: P - 4, y: P + 4, 'text-anchor': 'end', 'font-size': 9, fill: '#5f6f63' });
  ymax.textContent = `${top}`;
  s.append(ymax);
  return s;
}

function heightScatter(trees, col) {
  const W = 320, H = 180, P = 28;
  const pts = trees.map((t) => [Number(t[col]), Number(t.height_m)]).filter(([d, h]) => d > 0 && h > 0);
  const s = svg('svg', { viewBox: `0 0 ${W} ${H}`, role: 'img', 'aria-label': 'height against DBH' });
  if (!pts.length) return s;
  const dx = Math.max(...pts.map((p) => p[0])) * 1.05, hy = Math.max(...pts.map((p) => p[1])) * 1.05;
  for (const [d, h] of pts) {
    const c = svg('circle', { cx: P + ((W - 2 * P) * d) / dx, cy: H - P - ((H - 2 * P) * h) / hy, r: 3, fill: '#4f7d5c' });
    const t = svg('title', {});
    t.textContent = `DBH ${d.toFixed(1)} cm, height ${h.toFixed(1)} m`;
    c.append(t);
    s.append(c);
  }
  for (const [txt, x, y, anchor] of [[`${dx.toFixed(0)} cm`, W - P, H - P + 12, 'end'], [`${hy.toFixed(0)} m`, P - 4, P, 'end'], ['0', P - 4, H - P, 'end']]) {
    const t = svg('text', { x, y, 'text-anchor': anchor, 'font-size': 9, fill: '#5f6f63' });
    t.textContent = txt;
    s.append(t);
  }
  return s;
}

const TREE_COLUMNS = {
  tree_id: 'Tree', x: 'x (m)', y: 'y (m)', ground_z: 'ground z (m)', dbh_lidar_cm: 'DBH LiDAR (cm)', dbh_gs_cm: 'DBH Gaussians (cm)',
  n_points: 'points', rms_mm: 'fit RMS (mm)', arc_coverage: 'arc covered', quality: 'quality', gs_quality: 'quality (Gaussians)',
  height_m: 'height (m)', crown_base_m: 'crown base (m)', crown_area_m2: 'crown area (m²)', crown_diameter_m: 'crown ⌀ (m)',
  basal_area_m2: 'basal area (m²)', volume_m3: 'volume (m³)', agb_kg: 'biomass (kg)', carbon_kg: 'carbon (kg)',
};

function drawTrees() {
  const t = $('#trees');
  const header = page.treeHeader;
  const numeric = header.map((h) => page.trees.every((r) => r[h] === '' || isFinite(Number(r[h]))));
  const thr = el('tr');
  header.forEach((h, i) => {
    const th = el('th', { class: numeric[i] ? 'num' : '', 'data-col': h, scope: 'col' }, TREE_COLUMNS[h] || h);
    if (page.sort && page.sort.col === h) th.setAttribute('aria-sort', page.sort.dir > 0 ? 'ascending' : 'descending');
    th.addEventListener('click', () => {
      page.sort = { col: h, dir: page.sort && page.sort.col === h ? -page.sort.dir : 1, numeric: numeric[i] };
      drawTrees();
    });
    thr.append(th);
  });
  t.tHead.replaceChildren(thr);
  const rows = [...page.trees];
  if (page.sort) {
    const { col, dir, numeric: isNum } = page.sort;
    rows.sort((a, b) => {
      if (isNum) {
        const x = a[col] === '' ? -Infinity : Number(a[col]), y = b[col] === '' ? -Infinity : Number(b[col]);
        return dir * (x - y);
      }
      return dir * String(a[col]).localeCompare(String(b[col]));
    });
  }
  const tb = t.tBodies[0];
  tb.replaceChildren();
  for (const r of rows) {
    const tr = el('tr', { 'data-tree': r.tree_id }, ...header.map((h, i) => el('td', { class: numeric[i] ? 'num' : '' }, r[h])));
    tr.addEventListener('click', () => showStem(Number(r.tree_id), true));
    tb.append(tr);
  }
}

// ---------------------------------------------------------------- viewer

async function fetchBuffer(href) {
  const r = await api(href);
  if (!r.ok) throw await problem(r);
  return r.arrayBuffer();
}

function freshCanvas() {
  const old = $('#viewer-canvas');
  const c = old.cloneNode(false);
  old.replaceWith(c);
  return c;
}

async function renderViewer() {
  const tilesA = artifact('export/tileset.json');
  const splatA = artifact('export/splats.splat');
  const anchorA = artifact('segment/anchors.ply') || artifact('anchors/anchors.ply');
  const stemsA = artifactEnding('stems.json');
  const key = [tilesA, splatA, anchorA, stemsA].map((a) => a && a.sha256).join(',');
  if (!tilesA && !splatA && !anchorA) return;
  if (page.viewerKey === key) return;
  page.viewerKey = key;
  const note = $('#viewer-note');
  note.hidden = false;
  note.textContent = 'Loading the 3-D scene…';
  try {
    stopViewer();
    page.viewer = SylvaViewer.create(freshCanvas(), $('#viewer-labels'), { onStemClick: (s) => showStem(s.id, false) });
    let offset = [0, 0, 0];
    page.ply = null;
    page.splats = null;
    if (anchorA) {
      page.ply = SylvaViewer.parsePly(await fetchBuffer(anchorA.href));
      offset = page.ply.offset;
    }
    let tilesFailed = null;
    if (tilesA) {
      // The tileset streams by level of detail: coarse tiles first, finer ones as the view
      // comes closer (tiles.js).
      let framed = false;
      try {
        page.tiles = await SylvaTiles.stream(page.viewer, tilesA.href, fetchBuffer, {
          onChange: (st, merged) => {
            page.splats = merged;
            if (!framed && merged.count) { framed = true; page.viewer.frame(); }
            const levels = st.minDepth === st.maxDepth ? `level ${st.minDepth}` : `levels ${st.minDepth}–${st.maxDepth}`;
            $('#viewer-source').textContent = `${st.drawn.toLocaleString()} Gaussians in ${st.selected} of ${st.tiles} tiles (${levels}), streamed from the tileset`;
          },
        });
        $('#viewer-colour').disabled = true;
        $('#viewer-source').textContent = 'Streaming the tileset…';
      } catch (e) {
        tilesFailed = e;
        page.tiles = null;
      }
    }
    if (page.tiles) {
      // the tiles arrive through onChange
    } else if (splatA) {
      page.splats = SylvaViewer.parseSplat(await fetchBuffer(splatA.href));
      $('#viewer-source').textContent = `${page.splats.count.toLocaleString()} Gaussian splats`
        + (tilesFailed ? ` (the tileset could not be read: ${tilesFailed.message})` : '');
      $('#viewer-colour').disabled = true;
    } else if (page.ply) {
      page.splats = SylvaViewer.pointsToSplats(page.ply, $('#viewer-colour').value);
      $('#viewer-source').textContent = `${page.ply.count.toLocaleString()} anchor points (the splats come with stage export)`;
      $('#viewer-colour').disabled = false;
    } else if (tilesFailed) {
      throw tilesFailed;
    }
    if (page.splats) page.viewer.setSplats(page.splats);
    page.viewer.setScale(Number($('#viewer-size').value));
    if (page.splats) page.viewer.frame();
    if (stemsA) {
      const st = await apiJson(stemsA.href);
      const d = (st.offset || offset).map((v, i) => v - offset[i]);
      page.stems = (st.stems || []).map((s) => {
        const base = s.base.map((v, i) => v + d[i]);
        const c = s.dbh && s.dbh.center ? s.dbh.center.map((v, i) => v + d[i]) : [base[0], base[1], base[2] + 1.3];
        const diam = s.dbh ? s.dbh.diameter_m : 0;
        return {
          id: s.id, base, axis: s.axis || [0, 0, 1], height: Math.max(3, (c[2] - base[2]) + 2), slice: c,
          radius: diam / 2, raw: s, text: `#${s.id} · ${diam ? (diam * 100).toFixed(1) : '?'} cm`,
        };
      });
      page.viewer.setStems(page.stems);
    }
    note.hidden = true;
  } catch (e) {
    note.hidden = false;
    note.textContent = `The 3-D view could not be shown: ${e.message}`;
  }
}

/** The stem's 1.3 m slice: points within ±5 cm of the slice height, with the fitted circles. */
function showStem(id, focus) {
  const s = page.stems.find((x) => x.id === id);
  for (const tr of document.querySelectorAll('#trees tbody tr')) tr.classList.toggle('selected', tr.dataset.tree === String(id));
  if (!s) return;
  if (page.viewer) { page.viewer.select(id); if (focus) page.viewer.focus(id); }
  const tree = page.trees.find((t) => Number(t.tree_id) === id) || {};
  const c = s.slice, r = s.radius;
  const src = page.ply ? page.ply.props : null;
  const pts = [];
  const reach = Math.max(2.2 * r, 0.3);
  if (src) {
    for (let i = 0; i < page.ply.count; i++) {
      if (Math.abs(src.z[i] - c[2]) > 0.05) continue;
      const dx = src.x[i] - c[0], dy = src.y[i] - c[1];
      if (Math.abs(dx) < reach && Math.abs(dy) < reach) pts.push([dx, dy]);
    }
  } else if (page.splats) {
    const p = page.splats.positions;
    for (let i = 0; i < page.splats.count; i++) {
      if (Math.abs(p[3 * i + 2] - c[2]) > 0.05) continue;
      const dx = p[3 * i] - c[0], dy = p[3 * i + 1] - c[1];
      if (Math.abs(dx) < reach && Math.abs(dy) < reach) pts.push([dx, dy]);
    }
  }
  const W = 260, half = W / 2, k = (half - 14) / reach;
  const plot = svg('svg', { viewBox: `0 0 ${W} ${W}`, width: W, height: W, role: 'img', 'aria-label': `slice of tree ${id}` });
  plot.append(svg('rect', { x: 0, y: 0, width: W, height: W, fill: '#fbfcfa', stroke: '#dfe6df' }));
  for (const g of [-1, 0, 1]) {
    plot.append(svg('line', { x1: half + g * 0.1 * k, y1: 4, x2: half + g * 0.1 * k, y2: W - 4, stroke: '#edf0ec' }));
    plot.append(svg('line', { x1: 4, y1: half + g * 0.1 * k, x2: W - 4, y2: half + g * 0.1 * k, stroke: '#edf0ec' }));
  }
  for (const [x, y] of pts) plot.append(svg('circle', { cx: half + x * k, cy: half - y * k, r: 2, fill: '#7a8f7f', 'fill-opacity': 0.8 }));
  if (r > 0) plot.append(svg('circle', { class: 'fit-lidar', cx: half, cy: half, r: r * k, fill: 'none', stroke: '#c0392b', 'stroke-width': 2 }));
  const gs = Number(tree.dbh_gs_cm);
  if (gs > 0) plot.append(svg('circle', { class: 'fit-gs', cx: half, cy: half, r: (gs / 200) * k, fill: 'none', stroke: '#2d6b9a', 'stroke-width': 2, 'stroke-dasharray': '5 3' }));
  const scale = svg('text', { x: 8, y: W - 8, 'font-size': 11, fill: '#5f6f63' });
  scale.textContent = 'grid 10 cm';
  plot.append(scale);
  $('#stem-plot').replaceChildren(plot);
  $('#stem-title').textContent = `Tree ${id}`;
  const circle = s.raw && s.raw.dbh && s.raw.dbh.circle ? s.raw.dbh.circle : {};
  const facts = [
    ['DBH LiDAR', r ? `${(2 * r * 100).toFixed(1)} cm` : '—'],
    ['DBH Gaussians', gs > 0 ? `${gs.toFixed(1)} cm` : 'after stage dbh'],
    ['slice height', s.raw && s.raw.dbh ? `${Number(s.raw.dbh.slice_height_m).toFixed(2)} m` : '1.30 m'],
    ['points in slice', String(pts.length)],
    ['arc covered', circle.arc_coverage != null ? `${Math.round(circle.arc_coverage * 100)} %` : (tree.arc_coverage || '—')],
    ['fit RMS', circle.fit && circle.fit.rms != null ? `${(circle.fit.rms * 1000).toFixed(1)} mm` : (tree.rms_mm ? `${tree.rms_mm} mm` : '—')],
    ['lean', s.raw && s.raw.lean_deg != null ? `${s.raw.lean_deg.toFixed(1)}°` : '—'],
    ['quality', (s.raw && s.raw.dbh && s.raw.dbh.quality) || tree.quality || '—'],
  ];
  $('#stem-facts').replaceChildren(...facts.flatMap(([k, v]) => [el('dt', {}, k), el('dd', {}, v)]));
  $('#stem-panel').hidden = false;
}

// ---------------------------------------------------------------- job page lifecycle

async function refreshResults() {
  const names = page.job.artifacts.map((a) => a.name + a.sha256).join('|');
  if (names === page.artifactsSeen) return;
  page.artifactsSeen = names;
  renderArtifacts(page.job);
  const tasks = [renderInventory(), renderRegistration(), renderTraining(), renderViewer()];
  for (const t of tasks) await t.catch((e) => console.warn(e));
}

function onJob(j) {
  if (!j || j.id !== page.id) return;
  page.job = j;
  renderHeader(j);
  renderTimeline(j);
  refreshResults();
}

async function enterJob(id) {
  leaveJob();
  page.id = id;
  page.artifactsSeen = '';
  page.viewerKey = null;
  page.trees = [];
  page.stems = [];
  page.sort = null;
  page.ply = null;
  page.splats = null;
  $('#log').replaceChildren();
  $('#registration').replaceChildren(el('p', { class: 'muted' }, 'Not registered yet.'));
  $('#render-metrics').replaceChildren(el('p', { class: 'muted' }, 'Written by stage train.'));
  $('#loss').replaceChildren();
  $('#views-card').hidden = true;
  $('#trees').hidden = true;
  $('#inventory-downloads').hidden = true;
  $('#inventory-note').hidden = false;
  $('#inventory-plot').hidden = true;
  $('#inventory-charts').hidden = true;
  $('#inventory-summary').textContent = '';
  $('#stem-panel').hidden = true;
  $('#viewer-source').textContent = '';
  $('#viewer-note').hidden = false;
  $('#viewer-note').textContent = 'No 3-D result yet.';
  try {
    onJob(await apiJson(`/v1/jobs/${id}`));
  } catch (e) {
    $('#job-title').textContent = `Job ${id.slice(0, 8)}`;
    $('#job-error').hidden = false;
    $('#job-error').textContent = e.message;
    return;
  }
  page.stop = streamEvents(`/v1/jobs/${id}/events`, (type, data) => {
    if (type === 'job') onJob(data);
    else if (type === 'log' && data) appendLog(data);
    else if (type === 'end') {
      if (data && data.deleted) { location.hash = '#/'; return; }
      apiJson(`/v1/jobs/${id}`).then(onJob).catch(() => {});
    }
  });
}

function stopViewer() {
  if (page.tiles) { page.tiles.destroy(); page.tiles = null; }
  if (page.viewer) { page.viewer.destroy(); page.viewer = null; }
}

function leaveJob() {
  if (page.stop) page.stop();
  page.stop = null;
  page.id = null;
  stopViewer();
}

async function jobAction(path, opts, confirmText) {
  if (confirmText && !confirm(confirmText)) return;
  try {
    const r = await api(`/v1/jobs/${page.id}${path}`, opts);
    if (!r.ok) throw await problem(r);
    if (opts.method === 'DELETE') { location.hash = '#/'; return; }
    onJob(await r.json());
    if (path === '/retry') enterJob(page.id);
  } catch (e) { alert(e.message); }
}

// ---------------------------------------------------------------- routing and start

function route() {
  const m = location.hash.match(/^#\/jobs\/([0-9a-f]{32})/);
  if ($('#view-job').hidden === Boolean(m)) window.scrollTo(0, 0); // a new view opens at its top
  $('#view-jobs').hidden = Boolean(m);
  $('#view-job').hidden = !m;
  if (m) { leaveList(); if (page.id !== m[1]) enterJob(m[1]); } else { leaveJob(); enterList(); }
}

async function serverInfo() {
  try {
    const i = await apiJson('/v1/info');
    const gpu = i.gpu && (i.gpu.name || i.gpu.adapter) ? ` · GPU ${i.gpu.name || i.gpu.adapter}` : '';
    Object.assign(caller, i.caller || {});
    const who = caller.key ? ` · key ${caller.key}${caller.admin ? ' (admin: every owner\'s jobs)' : ''}` : '';
    $('#server-info').textContent = `v${i.version || '?'}${gpu}${who}`;
  } catch { /* the header line is decoration */ }
}

function start() {
  const until = $('#in-until');
  for (const s of STAGES) until.append(el('option', { value: s }, `until ${s}`));
  $('#upload-form').addEventListener('submit', submitPlot);
  $('#job-cancel').addEventListener('click', () => jobAction('/cancel', { method: 'POST' }));
  $('#job-retry').addEventListener('click', () => jobAction('/retry', { method: 'POST', json: {} }));
  $('#job-delete').addEventListener('click', () => jobAction('', { method: 'DELETE' }, 'Delete this job and all its results?'));
  $('#dl-csv').addEventListener('click', () => download(`/v1/jobs/${page.id}/trees.csv`, `trees-${page.id.slice(0, 8)}.csv`));
  $('#dl-geojson').addEventListener('click', () => download(`/v1/jobs/${page.id}/trees.geojson`, `trees-${page.id.slice(0, 8)}.geojson`));
  $('#dl-gpkg').addEventListener('click', () => {
    const a = artifactEnding('trees.gpkg');
    if (a) download(a.href, `trees-${page.id.slice(0, 8)}.gpkg`);
  });
  $('#viewer-colour').addEventListener('change', () => {
    if (!page.viewer || !page.ply || page.tiles || artifact('export/splats.splat')) return;
    page.splats = SylvaViewer.pointsToSplats(page.ply, $('#viewer-colour').value);
    page.viewer.setSplats(page.splats);
  });
  $('#viewer-size').addEventListener('input', () => page.viewer && page.viewer.setScale(Number($('#viewer-size').value)));
  $('#viewer-stems').addEventListener('change', () => page.viewer && page.viewer.setStemsVisible($('#viewer-stems').checked));
  $('#viewer-reset').addEventListener('click', () => page.viewer && page.viewer.reset());
  window.addEventListener('hashchange', route);
  // Who the key is decides whether the list shows owners: ask first, then route.
  serverInfo().finally(route);
}

window.Sylva = { uploadStats, page, parseCsv, streamEvents };
start();
