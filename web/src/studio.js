// The avatar-motor studio: a live view of the served world and its controls (docs/protocol.md).
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const token = params.get("token");
const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${token ? "?token=" + encodeURIComponent(token) : ""}`;

// ---------------------------------------------------------------- scene
// Low quality, for a browser without a GPU: no antialiasing, no shadows, Lambert shading and the
// human's coarse mesh (/api/human?detail=low). Software GL (headless Chromium, 2 cores) drew 8
// skinned humans at 2-3 frames/s in high quality; without antialiasing and shadows 6-7; the
// full-screen floor alone took ~40 ms a frame with physically based shading, ~20 with Lambert.
// Also 3/4 of the resolution, and the drawing buffer not kept after each frame (each of the two
// gave about 6 frames/s more there, where 8 humans then drew at 30).
// ?quality=low|high chooses; without it, low where WebGL is software (SwiftShader, llvmpipe)
function softwareGL() {
  const gl = document.createElement("canvas").getContext("webgl2") || document.createElement("canvas").getContext("webgl");
  if (!gl) return true;
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
  gl.getExtension("WEBGL_lose_context")?.loseContext();
  return /swiftshader|llvmpipe|softpipe|software/i.test(name);
}
const QUALITY = ["low", "high"].includes(params.get("quality")) ? params.get("quality") : softwareGL() ? "low" : "high";
// a surface's material: physically based, or Lambert in low quality
const surface = (opts) => QUALITY === "low"  // (Lambert takes the colours, not roughness or metalness)
  ? new THREE.MeshLambertMaterial(Object.fromEntries(Object.entries(opts).filter(([k]) => k === "color" || k === "emissive")))
  : new THREE.MeshStandardMaterial(opts);
const renderer = new THREE.WebGLRenderer({ antialias: QUALITY === "high", preserveDrawingBuffer: QUALITY === "high" });
renderer.setPixelRatio(QUALITY === "high" ? window.devicePixelRatio : Math.min(0.75, window.devicePixelRatio));
renderer.shadowMap.enabled = QUALITY !== "low";
$("view").appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x262c33);
scene.fog = new THREE.Fog(0x262c33, 15, 45);
const camera = new THREE.PerspectiveCamera(45, 1, 0.05, 200);
camera.position.set(2.5, 2.0, -3.5);
const orbit = new OrbitControls(camera, renderer.domElement);
orbit.target.set(0, 0.9, 0);
orbit.mouseButtons = { LEFT: null, MIDDLE: THREE.MOUSE.DOLLY, RIGHT: THREE.MOUSE.ROTATE };
scene.add(new THREE.HemisphereLight(0xdde8ff, 0x303030, 1.4));
const sun = new THREE.DirectionalLight(0xffffff, 2.2);
sun.position.set(4, 8, 3);
sun.castShadow = true;
sun.shadow.mapSize.set(2048, 2048);
Object.assign(sun.shadow.camera, { left: -6, right: 6, top: 6, bottom: -6, near: 0.5, far: 30 });
scene.add(sun, sun.target);
// (unlit in low quality: software GL shades every pixel of it, and lit it took ~19 ms of a frame
// with 128 avatars; it is one flat colour either way but for the shadows high quality casts)
const ground = new THREE.Mesh(new THREE.PlaneGeometry(200, 200), QUALITY === "low"
  ? new THREE.MeshBasicMaterial({ color: 0x353d46 }) : surface({ color: 0x3a434d, roughness: 0.95 }));
ground.rotation.x = -Math.PI / 2;
ground.receiveShadow = true;
scene.add(ground);
// a grid of 1-m squares around the camera's target (moved in whole metres, so its lines stay put
// on the floor): 60 m across in low quality, 120 m in high (the fog hides the floor from 45 m).
// Each line is made of short pieces: software GL dropped a whole line that reached behind the
// camera, so GridHelper's 90-m lines showed only far off, none around the avatars. Low quality
// draws fewer pieces (60 m of 2-m pieces: 3,700 instead of 16,000).
function makeGrid(size, piece, centre, other) {
  const half = size / 2, pos = [], col = [];
  const c1 = new THREE.Color(centre), c2 = new THREE.Color(other);
  for (let i = -half; i <= half; i++) {
    const c = i === 0 ? c1 : c2;
    for (let k = -half; k < half; k += piece) {
      pos.push(i, 0, k, i, 0, k + piece, k, 0, i, k + piece, 0, i);  // a piece along Z at x = i, one along X at z = i
      for (let n = 0; n < 4; n++) col.push(c.r, c.g, c.b);
    }
  }
  const geo = new THREE.BufferGeometry();
  geo.setAttribute("position", new THREE.Float32BufferAttribute(pos, 3));
  geo.setAttribute("color", new THREE.Float32BufferAttribute(col, 3));
  return new THREE.LineSegments(geo, new THREE.LineBasicMaterial({ vertexColors: true }));
}
const grid = QUALITY === "low" ? makeGrid(60, 2, 0x59646f, 0x48525c) : makeGrid(120, 1, 0x59646f, 0x48525c);
grid.matrixAutoUpdate = false;  // placed in animate(): on the floor (groundFrame), under the camera's target
scene.add(grid);
let groundFrame = new THREE.Matrix4();  // the floor's turn (drawEnvironment: a tilted ground)
const _gridAt = new THREE.Matrix4();
const magnetMesh = new THREE.Mesh(new THREE.TorusGeometry(0.25, 0.04, 8, 32), surface({ color: 0xff9040, emissive: 0x552200 }));
magnetMesh.rotation.x = Math.PI / 2;
magnetMesh.visible = false;
scene.add(magnetMesh);

function resize() {
  const w = window.innerWidth, h = window.innerHeight;
  renderer.setSize(w, h);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();

// ---------------------------------------------------------------- avatars
const COLORS = [0x6fa8dc, 0xe69138, 0x93c47d, 0xc27ba0, 0xffd966, 0x76a5af, 0xe06666, 0x8e7cc3];
const RADIUS = [0.09, 0.075, 0.075, 0.08, 0.06, 0.06, 0.08, 0.045, 0.045, 0.09, 0.035, 0.035, 0.05, 0.05, 0.05, 0.1, 0.05, 0.05, 0.04, 0.04, 0.035, 0.035];
let PARENTS = [];
let JOINTS = [];
const UP = new THREE.Vector3(0, 1, 0);

// the bodies beyond the skinned humans, as capsule figures. High quality: every avatar's joints
// and bones as two instanced meshes (two draw calls and their shadows for any crowd: one mesh per
// joint and bone had 128 avatars issue 11,000 draw calls a frame). Low quality: one mesh whose
// vertices are written here each frame (joints as octahedra, bones as open 4-sided prisms: with
// spheres of 12 x 8 and cylinders of 10 sides a figure is ~5,000 triangles): software GL spent
// ~20 us per instance of an instanced mesh whatever its size (128 avatars: 6.9 frames/s, and
// ~13 without the joints' 2,816 instances), while 38,000 vertices in one mesh cost it little
const JOINT_GEO = QUALITY === "low" ? null : new THREE.SphereGeometry(1, 12, 8);
const BONE_GEO = QUALITY === "low" ? null : new THREE.CylinderGeometry(1, 1, 1, 10);
const BODY_MAT = QUALITY === "low" ? new THREE.MeshLambertMaterial({ vertexColors: true }) : surface({ roughness: 0.55, metalness: 0.05 });
const _m = new THREE.Matrix4(), _q = new THREE.Quaternion(), _a = new THREE.Vector3(), _b = new THREE.Vector3(),
  _d = new THREE.Vector3(), _s = new THREE.Vector3(), _c = new THREE.Color(), _e1 = new THREE.Vector3(), _e2 = new THREE.Vector3(),
  _onRay = new THREE.Vector3();
const jointRadius = (j) => (j === 15 ? 0.11 : RADIUS[j] * 1.05);
const boneRadius = (j, p) => Math.min(RADIUS[j], RADIUS[p]) * 0.9;
// the merged mesh's layout per body: 22 octahedra (6 vertices, 8 triangles), then 21 prisms (8
// vertices: 4 around each end; 8 triangles)
const OCTA = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]];
const OCTA_FACES = [0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5];
const PRISM_FACES = [];
for (let i = 0; i < 4; i++) {  // side i: ends a_i, a_i+1 (vertices 0-3) and b_i, b_i+1 (4-7), outward
  const n = (i + 1) % 4;
  PRISM_FACES.push(i, n, 4 + i, n, 4 + n, 4 + i);
}
const BODY_VERTICES = 22 * 6 + 21 * 8, BODY_INDICES = 22 * 24 + 21 * 24;

class CrowdView {
  constructor() { this.capacity = 0; this.order = []; this.dirty = false; this.bonesOf = []; this.colorOf = []; this.colored = 0; }
  ensure(n) {  // room for n avatars, grown by doubling
    if (n <= this.capacity) return;
    this.capacity = Math.max(16, 2 ** Math.ceil(Math.log2(n)));
    this.colored = 0;
    if (QUALITY === "low") {
      if (this.mesh) { scene.remove(this.mesh); this.mesh.geometry.dispose(); }
      const geo = new THREE.BufferGeometry();
      const V = this.capacity * BODY_VERTICES;
      for (const [name, size] of [["position", 3], ["normal", 3], ["color", 3]]) {
        geo.setAttribute(name, new THREE.BufferAttribute(new Float32Array(V * size), size).setUsage(THREE.DynamicDrawUsage));
      }
      const index = new Uint32Array(this.capacity * BODY_INDICES);
      for (let k = 0, o = 0; k < this.capacity; k++) {
        const base = k * BODY_VERTICES;
        for (let j = 0; j < 22; j++) for (const f of OCTA_FACES) index[o++] = base + 6 * j + f;
        for (let n = 0; n < 21; n++) for (const f of PRISM_FACES) index[o++] = base + 22 * 6 + 8 * n + f;
      }
      geo.setIndex(new THREE.BufferAttribute(index, 1));
      geo.setDrawRange(0, 0);
      this.mesh = new THREE.Mesh(geo, BODY_MAT);
      this.mesh.frustumCulled = false;  // the vertices move every frame
      scene.add(this.mesh);
      return;
    }
    if (this.joints) { scene.remove(this.joints, this.bones); this.joints.dispose(); this.bones.dispose(); }
    this.joints = new THREE.InstancedMesh(JOINT_GEO, BODY_MAT, this.capacity * 22);
    this.bones = new THREE.InstancedMesh(BONE_GEO, BODY_MAT, this.capacity * 21);
    for (const m of [this.joints, this.bones]) {
      m.castShadow = true;
      m.frustumCulled = false;  // the instances move every frame
      m.count = 0;
      scene.add(m);
    }
  }
  // write every body's figure (when a frame arrived); bodies: Map id -> {positions}
  draw(bodies) {
    if (!this.dirty || !PARENTS.length) return;
    this.dirty = false;
    this.bonesOf = PARENTS.map((p, j) => (p >= 0 ? j : -1)).filter((j) => j >= 0);
    const ids = [...bodies.keys()].sort((x, y) => x - y);
    this.ensure(ids.length);
    this.order = [];
    let k = 0;
    for (const id of ids) {
      const pos = bodies.get(id).positions;
      if (!pos) continue;
      const recolor = k >= this.colored || this.colorOf[k] !== id;  // colours follow the avatar's id
      if (recolor) _c.setHex(COLORS[id % COLORS.length]);
      if (QUALITY === "low") this.writeBody(k, pos, recolor);
      else this.placeBody(k, pos, recolor);
      this.order.push(id);
      k++;
    }
    this.colorOf = this.order.slice();
    this.colored = k;
    if (QUALITY === "low") {
      const geo = this.mesh.geometry;
      for (const name of ["position", "normal"]) {
        geo.attributes[name].clearUpdateRanges();
        geo.attributes[name].addUpdateRange(0, k * BODY_VERTICES * 3);
        geo.attributes[name].needsUpdate = true;
      }
      if (this.colorsChanged) geo.attributes.color.needsUpdate = true;
      geo.setDrawRange(0, k * BODY_INDICES);
    } else {
      this.joints.count = k * 22;
      this.bones.count = k * 21;
      for (const m of [this.joints, this.bones]) {
        m.instanceMatrix.needsUpdate = true;
        if (m.instanceColor && this.colorsChanged) m.instanceColor.needsUpdate = true;
      }
    }
    this.colorsChanged = false;
  }
  // body k's vertices in the merged mesh (low quality)
  writeBody(k, pos, recolor) {
    const geo = this.mesh.geometry;
    const P = geo.attributes.position.array, N = geo.attributes.normal.array, C = geo.attributes.color.array;
    let v = k * BODY_VERTICES * 3;
    if (recolor) {
      for (let i = v; i < v + BODY_VERTICES * 3; i += 3) { C[i] = _c.r; C[i + 1] = _c.g; C[i + 2] = _c.b; }
      this.colorsChanged = true;
    }
    for (let j = 0; j < 22; j++) {
      const r = jointRadius(j), x = pos[3 * j], y = pos[3 * j + 1], z = pos[3 * j + 2];
      for (const [a, b, c] of OCTA) {
        P[v] = x + r * a; P[v + 1] = y + r * b; P[v + 2] = z + r * c;
        N[v] = a; N[v + 1] = b; N[v + 2] = c;
        v += 3;
      }
    }
    for (let n = 0; n < this.bonesOf.length; n++) {
      const j = this.bonesOf[n], p = PARENTS[j];
      _a.set(pos[3 * p], pos[3 * p + 1], pos[3 * p + 2]);
      _b.set(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
      _d.subVectors(_b, _a);
      if (_d.lengthSq() < 1e-12) _d.set(0, 1, 0);
      _d.normalize();
      // two axes across the bone, e1 x e2 = d (the faces' winding faces outward)
      _e1.set(Math.abs(_d.y) < 0.9 ? 0 : 1, Math.abs(_d.y) < 0.9 ? 1 : 0, 0).cross(_d).negate().normalize();
      _e2.crossVectors(_d, _e1);
      const r = boneRadius(j, p);
      for (const end of [_a, _b]) {
        for (let i = 0; i < 4; i++) {
          const s = i < 2 ? 1 : -1, e = i % 2 === 0 ? _e1 : _e2;
          const nx = s * e.x, ny = s * e.y, nz = s * e.z;
          P[v] = end.x + r * nx; P[v + 1] = end.y + r * ny; P[v + 2] = end.z + r * nz;
          N[v] = nx; N[v + 1] = ny; N[v + 2] = nz;
          v += 3;
        }
      }
    }
  }
  // body k's instances (high quality)
  placeBody(k, pos, recolor) {
    if (recolor) {
      for (let j = 0; j < 22; j++) this.joints.setColorAt(k * 22 + j, _c);
      for (let j = 0; j < 21; j++) this.bones.setColorAt(k * 21 + j, _c);
      this.colorsChanged = true;
    }
    for (let j = 0; j < 22; j++) {
      const r = jointRadius(j);
      _m.makeScale(r, r, r).setPosition(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
      this.joints.setMatrixAt(k * 22 + j, _m);
    }
    for (let n = 0; n < this.bonesOf.length; n++) {
      const j = this.bonesOf[n], p = PARENTS[j];
      _a.set(pos[3 * p], pos[3 * p + 1], pos[3 * p + 2]);
      _b.set(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
      _d.subVectors(_b, _a);
      const len = _d.length();
      const r = boneRadius(j, p);
      _q.setFromUnitVectors(UP, len > 1e-6 ? _d.divideScalar(len) : UP);
      _m.compose(_a.addScaledVector(_b.sub(_a), 0.5), _q, _s.set(r, Math.max(len, 1e-3), r));
      this.bones.setMatrixAt(k * 21 + n, _m);
    }
  }
  // the avatar and joint under the ray, or null: the nearest joint ball or bone it passes through
  // (from the streamed positions: the same in either quality)
  pick(ray) {
    let best = null;
    const consider = (t, avatar, joint) => { if (t > 0 && (!best || t < best.t)) best = { t, avatar, joint }; };
    for (const id of this.order) {
      const b = bodies.get(id);
      if (!b || !b.positions) continue;
      const pos = b.positions;
      for (let j = 0; j < 22; j++) {
        _a.set(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
        const r = jointRadius(j);
        if (ray.distanceSqToPoint(_a) <= r * r) consider(_d.subVectors(_a, ray.origin).dot(ray.direction), id, j);
      }
      for (const j of this.bonesOf) {
        const p = PARENTS[j], r = boneRadius(j, p);
        _a.set(pos[3 * p], pos[3 * p + 1], pos[3 * p + 2]);
        _b.set(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
        if (ray.distanceSqToSegment(_a, _b, _onRay) <= r * r) consider(_onRay.sub(ray.origin).dot(ray.direction), id, j);
      }
    }
    return best && { avatar: best.avatar, joint: best.joint, point: ray.at(best.t, new THREE.Vector3()) };
  }
}
// the skinned human (body/human.py): for the first HUMANS avatars, each fitted to its own body by
// the server (/api/human: a .glb of its skeleton and skinned mesh) and posed from the stream's
// rotations (joint 0 the pelvis's global rotation and position, the others relative to their
// parent, as the glTF's joint nodes take them); the rest of a crowd is drawn as capsules
const HUMANS = QUALITY === "low" ? 8 : 16;
const loader = new GLTFLoader();
class HumanView {
  constructor() { this.humans = new Map(); this.loading = new Set(); this.enabled = true; }
  // avatars drawn as humans now; loads the missing ones and drops those gone
  sync(bodies) {
    const want = this.enabled ? [...bodies.keys()].sort((x, y) => x - y).slice(0, HUMANS) : [];
    for (const id of [...this.humans.keys()]) {
      if (!want.includes(id)) {  // removed (or beyond HUMANS): its GPU buffers go with it
        const h = this.humans.get(id);
        scene.remove(h.root);
        h.mesh.geometry.dispose();
        h.mesh.material.dispose();
        this.humans.delete(id);
      }
    }
    for (const id of want) {
      if (this.humans.has(id) || this.loading.has(id) || !JOINTS.length) continue;
      this.loading.add(id);
      loader.load(`/api/human?avatar=${id}${QUALITY === "low" ? "&detail=low" : ""}${token ? "&token=" + encodeURIComponent(token) : ""}`, (gltf) => {
        this.loading.delete(id);
        if (!bodies.has(id) || !this.enabled) return;
        const root = gltf.scene;
        const bones = JOINTS.map((n) => root.getObjectByName(n));
        let mesh = null;
        root.traverse((o) => { if (o.isSkinnedMesh) { mesh = o; o.castShadow = true; o.frustumCulled = false; } });
        if (!mesh || bones.some((b) => !b)) { state.errors.push(`avatar ${id}: the human's skeleton is incomplete`); return; }
        mesh.material = QUALITY === "low" ? new THREE.MeshLambertMaterial({ color: mesh.material.color }) : mesh.material.clone();
        mesh.material.color.lerp(_c.setHex(COLORS[id % COLORS.length]), 0.25);  // each avatar's colour, lightly
        scene.add(root);
        this.humans.set(id, { root, bones, mesh });
        view.dirty = true;
      }, undefined, () => { this.loading.delete(id); });
    }
    for (const [id, h] of this.humans) {
      const b = bodies.get(id);
      if (!b || !b.rotations) continue;
      const p = b.positions, q = b.rotations;
      h.bones[0].position.set(p[0], p[1], p[2]);
      for (let j = 0; j < 22; j++) h.bones[j].quaternion.set(q[4 * j], q[4 * j + 1], q[4 * j + 2], q[4 * j + 3]);
    }
  }
  // the bodies still drawn as capsules
  others(bodies) {
    if (!this.humans.size) return bodies;
    return new Map([...bodies].filter(([id]) => !this.humans.has(id)));
  }
  // the avatar under the ray and its joint nearest the hit, or null
  pick(ray) {
    const meshes = [...this.humans.values()].map((h) => h.mesh);
    // three.js keeps a skinned mesh's first bounding sphere, and a ray outside it misses the mesh:
    // an avatar that walked away from where it was first picked could no longer be grabbed
    for (const m of meshes) m.computeBoundingSphere();
    const hits = meshes.length ? ray.intersectObjects(meshes) : [];
    if (!hits.length) return null;
    const id = [...this.humans.entries()].find(([, h]) => h.mesh === hits[0].object)[0];
    const p = bodies.get(id).positions, x = hits[0].point;
    let joint = 0, best = Infinity;
    for (let j = 0; j < 22; j++) {
      const d = (p[3 * j] - x.x) ** 2 + (p[3 * j + 1] - x.y) ** 2 + (p[3 * j + 2] - x.z) ** 2;
      if (d < best) { best = d; joint = j; }
    }
    return { avatar: id, joint, point: hits[0].point };
  }
}
const view = new CrowdView();
const humans = new HumanView();
const bodies = new Map();

