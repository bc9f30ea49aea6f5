// kpd view --browser: the shape's rig (a GLB, see kpd/morph.py) drawn with three.js.
//
// State is one vector of target weights `w` over every target kpd offers (keypoint_<i>_<axis>, prior_<i>_<axis>,
// pca_<c>). Each target t moves the keypoints by known offsets D_t (K x 3, asset.extras.kpd.keypointOffsets), and the
// mesh by B D_t, so every edit is a sum of keypoint offsets o_i = (sum_t w_t D_t)_i, and the GPU moves the mesh by
// sum_i B_i o_i, with B_i the rig's basis column.
//
// By default the GLB carries B as vertex attributes (_KPD_BASIS_<j>: columns 4j to 4j + 3) and the vertex shader
// adds sum_i B_i o_i (K multiply-adds per vertex). ?morph=three loads the GLB with the keypoint morph targets instead
// (keypoint i's are B_i (1, 0, 0), B_i (0, 1, 0), B_i (0, 0, 1), nine times the data) and sets their influences to
// the offsets: three.js's own morph targets (a texture fetch per target and vertex) draw the same mesh at a fraction
// of the speed on a software renderer. ?morph=none draws the rest mesh only (the cost of the draw without
// deformation, for benchmarks). Without a GPU a large mesh is drawn by its coarse stand-in while a keypoint is
// dragged (extras.kpdStandIn of its primitives).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const params = new URLSearchParams(location.search);
// this launch's secret is the first segment of the page's address (/<secret>/, as kpd view printed it): the page's
// relative URLs carry it, and its requests of the server's API carry it again in a header, which no other site's
// form or no-cors request can set (viewer/browser.py)
const secret = location.pathname.split('/')[1];
const api = { Authorization: `Bearer ${secret}` };
const timing = params.has('timing'); // finish each frame on the GPU and record its time (benchmarks, tests)
let threeMorphs = params.get('morph') === 'three'; // also when the packed basis needs more attributes than WebGL has
const noMorphs = params.get('morph') === 'none'; // the rest mesh only, the same draw without deformation (benchmarks)
const PICK_PIXELS = 14; // a press this close to a keypoint's marker grabs it

// stats.firstPicture: ms from the page's start to its first finished frame; with ?timing, stats.steps: per drag or
// slider step, {latency: ms from the input event to its finished frame, work: ms of the page's own work for it,
// at: when that frame was finished}
const kpd = { ready: false, error: null, stats: { firstPicture: null, loaded: null, steps: [] } };
window.kpd = kpd;

const view = document.getElementById('view');
const labels = document.getElementById('labels');
const statusLine = document.getElementById('status');
// multisampling doubles the cost of a frame on a software renderer (SwiftShader, where there is no GPU): it is on
// only where WebGL runs on a GPU. Without one, a drag also draws at half the resolution (a quarter of the pixels),
// full again on release
function softwareWebGL() {
  const gl = document.createElement('canvas').getContext('webgl2');
  const info = gl && gl.getExtension('WEBGL_debug_renderer_info');
  const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : '';
  gl?.getExtension('WEBGL_lose_context')?.loseContext();
  return /swiftshader|llvmpipe|software/i.test(name);
}
const software = softwareWebGL();
const renderer = new THREE.WebGLRenderer({ antialias: !software });
renderer.setPixelRatio(window.devicePixelRatio);
view.prepend(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf4f4f2);
const camera = new THREE.PerspectiveCamera(35, 1, 0.01, 1000);
scene.add(new THREE.HemisphereLight(0xffffff, 0x6c6c6c, 0.9));
const light = new THREE.DirectionalLight(0xffffff, 1.3);
light.position.set(0.4, 0.6, 1.0);
camera.add(light);
scene.add(camera);
const controls = new OrbitControls(camera, renderer.domElement);

