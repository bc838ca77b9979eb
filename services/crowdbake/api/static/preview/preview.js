// Crowd preview of a crowdbake export: loads export.json, the glTF of every LOD and the KTX2 textures,
// and draws a crowd with crowdview's layout, camera and LOD rule (high mesh, low mesh, UV-mapped
// impostor at the 1:1 pixel-to-texel distance), each character with its own texture variation,
// outfit colours and phase in the cycle.
//
// Query parameters: export=URL of the export folder (none: the page says how to give one), count=N (100),
// seed=S (1), time=T (seconds; fixed time, one frame: for screenshots), lod=auto|high|low|impostor,
// width, height (the drawing buffer, 1280 x 720; the canvas scales it to the window).
// The status line (#status, data-ready false | true | empty | error) says what is loading, what failed,
// or, once drawn, the figures the tests read.
// A private bundle's export is fetched with the key the jobs page keeps in this tab's sessionStorage,
// or one given in the fragment (#key=cbk_...; moved into sessionStorage and out of the address bar).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { createImpostorMaterial, createVatMaterial, loadKtx2Texture } from './crowd-materials.js';

const params = new URLSearchParams(location.search);
const exportUrl = params.get('export') ? new URL(params.get('export'), location.href) : null;
const count = Number(params.get('count') || 100);
const seed = BigInt(params.get('seed') || 1);
const fixedTime = params.has('time') ? Number(params.get('time')) : null;
const lodMode = params.get('lod') || 'auto';
const width = Number(params.get('width') || 1280);
const height = Number(params.get('height') || 720);
const status = document.getElementById('status');

// Loading (false), drawn (true), nothing to draw (empty) or failed (error), in words a user reads.
function showStatus(state, text) {
  status.dataset.ready = state;
  status.textContent = text;
}

// Refuses, in words, an export the page cannot animate: no frames, no meshes or no impostor.
// export.json's format (crowdbake/export/writer.py EXPORT_FORMAT_VERSION) whose VAT blocks this page reads.
const MIN_FORMAT_VERSION = 5;

function checkExport(sidecar) {
  const frames = sidecar.frame_count, fps = sidecar.frames_per_second;
  if (!(Number.isInteger(frames) && frames >= 1) || !(fps > 0)) {
    throw new Error(`the export has no animation (frame_count ${frames}, frames_per_second ${fps}): re-export a bake whose character has an animation`);
  }
  if (!Array.isArray(sidecar.lods) || sidecar.lods.length === 0 || !sidecar.impostor) {
    throw new Error('the export lists no meshes (lods) or no impostor: re-export the bake');
  }
  if (!(sidecar.format_version >= MIN_FORMAT_VERSION)) {
    throw new Error(`the export is format version ${sidecar.format_version}; this page reads version ${MIN_FORMAT_VERSION} and later ` +
      '(one VAT file a part, skinned bodies by their joints): export the bundle again with this crowdbake');
  }
}

const KEY_STORAGE = 'crowdbake.key';  // the jobs page's (api/static/app.js)
const fragment = new URLSearchParams(location.hash.slice(1));
if (fragment.get('key')) {
  sessionStorage.setItem(KEY_STORAGE, fragment.get('key'));
  history.replaceState(null, '', location.pathname + location.search);
}
const key = sessionStorage.getItem(KEY_STORAGE);
const authHeaders = key ? { Authorization: `Bearer ${key}` } : {};

// crowdview's constants (runtime/src/main.cpp, crowd.cpp), so both draw the same crowd.
const LIGHT_DIR = new THREE.Vector3(0.4, 0.8, 0.45).normalize();
const SKY = [0.62, 0.70, 0.78];
const FOV_Y_DEG = 45;
// crowdview's crowd_spacing (crowd.cpp): 1.6 m up to an impostor radius of 1 m, in proportion above it.
const HUMAN_SPACING_M = 1.6;
const HUMAN_RADIUS_M = 1.0;
const crowdSpacing = (radius) => (radius > HUMAN_RADIUS_M ? HUMAN_SPACING_M * radius / HUMAN_RADIUS_M : HUMAN_SPACING_M);
const OVERVIEW_PITCH = 0.35;

// crowdview's Rng (splitmix64), so a seed gives the same headings, phases, variations and outfits.
class Rng {
  constructor(seed) { this.state = BigInt.asUintN(64, seed); }
  next() {
    this.state = BigInt.asUintN(64, this.state + 0x9E3779B97F4A7C15n);
    let z = this.state;
    z = BigInt.asUintN(64, (z ^ (z >> 30n)) * 0xBF58476D1CE4E5B9n);
    z = BigInt.asUintN(64, (z ^ (z >> 27n)) * 0x94D049BB133111EBn);
    return z ^ (z >> 31n);
  }
  uniform(lo, hi) { return lo + (hi - lo) * Number(this.next() >> 40n) / 16777216; }
  below(n) { return Number((this.next() >> 32n) % BigInt(n)); }
}

