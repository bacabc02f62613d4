/**
 * `PosecastClient`: one user in one room of a posecast relay.
 *
 * `connect()` says hello, syncs its clock (pings, lowest round trip kept), joins
 * and resolves with the server's `joined`. Then `publish()` sends this user's
 * poses, `render()` returns every remote pose at the playout time, events tell
 * of peers, objects and errors. A connection that drops (1006), a relay going
 * away with others listed (1001) or a cluster node asking to reconnect (1012)
 * is resumed with the welcome's token, over the relay URLs in order, cycling,
 * for `resumeWindow` seconds; a relay that does not hold the session takes the
 * client back as a new member ("rejoined"). In a browser it says `bye` when the
 * page is hidden or left.
 */
import { ClockEstimator, monotonicSeconds } from "./clock.js";
import { ConnectionClosed, DecodeError, ERROR_CODES, JoinRefused, PosecastError, ServerError, UsageError } from "./errors.js";
import { Emitter } from "./events.js";
import { defaultWebSocket, Link } from "./link.js";
import type { WebSocketLike } from "./link.js";
import type { MethodName } from "./interp.js";
import {
  decodeMessage,
  encodeControl,
  encodeUpdate,
  PROTOCOL_VERSION,
  ROOM_USER,
} from "./messages.js";
import type {
  ControlMessage,
  ErrorMessage,
  Joined,
  JoinRate,
  Message,
  ObjectInfo,
  Owner,
  PeerJoined,
  Pose,
  PoseEntry,
  Snapshot,
  UserEvent,
  Vec3,
  Welcome,
} from "./messages.js";
import { Receiver } from "./receiver.js";
import type { RenderFrame, SharedObject } from "./receiver.js";
import type { Velocity } from "./buffers.js";
import { CompactSession } from "./compact.js";

export type Codec = "raw" | "compact";

export interface ClientOptions {
  /** The relay, `ws://host:port` or `wss://...`. */
  url?: string;
  /** Several relays (a cluster's nodes, spares): tried in order, cycling. */
  urls?: string[];
  room: string;
  /** Stream names: devices `head`, `left`, `right`; objects `object:NAME`. Default the three devices. */
  streams?: string[];
  /** Snapshot rate asked of the server (Hz); must be within the welcome's range.
   * Default: 30 Hz clamped to that range. Or "auto": the relay chooses the rate
   * from what this client's link delivers, and says each choice (the `rate` event). */
  rate?: JoinRate;
  /** With `rate: "auto"` only: the highest rate the relay may choose (Hz; default the welcome's max_rate). */
  maxRate?: number;
  /** An error budget in degrees of visual angle, in (0, 90) (`join.budget_deg`): the relay
   * sends each peer at the lowest rate whose expected error, seen from this client's head,
   * stays within it (section 5.6 of the spec); the receiver then sizes each peer's playout
   * delay from that peer's own keyframe interval. Default: every peer at the snapshot rate. */
  budgetDeg?: number;
  token?: string | null;
  /** A free label peers see with this user (e.g. what it plays). */
  label?: string | null;
  /** How poses are coded both ways: `raw` float records, or `compact` (quantised, delta-coded). */
  codec?: Codec;
  /** Watch only: no streams of its own, announced to nobody. */
  spectator?: boolean;
  /** Send this client's poses with velocities (linear m/s, angular rad/s, world frame). */
  velocities?: boolean;
  /** Names the client software in the server's logs. */
  agent?: string;
  /** Ask the server to hold this user's place when the connection drops, and resume it. */
  resume?: boolean;
  /** How long it tries to reconnect after a drop (s). */
  resumeWindow?: number;
  /** Seconds a connection attempt may take. */
  openTimeout?: number;
  pingInterval?: number;
  initialPings?: number;
  /** Websocket subprotocols to offer (e.g. ["posecast.v1"]); none by default. */
  protocols?: string[];
  /** The WebSocket constructor (default: the global one). */
  WebSocket?: WebSocketLike;
  /** This machine's monotonic clock in seconds (default performance.now() / 1000). */
  clock?: () => number;
  /** In a browser: send `bye` and close when the page is hidden or unloaded (default true). */
  byeWhenHidden?: boolean;
  /** Keyframes kept per remote stream. */
  bufferCapacity?: number;
}

