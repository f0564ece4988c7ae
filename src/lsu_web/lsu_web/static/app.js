// The LSU page: plain ES modules, three.js from the vendored copy (no build step, no CDN).
// Everything the page shows comes from the server (one client of the ROS graph); the page keeps
// only what it draws. window.lsu exposes counters the browser tests read.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';

const $ = (id) => document.getElementById(id);
const lsu = window.lsu = { clientId: 0, pointsDrawn: 0, progressPct: 0, imagesShown: 0, linesDrawn: 0,
                           lastResult: null, state: null, laserOn: null, meshLoaded: false, connected: false,
                           notices: [] };

// ---------------------------------------------------------------- tabs
for (const b of document.querySelectorAll('#tabs button')) {
  b.addEventListener('click', () => showTab(b.dataset.tab));
}
function showTab(name) {
  for (const b of document.querySelectorAll('#tabs button')) b.classList.toggle('active', b.dataset.tab === name);
  for (const s of document.querySelectorAll('.tab')) s.classList.toggle('active', s.id === 'tab-' + name);
  if (name === 'library') loadLibrary();
  if (name === 'faces') loadFaces();
  if (name === 'about') loadAbout();
  if (name === 'calibration') loadCalibration();
  if (name === 'scan') { resize3d(); requestRender(); }
}

// ---------------------------------------------------------------- API
async function api(method, path, body) {
  const opts = { method, headers: {} , credentials: 'same-origin' };
  if (body !== undefined) { opts.headers['Content-Type'] = 'application/json'; opts.body = JSON.stringify(body); }
  const r = await fetch(path, opts);
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  if (!r.ok) {
    let why = data && data.detail;
    if (Array.isArray(why)) why = why.map((d) => `${(d.loc || []).slice(1).join('.')}: ${d.msg}`).join('; ');
    throw new Error(why || `${r.status} ${r.statusText}`);
  }
  return data;
}
function say(el, text, kind) { el.textContent = text; el.className = 'message ' + (kind || 'info'); }
function esc(s) { return String(s).replace(/[&<>"']/g, (c) => ({'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;',"'":'&#39;'}[c])); }

// ---------------------------------------------------------------- 3D view
const view = $('view3d');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
view.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x10141c);
const camera = new THREE.PerspectiveCamera(40, 1, 0.005, 10);
camera.position.set(0, 0, 0.05);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0, -0.3);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.4); sun.position.set(0.3, 0.4, 0.5); scene.add(sun);
// data are in the left camera's optical frame (x right, y down, z forward): turn them so y is up and the
// face looks at the viewer
const world = new THREE.Group(); world.rotation.x = Math.PI; scene.add(world);
let cap = 1 << 17;
let pos = new Float32Array(cap * 3), col = new Float32Array(cap * 3);
const pgeo = new THREE.BufferGeometry();
pgeo.setAttribute('position', new THREE.BufferAttribute(pos, 3));
pgeo.setAttribute('color', new THREE.BufferAttribute(col, 3));
pgeo.setDrawRange(0, 0);
const pmat = new THREE.PointsMaterial({ size: 0.0012, vertexColors: true });
const pts = new THREE.Points(pgeo, pmat); pts.frustumCulled = false; world.add(pts);
let meshObj = null, needFit = true;

function resize3d() {
  const w = view.clientWidth || 600, h = view.clientHeight || 420;
  renderer.setSize(w, h, false); renderer.domElement.style.width = '100%'; renderer.domElement.style.height = '100%';
  camera.aspect = w / h; camera.updateProjectionMatrix();
}
window.addEventListener('resize', () => { resize3d(); requestRender(); });
resize3d();
// drawn on demand (a change of view or data), not every frame: an idle page costs no CPU, and a software-GL
// browser on a busy scanner PC has no render loop to fall behind with
let renderPending = false;
function requestRender() {
  if (renderPending) return;
  renderPending = true;
  requestAnimationFrame(() => { renderPending = false; renderer.render(scene, camera); lsu.frames = (lsu.frames || 0) + 1; });
}
controls.addEventListener('change', requestRender);
requestRender();

