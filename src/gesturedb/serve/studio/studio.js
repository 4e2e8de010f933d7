// The gesturedb studio: speech in (microphone or a WAV file), the body out, in sync;
// the database's masks as live toggles; a timeline of where every window came from.
// Everything comes from this server: three.js and its glTF loader are Debian's libjs-three, under
// /vendor/three/ in Debian's layout (the loader imports ../../../build/three.module.js: the same module).
// The protocol is docs/live.md; window.studio exposes the page's state (the browser test reads it).

const $ = (id) => document.getElementById(id);
const S = (window.studio = {
  health: null, skeleton: null, ready: null, threeLoaded: false, streaming: false, mode: null,
  framesReceived: 0, frames: [], steps: [], controlAcks: [], errors: [], log: [], late: 0, shownFrame: -1,
  done: null, closed: null, preview: null, character: null,
});
const JITTER_S = 0.3;       // played this much after the algorithmic latency: room for network and scheduling
const PX_PER_S = 90;        // timeline scale: a 0.53 s window is 48 px wide

function log(text, isError = false) {
  S.log.push(text);
  if (isError) S.errors.push(text);
  const li = document.createElement('li');
  li.textContent = text;
  if (isError) li.className = 'error';
  $('log').prepend(li);
}
function banner(text) { const b = $('banner'); b.hidden = false; b.textContent = text; }
async function getJSON(path) {
  const r = await fetch(path);
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

// ---- three.js -----------------------------------------------------------------------
let THREE = null;
try {
  THREE = await import('/vendor/three/build/three.module.js');
  S.threeLoaded = true;
} catch (e) {
  banner('three.js is missing on the server (Debian package libjs-three: apt-get install libjs-three), ' +
         'so the body cannot be drawn; frames and the timeline still work.');
}

const [health, skel, ctrls] = await Promise.all([getJSON('/health'), getJSON('/skeleton'), getJSON('/controls')]);
S.health = health; S.skeleton = skel;
const fps = skel.fps, J = skel.names.length, W = skel.frame_floats;
$('status').textContent = `${health.database} · ${(health.frames / health.fps / 60).toFixed(1)} min of motion · ` +
  `${J} joints · ${fps} fps` + (health.stream ? '' : ' · offline only');
if (!health.stream) $('mic').disabled = true;
if (!health.stream) banner(`${health.stream_error || 'Live streaming is not available.'} A WAV file is synthesized ` +
                           'offline instead; the microphone needs live streaming.');

// ---- the body -------------------------------------------------------------------------
const view = { renderer: null, scene: null, camera: null, bones: [], joints: [], target: null };
const wq = [], wp = [], offs = [];
function setupScene() {
  const canvas = $('view');
  const r = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  r.setPixelRatio(window.devicePixelRatio || 1);
  r.setClearColor(0xe9ecef);
  const scene = new THREE.Scene();
  scene.add(new THREE.HemisphereLight(0xffffff, 0x8899aa, 0.9));
  const sun = new THREE.DirectionalLight(0xffffff, 0.6);
  sun.position.set(1, 3, 2);
  scene.add(sun);
  scene.add(new THREE.GridHelper(8, 16, 0x9aa5b1, 0xc8d0d8));
  const camera = new THREE.PerspectiveCamera(30, 1, 0.05, 100);
  const boneMat = new THREE.MeshLambertMaterial({ color: 0x2b6cb0 });
  const jointMat = new THREE.MeshLambertMaterial({ color: 0xc05621 });
  const cyl = new THREE.CylinderBufferGeometry(1, 1, 1, 10);
  const ball = new THREE.SphereBufferGeometry(1, 12, 8);
  for (let j = 0; j < J; j++) {
    offs.push(new THREE.Vector3(...skel.offsets[j]));
    wq.push(new THREE.Quaternion());
    wp.push(new THREE.Vector3());
    const len = offs[j].length();
    const small = j > 0 && len < 0.06;                  // fingers and toes: thinner
    const isHead = /head/i.test(skel.names[j]) && !/end|top/i.test(skel.names[j]);
    const jm = new THREE.Mesh(ball, jointMat);
    jm.scale.setScalar(isHead ? 0.075 : small ? 0.008 : 0.022);
    scene.add(jm);
    view.joints.push(jm);
    if (j > 0) {
      const bm = new THREE.Mesh(cyl, boneMat);
      bm.userData.radius = small ? 0.005 : 0.016;
      scene.add(bm);
      view.bones.push(bm);
    } else view.bones.push(null);
  }
  Object.assign(view, { renderer: r, scene, camera });
  const resize = () => {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    r.setSize(w, h, false);
    camera.aspect = w / Math.max(h, 1);
    camera.updateProjectionMatrix();
  };
  window.addEventListener('resize', resize);
  resize();
}

const UP = THREE ? new THREE.Vector3(0, 1, 0) : null;
const _q = THREE ? new THREE.Quaternion() : null, _d = THREE ? new THREE.Vector3() : null;
function pose(row) {
  view.lastRow = row;
  // forward kinematics: p[j] = p[parent] + R[parent] offsets[j]; R[j] = R[parent] q[j]
  for (let j = 0; j < J; j++) {
    const o = 3 + 4 * j;
    _q.set(row[o + 1], row[o + 2], row[o + 3], row[o]);
    const p = skel.parents[j];
    if (p < 0) {
      wq[j].copy(_q);
      wp[j].set(row[0], row[1], row[2]);
    } else {
      wq[j].copy(wq[p]).multiply(_q);
      wp[j].copy(offs[j]).applyQuaternion(wq[p]).add(wp[p]);
    }
  }
  for (let j = 0; j < J; j++) {
    view.joints[j].position.copy(wp[j]);
    const b = view.bones[j];
    if (!b) continue;
    const a = wp[skel.parents[j]];
    _d.subVectors(wp[j], a);
    const len = _d.length();
    b.position.addVectors(a, wp[j]).multiplyScalar(0.5);
    b.scale.set(b.userData.radius, Math.max(len, 1e-4), b.userData.radius);
    if (len > 1e-6) b.quaternion.setFromUnitVectors(UP, _d.divideScalar(len));
  }
  if (view.character) poseCharacter();
  frameBody();
}

// The camera faces the body (the speaker faces +z) from as far as its whole height and width need,
// head to feet with a margin; it follows slowly so that a gesture does not shake the view.
const _box = THREE ? new THREE.Box3() : null, _p = THREE ? new THREE.Vector3() : null;
function frameBody() {
  _box.makeEmpty();
  if (view.character) for (const n of view.character.framed) _box.expandByPoint(n.getWorldPosition(_p));
  else for (let j = 0; j < J; j++) _box.expandByPoint(wp[j]);
  const lo = _box.min, hi = _box.max;
  const head = 0.12;                                   // the head's top above its highest joint
  const h = hi.y + head - Math.min(lo.y, 0) + 0.2;     // and the floor under the feet: 0.1 m each side
  const w = Math.max(hi.x - lo.x, 0.6) + 0.3;
  const tanHalf = Math.tan((view.camera.fov * Math.PI) / 360);
  const dist = Math.max(h / 2 / tanHalf, w / 2 / (tanHalf * view.camera.aspect)) + (hi.z - lo.z) / 2;
  const t = new THREE.Vector3((lo.x + hi.x) / 2, (Math.min(lo.y, 0) - 0.1 + hi.y + head + 0.1) / 2, (lo.z + hi.z) / 2);
  if (!view.target) { view.target = t; view.dist = dist; } else { view.target.lerp(t, 0.05); view.dist += 0.05 * (dist - view.dist); }
  // the slow follow never lets the body leave the view: a hand thrown up faster than the camera follows
  // moves it back at once, as far as the lagging target needs for the head, the feet and the hands
  const up = hi.y + head + 0.1 - view.target.y, down = view.target.y - (Math.min(lo.y, 0) - 0.1);
  const side = Math.max(hi.x + 0.15 - view.target.x, view.target.x - (lo.x - 0.15));
  const need = Math.max(Math.max(up, down) / tanHalf, side / (tanHalf * view.camera.aspect)) + (hi.z - lo.z) / 2;
  view.dist = Math.max(view.dist, need);
  view.camera.position.set(view.target.x, view.target.y, view.target.z + view.dist);
  view.camera.lookAt(view.target);
}

// the drawn body's vertical extent on screen, head top and floor under the feet included
// (normalised device coordinates, -1 bottom to 1 top): the browser test checks the framing with it
S.bodyExtent = () => {
  const pts = view.character ? view.character.framed.map((n) => n.getWorldPosition(new THREE.Vector3()))
                             : wp.map((p) => p.clone());
  const top = pts.reduce((a, p) => (p.y > a.y ? p : a), pts[0]).clone();
  top.y += 0.12;
  const ys = pts.concat([top]).map((p) => p.clone().project(view.camera).y);
  return [Math.min(...ys), Math.max(...ys)];
};

// ---- your character ----------------------------------------------------------------------------
// A rigged .glb (or a .gltf with its buffers inside) read in this page, never sent anywhere. Its nodes
// are matched to the database's joints by name (case, separators and a "prefix:" such as mixamorig:
// ignored); a matched node takes its joint's world rotation relative to the rest pose (both rigs'
// rest poses must point the limbs the same way, as gesturedb's own .glb and a T-pose do), the others
// keep their rest pose, and the root moves with the database's root scaled by the hips' heights.
const normName = (n) => String(n).toLowerCase().replace(/^.*[:|]/, '').replace(/[^a-z0-9]/g, '');
async function loadCharacter(file) {
  if (!THREE || !view.renderer) throw new Error('three.js is missing on the server, so nothing can be drawn');
  let GLTFLoader;
  try {
    ({ GLTFLoader } = await import('/vendor/three/examples/jsm/loaders/GLTFLoader.js'));
  } catch (e) {
    throw new Error("three.js's glTF loader is not on the server (Debian's libjs-three: " +
                    'examples/jsm/loaders/GLTFLoader.js), so a character cannot be read');
  }
  const data = await file.arrayBuffer();
  const gltf = await new Promise((resolve, reject) => new GLTFLoader().parse(data, '', resolve, (e) =>
    reject(new Error(`${e.message || e} (a .gltf must hold its buffers inside: pick the .glb)`))));
  const root = gltf.scene;
  root.traverse((n) => { n.frustumCulled = false; });  // a skinned mesh's bounds are those of its rest pose
  root.updateMatrixWorld(true);
  const order = [];                                    // every node, parents first
  root.traverse((n) => { if (n !== root) order.push(n); });
  const byName = new Map();
  for (const n of order) {                             // a skin's bones first, then other nodes of that name
    const k = normName(n.name || '');
    if (k && (!byName.has(k) || (n.isBone && !byName.get(k).isBone))) byName.set(k, n);
  }
  const joint = new Map(), unmatched = [];
  skel.names.forEach((name, j) => {
    const n = byName.get(normName(name));
    if (n && !joint.has(n)) joint.set(n, j); else unmatched.push(name);
  });
  if (!joint.size) {
    const some = [...byName.values()].filter((n) => n.isBone).slice(0, 8).map((n) => n.name);
    throw new Error(`none of the database's joints (${skel.names.slice(0, 6).join(', ')}, ...) names a node of ` +
                    `${file.name}` + (some.length ? ` (its bones: ${some.join(', ')}, ...)` : ' (it has no bones)'));
  }
  const undriven = order.filter((n) => n.isBone && !joint.has(n)).map((n) => n.name);
  const nodes = order.map((n) => ({
    n, j: joint.has(n) ? joint.get(n) : -1, restLocal: n.quaternion.clone(),
    restWorld: n.getWorldQuaternion(new THREE.Quaternion()), world: new THREE.Quaternion(),
  }));
  const index = new Map(nodes.map((x, i) => [x.n, i]));
  const hips = nodes.find((x) => x.j === 0);
  const dbHipY = skel.offsets[0][1];
  const charHipY = hips ? hips.n.getWorldPosition(new THREE.Vector3()).y : 0;
  view.character = {
    root, nodes, index, hips, rootWorld: root.getWorldQuaternion(new THREE.Quaternion()),
    scale: hips && dbHipY > 0 && charHipY > 0 ? charHipY / dbHipY : 1,
    framed: nodes.filter((x) => x.j >= 0).map((x) => x.n), name: file.name,
  };
  if (view.characterRoot) view.scene.remove(view.characterRoot);
  view.characterRoot = root;
  view.scene.add(root);
  for (const m of view.joints.concat(view.bones)) if (m) m.visible = false;
  S.character = { name: file.name, matched: joint.size, joints: J, unmatched, undriven,
                  scale: view.character.scale };
  return S.character;
}
function showSkeleton() {
  if (view.characterRoot) view.scene.remove(view.characterRoot);
  view.character = null; view.characterRoot = null; S.character = null;
  for (const m of view.joints.concat(view.bones)) if (m) m.visible = true;
}
const _inv = THREE ? new THREE.Quaternion() : null, _v = THREE ? new THREE.Vector3() : null;
function poseCharacter() {
  const c = view.character;
  for (const x of c.nodes) {
    const parentW = x.n.parent === c.root ? c.rootWorld : c.nodes[c.index.get(x.n.parent)].world;
    if (x.j >= 0) {
      x.world.copy(wq[x.j]).multiply(x.restWorld);     // the joint's rotation from rest, on the node's rest
      x.n.quaternion.copy(_inv.copy(parentW).inverse().multiply(x.world));
    } else {
      x.n.quaternion.copy(x.restLocal);
      x.world.copy(parentW).multiply(x.restLocal);
    }
  }
  if (c.hips) {
    const par = c.hips.n.parent;
    par.updateWorldMatrix(true, false);
    c.hips.n.position.copy(par.worldToLocal(_v.copy(wp[0]).multiplyScalar(c.scale)));
  }
  c.root.updateMatrixWorld(true);
}

function restRow() {
  const row = new Float32Array(W);
  row.set(skel.offsets[0], 0);
  for (let j = 0; j < J; j++) row[3 + 4 * j] = 1;
  return row;
}
const listed = (names) => (names.length > 24 ? `${names.slice(0, 24).join(', ')} and ${names.length - 24} more`
                                             : names.join(', '));
$('character').addEventListener('change', async (ev) => {
  const file = ev.target.files[0];
  ev.target.value = '';
  if (!file) return;
  const msg = $('character-msg');
  try {
    const c = await loadCharacter(file);
    if (S.shownFrame >= 0 && S.frames[S.shownFrame]) pose(S.frames[S.shownFrame]); else if (view.lastRow) pose(view.lastRow);
    msg.className = c.unmatched.length ? 'warn' : '';
    msg.textContent = `${file.name}: ${c.matched} of ${c.joints} joints of the database drive its bones` +
      (c.unmatched.length ? `; joints with no bone of that name (not shown): ${listed(c.unmatched)}` : '') +
      (c.undriven.length ? `; its bones no joint names (kept in their rest pose): ${listed(c.undriven)}` : '');
    $('skeleton-view').disabled = false;
    log(`character ${file.name}: ${c.matched} of ${c.joints} joints matched`);
  } catch (e) {
    msg.className = 'warn';
    msg.textContent = `${file.name}: ${e.message}`;
    log(`character ${file.name}: ${e.message}`, true);
  }
});
$('skeleton-view').addEventListener('click', () => {
  showSkeleton();
  $('skeleton-view').disabled = true;
  $('character-msg').className = '';
  $('character-msg').textContent = "the body is drawn as the database's skeleton";
  if (view.lastRow) pose(view.lastRow);
});

if (THREE) {
  try { setupScene(); pose(restRow()); } catch (e) { banner(`The 3D view could not start (${e.message}).`); THREE = null; }
}
// until speech comes, the body stands as in the database's first frame (the rest pose is a T)
if (THREE && ctrls.recordings.length) {
  fetch(`/source?${new URLSearchParams({ recording: ctrls.recordings[0], start_s: 0, end_s: 0.2 })}`)
    .then((r) => (r.ok ? r.arrayBuffer() : null))
    .then((b) => { if (b && S.shownFrame < 0) { view.target = null; pose(parseFrames(b).rows[0]); } S.idlePose = true; })
    .catch(() => { S.idlePose = true; });
}

// ---- frames in ---------------------------------------------------------------------------
const decoder = new TextDecoder();
function parseFrames(buf) {
  const dv = new DataView(buf);
  const magic = String.fromCharCode(dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3));
  if (magic !== 'GDBF' || dv.getUint32(4, true) !== 1) throw new Error('not a frames message of layout 1');
  const start = dv.getUint32(8, true), count = dv.getUint32(12, true), nj = dv.getUint32(16, true);
  const tail = dv.getUint32(20, true), w = 3 + 4 * nj;   // header field 24: the samples received (unused here)
  const data = new Float32Array(buf, 28, count * w);
  const steps = tail ? JSON.parse(decoder.decode(new Uint8Array(buf, 28 + count * w * 4, tail))) : [];
  const rows = [];
  for (let i = 0; i < count; i++) rows.push(data.subarray(i * w, (i + 1) * w));
  return { start, rows, steps };
}
function takeFrames(buf) {
  const f = parseFrames(buf);
  f.rows.forEach((row, i) => { S.frames[f.start + i] = row; });
  S.framesReceived = Math.max(S.framesReceived, f.start + f.rows.length);
  f.steps.forEach(addStep);
  $('framecount').textContent = `${S.framesReceived} frames`;
}