export interface ClientEvents {
  welcome: (welcome: Welcome) => void;
  joined: (joined: Joined) => void;
  peer_joined: (peer: PeerJoined) => void;
  peer_left: (user: number, reason: string) => void;
  peer_stalled: (user: number) => void;
  peer_resumed: (user: number) => void;
  event: (event: UserEvent) => void;
  object: (object: ObjectInfo) => void;
  owner: (owner: Owner) => void;
  object_removed: (stream: number, reason: string) => void;
  snapshot: (snapshot: Snapshot, arrival: number) => void;
  /** The relay chose another snapshot rate (Hz) for this client (it joined with rate "auto"). */
  rate: (rate: number) => void;
  /** A non-fatal server error, or a frame that could not be decoded. */
  error: (error: PosecastError) => void;
  /** The connection dropped; it tries to resume. */
  reconnecting: (closed: ConnectionClosed) => void;
  /** Back as the same user with the same streams. */
  resumed: (joined: Joined) => void;
  /** Back as a new member (a relay that did not hold the session): peers start afresh. */
  rejoined: (joined: Joined) => void;
  /** The session is over (closed by either side, or the connection lost for good). */
  closed: (closed: ConnectionClosed) => void;
}

type State = "idle" | "connecting" | "joined" | "reconnecting" | "closed";

interface Waiter {
  types: ReadonlySet<string>;
  resolve: (m: Message) => void;
  reject: (e: Error) => void;
}

const DEVICES = ["head", "left", "right"];
const QUAT_NORM_TOLERANCE = 1e-3;
/** Unsent bytes in the socket above which `publish` skips an update (bounded queue). */
const MAX_BUFFERED = 64 * 1024;

export class PosecastClient extends Emitter<ClientEvents> {
  readonly urls: string[];
  readonly options: Required<Pick<ClientOptions, "room" | "codec" | "spectator" | "velocities" | "agent" | "resume" | "resumeWindow" | "openTimeout" | "pingInterval" | "initialPings" | "byeWhenHidden">>;
  readonly clock: () => number;
  readonly clockSync = new ClockEstimator();
  receiver: Receiver;
  welcome: Welcome | null = null;
  joined: Joined | null = null;
  state: State = "idle";
  /** Index in `urls` of the relay in use. */
  relay = 0;
  /** Frames that could not be decoded (each also an "error" event). */
  decodeErrors = 0;
  bytesIn = 0;
  bytesOut = 0;
  /** Update frames and the poses in them, sent on all connections. */
  updatesSent = 0;
  posesSent = 0;
  updateBytes = 0;
  /** Updates not sent because the socket still held over `MAX_BUFFERED` unsent bytes
   * (a stalled network: poses are latest-wins, a backlog would only add delay). */
  updatesSkipped = 0;
  /** Snapshot frames received and their bytes, on all connections. */
  snapshotsIn = 0;
  snapshotBytes = 0;
  private link: Link | null = null;
  private waiters: Waiter[] = [];
  private seq = 0;
  private pingSeq = 0;
  private pinger: ReturnType<typeof setInterval> | null = null;
  private readonly streamNames: string[];
  private rate: JoinRate | undefined;
  private currentRateHz: number | undefined;
  private readonly WebSocket: WebSocketLike;
  private compact: CompactSession | null = null;
  private unhook: (() => void) | null = null;
  private readonly opts: ClientOptions;

