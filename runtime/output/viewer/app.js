// hailstorm's storm viewer: the seat's deformed surface, the stones, and the impacts of one storm.
// An ES module; the page's loader (boot.js) hands it the data (window.__hailstorm) and resolves
// 'three' and the orbit controls to the vendored three.js (vendor/three/, nothing is fetched).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const { meta, buffer } = window.__hailstorm;
const TYPES = { float32: Float32Array, int16: Int16Array, int32: Int32Array, uint32: Uint32Array };
function arr(name) {
  const a = meta.arrays[name];
  return new TYPES[a.dtype](buffer, a.offset, a.length);
}

const n = meta.n_vertices;
const F = meta.frames;
const X = arr('vertices');
const TRI = arr('triangles');
const U = { peak: arr('u_peak'), state: arr('u_state') };
const STONE_OFF = meta.stone_offsets;
const SP = arr('stone_pos'), SR = arr('stone_radius'), SID = arr('stone_id'), SF = arr('stone_force');

// ---- impacts.csv --------------------------------------------------------------------------
const IMP = meta.impacts;
const COL = Object.fromEntries(IMP.columns.map((c, j) => [c, j]));
const ROWS = IMP.lines.map((line) => line.split(','));
function num(i, key) {
  const j = COL[key];
  if (j === undefined) return NaN;
  const s = ROWS[i][j];
  return s === '' ? NaN : Number(s);
}
const IMPACT_POINT = ROWS.map((_, i) => [num(i, 'x_m'), num(i, 'y_m'), num(i, 'z_m')]);

// ---- colours ------------------------------------------------------------------------------
// |u| on a colour scale fixed for the whole storm: logarithmic over two decades below the
// largest |u| (grey below that: the dents of one storm span more than a decade), or linear from 0
const GREY = '#cfd6de';
const RAMP = [[0, '#fff3b0'], [0.3, '#fdae61'], [0.55, '#f46d43'], [0.8, '#d73027'], [1, '#7f0000']];
const SCALES_OF_COLOUR = {
  log: { stops: RAMP, below: GREY, decades: 2 },
  linear: { stops: [[0, GREY], [0.08, '#fff3b0'], ...RAMP.slice(1)], below: GREY, decades: 0 },
};
const LUT_N = 256;
function buildLut(stops) {
  const lut = new Float32Array(LUT_N * 3); // linear RGB
  const c0 = new THREE.Color(), c1 = new THREE.Color(), c = new THREE.Color();
  for (let i = 0; i < LUT_N; i++) {
    const x = i / (LUT_N - 1);
    let k = 0;
    while (k < stops.length - 2 && x > stops[k + 1][0]) k++;
    const [x0, s0] = stops[k], [x1, s1] = stops[k + 1];
    c0.set(s0); c1.set(s1); // (THREE.Color.set takes sRGB and stores linear)
    c.copy(c0).lerp(c1, Math.min(1, Math.max(0, (x - x0) / (x1 - x0))));
    lut.set([c.r, c.g, c.b], 3 * i);
  }
  return lut;
}
const LUTS = { log: buildLut(SCALES_OF_COLOUR.log.stops), linear: buildLut(SCALES_OF_COLOUR.linear.stops) };
const BELOW = new THREE.Color(GREY);
/** the colour-scale position of |u| = m in [0, 1], or -1 below the scale (grey) */
function colourPosition(m, top, kind) {
  if (!(top > 0)) return -1;
  if (kind === 'linear') return Math.min(1, m / top);
  if (m <= 0) return -1;
  const x = 1 + Math.log10(m / top) / SCALES_OF_COLOUR.log.decades;
  return x < 0 ? -1 : Math.min(1, x);
}

// ---- the scene ----------------------------------------------------------------------------
const canvas = document.getElementById('hs-canvas');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
const scene = new THREE.Scene();
scene.background = new THREE.Color('#1b1e24');

const box = new THREE.Box3();
for (let i = 0; i < n; i++) box.expandByPoint(new THREE.Vector3(X[3 * i], X[3 * i + 1], X[3 * i + 2]));
const center = box.getCenter(new THREE.Vector3());
const size = box.getSize(new THREE.Vector3());
const L = Math.max(size.x, size.y, size.z, 1e-9);

