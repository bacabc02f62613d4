/**
 * Errors: one class tree, every error carrying the protocol's code.
 *
 *     PosecastError            base: .code (a server error code, or a client one below)
 *     ├── ServerError          the server sent an `error` message (.fatal, .inReplyTo)
 *     │   └── JoinRefused      ... in reply to hello or join: the join failed
 *     ├── DecodeError          a frame from the server could not be decoded (.code is
 *     │                        the code the server would use: bad-frame, bad-baseline ...)
 *     ├── ConnectionClosed     the websocket closed (.closeCode, .reason)
 *     └── UsageError           this program called the SDK wrongly (bad-pose, bad-rate ...)
 */

/** Fatality and close code of every error code (the relay's table). */
export const ERROR_CODES: Readonly<Record<string, number | null>> = {
  "bad-frame": 1002,
  "frame-too-large": 1009,
  "unknown-type": 1002,
  "bad-message": 1002,
  "bad-baseline": 1002,
  "version-mismatch": 1002,
  "unexpected-message": 1002,
  "stream-not-owned": 1008,
  "too-many-streams": null,
  "duplicate-stream": null,
  "bad-stream-name": null,
  "bad-pose": null,
  "bad-velocity": null,
  "bad-rate": null,
  "payload-too-large": null,
  unauthorized: 1008,
  "room-full": null,
  "user-taken": null,
  "ownership-refused": null,
  "object-not-owned": null,
  "bad-room": null,
  "too-slow": 1008,
  "server-full": 1013,
  "internal-error": 1011,
};

export class PosecastError extends Error {
  constructor(
    readonly code: string,
    message: string,
  ) {
    super(`${code}: ${message}`);
    this.name = new.target.name;
  }
}

export class ServerError extends PosecastError {
  constructor(
    code: string,
    readonly detail: string,
    readonly fatal: boolean,
    readonly inReplyTo: string | null,
  ) {
    super(code, detail);
  }
}

export class JoinRefused extends ServerError {
  /** For bad-rate: the server's [min_rate, max_rate] from its welcome. */
  rateRange: [number, number] | null = null;
}

export class DecodeError extends PosecastError {}

export class ConnectionClosed extends PosecastError {
  constructor(
    readonly closeCode: number,
    readonly reason: string,
  ) {
    super("closed", `connection closed (${closeCode}${reason ? `: ${reason}` : ""})`);
  }
}

export class UsageError extends PosecastError {}