// ---------------------------------------------------------------- connection
const state = { frame: 0, connected: false, fpsTimes: [], renderTimes: [], selected: 0, model: "", lastStats: null,
  received: 0, drawn: 0, errors: [], stalls: 0, stallsRecent: 0, physics: new Set(), balls: [] };
window.studio = state;  // for tests and the console
state.quality = QUALITY;
state.humans = () => [...humans.humans.keys()];  // the avatars drawn as skinned humans
state.maxHumans = HUMANS;
state.triangles = (id) => humans.humans.has(id) ? humans.humans.get(id).mesh.geometry.index.count / 3 : 0;
let ws;
let nextId = 1;
const pending = new Map();

function send(cmd) {
  if (!ws || ws.readyState !== 1) return Promise.resolve(null);
  const id = nextId++;
  ws.send(JSON.stringify({ ...cmd, id }));
  return new Promise((resolve) => pending.set(id, resolve));
}
state.send = send;

function connect() {
  ws = new WebSocket(wsUrl);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { state.connected = true; if (token) send({ type: "hello", token }); };
  ws.onclose = () => { state.connected = false; $("warn").textContent = "disconnected: retrying…"; setTimeout(connect, 1000); };
  ws.onmessage = (ev) => {
    if (typeof ev.data !== "string") return onFrame(ev.data);
    const msg = JSON.parse(ev.data);
    if (msg.type === "welcome") {
      if (msg.auth) { $("warn").textContent = "this server needs its token: open the studio as /?token=..."; return; }
      PARENTS = msg.parents; JOINTS = msg.joint_names; state.model = msg.model;
      $("model").textContent = msg.model;
      $("licence").textContent = msg.licence;
      buildPresets(msg.presets);
      buildLabels(msg.adaptors);
      $("persona-panel").style.display = msg.persona ? "" : "none";
      if (msg.environment) drawEnvironment(msg.environment);
      $("warn").textContent = "";
    } else if (msg.type === "stats") {
      // stalls: ticks at which generation had no frame ready (the avatar held its pose)
      state.stallsRecent = state.lastStats ? msg.stalls - state.lastStats.stalls : 0;
      state.lastStats = msg;
      state.stalls = msg.stalls;
      $("gen").textContent = msg.gen_ms;
      $("stalls").textContent = msg.stalls;
      if (msg.environment) drawEnvironment(msg.environment);
      showPhysics();
      warn();
    } else if (msg.type === "environment") {
      drawEnvironment(msg);
    } else if (msg.type === "balls") {
      state.balls = msg.balls;
      drawBalls(msg.balls);
    } else if (msg.type === "ack" || msg.type === "error") {
      if (msg.type === "error") { state.errors.push(msg.error); console.warn(msg.error); }
      // avatars a failing batch stood up (World._give_up): in the HUD for 15 s
      if (msg.type === "error" && msg.avatars) state.notice = { text: msg.error, until: performance.now() + 15000 };
      const r = pending.get(msg.id);
      if (r) { pending.delete(msg.id); r(msg); }
    }
  };
}