const camera = new THREE.PerspectiveCamera(35, 1, L / 200, L * 50);
camera.up.set(0, 0, 1); // the storm's z is up: hail falls along -z
scene.add(camera);
scene.add(new THREE.HemisphereLight(0xffffff, 0x50555e, 1.6));
const keyLight = new THREE.DirectionalLight(0xffffff, 2.2);
keyLight.position.set(-0.4, 0.6, 1.0); // follows the camera: the lit side is the one looked at
camera.add(keyLight);

const controls = new OrbitControls(camera, canvas);
controls.addEventListener('change', requestRender);
function homeView() {
  const dir = new THREE.Vector3(0.75, -1.0, 0.85).normalize(); // three-quarter view from above
  const dist = (0.62 * L) / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  camera.position.copy(center).addScaledVector(dir, dist);
  controls.target.copy(center);
  controls.update();
}

// the seat
const pos = new Float32Array(3 * n);
const colour = new Float32Array(3 * n);
const seatGeom = new THREE.BufferGeometry();
seatGeom.setAttribute('position', new THREE.BufferAttribute(pos, 3).setUsage(THREE.DynamicDrawUsage));
seatGeom.setAttribute('color', new THREE.BufferAttribute(colour, 3).setUsage(THREE.DynamicDrawUsage));
seatGeom.setIndex(new THREE.BufferAttribute(TRI, 1));
const seat = new THREE.Mesh(seatGeom, new THREE.MeshStandardMaterial({
  vertexColors: true, roughness: 0.7, metalness: 0.0, side: THREE.DoubleSide,
}));
scene.add(seat);

// the stones (one instanced sphere each)
const maxStones = Math.max(1, meta.max_stones);
const stones = new THREE.InstancedMesh(new THREE.SphereGeometry(1, 20, 14),
  new THREE.MeshStandardMaterial({ roughness: 0.25, metalness: 0.0 }), maxStones);
stones.instanceMatrix.setUsage(THREE.DynamicDrawUsage);
stones.frustumCulled = false;
const ICE = new THREE.Color('#e6f4ff'), PRESSING = new THREE.Color('#4fc3f7');
for (let k = 0; k < maxStones; k++) stones.setColorAt(k, ICE);
scene.add(stones);

// the chosen impact's marker: a ring around its dent
const marker = new THREE.Mesh(new THREE.TorusGeometry(1, 0.07, 8, 48),
  new THREE.MeshBasicMaterial({ color: 0x00e5ff, depthTest: false, transparent: true, opacity: 0.9 }));
marker.renderOrder = 10; // drawn over the surface it lies on
marker.visible = false;
scene.add(marker);

// ---- state --------------------------------------------------------------------------------
const state = {
  frame: 0,
  field: meta.default_field,
  colours: 'log',
  scaleIndex: meta.scales.indexOf(meta.default_scale),
  playing: false,
  fps: meta.default_fps,
  selected: null, // impact index shown in the panel
};
const scale = () => meta.scales[state.scaleIndex];

const el = (id) => document.getElementById(id);
const frameInput = el('hs-frame'), scaleInput = el('hs-scale'), fieldInput = el('hs-field'), fpsInput = el('hs-fps');
const colourInput = el('hs-colours');
colourInput.value = state.colours;
frameInput.max = String(F - 1);
scaleInput.max = String(meta.scales.length - 1);
scaleInput.value = String(state.scaleIndex);
fieldInput.value = state.field;
fpsInput.value = String(state.fps);

function mm(v) { return (1e3 * v).toPrecision(3); }
function updateColourBar() {
  const top = meta.u_max[state.field];
  const kind = SCALES_OF_COLOUR[state.colours];
  el('hs-bar').style.background = 'linear-gradient(to top, ' +
    kind.stops.map(([x, c]) => `${c} ${(100 * x).toFixed(0)}%`).join(', ') + ')';
  const log = state.colours === 'log';
  el('hs-bar-top').textContent = mm(top);
  el('hs-bar-mid').textContent = mm(log ? top / 10 : top / 2);
  el('hs-bar-bottom').textContent = log ? mm(top / 100) : '0';
  el('hs-bar-label').textContent = (state.field === 'peak'
    ? '|u| peak since the previous frame (mm)' : '|u| at the frame\'s time (mm)') +
    (log ? `; log scale, grey below ${mm(top / 100)}` : '; linear scale');
}