  constructor(opts: ClientOptions) {
    super();
    const urls = opts.urls?.length ? [...opts.urls] : opts.url ? [opts.url] : [];
    if (opts.url && opts.urls?.length && !urls.includes(opts.url)) urls.unshift(opts.url);
    if (!urls.length) throw new UsageError("bad-url", "give url or urls");
    for (const u of urls) {
      if (!/^wss?:\/\/[^/]/.test(u)) throw new UsageError("bad-url", `${u} is not a ws:// or wss:// URL with a host`);
    }
    if (!opts.room) throw new UsageError("bad-room", "room must be a non-empty string");
    this.urls = urls;
    this.opts = opts;
    this.options = {
      room: opts.room,
      codec: opts.codec ?? "raw",
      spectator: opts.spectator ?? false,
      velocities: opts.velocities ?? false,
      agent: opts.agent ?? "posecast-js",
      resume: opts.resume ?? true,
      resumeWindow: opts.resumeWindow ?? 10,
      openTimeout: opts.openTimeout ?? 10,
      pingInterval: opts.pingInterval ?? 1,
      initialPings: opts.initialPings ?? 8,
      byeWhenHidden: opts.byeWhenHidden ?? true,
    };
    if (this.options.codec !== "raw" && this.options.codec !== "compact") {
      throw new UsageError("bad-message", `codec must be raw or compact, got ${String(this.options.codec)}`);
    }
    this.streamNames = opts.streams ? [...opts.streams] : [...DEVICES];
    if (opts.rate !== undefined && opts.rate !== "auto" && typeof opts.rate !== "number") {
      throw new UsageError("bad-rate", `rate must be a number of Hz or "auto", got ${String(opts.rate)}`);
    }
    if (opts.maxRate !== undefined && opts.rate !== "auto") throw new UsageError("bad-message", 'maxRate is only allowed with rate "auto"');
    if (opts.budgetDeg !== undefined && !(opts.budgetDeg > 0 && opts.budgetDeg < 90)) {
      throw new UsageError("bad-message", `budgetDeg must be in (0, 90) degrees, got ${String(opts.budgetDeg)}`);
    }
    this.rate = opts.rate;
    this.clock = opts.clock ?? monotonicSeconds;
    this.WebSocket = opts.WebSocket ?? defaultWebSocket();
    const first = opts.rate === "auto" ? (opts.maxRate ?? 30) : (opts.rate ?? 30);
    this.receiver = new Receiver({ rate: first, capacity: opts.bufferCapacity ?? 64, perPeer: opts.budgetDeg !== undefined });
  }

  /** This user's id (from welcome); -1 before. */
  get user(): number {
    return this.welcome?.user ?? -1;
  }

  /** The server's clock now (s), as estimated from pings. */
  serverNow(): number {
    return this.clock() + this.clockSync.offset;
  }

  /** Stream name -> id of this user's streams (once joined). */
  get streams(): Record<string, number> {
    return this.joined?.streams ?? {};
  }

  /** The snapshot rate the server granted (Hz). */
  get grantedRate(): number | undefined {
    return this.joined?.rate;
  }

  /** The rate snapshots come at now (Hz): the joined rate, then each rate the relay
   * chose (rate "auto", the `rate` event) or `setRate` asked. Undefined before joining. */
  get currentRate(): number | undefined {
    return this.currentRateHz;
  }

  /** Whether the relay chooses this client's rate (it joined with rate "auto" and
   * has not called `setRate` since). */
  get autoRate(): boolean {
    return this.rate === "auto";
  }

  /** The room's shared objects by stream id. */
  get objects(): ReadonlyMap<number, SharedObject> {
    return this.receiver.objects;
  }

