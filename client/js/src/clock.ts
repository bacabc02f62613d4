/**
 * Clock sync: the server-minus-client clock offset from ping/pong samples,
 * keeping the sample of lowest round trip among the last `window` ones (NTP-style).
 *
 * A `pong` answers a `ping` with `ping_time` (the pinger's clock), `recv_time`
 * and `send_time` (the answerer's clock); with t3 its arrival on the pinger's clock:
 *
 *     offset     = ((recv_time - ping_time) + (send_time - t3)) / 2
 *     round trip = (t3 - ping_time) - (send_time - recv_time)
 */
import type { Pong } from "./messages.js";

export function pongOffset(pong: Pong, arrival: number): number {
  return (pong.recv_time - pong.ping_time + (pong.send_time - arrival)) / 2;
}

export function pongRoundTrip(pong: Pong, arrival: number): number {
  return arrival - pong.ping_time - (pong.send_time - pong.recv_time);
}

export class ClockEstimator {
  private samples: [number, number][] = []; // [rtt, offset]

  constructor(readonly window = 16) {}

  add(offset: number, rtt: number): void {
    this.samples.push([rtt, offset]);
    while (this.samples.length > this.window) this.samples.shift();
  }

  addPong(pong: Pong, arrival: number): void {
    this.add(pongOffset(pong, arrival), pongRoundTrip(pong, arrival));
  }

  get ready(): boolean {
    return this.samples.length > 0;
  }

  private best(): [number, number] | undefined {
    let best: [number, number] | undefined;
    for (const s of this.samples) {
      // Lowest round trip; among equal ones the lowest offset (Python's min of tuples).
      if (!best || s[0] < best[0] || (s[0] === best[0] && s[1] < best[1])) best = s;
    }
    return best;
  }

  /** Server clock minus this clock (s); 0 before any sample. */
  get offset(): number {
    return this.best()?.[1] ?? 0;
  }

  /** Round trip of the sample in use (s); NaN before any sample. */
  get rtt(): number {
    return this.best()?.[0] ?? NaN;
  }
}

/** This machine's monotonic clock in seconds. */
export function monotonicSeconds(): number {
  return performance.now() / 1000;
}