// what the HUD warns about: the server's generation falling behind, the stream arriving below
// 30 fps (network or server), or this browser drawing below 30 fps
function warn() {
  const msgs = [];
  if (state.stallsRecent > 0) msgs.push(`generation is behind: ${state.stallsRecent} stalled frame(s) in the last second`);
  if (state.fpsTimes.length < 28 && state.connected && state.received > 60) msgs.push(`stream below 30 fps (${state.fpsTimes.length})`);
  if (state.notice && performance.now() < state.notice.until) msgs.push(state.notice.text);
  if (state.renderTimes.length < 28 && state.received > 60) msgs.push(`this browser draws ${state.renderTimes.length} fps${QUALITY === "high" ? " (open the studio with ?quality=low)" : ""}`);
  $("warn").textContent = msgs.join(" · ");
}

function onFrame(buf) {
  const dv = new DataView(buf);
  const frame = dv.getUint32(4, true), n = dv.getUint16(8, true);
  let off = 12;
  const seen = new Set();
  for (let k = 0; k < n; k++) {
    const id = dv.getUint32(off, true);
    const pos = new Float32Array(buf.slice(off + 4, off + 4 + 264));
    const rot = new Float32Array(buf.slice(off + 4 + 264, off + 4 + 264 + 352));
    off += 4 + 264 + 352;
    seen.add(id);
    if (PARENTS.length) bodies.set(id, { id, positions: pos, rotations: rot });
  }
  for (const id of [...bodies.keys()]) if (!seen.has(id)) bodies.delete(id);
  view.dirty = true;
  state.frame = frame;
  state.received++;
  const now = performance.now();
  state.fpsTimes.push(now);
  while (state.fpsTimes.length && now - state.fpsTimes[0] > 1000) state.fpsTimes.shift();
  refreshSelect();
}
state.pelvis = (id) => { const b = bodies.get(id ?? state.selected); return b && b.positions ? Array.from(b.positions.slice(0, 3)) : null; };
state.screenOfPoint = (x, y, z) => {  // pixel position of a world point (tests drive the mouse with it)
  const v = new THREE.Vector3(x, y, z).project(camera);
  return [(v.x + 1) / 2 * window.innerWidth, (1 - v.y) / 2 * window.innerHeight];
};
state.screenOf = (id, joint) => {  // pixel position of a joint
  const b = bodies.get(id);
  if (!b || !b.positions) return null;
  return state.screenOfPoint(b.positions[3 * joint], b.positions[3 * joint + 1], b.positions[3 * joint + 2]);
};
state.pickAt = (x, y) => {  // what a click at this pixel grabs: {avatar, joint} or null (tests aim with it)
  const el = document.elementFromPoint(x, y);
  if (el !== renderer.domElement) return null;  // a panel over the canvas takes the click
  const hit = bodyUnder({ clientX: x, clientY: y });
  return hit && { avatar: hit.avatar, joint: hit.joint };
};
state.joints = (id) => { const b = bodies.get(id ?? state.selected); return b && b.positions ? Array.from(b.positions) : null; };

