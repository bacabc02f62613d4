/**
 * Control messages and raw pose frames: one msgpack map per websocket frame.
 *
 * Every control message is `{"type": TYPE, field: value, ...}` with its fields in
 * the order of the table below. Fields marked `omit` are left out while they hold
 * their default; the others are always written (null as nil): the canonical
 * encoding of docs/protocol.md section 3. Decoding checks every field's type (a
 * float where an int belongs is refused), fills defaults, and refuses unknown
 * fields (`bad-message`), as the spec says.
 */
import { DecodeError } from "./errors.js";
import { F64, MsgpackError, plain, unpack, Writer } from "./msgpack.js";
import type { Packable } from "./msgpack.js";

export type Pose = [number, number, number, number, number, number, number];
export type Vec3 = [number, number, number];

/** The default room volume (welcome.volume absent): min x, y, z, max x, y, z. */
export const DEFAULT_VOLUME: readonly number[] = [-8, -2, -8, 8, 4, 8];
export const PROTOCOL_VERSION = 1;
/** The user id of every shared object's stream in snapshots. */
export const ROOM_USER = 65535;

type Kind =
  | "int"
  | "float"
  | "rate" // float, or the string "auto" (join.rate)
  | "str"
  | "bool"
  | "strs" // list of strings
  | "ids" // map name -> stream id
  | "pose" // 7 floats
  | "vec3" // 3 floats
  | "volume" // 6 floats
  | "map"; // any msgpack map

interface FieldSpec {
  name: string;
  kind: Kind;
  /** Absent from the map: required. */
  def?: unknown;
  nullable?: boolean;
  /** Left out of the map while it equals its default. */
  omit?: boolean;
}

function f(name: string, kind: Kind, opts: Partial<FieldSpec> = {}): FieldSpec {
  return { name, kind, ...opts };
}

const OPT_NULL = { def: null, nullable: true };
const OMIT_FALSE = { def: false, omit: true };
const OMIT_NULL = { def: null, nullable: true, omit: true };

