import * as THREE from "three";
import { VRButton } from "three/examples/jsm/webxr/VRButton.js";
import { PosecastClient, XRPublisher } from "posecast";

// Join the room: ?relay=ws://HOST:PORT, else port 8765 of the page's host (wss: on https:).
const relay = new URLSearchParams(location.search).get("relay") ?? `${location.protocol.replace("http", "ws")}//${location.hostname}:8765`;
const client = new PosecastClient({ url: relay, room: "lobby", label: "my-app" });
await client.connect(); // hello, clock sync, join

// A three.js scene with an "Enter VR" button (a local-floor space, posecast's frame).
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(70, innerWidth / innerHeight, 0.05, 100);
const renderer = new THREE.WebGLRenderer();
renderer.xr.enabled = true;
document.body.append(renderer.domElement, VRButton.createButton(renderer));
const publisher = new XRPublisher(client, null, { rate: 30 });

// Every remote device (head, left, right) drawn as a box.
const boxes = new Map(); // "user/name" -> THREE.Mesh
function box(key) {
  if (!boxes.has(key)) scene.add(boxes.set(key, new THREE.Mesh(new THREE.BoxGeometry(0.15, 0.1, 0.1))).get(key));
  return boxes.get(key);
}

renderer.setAnimationLoop((time, frame) => {
  if (frame) publisher.onFrame(frame, renderer.xr.getReferenceSpace()); // at most 30 Hz
  boxes.forEach((mesh) => (mesh.visible = false)); // a user who left shows nothing
  for (const { user, name, pose: [x, y, z, qw, qx, qy, qz] } of client.render("dq-slerp").poses) {
    const mesh = box(`${user}/${name}`);
    mesh.position.set(x, y, z);
    mesh.quaternion.set(qx, qy, qz, qw); // posecast is w first, three.js w last
    mesh.visible = true;
  }
  renderer.render(scene, camera);
});