// ---- the timeline ------------------------------------------------------------------------
// one hue per recording, spread by the golden angle so that neighbours differ (a mirrored copy too)
const hue = (name) => { const i = ctrls.recordings.indexOf(name); return i < 0 ? 0 : (150 + i * 137.508) % 360; };
let lastCtl = null;
function addStep(st) {
  S.steps.push(st);
  const x = (st.out_start / fps) * PX_PER_S, w = ((st.out_end - st.out_start) / fps) * PX_PER_S;
  const el = document.createElement('div');
  el.className = 'step';
  el.style.left = `${x}px`;
  el.style.width = `${w}px`;
  const src = st.source_start_s != null ? Number(st.source_start_s) : 0;
  el.style.background = `hsl(${hue(st.recording || '')}, 45%, ${38 + (src * 7) % 24}%)`;
  // colour: the recording (hue) and the moment in it (lightness); text: moment, ranks, recording
  el.innerHTML = '';
  for (const line of [`${src.toFixed(1)} s`, `p${st.pose_rank ?? '-'} a${st.audio_rank ?? '-'}`,
                      (st.recording || '?').endsWith('~mirror') ? `mirror ${st.recording.replace(/~mirror$/, '')}` : st.recording || '?']) {
    const d = document.createElement('div'); d.textContent = line; el.appendChild(d);
  }
  el.title = `step ${st.step}: output ${(st.out_start / fps).toFixed(2)}-${(st.out_end / fps).toFixed(2)} s\n` +
    `from ${st.recording} ${src.toFixed(2)}-${Number(st.source_end_s).toFixed(2)} s\n` +
    `pose rank ${st.pose_rank}, audio rank ${st.audio_rank}` +
    (st.pose_dist != null ? `, pose distance ${Number(st.pose_dist).toFixed(3)}` : '') +
    (st.audio_dist != null ? `, audio distance ${Number(st.audio_dist).toFixed(3)}` : '') +
    `\ncontrol: ${st.control ?? 'none'}` + (st.keyword ? `\nkeyword: ${st.keyword}` : '');
  el.dataset.control = st.control ?? '';
  el.addEventListener('click', () => playSource(st));
  $('steps').appendChild(el);
  const lanes = $('lanes');
  lanes.style.width = `${Math.max(lanes.clientWidth, x + w + 40)}px`;
  if (st.control) {
    if (lastCtl && lastCtl.control === st.control && lastCtl.end === st.out_start) {
      lastCtl.end = st.out_end;
      lastCtl.el.style.width = `${((lastCtl.end - lastCtl.start) / fps) * PX_PER_S}px`;
    } else {
      const c = document.createElement('div');
      c.className = 'ctl';
      c.style.left = `${x}px`;
      c.style.width = `${w}px`;
      c.textContent = c.title = st.control;
      $('controls').appendChild(c);
      lastCtl = { control: st.control, start: st.out_start, end: st.out_end, el: c };
    }
  } else lastCtl = null;
}

