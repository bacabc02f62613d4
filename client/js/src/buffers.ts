/**
 * The receiver model, as posecast's Python receiver (`scenarios/receiver.py`,
 * `scenarios/buffers.py`) has it; nothing here reads a clock.
 *
 * - `StreamBuffer`: one remote stream's keyframes by capture time; duplicates and
 *   stale keyframes dropped; bounded (oldest evicted); `bracket(t)` for rendering.
 * - `PlayoutDelay`: D = interval + p95(keyframe age) + margin, slewing (tau 1 s).
 * - `RoomPlayoutDelay`: a PlayoutDelay per remote user; the room's D from users
 *   whose ages are not outliers (the majority's median plus a bound that follows
 *   the room's jitter width, or the MAD of the medians); a late user is shown late alone.
 */
import type { Pose } from "./messages.js";

export const DEFAULT_BUFFER_CAPACITY = 64;
const UNIT_TOLERANCE = 1e-6;

export interface Bracket {
  lo: number;
  hi: number;
  s: number;
  stalled: boolean;
}

export type Velocity = [number, number, number, number, number, number];

/** A keyframe pose as numbers, its quaternion renormalised when off unit length by
 * more than 1e-6; null when it is not finite or the quaternion is zero. */
function checkedPose(pose: ArrayLike<number>): Pose | null {
  const p = Array.from(pose).slice(0, 7) as Pose;
  if (p.length !== 7 || !p.every(Number.isFinite)) return null;
  const n2 = p[3] * p[3] + p[4] * p[4] + p[5] * p[5] + p[6] * p[6];
  if (!(n2 > 1e-24)) return null;
  if (Math.abs(n2 - 1) > 2 * UNIT_TOLERANCE) {
    const n = Math.sqrt(n2);
    for (let i = 3; i < 7; i++) p[i]! /= n;
  }
  return p;
}

function bisectLeft(a: readonly number[], x: number): number {
  let lo = 0, hi = a.length;
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (a[mid]! < x) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

function bisectRight(a: readonly number[], x: number): number {
  let lo = 0, hi = a.length;
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (x < a[mid]!) hi = mid;
    else lo = mid + 1;
  }
  return lo;
}

export class StreamBuffer {
  readonly times: number[] = [];
  readonly poses: Pose[] = [];
  readonly velocities: (Velocity | null)[] = [];
  duplicates = 0;
  stale = 0;
  evicted = 0;
  invalid = 0;

  constructor(readonly capacity = DEFAULT_BUFFER_CAPACITY) {
    if (capacity < 1) throw new RangeError(`capacity must be at least 1, got ${capacity}`);
  }

  get length(): number {
    return this.times.length;
  }

  /** Add a keyframe; false if it was refused (duplicate, stale, invalid).
   * `floor`: the playout time already rendered (a keyframe superseded before it is stale). */
  push(capture: number, pose: ArrayLike<number>, floor = -Infinity, velocity: Velocity | null = null): boolean {
    const times = this.times;
    const i = bisectLeft(times, capture);
    if (i < times.length && times[i] === capture) {
      this.duplicates++;
      return false;
    }
    const superseded = capture < floor && i < times.length && times[i]! <= floor;
    if (superseded || (times.length >= this.capacity && i === 0)) {
      this.stale++;
      return false;
    }
    const checked = checkedPose(pose);
    if (checked === null || !Number.isFinite(capture)) {
      this.invalid++;
      return false;
    }
    times.splice(i, 0, capture);
    this.poses.splice(i, 0, checked);
    this.velocities.splice(i, 0, velocity);
    if (times.length > this.capacity) {
      times.shift();
      this.poses.shift();
      this.velocities.shift();
      this.evicted++;
    }
    return true;
  }