function showFrame(i) {
  i = Math.max(0, Math.min(F - 1, Math.round(i)));
  state.frame = i;
  const q = U[state.field];
  const qs = meta.quant[state.field][i]; // metres per int16 step of this frame
  const s = scale();
  const top = meta.u_max[state.field];
  const lut = LUTS[state.colours];
  const base = 3 * n * i;
  for (let v = 0; v < n; v++) {
    const ux = q[base + 3 * v] * qs, uy = q[base + 3 * v + 1] * qs, uz = q[base + 3 * v + 2] * qs;
    pos[3 * v] = X[3 * v] + s * ux;
    pos[3 * v + 1] = X[3 * v + 1] + s * uy;
    pos[3 * v + 2] = X[3 * v + 2] + s * uz;
    const x = colourPosition(Math.sqrt(ux * ux + uy * uy + uz * uz), top, state.colours);
    if (x < 0) {
      colour[3 * v] = BELOW.r; colour[3 * v + 1] = BELOW.g; colour[3 * v + 2] = BELOW.b;
    } else {
      const k = 3 * Math.round(x * (LUT_N - 1));
      colour[3 * v] = lut[k]; colour[3 * v + 1] = lut[k + 1]; colour[3 * v + 2] = lut[k + 2];
    }
  }
  seatGeom.attributes.position.needsUpdate = true;
  seatGeom.attributes.color.needsUpdate = true;
  seatGeom.computeVertexNormals();
  seatGeom.computeBoundingSphere();
  seatGeom.computeBoundingBox();

  const m4 = new THREE.Matrix4(), p = new THREE.Vector3(), quat = new THREE.Quaternion(), sc = new THREE.Vector3();
  const a = STONE_OFF[i], b = STONE_OFF[i + 1];
  for (let k = a; k < b; k++) {
    const r = SR[k];
    m4.compose(p.set(SP[3 * k], SP[3 * k + 1], SP[3 * k + 2]), quat, sc.set(r, r, r));
    stones.setMatrixAt(k - a, m4);
    stones.setColorAt(k - a, SF[k] > 0 ? PRESSING : ICE);
  }
  stones.count = b - a;
  stones.instanceMatrix.needsUpdate = true;
  if (stones.instanceColor) stones.instanceColor.needsUpdate = true;
  stones.computeBoundingSphere();

  frameInput.value = String(i);
  const t = meta.times[i];
  const contacts = meta.contacts ? `, ${meta.contacts[i]} open contact${meta.contacts[i] === 1 ? '' : 's'}` : '';
  el('hs-time').textContent = `t = ${t.toFixed(4)} s · frame ${i + 1} of ${F} · ${b - a} stones${contacts}`;
  el('hs-scale-value').textContent = `×${s}`;
  updateMarker();
  requestRender();
}

// ---- rendering on demand, playback --------------------------------------------------------
let pending = false;
let lastTick = null;
let rendered = 0;
function requestRender() {
  if (!pending) { pending = true; requestAnimationFrame(tick); }
}
function tick(now) {
  pending = false;
  if (state.playing) {
    if (lastTick !== null) {
      state.acc = (state.acc || 0) + ((now - lastTick) / 1000) * state.fps;
      const steps = Math.floor(state.acc);
      if (steps > 0) {
        state.acc -= steps;
        showFrame((state.frame + steps) % F);
      }
    }
    lastTick = now;
    requestRender();
  }
  renderer.render(scene, camera);
  rendered += 1;
}
function setPlaying(on) {
  state.playing = on;
  state.acc = 0;
  lastTick = null;
  el('hs-play').textContent = on ? '❚❚ pause' : '▶ play';
  el('hs-play').setAttribute('aria-pressed', on ? 'true' : 'false');
  requestRender();
}
function resize() {
  const w = canvas.clientWidth || window.innerWidth, h = canvas.clientHeight || window.innerHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  requestRender();
}

