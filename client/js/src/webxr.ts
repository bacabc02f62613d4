/**
 * WebXR adapter: publish the headset and its controllers from the XR animation frame.
 *
 * Head from `XRFrame.getViewerPose(space)`, hands from each input source's
 * `gripSpace` (handedness left / right), all in the reference space given
 * (request `local-floor`: +y up, the floor at y = 0, as posecast's world frame).
 * WebXR orientations are {x, y, z, w}; posecast poses are w first. A position
 * outside the room volume of the server's welcome is not sent (counted in
 * `outOfVolume`). Publishes at `rate` Hz on the page's frames, never in bursts.
 * The reference space is given once (the constructor) or with each frame (`onFrame(frame,
 * space)`: three.js makes its space only when the session starts,
 * `renderer.xr.getReferenceSpace()`). Structural types only: no dependency on WebXR
 * typings or on three.js.
 */
import type { PosecastClient } from "./client.js";
import type { Pose } from "./messages.js";
import { DEFAULT_VOLUME } from "./messages.js";
import { UsageError } from "./errors.js";

export interface XRVectorLike { x: number; y: number; z: number }
export interface XRQuaternionLike { x: number; y: number; z: number; w: number }
export interface XRRigidTransformLike { position: XRVectorLike; orientation: XRQuaternionLike }
export interface XRPoseLike { transform: XRRigidTransformLike }
export interface XRInputSourceLike { handedness: string; gripSpace?: unknown }
export interface XRFrameLike {
  session: { inputSources: Iterable<XRInputSourceLike> };
  getViewerPose(space: never): XRPoseLike | null | undefined;
  getPose(space: never, base: never): XRPoseLike | null | undefined;
}

export interface XRPublisherOptions {
  /** Updates per second (default 30). */
  rate?: number;
  /** Publish the head (default true). */
  head?: boolean;
  /** Publish the controllers' grip poses (default true). */
  hands?: boolean;
}

/** A WebXR transform as a posecast pose [px, py, pz, qw, qx, qy, qz]. */
export function xrPose(t: XRRigidTransformLike): Pose {
  const p = t.position;
  const q = t.orientation;
  return [p.x, p.y, p.z, q.w, q.x, q.y, q.z];
}

export class XRPublisher {
  /** Update frames sent, streams left out for being outside the volume. */
  published = 0;
  outOfVolume = 0;
  /** The poses of the last frame sent, by stream name. */
  last: Record<string, Pose> = {};
  private next = -Infinity;
  private readonly period: number;

  constructor(
    readonly client: PosecastClient,
    /** The reference space poses are read in (null: give it to each onFrame / read). */
    readonly space: unknown = null,
    readonly opts: XRPublisherOptions = {},
  ) {
    const rate = opts.rate ?? 30;
    if (!(rate > 0 && rate <= 240)) throw new RangeError(`rate must be in (0, 240] Hz, got ${rate}`);
    this.period = 1 / rate;
  }

  /** The poses of this XR frame in `space` (default: the constructor's), by stream name
   * (only the tracked ones). */
  read(frame: XRFrameLike, space: unknown = this.space): Record<string, Pose> {
    checkSpace(space);
    const out: Record<string, Pose> = {};
    if (this.opts.head ?? true) {
      const viewer = frame.getViewerPose(space as never);
      if (viewer) out.head = xrPose(viewer.transform);
    }
    if (this.opts.hands ?? true) {
      for (const source of frame.session.inputSources) {
        const hand = source.handedness;
        if ((hand !== "left" && hand !== "right") || !source.gripSpace) continue;
        const pose = frame.getPose(source.gripSpace as never, space as never);
        if (pose) out[hand] = xrPose(pose.transform);
      }
    }
    return out;
  }

  /** Call from the XR animation frame callback; publishes when one period has passed,
   * reading the poses in `space` (default: the constructor's). Returns the bytes sent
   * (0 when not due, or nothing was tracked). */
  onFrame(frame: XRFrameLike, space: unknown = this.space): number {
    checkSpace(space);
    const client = this.client;
    if (client.state !== "joined") return 0;
    const now = client.clock();
    if (now < this.next) return 0;
    this.next = now - this.next > this.period ? now + this.period : this.next + this.period;
    const volume = client.welcome?.volume ?? DEFAULT_VOLUME;
    const poses: Record<string, Pose> = {};
    const joined = client.streams;
    for (const [name, pose] of Object.entries(this.read(frame, space))) {
      if (!(name in joined)) continue;
      if (!inVolume(pose, volume)) {
        this.outOfVolume++;
        continue;
      }
      poses[name] = pose;
    }
    const bytes = client.publish(poses);
    if (bytes) {
      this.published++;
      this.last = poses;
    }
    return bytes;
  }
}

function checkSpace(space: unknown): void {
  if (space === null || space === undefined) {
    throw new UsageError("bad-space", "XRPublisher: no reference space (give one to the constructor or with each frame)");
  }
}

/** Whether a pose's position is inside volume [min x, y, z, max x, y, z] (inclusive). */
export function inVolume(pose: ArrayLike<number>, volume: readonly number[]): boolean {
  for (let i = 0; i < 3; i++) {
    const x = pose[i]!;
    if (!(x >= volume[i]! && x <= volume[i + 3]!)) return false;
  }
  return true;
}