/** Every control message type and its fields, in wire order. */
export const SCHEMAS: Readonly<Record<string, readonly FieldSpec[]>> = {
  hello: [
    f("version", "int", { def: PROTOCOL_VERSION }),
    f("agent", "str", { def: "" }),
    f("resumable", "bool", OMIT_FALSE),
    f("resume", "str", OMIT_NULL),
    f("wants_retry_after", "bool", OMIT_FALSE),
  ],
  welcome: [
    f("user", "int"),
    f("server_time", "float"),
    f("version", "int", { def: PROTOCOL_VERSION }),
    f("min_rate", "float", { def: 5 }),
    f("max_rate", "float", { def: 30 }),
    f("max_streams", "int", { def: 16 }),
    f("volume", "volume", { def: DEFAULT_VOLUME, omit: true }),
    f("resume", "str", OMIT_NULL),
    f("resumed", "bool", OMIT_FALSE),
  ],
  join: [
    f("room", "str"),
    f("streams", "strs"),
    f("rate", "rate"),
    f("token", "str", OPT_NULL),
    f("label", "str", OPT_NULL),
    f("sends_velocities", "bool", OMIT_FALSE),
    f("wants_velocities", "bool", OMIT_FALSE),
    f("codec", "str", { def: "raw", omit: true }),
    f("echo", "bool", OMIT_FALSE),
    f("spectator", "bool", OMIT_FALSE),
    f("max_rate", "float", OMIT_NULL),
    f("budget_deg", "float", OMIT_NULL),
  ],
  joined: [
    f("room", "str"),
    f("streams", "ids"),
    f("rate", "float"),
    f("objects", "ids", { def: {}, omit: true }),
  ],
  peer_joined: [
    f("user", "int"),
    f("streams", "ids"),
    f("label", "str", OPT_NULL),
    f("velocities", "bool", OMIT_FALSE),
  ],
  peer_left: [f("user", "int"), f("reason", "str", { def: "" })],
  peer_stalled: [f("user", "int")],
  peer_resumed: [f("user", "int")],
  ping: [f("seq", "int"), f("time", "float")],
  pong: [f("seq", "int"), f("ping_time", "float"), f("recv_time", "float"), f("send_time", "float")],
  set_rate: [f("rate", "float")],
  rate: [f("rate", "float")],
  renew: [f("token", "str")],
  event: [
    f("kind", "str"),
    f("stream", "int", OPT_NULL),
    f("user", "int", OPT_NULL),
    f("time", "float", OPT_NULL),
    f("payload", "map", { def: {} }),
  ],
  error: [
    f("code", "str"),
    f("message", "str"),
    f("fatal", "bool", { def: false }),
    f("in_reply_to", "str", OPT_NULL),
    f("retry_after", "float", OMIT_NULL),
  ],
  bye: [f("reason", "str", { def: "" })],
  object_create: [
    f("name", "str"),
    f("pose", "pose"),
    f("keep", "bool", { def: true }),
    f("steal", "bool", OMIT_FALSE),
    f("hold", "bool", OMIT_FALSE),
    f("time", "float", OMIT_NULL),
  ],
  request_ownership: [f("stream", "int"), f("steal", "bool", OMIT_FALSE), f("lock", "bool", OMIT_FALSE)],
  release: [f("stream", "int"), f("velocity", "vec3", OMIT_NULL), f("angular", "vec3", OMIT_NULL)],
  object: [
    f("name", "str"),
    f("stream", "int"),
    f("pose", "pose"),
    f("time", "float"),
    f("creator", "int"),
    f("owner", "int", OPT_NULL),
    f("keep", "bool", { def: true }),
    f("steal", "bool", OMIT_FALSE),
    f("locked", "bool", OMIT_FALSE),
  ],
  owner: [
    f("stream", "int"),
    f("owner", "int", { nullable: true }),
    f("previous", "int", { nullable: true }),
    f("reason", "str"),
    f("time", "float"),
    f("locked", "bool", OMIT_FALSE),
    f("velocity", "vec3", OMIT_NULL),
    f("angular", "vec3", OMIT_NULL),
  ],
  object_removed: [f("stream", "int"), f("reason", "str", { def: "" })],
};

// Typed views of the messages (snake_case keys, as on the wire).
export interface Hello { type: "hello"; version?: number; agent?: string; resumable?: boolean; resume?: string | null; wants_retry_after?: boolean }
export interface Welcome {
  type: "welcome"; user: number; server_time: number; version: number; min_rate: number;
  max_rate: number; max_streams: number; volume: number[]; resume: string | null; resumed: boolean;
}
/** `join.rate`: a number of Hz, or "auto" (the relay chooses; section 5.5 of the spec). */
export type JoinRate = number | "auto";
export interface Join {
  type: "join"; room: string; streams: string[]; rate: JoinRate; token?: string | null;
  label?: string | null; sends_velocities?: boolean; wants_velocities?: boolean;
  codec?: "raw" | "compact"; echo?: boolean; spectator?: boolean;
  /** With rate "auto" only: the highest rate the relay may choose (Hz; null: the welcome's). */
  max_rate?: number | null;
  /** An error budget in degrees of visual angle, in (0, 90): the relay may send each peer
   * at the lowest rate whose expected error seen from this client's head stays within it
   * (section 5.6 of the spec). null: every peer at the snapshot rate. */
  budget_deg?: number | null;
}
export interface Joined { type: "joined"; room: string; streams: Record<string, number>; rate: number; objects: Record<string, number> }
export interface PeerJoined { type: "peer_joined"; user: number; streams: Record<string, number>; label: string | null; velocities: boolean }
export interface PeerLeft { type: "peer_left"; user: number; reason: string }
export interface PeerStalled { type: "peer_stalled"; user: number }
export interface PeerResumed { type: "peer_resumed"; user: number }
export interface Ping { type: "ping"; seq: number; time: number }
export interface Pong { type: "pong"; seq: number; ping_time: number; recv_time: number; send_time: number }
export interface SetRate { type: "set_rate"; rate: number }
/** The rate the relay chose now for a client that joined with rate "auto". */
export interface RateNotice { type: "rate"; rate: number }
export interface Renew { type: "renew"; token: string }
export interface UserEvent {
  type: "event"; kind: "grab" | "release" | "button" | "scene_step" | string; stream?: number | null;
  user?: number | null; time?: number | null; payload?: Record<string, unknown>;
}
export interface ErrorMessage { type: "error"; code: string; message: string; fatal: boolean; in_reply_to: string | null; retry_after?: number | null }
export interface Bye { type: "bye"; reason?: string }
export interface ObjectCreate {
  type: "object_create"; name: string; pose: Pose; keep?: boolean; steal?: boolean; hold?: boolean; time?: number | null;
}
export interface RequestOwnership { type: "request_ownership"; stream: number; steal?: boolean; lock?: boolean }
export interface Release { type: "release"; stream: number; velocity?: Vec3 | null; angular?: Vec3 | null }
export interface ObjectInfo {
  type: "object"; name: string; stream: number; pose: Pose; time: number; creator: number;
  owner: number | null; keep: boolean; steal: boolean; locked: boolean;
}
export interface Owner {
  type: "owner"; stream: number; owner: number | null; previous: number | null; reason: string;
  time: number; locked: boolean; velocity: Vec3 | null; angular: Vec3 | null;
}
export interface ObjectRemoved { type: "object_removed"; stream: number; reason: string }