// crowdview's make_crowd (on the spot): a jittered grid, random heading, phase, variation, outfit.
function makeCrowd(n, variations, outfits, cycleSeconds, spacing) {
  const rng = new Rng(seed);
  const side = Math.ceil(Math.sqrt(n));
  const half = 0.5 * spacing * Math.max(side, 1);
  const characters = [];
  for (let i = 0; i < n; i++) {
    const row = Math.floor(i / side), column = i % side;
    // crowdview's compiler evaluates the glm::vec3 arguments right to left: z's jitter comes first.
    const z = (row + 0.5) * spacing - half + rng.uniform(-0.25, 0.25) * spacing;
    const x = (column + 0.5) * spacing - half + rng.uniform(-0.25, 0.25) * spacing;
    characters.push({
      position: new THREE.Vector3(x, 0, z),
      heading: rng.uniform(0, 2 * Math.PI),
      phase: rng.uniform(0, cycleSeconds),
      variation: rng.below(Math.max(variations, 1)),
      outfit: rng.below(Math.max(outfits, 1)),
      lod: null,
    });
  }
  return { characters, half };
}

// crowdview's camera_for_crowd: the whole crowd in view, looking down by `pitch`.
function overviewCamera(half, characterHeight, aspect) {
  const camera = new THREE.PerspectiveCamera(FOV_Y_DEG, aspect, 0.1, 2000);
  const fov = THREE.MathUtils.degToRad(FOV_Y_DEG);
  const center = new THREE.Vector3(0, 0.5 * characterHeight, 0);
  const radius = Math.SQRT2 * half + characterHeight;
  const halfFovX = Math.atan(Math.tan(0.5 * fov) * aspect);
  const halfFovY = Math.atan(Math.tan(0.5 * fov) / Math.max(Math.sin(OVERVIEW_PITCH), 0.5));
  const distance = radius / Math.sin(Math.min(halfFovX, halfFovY));
  const forward = new THREE.Vector3(0, Math.sin(-OVERVIEW_PITCH), -Math.cos(OVERVIEW_PITCH));
  camera.position.copy(center).addScaledVector(forward, -distance);
  camera.lookAt(camera.position.clone().add(forward));
  camera.far = Math.max(4 * (distance + radius + 1), 200);
  camera.updateProjectionMatrix();
  return camera;
}

// crowdview's LOD rule (crowd.h LodRule) with the sidecar's switch distance for this viewport.
function lodBoundaries(impostor, viewportHeight) {
  const s = impostor.switch_distance;
  const impostorDistance = impostor.bounds.radius * viewportHeight / (impostor.tile_size * Math.tan(THREE.MathUtils.degToRad(FOV_Y_DEG) / 2));
  return { low: impostorDistance * s.low_mesh_fraction, impostor: impostorDistance, hysteresis: s.hysteresis };
}

function chooseLod(depth, previous, rule, hasLow) {
  const levels = hasLow ? ['high', 'low', 'impostor'] : ['high', 'impostor'];
  const bounds = hasLow ? [rule.low, rule.impostor] : [rule.impostor];
  let i = 0;
  if (previous === null) {
    while (i < levels.length - 1 && depth >= bounds[i]) i++;
    return levels[i];
  }
  i = Math.max(levels.indexOf(previous), 0);
  while (i < levels.length - 1 && depth > bounds[i] * (1 + rule.hysteresis)) i++;
  while (i > 0 && depth < bounds[i - 1]) i--;
  return levels[i];
}

// The atlas tile whose bake camera is nearest the camera, in the character's own frame (crowd.cpp).
function selectTile(toCamera, heading, impostor) {
  const c = Math.cos(heading), s = Math.sin(heading);
  const local = new THREE.Vector3(c * toCamera.x - s * toCamera.z, toCamera.y, s * toCamera.x + c * toCamera.z).normalize();
  const azimuth = THREE.MathUtils.radToDeg(Math.atan2(local.x, local.z));
  const elevation = THREE.MathUtils.radToDeg(Math.asin(THREE.MathUtils.clamp(local.y, -1, 1)));
  const gap = (a, b) => { const d = Math.abs(a - b) % 360; return Math.min(d, 360 - d); };
  let a = 0, e = 0;
  impostor.azimuths_deg.forEach((value, k) => { if (gap(azimuth, value) < gap(azimuth, impostor.azimuths_deg[a])) a = k; });
  impostor.elevations_deg.forEach((value, k) => { if (Math.abs(elevation - value) < Math.abs(elevation - impostor.elevations_deg[e])) e = k; });
  return a + e * impostor.azimuths_deg.length;
}

