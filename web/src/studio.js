// The avatar-motor studio: a live view of the served world and its controls (docs/protocol.md).
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const token = params.get("token");
const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${token ? "?token=" + encodeURIComponent(token) : ""}`;

// ---------------------------------------------------------------- scene
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.shadowMap.enabled = true;
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
const ground = new THREE.Mesh(new THREE.PlaneGeometry(200, 200), new THREE.MeshStandardMaterial({ color: 0x3a434d, roughness: 0.95 }));
ground.rotation.x = -Math.PI / 2;
ground.receiveShadow = true;
scene.add(ground);
const grid = new THREE.GridHelper(200, 200, 0x59646f, 0x48525c);
grid.position.y = 0.002;
scene.add(grid);
const magnetMesh = new THREE.Mesh(new THREE.TorusGeometry(0.25, 0.04, 8, 32), new THREE.MeshStandardMaterial({ color: 0xff9040, emissive: 0x552200 }));
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

class Body {
  constructor(id) {
    this.id = id;
    this.group = new THREE.Group();
    const mat = new THREE.MeshStandardMaterial({ color: COLORS[id % COLORS.length], roughness: 0.55, metalness: 0.05 });
    this.joints = [];
    this.bones = [];
    for (let j = 0; j < 22; j++) {
      const s = new THREE.Mesh(new THREE.SphereGeometry(j === 15 ? 0.11 : RADIUS[j] * 1.05, 16, 12), mat);
      s.castShadow = true;
      s.userData = { avatar: id, joint: j };
      this.group.add(s);
      this.joints.push(s);
      if (PARENTS[j] >= 0) {
        const c = new THREE.Mesh(new THREE.CylinderGeometry(1, 1, 1, 12), mat);
        c.castShadow = true;
        c.userData = { avatar: id, joint: j };
        this.group.add(c);
        this.bones.push([j, c]);
      }
    }
    scene.add(this.group);
    this.positions = null;
  }
  update(pos) {  // pos: Float32Array(66), world metres (our world is three's world: Y up, right-handed)
    this.positions = pos;
    const p = (j) => new THREE.Vector3(pos[3 * j], pos[3 * j + 1], pos[3 * j + 2]);
    for (let j = 0; j < 22; j++) this.joints[j].position.copy(p(j));
    for (const [j, c] of this.bones) {
      const a = p(PARENTS[j]), b = p(j);
      const d = b.clone().sub(a);
      const len = d.length();
      const r = Math.min(RADIUS[j], RADIUS[PARENTS[j]]) * 0.9;
      c.position.copy(a).addScaledVector(d, 0.5);
      c.scale.set(r, Math.max(len, 1e-3), r);
      c.quaternion.setFromUnitVectors(UP, d.normalize());
    }
  }
  dispose() { scene.remove(this.group); }
}
const bodies = new Map();

// ---------------------------------------------------------------- connection
const state = { frame: 0, connected: false, fpsTimes: [], renderTimes: [], selected: 0, model: "", lastStats: null,
  received: 0, errors: [], stalls: 0, stallsRecent: 0 };
window.studio = state;  // for tests and the console
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
      $("warn").textContent = "";
    } else if (msg.type === "stats") {
      // stalls: ticks at which generation had no frame ready (the avatar held its pose)
      state.stallsRecent = state.lastStats ? msg.stalls - state.lastStats.stalls : 0;
      state.lastStats = msg;
      state.stalls = msg.stalls;
      $("gen").textContent = msg.gen_ms;
      $("stalls").textContent = msg.stalls;
      warn();
    } else if (msg.type === "ack" || msg.type === "error") {
      if (msg.type === "error") { state.errors.push(msg.error); console.warn(msg.error); }
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
  if (state.renderTimes.length < 28 && state.received > 60) msgs.push(`this browser draws ${state.renderTimes.length} fps`);
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
    off += 4 + 264 + 352;
    seen.add(id);
    if (!bodies.has(id) && PARENTS.length) bodies.set(id, new Body(id));
    if (bodies.has(id)) bodies.get(id).update(pos);
  }
  for (const [id, b] of bodies) if (!seen.has(id)) { b.dispose(); bodies.delete(id); }
  state.frame = frame;
  state.received++;
  const now = performance.now();
  state.fpsTimes.push(now);
  while (state.fpsTimes.length && now - state.fpsTimes[0] > 1000) state.fpsTimes.shift();
  refreshSelect();
}
state.pelvis = (id) => { const b = bodies.get(id ?? state.selected); return b && b.positions ? Array.from(b.positions.slice(0, 3)) : null; };
state.screenOf = (id, joint) => {  // pixel position of a joint (tests drive the mouse with it)
  const b = bodies.get(id);
  if (!b || !b.positions) return null;
  const v = new THREE.Vector3(b.positions[3 * joint], b.positions[3 * joint + 1], b.positions[3 * joint + 2]).project(camera);
  return [(v.x + 1) / 2 * window.innerWidth, (1 - v.y) / 2 * window.innerHeight];
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
$("select").onchange = (e) => { state.selected = Number(e.target.value); };

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
    b.onclick = () => send({ type: "label", avatar: state.selected, label: l, scale: Number($("scale").value) });
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
const download = (fmt) => {
  const s = Math.max(1, Math.min(60, Number($("seconds").value) || 10));
  location.href = `/api/record?avatar=${state.selected}&seconds=${s}&format=${fmt}${token ? "&token=" + token : ""}`;
};
$("bvh").onclick = () => download("bvh");
$("glb").onclick = () => download("glb");
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
  if (key !== lastGoal) { lastGoal = key; send({ type: "goal", avatar: state.selected, velocity: goal }); }
}
window.addEventListener("keydown", (e) => { keys.add(e.code); if (e.code.startsWith("Arrow")) e.preventDefault(); steer(); });
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
function onPlane(y) {
  const plane = new THREE.Plane(new THREE.Vector3(0, 1, 0), -y);
  const hit = new THREE.Vector3();
  return ray.ray.intersectPlane(plane, hit) ? hit : null;
}
renderer.domElement.addEventListener("pointerdown", (ev) => {
  if (ev.button !== 0) return;
  pick(ev);
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
  const meshes = [];
  for (const b of bodies.values()) meshes.push(...b.group.children);
  const hits = ray.intersectObjects(meshes);
  if (!hits.length) return;
  const { avatar, joint } = hits[0].object.userData;
  state.selected = avatar;
  $("select").value = String(avatar);
  drag = { avatar, joint, start: hits[0].point.clone(), y: hits[0].point.y };
  orbit.enabled = false;
});
renderer.domElement.addEventListener("pointermove", (ev) => {
  if (!drag) return;
  pick(ev);
  const p = onPlane(drag.y);
  if (!p) return;
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
  if (p) {
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
  const b = bodies.get(state.selected);
  if (b && b.positions) {  // follow the selected avatar, keeping the user's orbit offset
    const target = new THREE.Vector3(b.positions[0], 0.9, b.positions[2]);
    const delta = target.clone().sub(orbit.target).multiplyScalar(1 - Math.exp(-dt / FOLLOW_TIME));
    orbit.target.add(delta);
    camera.position.add(delta);
    sun.position.set(target.x + 4, 8, target.z + 3);
    sun.target.position.copy(target);
  }
  if (t - lastPad > 150 && navigator.getGamepads && [...navigator.getGamepads()].some(Boolean)) { lastPad = t; steer(); }
  orbit.update();
  renderer.render(scene, camera);
  state.renderTimes.push(t);
  while (state.renderTimes.length && t - state.renderTimes[0] > 1000) state.renderTimes.shift();
  $("fps").textContent = state.fpsTimes.length;
  $("drawn").textContent = state.renderTimes.length;
  $("frame").textContent = state.frame;
}
connect();
requestAnimationFrame(animate);
