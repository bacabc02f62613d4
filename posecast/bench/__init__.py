"""``posecast bench relay``: how much load one relay process carries, in figures.

Three processes on loopback:

- the **server**: ``posecast serve --port 0`` started as a subprocess; its CPU
  time is read from ``/proc/<pid>/stat`` and its counters from ``GET /metrics``;
- the **load**: one subprocess running every client in one asyncio loop. Each
  client is a raw websocket that does the hello/join handshake, then publishes
  its three streams (head, left, right) at ``rate`` Hz with capture time
  ``time.monotonic()`` and subscribes at ``rate``. No session checks, no
  jitter buffer, no interpolation: an update is the protocol's own wire map
  re-packed with a new seq and time, a snapshot is unpacked and its records
  viewed as ``protocol.SNAPSHOT_DTYPE`` in batches;
- this process, which starts both, fixes the measurement window once every
  client has joined and a warm-up has passed, samples CPU and metrics at both
  ends of the window, and prints the report.

CLOCK_MONOTONIC is system-wide, so the server's clock (``time.monotonic``) and
the load's are the same clock: capture-to-receipt latency is receipt time minus
capture time, with no clock sync. Figures per pose count **remote** poses, i.e.
not the echo of a subscriber's own streams that snapshots also carry.

Every wait is bounded and every child is killed on the way out.

Modules: :mod:`.common` (what both processes share), :mod:`.load` (the load
process), :mod:`.procs` (children, /proc and /metrics), :mod:`.relay` (the runs),
:mod:`.recorder` (the recorder's cost, Table 4), :mod:`.report` (the printed report).
"""

from posecast.bench.common import STREAMS, update_template
from posecast.bench.relay import run_relay_bench
from posecast.bench.report import print_relay_report

__all__ = ["STREAMS", "print_relay_report", "run_relay_bench", "update_template"]