function refreshSelect() {
  const sel = $("select");
  const ids = [...bodies.keys()].sort((a, b) => a - b);
  if (sel.options.length !== ids.length || ids.some((id, k) => Number(sel.options[k].value) !== id)) {
    sel.innerHTML = ids.map((id) => `<option value="${id}">avatar ${id}</option>`).join("");
    if (!ids.includes(state.selected) && ids.length) state.selected = ids[0];
    sel.value = String(state.selected);
  }
  $("count").textContent = ids.length;
}
$("select").onchange = (e) => { state.selected = Number(e.target.value); showPhysics(); };

// ---------------------------------------------------------------- panel
function buildPresets(presets) {
  $("presets").innerHTML = "";
  for (const p of presets) {
    const b = document.createElement("button");
    b.textContent = p.replace("_", " ");
    b.dataset.preset = p;
    b.onclick = () => send({ type: "impulse", avatar: state.selected, preset: p });
    $("presets").appendChild(b);
  }
}
// the label adaptors' labels (actions, styles): a row of buttons per adaptor, one "none" releases
// whichever steers the avatar, the slider is the CFG scale; a reaching adaptor drives the magnet
function buildLabels(adaptors) {
  const withLabels = (adaptors || []).filter((a) => a.control === "label" && a.labels.length);
  $("actions").style.display = withLabels.length ? "" : "none";
  $("labels").innerHTML = "";
  const button = (l) => {
    const b = document.createElement("button");
    b.textContent = l ?? "none";
    b.dataset.label = l ?? "";
    // no scale until the slider is moved: the server gives each adaptor its own (its card's)
    b.onclick = () => send({ type: "label", avatar: state.selected, label: l, ...(state.scaleSet ? { scale: Number($("scale").value) } : {}) });
    return b;
  };
  for (const a of withLabels) {
    const row = document.createElement("div");
    row.className = "group";
    row.dataset.adaptor = a.name;
    const name = document.createElement("span");
    name.textContent = a.name;
    row.appendChild(name);
    for (const l of a.labels) row.appendChild(button(l));
    $("labels").appendChild(row);
  }
  $("labels").appendChild(button(null));
  const reach = (adaptors || []).find((a) => a.control === "target");
  $("magnet-mode").textContent = reach ? `the reaching adaptor (${reach.name}) walks there` : "a velocity goal walks there";
}
$("scale").oninput = () => {
  state.scaleSet = true;
  $("scale-value").textContent = $("scale").value;
};
// ---------------------------------------------------------------- personas (a persona model)
// who each avatar is, in words; the crowd button spawns distinct people of distinct builds in a row
const PERSONAS = [
  ["a weary old man", [-0.5, -0.5, 0, 0, 0, 0]],
  ["an energetic teenager", [-0.8, 0.5, 0, 0, -0.5, 0]],
  ["a graceful, elegant woman", [-0.8, 0.3, 0, 0, -1.2, 0.8]],
  ["a broad, tough man who takes up space", [1.0, 0, 0, 0, 1.5, 0]],
  ["someone utterly drained and short of breath", [0, 0, 0, 0, 0, 0]],
  ["an ordinary adult in a neutral mood", [0.3, 0, 0, 0, 0, 0]],
  ["a proud person, head held high", [0.8, 0.5, 0.5, 0, 0.5, 0]],
  ["a sad person who has just lost something dear", [-0.3, 0, 0, 0, 0, 0]],
  ["a timid person lacking confidence", [-1.0, 0, 0, 0, -0.5, 0]],
  ["an angry person, furious and tense", [0.5, 0, 0, 0, 0.8, 0]],
  ["a small-time street thug acting tough", [0, 0, 0, 0.5, 0.5, 0]],
  ["a huge, heavy giant", [2.0, 0.5, 0.5, 0.5, 1.5, 1.0]],
  ["a happy person in a wonderful mood", [0, 0, 0, 0, 0, 0]],
  ["a small child, playful and restless", [-2.5, -1.0, -1.0, -1.0, -1.0, -1.0]],
  ["an elderly person whose joints ache with age", [-0.8, -0.5, 0, 0, -0.3, 0.3]],
  ["a musical performer moving like on a stage", [0, 0.5, 0, 0.5, 0, 0]],
];
const personaOf = new Map();  // avatar -> description (shown in the list)
async function setPersona(avatar, description) {
  const r = await send({ type: "persona", avatar, description });
  if (r && r.ok) { if (description) personaOf.set(avatar, description); else personaOf.delete(avatar); }
  return r;
}
$("persona-set").onclick = () => setPersona(state.selected, $("persona-text").value.trim() || null);
$("persona-clear").onclick = () => setPersona(state.selected, null);
$("persona-crowd").onclick = async () => {
  const n = Number($("persona-count").value) || 8;
  const p = state.pelvis() || [0, 0, 0];
  for (let k = 0; k < Math.min(n, PERSONAS.length); k++) {
    const [text, shape] = PERSONAS[k];
    const r = await send({ type: "spawn", position: [p[0] + 1.2 * (k - (n - 1) / 2), p[2] + 2.0], shape });
    if (!r || !r.ok) break;
    await setPersona(r.avatar, text);
  }
  $("steer-all").checked = true;
};
for (const [text] of PERSONAS.slice(0, 6)) {
  const b = document.createElement("button");
  b.textContent = text;
  b.onclick = () => { $("persona-text").value = text; setPersona(state.selected, text); };
  $("persona-examples").appendChild(b);
}