let names = [];          // every target, in kpd's order
let offsets = [];        // per target, K x 3 keypoint offsets of one unit of its weight
let rest = [];           // K x 3 rest keypoints, the user's frame
let w = null;            // Float64Array of the target weights
let root = null;         // the glTF root node: its local frame is the user's frame
let meshes = [];         // the mesh's primitives (three.js Meshes)
let offsetUniforms = []; // K Vector3 uniforms: the keypoints' offsets (packed basis path)
let standIns = [];       // {mesh, standIn}: a large primitive's coarse stand-in, drawn during drags without a GPU
let markers = [];        // one sphere per keypoint, children of `root`
let labelSpans = [];
let history = [];
let historyIndex = 0;
let frameRequested = false;
let pending = null;      // the input that the next frame shows: {start, work} (timing)
const index = new Map();

function status(text, error = false) {
  statusLine.textContent = text;
  statusLine.className = error ? 'error' : '';
}

function totalOffsets() {
  const k = rest.length;
  const total = Array.from({ length: k }, () => [0, 0, 0]);
  for (let t = 0; t < names.length; t++) {
    const weight = w[t];
    if (weight === 0) continue;
    const d = offsets[t];
    for (let i = 0; i < k; i++) {
      total[i][0] += weight * d[i][0];
      total[i][1] += weight * d[i][1];
      total[i][2] += weight * d[i][2];
    }
  }
  return total;
}

function keypointsUser() {
  const total = totalOffsets();
  return rest.map((p, i) => [p[0] + total[i][0], p[1] + total[i][1], p[2] + total[i][2]]);
}

function apply() {
  const total = totalOffsets();
  if (threeMorphs) {
    for (const mesh of meshes) {
      const dictionary = mesh.morphTargetDictionary;
      const influences = mesh.morphTargetInfluences;
      for (let i = 0; i < rest.length; i++) {
        for (let a = 0; a < 3; a++) {
          const slot = dictionary[`keypoint_${i}_${'xyz'[a]}`];
          if (slot !== undefined) influences[slot] = total[i][a];
        }
      }
    }
  } else if (!noMorphs) {
    total.forEach((o, i) => offsetUniforms[i].set(o[0], o[1], o[2]));
  }
  for (let i = 0; i < rest.length; i++) {
    markers[i].position.set(rest[i][0] + total[i][0], rest[i][1] + total[i][1], rest[i][2] + total[i][2]);
  }
  requestFrame();
}

function requestFrame() {
  if (frameRequested) return;
  frameRequested = true;
  requestAnimationFrame(draw);
}

function draw() {
  frameRequested = false;
  const start = performance.now();
  renderer.render(scene, camera);
  placeLabels();
  if (timing || kpd.stats.firstPicture === null) {
    renderer.getContext().finish();
    const now = performance.now();
    if (kpd.stats.firstPicture === null) kpd.stats.firstPicture = now;
    if (pending !== null) kpd.stats.steps.push({ latency: now - pending.start, work: pending.work + now - start, at: now });
  }
  pending = null;
}

function timed(event, work) { // run an input's work, remembering when the input came (timing)
  const start = performance.now();
  work();
  if (timing) pending = { start: Math.min(start, event.timeStamp), work: performance.now() - start };
}

function screenOf(position) {
  const p = position.clone().project(camera);
  const rect = renderer.domElement.getBoundingClientRect();
  return [(p.x + 1) / 2 * rect.width, (1 - p.y) / 2 * rect.height];
}

function placeLabels() {
  markers.forEach((marker, i) => {
    const [x, y] = screenOf(marker.getWorldPosition(new THREE.Vector3()));
    labelSpans[i].style.left = `${x}px`;
    labelSpans[i].style.top = `${y}px`;
  });
}

function resize() {
  const width = view.clientWidth, height = view.clientHeight;
  renderer.setSize(width, height, false);
  camera.aspect = width / height;
  camera.updateProjectionMatrix();
  requestFrame();
}

// --- history ----------------------------------------------------------------------------------------------------

