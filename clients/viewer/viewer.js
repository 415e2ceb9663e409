// EgoPoseVR web viewer: joins a session as a `render` client (PROTOCOL.md) and draws every pose.
//
// The avatar is a skinned VRM humanoid driven by the SMPL rotations (avatar.js; the bundled mannequin, or a .vrm
// dropped on the page), or, toggled off or without one, capsules between the 22 SMPL joints (`pose.joints`). The
// headset and controllers are boxes placed and turned by the SMPL rotations (`global_orient`, `body_pose`)
// through forward kinematics, with the device offsets of model/rig.py. The ground truth (`pose.truth`, recorded
// sessions) is a grey line ghost.
// World: right-handed, y up, metres, as on the wire. `window.viewerState` exposes what the page saw (tests
// and curious users read it). Without WebGL the page falls back to a 2D canvas projection.
import * as THREE from "three";
import { Avatar, PARENTS, globalRotations, jointsOf, parseVrm } from "./avatar.js";

const { encode, decode } = window.MessagePack;
const LEFT = new Set([1, 4, 7, 10, 13, 16, 18, 20]);
const RIGHT = new Set([2, 5, 8, 11, 14, 17, 19, 21]);
// Devices on the body (model/rig.py's DEFAULT_OFFSETS_M): offsets in the joint's frame; device = joint turned
// 180° about y. The headset's is where the training bodies have their eyes, which every bundled model hangs its
// head joint from; a pose's model that says otherwise in `models` (`head_joint_m`, PROTOCOL.md
// §model-head-joint) has its headset drawn where it says (headsetOffset).
const DEVICES = [
  { joint: 15, offset: [0.0, 0.024, 0.083], size: [0.18, 0.1, 0.12] },
  { joint: 20, offset: [0.085, -0.015, 0.015], size: [0.05, 0.05, 0.14] },
  { joint: 21, offset: [-0.085, -0.015, 0.015], size: [0.05, 0.05, 0.14] },
];
const DEVICE_FROM_JOINT = new THREE.Quaternion().setFromAxisAngle(new THREE.Vector3(0, 1, 0), Math.PI);

const state = (window.viewerState = {
  connected: false, session: null, model: null, models: [], poses: 0, lastSeq: null, fps: 0,
  headJoints: {}, // model name -> its head joint in the headset's frame (m), as `models` gives it, or null
  serverMs: null, camera: null, planted: null, skipped: 0, truthSeen: false, renderer: null, errors: [], sessions: [],
  headset: null, // from `session` messages: is an input client connected (null: not told yet)
  calibration: null, // the newest `calibration` message: {status, message, ...}
  body: null, // the newest `body` message: {bone_lengths_m, given, measured} (PROTOCOL.md §4.2)
  bodyNote: null, // what the body buttons last did, for the operator
  avatar: { loaded: false, name: null, error: null }, // the skinned avatar (null name: capsules only)
});

const $ = (id) => document.getElementById(id);
let ws = null;
let latest = null; // newest pose not yet drawn
let arrivals = []; // pose arrival times (ms) over the last second, for FPS