// The stretch of the recording a step copied, with the recording's own speech when the server has
// its file (the database keeps the path the build was given); the body follows the sound's clock.
async function playSource(st) {
  try {
    const q = new URLSearchParams({ recording: st.recording, start_s: st.source_start_s, end_s: st.source_end_s });
    const [r, a] = await Promise.all([fetch(`/source?${q}`), fetch(`/source?${q}&format=wav`)]);
    if (!r.ok) throw new Error((await r.json()).message);
    const f = parseFrames(await r.arrayBuffer());
    const what = `${st.recording} ${Number(st.source_start_s).toFixed(2)}-${Number(st.source_end_s).toFixed(2)} s`;
    let sound = null, why = null;
    if (a.ok) {
      try {
        if (!ctx) ctx = new AudioContext();
        await ctx.resume();
        sound = ctx.createBufferSource();
        sound.buffer = await ctx.decodeAudioData(await a.arrayBuffer());
        sound.connect(ctx.destination);
      } catch (e) { sound = null; why = `its speech could not be played here (${e.message})`; }
    } else why = (await a.json()).message;
    if (S.preview && S.preview.sound) try { S.preview.sound.stop(); } catch (e) { /* ended */ }
    const at = sound ? ctx.currentTime + 0.05 : null;
    if (sound) sound.start(at);
    S.preview = { rows: f.rows, t0: performance.now() + (sound ? 50 : 0), sound, at };
    S.sourcePlayed = { recording: st.recording, frames: f.rows.length, audio: !!sound, why };
    log(`playing the source: ${what}` + (sound ? ', with its speech' : `, without sound: ${why}`));
  } catch (e) { log(`source: ${e.message}`, true); }
}

