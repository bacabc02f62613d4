import { test } from "node:test";
import assert from "node:assert/strict";
import { decodeMessage, encodeControl, encodeSnapshot, encodeUpdate, float16, toFloat16 } from "../src/messages.js";
import type { Pose } from "../src/messages.js";
import { DecodeError } from "../src/errors.js";
import { pack } from "../src/msgpack.js";

const hex = (b: Uint8Array): string => Buffer.from(b).toString("hex");
const bytes = (h: string): Uint8Array => new Uint8Array(Buffer.from(h, "hex"));

// Bytes of posecast's Python encoder (protocol.wire.encode_message) for the same messages.
const PINNED: [string, Parameters<typeof encodeControl>[0], string][] = [
  ["hello", { type: "hello", agent: "js", resumable: true }, "84a474797065a568656c6c6fa776657273696f6e01a56167656e74a26a73a9726573756d61626c65c3"],
  [
    "join (integral rate as float64, omitted defaults)",
    { type: "join", room: "lab", streams: ["head", "left", "right"], rate: 20, label: "orbit", codec: "compact" },
    "87a474797065a46a6f696ea4726f6f6da36c6162a773747265616d7393a468656164a46c656674a57269676874a472617465cb4034000000000000a5746f6b656ec0a56c6162656ca56f72626974a5636f646563a7636f6d70616374",
  ],
  ["ping", { type: "ping", seq: 3, time: 12 }, "83a474797065a470696e67a373657103a474696d65cb4028000000000000"],
  [
    "object_create",
    { type: "object_create", name: "object:cup", pose: [0, 1, 0, 1, 0, 0, 0], hold: true },
    "85a474797065ad6f626a6563745f637265617465a46e616d65aa6f626a6563743a637570a4706f736597cb0000000000000000cb3ff0000000000000cb0000000000000000cb3ff0000000000000cb0000000000000000cb0000000000000000cb0000000000000000a46b656570c3a4686f6c64c3",
  ],
  [
    "release with velocity",
    { type: "release", stream: 7, velocity: [1, 2, 3] },
    "83a474797065a772656c65617365a673747265616d07a876656c6f6369747993cb3ff0000000000000cb4000000000000000cb4008000000000000",
  ],
];

for (const [name, message, want] of PINNED) {
  test(`${name} encodes to the Python encoder's bytes`, () => {
    assert.equal(hex(encodeControl(message)), want);
  });
}

test("a raw update encodes to the Python encoder's bytes and decodes back", () => {
  const entries = [
    { user: -1, stream: 0, capture: 10, pose: [0, 1.5, 0, 1, 0, 0, 0] as Pose },
    { user: -1, stream: 2, capture: 10, pose: [0.25, 1, -0.5, 0, 1, 0, 0] as Pose },
  ];
  const frame = encodeUpdate(5, 10, entries);
  assert.equal(
    hex(frame),
    "84a474797065a6757064617465a373657105a474696d65cb4024000000000000a5706f736573c444000000000000000000000000c03f000000000000803f0000000000000000000000000200000000000000803e0000803f000000bf000000000000803f0000000000000000",
  );
  const back = decodeMessage(frame);
  assert.equal(back.type, "update");
  if (back.type !== "update") return;
  assert.equal(back.seq, 5);
  assert.deepEqual(back.entries.map((e) => [e.stream, e.capture, e.pose]), entries.map((e) => [e.stream, e.capture, e.pose]));
});

test("a raw snapshot decodes to users, streams, capture times and poses", () => {
  const entries = [
    { user: 3, stream: 1, capture: 99.5, pose: [0.5, 1.25, -1, 0, 0, 1, 0] as Pose },
    { user: 65535, stream: 9, capture: 99.75, pose: [1, 1, 1, 1, 0, 0, 0] as Pose },
  ];
  const snap = decodeMessage(encodeSnapshot(42, 100, entries));
  assert.equal(snap.type, "snapshot");
  if (snap.type !== "snapshot") return;
  assert.equal(snap.tick, 42);
  assert.equal(snap.time, 100);
  assert.deepEqual(snap.entries, entries);
});

test("decoding fills defaults and checks types", () => {
  const welcome = decodeMessage(bytes("83a474797065a777656c636f6d65a475736572cd0102ab7365727665725f74696d65cb4059000000000000"));
  assert.deepEqual(welcome, {
    type: "welcome", user: 258, server_time: 100, version: 1, min_rate: 5, max_rate: 30, max_streams: 16,
    volume: [-8, -2, -8, 8, 4, 8], resume: null, resumed: false,
  });
  const bad = pack({ type: "ping", seq: 1, time: null });
  assert.throws(() => decodeMessage(bad), (e: unknown) => e instanceof DecodeError && e.code === "bad-message" && /ping.time/.test(e.message));
});

test("garbage, non-maps and unknown types get the relay's codes", () => {
  const code = (data: Uint8Array): string => {
    try {
      decodeMessage(data);
    } catch (e) {
      return (e as DecodeError).code;
    }
    return "ok";
  };
  assert.equal(code(bytes("c1")), "bad-frame");
  assert.equal(code(bytes("93010203")), "bad-frame");
  assert.equal(code(bytes("81a474797065a3666f6f")), "unknown-type");
  assert.equal(code(bytes("82a474797065a568656c6c6fa776657273696f6e02")), "version-mismatch");
  assert.equal(code(encodeControl({ type: "bye", reason: "x" }).slice(0, 5)), "bad-frame");
});

test("float16 conversion rounds to nearest even and clamps finite values", () => {
  for (const x of [0, 1, -2.5, 0.1, 65504, 6e-8, 1e-5, 3.14159]) {
    const back = float16(toFloat16(x));
    assert.ok(Math.abs(back - x) <= Math.abs(x) * 2 ** -11 + 2 ** -25, `${x} -> ${back}`);
  }
  assert.equal(toFloat16(1e9), 0x7bff);
  assert.equal(toFloat16(1 + 2 ** -11), 0x3c00); // a tie rounds to even
  assert.equal(toFloat16(1 + 3 * 2 ** -11), 0x3c02);
  assert.ok(Number.isNaN(float16(toFloat16(NaN))));
});

test('a join asking rate "auto" encodes to the Python encoder\'s bytes (max_rate last, omitted while nil)', () => {
  // posecast.protocol.encode_message(Join(room="lab", streams=("head",), rate="auto", max_rate=24.0)), and without max_rate.
  const withMax = "87a474797065a46a6f696ea4726f6f6da36c6162a773747265616d7391a468656164a472617465a46175746fa5746f6b656ec0a56c6162656cc0a86d61785f72617465cb4038000000000000";
  const without = "86a474797065a46a6f696ea4726f6f6da36c6162a773747265616d7391a468656164a472617465a46175746fa5746f6b656ec0a56c6162656cc0";
  const hex = (b: Uint8Array) => Buffer.from(b).toString("hex");
  assert.equal(hex(encodeControl({ type: "join", room: "lab", streams: ["head"], rate: "auto", max_rate: 24 })), withMax);
  assert.equal(hex(encodeControl({ type: "join", room: "lab", streams: ["head"], rate: "auto" })), without);
  const back = decodeMessage(Buffer.from(withMax, "hex"));
  assert.ok(back.type === "join" && back.rate === "auto" && back.max_rate === 24);
  assert.throws(() => decodeMessage(pack({ type: "join", room: "lab", streams: ["head"], rate: "fast" })), (e: unknown) => e instanceof DecodeError && e.code === "bad-message");
});