function remember() {
  history = history.slice(0, historyIndex + 1);
  history.push(Float64Array.from(w));
  historyIndex = history.length - 1;
  syncControls();
}

function restore(step) {
  const target = historyIndex + step;
  if (target < 0 || target >= history.length) return;
  historyIndex = target;
  w = Float64Array.from(history[historyIndex]);
  syncControls();
  apply();
}

function reset() {
  w = new Float64Array(names.length);
  remember();
  apply();
}

function syncControls() {
  document.getElementById('undo').disabled = historyIndex <= 0;
  document.getElementById('redo').disabled = historyIndex >= history.length - 1;
  for (const slider of document.querySelectorAll('#sliders input')) {
    slider.value = w[index.get(slider.dataset.target)];
  }
}

// --- dragging ---------------------------------------------------------------------------------------------------

let drag = null; // {keypoint, plane, moved}
const raycaster = new THREE.Raycaster();

function pointerRay(event) {
  const rect = renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1,
    -((event.clientY - rect.top) / rect.height) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  return raycaster.ray;
}

function pick(event) {
  const rect = renderer.domElement.getBoundingClientRect();
  let best = -1, bestDistance = PICK_PIXELS;
  markers.forEach((marker, i) => {
    const [x, y] = screenOf(marker.getWorldPosition(new THREE.Vector3()));
    const distance = Math.hypot(x - (event.clientX - rect.left), y - (event.clientY - rect.top));
    if (distance < bestDistance) { best = i; bestDistance = distance; }
  });
  return best;
}

function onPointerDown(event) {
  if (!kpd.ready || event.button !== 0) return;
  const keypoint = pick(event);
  if (keypoint < 0) return;
  controls.enabled = false;
  const normal = camera.getWorldDirection(new THREE.Vector3());
  const plane = new THREE.Plane().setFromNormalAndCoplanarPoint(normal,
    markers[keypoint].getWorldPosition(new THREE.Vector3()));
  drag = { keypoint, plane, moved: false };
  if (software) { // a quarter of the pixels, and a large mesh's stand-in, while dragging
    renderer.setPixelRatio(window.devicePixelRatio / 2);
    showStandIns(true);
  }
  renderer.domElement.setPointerCapture(event.pointerId);
  event.preventDefault();
  event.stopImmediatePropagation();
}

function onPointerMove(event) {
  if (drag === null) return;
  timed(event, () => dragTo(event));
}

function dragTo(event) {
  const hit = pointerRay(event).intersectPlane(drag.plane, new THREE.Vector3());
  if (hit === null) return;
  const target = root.worldToLocal(hit); // the user's frame
  const current = keypointsUser()[drag.keypoint];
  const prefix = document.getElementById('prior').checked ? 'prior' : 'keypoint';
  for (let a = 0; a < 3; a++) {
    w[index.get(`${prefix}_${drag.keypoint}_${'xyz'[a]}`)] += target.getComponent(a) - current[a];
  }
  drag.moved = true;
  apply();
}

function onPointerUp(event) {
  if (drag === null) return;
  if (drag.moved) remember();
  drag = null;
  controls.enabled = true;
  if (software) {
    renderer.setPixelRatio(window.devicePixelRatio);
    showStandIns(false);
    requestFrame();
  }
  renderer.domElement.releasePointerCapture(event.pointerId);
}

// --- saving -----------------------------------------------------------------------------------------------------

async function save() {
  const weights = {};
  names.forEach((name, t) => { if (w[t] !== 0) weights[name] = w[t]; });
  status('saving...');
  try {
    const response = await fetch('save', { method: 'POST', headers: { ...api, 'Content-Type': 'application/json' },
      body: JSON.stringify({ weights }) });
    const answer = await response.json();
    status(answer.message, !answer.ok);
    kpd.lastSave = answer;
  } catch (error) {
    status(`save failed: ${error}`, true);
    kpd.lastSave = { ok: false, message: String(error) };
  }
}