// ---- controls -----------------------------------------------------------------------------
const chosen = new Set();
for (const m of ctrls.masks) {
  const c = document.createElement('span');
  c.className = 'chip';
  c.textContent = m.name.replace(/_/g, ' ');
  c.title = m.definition || m.name;
  c.dataset.mask = m.name;
  c.addEventListener('click', () => {
    if (chosen.has(m.name)) chosen.delete(m.name); else chosen.add(m.name);
    c.classList.toggle('on', chosen.has(m.name));
    $('expr').value = '';
    sendControl();
  });
  $('masks').appendChild(c);
}
if (!ctrls.masks.length) $('masks').textContent = 'this database has no saved masks';
$('apply').addEventListener('click', () => {
  chosen.clear();
  document.querySelectorAll('.chip.on').forEach((c) => c.classList.remove('on'));
  sendControl();
});
$('expr').addEventListener('keydown', (e) => { if (e.key === 'Enter') $('apply').click(); });
function currentControl() {
  const e = $('expr').value.trim();
  if (e) return e;
  return chosen.size ? [...chosen].join(' and ') : null;
}
function sendControl() {
  const c = currentControl();
  $('control-now').textContent = c ? `asked: ${c}` : 'no control: the whole database';
  if (ws && ws.readyState === WebSocket.OPEN && S.ready) ws.send(JSON.stringify({ type: 'control', control: c }));
}

