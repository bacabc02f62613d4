// Remote users as three.js objects: a head with a visor, and two controllers.
// Poses come from PosecastClient.render(): [px, py, pz, qw, qx, qy, qz], w first;
// three.js quaternions are (x, y, z, w).
import * as THREE from "three";

const HUES = [0.02, 0.12, 0.3, 0.55, 0.72, 0.85];

function head(color) {
  const g = new THREE.Group();
  const skull = new THREE.Mesh(
    new THREE.BoxGeometry(0.18, 0.22, 0.2),
    new THREE.MeshStandardMaterial({ color, roughness: 0.6 }),
  );
  // The visor faces -z, where the headset looks (OpenXR: -z forward).
  const visor = new THREE.Mesh(
    new THREE.BoxGeometry(0.19, 0.08, 0.04),
    new THREE.MeshStandardMaterial({ color: 0x111318, roughness: 0.2, metalness: 0.5 }),
  );
  visor.position.set(0, 0.02, -0.11);
  g.add(skull, visor);
  return g;
}

function controller(color) {
  const g = new THREE.Group();
  const grip = new THREE.Mesh(
    new THREE.CylinderGeometry(0.018, 0.022, 0.12, 12),
    new THREE.MeshStandardMaterial({ color, roughness: 0.5 }),
  );
  grip.rotation.x = Math.PI / 2 - 0.35;
  const ring = new THREE.Mesh(
    new THREE.TorusGeometry(0.045, 0.008, 8, 24),
    new THREE.MeshStandardMaterial({ color: 0xdddddd }),
  );
  ring.position.set(0, 0.03, -0.05);
  ring.rotation.x = 0.5;
  g.add(grip, ring);
  return g;
}

export class Avatars {
  constructor(scene) {
    this.scene = scene;
    /** user -> { group, parts: {head, left, right, ...} } */
    this.users = new Map();
  }

  part(user, name) {
    let u = this.users.get(user);
    if (!u) {
      const color = new THREE.Color().setHSL(HUES[user % HUES.length], 0.6, 0.55);
      u = { group: new THREE.Group(), parts: {}, color };
      u.group.name = `user-${user}`;
      this.scene.add(u.group);
      this.users.set(user, u);
    }
    let obj = u.parts[name];
    if (!obj) {
      obj = name === "head" ? head(u.color) : controller(u.color);
      obj.name = name;
      u.parts[name] = obj;
      u.group.add(obj);
    }
    return obj;
  }

  /** Place every remote stream of a render frame; a stalled user is drawn faded. */
  update(frame) {
    for (const p of frame.poses) {
      if (p.user === 65535) continue; // shared objects are not drawn here
      const [x, y, z, qw, qx, qy, qz] = p.pose;
      const obj = this.part(p.user, p.name);
      obj.position.set(x, y, z);
      obj.quaternion.set(qx, qy, qz, qw);
      obj.visible = true;
    }
  }

  stalled(user, yes) {
    const u = this.users.get(user);
    if (!u) return;
    u.group.traverse((o) => {
      if (o.material) {
        o.material.transparent = yes;
        o.material.opacity = yes ? 0.35 : 1;
      }
    });
  }

  remove(user) {
    const u = this.users.get(user);
    if (!u) return;
    this.scene.remove(u.group);
    u.group.traverse((o) => {
      o.geometry?.dispose();
      o.material?.dispose();
    });
    this.users.delete(user);
  }
}
