/** Compact codec (in progress). */
import { UsageError } from "./errors.js";
import type { Pose, PoseEntry, Snapshot } from "./messages.js";

export const CODEC_FRAME_BYTE = 0xc1;

export class CompactSession {
  constructor(
    readonly volume: readonly number[],
    readonly velocities: boolean,
  ) {
    throw new UsageError("bad-message", "the compact codec is not in this build yet: use codec 'raw'");
  }
  isCompact(data: Uint8Array): boolean {
    return data[0] === CODEC_FRAME_BYTE;
  }
  checkVolume(_name: string, _pose: Pose): void {}
  encodeUpdate(_seq: number, _time: number, _entries: PoseEntry[]): Uint8Array {
    return new Uint8Array();
  }
  decodeSnapshot(_data: Uint8Array): Snapshot {
    return { type: "snapshot", tick: 0, time: 0, entries: [] };
  }
}