// ---- audio and the stream ----------------------------------------------------------------
let ctx = null, ws = null, cap = null, srcNode = null, stopSource = null, workletLoaded = false, delayS = 0;
async function audioContext() {
  if (!ctx) ctx = new AudioContext();
  await ctx.resume();
  if (!workletLoaded) { await ctx.audioWorklet.addModule('/studio/capture-worklet.js'); workletLoaded = true; }
  return ctx;
}

function resetSession() {
  Object.assign(S, { ready: null, framesReceived: 0, frames: [], steps: [], controlAcks: [], late: 0, shownFrame: -1,
                     done: null, closed: null, t0: null, preview: null });
  lastCtl = null;
  $('steps').innerHTML = ''; $('controls').innerHTML = '';
  for (const f of ['bvh', 'glb', 'npz']) { const a = $(`dl-${f}`); a.classList.add('disabled'); a.removeAttribute('href'); a.onclick = null; }
}

function openStream() {
  return new Promise((resolve, reject) => {
    ws = new WebSocket(`${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/stream`);
    ws.binaryType = 'arraybuffer';
    ws.onopen = () => ws.send(JSON.stringify({ type: 'start', sample_rate: ctx.sampleRate, format: 'f32',
                                               control: currentControl() }));
    ws.onmessage = (ev) => {
      if (typeof ev.data !== 'string') { takeFrames(ev.data); return; }
      const m = JSON.parse(ev.data);
      if (m.type === 'ready') {
        S.ready = m;
        log(`live: ${m.fps} fps, latency ${m.latency_s.toFixed(2)} s at ${m.sample_rate} Hz`);
        resolve(m);
      } else if (m.type === 'error') {
        log(`${m.code}: ${m.message}`, true);
        if (m.fatal) reject(new Error(m.message));
      } else if (m.type === 'control') {
        S.controlAcks.push(m);
        $('control-now').textContent = m.control ? `in force from frame ${m.from_frame}: ${m.control}` : 'no control: the whole database';
      } else if (m.type === 'done') {
        S.done = m;
        log(`done: ${m.frames} frames`);
        if (m.result) for (const f of ['bvh', 'glb', 'npz']) {
          const a = $(`dl-${f}`); a.href = `${m.result}?format=${f}`; a.classList.remove('disabled');
        }
      }
    };
    ws.onclose = (ev) => {
      S.closed = { code: ev.code, reason: ev.reason };
      if (ev.code !== 1000) log(`stream closed (${ev.code}${ev.reason ? ': ' + ev.reason : ''})`, ev.code !== 1000);
      reject(new Error(`closed ${ev.code}`));
      endUi();
    };
    ws.onerror = () => reject(new Error('the stream could not be opened'));
  });
}