  /** Connect (the first relay that answers), sync the clock and join. */
  async connect(): Promise<Joined> {
    if (this.state !== "idle" && this.state !== "closed") throw new UsageError("unexpected-message", `connect() while ${this.state}`);
    this.state = "connecting";
    this.closing = false;
    this.rekey = false;
    this.receiver.reset(); // a new session: nobody from an earlier one
    let first: Error | null = null;
    for (let i = 0; i < this.urls.length; i++) {
      try {
        await this.hello(this.urls[i]!, null);
        this.relay = i;
        first = null;
        break;
      } catch (err) {
        first ??= err as Error;
      }
    }
    if (first) {
      this.state = "closed";
      throw first;
    }
    try {
      await this.sync(this.options.initialPings);
      const joined = await this.join(this.opts.label ?? null);
      this.state = "joined";
      this.startPinger();
      this.hookPage();
      return joined;
    } catch (err) {
      this.state = "closed";
      this.link?.close(1000, "join failed");
      throw err;
    }
  }

  /** Open a link to `url` and say hello; resolves with the welcome. */
  private async hello(url: string, resume: string | null, timeout = this.options.openTimeout): Promise<Welcome> {
    const link = await Link.open(url, {
      WebSocket: this.WebSocket,
      protocols: this.opts.protocols ?? [],
      timeout,
      clock: this.clock,
    });
    this.attach(link);
    this.send({ type: "hello", version: PROTOCOL_VERSION, agent: this.options.agent, resumable: this.options.resume, resume });
    try {
      const welcome = (await this.expect(["welcome"], timeout)) as Welcome;
      this.welcome = welcome;
      this.emit("welcome", welcome);
      return welcome;
    } catch (err) {
      link.close(1000, "handshake failed");
      throw err;
    }
  }

  private attach(link: Link): void {
    this.link = link;
    link.onFrame = (data, arrival) => {
      if (this.link !== link) return;
      this.bytesIn += typeof data === "string" ? data.length : data.length;
      this.receive(data, arrival);
    };
    link.onClose = (closed) => {
      if (this.link !== link) return;
      this.bytesOut += link.bytesOut;
      this.linkClosed(closed);
    };
  }

  private async join(label: string | null): Promise<Joined> {
    const welcome = this.welcome!;
    const rate = this.rate ?? Math.min(welcome.max_rate, Math.max(welcome.min_rate, 30));
    const auto = rate === "auto";
    const asked = auto ? this.opts.maxRate : rate; // auto without maxRate: the welcome's max_rate
    if (asked !== undefined && !(asked >= welcome.min_rate && asked <= welcome.max_rate)) {
      const what = auto ? "max_rate" : "rate";
      const err = new JoinRefused("bad-rate", `${what} ${asked} Hz is refused; the server allows ${welcome.min_rate}-${welcome.max_rate} Hz`, false, "join");
      err.rateRange = [welcome.min_rate, welcome.max_rate];
      throw err;
    }
    const compact = this.options.codec === "compact";
    this.send({
      type: "join",
      room: this.options.room,
      streams: this.streamNames, // nominal for a spectator, but a join needs at least one
      rate,
      token: this.opts.token ?? null,
      label,
      sends_velocities: this.options.velocities,
      wants_velocities: false,
      codec: this.options.codec,
      spectator: this.options.spectator,
      max_rate: auto ? (this.opts.maxRate ?? null) : null,
      budget_deg: this.opts.budgetDeg ?? null,
    });
    // The codec's baselines start afresh with each join.
    this.compact = compact ? new CompactSession(welcome.volume, this.options.velocities) : null;
    const joined = (await this.expect(["joined"], this.options.openTimeout)) as Joined;
    this.joined = joined;
    this.seq = 0;
    this.receiver.me = welcome.user;
    this.receiver.setRate(joined.rate);
    this.currentRateHz = joined.rate;
    this.emit("joined", joined);
    return joined;
  }

  /** Ping `n` times, one after the other, each answer improving the estimate. */
  private async sync(n: number): Promise<void> {
    for (let i = 0; i < n; i++) {
      this.ping();
      try {
        await this.expect(["pong"], 2);
      } catch (err) {
        if (err instanceof PosecastError && err.code === "timeout") continue;
        throw err;
      }
    }
  }

  private ping(): void {
    this.pingSeq++;
    this.send({ type: "ping", seq: this.pingSeq, time: this.clock() });
  }