export type ControlMessage =
  | Hello | Welcome | Join | Joined | PeerJoined | PeerLeft | PeerStalled | PeerResumed | Ping
  | Pong | SetRate | RateNotice | Renew | UserEvent | ErrorMessage | Bye | ObjectCreate | RequestOwnership
  | Release | ObjectInfo | Owner | ObjectRemoved;

/** One pose of a pose frame: who, which stream, when (server clock) and where. */
export interface PoseEntry {
  /** The publishing user (snapshots; updates: -1). */
  user: number;
  stream: number;
  /** Capture time, server clock, seconds. */
  capture: number;
  pose: Pose;
  /** Linear (m/s) then angular (rad/s) velocity, world frame; velocity variant only. */
  velocity?: [number, number, number, number, number, number];
}

export interface PoseUpdate { type: "update"; seq: number; time: number; entries: PoseEntry[] }
export interface Snapshot { type: "snapshot"; tick: number; time: number; entries: PoseEntry[] }

export type Message = ControlMessage | PoseUpdate | Snapshot;

function sameValue(a: unknown, b: unknown): boolean {
  if (a === b) return true;
  if (Array.isArray(a) && Array.isArray(b)) return a.length === b.length && a.every((x, i) => x === b[i]);
  if (a && b && typeof a === "object" && typeof b === "object") {
    const ka = Object.keys(a);
    return ka.length === Object.keys(b).length && ka.length === 0;
  }
  return false;
}

function writeField(w: Writer, spec: FieldSpec, value: unknown): void {
  if (value === null || value === undefined) {
    w.u8(0xc0);
    return;
  }
  switch (spec.kind) {
    case "int":
      w.int(value as number);
      return;
    case "float":
      w.float(value as number);
      return;
    case "rate":
      if (typeof value === "string") w.str(value);
      else w.float(value as number);
      return;
    case "str":
      w.str(value as string);
      return;
    case "bool":
      w.u8(value ? 0xc3 : 0xc2);
      return;
    case "strs": {
      const list = value as string[];
      w.arrayHead(list.length);
      for (const s of list) w.str(s);
      return;
    }
    case "ids": {
      const entries = Object.entries(value as Record<string, number>);
      w.mapHead(entries.length);
      for (const [k, v] of entries) {
        w.str(k);
        w.int(v);
      }
      return;
    }
    case "pose":
    case "vec3":
    case "volume": {
      const list = value as number[];
      w.arrayHead(list.length);
      for (const x of list) w.float(x);
      return;
    }
    case "map":
      w.any(value as never);
      return;
  }
}