$("add").onclick = async () => {
  const p = state.pelvis() || [0, 0, 0];
  const r = await send({ type: "spawn", position: [p[0] + 1.2, p[2]] });
  if (r && r.ok) state.selected = r.avatar;
};
$("remove").onclick = () => send({ type: "remove", avatar: state.selected });
$("reset").onclick = () => send({ type: "reset", avatar: state.selected });
let placingMagnet = false;
$("magnet").onclick = () => { placingMagnet = !placingMagnet; $("magnet").classList.toggle("on", placingMagnet); };
$("unmagnet").onclick = () => { magnetMesh.visible = false; send({ type: "target", avatar: state.selected, position: null }); };

// ---------------------------------------------------------------- physics: toggle, balls, springs
const ballMeshes = [];
const BALL_MAT = surface({ color: 0xe8e0c8, roughness: 0.6 });
function drawBalls(balls) {
  while (ballMeshes.length < balls.length) {
    const m = new THREE.Mesh(new THREE.SphereGeometry(1, 16, 12), BALL_MAT);
    m.castShadow = true;
    scene.add(m);
    ballMeshes.push(m);
  }
  ballMeshes.forEach((m, k) => {
    m.visible = k < balls.length;
    if (m.visible) { m.position.fromArray(balls[k].position); m.scale.setScalar(balls[k].radius); }
  });
}
function showPhysics() {
  const on = state.physics.has(state.selected);
  // the server simulates an avatar near a low obstacle by itself (it steps over it): say so
  const stepping = !on && (state.lastStats?.simulated || []).includes(state.selected);
  $("physics").textContent = `physics: ${on ? "on" : "off"}${stepping ? " (stepping over)" : ""}`;
  $("physics").classList.toggle("on", on);
}
$("physics").onclick = async () => {
  const on = !state.physics.has(state.selected);
  const r = await send({ type: "physics", avatar: state.selected, on });
  if (r && r.ok) { if (on) state.physics.add(state.selected); else state.physics.delete(state.selected); }
  showPhysics();
};
// a ball from the camera at the selected avatar's chest (spine3), at the panel's speed and mass
state.throwBall = async () => {
  const b = bodies.get(state.selected);
  if (!b || !b.positions) return null;
  if (!state.physics.has(state.selected)) { await $("physics").onclick(); }
  const chest = new THREE.Vector3(b.positions[27], b.positions[28], b.positions[29]);
  const from = camera.position.clone();
  const d = chest.clone().sub(from);
  const speed = Number($("ball-speed").value) || 10;
  const time = d.length() / speed;  // aim above the chest by the drop gravity gives over the flight
  const v = d.normalize().multiplyScalar(speed);
  v.y += 0.5 * 9.81 * time;
  return send({ type: "ball", avatar: state.selected, position: from.toArray().map((x) => +x.toFixed(3)),
    velocity: v.toArray().map((x) => +x.toFixed(3)), mass: Number($("ball-mass").value) || 2 });
};
$("throw").onclick = () => state.throwBall();

