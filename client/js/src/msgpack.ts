/**
 * msgpack, the subset posecast uses (nil, bool, int, float, str, bin, array, map).
 *
 * The writer chooses every number's encoding itself: integers in their smallest
 * form, fields the protocol types as float always as float64 (as the relay's
 * encoder writes a float, even 20.0): the canonical encoding of docs/protocol.md
 * section 3, so the golden vectors' client frames are reproduced byte for byte.
 * The reader keeps floats apart from ints (`F64`), since an int field given a
 * float is refused.
 */

/** A number to be written as a float64 even when it is integral. */
export class F64 {
  constructor(readonly value: number) {}
}

export type Packable =
  | null
  | undefined
  | boolean
  | number
  | F64
  | string
  | Uint8Array
  | readonly Packable[]
  | { readonly [key: string]: Packable };

const textEncoder = new TextEncoder();

export class Writer {
  private buf: Uint8Array;
  private view: DataView;
  length = 0;

  constructor(capacity = 256) {
    this.buf = new Uint8Array(capacity);
    this.view = new DataView(this.buf.buffer);
  }

  private reserve(n: number): void {
    if (this.length + n <= this.buf.length) return;
    let size = this.buf.length * 2;
    while (size < this.length + n) size *= 2;
    const next = new Uint8Array(size);
    next.set(this.buf.subarray(0, this.length));
    this.buf = next;
    this.view = new DataView(next.buffer);
  }

  bytes(): Uint8Array {
    return this.buf.slice(0, this.length);
  }

  u8(x: number): void {
    this.reserve(1);
    this.buf[this.length++] = x;
  }

  raw(data: Uint8Array): void {
    this.reserve(data.length);
    this.buf.set(data, this.length);
    this.length += data.length;
  }

  private head(tag: number, n: number, bytes: 1 | 2 | 4 | 8): void {
    this.reserve(1 + bytes);
    this.buf[this.length++] = tag;
    const v = this.view;
    const at = this.length;
    if (bytes === 1) v.setUint8(at, n);
    else if (bytes === 2) v.setUint16(at, n);
    else if (bytes === 4) v.setUint32(at, n);
    else v.setBigUint64(at, BigInt(n));
    this.length += bytes;
  }

  int(n: number): void {
    if (!Number.isSafeInteger(n)) throw new RangeError(`not a safe integer: ${n}`);
    if (n >= 0) {
      if (n < 0x80) this.u8(n);
      else if (n <= 0xff) this.head(0xcc, n, 1);
      else if (n <= 0xffff) this.head(0xcd, n, 2);
      else if (n <= 0xffffffff) this.head(0xce, n, 4);
      else this.head(0xcf, n, 8);
      return;
    }
    this.reserve(9);
    const v = this.view;
    if (n >= -32) {
      this.buf[this.length++] = n & 0xff;
    } else if (n >= -0x80) {
      this.buf[this.length++] = 0xd0;
      v.setInt8(this.length, n);
      this.length += 1;
    } else if (n >= -0x8000) {
      this.buf[this.length++] = 0xd1;
      v.setInt16(this.length, n);
      this.length += 2;
    } else if (n >= -0x80000000) {
      this.buf[this.length++] = 0xd2;
      v.setInt32(this.length, n);
      this.length += 4;
    } else {
      this.buf[this.length++] = 0xd3;
      v.setBigInt64(this.length, BigInt(n));
      this.length += 8;
    }
  }

  float(x: number): void {
    this.reserve(9);
    this.buf[this.length++] = 0xcb;
    this.view.setFloat64(this.length, x);
    this.length += 8;
  }

  str(s: string): void {
    const data = textEncoder.encode(s);
    const n = data.length;
    if (n < 32) this.u8(0xa0 | n);
    else if (n <= 0xff) this.head(0xd9, n, 1);
    else if (n <= 0xffff) this.head(0xda, n, 2);
    else this.head(0xdb, n, 4);
    this.raw(data);
  }

  bin(data: Uint8Array): void {
    const n = data.length;
    if (n <= 0xff) this.head(0xc4, n, 1);
    else if (n <= 0xffff) this.head(0xc5, n, 2);
    else this.head(0xc6, n, 4);
    this.raw(data);
  }

  arrayHead(n: number): void {
    if (n < 16) this.u8(0x90 | n);
    else if (n <= 0xffff) this.head(0xdc, n, 2);
    else this.head(0xdd, n, 4);
  }

  mapHead(n: number): void {
    if (n < 16) this.u8(0x80 | n);
    else if (n <= 0xffff) this.head(0xde, n, 2);
    else this.head(0xdf, n, 4);
  }

  /** Any value: integral numbers as ints, others as float64, F64 as float64. */
  any(x: Packable): void {
    if (x === null || x === undefined) this.u8(0xc0);
    else if (x === true) this.u8(0xc3);
    else if (x === false) this.u8(0xc2);
    else if (typeof x === "number") {
      if (Number.isSafeInteger(x)) this.int(x);
      else this.float(x);
    } else if (x instanceof F64) this.float(x.value);
    else if (typeof x === "string") this.str(x);
    else if (x instanceof Uint8Array) this.bin(x);
    else if (Array.isArray(x)) {
      this.arrayHead(x.length);
      for (const item of x as readonly Packable[]) this.any(item);
    } else {
      const entries = Object.entries(x as { [key: string]: Packable });
      this.mapHead(entries.length);
      for (const [k, v] of entries) {
        this.str(k);
        this.any(v);
      }
    }
  }
}

