/**
 * The three pair interpolators of posecast's `interp/`, for one pose at a time.
 *
 * A pose is `[px, py, pz, qw, qx, qy, qz]` (metres, unit quaternion, w first).
 * `f(a, b, s)` returns the pose a fraction `s` of the way from `a` to `b`: exactly
 * `a` at s = 0 and exactly `b` at s = 1. Each puts `b`'s quaternion in `a`'s
 * hemisphere first, so q and -q interpolate alike. Quaternions off unit length by
 * more than 1e-6 are normalised first. The formulas are those of
 * `interp/methods.py`; the JS tests check them against it to 1e-9.
 *
 * - `soa`: position LERP + quaternion SLERP (what engines do today).
 * - `dq-slerp`: dual-quaternion screw interpolation (ScLERP), constant-speed screw.
 * - `motor-lerp`: linear blend of PGA motors, then Study-number normalisation.
 */
import type { Pose } from "./messages.js";

export type Interpolator = (a: ArrayLike<number>, b: ArrayLike<number>, s: number) => Pose;
export type MethodName = "soa" | "dq-slerp" | "motor-lerp";

const UNIT_TOLERANCE = 1e-6;

interface Prepared {
  t0x: number; t0y: number; t0z: number;
  t1x: number; t1y: number; t1z: number;
  /** q0 */
  aw: number; ax: number; ay: number; az: number;
  /** q1, in q0's hemisphere */
  bw: number; bx: number; by: number; bz: number;
  /** q0 . q1 >= 0 */
  dot: number;
  /** What b's quaternion was multiplied by (+1 or -1). */
  sign: number;
}

function unit(p: ArrayLike<number>, name: string): [number, number, number, number] {
  let w = p[3]!, x = p[4]!, y = p[5]!, z = p[6]!;
  const n2 = w * w + x * x + y * y + z * z;
  if (!Number.isFinite(n2) || !(n2 > 1e-24)) throw new RangeError(`expected \`${name}\` to hold a finite, non-zero quaternion`);
  if (Math.abs(n2 - 1) > 2 * UNIT_TOLERANCE) {
    const n = Math.sqrt(n2);
    w /= n; x /= n; y /= n; z /= n;
  }
  return [w, x, y, z];
}

/** The sign (+1 or -1) that puts q1 in q0's hemisphere; at an exact half turn
 * (dot 0) the relative rotation q0* q1's largest component is made positive. */
export function hemisphereSign(a: readonly number[], b: readonly number[], dot: number): number {
  if (dot !== 0) return dot > 0 ? 1 : -1;
  const [aw, ax, ay, az] = a as [number, number, number, number];
  const [bw, bx, by, bz] = b as [number, number, number, number];
  const rel = [
    aw * bx - ax * bw - ay * bz + az * by,
    aw * by + ax * bz - ay * bw - az * bx,
    aw * bz - ax * by + ay * bx - az * bw,
  ];
  let k = 0;
  for (let i = 1; i < 3; i++) if (Math.abs(rel[i]!) > Math.abs(rel[k]!)) k = i;
  // Python's argmax takes the first of equal magnitudes, as this loop does.
  return rel[k]! < 0 ? -1 : 1;
}

function prepare(a: ArrayLike<number>, b: ArrayLike<number>): Prepared {
  for (let i = 0; i < 7; i++) {
    if (!Number.isFinite(a[i]!) || !Number.isFinite(b[i]!)) throw new RangeError("expected `a` and `b` to hold 7 finite values");
  }
  const q0 = unit(a, "a");
  const q1 = unit(b, "b");
  const d = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3];
  const sign = hemisphereSign(q0, q1, d);
  return {
    t0x: a[0]!, t0y: a[1]!, t0z: a[2]!, t1x: b[0]!, t1y: b[1]!, t1z: b[2]!,
    aw: q0[0], ax: q0[1], ay: q0[2], az: q0[3],
    bw: sign * q1[0], bx: sign * q1[1], by: sign * q1[2], bz: sign * q1[3],
    dot: d * sign,
    sign,
  };
}

/** s = 0 and s = 1 give the (validated) keyframes exactly. */
function ends(p: Prepared, s: number): Pose | null {
  if (s === 0) return [p.t0x, p.t0y, p.t0z, p.aw, p.ax, p.ay, p.az];
  const k = p.sign; // undo the hemisphere flip: b as given
  if (s === 1) return [p.t1x, p.t1y, p.t1z, k * p.bw, k * p.bx, k * p.by, k * p.bz];
  return null;
}

