"""Write the JS SDK's shared test vectors from posecast's Python code.

- test/interp-vectors.json: pose pairs, fractions and what ``interp`` (soa,
  dq-slerp, motor-lerp) returns for them;
- test/receiver-vectors.json: a scripted run of the client core's
  ``RoomPlayoutDelay`` (``client.playout``; keyframe ages of three users, one of
  them late), of one with ``per_peer`` (users at their own keyframe intervals),
  and of a ``StreamBuffer`` (``client.buffers``; pushes, some duplicate
  or stale, and brackets).

Run from the repository root: ``.venv/bin/python client/js/test/make_vectors.py``.
Seeded: the same files every run.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from posecast.client.buffers import StreamBuffer
from posecast.client.playout import RoomPlayoutDelay
from posecast.interp import dq_slerp, motor_lerp, soa

OUT = Path(__file__).with_name("interp-vectors.json")
RECEIVER_OUT = Path(__file__).with_name("receiver-vectors.json")
FRACTIONS = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)


def _unit(q: np.ndarray) -> np.ndarray:
    out: np.ndarray = q / np.linalg.norm(q)
    return out


def _axis_angle(axis: list[float], angle: float) -> np.ndarray:
    a = _unit(np.asarray(axis, dtype=float))
    return np.array([math.cos(angle / 2), *(math.sin(angle / 2) * a)])


def pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Random pairs of every size of motion, and the edge cases of the formulas."""
    rng = np.random.default_rng(26)
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    for i in range(40):
        scale = [0.001, 0.05, 0.5, 3.0][i % 4]
        t0 = rng.uniform(-2, 2, 3)
        t1 = t0 + rng.normal(0, scale, 3)
        q0 = _unit(rng.normal(size=4))
        turn = [1e-4, 0.05, 0.6, 2.5][(i // 4) % 4]
        q1 = _unit(np.array([1.0, *(rng.normal(size=3) * turn)]))
        # q1 relative to q0, in either hemisphere
        w0, x0, y0, z0 = q0
        w1, x1, y1, z1 = q1
        prod = np.array(
            [
                w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1,
                w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1,
                w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1,
            ]
        )
        if i % 3 == 0:
            prod = -prod
        out.append((f"random-{i}", np.concatenate([t0, q0]), np.concatenate([t1, prod])))
    ident = np.array([1.0, 0, 0, 0])
    q = _axis_angle([0.3, 1, -0.2], 1.1)
    out += [
        ("same-rotation", np.array([0, 1.6, 0, *q]), np.array([0.4, 1.5, -0.3, *q])),
        ("same-pose", np.array([0.1, 1.2, 0.3, *q]), np.array([0.1, 1.2, 0.3, *q])),
        ("negated-q", np.array([0, 1, 0, *q]), np.array([0.2, 1, 0, *(-q)])),
        (
            "pure-rotation",
            np.array([0.5, 1, 0.5, *ident]),
            np.array([0.5, 1, 0.5, *_axis_angle([0, 1, 0], 2.0)]),
        ),
        ("half-turn", np.array([0, 1, 0, *ident]), np.array([1, 1, 0, 0.0, 0.0, 1.0, 0.0])),
        (
            "half-turn-negated",
            np.array([0, 1, 0, *ident]),
            np.array([1, 1, 0, 0.0, 0.0, -1.0, 0.0]),
        ),
        ("screw", np.array([0, 0, 0, *ident]), np.array([0, 0, 1.0, *_axis_angle([0, 0, 1], 1.5)])),
        ("tiny-rotation", np.array([0, 1, 0, *q]), np.array([0.01, 1, 0, *_unit(q + 1e-9)])),
        (
            "not-unit",
            np.array([0, 1, 0, *(q * 1.0005)]),
            np.array([0.2, 1.1, 0, *(_axis_angle([1, 0, 0], 0.4) * 0.9995)]),
        ),
    ]
    return out


def playout_script() -> dict[str, object]:
    """Four users at 20 Hz; user 2's keyframes arrive 0.3 s late from t = 1 s to 6 s,
    user 4's always 90 ms late (under the former fixed 100 ms bound)."""
    rng = np.random.default_rng(7)
    delay = RoomPlayoutDelay(interval=1 / 20)
    steps: list[dict[str, object]] = []
    t = 0.0
    while t < 7.0:
        t = round(t + 0.011, 6)
        obs = []
        for user in (1, 2, 3, 4):
            if rng.random() < 0.25:
                lag = 0.3 if user == 2 and 1 < t < 6 else 0.09 if user == 4 else 0.0
                age = float(0.02 + abs(rng.normal(0, 0.01)) + lag)
                delay.observe(user, age)
                obs.append([user, age])
        room = delay.update(t)
        steps.append(
            {
                "now": t,
                "observe": obs,
                "room": room,
                "own": {str(u): d for u, d in delay.own.items()},
            }
        )
    return {"interval": 1 / 20, "steps": steps}


def per_peer_script() -> dict[str, object]:
    """Per-peer D at 30 Hz: users 1 and 2 in every snapshot, 3 in every 4th, 4 in
    every 2nd and from t = 3 s in every 6th (it slows down), 5 late by 0.25 s from
    t = 2 s; each keyframe with its snapshot's send time."""
    rng = np.random.default_rng(31)
    rate = 30.0
    delay = RoomPlayoutDelay(interval=1 / rate, rate=rate, per_peer=True)
    steps: list[dict[str, object]] = []
    tick, snap = 0, 0.0
    for f in range(6 * 90):
        t = round(f / 90, 6)
        obs = []
        while snap <= t:
            every = {1: 1, 2: 1, 3: 4, 4: 2 if snap < 3 else 6, 5: 1}
            for user, k in every.items():
                if tick % k == 0:
                    lag = 0.25 if user == 5 and snap > 2 else 0.0
                    age = float(0.004 + abs(rng.normal(0, 0.008)) + lag)
                    delay.observe(user, age, snap)
                    obs.append([user, age, snap])
            tick += 1
            snap = round(tick / rate, 9)
        room = delay.update(t)
        steps.append(
            {
                "now": t,
                "observe": obs,
                "room": room,
                "own": {str(u): d for u, d in delay.own_delays().items()},
                "delay": {str(u): delay.delay(u) for u in (1, 2, 3, 4, 5)},
            }
        )
    return {"rate": rate, "steps": steps}


def buffer_script() -> dict[str, object]:
    """Pushes (in and out of order, duplicate, stale, over capacity) and brackets."""
    rng = np.random.default_rng(11)
    buf = StreamBuffer(capacity=8)
    ops: list[dict[str, object]] = []
    floor = -np.inf
    last = 0.0
    for i in range(60):
        capture = round(i * 0.05 + float(rng.normal(0, 0.02)), 6)
        if i % 7 == 3:
            capture = last  # a duplicate
        last = capture
        q = _unit(rng.normal(size=4))
        pose = np.concatenate([rng.uniform(-1, 1, 3), q]).astype(np.float32)
        took = buf.push(capture, pose, floor)
        ops.append(
            {
                "capture": capture,
                "pose": pose.astype(float).tolist(),
                "floor": floor if np.isfinite(floor) else None,
                "took": took,
            }
        )
        t = round(i * 0.05 - 0.12, 6)
        lo, hi, s, stall = buf.bracket(t)
        ops.append({"t": t, "times": list(buf.times), "lo": lo, "hi": hi, "s": s, "stalled": stall})
        floor = t - 0.1
    return {"capacity": 8, "ops": ops}


def main() -> int:
    cases = []
    for name, a, b in pairs():
        for s in FRACTIONS:
            cases.append(
                {
                    "name": name,
                    "a": a.tolist(),
                    "b": b.tolist(),
                    "s": s,
                    "soa": soa(a, b, s).tolist(),
                    "dq-slerp": dq_slerp(a, b, s).tolist(),
                    "motor-lerp": motor_lerp(a, b, s).tolist(),
                }
            )
    doc = {
        "about": "posecast interp/ results for the JS SDK's tests; regenerate with "
        "client/js/test/make_vectors.py",
        "cases": cases,
    }
    OUT.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
    print(f"wrote {len(cases)} cases to {OUT}", file=sys.stderr)
    receiver = {
        "about": "posecast scenarios.receiver runs for the JS SDK's tests; regenerate with "
        "client/js/test/make_vectors.py",
        "playout": playout_script(),
        "per_peer": per_peer_script(),
        "buffer": buffer_script(),
    }
    RECEIVER_OUT.write_text(json.dumps(receiver, separators=(",", ":")) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