/** msgpack bytes of a value (see Writer.any). */
export function pack(x: Packable): Uint8Array {
  const w = new Writer();
  w.any(x);
  return w.bytes();
}

const textDecoder = new TextDecoder("utf-8", { fatal: true });

/** Why a msgpack frame could not be read (the caller turns it into bad-frame). */
export class MsgpackError extends Error {}

/**
 * Read one msgpack value that fills `data` exactly. Floats come back as `F64`
 * (so a schema can tell `3.0` from `3`), ints as numbers, bin as Uint8Array,
 * maps as plain objects (string keys only). Every length is checked against the
 * bytes present before anything is allocated.
 */
export function unpack(data: Uint8Array, maxDepth = 64): Packable {
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  let at = 0;
  const need = (n: number): void => {
    if (at + n > data.length) throw new MsgpackError("truncated");
  };
  const u = (n: 1 | 2 | 4): number => {
    need(n);
    const v = n === 1 ? view.getUint8(at) : n === 2 ? view.getUint16(at) : view.getUint32(at);
    at += n;
    return v;
  };
  const bytes = (n: number): Uint8Array => {
    need(n);
    const out = data.subarray(at, at + n);
    at += n;
    return out;
  };
  const read = (depth: number): Packable => {
    if (depth > maxDepth) throw new MsgpackError("nested too deep");
    const tag = u(1);
    if (tag < 0x80) return tag;
    if (tag >= 0xe0) return tag - 0x100;
    if (tag <= 0x8f) return map(tag & 0x0f, depth);
    if (tag <= 0x9f) return array(tag & 0x0f, depth);
    if (tag <= 0xbf) return str(tag & 0x1f);
    switch (tag) {
      case 0xc0: return null;
      case 0xc2: return false;
      case 0xc3: return true;
      case 0xc4: return bytes(u(1)).slice();
      case 0xc5: return bytes(u(2)).slice();
      case 0xc6: return bytes(u(4)).slice();
      case 0xca: need(4); at += 4; return new F64(view.getFloat32(at - 4));
      case 0xcb: need(8); at += 8; return new F64(view.getFloat64(at - 8));
      case 0xcc: return u(1);
      case 0xcd: return u(2);
      case 0xce: return u(4);
      case 0xcf: need(8); at += 8; return Number(view.getBigUint64(at - 8));
      case 0xd0: need(1); at += 1; return view.getInt8(at - 1);
      case 0xd1: need(2); at += 2; return view.getInt16(at - 2);
      case 0xd2: need(4); at += 4; return view.getInt32(at - 4);
      case 0xd3: need(8); at += 8; return Number(view.getBigInt64(at - 8));
      case 0xd9: return str(u(1));
      case 0xda: return str(u(2));
      case 0xdb: return str(u(4));
      case 0xdc: return array(u(2), depth);
      case 0xdd: return array(u(4), depth);
      case 0xde: return map(u(2), depth);
      case 0xdf: return map(u(4), depth);
      default: throw new MsgpackError(`msgpack type 0x${tag.toString(16)} is not used by posecast`);
    }
  };
  const str = (n: number): string => {
    try {
      return textDecoder.decode(bytes(n));
    } catch (err) {
      if (err instanceof MsgpackError) throw err;
      throw new MsgpackError("invalid UTF-8");
    }
  };
  const array = (n: number, depth: number): Packable[] => {
    need(n); // every element takes at least a byte
    const out: Packable[] = [];
    for (let i = 0; i < n; i++) out.push(read(depth + 1));
    return out;
  };
  const map = (n: number, depth: number): { [key: string]: Packable } => {
    need(2 * n);
    const out: { [key: string]: Packable } = {};
    for (let i = 0; i < n; i++) {
      const key = read(depth + 1);
      if (typeof key !== "string") throw new MsgpackError("a map key is not a string");
      // defineProperty: a "__proto__" key is data, never the prototype.
      Object.defineProperty(out, key, { value: read(depth + 1), enumerable: true, writable: true, configurable: true });
    }
    return out;
  };
  const value = read(0);
  if (at !== data.length) throw new MsgpackError("trailing bytes after frame");
  return value;
}

/** `x` with every F64 replaced by its number (for free-form payloads). */
export function plain(x: Packable): unknown {
  if (x instanceof F64) return x.value;
  if (Array.isArray(x)) return x.map((v: Packable) => plain(v));
  if (x && typeof x === "object" && !(x instanceof Uint8Array)) {
    const out: Record<string, unknown> = {};
    for (const [k, v] of Object.entries(x)) Object.defineProperty(out, k, { value: plain(v), enumerable: true, writable: true, configurable: true });
    return out;
  }
  return x;
}