// --- the basis as K vertex attributes, added by the vertex shader ------------------------------------------------

function basisAttributes(mesh) {
  // the GLB's _KPD_BASIS_<j> (three.js names an application's attribute in lower case) as kpdBasis<j>: B_i of every
  // vertex in ceil(K / 4) vec4 attributes
  const geometry = mesh.geometry;
  const k = rest.length;
  const slots = Math.ceil(k / 4);
  for (let j = 0; j < slots; j++) {
    const attribute = geometry.getAttribute(`_kpd_basis_${j}`);
    if (!attribute) throw new Error(`the rig has no basis attribute _KPD_BASIS_${j}`);
    geometry.deleteAttribute(`_kpd_basis_${j}`);
    if (!noMorphs) geometry.setAttribute(`kpdBasis${j}`, attribute);
  }
  if (noMorphs) return;
  const sum = Array.from({ length: k }, (_, i) => `kpdBasis${i >> 2}.${'xyzw'[i & 3]} * kpdOffsets[${i}]`);
  mesh.material.onBeforeCompile = (shader) => {
    shader.uniforms.kpdOffsets = { value: offsetUniforms };
    shader.vertexShader = Array.from({ length: slots }, (_, j) => `attribute vec4 kpdBasis${j};\n`).join('')
      + `uniform vec3 kpdOffsets[${k}];\n`
      + shader.vertexShader.replace('#include <begin_vertex>', `#include <begin_vertex>\ntransformed += ${sum.join(' + ')};`);
  };
  mesh.material.customProgramCacheKey = () => `kpd-basis-${k}`;
  mesh.material.needsUpdate = true;
}

// --- stand-ins of large meshes -----------------------------------------------------------------------------------

async function makeStandIns(parser) {
  // a primitive of many triangles comes with a coarse stand-in over its own vertices (extras.kpdStandIn: the window
  // editor's, vertices clustered on a grid): the same attributes, a few triangles, drawn while a keypoint is dragged
  // where WebGL runs without a GPU, the whole mesh again on release
  for (const mesh of meshes) {
    const accessor = mesh.geometry.userData.kpdStandIn;
    if (accessor === undefined) continue;
    const geometry = new THREE.BufferGeometry();
    for (const [name, attribute] of Object.entries(mesh.geometry.attributes)) geometry.setAttribute(name, attribute);
    geometry.setIndex(await parser.getDependency('accessor', accessor));
    const standIn = new THREE.Mesh(geometry, mesh.material);
    standIn.position.copy(mesh.position);
    standIn.quaternion.copy(mesh.quaternion);
    standIn.scale.copy(mesh.scale);
    standIn.visible = false;
    standIn.frustumCulled = false;
    mesh.parent.add(standIn);
    standIns.push({ mesh, standIn });
  }
}

function showStandIns(on) {
  for (const { mesh, standIn } of standIns) {
    mesh.visible = !on;
    standIn.visible = on;
  }
}

// --- start ------------------------------------------------------------------------------------------------------

function buildPanel(info) {
  document.getElementById('title').textContent = info.name;
  document.title = `kpd view - ${info.name}`;
  const prior = document.getElementById('prior');
  prior.disabled = !names.some((n) => n.startsWith('prior_'));
  prior.checked = info.prior && !prior.disabled;
  const sliders = document.getElementById('sliders');
  for (const name of names.filter((n) => n.startsWith('pca_'))) {
    const label = document.createElement('label');
    label.textContent = `component ${name.slice(4)} (standard deviations)`;
    const slider = document.createElement('input');
    Object.assign(slider, { type: 'range', min: -3, max: 3, step: 0.01, value: 0 });
    slider.dataset.target = name;
    slider.addEventListener('input', (event) => timed(event, () => { w[index.get(name)] = Number(slider.value); apply(); }));
    slider.addEventListener('change', remember);
    label.append(slider);
    sliders.append(label);
  }
  const save_ = document.getElementById('save');
  if (info.out === null) {
    save_.disabled = true;
    save_.title = 'start kpd view with --out FILE to save';
  } else {
    save_.textContent = `save mesh to ${info.out.split('/').pop()}`;
  }
  save_.addEventListener('click', save);
  document.getElementById('undo').addEventListener('click', () => restore(-1));
  document.getElementById('redo').addEventListener('click', () => restore(1));
  document.getElementById('reset').addEventListener('click', reset);
  window.addEventListener('keydown', (event) => {
    if (!(event.ctrlKey || event.metaKey)) return;
    const key = event.key.toLowerCase();
    if (key === 'z' && !event.shiftKey) { restore(-1); event.preventDefault(); }
    if (key === 'y' || (key === 'z' && event.shiftKey)) { restore(1); event.preventDefault(); }
  });
}