/** The frame bytes of a control message (fields in wire order, defaults filled). */
export function encodeControl(message: ControlMessage): Uint8Array {
  const schema = SCHEMAS[message.type];
  if (!schema) throw new DecodeError("unknown-type", `unknown message type ${message.type}`);
  const m = message as unknown as Record<string, unknown>;
  const present: [FieldSpec, unknown][] = [];
  for (const spec of schema) {
    let value = m[spec.name];
    if (value === undefined) {
      if (!("def" in spec)) throw new DecodeError("bad-message", `${message.type} lacks field '${spec.name}'`);
      value = spec.def;
    }
    if (spec.omit && sameValue(value, spec.def)) continue;
    present.push([spec, value]);
  }
  const w = new Writer(64);
  w.mapHead(present.length + 1);
  w.str("type");
  w.str(message.type);
  for (const [spec, value] of present) {
    w.str(spec.name);
    writeField(w, spec, value);
  }
  return w.bytes();
}

function bad(where: string, why: string): DecodeError {
  return new DecodeError("bad-message", `${where} ${why}`);
}

/** A float field's value: any int within +-2^53 or float, finite; else undefined. */
function floatValue(x: unknown): number | undefined {
  const v = x instanceof F64 ? x.value : x;
  if (typeof v !== "number" || !Number.isFinite(v)) return undefined;
  if (!(x instanceof F64) && Math.abs(v) > 2 ** 53) return undefined;
  return v;
}

function isNumber(x: unknown): boolean {
  return floatValue(x) !== undefined;
}

function checkField(type: string, spec: FieldSpec, value: unknown): unknown {
  const where = `${type}.${spec.name}`;
  if (value === null) {
    if (spec.nullable) return null;
    throw bad(where, "must not be nil");
  }
  const floats = (n: number): number[] => {
    if (!Array.isArray(value) || value.length !== n || !value.every(isNumber)) throw bad(where, `must be ${n} numbers`);
    return value.map((x) => floatValue(x)!);
  };
  switch (spec.kind) {
    case "int":
      if (typeof value !== "number" || !Number.isInteger(value) || value < 0) throw bad(where, "must be an int >= 0");
      return value;
    case "float": {
      const v = floatValue(value);
      if (v === undefined) throw bad(where, "must be a finite number");
      return v;
    }
    case "rate": {
      if (value === "auto") return value;
      const v = floatValue(value);
      if (v === undefined) throw bad(where, 'must be a finite number or "auto"');
      return v;
    }
    case "str":
      if (typeof value !== "string") throw bad(where, "must be a string");
      return value;
    case "bool":
      if (typeof value !== "boolean") throw bad(where, "must be a bool");
      return value;
    case "strs":
      if (!Array.isArray(value) || !value.every((s) => typeof s === "string")) throw bad(where, "must be a list of strings");
      return value;
    case "ids": {
      if (!value || typeof value !== "object" || Array.isArray(value) || value instanceof Uint8Array) throw bad(where, "must be a map");
      for (const v of Object.values(value)) {
        if (typeof v !== "number" || !Number.isInteger(v) || v < 0 || v > 65535) throw bad(where, "must map names to u16 ids");
      }
      return value;
    }
    case "pose":
      return floats(7);
    case "vec3":
      return floats(3);
    case "volume":
      return floats(6);
    case "map":
      if (!value || typeof value !== "object" || Array.isArray(value) || value instanceof Uint8Array || value instanceof F64) throw bad(where, "must be a map");
      return plain(value as Packable);
  }
}

const RECORD_SIZES = {
  update: { plain: 34, velocity: 46, head: 2 },
  snapshot: { plain: 36, velocity: 48, head: 4 },
} as const;

