/**
 * What a client knows of everyone else: peers, shared objects, every remote
 * stream's jitter buffer, the per-user playout delay, and the render call.
 *
 * Sans-I/O: it is fed decoded messages with their arrival times (server clock)
 * and asked for poses at a playout time; it never reads a clock.
 */
import { RoomPlayoutDelay, StreamBuffer, DEFAULT_BUFFER_CAPACITY } from "./buffers.js";
import type { Velocity } from "./buffers.js";
import { interpolator } from "./interp.js";
import type { MethodName } from "./interp.js";
import type { ObjectInfo, Owner, PeerJoined, Pose, Snapshot, Vec3 } from "./messages.js";
import { ROOM_USER } from "./messages.js";

/** A relay codec snapshot codes capture times to 1 ms against its own base time:
 * a resent unchanged keyframe comes back within that of the first. */
const REPEAT_TIME = 1e-3 + 1e-9;

export interface Peer {
  user: number;
  label: string | null;
  /** Stream name -> id. */
  streams: Record<string, number>;
  velocities: boolean;
  stalled: boolean;
}

export interface SharedObject {
  name: string;
  stream: number;
  creator: number;
  owner: number | null;
  keep: boolean;
  steal: boolean;
  locked: boolean;
  /** Latest pose the server told of (object message); snapshots carry the rest. */
  pose: Pose;
  time: number;
  /** A throw's release velocity while it flies (the relay moves it; its keyframes
   * arrive in snapshots like any stream). */
  velocity: Vec3 | null;
  angular: Vec3 | null;
}

export interface RemoteStream {
  user: number;
  stream: number;
  /** "head", "left", "right", "object:NAME", or "streamN" when not announced. */
  name: string;
  label: string | null;
  buffer: StreamBuffer;
  /** Keyframes received (repeats of the last one not counted). */
  received: number;
}

export interface RenderedPose {
  user: number;
  stream: number;
  name: string;
  label: string | null;
  pose: Pose;
  /** No keyframe after the playout time: the newest is held. */
  stalled: boolean;
  /** The playout time this stream was rendered at (server clock). */
  time: number;
  /** The delay it was rendered with (s). */
  delay: number;
}

export interface RenderFrame {
  /** The server time the frame was rendered for (playout time = now - delay). */
  now: number;
  /** The room's playout delay (s). */
  delay: number;
  poses: RenderedPose[];
}

export interface ReceiverOptions {
  /** Snapshot rate (Hz): the playout delay starts at one interval. */
  rate: number;
  capacity?: number;
  /** Size each peer's playout delay from its own keyframe interval too (a client that
   * joined with `budgetDeg`: the relay sends each peer at its own rate). */
  perPeer?: boolean;
}

export class Receiver {
  readonly peers = new Map<number, Peer>();
  readonly objects = new Map<number, SharedObject>();
  readonly streams = new Map<string, RemoteStream>();
  delay: RoomPlayoutDelay;
  /** This client's own user id: its streams are not rendered. */
  me = -1;
  posesReceived = 0;
  private floor = -Infinity;
  private readonly capacity: number;
  /** Each peer's playout delay is sized from its own keyframe interval too (`perPeer`). */
  readonly perPeer: boolean;

  constructor(opts: ReceiverOptions) {
    this.capacity = opts.capacity ?? DEFAULT_BUFFER_CAPACITY;
    this.perPeer = opts.perPeer ?? false;
    this.delay = this.makeDelay(1 / opts.rate);
  }

  private makeDelay(interval: number): RoomPlayoutDelay {
    const d = new RoomPlayoutDelay(interval);
    d.perPeer = this.perPeer;
    return d;
  }

  /** A new snapshot rate (set_rate, rejoin): the delay's interval follows it. */
  setRate(rate: number): void {
    this.delay = this.makeDelay(1 / rate);
  }

  /** The relay chose another rate (a `rate` notice, auto rate): the delay keeps its
   * measured ages and slews to the new interval. */
  retime(rate: number): void {
    this.delay.retime(rate);
  }

  /** Forget everyone (a rejoin as a new member: ids from before mean nothing). */
  reset(): void {
    this.peers.clear();
    this.objects.clear();
    this.streams.clear();
    this.delay = this.makeDelay(this.delay.interval);
    this.floor = -Infinity;
  }