// ---------------------------------------------------------------- physics: the ground and obstacles
// drawn as the server describes them (welcome, `environment`, each stats message)
const OBSTACLE_MAT = surface({ color: 0x9a6a44, roughness: 0.8 });
const obstacleMeshes = [];
let environmentKey = "";
// the ground at stream frame `frame`: the environment's, or on its way there from `ground.from`
// (a tilting platform: tilt and pivot each at a constant rate over `from.frames` frames)
function groundAt(g, frame) {
  if (!g.from) return g;
  const s = Math.min(Math.max((frame - g.from.frame) / Math.max(g.from.frames, 1), 0), 1);
  const lerp = (a, b) => a.map((x, k) => x + s * (b[k] - x));
  return { tilt: lerp(g.from.tilt, g.tilt), pivot: lerp(g.from.pivot, g.pivot) };
}
state.groundAt = (frame, g) => groundAt(g ?? state.environment.ground, frame ?? state.frame ?? 0);
let groundShown = "";
function placeGround(g) {
  const key = JSON.stringify([g.tilt, g.pivot]);
  if (key === groundShown) return;
  groundShown = key;
  const [ax, az] = g.tilt.map((d) => (d * Math.PI) / 180);
  const [px, pz] = g.pivot;
  // the floor turned by R_z(az) R_x(ax) about the pivot (the plane mesh lies in its own XY plane)
  const turn = new THREE.Matrix4().makeRotationZ(az).multiply(new THREE.Matrix4().makeRotationX(ax));
  const about = new THREE.Matrix4().makeTranslation(px, 0, pz).multiply(turn).multiply(new THREE.Matrix4().makeTranslation(-px, 0, -pz));
  ground.matrixAutoUpdate = false;
  ground.matrix.copy(about.clone().multiply(new THREE.Matrix4().makeRotationX(-Math.PI / 2)));
  groundFrame = about;
  ground.matrixWorldNeedsUpdate = true;
}
function drawEnvironment(env) {
  const key = JSON.stringify([env.ground, env.obstacles]);
  if (key === environmentKey) return;
  environmentKey = key;
  state.environment = { ground: env.ground, obstacles: env.obstacles };
  placeGround(groundAt(env.ground, state.frame || 0));
  $("tilt").value = String(Math.round(env.ground.tilt[0]));
  $("tilt-value").textContent = String(Math.round(env.ground.tilt[0]));
  while (obstacleMeshes.length < env.obstacles.length) {
    const m = new THREE.Mesh(new THREE.BoxGeometry(1, 1, 1), OBSTACLE_MAT);
    m.castShadow = true;
    m.receiveShadow = true;
    scene.add(m);
    obstacleMeshes.push(m);
  }
  obstacleMeshes.forEach((m, k) => {
    const o = env.obstacles[k];
    m.visible = !!o;
    if (!o) return;
    m.scale.set(o.size[0], o.size[1], o.size[2]);
    m.position.set(o.centre[0], o.size[1] / 2, o.centre[1]);
    m.rotation.set(0, (o.yaw * Math.PI) / 180, 0);
  });
}
state.drawEnvironment = drawEnvironment;
let placingObstacle = false;
$("obstacle").onclick = () => { placingObstacle = !placingObstacle; $("obstacle").classList.toggle("on", placingObstacle); };
$("clear-obstacles").onclick = () => send({ type: "remove_obstacle" });
// a bar 2 m wide and 15 cm deep across the way from the selected avatar to the clicked point;
// the avatar is put in physics mode, so that it can step over or trip on the bar (to an avatar
// the model moves alone a bar higher than the runtime's step_over is a wall; a lower one it is
// simulated for while near it)
state.placeObstacle = async (x, z) => {
  const p = state.pelvis() || [0, 0, 0];
  const yaw = Math.atan2(x - p[0], z - p[2]) * 180 / Math.PI;  // the bar's depth (its Z) along the way
  const h = Math.max(0.02, Math.min(3, Number($("obstacle-height").value) || 0.2));
  if (!state.physics.has(state.selected)) { await $("physics").onclick(); }
  return send({ type: "obstacle", centre: [+x.toFixed(3), +z.toFixed(3)], size: [2, +h.toFixed(3), 0.15], yaw: +yaw.toFixed(1) });
};
const TILT_RATE = 10;  // degrees a second
$("tilt").oninput = () => { $("tilt-value").textContent = $("tilt").value; };
$("tilt").onchange = async () => {
  const p = state.pelvis() || [0, 0, 0];
  if (!state.physics.has(state.selected)) { await $("physics").onclick(); }
  // a tilting platform: it turns there at TILT_RATE degrees a second
  const now = state.environment ? groundAt(state.environment.ground, state.frame || 0).tilt[0] : 0;
  const seconds = Math.min(60, Math.abs(Number($("tilt").value) - now) / TILT_RATE);
  send({ type: "ground", tilt: [Number($("tilt").value), 0], pivot: [+p[0].toFixed(3), +p[2].toFixed(3)], seconds: +seconds.toFixed(2) });
};
const download = (fmt) => {
  const s = Math.max(1, Math.min(60, Number($("seconds").value) || 10));
  location.href = `/api/record?avatar=${state.selected}&seconds=${s}&format=${fmt}${token ? "&token=" + token : ""}`;
};
$("bvh").onclick = () => download("bvh");
$("glb").onclick = () => download("glb");
$("human").onchange = (e) => { humans.enabled = e.target.checked; view.dirty = true; };
// off: the view stays where the user put it (to frame a scene, or to click a fixed spot on the floor)
state.follow = true;
$("follow").onchange = (e) => { state.follow = e.target.checked; };
$("events").onclick = async () => {
  const r = await fetch(`/api/events${token ? "?token=" + token : ""}`);
  const blob = new Blob([await r.text()], { type: "application/json" });
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = "events.json";
  a.click();
};