function frameCamera(info) {
  // the rest shape's box (three.js's own bounds of a mesh with morph targets grow by a unit weight of each target,
  // which is a unit of the user's length: a metre around a banana scanned in metres)
  const box = new THREE.Box3();
  for (const mesh of meshes) {
    box.union(new THREE.Box3().setFromBufferAttribute(mesh.geometry.attributes.position).applyMatrix4(mesh.matrixWorld));
  }
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const distance = sphere.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.2; // room for edits
  const azimuth = THREE.MathUtils.degToRad(Number(params.get('azimuth') ?? info.azimuth));
  const elevation = THREE.MathUtils.degToRad(Number(params.get('elevation') ?? info.elevation));
  camera.position.copy(sphere.center).add(new THREE.Vector3(Math.sin(azimuth) * Math.cos(elevation),
    Math.sin(elevation), Math.cos(azimuth) * Math.cos(elevation)).multiplyScalar(distance));
  camera.near = distance / 100;
  camera.far = distance * 10;
  camera.updateProjectionMatrix();
  controls.target.copy(sphere.center);
  controls.update();
  return sphere.radius;
}

async function start() {
  const answer = await fetch('info.json', { headers: api });
  const info = await answer.json();
  if (!answer.ok) throw new Error(info.message);
  threeMorphs ||= Math.ceil(info.keypoints / 4) + 4 > renderer.capabilities.maxAttributes;
  const gltf = await new GLTFLoader().setRequestHeader(api).loadAsync(threeMorphs ? 'rig.glb?morph=three' : 'rig.glb');
  kpd.stats.loaded = performance.now();
  const extras = gltf.parser.json.asset.extras.kpd;
  names = extras.targets;
  offsets = extras.keypointOffsets;
  rest = extras.keypoints;
  names.forEach((name, t) => index.set(name, t));
  w = new Float64Array(names.length);
  root = gltf.scene.children[0];
  gltf.scene.traverse((object) => {
    if (object.isMesh) {
      // diffuse shading (kpd's materials are matte: no metal, full roughness) at a fraction of PBR's cost per pixel
      const source = object.material;
      object.material = new THREE.MeshLambertMaterial({ color: source.color, map: source.map,
        vertexColors: source.vertexColors, flatShading: source.flatShading });
      meshes.push(object);
      object.frustumCulled = false; // the bounding sphere is the rest shape's
    }
  });
  offsetUniforms = rest.map(() => new THREE.Vector3());
  if (!threeMorphs) meshes.forEach(basisAttributes);
  if (software && !threeMorphs) await makeStandIns(gltf.parser);
  scene.add(gltf.scene);
  gltf.scene.updateMatrixWorld(true);
  const radius = frameCamera(info);
  const sphere = new THREE.SphereGeometry(radius * 0.018, 16, 12);
  const material = new THREE.MeshBasicMaterial({ color: 0xff7a00, depthTest: false });
  rest.forEach((p, i) => {
    const marker = new THREE.Mesh(sphere, material);
    marker.renderOrder = 1; // drawn over the mesh, so a keypoint behind it can still be grabbed
    marker.position.set(p[0], p[1], p[2]);
    root.add(marker);
    markers.push(marker);
    const span = document.createElement('span');
    span.textContent = String(i);
    labels.append(span);
    labelSpans.push(span);
  });
  buildPanel(info);
  history = [Float64Array.from(w)];
  historyIndex = 0;
  syncControls();
  renderer.domElement.addEventListener('pointerdown', onPointerDown, { capture: true });
  renderer.domElement.addEventListener('pointermove', onPointerMove);
  renderer.domElement.addEventListener('pointerup', onPointerUp);
  controls.addEventListener('change', requestFrame);
  window.addEventListener('resize', resize);
  resize();
  apply();
  kpd.ready = true;
  status(`${names.length} edits of ${rest.length} keypoints; the mesh follows on your GPU`);
}