  private startPinger(): void {
    this.stopPinger();
    this.pinger = setInterval(() => {
      if (this.state === "joined" && this.link && !this.link.closed) this.ping();
    }, this.options.pingInterval * 1000);
  }

  private stopPinger(): void {
    if (this.pinger !== null) clearInterval(this.pinger);
    this.pinger = null;
  }

  /** Wait for the next message of one of `types`; an error in reply rejects. */
  private expect(types: string[], timeout: number): Promise<Message> {
    return new Promise((resolve, reject) => {
      const waiter: Waiter = {
        types: new Set(types),
        resolve: (m) => {
          clearTimeout(timer);
          resolve(m);
        },
        reject: (e) => {
          clearTimeout(timer);
          reject(e);
        },
      };
      const timer = setTimeout(() => {
        this.waiters = this.waiters.filter((w) => w !== waiter);
        reject(new PosecastError("timeout", `no ${types.join(" or ")} within ${timeout} s`));
      }, timeout * 1000);
      this.waiters.push(waiter);
    });
  }

  private send(message: ControlMessage): void {
    if (!this.link) throw new UsageError("unexpected-message", "not connected");
    this.link.send(encodeControl(message));
  }

  private receive(data: Uint8Array | string, arrival: number): void {
    let message: Message;
    try {
      if (typeof data === "string") throw new DecodeError("bad-frame", "text frame, posecast frames are binary");
      message = this.compact?.isCompact(data) ? this.compact.decodeSnapshot(data) : decodeMessage(data);
    } catch (err) {
      this.decodeErrors++;
      const e = err instanceof PosecastError ? err : new DecodeError("bad-frame", String(err));
      this.emit("error", e);
      this.fatalDecodeError(e, typeof data === "string" ? undefined : data);
      return;
    }
    if (message.type === "snapshot") {
      this.snapshotsIn++;
      this.snapshotBytes += data.length;
    }
    this.dispatch(message, arrival);
  }

  /** A frame from the relay could not be decoded: every such error is fatal
   * (docs/protocol.md 8). Tell the relay, close with the error's close code, and
   * then either fail the handshake under way or reconnect: a broken compact chain
   * (bad-baseline, 11.3) can only be mended by a new connection. */
  private fatalDecodeError(e: PosecastError, data?: Uint8Array): void {
    const closeCode = ERROR_CODES[e.code] ?? 1002;
    try {
      const inReplyTo = data && this.compact?.isCompact(data) ? "snapshot" : null;
      this.send({ type: "error", code: e.code, message: e.message.slice(0, 200), fatal: true, in_reply_to: inReplyTo });
    } catch {
      // the link may be gone already
    }
    if (this.waiters.length) {
      const waiters = this.waiters;
      this.waiters = [];
      for (const w of waiters) w.reject(e);
    } else {
      this.rekey = true;
    }
    this.link?.close(closeCode, e.code);
  }