// ---------------------------------------------------------------- steering: keyboard and gamepad
const keys = new Set();
let lastGoal = "";
function steer() {
  let f = 0, s = 0, run = keys.has("ShiftLeft") || keys.has("ShiftRight");
  if (keys.has("KeyW") || keys.has("ArrowUp")) f += 1;
  if (keys.has("KeyS") || keys.has("ArrowDown")) f -= 1;
  if (keys.has("KeyA") || keys.has("ArrowLeft")) s += 1;
  if (keys.has("KeyD") || keys.has("ArrowRight")) s -= 1;
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter(Boolean) : [];
  if (pads.length) {
    const [x, y] = pads[0].axes;
    if (Math.hypot(x, y) > 0.2) { f = -y; s = -x; run = run || Math.hypot(x, y) > 0.9 || (pads[0].buttons[0] && pads[0].buttons[0].pressed); }
  }
  // camera-relative directions on the ground
  const fwd = new THREE.Vector3();
  camera.getWorldDirection(fwd);
  fwd.y = 0; fwd.normalize();
  const left = new THREE.Vector3().crossVectors(UP, fwd).normalize();
  const d = fwd.multiplyScalar(f).addScaledVector(left, s);
  let goal = null;
  if (d.length() > 0.1) { d.normalize().multiplyScalar(run ? 3.0 : 1.3); goal = [+d.x.toFixed(2), +d.z.toFixed(2)]; }
  const key = JSON.stringify(goal);
  if (key !== lastGoal) {
    lastGoal = key;
    // "steer all": the crowd walks the same way (each avatar follows the stick in its own style)
    const who = $("steer-all").checked ? [...bodies.keys()] : [state.selected];
    for (const a of who) send({ type: "goal", avatar: a, velocity: goal });
  }
}
// typing a description must not walk the avatar
const typing = (e) => e.target && (e.target.tagName === "INPUT" || e.target.tagName === "TEXTAREA");
window.addEventListener("keydown", (e) => { if (typing(e)) return; keys.add(e.code); if (e.code.startsWith("Arrow")) e.preventDefault(); steer(); });
window.addEventListener("keyup", (e) => { keys.delete(e.code); steer(); });