  /** The keyframes either side of playout time `t`, and the fraction between them.
   * Past the newest (or before the first) it holds the newest: a stall. */
  bracket(t: number): Bracket {
    const times = this.times;
    const hi = bisectRight(times, t);
    if (hi === 0) {
      const newest = times.length - 1;
      return { lo: newest, hi: newest, s: 0, stalled: true };
    }
    const lo = hi - 1;
    if (times[lo] === t) return { lo, hi: lo, s: 0, stalled: false };
    if (hi >= times.length) return { lo, hi: lo, s: 0, stalled: true };
    return { lo, hi, s: (t - times[lo]!) / (times[hi]! - times[lo]!), stalled: false };
  }
}

/** numpy's default (linear) percentile of `values`, q in [0, 100]. */
export function percentile(values: readonly number[], q: number): number {
  const a = [...values].sort((x, y) => x - y);
  const n = a.length;
  if (n === 0) return NaN;
  const pos = ((n - 1) * q) / 100;
  const lo = Math.floor(pos);
  const hi = Math.min(lo + 1, n - 1);
  const frac = pos - lo;
  // numpy's _lerp: a + (b - a) * t, or b - (b - a) * (1 - t) for t >= 0.5.
  const x = a[lo]!, y = a[hi]!;
  const diff = y - x;
  return frac >= 0.5 ? y - diff * (1 - frac) : x + diff * frac;
}

export function median(values: readonly number[]): number {
  return percentile(values, 50);
}

/** Bounded window of recent values (a deque with maxlen). */
class Window {
  readonly values: number[] = [];
  constructor(readonly size: number) {}
  push(x: number): void {
    this.values.push(x);
    if (this.values.length > this.size) this.values.shift();
  }
  get length(): number {
    return this.values.length;
  }
}

export class PlayoutDelay {
  value: number;
  readonly ages: Window;
  last: number | null = null;

  constructor(
    /** The snapshot interval D bridges (s); `RoomPlayoutDelay.retime` changes it. */
    public interval: number,
    readonly pct = 95,
    readonly tau = 1,
    window = 256,
    readonly margin = 0.002,
  ) {
    this.value = interval + margin;
    this.ages = new Window(window);
  }

  /** One keyframe's age on arrival (arrival minus capture, server clock). */
  observe(age: number): void {
    this.ages.push(age);
  }

  get target(): number {
    if (!this.ages.length) return this.interval + this.margin;
    return this.interval + percentile(this.ages.values, this.pct) + this.margin;
  }

  /** Slew towards the target (or `target`); the first one sets D directly. */
  update(now: number, target: number | null = null): number {
    const given = target !== null;
    const goal = target ?? this.target;
    if (this.last === null) {
      if (this.ages.length || given) {
        this.value = goal;
        this.last = now;
      }
      return this.value;
    }
    const dt = Math.max(0, now - this.last);
    this.last = now;
    this.value += (goal - this.value) * Math.min(1, dt / this.tau);
    return this.value;
  }
}

/** Playout delay per remote user: one late user cannot raise D for the others. The
 * late bound follows the room's own spread of ages, as Python's
 * `client.playout.RoomPlayoutDelay` (its docstring states the rule).
 *
 * Per peer (`perPeer`, for a client that joined with a `budgetDeg`: the relay sends
 * each peer every k snapshot intervals, its own k): the send times of the snapshots
 * carrying a user's new keyframes give its keyframe interval in snapshot intervals
 * (the last `gapWindow` of them); its divisor k is their `pct` percentile (nearest
 * rank), and its D is the above plus (k - 1) intervals, slewing like any D. A user at
 * the snapshot rate has k = 1 and the D it had without `perPeer`. */
export class RoomPlayoutDelay {
  readonly room: PlayoutDelay;
  /** Users shown late alone (or slewing back to the room's D): their own D (s). */
  readonly own = new Map<number, number>();
  readonly late = new Set<number>();
  private readonly users = new Map<number, PlayoutDelay>();
  private dirty = false;
  private target: number | null = null;
  private ownTargets = new Map<number, number>();
  private seated = new Set<number>();
  private was = new Set<number>();
  /** Size each user's D from its own keyframe interval too (see the class comment). */
  perPeer = false;
  /** Keyframe intervals (in snapshot intervals) a user's divisor is judged over. */
  gapWindow = 16;
  private readonly sent = new Map<number, number>();
  private readonly gaps = new Map<number, Window>();
  private readonly extra = new Map<number, number>();
  private extraAt: number | null = null;

