"""A compact bot and a raw bot in one room of a real relay on loopback."""

from __future__ import annotations

import asyncio

from support import running_server

from posecast.client.bot import BotConfig, BotReport, motion_for_bot, run_bot
from posecast.client.swarm import swarm_report

#: What a raw snapshot spends a pose (SNAPSHOT_ENTRY_SIZE): compact updates beat it.
RAW_SNAPSHOT_POSE = 36


async def _session() -> list[BotReport]:
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        configs = [
            BotConfig(
                url=url,
                room="codec",
                rate=15,
                motion=motion_for_bot("traces:sample", i)[0],
                duration=3,
                methods=("soa",),
                name=codec,
                codec=codec,
            )
            for i, codec in enumerate(("compact", "raw"))
        ]
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(run_bot(c)) for c in configs]
    return [t.result() for t in tasks]


def test_compact_and_raw_bots_see_each_other() -> None:
    compact, raw = asyncio.run(_session())
    for rep, other in ((compact, raw), (raw, compact)):
        assert rep.ending.kind == "complete", rep.ending
        names = sorted(rs.name for rs in rep.streams.values())
        assert names == ["head", "left", "right"]
        assert {rs.user for rs in rep.streams.values()} == {other.user}
        assert rep.poses_received > 0 and rep.poses_sent > 0
    up_compact = compact.update_bytes / compact.poses_sent
    up_raw = raw.update_bytes / raw.poses_sent
    print(f"\nupstream bytes per pose: compact {up_compact:.2f}, raw {up_raw:.2f}")
    assert up_compact < RAW_SNAPSHOT_POSE < up_raw
    # Downstream: the compact bot gets relay delta snapshots without its own streams.
    down_compact = compact.snapshot_bytes / compact.poses_received
    down_raw = raw.snapshot_bytes / raw.poses_received
    print(f"downstream bytes per pose: compact {down_compact:.2f}, raw {down_raw:.2f}")
    assert down_compact < 16 < RAW_SNAPSHOT_POSE < down_raw
    wire = swarm_report([compact, raw])["wire"]
    assert wire["codec"] == "compact+raw"
    assert wire["up_bytes_per_pose"] == (compact.update_bytes + raw.update_bytes) / (
        compact.poses_sent + raw.poses_sent
    )