  private dispatch(m: Message, arrival: number): void {
    const waiter = this.waiters.find((w) => w.types.has(m.type));
    if (waiter) {
      this.waiters = this.waiters.filter((w) => w !== waiter);
      waiter.resolve(m);
    }
    switch (m.type) {
      case "snapshot":
        this.receiver.snapshot(m, arrival + this.clockSync.offset);
        this.emit("snapshot", m, arrival);
        return;
      case "pong":
        this.clockSync.addPong(m, arrival);
        return;
      case "ping":
        this.send({ type: "pong", seq: m.seq, ping_time: m.time, recv_time: arrival, send_time: this.clock() });
        return;
      case "peer_joined":
        this.receiver.peerJoined(m);
        this.emit("peer_joined", m);
        return;
      case "peer_left":
        // Handlers still see the peer's streams in `receiver`; they go right after.
        this.emit("peer_left", m.user, m.reason);
        this.receiver.peerLeft(m.user);
        return;
      case "peer_stalled":
        this.receiver.peerStalled(m.user, true);
        this.emit("peer_stalled", m.user);
        return;
      case "peer_resumed":
        this.receiver.peerStalled(m.user, false);
        this.emit("peer_resumed", m.user);
        return;
      case "joined":
        for (const [name, stream] of Object.entries(m.objects)) {
          if (!this.receiver.objects.has(stream)) {
            // Its object message follows with pose and owner.
            this.receiver.object({ type: "object", name, stream, pose: [0, 0, 0, 1, 0, 0, 0], time: 0, creator: ROOM_USER, owner: null, keep: true, steal: false, locked: false });
          }
        }
        return;
      case "object":
        this.receiver.object(m);
        this.emit("object", m);
        return;
      case "owner":
        this.receiver.owner(m);
        this.emit("owner", m);
        return;
      case "object_removed":
        this.receiver.objectRemoved(m.stream);
        this.emit("object_removed", m.stream, m.reason);
        return;
      case "event":
        this.emit("event", m);
        return;
      case "rate":
        // The relay's choice for an auto-rate client (docs/protocol.md 5.5): the
        // playout delay follows the new interval, keeping its measured ages.
        this.currentRateHz = m.rate;
        this.receiver.retime(m.rate);
        this.emit("rate", m.rate);
        return;
      case "error":
        this.serverError(m);
        return;
      case "bye":
        this.closing = true;
        return;
      default:
        return;
    }
  }

  private closing = false;
  /** The connection was closed for a broken compact chain: reconnect whatever the code. */
  private rekey = false;

  private serverError(m: ErrorMessage): void {
    const handshake = m.in_reply_to === "join" || m.in_reply_to === "hello" || this.state === "connecting" || this.state === "reconnecting";
    const Err = handshake && (m.fatal || m.in_reply_to === "join" || m.in_reply_to === "hello") ? JoinRefused : ServerError;
    const err = new Err(m.code, m.message, m.fatal, m.in_reply_to);
    if (err instanceof JoinRefused && m.code === "bad-rate" && this.welcome) {
      err.rateRange = [this.welcome.min_rate, this.welcome.max_rate];
    }
    const waiter = this.waiters.find((w) => w.types.has("welcome") || w.types.has("joined"));
    if (waiter && (err instanceof JoinRefused || m.fatal)) {
      this.waiters = this.waiters.filter((w) => w !== waiter);
      waiter.reject(err);
      return;
    }
    if (m.fatal) this.closing = true; // the server closes next: no resume
    this.emit("error", err);
  }

  private linkClosed(closed: ConnectionClosed): void {
    for (const w of this.waiters) w.reject(closed);
    this.waiters = [];
    if (this.state !== "joined") return; // connect() and the reconnect loop handle theirs
    const rekey = this.rekey;
    this.rekey = false;
    if (!this.closing && (this.reconnects(closed.closeCode) || (rekey && this.options.resume))) {
      void this.reconnect(closed);
      return;
    }
    this.finish(closed);
  }

  /** Whether a joined session goes on after its connection ended: a drop (1006) with
   * a resume token or other relays; a relay going away (1001) with others; a cluster
   * node asking its clients to reconnect (1012). */
  private reconnects(code: number): boolean {
    if (!this.options.resume || !this.welcome || !this.joined) return false;
    const several = this.urls.length > 1;
    if (code === 1006) return several || this.welcome.resume !== null;
    return code === 1012 || (several && code === 1001);
  }

