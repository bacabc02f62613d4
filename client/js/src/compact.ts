/**
 * The compact codec of docs/protocol.md section 11, both ways.
 *
 * - Codes (11.2): a pose is 7 integers `[idx, a, b, c, px, py, pz]` (smallest-three
 *   rotation, positions quantised in the room volume), 13 with velocities.
 * - Version-1 update frames (11.5): what a client sends; encoded here byte for byte
 *   as the reference does (and decoded, for tests and tools).
 * - Version-2 snapshot frames (11.6): what the relay sends; decoded here.
 * - `CompactSession`: one connection's two directions with their baselines (11.3).
 */
import { DecodeError, UsageError } from "./errors.js";
import type { Pose, PoseEntry, Snapshot } from "./messages.js";

export const CODEC_FRAME_BYTE = 0xc1;
const M = 4095;
const S = Math.SQRT2 * M;
const FLAG_UPDATE = 0x01;
const FLAG_VELOCITY = 0x02;
const FLAG_SPLIT = 0x04;
const FLAG_RELATIVE = 0x08;
const LIN_STEP = 2 ** -9;
const ANG_STEP = 2 ** -8;
const MAX_OFFSET = 2 ** 30;
const MAX_BASE_US = 2n ** 62n;
const MAX_NUMBER = 2n ** 63n;

// ---------------------------------------------------------------------------
// Primitives (11.1)

/** Round half to even (the spec's "round"; Math.round rounds half up). */
export function roundHalfEven(x: number): number {
  const r = Math.round(x);
  return r - x === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

export function zigzag(v: number): number {
  return v >= 0 ? 2 * v : -2 * v - 1;
}

export function unzigzag(z: number): number {
  return z % 2 ? -(z + 1) / 2 : z / 2;
}

function bitLength(x: number): number {
  if (x < 0x80000000) return 32 - Math.clz32(x);
  let n = 0;
  while (x >= 2 ** 24) {
    x = Math.floor(x / 2 ** 24);
    n += 24;
  }
  return n + 32 - Math.clz32(x);
}

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let i = 0; i < 256; i++) {
    let c = i;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[i] = c >>> 0;
  }
  return t;
})();