async function begin(node, { audible, label }) {
  await audioContext();
  resetSession();
  await openStream();
  delayS = S.ready.latency_s + JITTER_S;
  cap = new AudioWorkletNode(ctx, 'gesturedb-capture', { processorOptions: { blockSamples: 2048 } });
  cap.port.onmessage = (e) => { if (S.streaming && ws.readyState === WebSocket.OPEN) ws.send(e.data.buffer); };
  node.connect(cap);
  const out = audible ? ctx.createDelay(10) : ctx.createGain();
  if (audible) out.delayTime.value = delayS; else out.gain.value = 0;   // the microphone is not played back
  cap.connect(out).connect(ctx.destination);
  srcNode = node;
  S.t0 = ctx.currentTime;
  S.streaming = true;
  S.mode = label;
  $('stop').disabled = false; $('mic').disabled = true;
  $('source-name').textContent = label;
}

function stop() {
  if (!S.streaming) return;
  S.streaming = false;
  if (cap) cap.port.postMessage('flush');
  try { if (stopSource) stopSource(); } catch (e) { /* already stopped */ }
  // the flushed block is sent before the end (the worklet answers within a render quantum)
  setTimeout(() => {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: 'end' }));
    try { srcNode && srcNode.disconnect(); cap && cap.disconnect(); } catch (e) { /* gone */ }
  }, 150);
  $('stop').disabled = true;
}
function endUi() { S.streaming = false; $('stop').disabled = true; $('mic').disabled = !health.stream; }