  /** A member is in the room. Announced again (after this client resumed, the relay
   * repeats every member) with the same streams, its buffers stay; with other
   * streams it is another member under a reused id, and starts afresh. Keyframes
   * that came before the announcement are kept and named now. */
  peerJoined(ev: PeerJoined): void {
    const known = this.peers.get(ev.user);
    if (known && JSON.stringify(known.streams) !== JSON.stringify(ev.streams)) this.forget(ev.user);
    this.peers.set(ev.user, { user: ev.user, label: ev.label, streams: ev.streams, velocities: ev.velocities, stalled: false });
    for (const rs of this.streams.values()) {
      if (rs.user === ev.user) [rs.name, rs.label] = this.names(rs.user, rs.stream);
    }
  }

  peerLeft(user: number): void {
    this.peers.delete(user);
    this.forget(user);
  }

  peerStalled(user: number, stalled: boolean): void {
    const p = this.peers.get(user);
    if (p) p.stalled = stalled;
  }

  private forget(user: number): void {
    for (const [key, rs] of this.streams) if (rs.user === user) this.streams.delete(key);
    this.delay.forget(user);
  }

  object(ev: ObjectInfo): void {
    this.objects.set(ev.stream, {
      name: ev.name, stream: ev.stream, creator: ev.creator, owner: ev.owner, keep: ev.keep,
      steal: ev.steal, locked: ev.locked, pose: ev.pose, time: ev.time, velocity: null, angular: null,
    });
    const rs = this.streams.get(key(ROOM_USER, ev.stream));
    if (rs) rs.name = ev.name;
  }

  owner(ev: Owner): void {
    const o = this.objects.get(ev.stream);
    if (!o) return;
    o.owner = ev.owner;
    o.locked = ev.locked;
    o.velocity = ev.velocity;
    o.angular = ev.angular;
  }

  objectRemoved(stream: number): void {
    this.objects.delete(stream);
    this.streams.delete(key(ROOM_USER, stream));
  }

  private names(user: number, stream: number): [string, string | null] {
    if (user === ROOM_USER) return [this.objects.get(stream)?.name ?? `stream${stream}`, null];
    const peer = this.peers.get(user);
    if (!peer) return [`stream${stream}`, null];
    for (const [name, id] of Object.entries(peer.streams)) if (id === stream) return [name, peer.label];
    return [`stream${stream}`, peer.label];
  }

  /** Buffer a snapshot's keyframes; `arrival`: when it arrived, server clock. */
  snapshot(snap: Snapshot, arrival: number): number {
    let added = 0;
    for (const e of snap.entries) {
      if (e.user === this.me) continue;
      const k = key(e.user, e.stream);
      let rs = this.streams.get(k);
      if (!rs) {
        const [name, label] = this.names(e.user, e.stream);
        rs = { user: e.user, stream: e.stream, name, label, buffer: new StreamBuffer(this.capacity), received: 0 };
        this.streams.set(k, rs);
      } else if (rs.label === null && rs.user !== ROOM_USER && this.peers.has(rs.user)) {
        [rs.name, rs.label] = this.names(rs.user, rs.stream);
      }
      const b = rs.buffer;
      const n = b.length;
      if (n && Math.abs(e.capture - b.times[n - 1]!) <= REPEAT_TIME && samePose(e.pose, b.poses[n - 1]!)) continue;
      rs.received++;
      this.posesReceived++;
      b.push(e.capture, e.pose, this.floor, (e.velocity as Velocity | undefined) ?? null);
      this.delay.observe(e.user, arrival - e.capture, snap.time);
      added++;
    }
    return added;
  }

  /** Every remote stream at server time `now` minus its playout delay. */
  render(now: number, method: MethodName | string = "soa"): RenderFrame {
    const fn = interpolator(method);
    const room = this.delay.update(now);
    const poses: RenderedPose[] = [];
    let floor = Infinity;
    for (const rs of this.streams.values()) {
      const b = rs.buffer;
      if (!b.length) continue;
      const d = this.delay.delay(rs.user);
      const t = now - d;
      floor = Math.min(floor, t);
      const br = b.bracket(t);
      const pose = br.lo === br.hi ? ([...b.poses[br.lo]!] as Pose) : fn(b.poses[br.lo]!, b.poses[br.hi]!, br.s);
      poses.push({ user: rs.user, stream: rs.stream, name: rs.name, label: rs.label, pose, stalled: br.stalled, time: t, delay: d });
    }
    if (Number.isFinite(floor)) this.floor = Math.max(this.floor, floor);
    return { now, delay: room, poses };
  }
}

function key(user: number, stream: number): string {
  return `${user}:${stream}`;
}

function samePose(a: ArrayLike<number>, b: ArrayLike<number>): boolean {
  // Poses arrive as float32 values; the buffer keeps them as they came (renormalised
  // only when off unit length, which a float32 pose from a relay never is).
  for (let i = 0; i < 7; i++) if (Math.fround(a[i]!) !== Math.fround(b[i]!)) return false;
  return true;
}
