"""``posecast bench relay``: how much load one relay process carries, in figures.

Processes on loopback:

- the **server**: ``posecast serve --port 0`` started as a subprocess (or, for
  ``--baseline``, the bare broadcast server of :mod:`.baseline`); its CPU time
  is read from ``/proc/<pid>/stat`` and its counters from ``GET /metrics``;
- the **load**: ``--procs`` subprocesses sharing the clients (:mod:`.fleet`),
  each running its share in one event loop (:mod:`.load`). A client is a bare
  websocket connection (:mod:`.wsclient`: websockets' sans-I/O client,
  snapshots cut out of each read, no task per connection) that does the
  hello/join handshake through the protocol's session, then publishes its
  three streams (head, left, right) at ``rate`` Hz from pre-encoded frames
  (raw or ``--codec compact``) and subscribes at ``rate``. Snapshots are
  counted from their headers; one in 16 of a client's is decoded for capture
  -> receipt latency;
- this process, which starts them, fixes the measurement window once every
  client has joined and a warm-up has passed, samples CPU and metrics at both
  ends of the window, prints the report and says who was saturated.

CLOCK_MONOTONIC is system-wide, so the server's clock (``time.monotonic``) and
the load's are the same clock: capture-to-receipt latency is receipt time minus
capture time, with no clock sync. Figures per pose count **remote** poses, i.e.
not the echo of a subscriber's own streams that raw snapshots also carry.

Every wait is bounded and every child is killed on the way out.

Modules: :mod:`.common` (what the processes share), :mod:`.wsclient` (the
load's websocket client and pre-encoded updates), :mod:`.load` (a load
process), :mod:`.fleet` (the load processes as one), :mod:`.baseline` (the bare
broadcast server), :mod:`.procs` (children, /proc and /metrics), :mod:`.relay`
(the runs), :mod:`.sweep` (the curve over client counts, the baseline beside
it), :mod:`.recorder` (the recorder's cost, Table 4), :mod:`.report` (the
printed report, who was saturated), :mod:`.cluster` (``--nodes N``: the same
load on one relay, then split over N relays on a local nats-server).
"""

from posecast.bench.common import STREAMS, update_template
from posecast.bench.relay import run_relay_bench
from posecast.bench.report import print_relay_report
from posecast.bench.sweep import parse_counts, run_relay_curve

__all__ = [
    "STREAMS",
    "parse_counts",
    "print_relay_report",
    "run_relay_bench",
    "run_relay_curve",
    "update_template",
]