/** Position LERP + shortest-path quaternion SLERP. */
export function soa(a: ArrayLike<number>, b: ArrayLike<number>, s: number): Pose {
  const p = prepare(a, b);
  const end = ends(p, s);
  if (end) return end;
  const r = 1 - s;
  const dw = p.bw - p.aw, dx = p.bx - p.ax, dy = p.by - p.ay, dz = p.bz - p.az;
  const mw = p.bw + p.aw, mx = p.bx + p.ax, my = p.by + p.ay, mz = p.bz + p.az;
  const nd = Math.sqrt(dw * dw + dx * dx + dy * dy + dz * dz);
  const nm = Math.sqrt(mw * mw + mx * mx + my * my + mz * mz);
  const sinW = 0.5 * nd * nm; // sin w, w the angle between q0 and q1
  const sw = 2 * s * Math.atan2(nd, nm);
  const sinSw = Math.sin(sw);
  const cosSw = Math.cos(sw);
  // sin((1-s) w) / sin w and sin(s w) / sin w, limits 1 - s and s at w = 0.
  const c0 = sinW === 0 ? r : (sinW * cosSw - p.dot * sinSw) / sinW;
  const c1 = sinW === 0 ? s : sinSw / sinW;
  return [
    p.t0x + s * (p.t1x - p.t0x),
    p.t0y + s * (p.t1y - p.t0y),
    p.t0z + s * (p.t1z - p.t0z),
    c0 * p.aw + c1 * p.bw,
    c0 * p.ax + c1 * p.bx,
    c0 * p.ay + c1 * p.by,
    c0 * p.az + c1 * p.bz,
  ];
}

/** Vector part of q0 q1* (motor LERP's c); minus it is that of q1 q0*. */
function cVec(p: Prepared): [number, number, number] {
  return [
    -p.aw * p.bx + p.ax * p.bw - p.ay * p.bz + p.az * p.by,
    -p.aw * p.by + p.ax * p.bz + p.ay * p.bw - p.az * p.bx,
    -p.aw * p.bz - p.ax * p.by + p.ay * p.bx + p.az * p.bw,
  ];
}

/** Dual-quaternion ScLERP: constant-speed screw motion from a to b. */
export function dqSlerp(a: ArrayLike<number>, b: ArrayLike<number>, s: number): Pose {
  const p = prepare(a, b);
  const end = ends(p, s);
  if (end) return end;
  const r = 1 - s;
  const c = cVec(p);
  const vx = -c[0], vy = -c[1], vz = -c[2]; // q1 q0* = (cos phi, sin(phi) u), world frame
  const sinPhi = Math.sqrt(vx * vx + vy * vy + vz * vz);
  const cosPhi = p.dot;
  const sphi = s * Math.atan2(sinPhi, cosPhi);
  const sinS = Math.sin(sphi);
  const cosS = Math.cos(sphi);
  const sinR = sinPhi * cosS - cosPhi * sinS; // sin((1-s) phi)
  const cosR = cosPhi * cosS + sinPhi * sinS; // cos((1-s) phi)
  const zero = sinPhi === 0;
  const div = zero ? 1 : sinPhi;
  const k = zero ? s : sinS / div;
  const kr = zero ? r : sinR / div;
  const kc = k * cosR;
  const dx = p.t1x - p.t0x, dy = p.t1y - p.t0y, dz = p.t1z - p.t0z;
  const ux = vx / div, uy = vy / div, uz = vz / div; // unit axis, or 0 without rotation
  const along = (s - kc) * (dx * ux + dy * uy + dz * uz);
  // v x D
  const cx = vy * dz - vz * dy, cy = vz * dx - vx * dz, cz = vx * dy - vy * dx;
  const kk = k * kr;
  return [
    p.t0x + (kc * dx + along * ux - kk * cx),
    p.t0y + (kc * dy + along * uy - kk * cy),
    p.t0z + (kc * dz + along * uz - kk * cz),
    kr * p.aw + k * p.bw,
    kr * p.ax + k * p.bx,
    kr * p.ay + k * p.by,
    kr * p.az + k * p.bz,
  ];
}

/** Motor LERP: blend (1-s) M0 + s M1 and divide by its Study number. */
export function motorLerp(a: ArrayLike<number>, b: ArrayLike<number>, s: number): Pose {
  const p = prepare(a, b);
  const end = ends(p, s);
  if (end) return end;
  const r = 1 - s;
  const c = cVec(p);
  const ux = p.t0x - p.t1x, uy = p.t0y - p.t1y, uz = p.t0z - p.t1z;
  // (t0 - t1) x c
  const xx = uy * c[2] - uz * c[1], xy = uz * c[0] - ux * c[2], xz = ux * c[1] - uy * c[0];
  const rr = r * r, ss = s * s, rs = r * s;
  const den = rr + ss + 2 * rs * p.dot;
  const tx = (rr * p.t0x + ss * p.t1x + rs * (p.dot * (p.t0x + p.t1x) + xx)) / den;
  const ty = (rr * p.t0y + ss * p.t1y + rs * (p.dot * (p.t0y + p.t1y) + xy)) / den;
  const tz = (rr * p.t0z + ss * p.t1z + rs * (p.dot * (p.t0z + p.t1z) + xz)) / den;
  const qw = r * p.aw + s * p.bw, qx = r * p.ax + s * p.bx, qy = r * p.ay + s * p.by, qz = r * p.az + s * p.bz;
  const n = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
  return [tx, ty, tz, qw / n, qx / n, qy / n, qz / n];
}

export const INTERPOLATORS: Readonly<Record<MethodName, Interpolator>> = {
  soa,
  "dq-slerp": dqSlerp,
  "motor-lerp": motorLerp,
};

/** The interpolator registered under `name`. */
export function interpolator(name: string): Interpolator {
  const fn = (INTERPOLATORS as Record<string, Interpolator>)[name];
  if (!fn) throw new RangeError(`unknown interpolator '${name}' (known: ${Object.keys(INTERPOLATORS).join(", ")})`);
  return fn;
}