// The baked frame nearest `frame` (of the clip starting at pose frame `first`) around the clip (crowd.cpp
// impostor_layer); layers of other clips and transitions are not candidates.
function impostorLayer(frame, frameIndices, frameCount, first = 0) {
  let best = 0, bestDistance = Infinity;
  frameIndices.forEach((f, k) => {
    if (f < first || f >= first + frameCount) return;
    const d = Math.abs(frame - (f - first));
    const around = Math.min(d, frameCount - d);
    if (around < bestDistance) { best = k; bestDistance = around; }
  });
  return best;
}

function instanced(geometry, capacity) {
  const result = new THREE.InstancedBufferGeometry();
  result.index = geometry.index;
  for (const [name, attribute] of Object.entries(geometry.attributes)) result.setAttribute(name, attribute);
  result.setAttribute('iPose', new THREE.InstancedBufferAttribute(new Float32Array(capacity * 4), 4));
  result.setAttribute('iIds', new THREE.InstancedBufferAttribute(new Float32Array(capacity * 4), 4));
  result.instanceCount = 0;
  return result;
}

async function main() {
  if (exportUrl === null) {
    showStatus('empty', 'No export to show: open this page with ?export=URL of an export folder ' +
      '(the jobs page\'s "Preview crowd" link gives one).');
    return;
  }
  if (!(Number.isInteger(count) && count >= 0) || !(width >= 16 && height >= 16)) {
    throw new Error(`count must be a whole number >= 0 and width, height at least 16 (got count=${params.get('count')}, ` +
      `width=${params.get('width')}, height=${params.get('height')})`);
  }
  if (count === 0) {
    showStatus('empty', 'count=0: no characters to draw.');
    return;
  }
  const sidecarUrl = new URL('export.json', exportUrl);
  showStatus('false', `Loading ${sidecarUrl.href} …`);
  const response = await fetch(sidecarUrl, { headers: authHeaders });
  if (!response.ok) {
    // A private bundle answers 404 to a caller without its key, as a missing one does.
    const hint = [401, 403, 404].includes(response.status) ? ' (missing, or a private bundle: open the preview from the jobs page, which holds the key)' : '';
    throw new Error(`${sidecarUrl.href}: HTTP ${response.status}${hint}`);
  }
  const sidecar = await response.json().catch(() => { throw new Error(`${sidecarUrl.href} is not JSON`); });
  checkExport(sidecar);
  showStatus('false', `Loading textures and meshes of ${sidecar.bundle?.name ?? 'the export'} …`);
  const url = (path) => new URL(path, exportUrl).href;
  // A bundle of several clips plays its first clip, looped (docs/export.md "Several clips").
  const clip = sidecar.animations?.find((a) => a.playback === 'loop')?.vat ?? { first_frame: 0, frames: sidecar.frame_count };
  const fps = sidecar.frames_per_second, frameCount = clip.frames;
  const impostor = sidecar.impostor;

  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  const load = (path, options = {}) => loadKtx2Texture(url(path), { headers: authHeaders, renderer, ...options });
  // A VAT file LODs share (export.json `texels_of_lod`) is fetched and uploaded once.
  const vatTextures = new Map();
  const loadOnce = (path) => {
    if (!vatTextures.has(path)) vatTextures.set(path, load(path));
    return vatTextures.get(path);
  };

  // Textures shared by every LOD: diffuse arrays per material, outfits, impostor maps.
  const diffuse = await Promise.all(sidecar.materials.map((m) => load(m.diffuse.ktx2, { filter: THREE.LinearFilter })));
  const variations = sidecar.materials.map((m) => m.variations);
  const outfits = await load(sidecar.outfits.ktx2);
  const [uvMap, normalMap] = await Promise.all([load(impostor.maps.uv.ktx2), load(impostor.maps.normal.ktx2)]);

  const scene = new THREE.Scene();
  const capacity = count;
  const groups = {};  // lod name -> [{mesh}] drawn with that LOD's instances
  const loader = new GLTFLoader().setRequestHeader(authHeaders);
  const lodNames = ['high', 'low'];
  for (const lod of sidecar.lods.slice(0, 2)) {
    const gltf = await loader.loadAsync(url(lod.glb));
    const meshes = [];
    gltf.scene.traverse((object) => { if (object.isMesh) meshes.push(object); });
    const entries = [];
    for (const part of lod.parts) {
      const mesh = meshes.find((m) => m.name === part.part || m.parent?.name === part.part || m.geometry.name === part.part);
      if (!mesh) throw new Error(`${lod.glb}: no mesh named ${part.part}`);
      const geometry = mesh.geometry;
      geometry.setAttribute('vatUv', geometry.getAttribute('uv1'));  // glTF TEXCOORD_1
      const [vat, joints] = await Promise.all([loadOnce(part.vat.texture.ktx2), part.vat.joints ? loadOnce(part.vat.joints.ktx2) : null]);
      const material = createVatMaterial({
        vat: part.vat,
        textures: { vat, joints, diffuse: diffuse[part.material], outfits },
        variations: variations[part.material],
        lightDir: LIGHT_DIR,
        doubleSided: part.kind === 'garment',
        clip,
      });
      const drawn = new THREE.Mesh(instanced(geometry, capacity), material);
      drawn.frustumCulled = false;
      scene.add(drawn);
      entries.push(drawn);
    }
    groups[lodNames[lod.lod]] = entries;
  }
  const hasLow = Boolean(groups.low);
  const quad = new THREE.BufferGeometry();
  quad.setAttribute('position', new THREE.Float32BufferAttribute([-1, -1, 0, 1, -1, 0, -1, 1, 0, 1, 1, 0], 3));
  quad.setIndex([0, 1, 2, 2, 1, 3]);
  const impostorMesh = new THREE.Mesh(instanced(quad, capacity), createImpostorMaterial({
    impostor, textures: { uv: uvMap, normal: normalMap, outfits, diffuse }, variations, lightDir: LIGHT_DIR,
  }));
  impostorMesh.frustumCulled = false;
  scene.add(impostorMesh);
  groups.impostor = [impostorMesh];

  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;  // crowdview writes shader colours as they are
  renderer.setPixelRatio(1);
  renderer.setSize(width, height, false);  // the stylesheet fits the canvas to the window
  renderer.setClearColor(new THREE.Color().setRGB(...SKY, THREE.LinearSRGBColorSpace), 1);
  document.body.appendChild(renderer.domElement);

  const characterHeight = impostor.bounds.center[1] + impostor.bounds.radius;
  const crowd = makeCrowd(count, Math.max(...variations), sidecar.outfits.count, frameCount / fps, crowdSpacing(impostor.bounds.radius));
  const camera = overviewCamera(crowd.half, characterHeight, width / height);
  const rule = lodBoundaries(impostor, height);
  const forward = camera.getWorldDirection(new THREE.Vector3());
  const counts = { high: 0, low: 0, impostor: 0 };
  const center = new THREE.Vector3(...impostor.bounds.center);

  function update(time) {
    const lists = { high: [], low: [], impostor: [] };
    for (const c of crowd.characters) {
      const h = c.heading, ch = Math.cos(h), sh = Math.sin(h);
      const worldCenter = new THREE.Vector3(ch * center.x + sh * center.z, center.y, -sh * center.x + ch * center.z).add(c.position);
      const depth = worldCenter.clone().sub(camera.position).dot(forward);
      let lod = lodMode === 'auto' ? chooseLod(depth, c.lod, rule, hasLow) : lodMode;
      if (lod === 'low' && !hasLow) lod = 'high';
      c.lod = lod;
      const frame = (((time + c.phase) * fps) % frameCount + frameCount) % frameCount;
      if (lod === 'impostor') {
        const tile = selectTile(camera.position.clone().sub(worldCenter), h, impostor);
        const layer = impostorLayer(Math.floor(frame), impostor.frame_indices, frameCount, clip.first_frame);
        lists.impostor.push([c, layer, tile]);
      } else {
        lists[lod].push([c, frame, 0]);
      }
    }
    for (const [lod, list] of Object.entries(lists)) {
      counts[lod] = list.length;
      for (const mesh of groups[lod] || []) {
        const pose = mesh.geometry.getAttribute('iPose'), ids = mesh.geometry.getAttribute('iIds');
        list.forEach(([c, frameOrLayer, tile], k) => {
          pose.setXYZW(k, c.position.x, c.position.y, c.position.z, c.heading);
          ids.setXYZW(k, frameOrLayer, c.variation, c.outfit, tile);
        });
        pose.needsUpdate = ids.needsUpdate = true;
        mesh.geometry.instanceCount = list.length;
        mesh.visible = list.length > 0;
      }
    }
  }

  const report = () => {
    status.textContent = JSON.stringify({ ready: true, characters: count, lod: counts, switch_distance_m: rule.impostor, bundle: sidecar.bundle, clip,
      texture_formats: [...new Set([...diffuse, outfits, uvMap, normalMap].map((t) => t.userData.vkFormat))].sort((a, b) => a - b) });
    status.dataset.ready = 'true';
  };
  if (fixedTime !== null) {
    update(fixedTime);
    renderer.render(scene, camera);
    report();
  } else {
    const start = performance.now();
    renderer.setAnimationLoop(() => {
      update((performance.now() - start) / 1000);
      renderer.render(scene, camera);
      report();
    });
  }
}

main().catch((error) => {
  showStatus('error', `Could not show the export: ${error && error.message || error}`);
  console.error(error);
});
