import { test } from "node:test";
import assert from "node:assert/strict";
import { XRPublisher, inVolume, xrPose } from "../src/webxr.js";
import type { XRFrameLike } from "../src/webxr.js";
import type { PosecastClient } from "../src/client.js";
import { UsageError } from "../src/errors.js";

/** A client stand-in that records what would be published (its clock is ours). */
function fakeClient(now: { t: number }) {
  const published: Record<string, number[]>[] = [];
  const c = {
    state: "joined",
    clock: () => now.t,
    welcome: { volume: [-2, 0, -2, 2, 3, 2] },
    streams: { head: 0, left: 1, right: 2 },
    publish: (poses: Record<string, number[]>) => {
      published.push(poses);
      return 10;
    },
  };
  return { client: c as unknown as PosecastClient, published };
}

const SPACE = { name: "local-floor" };
const GRIP_L = { name: "grip-left" };
const GRIP_R = { name: "grip-right" };

function frame(headY: number, rightX = 0.3): XRFrameLike {
  const t = (x: number, y: number, z: number) => ({ transform: { position: { x, y, z }, orientation: { x: 0, y: 0.6, z: 0, w: 0.8 } } });
  return {
    session: { inputSources: [{ handedness: "left", gripSpace: GRIP_L }, { handedness: "right", gripSpace: GRIP_R }, { handedness: "none", gripSpace: null }] },
    getViewerPose: ((space: unknown) => (space === SPACE ? t(0, headY, 0) : null)) as never,
    getPose: ((space: unknown, base: unknown) => (base !== SPACE ? null : space === GRIP_L ? t(-0.3, 1, -0.2) : space === GRIP_R ? t(rightX, 1, -0.2) : null)) as never,
  };
}

test("WebXR orientations {x, y, z, w} become w-first poses", () => {
  assert.deepEqual(xrPose({ position: { x: 1, y: 2, z: 3 }, orientation: { x: 0.1, y: 0.2, z: 0.3, w: 0.9 } }), [1, 2, 3, 0.9, 0.1, 0.2, 0.3]);
  assert.ok(inVolume([0, 0, 0], [-1, 0, -1, 1, 1, 1]));
  assert.ok(!inVolume([0, -0.01, 0], [-1, 0, -1, 1, 1, 1]));
});

test("head from the viewer pose, hands from the grip spaces, at the chosen rate, inside the volume", () => {
  const now = { t: 10 };
  const { client, published } = fakeClient(now);
  const pub = new XRPublisher(client, SPACE, { rate: 30 });
  // 90 Hz frames for one second: 30 updates, never two within a period.
  for (let i = 0; i < 90; i++) {
    now.t = 10 + i / 90;
    pub.onFrame(frame(1.6));
  }
  assert.equal(published.length, 30);
  assert.deepEqual(Object.keys(published[0]!).sort(), ["head", "left", "right"]);
  assert.deepEqual(published[0]!.head, [0, 1.6, 0, 0.8, 0, 0.6, 0]);
  // The right hand outside the room volume is left out (and counted).
  now.t = 20;
  pub.onFrame(frame(1.6, 5));
  assert.deepEqual(Object.keys(published.at(-1)!).sort(), ["head", "left"]);
  assert.equal(pub.outOfVolume, 1);
});

test("the reference space may come with each frame (three.js makes it at session start)", () => {
  const now = { t: 10 };
  const { client, published } = fakeClient(now);
  const pub = new XRPublisher(client, null, { rate: 30 });
  assert.throws(() => pub.onFrame(frame(1.6)), (e: Error) => e instanceof UsageError && /no reference space/.test(e.message));
  assert.equal(published.length, 0);
  pub.onFrame(frame(1.6), SPACE);
  assert.deepEqual(published[0]!.head, [0, 1.6, 0, 0.8, 0, 0.6, 0]);
  assert.deepEqual(pub.read(frame(1.5), SPACE).head, [0, 1.5, 0, 0.8, 0, 0.6, 0]);
});