// ------------------------------------------------------------------------------------------ connection
function wsUrl(session) {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/ws?session=${encodeURIComponent(session)}`;
}

function connect(session) {
  if (ws) { ws.onclose = null; ws.close(); }
  state.session = session; state.connected = false; state.poses = 0; state.lastSeq = null;
  const url = new URL(location.href);
  url.searchParams.set("session", session);
  history.replaceState(null, "", url);
  ws = new WebSocket(wsUrl(session));
  ws.binaryType = "arraybuffer";
  ws.onopen = () => send({ type: "hello", role: "render", session, client: "egoposevr viewer" });
  ws.onmessage = (event) => {
    let msg;
    try { msg = decode(new Uint8Array(event.data)); } catch (err) {  // skipped and shown; the stream goes on (PROTOCOL.md §8)
      state.errors = [...state.errors.slice(-19), `unreadable server message: ${err.message}`];
      return;
    }
    onMessage(msg);
  };
  ws.onclose = () => { state.connected = false; setTimeout(() => connect(state.session), 1000); };
}

// The headset's offset from the head joint in the joint's frame (x left, y up, z forward) under a model: its
// `head_joint_m` is the joint in the headset's frame (x right, y up, z back), the same point seen the other way.
function headsetOffset(model) {
  const joint = state.headJoints[model];
  return joint ? [joint[0], -joint[1], joint[2]] : DEVICES[0].offset;
}

function onMessage(msg) {
  if (msg.type === "welcome") { state.connected = true; state.model = msg.model; }
  else if (msg.type === "models") {
    state.model = msg.active;
    state.models = msg.models.map((m) => m.name);
    state.headJoints = Object.fromEntries(msg.models.map((m) => [m.name, m.head_joint_m ?? null]));
    fillModels(msg.models);
  }
  else if (msg.type === "pose") { onPose(msg); }
  else if (msg.type === "error") {
    state.errors = [...state.errors.slice(-19), `${msg.code}: ${msg.message}`];
    if (msg.ref && msg.ref.type === "set_body") state.bodyNote = `body refused: ${msg.message}`;
  }
  else if (msg.type === "session") { state.headset = msg.input; }
  else if (msg.type === "calibration") { state.calibration = msg; }
  else if (msg.type === "body") { onBody(msg); }
  // Any other type is one this viewer does not know: ignored (PROTOCOL.md §8).
}

function onPose(pose) {
  const now = performance.now();
  arrivals.push(now);
  while (arrivals.length && arrivals[0] < now - 1000) arrivals.shift();
  latest = pose;
  state.poses += 1; state.lastSeq = pose.seq; state.model = pose.model; state.fps = arrivals.length;
  state.serverMs = pose.timing_us && pose.timing_us.total !== undefined ? pose.timing_us.total / 1000 : null;
  state.camera = pose.camera === undefined ? null : pose.camera;
  state.planted = Array.isArray(pose.planted) ? pose.planted : null; // PROTOCOL.md §planted-feet
  state.skipped += pose.skipped || 0;
  state.truthSeen = state.truthSeen || Boolean(pose.truth);
}

async function refreshSessions() {
  try {
    const reply = await fetch("/api/sessions");
    state.sessions = (await reply.json()).map((s) => s.session);
  } catch { return; }
  const select = $("session");
  const names = new Set(state.sessions);
  if (state.session) names.add(state.session);
  const wanted = [...names].sort();
  if (wanted.join() !== [...select.options].map((o) => o.value).join()) {
    select.replaceChildren(...wanted.map((n) => new Option(n, n, false, n === state.session)));
  }
  if (!state.session && state.sessions.length) connect(state.sessions[0]);
}

// Each option's tooltip: what the model is, and which file serves it (PROTOCOL.md §model-digests), for a report.
function fillModels(models) {
  const select = $("model");
  const titles = new Map(models.map((m) => [m.name, [m.description, m.sha256 && `sha256 ${m.sha256.slice(0, 12)}`]]));
  select.replaceChildren(...state.models.map((n) => {
    const option = new Option(n, n, false, n === state.model);
    option.title = (titles.get(n) || []).filter(Boolean).join(" · ");
    return option;
  }));
}

// ------------------------------------------------------------------------------------------ a returning wearer's body
// Kept in this browser's localStorage under the wearer's name (PROTOCOL.md §4.2): "keep body" asks the session for
// its body and keeps it if it is worth keeping (measured by the server, or one a client gave); "give kept body"
// serves it to the session from the next sample on; "estimate body" gives the estimate back.
const BODY_KEY = "egoposevr.body.";
let keepAsked = null; // the wearer a get_body was sent for, until its answer

function wearer() {
  const name = $("wearer").value.trim();
  if (!name) state.bodyNote = "name the wearer first";
  return name || null;
}

// A message to the server now; false when the connection is not open (the page reconnects by itself).
function send(msg) {
  if (!ws || ws.readyState !== 1) return false;
  ws.send(encode({ type: msg.type, v: 1, ...msg }));
  return true;
}

function sendToSession(msg) {
  const sent = send(msg);
  if (!sent) state.bodyNote = "not connected";
  return sent;
}

function keptBody(name) {
  try {
    const kept = JSON.parse(localStorage.getItem(BODY_KEY + name));
    const lengths = kept && kept.bone_lengths_m;
    return Array.isArray(lengths) && lengths.length === 21 && lengths.every((x) => Number.isFinite(x) && x > 0) ? lengths : null;
  } catch { return null; } // damaged: as if none were kept
}

function onBody(body) {
  state.body = body;
  if (keepAsked === null) return;
  const name = keepAsked;
  keepAsked = null;
  if (!body.measured && !body.given) {
    state.bodyNote = `not kept: the server has not measured ${name} yet (keep it after they have stood and the camera has seen their legs)`;
    return;
  }
  localStorage.setItem(BODY_KEY + name, JSON.stringify({ bone_lengths_m: body.bone_lengths_m, kept_at: new Date().toISOString() }));
  state.bodyNote = `body kept for ${name}`;
}

$("keepBody").onclick = () => {
  const name = wearer();
  if (name && sendToSession({ type: "get_body" })) keepAsked = name;
};
$("giveBody").onclick = () => {
  const name = wearer();
  if (!name) return;
  const lengths = keptBody(name);
  if (!lengths) { state.bodyNote = `no body kept for ${name}`; return; }
  if (sendToSession({ type: "set_body", bone_lengths_m: lengths })) state.bodyNote = `gave ${name}'s body`;
};
$("estimateBody").onclick = () => {
  if (sendToSession({ type: "set_body", clear: true })) state.bodyNote = "the server estimates the body";
};