// ---- picking: a click on a dent or a stone shows its impact -------------------------------
const raycaster = new THREE.Raycaster();
const pointer = new THREE.Vector2();
let downAt = null;
canvas.addEventListener('pointerdown', (e) => { downAt = [e.clientX, e.clientY]; });
canvas.addEventListener('pointerup', (e) => {
  if (!downAt) return;
  const moved = Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]);
  downAt = null;
  if (moved < 5) pick(e.clientX, e.clientY);
});

function undeformedPoint(hit) {
  // the hit point on the deformed surface, carried back to the undeformed seat (barycentric)
  const f = hit.face;
  const tri = new THREE.Triangle(
    new THREE.Vector3().fromArray(pos, 3 * f.a), new THREE.Vector3().fromArray(pos, 3 * f.b),
    new THREE.Vector3().fromArray(pos, 3 * f.c));
  const w = tri.getBarycoord(hit.point, new THREE.Vector3()) || new THREE.Vector3(1 / 3, 1 / 3, 1 / 3);
  const out = new THREE.Vector3();
  for (const [idx, wt] of [[f.a, w.x], [f.b, w.y], [f.c, w.z]]) {
    out.x += wt * X[3 * idx]; out.y += wt * X[3 * idx + 1]; out.z += wt * X[3 * idx + 2];
  }
  return out;
}

function impactNear(p) {
  // the impact whose dent is at p: of those within reach of p, the one of this frame, else the
  // latest before it, else the first after it (the nearest within each group)
  let best = null;
  for (let i = 0; i < ROWS.length; i++) {
    const [x, y, z] = IMPACT_POINT[i];
    const d = Math.hypot(p.x - x, p.y - y, p.z - z);
    const reach = Math.max(2.5 * num(i, 'radius_m'), 0.01);
    if (!(d <= reach)) continue;
    const f = IMP.frame[i];
    const group = f === state.frame ? 0 : f < state.frame ? 1 : 2;
    const key = [group, group === 1 ? -f : group === 2 ? f : 0, d];
    if (best === null || key[0] < best.key[0] || (key[0] === best.key[0] &&
        (key[1] < best.key[1] || (key[1] === best.key[1] && key[2] < best.key[2])))) best = { i, key };
  }
  return best === null ? null : best.i;
}

function impactsOfStone(id) {
  const out = [];
  for (let i = 0; i < ROWS.length; i++) if (num(i, 'stone') === id) out.push(i);
  return out;
}