/** Whole-frame decode: a control message, or a raw pose frame (`poses`/`vpose` records). */
export function decodeMessage(data: Uint8Array): Message {
  if (data.length > 64 * 1024) throw new DecodeError("frame-too-large", `frame of ${data.length} bytes`);
  let wire: unknown;
  try {
    wire = unpack(data);
  } catch (err) {
    if (err instanceof MsgpackError) throw new DecodeError("bad-frame", `not a msgpack frame: ${err.message}`);
    throw err;
  }
  if (!wire || typeof wire !== "object" || Array.isArray(wire) || wire instanceof Uint8Array || wire instanceof F64) {
    throw new DecodeError("bad-frame", "frame is not a map");
  }
  const map = wire as Record<string, unknown>;
  const type = map.type;
  if (typeof type !== "string") throw new DecodeError("bad-frame", "frame has no string type");
  if (type === "update" || type === "snapshot") return decodePoseFrame(map, type);
  const schema = SCHEMAS[type];
  if (!schema) throw new DecodeError("unknown-type", `unknown type '${type.slice(0, 32)}'`);
  if ((type === "hello" || type === "welcome") && map.version !== undefined && map.version !== PROTOCOL_VERSION) {
    throw new DecodeError("version-mismatch", `${type} for version ${String(map.version).slice(0, 16)}, this is ${PROTOCOL_VERSION}`);
  }
  const out: Record<string, unknown> = { type };
  for (const key of Object.keys(map)) {
    if (key !== "type" && !schema.some((spec) => spec.name === key)) throw bad(type, `has unknown field '${key.slice(0, 32)}'`);
  }
  for (const spec of schema) {
    if (!(spec.name in map)) {
      if (!("def" in spec)) throw bad(type, `lacks field '${spec.name}'`);
      out[spec.name] = spec.def;
      continue;
    }
    out[spec.name] = checkField(type, spec, map[spec.name]);
  }
  return out as unknown as ControlMessage;
}

function decodePoseFrame(map: Record<string, unknown>, type: "update" | "snapshot"): PoseUpdate | Snapshot {
  const counter = type === "update" ? "seq" : "tick";
  const velocity = "vpose" in map;
  const body = map[velocity ? "vpose" : "poses"];
  if (!(body instanceof Uint8Array)) throw bad(type, "needs poses (or vpose) as bin");
  const keys = Object.keys(map).sort().join(",");
  const plainKeys = ["type", counter, "time", "poses"].sort().join(",");
  const velocityKeys = ["type", counter, "time", "vpose"].sort().join(",");
  if (keys !== plainKeys && keys !== velocityKeys) throw bad(type, `needs exactly ${counter}, time and poses (or vpose)`);
  const n = map[counter];
  const time = floatValue(map.time);
  if (typeof n !== "number" || !Number.isInteger(n) || n < 0) throw bad(`${type}.${counter}`, "must be an int >= 0");
  if (time === undefined) throw bad(`${type}.time`, "must be a finite number");
  const sizes = RECORD_SIZES[type];
  const size = velocity ? sizes.velocity : sizes.plain;
  if (body.length % size) throw bad(type, `records are not whole ${size}-byte records`);
  const view = new DataView(body.buffer, body.byteOffset, body.byteLength);
  const entries: PoseEntry[] = [];
  for (let at = 0; at < body.length; at += size) {
    let o = at;
    const user = type === "snapshot" ? view.getUint16(o, true) : -1;
    if (type === "snapshot") o += 2;
    const stream = view.getUint16(o, true);
    const dt = view.getFloat32(o + 2, true);
    o += 6;
    const pose = [0, 0, 0, 0, 0, 0, 0] as Pose;
    for (let i = 0; i < 7; i++) pose[i] = view.getFloat32(o + 4 * i, true);
    const entry: PoseEntry = { user, stream, capture: time + dt, pose };
    if (velocity) {
      o += 28;
      const v = [0, 0, 0, 0, 0, 0] as [number, number, number, number, number, number];
      for (let i = 0; i < 6; i++) v[i] = float16(view.getUint16(o + 2 * i, true));
      entry.velocity = v;
    }
    entries.push(entry);
  }
  return type === "update"
    ? { type, seq: n, time, entries }
    : { type, tick: n, time, entries };
}