$("session").onchange = (e) => connect(e.target.value);
$("calibrate").onclick = () =>
  send({ type: "calibrate", pose: "tpose", seconds: 2.0 });
$("model").onchange = (e) => send({ type: "select_model", model: e.target.value });

// ------------------------------------------------------------------------------------------ colours
function colourOf(j) { return LEFT.has(j) ? 0xff8c3c : RIGHT.has(j) ? 0x3ca0ff : 0xe6e6e6; }

// ------------------------------------------------------------------------------------------ WebGL scene
function webglView(stage) {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  stage.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x202225);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5);
  sun.position.set(2, 4, 3);
  scene.add(sun);
  scene.add(new THREE.GridHelper(10, 20, 0x666666, 0x3a3a3a));
  const camera = new THREE.PerspectiveCamera(50, 1, 0.05, 50);
  const unitCylinder = new THREE.CylinderGeometry(1, 1, 1, 12);
  const unitSphere = new THREE.SphereGeometry(1, 16, 12);
  const bones = [], spheres = [];
  for (let j = 1; j < 22; j++) {
    const mesh = new THREE.Mesh(unitCylinder, new THREE.MeshStandardMaterial({ color: colourOf(j), roughness: 0.6 }));
    scene.add(mesh); bones.push(mesh);
  }
  for (let j = 0; j < 22; j++) {
    const mesh = new THREE.Mesh(unitSphere, new THREE.MeshStandardMaterial({ color: colourOf(j), roughness: 0.6 }));
    mesh.scale.setScalar(j === 15 ? 0.09 : 0.035); scene.add(mesh); spheres.push(mesh);
  }
  const devices = DEVICES.map((d) => {
    const mesh = new THREE.Mesh(new THREE.BoxGeometry(...d.size), new THREE.MeshStandardMaterial({ color: 0x50dc50 }));
    scene.add(mesh); return mesh;
  });
  const truthGeometry = new THREE.BufferGeometry();
  truthGeometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(21 * 2 * 3), 3));
  const truthLines = new THREE.LineSegments(truthGeometry, new THREE.LineBasicMaterial({ color: 0x9a9a9a }));
  truthLines.visible = false; scene.add(truthLines);
  const focus = new THREE.Vector3(0, 1, 0);
  const up = new THREE.Vector3(0, 1, 0);
  let avatar = null, lastPose = null;

  async function loadAvatar(bytes, name) {
    try {
      const next = new Avatar(await parseVrm(bytes), name);
      if (avatar) scene.remove(avatar.vrm.scene);
      avatar = next; scene.add(avatar.vrm.scene);
      state.avatar = { loaded: true, name, error: null };
      if (lastPose) show(lastPose);
    } catch (error) {
      console.warn("avatar not loaded:", error);
      state.avatar = { loaded: Boolean(avatar), name: avatar ? avatar.name : null, error: `${name}: ${error.message || error}` };
    }
  }
  fetch("avatar/mannequin.vrm").then((r) => r.arrayBuffer()).then((b) => loadAvatar(b, "mannequin.vrm"));
  stage.addEventListener("dragover", (event) => event.preventDefault());
  stage.addEventListener("drop", async (event) => { // the user's own avatar: a .vrm dropped on the page
    event.preventDefault();
    const file = event.dataTransfer.files[0];
    if (file) await loadAvatar(await file.arrayBuffer(), file.name);
  });
  window.viewerAvatar = { // for tests and the curious: load bytes, or pose the avatar and read its bones back
    load: (bytes, name) => loadAvatar(bytes, name),
    pose: (pose) => { avatar.show(pose); return avatar.bonePositions(); },
    legM: () => avatar.legM,
  };

  function resize() {
    const w = stage.clientWidth, h = stage.clientHeight;
    renderer.setSize(w, h, false); camera.aspect = w / Math.max(h, 1); camera.updateProjectionMatrix();
  }
  window.addEventListener("resize", resize); resize();

  function show(pose) {
    lastPose = pose;
    const joints = jointsOf(pose.joints);
    const skinned = Boolean(avatar) && $("avatar").checked;
    if (avatar) { avatar.vrm.scene.visible = skinned; if (skinned) avatar.show(pose); }
    bones.forEach((mesh) => { mesh.visible = !skinned; });
    spheres.forEach((mesh) => { mesh.visible = !skinned; });
    for (let j = 1; j < 22; j++) {
      const a = joints[PARENTS[j]], b = joints[j], mesh = bones[j - 1];
      const length = a.distanceTo(b);
      mesh.position.copy(a).add(b).multiplyScalar(0.5);
      mesh.scale.set(0.025, Math.max(length, 1e-4), 0.025);
      mesh.quaternion.setFromUnitVectors(up, b.clone().sub(a).normalize());
    }
    joints.forEach((p, j) => spheres[j].position.copy(p));
    const rot = globalRotations(pose);
    DEVICES.forEach((d, k) => {
      const offset = k === 0 ? headsetOffset(pose.model) : d.offset;
      devices[k].position.copy(new THREE.Vector3(...offset).applyQuaternion(rot[d.joint]).add(joints[d.joint]));
      devices[k].quaternion.copy(rot[d.joint]).multiply(DEVICE_FROM_JOINT);
    });
    const showTruth = Boolean(pose.truth) && $("truth").checked;
    truthLines.visible = showTruth;
    if (showTruth) {
      const truth = jointsOf(pose.truth), buffer = truthGeometry.attributes.position.array;
      for (let j = 1; j < 22; j++) {
        truth[PARENTS[j]].toArray(buffer, 6 * (j - 1)); truth[j].toArray(buffer, 6 * (j - 1) + 3);
      }
      truthGeometry.attributes.position.needsUpdate = true;
    }
    focus.lerp(new THREE.Vector3(joints[0].x, 1.0, joints[0].z), 0.1); // a steady camera that follows
    camera.position.set(focus.x - 1.7, 1.5, focus.z - 2.1);
    camera.lookAt(focus);
  }
  return { show, draw: () => renderer.render(scene, camera), name: "webgl" };
}

