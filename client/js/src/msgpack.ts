/**
 * A small msgpack writer that chooses every number's encoding itself: integers in
 * their smallest form, and fields the protocol types as float always as float64
 * (as Python's msgpack writes a float, even 20.0). Byte-for-byte what the relay's
 * encoder writes, so the golden vectors' client frames can be reproduced.
 * Decoding is `@msgpack/msgpack`'s.
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