$('mic').addEventListener('click', async () => {
  if (!health.stream) { log('the microphone needs live streaming, which this server does not have', true); return; }
  try {
    const media = await navigator.mediaDevices.getUserMedia({
      audio: { echoCancellation: false, noiseSuppression: false, autoGainControl: false, channelCount: 1 } });
    await audioContext();
    stopSource = () => media.getTracks().forEach((t) => t.stop());
    await begin(ctx.createMediaStreamSource(media), { audible: false, label: 'microphone' });
  } catch (e) { log(`microphone: ${e.message}`, true); endUi(); }
});
$('stop').addEventListener('click', stop);
$('wav').addEventListener('change', async (ev) => {
  const file = ev.target.files[0];
  ev.target.value = '';
  if (!file) return;
  try {
    await audioContext();
    const buf = await ctx.decodeAudioData(await file.arrayBuffer());
    if (!health.stream) { await offline(file, buf); return; }
    const src = ctx.createBufferSource();
    src.buffer = buf;
    stopSource = () => src.stop();
    src.onended = () => stop();
    await begin(src, { audible: true, label: file.name });
    src.start();
  } catch (e) { log(`${file.name}: ${e.message}`, true); endUi(); }
});

async function offline(file, buf) {
  // no live stream on this server: the whole file is synthesized first, then played in sync
  resetSession();
  log(`synthesizing ${file.name} offline…`);
  const r = await fetch('/synth?format=frames', { method: 'POST', body: file, headers: { 'content-type': 'audio/wav' } });
  if (!r.ok) { log(`synthesis: ${(await r.json()).message}`, true); return; }
  takeFrames(await r.arrayBuffer());
  for (const f of ['bvh', 'glb', 'npz']) {
    const a = $(`dl-${f}`); a.classList.remove('disabled'); a.href = '#';
    a.onclick = async (e) => {
      e.preventDefault();
      const x = await fetch(`/synth?format=${f}`, { method: 'POST', body: file, headers: { 'content-type': 'audio/wav' } });
      const url = URL.createObjectURL(await x.blob());
      const tmp = document.createElement('a'); tmp.href = url; tmp.download = `gesturedb.${f}`; tmp.click();
    };
  }
  const src = ctx.createBufferSource();
  src.buffer = buf;
  src.connect(ctx.destination);
  delayS = 0;
  S.t0 = ctx.currentTime;
  S.mode = file.name;
  src.start();
}