// ------------------------------------------------------------------------------------------ 2D fallback
function canvasView(stage) {
  const canvas = document.createElement("canvas");
  stage.appendChild(canvas);
  const ctx = canvas.getContext("2d");
  let pose = null;
  function project(p, focus, w, h) { // a fixed oblique view: x right, y up, z towards the viewer
    const s = Math.min(w, h) / 3;
    return [w / 2 + s * ((p.x - focus.x) - 0.35 * (p.z - focus.z)), h * 0.85 - s * (p.y + 0.25 * (p.z - focus.z))];
  }
  function draw() {
    const w = (canvas.width = stage.clientWidth), h = (canvas.height = stage.clientHeight);
    ctx.fillStyle = "#202225"; ctx.fillRect(0, 0, w, h);
    if (!pose) return;
    const joints = jointsOf(pose.joints), focus = joints[0];
    const line = (pts, colour, width) => {
      ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.beginPath();
      ctx.moveTo(...project(pts[0], focus, w, h)); ctx.lineTo(...project(pts[1], focus, w, h)); ctx.stroke();
    };
    for (let k = -5; k <= 5; k++) {
      line([new THREE.Vector3(focus.x + k * 0.5, 0, focus.z - 2.5), new THREE.Vector3(focus.x + k * 0.5, 0, focus.z + 2.5)], "#3a3a3a", 1);
      line([new THREE.Vector3(focus.x - 2.5, 0, focus.z + k * 0.5), new THREE.Vector3(focus.x + 2.5, 0, focus.z + k * 0.5)], "#3a3a3a", 1);
    }
    if (pose.truth && $("truth").checked) {
      const truth = jointsOf(pose.truth);
      for (let j = 1; j < 22; j++) line([truth[PARENTS[j]], truth[j]], "#9a9a9a", 2);
    }
    for (let j = 1; j < 22; j++) line([joints[PARENTS[j]], joints[j]], "#" + colourOf(j).toString(16).padStart(6, "0"), 5);
  }
  state.avatar = { loaded: false, name: null, error: "no WebGL: capsules in 2D" };
  return { show: (p) => { pose = p; }, draw, name: "2d" };
}