// ---------------------------------------------------------------- pushing and the magnet
const ray = new THREE.Raycaster();
const mouse = new THREE.Vector2();
let drag = null;
const arrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 1, 0xff5050);
arrow.visible = false;
scene.add(arrow);
function pick(ev) {
  mouse.set((ev.clientX / window.innerWidth) * 2 - 1, -(ev.clientY / window.innerHeight) * 2 + 1);
  ray.setFromCamera(mouse, camera);
}
function bodyUnder(ev) {  // the avatar part under the pointer (a skinned human, else a capsule), or null
  pick(ev);
  return humans.pick(ray) || view.pick(ray);
}
function onPlane(y) {
  const plane = new THREE.Plane(new THREE.Vector3(0, 1, 0), -y);
  const hit = new THREE.Vector3();
  return ray.ray.intersectPlane(plane, hit) ? hit : null;
}
renderer.domElement.addEventListener("pointerdown", (ev) => {
  if (ev.button !== 0) return;
  pick(ev);
  if (placingObstacle) {
    const hit = onPlane(0);
    if (hit) state.placeObstacle(hit.x, hit.z);
    placingObstacle = false;
    $("obstacle").classList.remove("on");
    return;
  }
  if (placingMagnet) {
    const hit = onPlane(0);
    if (hit) {
      magnetMesh.position.set(hit.x, 0.03, hit.z);
      magnetMesh.visible = true;
      send({ type: "target", avatar: state.selected, position: [+hit.x.toFixed(3), +hit.z.toFixed(3)] });
    }
    placingMagnet = false;
    $("magnet").classList.remove("on");
    return;
  }
  const hit = bodyUnder(ev);
  if (!hit) return;
  const { avatar, joint, point } = hit;
  state.selected = avatar;
  $("select").value = String(avatar);
  drag = { avatar, joint, start: point.clone(), y: point.y };
  orbit.enabled = false;
});
let lastSpring = 0;
renderer.domElement.addEventListener("pointermove", (ev) => {
  if (!drag) return;
  pick(ev);
  const p = onPlane(drag.y);
  if (!p) return;
  if (state.physics.has(drag.avatar) && performance.now() - lastSpring > 60) {  // at most ~16 updates a second
    lastSpring = performance.now();
    send({ type: "spring", avatar: drag.avatar, joint: drag.joint, target: p.toArray().map((x) => +x.toFixed(3)), stiffness: 1500 });
  }
  const d = p.clone().sub(drag.start);
  arrow.position.copy(drag.start);
  arrow.setDirection(d.clone().normalize());
  arrow.setLength(Math.max(d.length(), 0.01));
  arrow.visible = d.length() > 0.02;
});
window.addEventListener("pointerup", (ev) => {
  if (!drag) return;
  pick(ev);
  const p = onPlane(drag.y);
  if (state.physics.has(drag.avatar)) {  // the spring lets go
    send({ type: "spring", avatar: drag.avatar, joint: drag.joint, target: null });
  } else if (p) {
    const d = p.sub(drag.start);
    const v = d.multiplyScalar(4.0);  // 1 m of drag = 4 m/s
    if (v.length() > 8) v.setLength(8);
    if (v.length() > 0.1) send({ type: "push", avatar: drag.avatar, joint: drag.joint, velocity: [+v.x.toFixed(3), +v.y.toFixed(3), +v.z.toFixed(3)] });
  }
  drag = null;
  arrow.visible = false;
  orbit.enabled = true;
});

// ---------------------------------------------------------------- render loop
let lastPad = 0;
let lastT = null;
const FOLLOW_TIME = 0.35;  // seconds for the camera to close ~63 % of the way to the avatar, at any frame rate
function animate(t) {
  requestAnimationFrame(animate);
  const dt = lastT === null ? 0 : Math.min(0.1, (t - lastT) / 1000);
  lastT = t;
  if (state.environment && state.environment.ground.from) placeGround(groundAt(state.environment.ground, state.frame || 0));
  const b = bodies.get(state.selected);
  if (b && b.positions) {  // follow the selected avatar, keeping the user's orbit offset
    const target = new THREE.Vector3(b.positions[0], 0.9, b.positions[2]);
    const delta = state.follow ? target.clone().sub(orbit.target).multiplyScalar(1 - Math.exp(-dt / FOLLOW_TIME)) : new THREE.Vector3();
    orbit.target.add(delta);
    camera.position.add(delta);
    sun.position.set(target.x + 4, 8, target.z + 3);
    sun.target.position.copy(target);
    // (in whole metres, so its lines stay put on the floor; it had stayed around the origin once
    // the world's environment was drawn, and was gone 45 m away)
    grid.matrix.copy(groundFrame).multiply(_gridAt.makeTranslation(Math.round(orbit.target.x), 0.002, Math.round(orbit.target.z)));
    grid.matrixWorldNeedsUpdate = true;
  }
  if (t - lastPad > 150 && navigator.getGamepads && [...navigator.getGamepads()].some(Boolean)) { lastPad = t; steer(); }
  orbit.update();
  humans.sync(bodies);
  view.draw(humans.others(bodies));
  renderer.render(scene, camera);
  state.renderTimes.push(t);
  state.drawn += 1;
  while (state.renderTimes.length && t - state.renderTimes[0] > 1000) state.renderTimes.shift();
  $("fps").textContent = state.fpsTimes.length;
  $("drawn").textContent = state.renderTimes.length;
  $("frame").textContent = state.frame;
}
connect();
requestAnimationFrame(animate);