// ---- drawing -------------------------------------------------------------------------------
let lateSeen = -1;
function frame() {
  requestAnimationFrame(frame);
  let row = null;
  if (S.preview) {
    const p = S.preview;
    const i = Math.max(0, Math.floor((p.sound ? ctx.currentTime - p.at : (performance.now() - p.t0) / 1000) * fps));
    if (i < S.preview.rows.length) row = S.preview.rows[i]; else S.preview = null;
  }
  if (!row && S.t0 != null && ctx) {
    const t = ctx.currentTime - S.t0 - delayS;
    const i = Math.floor(t * fps);
    $('clock').textContent = `${Math.max(t, 0).toFixed(1)} s`;
    if (i >= 0) {
      const last = S.framesReceived - 1;
      if (i > last && S.streaming && i > lateSeen) { S.late += 1; lateSeen = i; $('late').textContent = `${S.late} late`; }
      const k = Math.min(i, last);
      if (k >= 0 && S.frames[k]) { row = S.frames[k]; S.shownFrame = k; }
      $('playhead').style.left = `${Math.max(t, 0) * PX_PER_S}px`;
      const tl = $('timeline');
      const x = Math.max(t, 0) * PX_PER_S;
      if (x > tl.scrollLeft + tl.clientWidth - 60 || x < tl.scrollLeft) tl.scrollLeft = Math.max(0, x - 100);
    }
  }
  if (THREE && view.renderer) {
    if (row) pose(row);
    view.renderer.render(view.scene, view.camera);
  }
}
requestAnimationFrame(frame);
log('ready: talk into the microphone or play a WAV file');