  constructor(
    /** The snapshot interval (s), 1 / rate; `retime` changes it. */
    public interval: number,
    readonly pct = 95,
    readonly tau = 1,
    readonly window = 256,
    readonly margin = 0.002,
    /** Floor of the late bound (s). */
    readonly tolerance = 0.005,
    readonly spread = 3,
    readonly minSamples = 3,
    /** The snapshot rate `interval` is for (Hz; default 1 / interval). */
    public rate = 1 / interval,
    /** Share of the room's jitter width (percentile minus median age) a lag may reach. */
    readonly jitter = 0.3,
    /** Ages a user needs to be judged by the room's spread; before, by `early` (s). */
    readonly settle = 20,
    readonly early = 0.1,
    /** Honest spread of median ages from publish phases (s); null: one interval. */
    readonly phase: number | null = null,
  ) {
    this.room = this.make();
  }

  private make(): PlayoutDelay {
    return new PlayoutDelay(this.interval, this.pct, this.tau, this.window, this.margin);
  }

  /** The snapshots now come at `rate` (Hz), as a relay's `rate` notice says: the
   * interval every D covers scales by the old rate / the new one (1 / rate in
   * `Receiver`). The ages measured so far are kept, and each D slews to its new
   * target (time constant `tau`), never jumps: a playout time that jumped back
   * would show poses again. As Python's `RoomPlayoutDelay.retime`. */
  retime(rate: number): void {
    if (!(rate > 0) || !Number.isFinite(rate)) return;
    const scale = this.rate / rate;
    this.rate = rate;
    this.interval *= scale;
    for (const d of [this.room, ...this.users.values()]) d.interval *= scale;
    this.gaps.clear(); // counted in the old intervals; the extras slew from where they are
    this.dirty = true;
  }

  /** One keyframe of `user`'s, its age on arrival (server clock); `sent`: the send
   * time of the snapshot that carried it (server clock; used with `perPeer`). */
  observe(user: number, age: number, sent: number | null = null): void {
    let d = this.users.get(user);
    if (!d) this.users.set(user, (d = this.make()));
    d.observe(age);
    this.dirty = true;
    if (!this.perPeer || sent === null) return;
    const last = this.sent.get(user);
    if (last === undefined || sent > last) this.sent.set(user, sent);
    if (last === undefined || !(sent > last)) return;
    let gaps = this.gaps.get(user);
    if (!gaps) this.gaps.set(user, (gaps = new Window(this.gapWindow)));
    const step = this.rate > 0 ? 1 / this.rate : this.interval;
    gaps.push(Math.max(1, Math.floor((sent - last) / step + 0.5)));
  }

  /** `user`'s keyframe interval in snapshot intervals (1 without `perPeer`). */
  divisor(user: number): number {
    const gaps = this.gaps.get(user);
    if (!gaps || !gaps.length) return 1;
    const ranked = [...gaps.values].sort((a, b) => a - b);
    return ranked[Math.max(0, Math.ceil((ranked.length * this.pct) / 100) - 1)]!;
  }

  /** Every user shown at another D than the room's: late ones, slower peers. */
  ownDelays(): Map<number, number> {
    const out = new Map(this.own);
    for (const [u, e] of this.extra) if (e > 1e-9) out.set(u, (this.own.get(u) ?? this.room.value) + e);
    return out;
  }

  forget(user: number): void {
    this.users.delete(user);
    this.own.delete(user);
    this.late.delete(user);
    this.sent.delete(user);
    this.gaps.delete(user);
    this.extra.delete(user);
    this.dirty = true;
  }

  /** The D `user`'s streams are rendered with. */
  delay(user: number): number {
    return (this.own.get(user) ?? this.room.value) + (this.extra.get(user) ?? 0);
  }