function makeView(stage) {
  try { return webglView(stage); } catch (error) {
    console.warn("WebGL unavailable, drawing in 2D:", error);
    return canvasView(stage);
  }
}

// ------------------------------------------------------------------------------------------ main loop
const view = makeView($("stage"));
state.renderer = view.name;

// Which feet the server holds planted: "L down R up", or "n/a" for a model that plants none.
function feetText(planted) {
  return planted ? planted.map((down, k) => `${k ? "R" : "L"} ${down ? "down" : "up"}`).join(" ") : "n/a";
}

function frame() {
  if (latest) { view.show(latest); latest = null; }
  view.draw();
  const s = state;
  const headset = s.headset === null ? "" : s.headset ? " · headset connected" : " · no headset";
  const calibration = s.calibration ? ` · calibration ${s.calibration.status}: ${s.calibration.message}` : "";
  const body = s.bodyNote ? ` · ${s.bodyNote}` : s.body ? ` · body ${s.body.given ? "given" : "estimated"}` : "";
  $("status").textContent = s.connected ? `${s.session} · ${s.model || "?"}${headset}${calibration}${body}` : "connecting…";
  $("hud").textContent = s.poses
    ? `poses ${s.poses}  ·  ${s.fps} FPS  ·  server ${s.serverMs?.toFixed(1) ?? "?"} ms  ·  camera ${s.camera === null ? "n/a" : s.camera ? "on" : "off"}  ·  feet ${feetText(s.planted)}  ·  skipped ${s.skipped}` +
      (s.errors.length ? `  ·  last error ${s.errors[s.errors.length - 1]}` : "")
    : "waiting for poses…";
  requestAnimationFrame(frame);
}

const requested = new URLSearchParams(location.search).get("session");
if (requested) connect(requested);
refreshSessions();
setInterval(refreshSessions, 2000);
requestAnimationFrame(frame);