// --- what tests and benchmarks read -----------------------------------------------------------------------------

Object.assign(kpd, {
  names: () => names,
  weights: () => Object.fromEntries(names.map((n, t) => [n, w[t]])),
  setWeights: (values) => { w = new Float64Array(names.length); for (const [n, v] of Object.entries(values)) w[index.get(n)] = v; remember(); apply(); },
  keypoints: () => keypointsUser(),
  // what is drawn now: 'stand-in' (a large mesh while a keypoint is dragged without a GPU) or 'whole'; and how many
  // triangles each primitive's stand-in has (0: none)
  drawing: () => (standIns.some(({ standIn }) => standIn.visible) ? 'stand-in' : 'whole'),
  standInTriangles: () => meshes.map((mesh) => {
    const found = standIns.find((s) => s.mesh === mesh);
    return found ? found.standIn.geometry.index.count / 3 : 0;
  }),
  keypointScreen: (i) => { root.updateMatrixWorld(true); return screenOf(markers[i].getWorldPosition(new THREE.Vector3())); },
  // vertex positions at the page's weights, in the user's frame, per primitive: three.js's own evaluation of its
  // morph targets (Mesh.getVertexPosition) with ?morph=three, else the sum the shader adds, sum_i B_i o_i
  positions: () => meshes.map((mesh) => {
    const count = mesh.geometry.attributes.position.count;
    const out = new Array(count * 3);
    const p = new THREE.Vector3();
    const total = totalOffsets();
    const basis = threeMorphs ? [] : Array.from({ length: Math.ceil(rest.length / 4) },
      (_, j) => mesh.geometry.getAttribute(`kpdBasis${j}`));
    for (let v = 0; v < count; v++) {
      if (threeMorphs) {
        mesh.getVertexPosition(v, p);
      } else {
        p.fromBufferAttribute(mesh.geometry.attributes.position, v);
        if (!noMorphs) {
          for (let i = 0; i < rest.length; i++) {
            const b = basis[i >> 2].getComponent(v, i & 3);
            p.x += total[i][0] * b; p.y += total[i][1] * b; p.z += total[i][2] * b;
          }
        }
      }
      root.worldToLocal(mesh.localToWorld(p));
      out[3 * v] = p.x; out[3 * v + 1] = p.y; out[3 * v + 2] = p.z;
    }
    return out;
  }),
  // the picture as drawn now (a PNG data URL): the GPU's result, to compare the two ways of drawing
  snapshot: () => { renderer.render(scene, camera); return renderer.domElement.toDataURL('image/png'); },
  restPositions: () => meshes.map((mesh) => {
    const attribute = mesh.geometry.attributes.position;
    const out = new Array(attribute.count * 3);
    const p = new THREE.Vector3();
    for (let v = 0; v < attribute.count; v++) {
      p.fromBufferAttribute(attribute, v);
      root.worldToLocal(mesh.localToWorld(p));
      out[3 * v] = p.x; out[3 * v + 1] = p.y; out[3 * v + 2] = p.z;
    }
    return out;
  }),
});

start().catch((error) => {
  kpd.error = String(error && error.stack || error);
  status(`cannot show the rig: ${error}`, true);
});