  private async reconnect(closed: ConnectionClosed): Promise<void> {
    this.state = "reconnecting";
    this.stopPinger();
    this.emit("reconnecting", closed);
    const token = this.welcome?.resume ?? null;
    const before = this.joined!;
    const giveUp = this.clock() + this.options.resumeWindow;
    const n = this.urls.length;
    let tries = 0;
    while (this.clock() < giveUp && !this.closing) {
      const i = (this.relay + tries) % n;
      tries++;
      try {
        const left = Math.max(0.1, Math.min(2, giveUp - this.clock()));
        const welcome = await this.hello(this.urls[i]!, token, left);
        const resumed = welcome.resumed;
        if (!resumed) this.receiver.reset();
        this.compact = null;
        const joined = await this.join(resumed ? null : (this.opts.label ?? null));
        if (resumed && JSON.stringify(joined.streams) !== JSON.stringify(before.streams)) {
          throw new PosecastError("resume-failed", "the resumed join got other stream ids");
        }
        this.relay = i;
        this.state = "joined";
        this.startPinger();
        void this.sync(2).catch(() => {});
        this.emit(resumed ? "resumed" : "rejoined", joined);
        return;
      } catch {
        this.link?.close(1000, "reconnect failed");
        if (tries % n === 0) await sleep(Math.max(0, Math.min(0.2, giveUp - this.clock())));
      }
    }
    this.finish(closed);
  }

  private finish(closed: ConnectionClosed): void {
    if (this.state === "closed") return;
    this.state = "closed";
    this.stopPinger();
    this.unhook?.();
    this.unhook = null;
    this.emit("closed", closed);
  }

  /** Send this user's poses: stream name -> [px, py, pz, qw, qx, qy, qz] (metres,
   * unit quaternion w first), captured at `capture` (server clock; default now).
   * Returns the frame's size in bytes; 0 when nothing was sent (not joined, or the
   * socket still holds 64 KiB unsent: the update is skipped, `updatesSkipped`). */
  publish(
    poses: Readonly<Record<string, ArrayLike<number> | null | undefined>>,
    opts: { capture?: number; velocities?: Readonly<Record<string, ArrayLike<number>>> } = {},
  ): number {
    if (this.state !== "joined" || !this.link || !this.joined) return 0;
    if (this.link.buffered > MAX_BUFFERED) {
      this.updatesSkipped++;
      return 0;
    }
    const capture = opts.capture ?? this.serverNow();
    const entries: PoseEntry[] = [];
    for (const [name, pose] of Object.entries(poses)) {
      if (!pose) continue;
      const stream = this.streamId(name);
      const p = checkPose(name, pose);
      if (this.compact) this.compact.checkVolume(name, p);
      const entry: PoseEntry = { user: -1, stream, capture, pose: p };
      if (this.options.velocities) {
        const v = opts.velocities?.[name];
        entry.velocity = (v ? Array.from(v).slice(0, 6) : [0, 0, 0, 0, 0, 0]) as Velocity;
      }
      entries.push(entry);
    }
    if (!entries.length) return 0;
    this.seq++;
    const frame = this.compact
      ? this.compact.encodeUpdate(this.seq, capture, entries)
      : encodeUpdate(this.seq, capture, entries, this.options.velocities);
    this.link.send(frame);
    this.updatesSent++;
    this.posesSent += entries.length;
    this.updateBytes += frame.length;
    return frame.length;
  }

  /** The stream id of this user's stream `name`, or of a shared object it may publish. */
  streamId(name: string): number {
    const own = this.joined?.streams[name];
    if (own !== undefined) return own;
    for (const o of this.receiver.objects.values()) if (o.name === name) return o.stream;
    throw new UsageError("stream-not-owned", `no stream named '${name}' (joined: ${Object.keys(this.streams).join(", ")})`);
  }

  /** Every remote stream at the playout time (server now minus the playout delay). */
  render(method: MethodName | string = "soa", now = this.serverNow()): RenderFrame {
    return this.receiver.render(now, method);
  }

  /** Ask for another snapshot rate (Hz), within the welcome's range (ends an auto rate). */
  setRate(rate: number): void {
    const w = this.welcome;
    if (w && !(rate >= w.min_rate && rate <= w.max_rate)) {
      throw new UsageError("bad-rate", `rate ${rate} Hz is refused; the server allows ${w.min_rate}-${w.max_rate} Hz`);
    }
    this.rate = rate; // ends an auto rate: the relay serves this number from now on
    this.send({ type: "set_rate", rate });
    this.receiver.setRate(rate);
    this.currentRateHz = rate;
  }

