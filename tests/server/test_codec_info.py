"""GET /metrics says what runs the compact codec: the compiled accelerator or pure Python."""

from __future__ import annotations

from support import running_server
from test_http import http_get, parse_metrics

from posecast.protocol import _accel, codec


async def test_metrics_name_the_codec_implementation() -> None:
    """posecast_codec_info is 1, labelled with codec.IMPLEMENTATION, and follows a switch."""
    was_pure = _accel.speedups is None
    try:
        async with running_server() as srv:
            for pure in (False, True):
                _accel.use(pure)
                status, _, body = await http_get(srv.port, "/metrics")
                assert status == 200
                label = f'{{implementation="{codec.IMPLEMENTATION}"}}'
                assert parse_metrics(body)["posecast_codec_info"] == {label: 1.0}
    finally:
        _accel.use(was_pure)