function clearPoints() { lsu.pointsDrawn = 0; pgeo.setDrawRange(0, 0); needFit = true; $('points-drawn').textContent = '0';
  if (meshObj) { world.remove(meshObj); meshObj.geometry.dispose(); meshObj = null; } pts.visible = true; lsu.meshLoaded = false; requestRender(); }
function addPoints(xyz, rgb) {
  const n = xyz.length / 3;
  if (lsu.pointsDrawn + n > cap) {
    while (lsu.pointsDrawn + n > cap) cap *= 2;
    const p2 = new Float32Array(cap * 3), c2 = new Float32Array(cap * 3);
    p2.set(pos.subarray(0, lsu.pointsDrawn * 3)); c2.set(col.subarray(0, lsu.pointsDrawn * 3));
    pos = p2; col = c2;
    pgeo.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    pgeo.setAttribute('color', new THREE.BufferAttribute(col, 3));
  }
  pos.set(xyz, lsu.pointsDrawn * 3);
  for (let i = 0; i < n * 3; i++) col[lsu.pointsDrawn * 3 + i] = rgb[i] / 255;
  lsu.pointsDrawn += n;
  pgeo.attributes.position.needsUpdate = true; pgeo.attributes.color.needsUpdate = true;
  pgeo.setDrawRange(0, lsu.pointsDrawn);
  $('points-drawn').textContent = lsu.pointsDrawn.toLocaleString();
  if (needFit && lsu.pointsDrawn > 200) { fit(); needFit = false; }
  renderSoon();
}
// points arrive with every snap (5-30 a second): redraw at most twice a second while they stream
let soon = null;
function renderSoon() { if (soon === null) soon = setTimeout(() => { soon = null; requestRender(); }, 500); }
function fit(object) {
  const box = new THREE.Box3();
  if (object) box.setFromObject(object);
  else {
    pgeo.computeBoundingBox(); box.copy(pgeo.boundingBox); box.applyMatrix4(world.matrixWorld);
  }
  if (box.isEmpty()) return;
  const c = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3()).length() || 0.2;
  controls.target.copy(c);
  camera.position.set(c.x, c.y, c.z + size * 1.4);
  camera.near = size / 100; camera.far = size * 20; camera.updateProjectionMatrix();
  controls.update(); requestRender();
}
$('view3d-reset').addEventListener('click', (e) => { e.preventDefault(); fit(meshObj || undefined); });

function loadMesh(scanId) {
  new PLYLoader().load(`/api/scans/${encodeURIComponent(scanId)}/download/mesh.ply`, (geo) => {
    // open3d writes double coordinates; WebGL draws float32 only
    for (const name of ['position', 'normal']) {
      const a = geo.getAttribute(name);
      if (a && a.array instanceof Float64Array) geo.setAttribute(name, new THREE.Float32BufferAttribute(Float32Array.from(a.array), a.itemSize));
    }
    geo.computeVertexNormals();
    const mat = new THREE.MeshStandardMaterial({ vertexColors: geo.hasAttribute('color'), color: geo.hasAttribute('color') ? 0xffffff : 0xd8c3b0,
                                                 roughness: 0.8, side: THREE.DoubleSide });
    if (meshObj) { world.remove(meshObj); meshObj.geometry.dispose(); }
    meshObj = new THREE.Mesh(geo, mat); world.add(meshObj); world.updateMatrixWorld();
    pts.visible = false; lsu.meshLoaded = true;
    $('view3d-note').textContent = `mesh of ${scanId}: ${(geo.index ? geo.index.count / 3 : geo.attributes.position.count / 3) | 0} triangles`;
    fit(meshObj);
  }, undefined, () => { $('view3d-note').textContent = 'no mesh for this scan (the points stay)'; });
}