/** float16 bits to a number. */
export function float16(bits: number): number {
  const sign = bits & 0x8000 ? -1 : 1;
  const exp = (bits >> 10) & 0x1f;
  const frac = bits & 0x3ff;
  if (exp === 0) return sign * frac * 2 ** -24;
  if (exp === 31) return frac ? NaN : sign * Infinity;
  return sign * (1 + frac / 1024) * 2 ** (exp - 15);
}

/** A number to float16 bits (round to nearest even), clamped to +-65504 when finite. */
export function toFloat16(x: number): number {
  if (Number.isNaN(x)) return 0x7e00;
  if (x === Infinity) return 0x7c00;
  if (x === -Infinity) return 0xfc00;
  x = Math.max(-65504, Math.min(65504, x));
  const sign = x < 0 || Object.is(x, -0) ? 0x8000 : 0;
  // Round through float64 exactly: value / ulp, then round half to even.
  const a = Math.abs(x);
  if (a < 2 ** -14) {
    const m = roundEven(a / 2 ** -24);
    return sign | m; // m may reach 1024: the smallest normal, bits carry over correctly
  }
  let e = Math.floor(Math.log2(a));
  if (2 ** e > a) e -= 1;
  if (2 ** (e + 1) <= a) e += 1;
  let m = roundEven((a / 2 ** e - 1) * 1024);
  if (m === 1024) {
    m = 0;
    e += 1;
  }
  return sign | ((e + 15) << 10) | m;
}

function roundEven(x: number): number {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

/** A raw `update` frame: one record per stream, `time` its base (dt = capture - time). */
export function encodeUpdate(seq: number, time: number, entries: readonly PoseEntry[], velocities = false): Uint8Array {
  const size = velocities ? 46 : 34;
  const body = new Uint8Array(entries.length * size);
  const view = new DataView(body.buffer);
  let o = 0;
  for (const e of entries) {
    view.setUint16(o, e.stream, true);
    view.setFloat32(o + 2, e.capture - time, true);
    for (let i = 0; i < 7; i++) view.setFloat32(o + 6 + 4 * i, e.pose[i]!, true);
    if (velocities) {
      const v = e.velocity ?? [0, 0, 0, 0, 0, 0];
      for (let i = 0; i < 6; i++) view.setUint16(o + 34 + 2 * i, toFloat16(v[i]!), true);
    }
    o += size;
  }
  const w = new Writer(body.length + 48);
  w.mapHead(4);
  w.str("type");
  w.str("update");
  w.str("seq");
  w.int(seq);
  w.str("time");
  w.float(time);
  w.str(velocities ? "vpose" : "poses");
  w.bin(body);
  return w.bytes();
}

/** A raw `snapshot` frame (what the relay sends; for tests and replay tools). */
export function encodeSnapshot(tick: number, time: number, entries: readonly PoseEntry[]): Uint8Array {
  const body = new Uint8Array(entries.length * 36);
  const view = new DataView(body.buffer);
  let o = 0;
  for (const e of entries) {
    view.setUint16(o, e.user, true);
    view.setUint16(o + 2, e.stream, true);
    view.setFloat32(o + 4, e.capture - time, true);
    for (let i = 0; i < 7; i++) view.setFloat32(o + 8 + 4 * i, e.pose[i]!, true);
    o += 36;
  }
  const w = new Writer(body.length + 48);
  w.mapHead(4);
  w.str("type");
  w.str("snapshot");
  w.str("tick");
  w.int(tick);
  w.str("time");
  w.float(time);
  w.str("poses");
  w.bin(body);
  return w.bytes();
}

export { F64 };
