"""Session files: record a room to MCAP, read it back, recover it after a crash.

- :class:`SessionRecorder` (``recorder.writer``): the relay's non-blocking tap;
  a bounded queue and a writer thread; ``NAME.mcap.part`` renamed on close.
- :class:`ProcessRecorder`, :class:`RecorderHost` (``recorder.host``): the same
  tap with the writer in a child process (``recorder.writerproc``) fed the raw
  update frames through a pipe (``recorder.pipe``); what the server uses. The
  host owns the child and the pipe; one room's side (batches, losses, counters,
  close) is ``recorder.hostroom``.
- ``recorder.tap``: the ``record_*`` encoders both recorders share, their
  counters and :class:`RecorderError`.
- :class:`RecordOptions` (``recorder.options``): how a room is recorded, for
  either recorder.
- :func:`recover`, :func:`find_leftovers`, :func:`recover_leftovers`
  (``recorder.recovery``): chunk-by-chunk recovery of a ``.part`` file.
- :class:`SessionReader`, :func:`info`, :func:`format_info`, :func:`load_streams`,
  :func:`read_records` (``recorder.reader``): records, time ranges, arrays.
- ``recorder.format``: channels, the pose message layout, :class:`PoseRecord`.
- ``recorder.objects``: shared objects read back (records, ownership changes,
  keyframes as the room stored them); ``recorder.plan``: what a live replay sends.
- ``recorder.scan``: the forgiving linear MCAP parser behind recovery.
"""

from posecast.recorder.format import FormatError, PoseRecord, decode_pose, encode_pose
from posecast.recorder.host import ProcessRecorder, RecorderHost, RoomRecorder
from posecast.recorder.options import RecordOptions
from posecast.recorder.reader import (
    DropRecord,
    EventRecord,
    PoseColumns,
    PresenceRecord,
    Record,
    SessionReader,
    StreamData,
    UserInfo,
    decode_poses,
    format_info,
    info,
    load_streams,
    read_records,
)
from posecast.recorder.recovery import (
    RecoveryError,
    RecoveryReport,
    find_leftovers,
    recover,
    recover_leftovers,
)
from posecast.recorder.scan import ScanProblem
from posecast.recorder.tap import RecorderError, RecorderStatistics
from posecast.recorder.writer import SessionRecorder

__all__ = [
    "DropRecord",
    "EventRecord",
    "FormatError",
    "PoseColumns",
    "PoseRecord",
    "PresenceRecord",
    "ProcessRecorder",
    "Record",
    "RecordOptions",
    "RecorderError",
    "RecorderHost",
    "RecorderStatistics",
    "RecoveryError",
    "RecoveryReport",
    "RoomRecorder",
    "ScanProblem",
    "SessionReader",
    "SessionRecorder",
    "StreamData",
    "UserInfo",
    "decode_pose",
    "decode_poses",
    "encode_pose",
    "find_leftovers",
    "format_info",
    "info",
    "load_streams",
    "read_records",
    "recover",
    "recover_leftovers",
]