// ---------------------------------------------------------------- cameras
const cams = { L: { canvas: $('cam-left'), stamp: 0, w: 0, bitmap: null }, R: { canvas: $('cam-right'), stamp: 0, w: 0, bitmap: null } };
async function showImage(side, stamp, width, height, jpeg) {
  const cam = cams[side];
  const bmp = await createImageBitmap(new Blob([jpeg], { type: 'image/jpeg' }));
  cam.stamp = stamp; cam.w = width; cam.bitmap = bmp;
  const c = cam.canvas;
  if (c.width !== bmp.width || c.height !== bmp.height) { c.width = bmp.width; c.height = bmp.height; }
  c.getContext('2d').drawImage(bmp, 0, 0);
  lsu.imagesShown++;
}
function drawLine(side, stamp, u, v) {
  const cam = cams[side];
  if (cam.stamp !== stamp || !cam.bitmap || u.length < 2) return;
  const c = cam.canvas, g = c.getContext('2d'), s = c.width / cam.w;
  g.strokeStyle = '#ff3b30'; g.lineWidth = 1.5; g.beginPath();
  for (let i = 0; i < u.length; i++) {
    const x = u[i] * s, y = v[i] * s;
    if (i === 0 || Math.abs(v[i] - v[i - 1]) > 8) g.moveTo(x, y); else g.lineTo(x, y);
  }
  g.stroke(); lsu.linesDrawn++;
}

