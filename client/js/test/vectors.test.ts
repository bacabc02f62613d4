// Every golden vector of protocol/vectors/ (docs/protocol.md section 14), both ways:
// decode equals what the vector states; the client's frames encode to the same bytes.
import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync, readdirSync } from "node:fs";
import { decodeMessage, encodeControl } from "../src/messages.js";
import type { ControlMessage } from "../src/messages.js";
import { DecodeError, ERROR_CODES } from "../src/errors.js";
import { Volume, codesToPose, decodeSnapshotFrame, decodeUpdateFrame, encodeUpdateFrame } from "../src/compact.js";
import type { CompactHeader } from "../src/compact.js";

const DIR = new URL("../../../protocol/vectors/", import.meta.url);

interface Entry {
  user?: number;
  stream: number;
  dt?: number;
  offset_ms?: number;
  capture_time: number;
  delta?: boolean;
  codes?: number[];
  pose: number[];
  velocity: number[] | null;
}

interface Vector {
  name: string;
  direction: string;
  frame: "msgpack" | "compact-update" | "compact-snapshot";
  encode: boolean;
  hex: string;
  message?: Record<string, unknown>;
  pose_frame?: { kind: string; number: number; time?: number; base_us?: number; entries: Entry[] };
  volume?: number[];
  velocity?: boolean;
  baselines_before?: { user?: number; stream: number; codes: number[] }[];
  baselines_after?: { user?: number; stream: number; codes: number[] }[];
  previous_header?: { number: number; base_us: number } | null;
  error?: { code: string; fatal: boolean; close_code: number | null };
}

const index = JSON.parse(readFileSync(new URL("index.json", DIR), "utf8")) as { schema: number; vectors: { name: string }[] };
const vectors: Vector[] = index.vectors.map((v) => JSON.parse(readFileSync(new URL(`${v.name}.json`, DIR), "utf8")) as Vector);
const bytes = (h: string): Uint8Array => new Uint8Array(Buffer.from(h, "hex"));
const hex = (b: Uint8Array): string => Buffer.from(b).toString("hex");

function baselines(v: Vector, list = v.baselines_before ?? []): Map<number, number[]> {
  const snapshot = v.frame === "compact-snapshot";
  return new Map(list.map((b) => [snapshot ? b.user! * 65536 + b.stream : b.stream, b.codes]));
}

function previous(v: Vector): CompactHeader | null {
  return v.previous_header ? { number: v.previous_header.number, baseUs: v.previous_header.base_us } : null;
}

function decode(v: Vector): unknown {
  const data = bytes(v.hex);
  if (v.frame === "msgpack") return decodeMessage(data);
  const volume = new Volume(v.volume!);
  return v.frame === "compact-update"
    ? decodeUpdateFrame(data, volume, baselines(v), previous(v))
    : decodeSnapshotFrame(data, volume, baselines(v));
}

// JSON numbers of the vectors: compare numerically (20.0 and 20 alike); bin as {"bin": hex}.
function sameJson(got: unknown, want: unknown, where: string): void {
  if (want && typeof want === "object" && !Array.isArray(want) && "bin" in want) {
    assert.ok(got instanceof Uint8Array, `${where}: want bin`);
    assert.equal(hex(got), (want as { bin: string }).bin, where);
    return;
  }
  if (Array.isArray(want)) {
    assert.ok(Array.isArray(got), `${where}: want an array`);
    assert.equal(got.length, want.length, `${where}: length`);
    want.forEach((w, i) => sameJson((got as unknown[])[i], w, `${where}[${i}]`));
    return;
  }
  if (want && typeof want === "object") {
    assert.ok(got && typeof got === "object", `${where}: want a map`);
    for (const [k, w] of Object.entries(want)) sameJson((got as Record<string, unknown>)[k], w, `${where}.${k}`);
    return;
  }
  assert.equal(got, want, where);
}

test("the golden vectors are here, every kind of them", () => {
  assert.equal(index.schema, 1);
  const kinds = new Set(vectors.map((v) => `${v.frame}:${v.error ? "error" : "ok"}`));
  for (const k of ["msgpack:ok", "msgpack:error", "compact-update:ok", "compact-update:error", "compact-snapshot:ok", "compact-snapshot:error"]) {
    assert.ok(kinds.has(k), k);
  }
});

