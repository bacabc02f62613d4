/** One websocket to a relay: binary frames in with their arrival time, bytes out. */
import { ConnectionClosed, PosecastError } from "./errors.js";

/** The standard WebSocket constructor (the browser's, Node 22's global, or a compatible one). */
export type WebSocketLike = new (url: string, protocols?: string | string[]) => WebSocket;

export function defaultWebSocket(): WebSocketLike {
  const ws = (globalThis as { WebSocket?: WebSocketLike }).WebSocket;
  if (!ws) {
    throw new PosecastError(
      "no-websocket",
      "this runtime has no global WebSocket: use Node >= 22, run Node 20 with --experimental-websocket, or pass options.WebSocket",
    );
  }
  return ws;
}

/** Close code given when the connection broke without a close frame. */
export const ABNORMAL_CLOSURE = 1006;

export class Link {
  bytesIn = 0;
  bytesOut = 0;
  framesIn = 0;
  framesOut = 0;
  closed: ConnectionClosed | null = null;
  onFrame: (data: Uint8Array | string, arrival: number) => void = () => {};
  onClose: (closed: ConnectionClosed) => void = () => {};

  private constructor(
    readonly url: string,
    private readonly ws: WebSocket,
    private readonly clock: () => number,
  ) {
    ws.onmessage = (ev: MessageEvent) => {
      const arrival = this.clock();
      const data = ev.data;
      this.framesIn++;
      if (typeof data === "string") {
        this.bytesIn += data.length;
        this.onFrame(data, arrival);
        return;
      }
      const bytes = new Uint8Array(data as ArrayBuffer);
      this.bytesIn += bytes.length;
      this.onFrame(bytes, arrival);
    };
    ws.onclose = (ev: CloseEvent) => this.ended(ev.code || ABNORMAL_CLOSURE, ev.reason || "");
    // Browsers fire close after every error; Node 20's WebSocket may not: an error
    // is the end of the connection either way (a close event after it changes nothing).
    ws.onerror = () => this.ended(ABNORMAL_CLOSURE, "network error");
  }

  private ended(code: number, reason: string): void {
    if (this.closed) return;
    this.closed = new ConnectionClosed(code, reason);
    this.onClose(this.closed);
  }

  /** Open a websocket to `url`; rejects if it is not open within `timeout` s. */
  static open(
    url: string,
    opts: { WebSocket: WebSocketLike; protocols?: string[]; timeout: number; clock: () => number },
  ): Promise<Link> {
    return new Promise((resolve, reject) => {
      let ws: WebSocket;
      try {
        ws = opts.protocols?.length ? new opts.WebSocket(url, opts.protocols) : new opts.WebSocket(url);
      } catch (err) {
        reject(new PosecastError("bad-url", `${url}: ${(err as Error).message}`));
        return;
      }
      ws.binaryType = "arraybuffer";
      const timer = setTimeout(() => {
        cleanup();
        try {
          ws.close();
        } catch {
          // closing a socket that never opened may throw; it is dropped either way
        }
        reject(new PosecastError("connect-timeout", `${url}: no answer within ${opts.timeout} s`));
      }, opts.timeout * 1000);
      const cleanup = (): void => {
        clearTimeout(timer);
        ws.onopen = null;
        ws.onclose = null;
        ws.onerror = null;
      };
      ws.onopen = () => {
        cleanup();
        resolve(new Link(url, ws, opts.clock));
      };
      ws.onclose = (ev: CloseEvent) => {
        cleanup();
        reject(new ConnectionClosed(ev.code || ABNORMAL_CLOSURE, ev.reason || `could not connect to ${url}`));
      };
      ws.onerror = () => {
        cleanup();
        reject(new ConnectionClosed(ABNORMAL_CLOSURE, `could not connect to ${url}`));
      };
    });
  }

  send(data: Uint8Array): void {
    if (this.closed) throw this.closed;
    this.ws.send(data);
    this.framesOut++;
    this.bytesOut += data.length;
  }

  /** Bytes queued in the socket and not yet sent (backpressure). */
  get buffered(): number {
    return this.ws.bufferedAmount;
  }

  close(code = 1000, reason = ""): void {
    try {
      this.ws.close(code, reason);
    } catch {
      // already closing
    }
    // The close handshake may take a while; the session is over for us now.
    this.ended(code, reason);
  }
}