function pick(clientX, clientY) {
  const r = canvas.getBoundingClientRect();
  pointer.set(((clientX - r.left) / r.width) * 2 - 1, -((clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(pointer, camera);
  const hits = raycaster.intersectObjects([seat, stones], false);
  if (!hits.length) { select(null, 'nothing here: click a dent or a stone'); return; }
  const hit = hits[0];
  if (hit.object === stones) {
    const k = STONE_OFF[state.frame] + hit.instanceId;
    const id = SID[k];
    const mine = impactsOfStone(id);
    if (!mine.length) {
      select(null, `stone ${id} (radius ${mm(SR[k])} mm): no impact on the seat` +
        (SF[k] > 0 ? ' (touching it slowly, below the impact speed)' : ''));
      return;
    }
    // the impact of this stone at or before this frame, else its first
    const before = mine.filter((i) => IMP.frame[i] <= state.frame);
    select(before.length ? before[before.length - 1] : mine[0], null, `stone ${id}`);
    return;
  }
  const p = undeformedPoint(hit);
  const i = impactNear(p);
  if (i === null) {
    select(null, `no impact within reach of (${mm(p.x)}, ${mm(p.y)}, ${mm(p.z)}) mm`);
    return;
  }
  select(i, null, 'dent');
}

// ---- the impact panel ---------------------------------------------------------------------
const LIM = meta.limits;
function fmt(v, digits = 4) {
  if (!Number.isFinite(v)) return Number.isNaN(v) ? 'not measured' : String(v);
  return Number(v.toPrecision(digits)).toString();
}
function limitText(key, sense) {
  const v = LIM[key];
  return v === undefined || v === null ? '' : `${sense} ${v}`;
}
function row(label, key, { factor = 1, unit = '', limit = '', beyond = false } = {}) {
  const j = COL[key];
  const raw = j === undefined ? '' : ROWS[state.selected][j];
  const v = raw === '' ? NaN : Number(raw) * factor;
  const cls = beyond ? ' class="beyond"' : '';
  const shown = key === 'stone' ? raw : fmt(v) + (Number.isFinite(v) && unit ? ` ${unit}` : '');
  return `<tr${cls}><th>${label}</th><td data-key="${key}" data-value="${raw}">${shown}</td>` +
    `<td class="limit">${limit}</td></tr>`;
}
function select(i, message, via = '') {
  state.selected = i;
  const panel = el('hs-info');
  panel.hidden = false;
  if (i === null) {
    panel.dataset.impact = '';
    el('hs-info-body').innerHTML = `<p class="note">${message}</p>`;
    updateMarker();
    requestRender();
    return;
  }
  panel.dataset.impact = String(i);
  const over = new Set((ROWS[i][COL.beyond] || '').split(';').filter(Boolean));
  const f = IMP.frame[i];
  const when = f === 0 ? `by t = ${meta.times[0].toFixed(4)} s`
    : `between t = ${meta.times[f - 1].toFixed(4)} and ${meta.times[f].toFixed(4)} s (frame ${f + 1})`;
  const others = impactsOfStone(num(i, 'stone')).filter((k) => k !== i);
  const html = [
    `<h2>impact ${i + 1} of ${ROWS.length} <span class="via">${via}</span></h2>`,
    `<p class="when">${when}</p>`,
    '<table>',
    row('stone', 'stone'),
    row('radius', 'radius_m', { factor: 1e3, unit: 'mm' }),
    row('mass', 'mass_kg', { factor: 1e3, unit: 'g' }),
    row('speed (normal, at onset)', 'speed_m_s', { unit: 'm/s' }),
    row('peak force, quasi-static', 'peak_force_N', { unit: 'N' }),
    row('peak force with the pad\'s inertia', 'peak_force_dynamic_N', { unit: 'N' }),
    row('indentation', 'indentation_m', { factor: 1e3, unit: 'mm' }),
    row('pad thickness under it', 'thickness_m', { factor: 1e3, unit: 'mm' }),
    '<tr class="section"><th colspan="3">validity measures (docs/validity.md)</th></tr>',
    row('indentation / thickness', 'indentation_thickness_ratio',
      { limit: limitText('limit_indentation_thickness_ratio', '≤'), beyond: over.has('indentation') }),
    row('contact radius / stone radius', 'contact_radius_ratio',
      { limit: limitText('limit_contact_radius_ratio', '≤'), beyond: over.has('radius') }),
    row('estimated peak strain', 'strain_ratio', { limit: limitText('limit_strain_ratio', '≤'), beyond: over.has('strain') }),
    row('contact time / pad wave period', 'contact_time_ratio',
      { limit: limitText('limit_contact_time_ratio', '≥'), beyond: over.has('contact_time') }),
    row('inertia factor: force', 'inertia_force', { beyond: over.has('inertia'),
      limit: LIM.limit_inertia_change != null ? `within ${100 * LIM.limit_inertia_change} % of 1` : '' }),
    row('inertia factor: duration', 'inertia_duration'),
    row('inertia factor: restitution', 'inertia_restitution'),
    row('inertia factor: dent', 'inertia_dent'),
    `<tr><th>beyond the limits</th><td data-key="beyond" data-value="${ROWS[i][COL.beyond] || ''}" colspan="2">` +
      `${over.size ? [...over].join(', ') : 'none'}</td></tr>`,
    '</table>',
    others.length ? `<p class="others">this stone's other impacts: ${others.map((k) =>
      `<button data-goto="${k}">${k + 1}</button>`).join(' ')}</p>` : '',
    '<details open><summary>its row of impacts.csv</summary>',
    `<pre id="hs-csv-row">${IMP.columns.join(',')}\n${IMP.lines[i]}</pre></details>`,
  ].join('');
  el('hs-info-body').innerHTML = html;
  for (const b of el('hs-info-body').querySelectorAll('button[data-goto]')) {
    b.addEventListener('click', () => { const k = Number(b.dataset.goto); showFrame(IMP.frame[k]); select(k, null, 'listed'); });
  }
  updateMarker();
  requestRender();
}
function updateMarker() {
  const i = state.selected;
  if (i === null) { marker.visible = false; return; }
  const [x, y, z] = IMPACT_POINT[i];
  const v = nearestVertex(x, y, z);
  const u = displacementAt(v);
  const s = scale();
  marker.position.set(x + s * u[0], y + s * u[1], z + s * u[2]);
  const nrm = seatGeom.attributes.normal;
  if (nrm) {
    const normal = new THREE.Vector3(nrm.getX(v), nrm.getY(v), nrm.getZ(v));
    if (normal.lengthSq() > 0) marker.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), normal.normalize());
  }
  const r = Math.max(1.6 * num(i, 'radius_m') * (num(i, 'contact_radius_ratio') || 0.5), L / 120);
  marker.scale.set(r, r, r);
  marker.visible = true;
}
function nearestVertex(x, y, z) {
  let best = 0, bd = Infinity;
  for (let v = 0; v < n; v++) {
    const d = (X[3 * v] - x) ** 2 + (X[3 * v + 1] - y) ** 2 + (X[3 * v + 2] - z) ** 2;
    if (d < bd) { bd = d; best = v; }
  }
  return best;
}
function displacementAt(v, field = state.field, frame = state.frame) {
  const q = U[field], qs = meta.quant[field][frame], b = 3 * n * frame + 3 * v;
  return [q[b] * qs, q[b + 1] * qs, q[b + 2] * qs];
}

// ---- controls -----------------------------------------------------------------------------
el('hs-play').addEventListener('click', () => setPlaying(!state.playing));
frameInput.addEventListener('input', () => { setPlaying(false); showFrame(Number(frameInput.value)); });
scaleInput.addEventListener('input', () => { state.scaleIndex = Number(scaleInput.value); showFrame(state.frame); });
fieldInput.addEventListener('change', () => { state.field = fieldInput.value; updateColourBar(); showFrame(state.frame); });
colourInput.addEventListener('change', () => { state.colours = colourInput.value; updateColourBar(); showFrame(state.frame); });
fpsInput.addEventListener('change', () => { state.fps = Number(fpsInput.value); });
el('hs-home').addEventListener('click', () => { homeView(); requestRender(); });
el('hs-info-close').addEventListener('click', () => { el('hs-info').hidden = true; state.selected = null; updateMarker(); requestRender(); });
window.addEventListener('keydown', (e) => {
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  if (e.key === ' ') { e.preventDefault(); setPlaying(!state.playing); }
  else if (e.key === 'ArrowRight') { setPlaying(false); showFrame(state.frame + 1); }
  else if (e.key === 'ArrowLeft') { setPlaying(false); showFrame(state.frame - 1); }
});
window.addEventListener('resize', resize);

// ---- the page's face for scripts (and its tests) ------------------------------------------
window.hailstormViewer = {
  frames: F,
  get frame() { return state.frame; },
  get rendered() { return rendered; },
  get selected() { return state.selected; },
  get playing() { return state.playing; },
  setFrame(i) { setPlaying(false); showFrame(i); },
  setField(f) { state.field = f; fieldInput.value = f; updateColourBar(); showFrame(state.frame); },
  impactFrame(i) { return IMP.frame[i]; },
  displacement(x, y, z) { return displacementAt(nearestVertex(x, y, z)); },
  /** client (CSS pixel) coordinates of the seat's point (x, y, z) [m] as shown (displaced and scaled) */
  project(x, y, z) {
    const u = displacementAt(nearestVertex(x, y, z));
    const s = scale();
    const p = new THREE.Vector3(x + s * u[0], y + s * u[1], z + s * u[2]).project(camera);
    const r = canvas.getBoundingClientRect();
    return { x: r.left + ((p.x + 1) / 2) * r.width, y: r.top + ((1 - p.y) / 2) * r.height };
  },
};

el('hs-title-text').textContent = meta.title;
el('hs-summary').textContent = meta.summary_line;
el('hs-frames-note').textContent = meta.frames_note;
updateColourBar();
homeView();
resize();
showFrame(0);
document.body.dataset.ready = '1';