  /** A fresh access token for the same room and user (before the old one expires). */
  renew(token: string): void {
    this.opts.token = token;
    this.send({ type: "renew", token });
  }

  /** A reliable, ordered interaction event to everyone in the room. */
  sendEvent(kind: "grab" | "release" | "button" | "scene_step", opts: { stream?: number | null; time?: number | null; payload?: Record<string, unknown> } = {}): void {
    this.send({ type: "event", kind, stream: opts.stream ?? null, user: null, time: opts.time ?? this.serverNow(), payload: opts.payload ?? {} });
  }

  /** Create shared object `object:NAME` at `pose` (everyone gets an `object` message). */
  createObject(name: string, pose: ArrayLike<number>, opts: { hold?: boolean; keep?: boolean; steal?: boolean; time?: number | null } = {}): void {
    if (!name.startsWith("object:")) throw new UsageError("bad-stream-name", `object names start with 'object:', got '${name}'`);
    this.send({ type: "object_create", name, pose: checkPose(name, pose), keep: opts.keep ?? true, steal: opts.steal ?? false, hold: opts.hold ?? false, time: opts.time ?? null });
  }

  /** Ask to own object `stream` (a grab, or a catch while it flies). */
  requestOwnership(stream: number, opts: { steal?: boolean; lock?: boolean } = {}): void {
    this.send({ type: "request_ownership", stream, steal: opts.steal ?? false, lock: opts.lock ?? false });
  }

  /** Let go of object `stream`: at rest, or thrown with `velocity` (m/s) and `angular` (rad/s, world). */
  release(stream: number, velocity: Vec3 | null = null, angular: Vec3 | null = null): void {
    this.send({ type: "release", stream, velocity, angular });
  }

  /** Leave: `bye`, then close the websocket (1000). */
  close(reason = "bye"): void {
    this.closing = true;
    const link = this.link;
    if (link && !link.closed) {
      try {
        this.send({ type: "bye", reason });
      } catch {
        // the link is going anyway
      }
      link.close(1000, reason);
    }
    this.finish(link?.closed ?? new ConnectionClosed(1000, reason));
  }

  /** In a browser: `bye` when the page is hidden or unloaded. */
  private hookPage(): void {
    if (!this.options.byeWhenHidden || this.unhook) return;
    const g = globalThis as { addEventListener?: typeof addEventListener; removeEventListener?: typeof removeEventListener; document?: Document };
    const doc = g.document;
    if (!doc || !g.addEventListener || !g.removeEventListener) return;
    const onHide = (): void => this.close("page hidden");
    const onVisibility = (): void => {
      if (doc.visibilityState === "hidden") onHide();
    };
    g.addEventListener("pagehide", onHide);
    doc.addEventListener("visibilitychange", onVisibility);
    this.unhook = () => {
      g.removeEventListener!("pagehide", onHide);
      doc.removeEventListener("visibilitychange", onVisibility);
    };
  }
}

function sleep(s: number): Promise<void> {
  return new Promise((r) => setTimeout(r, s * 1000));
}

/** 7 finite numbers with a unit quaternion (within 1e-3), else a bad-pose UsageError. */
export function checkPose(name: string, pose: ArrayLike<number>): Pose {
  if (pose.length !== 7) throw new UsageError("bad-pose", `${name}: a pose is 7 numbers [px, py, pz, qw, qx, qy, qz]`);
  const p = Array.from(pose) as Pose;
  if (!p.every(Number.isFinite)) throw new UsageError("bad-pose", `${name}: non-finite pose`);
  const n = Math.hypot(p[3], p[4], p[5], p[6]);
  if (Math.abs(n - 1) > QUAT_NORM_TOLERANCE) throw new UsageError("bad-pose", `${name}: quaternion norm ${n.toPrecision(4)} is not 1`);
  return p;
}
