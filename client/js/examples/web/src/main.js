// posecast's WebXR example page: joins a room with the SDK, publishes the local
// headset and controllers from the XR frame loop, and draws every remote user as a
// head with a visor and two controllers, interpolated at the playout time.
//
// Settings: /config.json (written by `posecast web`), overridden by the query string:
//   url=ws://HOST:PORT  room=NAME  codec=raw|compact  method=soa|dq-slerp|motor-lerp
//   label=TEXT  rate=HZ (publish rate)  emulate=quest3 (IWER: an emulated Meta Quest 3,
//   entered at once, no headset or gesture needed; what the browser tests use)
import * as THREE from "three";
import { VRButton } from "three/examples/jsm/webxr/VRButton.js";
import * as sdk from "../../../src/index.ts";
import { Avatars } from "./avatars.js";

const { PosecastClient, XRPublisher } = sdk;
const KEYFRAME_LOG = 900; // keyframes kept per remote stream (for tests and debugging)

const statusEl = document.getElementById("status");
const state = {
  client: null,
  device: null,
  publisher: null,
  session: null,
  method: "dq-slerp",
  lastFrame: null,
  frames: 0,
  keyframes: new Map(), // "user/stream" -> [[capture, px, py, pz, qw, qx, qy, qz], ...]
  notices: [],
  error: null,
  sdk, // the SDK's exports (tests measure its codecs in this browser)
  iwer: null,
};
window.posecastPage = state;

function show(text) {
  statusEl.textContent = text;
}

async function settings() {
  let cfg = {};
  try {
    const r = await fetch("config.json", { cache: "no-store" });
    if (r.ok) cfg = await r.json();
  } catch {
    // no config.json: the query string says it all
  }
  const q = new URLSearchParams(location.search);
  for (const k of ["url", "room", "codec", "method", "label", "rate", "emulate"]) {
    if (q.has(k)) cfg[k] = q.get(k);
  }
  if (!cfg.url) {
    const host = location.hostname || "127.0.0.1";
    cfg.url = `${location.protocol === "https:" ? "wss" : "ws"}://${host}:8765`;
  }
  cfg.room ??= "lobby";
  return cfg;
}

function scene3() {
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x20242c);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x445566, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5);
  sun.position.set(2, 4, 1);
  scene.add(sun);
  const floor = new THREE.GridHelper(16, 16, 0x667788, 0x3a4250);
  scene.add(floor);
  const camera = new THREE.PerspectiveCamera(70, innerWidth / innerHeight, 0.05, 100);
  camera.position.set(0, 1.6, 2.5);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setSize(innerWidth, innerHeight);
  renderer.setPixelRatio(Math.min(devicePixelRatio, 2));
  renderer.xr.enabled = true;
  renderer.xr.setReferenceSpaceType("local-floor");
  document.body.appendChild(renderer.domElement);
  addEventListener("resize", () => {
    camera.aspect = innerWidth / innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(innerWidth, innerHeight);
  });
  return { scene, camera, renderer };
}

function logKeyframes(snapshot) {
  for (const e of snapshot.entries) {
    const key = `${e.user}/${e.stream}`;
    let log = state.keyframes.get(key);
    if (!log) state.keyframes.set(key, (log = []));
    log.push([e.capture, ...e.pose]);
    if (log.length > KEYFRAME_LOG) log.splice(0, log.length - KEYFRAME_LOG);
  }
}

function describe() {
  const c = state.client;
  if (state.error) return `error: ${state.error}`;
  if (!c) return "connecting...";
  const peers = c.receiver.peers.size;
  const xr = state.session ? "in VR" : "not in VR (Enter VR below)";
  return `${c.state} as user ${c.state === "joined" ? c.user : "-"} in ${state.room}; ` +
    `${peers} other user${peers === 1 ? "" : "s"}; ${xr}; sent ${state.publisher?.published ?? 0}`;
}

async function enterEmulated(renderer) {
  const session = await navigator.xr.requestSession("immersive-vr", {
    requiredFeatures: ["local-floor"],
  });
  await renderer.xr.setSession(session);
}

async function main() {
  const cfg = await settings();
  state.method = cfg.method ?? "dq-slerp";
  state.room = cfg.room;
  if (cfg.emulate) {
    const iwer = await import("iwer");
    const { XRDevice, metaQuest3 } = iwer;
    state.iwer = iwer;
    const device = new XRDevice(metaQuest3);
    // Headless Chromium has a native navigator.xr that wants a user gesture: replace it.
    device.installRuntime({ forceInstall: true });
    state.device = device;
  }
  const { scene, camera, renderer } = scene3();
  state.scene = scene;
  state.renderer = renderer;
  const avatars = (state.avatars = new Avatars(scene));
  document.body.appendChild(VRButton.createButton(renderer));

  const client = new PosecastClient({
    url: cfg.url,
    room: cfg.room,
    codec: cfg.codec ?? "raw",
    label: cfg.label ?? "web",
    protocols: ["posecast.v1"],
  });
  state.client = client;
  client.on("snapshot", logKeyframes);
  client.on("peer_left", (user) => {
    state.notices.push(["peer_left", user]);
    avatars.remove(user);
  });
  client.on("peer_stalled", (user) => {
    state.notices.push(["peer_stalled", user]);
    avatars.stalled(user, true);
  });
  client.on("peer_resumed", (user) => {
    state.notices.push(["peer_resumed", user]);
    avatars.stalled(user, false);
  });
  for (const name of ["resumed", "rejoined", "reconnecting", "closed"]) {
    client.on(name, () => state.notices.push([name, client.user]));
  }

  renderer.xr.addEventListener("sessionstart", () => {
    state.session = renderer.xr.getSession();
    state.publisher = new XRPublisher(client, renderer.xr.getReferenceSpace(), {
      rate: Number(cfg.rate ?? 30),
    });
  });
  renderer.xr.addEventListener("sessionend", () => {
    state.session = null;
    state.publisher = null;
  });

  renderer.setAnimationLoop((_time, frame) => {
    if (frame && state.publisher) state.publisher.onFrame(frame);
    if (client.state === "joined" || client.state === "reconnecting") {
      const f = client.render(state.method);
      avatars.update(f);
      state.lastFrame = f;
    }
    renderer.render(scene, camera);
    state.frames++;
    if (state.frames % 30 === 0) show(describe());
  });

  show(`connecting to ${cfg.url} ...`);
  try {
    await client.connect();
  } catch (err) {
    state.error = `${err?.name ?? "Error"}: ${err?.message ?? err}`;
    show(describe());
    return;
  }
  show(describe());
  if (cfg.emulate) await enterEmulated(renderer);
}

main().catch((err) => {
  state.error = String(err?.stack ?? err);
  show(`error: ${err?.message ?? err}`);
});