  private classify(): number | null {
    const judged = new Map<number, PlayoutDelay>();
    for (const [u, d] of this.users) if (d.ages.length >= this.minSamples) judged.set(u, d);
    if (judged.size) {
      const med = new Map<number, number>();
      const top = new Map<number, number>();
      for (const [u, d] of judged) {
        med.set(u, median(d.ages.values));
        top.set(u, percentile(d.ages.values, this.pct));
      }
      const ranked = [...med.values()].sort((a, b) => a - b);
      const ref = ranked[(ranked.length - 1) >> 1]!;
      const widths = [...judged]
        .filter(([, d]) => d.ages.length >= this.settle)
        .map(([u]) => top.get(u)! - med.get(u)!)
        .sort((a, b) => a - b);
      const width = widths.length ? widths[(widths.length - 1) >> 1]! : 0;
      const mad = ranked.length > 2 ? median(ranked.map((m) => Math.abs(m - ref))) : 0;
      const phase = this.phase ?? (this.rate > 0 ? 1 / this.rate : this.interval);
      const paths = this.spread * 1.4826 * Math.max(0, mad - phase / 2);
      const bound = Math.max(this.tolerance, this.jitter * width) + phase + paths;
      const over = new Map<number, boolean>();
      for (const [u, d] of judged) {
        const n = d.ages.length;
        const allowed = n >= this.settle ? bound + (3 * width) / Math.sqrt(n) : this.early;
        over.set(u, med.get(u)! - ref > allowed);
      }
      for (const [u, o] of over) if (o) this.late.add(u);
      const seatedAges = [...judged].filter(([u]) => !this.late.has(u)).map(([, d]) => d.ages.values);
      const roomTop = seatedAges.length ? percentile(seatedAges.flat(), this.pct) : ref;
      for (const u of [...this.late]) {
        if (judged.has(u) && !over.get(u) && top.get(u)! < roomTop + bound) this.late.delete(u);
      }
    }
    this.ownTargets = new Map([...this.late].map((u) => [u, this.users.get(u)!.target]));
    const seated = new Set([...judged.keys()].filter((u) => !this.late.has(u)));
    if (seated.size && ![...seated].some((u) => this.seated.has(u))) this.room.last = null;
    this.was = this.seated;
    this.seated = seated;
    let pool = [...judged].filter(([u]) => seated.has(u)).map(([, d]) => d.ages.values);
    if (!pool.length) pool = [...this.users.values()].filter((d) => d.ages.length).map((d) => d.ages.values);
    if (!pool.length) return null;
    return this.interval + percentile(pool.flat(), this.pct) + this.margin;
  }

  /** Slew the room's D and every late user's own D; returns the room's. */
  update(now: number): number {
    const before = this.room.value;
    if (this.dirty) {
      this.target = this.classify();
      this.dirty = false;
    }
    const target = this.target;
    const room = this.room.update(now, target);
    for (const u of this.late) {
      if (this.own.has(u)) continue; // newly late: from where it was shown
      const d = this.users.get(u)!;
      d.value = before;
      d.last = this.was.has(u) ? now : null;
    }
    for (const u of new Set([...this.own.keys(), ...this.late])) {
      const d = this.users.get(u)!;
      if (this.late.has(u)) {
        this.own.set(u, d.update(now, Math.max(this.ownTargets.get(u)!, target || room)));
      } else if (Math.abs(d.update(now, room) - room) < 1e-3) {
        this.own.delete(u);
      } else {
        this.own.set(u, d.value);
      }
    }
    if (this.gaps.size) this.slewExtras(now);
    return room;
  }

  /** Each slower peer's extra D towards (k - 1) intervals. */
  private slewExtras(now: number): void {
    const step = this.extraAt === null ? 1 : Math.min(1, Math.max(0, now - this.extraAt) / this.tau);
    this.extraAt = now;
    for (const u of this.gaps.keys()) {
      const goal = (this.divisor(u) - 1) * this.interval;
      const e = this.extra.get(u);
      this.extra.set(u, e === undefined ? goal : e + (goal - e) * step);
    }
  }
}