/** CRC-32 of zlib (ISO-HDLC). */
export function crc32(data: Uint8Array): number {
  let c = 0xffffffff;
  for (let i = 0; i < data.length; i++) c = CRC_TABLE[(c ^ data[i]!) & 0xff]! ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

class BitWriter {
  readonly out: number[] = [];
  private acc = 0;
  private n = 0;

  /** `v` (unsigned, < 2^53) in `bits` bits, most significant first. */
  write(v: number, bits: number): void {
    while (bits > 0) {
      const take = Math.min(bits, 24);
      const shift = bits - take;
      const chunk = (shift ? Math.floor(v / 2 ** shift) : v) % 2 ** take;
      this.acc = (this.acc << take) | chunk;
      this.n += take;
      while (this.n >= 8) {
        this.n -= 8;
        this.out.push((this.acc >>> this.n) & 0xff);
      }
      this.acc &= (1 << this.n) - 1;
      bits -= take;
    }
  }

  /** The bytes, the last one padded with zero bits. */
  finish(): number[] {
    if (this.n) this.out.push((this.acc << (8 - this.n)) & 0xff);
    this.acc = this.n = 0;
    return this.out;
  }
}

function truncated(): DecodeError {
  return new DecodeError("bad-frame", "compact frame truncated");
}

class BitReader {
  private pos: number;
  private readonly end: number;

  constructor(
    private readonly data: Uint8Array,
    start: number,
  ) {
    this.pos = start * 8;
    this.end = data.length * 8;
  }

  get remaining(): number {
    return this.end - this.pos;
  }

  read(bits: number): number {
    if (this.pos + bits > this.end) throw truncated();
    let v = 0;
    while (bits > 0) {
      const byte = this.data[this.pos >> 3]!;
      const avail = 8 - (this.pos & 7);
      const take = Math.min(avail, bits);
      v = v * 2 ** take + ((byte >> (avail - take)) & ((1 << take) - 1));
      this.pos += take;
      bits -= take;
    }
    return v;
  }

  /** Zeros up to (and through) the next one bit. */
  zeros(limit: number): number {
    let n = 0;
    for (;;) {
      if (this.pos >= this.end) throw truncated();
      const bit = (this.data[this.pos >> 3]! >> (7 - (this.pos & 7))) & 1;
      this.pos++;
      if (bit) return n;
      if (++n > limit) throw new DecodeError("bad-frame", "Exp-Golomb prefix too long");
    }
  }

  /** Fewer than 8 padding bits, all zero, and nothing after them. */
  finish(): void {
    const rest = this.end - this.pos;
    if (rest >= 8) throw new DecodeError("bad-frame", "bytes after the compact frame's bitstream");
    if (rest && this.read(rest) !== 0) throw new DecodeError("bad-frame", "non-zero padding bits");
  }
}

/** The smallest k in 0..15 giving the fewest bits for `values` (0 for none). */
export function bestOrder(values: readonly number[]): number {
  // With b = bitlength(v): EGk takes 1 + k bits if b <= k, else 2b - k.
  const lengths = values.map(bitLength);
  let best = 0;
  let bestBits = Infinity;
  for (let k = 0; k < 16; k++) {
    let bits = 0;
    for (const b of lengths) bits += b <= k ? 1 + k : 2 * b - k;
    if (bits < bestBits) {
      bestBits = bits;
      best = k;
    }
  }
  return best;
}

function egPrefix(w: BitWriter, v: number, k: number): void {
  const L = Math.max(0, bitLength(v) - k);
  w.write(1, L + 1);
}

function egSuffix(w: BitWriter, v: number, k: number): void {
  const L = Math.max(0, bitLength(v) - k);
  const n = L === 0 ? k : L - 1 + k;
  if (n) w.write(v % 2 ** n, n);
}

/** A column: every value's prefix, then every suffix. */
function egColumn(w: BitWriter, values: readonly number[], k: number): void {
  for (const v of values) egPrefix(w, v, k);
  for (const v of values) egSuffix(w, v, k);
}

function egSuffixRead(r: BitReader, L: number, k: number): number {
  if (L === 0) return k ? r.read(k) : 0;
  return 2 ** (L - 1 + k) + r.read(L - 1 + k);
}

function egRead(r: BitReader, k: number): number {
  return egSuffixRead(r, r.zeros(48 - k), k);
}

function egColumnRead(r: BitReader, n: number, k: number): number[] {
  const prefixes: number[] = [];
  for (let i = 0; i < n; i++) prefixes.push(r.zeros(48 - k));
  return prefixes.map((L) => egSuffixRead(r, L, k));
}

function writeUvarint(out: number[], v: bigint): void {
  do {
    let byte = Number(v & 0x7fn);
    v >>= 7n;
    if (v) byte |= 0x80;
    out.push(byte);
  } while (v);
}

function writeSvarint(out: number[], v: bigint): void {
  writeUvarint(out, v >= 0n ? 2n * v : -2n * v - 1n);
}

function svarintValue(z: bigint): bigint {
  return z & 1n ? -(z + 1n) / 2n : z / 2n;
}

// ---------------------------------------------------------------------------
// Codes (11.2)

/** The room volume's quantisation: bits and step per axis. */
export class Volume {
  readonly lo: [number, number, number];
  readonly hi: [number, number, number];
  readonly bits: [number, number, number];
  readonly step: [number, number, number];

  /** `volume`: welcome.volume, [min x, y, z, max x, y, z]. */
  constructor(volume: readonly number[]) {
    if (volume.length !== 6) throw new UsageError("bad-message", "a volume is 6 numbers");
    this.lo = [volume[0]!, volume[1]!, volume[2]!];
    this.hi = [volume[3]!, volume[4]!, volume[5]!];
    const bits: number[] = [];
    const step: number[] = [];
    for (let i = 0; i < 3; i++) {
      const span = this.hi[i]! - this.lo[i]!;
      if (!(span > 0 && span <= 4096)) throw new UsageError("bad-message", "volume axis must have lo < hi <= lo + 4096");
      const b = Math.max(1, Math.ceil(Math.log2(span / 0.0005 + 1)));
      bits.push(b);
      step.push(span / (2 ** b - 1));
    }
    this.bits = bits as [number, number, number];
    this.step = step as [number, number, number];
  }

  /** The largest position code of axis `i`. */
  max(i: number): number {
    return 2 ** this.bits[i]! - 1;
  }
}

const OTHERS = [
  [1, 2, 3],
  [0, 2, 3],
  [0, 1, 3],
  [0, 1, 2],
] as const;

/** The codes of a pose (and velocity): 7 or 13 integers. A position more than half a
 * step outside the volume, or a non-finite value, is a `bad-pose` UsageError. */
export function poseCodes(pose: ArrayLike<number>, volume: Volume, velocity?: ArrayLike<number> | null): number[] {
  // Quantised as sent raw: the float32 values of the 7 numbers, widened (11.2).
  const f = Math.fround;
  const q = [f(pose[3]!), f(pose[4]!), f(pose[5]!), f(pose[6]!)];
  // The reference's summation order: (w*w + y*y) + (x*x + z*z).
  const norm = Math.sqrt(q[0]! * q[0]! + q[2]! * q[2]! + (q[1]! * q[1]! + q[3]! * q[3]!));
  if (!(norm > 0) || !Number.isFinite(norm)) throw new UsageError("bad-pose", "quaternion is zero or not finite");
  for (let i = 0; i < 4; i++) q[i]! /= norm;
  let idx = 0;
  for (let i = 1; i < 4; i++) if (Math.abs(q[i]!) > Math.abs(q[idx]!)) idx = i;
  const sign = q[idx]! < 0 ? -1 : 1;
  const codes = [idx];
  for (const o of OTHERS[idx]!) codes.push(Math.max(-M, Math.min(M, roundHalfEven(sign * q[o]! * S))));
  for (let i = 0; i < 3; i++) {
    const c = roundHalfEven((f(pose[i]!) - volume.lo[i]!) / volume.step[i]!);
    if (!(c >= 0 && c <= volume.max(i))) {
      throw new UsageError("bad-pose", `position ${pose[i]} outside the room volume [${volume.lo[i]}, ${volume.hi[i]}] on axis ${"xyz"[i]}`);
    }
    codes.push(c);
  }
  if (velocity) {
    for (let i = 0; i < 6; i++) {
      const v = velocity[i]!;
      if (!Number.isFinite(v)) throw new UsageError("bad-velocity", "non-finite velocity");
      codes.push(roundHalfEven(Math.max(-64, Math.min(64, v)) / (i < 3 ? LIN_STEP : ANG_STEP)));
    }
  }
  return codes;
}

/** Whether codes are in range (11.2). */
export function codesValid(codes: readonly number[], volume: Volume): boolean {
  const [idx, a, b, c] = codes as [number, number, number, number];
  if (!(idx >= 0 && idx <= 3)) return false;
  if (Math.abs(a) > M || Math.abs(b) > M || Math.abs(c) > M || a * a + b * b + c * c > 2 * M * M) return false;
  for (let i = 0; i < 3; i++) {
    const p = codes[4 + i]!;
    if (!(p >= 0 && p <= volume.max(i))) return false;
  }
  for (let i = 7; i < codes.length; i++) {
    if (Math.abs(codes[i]!) > (i < 10 ? 32768 : 16384)) return false;
  }
  return true;
}

/** The pose (and velocity) of codes, as float32 values (11.2). */
export function codesToPose(codes: readonly number[], volume: Volume): { pose: Pose; velocity: number[] | null } {
  const idx = codes[0]!;
  const x = codes[1]! / S;
  const y = codes[2]! / S;
  const z = codes[3]! / S;
  const q = [0, 0, 0, 0];
  q[idx] = Math.sqrt(Math.max(0, 1 - (x * x + z * z + y * y)));
  const o = OTHERS[idx]!;
  q[o[0]] = x;
  q[o[1]] = y;
  q[o[2]] = z;
  const pose = [0, 0, 0, 0, 0, 0, 0] as Pose;
  for (let i = 0; i < 3; i++) pose[i] = Math.fround(volume.lo[i]! + codes[4 + i]! * volume.step[i]!);
  for (let i = 0; i < 4; i++) pose[3 + i] = Math.fround(q[i]!);
  let velocity: number[] | null = null;
  if (codes.length === 13) {
    velocity = [];
    for (let i = 0; i < 6; i++) velocity.push(Math.fround(codes[7 + i]! * (i < 3 ? LIN_STEP : ANG_STEP)));
  }
  return { pose, velocity };
}

/** The baseline's rotation re-expressed with index `idx` (11.7). */
export function predict(base: readonly number[], idx: number): [number, number, number] {
  const [i0, a, b, c] = base as [number, number, number, number];
  if (idx === i0) return [a, b, c];
  const rest = Math.max(0, 2 * M * M - (a * a + b * b + c * c));
  const big = Math.floor((Math.floor(Math.sqrt(4 * rest)) + 1) / 2);
  const full = [0, 0, 0, 0];
  full[i0] = big;
  const o = OTHERS[i0]!;
  full[o[0]] = a;
  full[o[1]] = b;
  full[o[2]] = c;
  const sign = full[idx]! < 0 ? -1 : 1;
  const n = OTHERS[idx]!;
  return [clampM(sign * full[n[0]]!), clampM(sign * full[n[1]]!), clampM(sign * full[n[2]]!)];
}

function clampM(v: number): number {
  return Math.max(-M, Math.min(M, v));
}

// ---------------------------------------------------------------------------
// Frames

export interface CompactEntry {
  /** Snapshots: the user id; updates: absent. */
  user?: number;
  stream: number;
  /** Milliseconds before the frame's base time (may be negative). */
  offsetMs: number;
  codes: number[];
  delta: boolean;
}

export interface CompactHeader {
  number: number;
  baseUs: number;
}

export interface CompactFrame extends CompactHeader {
  kind: "update" | "snapshot";
  velocity: boolean;
  entries: CompactEntry[];
}

/** Baselines: per stream (updates) or per `user * 65536 + stream` (snapshots). */
export type Baselines = Map<number, number[]>;

function pack32(rows: readonly (readonly number[])[], ids?: readonly [number, number]): Uint8Array {
  const head = ids ? 4 : 0;
  const out = new Uint8Array(head + rows.reduce((n, r) => n + 4 * r.length, 0));
  const view = new DataView(out.buffer);
  if (ids) {
    view.setUint16(0, ids[0], true);
    view.setUint16(2, ids[1], true);
  }
  let o = head;
  for (const r of rows) {
    for (const v of r) {
      view.setInt32(o, v, true);
      o += 4;
    }
  }
  return out;
}

/** A version-1 update frame (11.5), as the reference writes it: a delta entry for
 * every stream `baselines` holds, a relative header when `previous` is given, every
 * Exp-Golomb order the smallest giving the fewest bits. Entries in any order. */
export function encodeUpdateFrame(
  volume: Volume,
  frame: CompactHeader & { entries: readonly { stream: number; offsetMs: number; codes: readonly number[] }[] },
  baselines: ReadonlyMap<number, readonly number[]>,
  previous: CompactHeader | null,
  velocity: boolean,
): Uint8Array {
  const sorted = [...frame.entries].sort((x, y) => x.stream - y.stream);
  const keys = sorted.filter((e) => !baselines.has(e.stream));
  const deltas = sorted.filter((e) => baselines.has(e.stream));
  const out = [CODEC_FRAME_BYTE, 0x10 | FLAG_UPDATE | FLAG_SPLIT | (velocity ? FLAG_VELOCITY : 0) | (previous ? FLAG_RELATIVE : 0)];
  if (previous) {
    const d = BigInt(frame.number) - BigInt(previous.number);
    writeUvarint(out, d >= 0n ? 2n * d : -2n * d - 1n);
    writeSvarint(out, BigInt(frame.baseUs) - BigInt(previous.baseUs));
  } else {
    writeUvarint(out, BigInt(frame.number));
    writeSvarint(out, BigInt(frame.baseUs));
  }
  writeUvarint(out, BigInt(keys.length));
  writeUvarint(out, BigInt(deltas.length));
  if (deltas.length) {
    const crc = crc32(pack32(deltas.map((e) => baselines.get(e.stream)!))) & 0xffff;
    out.push(crc & 0xff, crc >> 8);
  }
  const w = new BitWriter();
  const nibbles: number[] = [];
  const body: (() => void)[] = [];
  const lin = [7, 8, 9];
  const ang = [10, 11, 12];
  const section = (entries: typeof sorted, delta: boolean): void => {
    if (!entries.length) return;
    const sg = entries.map((e, i) => (i ? e.stream - entries[i - 1]!.stream - 1 : e.stream));
    const tFirst = zigzag(entries[0]!.offsetMs);
    const tSame = entries.slice(1).map((e, i) => zigzag(e.offsetMs - entries[i]!.offsetMs));
    const kFirst = bestOrder([tFirst]);
    nibbles.push(kFirst);
    const head = (): void => {
      egColumn(w, sg, 0);
      egColumn(w, [tFirst], kFirst);
      egColumn(w, tSame, 0);
    };
    if (!delta) {
      const kLin = velocity ? bestOrder(entries.flatMap((e) => lin.map((i) => zigzag(e.codes[i]!)))) : 0;
      const kAng = velocity ? bestOrder(entries.flatMap((e) => ang.map((i) => zigzag(e.codes[i]!)))) : 0;
      if (velocity) nibbles.push(kLin, kAng);
      body.push(() => {
        head();
        for (const e of entries) w.write(e.codes[0]!, 2);
        for (let c = 1; c <= 3; c++) for (const e of entries) w.write(e.codes[c]! + M, 13);
        for (let c = 0; c < 3; c++) {
          const bits = volume.bits[c]!;
          for (const e of entries) w.write(e.codes[4 + c]!, bits);
        }
        if (velocity) {
          for (const i of lin) egColumn(w, entries.map((e) => zigzag(e.codes[i]!)), kLin);
          for (const i of ang) egColumn(w, entries.map((e) => zigzag(e.codes[i]!)), kAng);
        }
      });
      return;
    }
    // Delta differences per entry: idx step, then 3 rotation, 3 position (6 velocity).
    const diffs = entries.map((e) => {
      const b = baselines.get(e.stream)!;
      const idx = e.codes[0]!;
      const p = predict(b, idx);
      const d = [
        (((idx - b[0]!) % 4) + 4) % 4,
        zigzag(e.codes[1]! - p[0]),
        zigzag(e.codes[2]! - p[1]),
        zigzag(e.codes[3]! - p[2]),
      ];
      for (let i = 4; i < e.codes.length; i++) d.push(zigzag(e.codes[i]! - b[i]!));
      return d;
    });
    // Class 0: stream 0; class 1: the others (the split flag is always set).
    const members: [number[], number[]] = [[], []];
    entries.forEach((e, i) => members[e.stream === 0 ? 0 : 1].push(i));
    const group = (cols: number[], c: 0 | 1): number[] => {
      const out: number[] = [];
      for (const i of members[c]) for (const j of cols) out.push(diffs[i]![j]!);
      return out;
    };
    const groups: [number[], 0 | 1][] = [
      [[1, 2, 3], 0],
      [[1, 2, 3], 1],
      [[4, 5, 6], 0],
      [[4, 5, 6], 1],
    ];
    if (velocity) groups.push([[7, 8, 9], 0], [[7, 8, 9], 1], [[10, 11, 12], 0], [[10, 11, 12], 1]);
    const orders = groups.map(([cols, c]) => bestOrder(group(cols, c)));
    nibbles.push(...orders);
    body.push(() => {
      head();
      egColumn(w, diffs.map((d) => d[0]!), 0);
      const column = (j: number, k0: number, k1: number): void => {
        egColumn(w, members[0].map((i) => diffs[i]![j]!), k0);
        egColumn(w, members[1].map((i) => diffs[i]![j]!), k1);
      };
      for (const j of [1, 2, 3]) column(j, orders[0]!, orders[1]!);
      for (const j of [4, 5, 6]) column(j, orders[2]!, orders[3]!);
      if (velocity) {
        for (const j of [7, 8, 9]) column(j, orders[4]!, orders[5]!);
        for (const j of [10, 11, 12]) column(j, orders[6]!, orders[7]!);
      }
    });
  };
  section(keys, false);
  section(deltas, true);
  for (let i = 0; i < nibbles.length; i += 2) out.push((nibbles[i]! << 4) | (nibbles[i + 1] ?? 0));
  for (const write of body) write();
  const tail = w.finish();
  const bytes = new Uint8Array(out.length + tail.length);
  bytes.set(out);
  bytes.set(tail, out.length);
  return bytes;
}

interface Head {
  flags: number;
  velocity: boolean;
  number: number;
  baseUs: number;
  nKey: number;
  nDelta: number;
  check: number;
  orders: number[];
  bits: BitReader;
}

function readUvarint(data: Uint8Array, at: { i: number }): bigint {
  let v = 0n;
  for (let n = 0; n < 10; n++) {
    if (at.i >= data.length) throw truncated();
    const byte = data[at.i++]!;
    v |= BigInt(byte & 0x7f) << BigInt(7 * n);
    if (!(byte & 0x80)) return v;
  }
  throw new DecodeError("bad-frame", "varint over 10 bytes");
}

function readHead(data: Uint8Array, expect: "update" | "snapshot", previous: CompactHeader | null): Head {
  if (data[0] !== CODEC_FRAME_BYTE) throw new DecodeError("bad-frame", "not a compact frame");
  if (data.length < 2) throw truncated();
  const flags = data[1]!;
  const version = flags >> 4;
  // The order of docs/protocol.md 11.4: version and flag bits (bad-frame), then the kind.
  const bits = flags & 0x0f;
  if (expect === "update") {
    if (version !== 1) throw new DecodeError("bad-frame", `compact codec version ${version} on an update`);
    if (!(bits & FLAG_UPDATE)) throw new DecodeError("bad-message", "a snapshot frame where an update is expected");
  } else if (version !== 2 || (bits & ~(FLAG_VELOCITY | FLAG_SPLIT)) !== 0) {
    throw new DecodeError("bad-frame", `flags 0x${flags.toString(16)}: no version-2 snapshot`);
  }
  const velocity = (flags & FLAG_VELOCITY) !== 0;
  const at = { i: 2 };
  let number = readUvarint(data, at);
  let base = svarintValue(readUvarint(data, at));
  if (flags & FLAG_RELATIVE) {
    if (!previous) throw new DecodeError("bad-baseline", "a relative header with no update before it");
    number = BigInt(previous.number) + svarintValue(number);
    base = BigInt(previous.baseUs) + base;
    if (number < 0n) throw new DecodeError("bad-baseline", "relative header out of range");
  }
  if (number >= MAX_NUMBER) throw new DecodeError("bad-message", "frame number >= 2^63");
  if (base >= MAX_BASE_US || base <= -MAX_BASE_US) throw new DecodeError("bad-message", "base time out of range");
  const nKey = readUvarint(data, at);
  const nDelta = readUvarint(data, at);
  const left = BigInt((data.length - at.i) * 8);
  if (nKey + nDelta > left) throw new DecodeError("bad-frame", "entry counts the frame cannot hold");
  let check = 0;
  if (nDelta > 0n) {
    const size = version === 1 ? 2 : 4;
    if (at.i + size > data.length) throw truncated();
    for (let k = size - 1; k >= 0; k--) check = check * 256 + data[at.i + k]!;
    at.i += size;
  }
  const count = (nKey ? (velocity ? 3 : 1) : 0) + (nDelta ? (velocity ? 9 : 5) : 0);
  const orders: number[] = [];
  for (let k = 0; k < count; k += 2) {
    if (at.i >= data.length) throw truncated();
    const byte = data[at.i++]!;
    orders.push(byte >> 4);
    if (k + 1 < count) orders.push(byte & 15);
    else if (byte & 15) throw new DecodeError("bad-frame", "non-zero padding nibble");
  }
  return {
    flags, velocity, number: Number(number), baseUs: Number(base), nKey: Number(nKey), nDelta: Number(nDelta),
    check, orders, bits: new BitReader(data, at.i),
  };
}

function rotationAndRest(b: readonly number[], step: number, rot: number[], rest: number[]): number[] {
  const idx = (b[0]! + step) % 4;
  const p = predict(b, idx);
  const codes = [idx, p[0] + unzigzag(rot[0]!), p[1] + unzigzag(rot[1]!), p[2] + unzigzag(rot[2]!)];
  for (let i = 0; i < rest.length; i++) codes.push(b[4 + i]! + unzigzag(rest[i]!));
  return codes;
}

/** Decode a version-1 update frame (11.5) against the stream baselines the relay holds. */
export function decodeUpdateFrame(data: Uint8Array, volume: Volume, baselines: ReadonlyMap<number, readonly number[]>, previous: CompactHeader | null): CompactFrame {
  const h = readHead(data, "update", previous);
  const r = h.bits;
  const width = h.velocity ? 13 : 7;
  const entries: CompactEntry[] = [];
  let o = 0;
  const section = (n: number, delta: boolean): void => {
    if (!n) return;
    const sg = egColumnRead(r, n, 0);
    const kFirst = h.orders[o++]!;
    const first = unzigzag(egColumnRead(r, 1, kFirst)[0]!);
    const same = egColumnRead(r, n - 1, 0).map(unzigzag);
    const streams: number[] = [];
    const offsets: number[] = [first];
    sg.forEach((g, i) => streams.push(i ? streams[i - 1]! + g + 1 : g));
    same.forEach((d) => offsets.push(offsets[offsets.length - 1]! + d));
    const split = (h.flags & FLAG_SPLIT) !== 0;
    const cls = streams.map((s) => (split && s !== 0 ? 1 : 0));
    let rows: number[][];
    if (!delta) {
      const kLin = h.velocity ? h.orders[o++]! : 0;
      const kAng = h.velocity ? h.orders[o++]! : 0;
      rows = streams.map(() => []);
      for (let i = 0; i < n; i++) rows[i]!.push(r.read(2));
      for (let c = 0; c < 3; c++) for (let i = 0; i < n; i++) rows[i]!.push(r.read(13) - M);
      for (let c = 0; c < 3; c++) for (let i = 0; i < n; i++) rows[i]!.push(r.read(volume.bits[c]!));
      if (h.velocity) {
        for (let c = 0; c < 6; c++) {
          const col = egColumnRead(r, n, c < 3 ? kLin : kAng);
          for (let i = 0; i < n; i++) rows[i]!.push(unzigzag(col[i]!));
        }
      }
    } else {
      const orders = h.orders.slice(o, o + (h.velocity ? 8 : 4));
      o += orders.length;
      const steps = egColumnRead(r, n, 0);
      const diff: number[][] = streams.map(() => []);
      const column = (k0: number, k1: number): void => {
        for (const c of [0, 1]) {
          const members = cls.flatMap((x, i) => (x === c ? [i] : []));
          const col = egColumnRead(r, members.length, c ? k1 : k0);
          members.forEach((i, j) => diff[i]!.push(col[j]!));
        }
      };
      for (let j = 0; j < 3; j++) column(orders[0]!, orders[1]!);
      for (let j = 0; j < 3; j++) column(orders[2]!, orders[3]!);
      if (h.velocity) {
        for (let j = 0; j < 3; j++) column(orders[4]!, orders[5]!);
        for (let j = 0; j < 3; j++) column(orders[6]!, orders[7]!);
      }
      rows = streams.map((s, i) => {
        const b = baselines.get(s);
        if (!b || b.length !== width) throw new DecodeError("bad-baseline", `a delta entry for stream ${s}, which has no baseline`);
        return rotationAndRest(b, steps[i]!, diff[i]!.slice(0, 3), diff[i]!.slice(3));
      });
    }
    streams.forEach((s, i) => entries.push({ stream: s, offsetMs: offsets[i]!, codes: rows[i]!, delta }));
  };
  section(h.nKey, false);
  section(h.nDelta, true);
  r.finish();
  if (h.nDelta) {
    const deltas = entries.filter((e) => e.delta).map((e) => baselines.get(e.stream)!);
    if ((crc32(pack32(deltas)) & 0xffff) !== h.check) throw new DecodeError("bad-baseline", "update coded against other baselines (check differs)");
  }
  const seen = new Set<number>();
  for (const e of entries) {
    if (e.stream > 65535 || seen.has(e.stream)) throw new DecodeError("bad-message", `stream ${e.stream} twice or over 65535`);
    seen.add(e.stream);
    if (!codesValid(e.codes, volume)) throw new DecodeError("bad-pose", `stream ${e.stream}: codes out of range`);
    if (Math.abs(e.offsetMs) >= MAX_OFFSET) throw new DecodeError("bad-pose", "time offset out of range");
  }
  entries.sort((x, y) => x.stream - y.stream);
  return { kind: "update", number: h.number, baseUs: h.baseUs, velocity: h.velocity, entries };
}

/** Decode a version-2 snapshot frame (11.6) against this client's snapshot baselines. */
export function decodeSnapshotFrame(data: Uint8Array, volume: Volume, baselines: ReadonlyMap<number, readonly number[]>): CompactFrame {
  const h = readHead(data, "snapshot", null);
  const r = h.bits;
  const width = h.velocity ? 13 : 7;
  if (h.nKey + h.nDelta === 0) throw new DecodeError("bad-message", "a snapshot frame with no entry");
  const entries: CompactEntry[] = [];
  let o = 0;
  const section = (n: number, delta: boolean): void => {
    if (!n) return;
    const kFirst = h.orders[o++]!;
    const orders = h.orders.slice(o, o + (delta ? (h.velocity ? 8 : 4) : h.velocity ? 2 : 0));
    o += orders.length;
    let user = -1;
    let stream = -1;
    let offset = 0;
    for (let i = 0; i < n; i++) {
      const ug = egRead(r, 0);
      const firstOfUser = i === 0 || ug > 0;
      user = i === 0 ? ug : user + ug;
      const sg = egRead(r, 0);
      stream = firstOfUser ? sg : stream + sg + 1;
      offset = firstOfUser ? unzigzag(egRead(r, kFirst)) : offset + unzigzag(egRead(r, 0));
      let codes: number[];
      if (!delta) {
        codes = [r.read(2), r.read(13) - M, r.read(13) - M, r.read(13) - M];
        for (let c = 0; c < 3; c++) codes.push(r.read(volume.bits[c]!));
        if (h.velocity) for (let c = 0; c < 6; c++) codes.push(unzigzag(egRead(r, orders[c < 3 ? 0 : 1]!)));
      } else {
        const cls = firstOfUser ? 0 : 1;
        const step = egRead(r, 0);
        const rot = [0, 1, 2].map(() => egRead(r, orders[cls]!));
        const rest = [0, 1, 2].map(() => egRead(r, orders[2 + cls]!));
        if (h.velocity) {
          for (let c = 0; c < 3; c++) rest.push(egRead(r, orders[4 + cls]!));
          for (let c = 0; c < 3; c++) rest.push(egRead(r, orders[6 + cls]!));
        }
        if (user > 65535 || stream > 65535) throw new DecodeError("bad-message", "an id over 65535");
        const b = baselines.get(user * 65536 + stream);
        if (!b || b.length !== width) throw new DecodeError("bad-baseline", `a delta entry for user ${user} stream ${stream}, which has no baseline`);
        codes = rotationAndRest(b, step, rot, rest);
      }
      entries.push({ user, stream, offsetMs: offset, codes, delta });
    }
  };
  section(h.nKey, false);
  section(h.nDelta, true);
  r.finish();
  const seen = new Set<number>();
  for (const e of entries) {
    if (e.user! > 65535 || e.stream > 65535) throw new DecodeError("bad-message", "an id over 65535");
    const key = e.user! * 65536 + e.stream;
    if (seen.has(key)) throw new DecodeError("bad-message", `user ${e.user} stream ${e.stream} twice in a frame`);
    seen.add(key);
  }
  if (h.nDelta) {
    let x = 0;
    for (const e of entries) if (e.delta) x = (x ^ crc32(pack32([baselines.get(e.user! * 65536 + e.stream)!], [e.user!, e.stream]))) >>> 0;
    if (x !== h.check) throw new DecodeError("bad-baseline", "snapshot coded against other baselines (check differs)");
  }
  for (const e of entries) {
    if (!codesValid(e.codes, volume)) throw new DecodeError("bad-message", `user ${e.user} stream ${e.stream}: codes out of range`);
    if (Math.abs(e.offsetMs) >= MAX_OFFSET) throw new DecodeError("bad-message", "time offset out of range");
  }
  entries.sort((x, y) => x.user! - y.user! || x.stream - y.stream);
  return { kind: "snapshot", number: h.number, baseUs: h.baseUs, velocity: h.velocity, entries };
}

// ---------------------------------------------------------------------------
// One connection's codec state

/** Compact coding of one connection: updates out, snapshots in, each with its baselines. */
export class CompactSession {
  readonly volume: Volume;
  readonly up: Baselines = new Map();
  readonly down: Baselines = new Map();
  private previous: CompactHeader | null = null;

  /** `volume`: welcome.volume; `velocities`: updates carry velocities (join.sends_velocities). */
  constructor(
    volume: readonly number[],
    readonly velocities: boolean,
  ) {
    this.volume = new Volume(volume);
  }

  isCompact(data: Uint8Array): boolean {
    return data[0] === CODEC_FRAME_BYTE;
  }

  /** bad-pose UsageError unless `pose`'s position is in the room volume. */
  checkVolume(name: string, pose: Pose): void {
    for (let i = 0; i < 3; i++) {
      const c = roundHalfEven((Math.fround(pose[i]!) - this.volume.lo[i]!) / this.volume.step[i]!);
      if (!(c >= 0 && c <= this.volume.max(i))) {
        throw new UsageError("bad-pose", `${name}: position ${pose[i]} outside the room volume on axis ${"xyz"[i]}`);
      }
    }
  }

  /** An update frame of `entries` (capture times in server time), base time `time`;
   * every entry becomes its stream's baseline. */
  encodeUpdate(seq: number, time: number, entries: readonly PoseEntry[]): Uint8Array {
    const baseUs = roundHalfEven(time * 1e6);
    const base = baseUs / 1e6;
    const coded = entries.map((e) => ({
      stream: e.stream,
      offsetMs: roundHalfEven((base - e.capture) * 1000),
      codes: poseCodes(e.pose, this.volume, this.velocities ? (e.velocity ?? [0, 0, 0, 0, 0, 0]) : null),
    }));
    const header = { number: seq, baseUs };
    const frame = encodeUpdateFrame(this.volume, { ...header, entries: coded }, this.up, this.previous, this.velocities);
    for (const e of coded) this.up.set(e.stream, e.codes);
    this.previous = header;
    return frame;
  }

  /** A snapshot frame as a Snapshot (capture times in server time, poses float32). */
  decodeSnapshot(data: Uint8Array): Snapshot {
    const frame = decodeSnapshotFrame(data, this.volume, this.down);
    const base = frame.baseUs / 1e6;
    const entries: PoseEntry[] = frame.entries.map((e) => {
      this.down.set(e.user! * 65536 + e.stream, e.codes);
      const { pose, velocity } = codesToPose(e.codes, this.volume);
      const entry: PoseEntry = { user: e.user!, stream: e.stream, capture: base - e.offsetMs / 1000, pose };
      if (velocity) entry.velocity = velocity as PoseEntry["velocity"];
      return entry;
    });
    return { type: "snapshot", tick: frame.number, time: base, entries };
  }
}