// ---------------------------------------------------------------- live WebSocket
let ws = null;
function connect() {
  ws = new WebSocket((location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws');
  ws.binaryType = 'arraybuffer';
  ws.onopen = () => { lsu.connected = true; chip('chip-link', 'page: live', 'ok'); };
  ws.onclose = () => { lsu.connected = false; lsu.clientId = 0; chip('chip-link', 'page: reconnecting…', 'bad');
                       setTimeout(connect, 1500); };
  ws.onmessage = (ev) => {
    if (typeof ev.data === 'string') { onControl(JSON.parse(ev.data)); return; }
    const buf = ev.data, dv = new DataView(buf), kind = String.fromCharCode(dv.getUint8(0));
    if (kind === 'P') {
      const n = dv.getUint32(1, true);
      const xyz = new Float32Array(buf.slice(5, 5 + n * 12));
      const rgb = new Uint8Array(buf, 5 + n * 12, n * 3);
      if (!meshObj) addPoints(xyz, rgb);
    } else if (kind === 'I') {
      const side = String.fromCharCode(dv.getUint8(1));
      const stamp = dv.getBigInt64(2, true), w = dv.getUint32(10, true), h = dv.getUint32(14, true);
      showImage(side, stamp, w, h, new Uint8Array(buf, 18));
    } else if (kind === 'L') {
      const side = String.fromCharCode(dv.getUint8(1));
      const stamp = dv.getBigInt64(2, true), n = dv.getUint32(10, true);
      const u = new Float32Array(buf.slice(14, 14 + n * 4)), v = new Float32Array(buf.slice(14 + n * 4, 14 + n * 8));
      drawLine(side, stamp, u, v);
    }
  };
}
function chip(id, text, kind) { const c = $(id); c.textContent = text; c.className = 'chip ' + (kind || ''); }

let running = false;
function onControl(m) {
  if (m.type === 'hello') { lsu.clientId = m.client; return; }
  if (m.type === 'state') { onState(m); return; }
  if (m.type === 'progress') { onProgress(m); return; }
  if (m.type === 'result') { onResult(m); return; }
  if (m.type === 'event') { onEvent(m); return; }
  if (m.type === 'notice') { onNotice(m); return; }
  if (m.type === 'laser_hold') {
    if (m.seconds > 0) say($('laser-message'), `laser on for at most ${m.seconds} s`, 'info');
    else if (m.why_off) say($('laser-message'), `laser off: ${m.why_off}`, 'ok');
  }
}
function onState(s) {
  lsu.state = s; lsu.laserOn = s.laser_on;
  chip('chip-connected', s.connected ? `unit: ${s.firmware || 'connected'}` : 'unit: not connected', s.connected ? 'ok' : 'bad');
  chip('chip-homed', s.homed ? 'homed' : 'not homed', s.homed ? 'ok' : 'warn');
  chip('chip-laser', s.laser_on ? 'laser ON' : 'laser off', s.laser_on ? 'warn' : '');
  chip('chip-position', `carriage: ${s.position}${s.moving ? ' → ' + s.target : ''} / ${s.track || '?'}`, '');
  chip('chip-sensors', `ends: start ${s.at_start ? '●' : '○'} end ${s.at_end ? '●' : '○'}`, '');
  $('hw-start').classList.toggle('on', s.at_start); $('hw-end').classList.toggle('on', s.at_end);
  $('hw-pos').textContent = s.position; $('hw-track').textContent = s.track || '?';
  const f = $('fault'); f.classList.toggle('hidden', !s.fault); f.textContent = s.fault ? 'Unit: ' + s.fault : '';
}
function setRunning(r) {
  running = r; $('btn-start').disabled = r; $('btn-cancel').disabled = !r;
}
function onProgress(p) {
  if (p.stage === 'starting') { setRunning(true); return; }
  if (!p.total) return;
  setRunning(true);
  const pct = Math.min(100, Math.round(100 * p.done / p.total));
  lsu.progressPct = pct;
  $('progress-fill').style.width = pct + '%';
  $('progress-text').textContent = `${pct} %` + (p.eta_s != null ? ` · ETA ${p.eta_s.toFixed(1)} s` : '');
  $('progress-detail').textContent = `${p.stage}: ${p.done} / ${p.total}` + (p.position != null ? ` at ${p.position} steps` : '')
      + (p.points != null ? ` · ${p.points.toLocaleString()} points` : '');
}
// a notice from the scan coordinator (its words: "hold still, scanning again" before a rescan), shown until
// the next scan starts from this page
function onNotice(n) {
  lsu.notices.push(n.text);
  const el = $('scan-notice'); el.textContent = n.text; el.classList.remove('hidden');
}
function onEvent(e) {
  if (e.event === 'STARTED' || e.event === 'SWEEP_START') {
    if (e.event === 'STARTED') clearPoints();
    $('view3d-note').textContent = 'points appear as the scan runs';
    setRunning(true);
  }
}
function onResult(r) {
  lsu.lastResult = r; setRunning(false);
  const done = r.outcome === 'SUCCEEDED';
  if (done) { lsu.progressPct = 100; $('progress-fill').style.width = '100%'; $('progress-text').textContent = '100 % · done'; }
  else $('progress-text').textContent = r.outcome.toLowerCase();
  $('progress-detail').textContent = `${r.snaps} snaps, ${r.points.toLocaleString()} points in ${r.seconds} s`;
  const laser = r.laser_on === false ? 'The laser is off.' : r.laser_on ? 'WARNING: the laser is still reported ON.' : 'Laser state unknown.';
  const what = r.outcome === 'CANCELED' ? 'Scan canceled; what was captured is kept.' : r.status;
  say($('scan-message'), `${what.replace(/\.?$/, '.')} ${laser}`, done && r.laser_on === false ? 'ok' : (r.laser_on ? 'bad' : 'info'));
  if (r.scan_id && r.output_dir) showResult(r.scan_id, done && r.points > 0);
}
async function showResult(scanId, withMesh) {
  // the face processor writes the mesh and renders a moment after the scan's end: look a few times
  let meshAsked = false;
  for (let attempt = 0; attempt < 20; attempt++) {
    let d = null;
    try { d = await api('GET', `/api/scans/${encodeURIComponent(scanId)}`); } catch (e) { d = null; }
    if (d) {
      renderResult(d);
      if (d.downloads.includes('mesh.ply') && !meshAsked) { meshAsked = true; if (withMesh) loadMesh(scanId); }
      if (meshAsked && d.images.length) return;
    }
    await new Promise((res) => setTimeout(res, 1500));
  }
}
function summaryRows(d) {
  const rec = d.record || {}, t = rec.timings_s || {}, rows = [['status', d.status], ['mode', d.mode || 'stopsnap'],
    ['snaps', d.snaps_expected != null ? `${d.snaps} of ${d.snaps_expected}` : d.snaps],
    ['points', d.points != null ? d.points.toLocaleString() : ''],
    ['scan time', t.scan != null ? `${t.scan.toFixed(1)} s (mechanical lower bound ${t.mechanical_lower_bound != null ? t.mechanical_lower_bound.toFixed(1) : '?'} s)` : ''],
    ['partial', d.partial ? 'yes: ' + (rec.status || '') : 'no'],
    ['laser pauses', Array.isArray(rec.laser_pauses) ? `${rec.laser_pauses.length}` + (rec.laser_pauses.length ? ` (first: ${rec.laser_pauses[0].why})` : '') : '–'],
    ['calibration', rec.calibration || '']];
  const acc = (rec.demo && rec.demo.accuracy_vs_truth) || rec.accuracy;
  if (acc) for (const [k, v] of Object.entries(acc)) rows.push(['accuracy ' + k.replace(/_/g, ' '), typeof v === 'number' ? v.toFixed(3) : v]);
  else rows.push(['accuracy', 'no accuracy record in scan.json (make demo adds one against the simulator\'s truth; lsu accuracy for the study)']);
  const sw = rec.sweep || {};
  for (const [k, v] of Object.entries(sw)) if (typeof v === 'number') rows.push(['sweep ' + k.replace(/_/g, ' '), v]);
  return rows;
}
function renderResult(d) {
  $('result-card').classList.remove('hidden');
  $('result-id').textContent = d.id + (d.label ? ' · ' + d.label : '');
  $('result-summary').innerHTML = '<table class="summary">' + summaryRows(d).map(([k, v]) => `<tr><td>${esc(k)}</td><td>${esc(v ?? '')}</td></tr>`).join('') + '</table>';
  $('result-renders').innerHTML = d.images.map((n) => `<img alt="${esc(n)}" src="/api/scans/${encodeURIComponent(d.id)}/files/${n.split('/').map(encodeURIComponent).join('/')}">`).join('');
  $('result-downloads').innerHTML = downloadLinks(d);
}
function downloadLinks(d) {
  const names = { 'cloud.ply': 'cloud PLY', 'mesh.ply': 'mesh PLY', 'mesh.obj': 'mesh OBJ', 'mesh.stl': 'mesh STL', 'bag.zip': 'bag', 'scan.json': 'scan.json' };
  const kinds = d.downloads;
  return kinds.map((k) => `<a class="dl" data-kind="${k}" href="/api/scans/${encodeURIComponent(d.id)}/download/${k}" download>${names[k] || k}</a>`).join('');
}

// ---------------------------------------------------------------- scan form
const form = $('scan-form');
form.mode.addEventListener('change', () => {
  const sweep = form.mode.value === 'sweep';
  for (const e of document.querySelectorAll('.sweep-only')) e.classList.toggle('hidden', !sweep);
  for (const e of document.querySelectorAll('.stopsnap-only')) e.classList.toggle('hidden', sweep);
});
form.addEventListener('submit', async (ev) => {
  ev.preventDefault();
  const goal = { mode: form.mode.value, name: form.name.value, start: +form.start.value, end: +form.end.value,
                 step: +form.step.value, settle_s: +form.settle_s.value, sweep_rate: +form.sweep_rate.value,
                 fps: +form.fps.value, texture: form.texture.checked, record_bag: form.record_bag.checked };
  $('btn-start').disabled = true;
  say($('scan-message'), 'starting…', 'info');
  $('scan-notice').classList.add('hidden'); $('scan-notice').textContent = ''; lsu.notices = [];
  clearPoints(); lsu.progressPct = 0; lsu.lastResult = null; $('progress-fill').style.width = '0'; $('progress-text').textContent = '0 %';
  $('result-card').classList.add('hidden');
  try { await api('POST', '/api/scan', goal); say($('scan-message'), 'scanning', 'info'); setRunning(true); }
  catch (e) { say($('scan-message'), 'not started: ' + e.message, 'bad'); setRunning(false); }
});
$('btn-cancel').addEventListener('click', async () => {
  $('btn-cancel').disabled = true;
  try { const r = await api('POST', '/api/scan/cancel'); say($('scan-message'), r.message + ' …', 'info'); }
  catch (e) { say($('scan-message'), 'cancel failed: ' + e.message, 'bad'); $('btn-cancel').disabled = false; }
});

// ---------------------------------------------------------------- library
async function loadLibrary() {
  const box = $('library');
  let data;
  try { data = await api('GET', '/api/scans'); } catch (e) { box.textContent = 'cannot list the scans: ' + e.message; return; }
  $('library-root').textContent = data.root;
  lsu.library = data.scans.map((s) => s.id);
  if (!data.scans.length) { box.innerHTML = '<p class="muted">no scans yet</p>'; return; }
  box.innerHTML = data.scans.map((s) => `<div class="scan-tile" data-id="${esc(s.id)}">
    <div class="thumb">${s.thumbnail ? `<img alt="" src="/api/scans/${encodeURIComponent(s.id)}/files/${s.thumbnail.split('/').map(encodeURIComponent).join('/')}">` : 'no render'}</div>
    <div class="body"><div class="title">${esc(s.label || s.id)}</div>
      <div class="muted small">${esc(s.id)} · ${s.points != null ? s.points.toLocaleString() + ' points' : ''} ${s.seconds != null ? '· ' + Number(s.seconds).toFixed(1) + ' s' : ''}
        ${s.partial ? '<span class="tag bad">partial</span>' : ''} ${s.mode ? `<span class="tag">${esc(s.mode)}</span>` : ''}</div>
      <div class="downloads">${downloadLinks(s)}</div>
      <div class="actions"><button data-act="view">view</button><button data-act="delete" class="danger">delete</button></div></div></div>`).join('');
}
$('library').addEventListener('click', async (ev) => {
  const b = ev.target.closest('button'); if (!b) return;
  const id = b.closest('.scan-tile').dataset.id;
  if (b.dataset.act === 'delete') {
    if (!confirm(`Delete scan ${id} and all its files?`)) return;
    try { await api('DELETE', `/api/scans/${encodeURIComponent(id)}`); } catch (e) { alert('not deleted: ' + e.message); }
    loadLibrary();
  } else if (b.dataset.act === 'view') {
    showTab('scan'); clearPoints(); showResult(id, true);
  }
});
$('library-refresh').addEventListener('click', loadLibrary);

// ---------------------------------------------------------------- faces
async function loadFaces() {
  const sel = $('face-scan'), g = $('gallery');
  try {
    const lib = await api('GET', '/api/scans');
    sel.innerHTML = lib.scans.filter((s) => s.downloads.includes('cloud.ply')).map((s) => `<option value="${esc(s.id)}">${esc(s.label ? s.label + ' · ' + s.id : s.id)}</option>`).join('');
  } catch (e) { sel.innerHTML = ''; }
  try {
    const f = await api('GET', '/api/faces');
    $('btn-enroll').disabled = !f.enrolment;
    if (!f.enrolment) { g.innerHTML = '<p class="muted">This gallery does not allow enrolment through the graph (face_processor allow_enrolment is false): identify only. The gallery\'s owner enrols with <code>lsu face enroll</code>.</p>'; return; }
    g.innerHTML = f.names.length ? f.names.map((n) => `<div class="gallery-row"><span>${esc(n.name)} <span class="muted">(${n.samples} sample${n.samples > 1 ? 's' : ''})</span></span><button data-name="${esc(n.name)}" class="danger small-btn">remove</button></div>`).join('') : '<p class="muted">the gallery is empty</p>';
  } catch (e) { g.textContent = 'gallery not available: ' + e.message; }
}
$('gallery').addEventListener('click', async (ev) => {
  const b = ev.target.closest('button'); if (!b) return;
  if (!confirm(`Remove ${b.dataset.name} (all samples) from the gallery?`)) return;
  try { await api('DELETE', `/api/faces/${encodeURIComponent(b.dataset.name)}`); } catch (e) { say($('face-message'), e.message, 'bad'); }
  loadFaces();
});
$('btn-enroll').addEventListener('click', async () => {
  say($('face-message'), 'enrolling…', 'info');
  try { const r = await api('POST', '/api/faces/enroll', { scan_id: $('face-scan').value, name: $('face-name').value });
        say($('face-message'), `enrolled as entry ${r.entry_id} (${r.points_used} face points)`, 'ok'); loadFaces(); }
  catch (e) { say($('face-message'), 'not enrolled: ' + e.message, 'bad'); }
});
$('btn-identify').addEventListener('click', async () => {
  say($('face-message'), 'identifying…', 'info');
  try { const r = await api('POST', '/api/faces/identify', { scan_id: $('face-scan').value });
        const list = r.matches.map((m) => `${m.name} ${m.score}`).join(', ');
        say($('face-message'), r.accepted ? `identified: ${r.best_name} (${list})` : `no accepted match${list ? ' (' + list + ')' : ''}${r.message ? ': ' + r.message : ''}`, r.accepted ? 'ok' : 'info'); }
  catch (e) { say($('face-message'), 'identify failed: ' + e.message, 'bad'); }
});

// ---------------------------------------------------------------- calibration
function coverageBars(st) {
  if (!st.session) return '<p class="muted">no session: set the board and press New session</p>';
  const bars = st.coverage.map((c) => `<div class="cov"><span>${esc(c.name)}</span><div class="bar small-bar"><div style="width:${Math.round(100 * c.progress)}%"></div></div><span>${Math.round(100 * c.progress)} %</span></div>`).join('');
  return `<p>${st.views} view(s) kept of ${st.captures} captured (need ${st.min_views}); ${st.good_enough ? '<b class="okc">coverage good enough: calibrate</b>' : 'keep moving the board'}</p>${bars}`;
}
function showCal(st) {
  lsu.calibration = st;
  $('cal-coverage').innerHTML = coverageBars(st);
  if (st.last && st.last.accepted !== undefined) say($('cal-message'), st.last.accepted ? 'pair kept' : 'pair not kept: ' + st.last.reason, st.last.accepted ? 'ok' : 'info');
}
async function loadCalibration() {
  try { const st = await api('GET', '/api/calibration'); showCal(st); $('cal-dir').textContent = st.calibration_dir_shown || '?'; }
  catch (e) { say($('cal-message'), e.message, 'bad'); }
  try {
    const lib = await api('GET', '/api/scans');
    const withBag = lib.scans.filter((s) => s.downloads.includes('bag.zip'));
    $('laser-scans').innerHTML = withBag.length ? withBag.map((s) => `<label class="check"><input type="checkbox" value="${esc(s.id)}"> ${esc(s.label || s.id)} <span class="muted">${esc(s.id)}</span></label>`).join('<br>') : '<p class="muted">no scans with a recorded bag yet</p>';
  } catch (e) { $('laser-scans').textContent = e.message; }
}
$('btn-cal-start').addEventListener('click', async () => {
  try { showCal(await api('POST', '/api/calibration/start', { board: $('cal-board').value, square_mm: +$('cal-square').value, min_views: +$('cal-min').value }));
        say($('cal-message'), 'session started: capture pairs', 'ok'); $('cal-result').innerHTML = ''; }
  catch (e) { say($('cal-message'), e.message, 'bad'); }
});
$('btn-cal-capture').addEventListener('click', async () => {
  say($('cal-message'), 'capturing…', 'info');
  try { showCal(await api('POST', '/api/calibration/capture')); } catch (e) { say($('cal-message'), e.message, 'bad'); }
});
$('btn-cal-solve').addEventListener('click', async () => {
  say($('cal-message'), 'calibrating…', 'info');
  try {
    const r = await api('POST', '/api/calibration/solve');
    say($('cal-message'), `written to ${r.folder}`, 'ok');
    $('cal-result').innerHTML = `<table class="summary"><tr><td>overall</td><td>RMS left ${r.left_rms_px.toFixed(3)} px, right ${r.right_rms_px.toFixed(3)} px, stereo ${r.stereo_rms_px.toFixed(3)} px; baseline ${r.baseline_mm.toFixed(2)} mm</td></tr>` +
      r.views.map((v) => `<tr><td>view ${esc(v.name)}</td><td>left ${v.left_px.toFixed(3)} px, right ${v.right_px.toFixed(3)} px ${v.used ? '' : '<span class="tag bad">dropped: ' + esc(v.reason) + '</span>'}</td></tr>`).join('') + '</table>';
  } catch (e) { say($('cal-message'), 'not calibrated: ' + e.message, 'bad'); }
});
$('btn-laser-fit').addEventListener('click', async () => {
  const ids = [...document.querySelectorAll('#laser-scans input:checked')].map((i) => i.value);
  say($('laser-cal-message'), 'fitting…', 'info');
  try {
    const r = await api('POST', '/api/calibration/laser', { scan_ids: ids });
    say($('laser-cal-message'), `laser.yaml written to ${r.folder}`, 'ok');
    $('laser-cal-result').innerHTML = `<table class="summary"><tr><td>overall</td><td>RMS ${r.residual_mm.toFixed(3)} mm over ${r.points} points (${r.rejected} trimmed)</td></tr>` +
      r.scans.map((x) => `<tr><td>${esc(x.name)}</td><td>${x.points} points, RMS ${x.rms_mm.toFixed(3)} mm, max ${x.max_mm.toFixed(3)} mm, flatness ${x.flatness_rms_mm.toFixed(3)} mm</td></tr>`).join('') + '</table>';
  } catch (e) { say($('laser-cal-message'), 'not fitted: ' + e.message, 'bad'); }
});

// ---------------------------------------------------------------- hardware
async function hw(path, body, el) {
  say(el, 'working…', 'info');
  try { const r = await api('POST', path, body); say(el, r.message || (r.position != null ? `at ${r.position} steps` : 'done'), 'ok'); }
  catch (e) { say(el, e.message, 'bad'); }
}
$('btn-home').addEventListener('click', () => hw('/api/hardware/home', undefined, $('hw-message')));
$('btn-move').addEventListener('click', () => hw('/api/hardware/move', { position: +$('move-to').value }, $('hw-message')));
$('btn-laser-on').addEventListener('click', () => hw('/api/hardware/laser', { on: true, seconds: +$('laser-seconds').value, client: lsu.clientId }, $('laser-message')));
$('btn-laser-off').addEventListener('click', () => hw('/api/hardware/laser', { on: false }, $('laser-message')));

// ---------------------------------------------------------------- about
function table(el, obj) {
  el.innerHTML = Object.entries(obj).map(([k, v]) => `<tr><td>${esc(k)}</td><td>${esc(typeof v === 'object' ? JSON.stringify(v) : v)}</td></tr>`).join('');
}
async function loadAbout() {
  try {
    const a = await api('GET', '/api/about');
    table($('about-versions'), { ...a.versions, ROS: a.ros_distro });
    table($('about-server'), { ...a.server, ROS_DOMAIN_ID: a.ros_domain_id });
    $('about-nodes').innerHTML = a.nodes.map((n) => `<li>${esc(n)}</li>`).join('');
    table($('about-coordinator'), a.scan_coordinator);
  } catch (e) { $('about-versions').innerHTML = `<tr><td>${esc(e.message)}</td></tr>`; }
}

// ---------------------------------------------------------------- start
connect();
api('GET', '/api/status').then((s) => { if (s.state) onState(s.state); if (s.scanning) setRunning(true); }).catch(() => {});
const tab = new URLSearchParams(location.search).get('tab'); if (tab) showTab(tab);