test("ERROR_CODES is the spec's error table (generated from protocol/errors.py), code for code", () => {
  const spec = readFileSync(new URL("../../../docs/protocol.md", import.meta.url), "utf8");
  const table = spec.slice(spec.indexOf("<!-- errors:begin -->"), spec.indexOf("<!-- errors:end -->"));
  const rows = [...table.matchAll(/^\| `([a-z-]+)` \| (yes|no) \| (\d+|-) \|/gm)];
  assert.ok(rows.length >= 20, `only ${rows.length} rows read from docs/protocol.md section 8`);
  const want = Object.fromEntries(rows.map((r) => [r[1]!, r[3] === "-" ? null : Number(r[3])]));
  assert.deepEqual({ ...ERROR_CODES }, want);
  for (const r of rows) assert.equal(r[2] === "yes", r[3] !== "-", `${r[1]}: fatal exactly when it closes`);
});

for (const v of vectors) {
  if (v.error) {
    test(`${v.name}: refused with ${v.error.code}`, () => {
      assert.throws(
        () => decode(v),
        (e: unknown) => e instanceof DecodeError && e.code === v.error!.code,
        `${v.name} must raise ${v.error!.code}`,
      );
      assert.equal(ERROR_CODES[v.error!.code], v.error!.close_code);
    });
    continue;
  }
  test(`${v.name}: decodes to what it states${v.encode ? ", encodes to its bytes" : ""}`, () => {
    const got = decode(v) as Record<string, unknown>;
    if (v.frame === "msgpack") {
      const message = v.message!;
      if (message.type === "update" || message.type === "snapshot") {
        const frame = v.pose_frame!;
        assert.equal(got.type, frame.kind);
        assert.equal(got.type === "update" ? got.seq : got.tick, frame.number);
        assert.equal(got.time, frame.time);
        const entries = got.entries as { user: number; stream: number; capture: number; pose: number[]; velocity?: number[] }[];
        assert.equal(entries.length, frame.entries.length);
        frame.entries.forEach((e, i) => {
          const g = entries[i]!;
          if (e.user !== undefined) assert.equal(g.user, e.user);
          assert.equal(g.stream, e.stream);
          assert.equal(g.capture, e.capture_time);
          assert.deepEqual(g.pose, e.pose);
          assert.deepEqual(g.velocity ?? null, e.velocity);
        });
      } else {
        sameJson(got, message, v.name);
        if (v.encode) assert.equal(hex(encodeControl(message as unknown as ControlMessage)), v.hex);
      }
      return;
    }
    const frame = v.pose_frame!;
    assert.equal(got.number, frame.number);
    assert.equal(got.baseUs, frame.base_us);
    const entries = got.entries as { user?: number; stream: number; offsetMs: number; codes: number[]; delta: boolean }[];
    assert.equal(entries.length, frame.entries.length);
    const volume = new Volume(v.volume!);
    frame.entries.forEach((e, i) => {
      const g = entries[i]!;
      if (e.user !== undefined) assert.equal(g.user, e.user);
      assert.equal(g.stream, e.stream);
      assert.equal(g.offsetMs, e.offset_ms);
      assert.equal(g.delta, e.delta);
      assert.deepEqual(g.codes, e.codes);
      assert.equal(frame.base_us! / 1e6 - g.offsetMs / 1000, e.capture_time);
      const { pose, velocity } = codesToPose(g.codes, volume);
      assert.deepEqual(pose, e.pose, `${v.name} entry ${i} pose`);
      assert.deepEqual(velocity, e.velocity);
    });
    // Baselines after: the ones before, every entry's codes replacing its stream's.
    const after = baselines(v);
    for (const g of entries) after.set(v.frame === "compact-snapshot" ? g.user! * 65536 + g.stream : g.stream, g.codes);
    assert.deepEqual(after, baselines(v, v.baselines_after));
    if (v.encode) {
      const encoded = encodeUpdateFrame(
        volume,
        { number: frame.number, baseUs: frame.base_us!, entries: frame.entries.map((e) => ({ stream: e.stream, offsetMs: e.offset_ms!, codes: e.codes! })) },
        baselines(v),
        previous(v),
        v.velocity ?? false,
      );
      assert.equal(hex(encoded), v.hex);
    }
  });
}
