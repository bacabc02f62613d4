"""The relay sheds load instead of collapsing: its capacity from its own measurements.

The decision (``server.capacity``) is tested with made-up measurements and times,
never a real clock; the core's refusals with protocol bytes and fake times; then a
real relay on loopback refuses a real client (``server-full``, close 1013) once its
own measurements say it is full, and a bot given two relays goes to the second.
"""

from __future__ import annotations

import asyncio
import math

import pytest
from support import poll_until, running_server
from test_core import Client, connect
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import ConnectionClosed

from posecast.client.bot import BotConfig, run_bot
from posecast.protocol import ClientSession, ErrorMessage, Hello, Join, Joined, PeerJoined, Welcome
from posecast.server.capacity import (
    GROWTH_MIN,
    LAG_CPU_FLOOR,
    LAG_MIN_MEMBERS,
    PRESSURE_TICKS,
    RETRY_AFTER,
    Capacity,
    CapacityBudget,
    stale_error_due,
)
from posecast.server.core import Close, RelayCore, ServerConfig

# -- the decision, from injected measurements -----------------------------------------------


def measured(cpu: float, members: int, budget: CapacityBudget | None = None) -> Capacity:
    """A capacity that measured ``cpu`` of a core over the window [0, 1] with ``members``."""
    cap = Capacity(budget or CapacityBudget(min_members=0))
    cap.sample(0.0, 100.0, 0, members)
    cap.sample(1.0, 100.0 + cpu, 0, members)
    return cap


def test_few_members_are_never_refused_for_cpu_or_lag() -> None:
    """Below ``min_members`` (16 by default) a busy process or a late tick is someone
    else's (bots sharing the process, other programs): no refusal; from 16, it counts."""
    cap = Capacity()
    cap.sample(0.0, 100.0, 0, 5)
    cap.sample(1.0, 100.9, 0, 5)  # 0.9 of a core "for" 5 members
    for t in (1.1, 1.2, 1.3):
        cap.tick_lag(t, 0.2)  # every tick 200 ms late
    assert cap.refusal(5, 1.4) is None
    assert cap.refusal(15, 1.4) is None
    assert cap.refusal(16, 1.4) is not None


def test_cpu_admits_until_one_more_member_is_over_budget() -> None:
    """0.7 of a core for 50 members: a 57th fits under 0.8 (0.798), a 58th does not."""
    cap = measured(0.7, 50)
    assert cap.cpu == pytest.approx(0.7) and cap.cpu_members == 50
    assert cap.refusal(50, 1.2) is None
    assert cap.refusal(56, 1.2) is None
    why = cap.refusal(57, 1.2)
    assert why is not None and "58 members would use 0.81 of a core" in why


def test_growth_per_reading_is_bounded() -> None:
    """Half the members of the last reading join before the next one (at least
    GROWTH_MIN): a burst of joins cannot outrun the measurements."""
    cap = measured(0.1, 50)  # room for far more, by CPU
    assert cap.refusal(74, 1.2) is None  # the 25th since the reading
    why = cap.refusal(75, 1.2)
    assert why is not None and "full for now: 75 members" in why
    small = measured(0.01, 2)
    assert small.refusal(2 + GROWTH_MIN - 1, 1.2) is None
    assert small.refusal(2 + GROWTH_MIN, 1.2) is not None
    cap.sample(2.0, 100.2, 0, 75)  # the next reading: half of 75 more may come
    assert cap.refusal(75 + 36, 2.2) is None and cap.refusal(75 + 37, 2.2) is not None


def test_members_admitted_since_the_window_count() -> None:
    """A ramp cannot overshoot by a window's joins: the reading scales to members now."""
    cap = measured(0.4, 40)
    assert cap.usage(40, 1.5)["cpu"] == pytest.approx(0.4 * 41 / 40 / 0.8)
    assert cap.usage(90, 1.5)["cpu"] == pytest.approx(0.4 * 91 / 40 / 0.8)


def test_a_window_serves_the_mean_of_its_members() -> None:
    """Members that joined during the window cost only part of it: 20 then 60 -> 40."""
    cap = Capacity()
    cap.sample(0.0, 10.0, 0, 20)
    cap.sample(0.5, 10.1, 0, 40)  # (not a window yet)
    cap.sample(1.0, 10.4, 0, 60)
    assert cap.cpu == pytest.approx(0.4) and cap.cpu_members == 40


def test_an_empty_or_unmeasured_relay_admits() -> None:
    """No reading yet, no members when measured, or a reading too old: no CPU verdict."""
    assert Capacity().refusal(1000, 5.0) is None
    assert measured(0.9, 0).refusal(10, 1.5) is None
    cap = measured(0.9, 10)
    assert cap.refusal(10, 1.5) is not None
    assert cap.refusal(10, 1.0 + 6 * cap.budget.window) is None


def test_tick_lag_refuses_only_a_loaded_relay() -> None:
    """Over 1 % of a window's ticks later than the budget: full, if the relay uses at
    least LAG_CPU_FLOOR of a core, or holds LAG_MIN_MEMBERS (starved of CPU by other
    work, it uses little); a near-idle relay's lag is its machine's."""
    few = LAG_MIN_MEMBERS - 2
    busy = measured(LAG_CPU_FLOOR + 0.05, few)
    idle = measured(LAG_CPU_FLOOR - 0.05, few)
    for cap in (busy, idle):
        for i in range(200):
            cap.tick_lag(1.0 + i * 0.001, 0.100 if i < 3 else 0.001)  # 1.5 % late
    why = busy.refusal(few, 1.3)
    assert why is not None and "ticks run over 25 ms late" in why
    assert idle.refusal(few, 1.3) is None
    assert busy.usage(few, 1.3)["lag"] == pytest.approx(1.5)
    starved = idle.refusal(LAG_MIN_MEMBERS, 1.3)  # the same idle CPU, many members
    assert starved is not None and "ticks run over" in starved


def test_one_late_tick_in_a_hundred_is_within_budget() -> None:
    cap = measured(0.5, 100)
    for i in range(100):
        cap.tick_lag(1.0 + i * 0.001, 0.5 if i == 0 else 0.0)
    assert cap.usage(100, 1.2)["lag"] == pytest.approx(1.0)
    assert cap.refusal(100, 1.2) is None


def test_lag_is_forgotten_two_windows_later() -> None:
    """The current window and the one before count; after that, the lag is gone."""
    cap = measured(0.5, 100)
    for i in range(10):
        cap.tick_lag(1.0 + i * 0.01, 0.2)
    assert cap.refusal(100, 1.5) is not None
    assert cap.lateness(1.5) == pytest.approx(0.2) and cap.late == pytest.approx(0.2)
    cap.tick_lag(2.05, 0.0)  # a new window: the late one is the previous
    assert cap.refusal(100, 2.1) is not None and cap.late == pytest.approx(0.2)
    cap.tick_lag(3.1, 0.0)  # and now it is gone
    assert cap.refusal(100, 3.2) is None
    assert cap.lateness(3.2) == 0.0 and cap.late == 0.0
    assert cap.lateness(10.0) == 0.0  # idle since: nothing recent


def test_backlog_over_budget_refuses() -> None:
    cap = Capacity(CapacityBudget(backlog=1 << 20))
    cap.sample(0.0, 0.0, 2 << 20, 10)
    why = cap.refusal(10, 0.5)
    assert why is not None and "2 MiB unsent" in why


def test_a_zero_budget_turns_its_signal_off() -> None:
    cap = measured(5.0, 10, CapacityBudget(cpu=0.0, lag=0.0, backlog=0))
    for i in range(100):
        cap.tick_lag(1.0 + i * 0.001, 10.0)
    cap.sample(1.5, 200.0, 1 << 40, 10)
    assert cap.refusal(1000, 1.6) is None
    assert cap.usage(1000, 1.6) == {"cpu": 0.0, "lag": 0.0, "backlog": 0.0, "growth": 0.0}


# -- the core's refusals -----------------------------------------------------------------------

#: A relay whose CPU and lag count from its first member (by default from 16: fewer
#: cannot load a core by themselves, see test_few_members_are_never_refused_for_cpu).
SMALL = ServerConfig(capacity_min_members=0)


def full_core(members: int = 1) -> tuple[RelayCore, list[Client]]:
    """A core with ``members`` members whose capacity measured 0.9 of a core for them."""
    core = RelayCore(SMALL)
    clients = [connect(core, 0.5) for _ in range(members)]
    core.capacity.sample(0.0, 0.0, 0, members)
    core.capacity.sample(1.0, 0.9, 0, members)
    return core, clients


def test_a_hello_over_capacity_is_refused_server_full_1013() -> None:
    """At once, fatal, with retry_after (asked); close 1013; the members hear nothing."""
    core, (a,) = full_core()
    a.read(1.0)
    c = Client(core, core.connect(1.5))
    actions = c.send(Hello(agent="late", wants_retry_after=True), 1.5)
    (err,) = c.read(1.5)
    assert isinstance(err, ErrorMessage)
    assert (err.code, err.fatal, err.in_reply_to, err.retry_after) == (
        "server-full",
        True,
        "hello",
        RETRY_AFTER,
    )
    assert "2 members would use 1.80 of a core" in err.message and "retry in 5 s" in err.message
    (close,) = [x for x in actions if isinstance(x, Close)]
    assert close.code == 1013 and close.reason.startswith("try again later: the relay is full")
    assert a.read(1.5) == [] and len(core.rooms["lobby"].members) == 1
    assert core.capacity.joins_refused == {"server-full": 1}
    core.disconnect(c.conn, 1.6)
    assert core.users.take() is not None  # (no user id was taken by the refused hello)


def test_retry_after_goes_only_to_a_client_that_asked() -> None:
    """A new field is sent on request only (the compatibility policy): without
    hello.wants_retry_after the same error, its message saying when to retry."""
    core, _ = full_core()
    c = Client(core, core.connect(1.5))
    c.send(Hello(agent="old"), 1.5)
    (err,) = c.read(1.5)
    assert isinstance(err, ErrorMessage) and err.code == "server-full"
    assert err.retry_after is None and "retry in 5 s" in err.message
    assert "retry_after" not in err.to_wire()


def test_a_join_over_capacity_is_refused_too() -> None:
    """A hello welcomed while there was room, a join when there is none: server-full."""
    core = RelayCore(SMALL)
    a = connect(core, 0.5)
    c = Client(core, core.connect(0.6))
    c.send(Hello(agent="c"), 0.6)
    assert isinstance(c.read(0.6)[0], Welcome)
    core.capacity.sample(0.0, 0.0, 0, 1)
    core.capacity.sample(1.0, 0.9, 0, 1)
    actions = c.send(Join(room="lobby", streams=("head",), rate=10.0), 1.5)
    (err,) = [e for e in c.read(1.5) if isinstance(e, ErrorMessage)]
    assert (err.code, err.in_reply_to, err.fatal) == ("server-full", "join", True)
    assert [x.code for x in actions if isinstance(x, Close)] == [1013]
    assert not [e for e in a.read(1.5) if isinstance(e, PeerJoined)]


def test_a_member_resuming_its_dropped_connection_is_never_shed() -> None:
    """Its hello (with its resume token) and its join come back in, full or not."""
    core = RelayCore(SMALL)
    a = Client(core, core.connect(0.5))
    a.send(Hello(agent="a", resumable=True), 0.5)
    (welcome,) = a.read(0.5)
    assert isinstance(welcome, Welcome) and welcome.resume
    a.send(Join(room="lobby", streams=("head",), rate=10.0), 0.5)
    a.read(0.5)
    core.disconnect(a.conn, 0.8)  # dropped: parked
    core.capacity.sample(0.0, 0.0, 0, 1)
    core.capacity.sample(1.0, 0.9, 0, 1)
    b = Client(core, core.connect(1.2))
    b.send(Hello(agent="a", resumable=True, resume=welcome.resume), 1.2)
    (again,) = b.read(1.2)
    assert isinstance(again, Welcome) and again.resumed
    b.send(Join(room="lobby", streams=("head",), rate=10.0), 1.2)
    assert any(isinstance(e, Joined) for e in b.read(1.2))
    assert core.capacity.joins_refused == {}


def test_room_full_refusals_are_counted_by_code() -> None:
    core = RelayCore(ServerConfig(max_members=1))
    connect(core, 0.5)
    c = Client(core, core.connect(0.6))
    c.send(Hello(agent="c"), 0.6)
    c.read(0.6)
    c.send(Join(room="lobby", streams=("head",), rate=10.0), 0.6)
    assert [e.code for e in c.read(0.6) if isinstance(e, ErrorMessage)] == ["room-full"]
    assert core.capacity.joins_refused == {"room-full": 1}


# -- a late relay does not blame its clients -----------------------------------------------------


def test_a_late_relay_widens_the_capture_age_by_its_own_lateness() -> None:
    """An update read 1.5 s after its capture while the relay's ticks run 0.8 s late is
    the relay's doing: kept. Without the relay's lag it is stale (max_capture_age 1 s)."""
    for lag, kept in ((0.0, False), (0.8, True)):
        core = RelayCore(SMALL)
        a = connect(core, 10.0)
        core.capacity.tick_lag(10.0, lag)
        a.publish(10.2, capture=8.7)
        stats = core.peer(a.conn).statistics()
        assert (stats.stale_captures == 0) == kept, lag
        errors = [e for e in a.read(10.2) if isinstance(e, ErrorMessage)]
        assert len(errors) == (0 if kept else 1)


def test_stale_updates_get_one_error_a_second_not_one_each() -> None:
    """Each stale update is refused and counted; errors go out once a second at most."""
    core = RelayCore(ServerConfig(max_update_rate=1000.0))
    a = connect(core, 10.0)
    for i in range(300):
        a.publish(10.0 + 0.01 * i, capture=1.0)  # 3 s of 100 updates/s, all stale
    stats = core.peer(a.conn).statistics()
    assert stats.stale_captures == 300
    errors = [e for e in a.read(13.0) if isinstance(e, ErrorMessage)]
    assert [e.code for e in errors] == ["bad-pose"] * 3
    assert core.peer(a.conn).close_request is None


def test_stale_error_due_once_per_interval() -> None:
    class P:
        stale_error_at = -math.inf

    p = P()
    assert stale_error_due(p, 5.0)  # type: ignore[arg-type]
    assert not stale_error_due(p, 5.9)  # type: ignore[arg-type]
    assert stale_error_due(p, 6.0)  # type: ignore[arg-type]


# -- a real relay on loopback ------------------------------------------------------------------


async def _member(url: str, room: str) -> tuple[object, ClientSession]:
    """A real websocket client that said hello and joined ``room`` (kept open)."""
    ws = await ws_connect(url)
    session = ClientSession()
    await ws.send(session.send(Hello(agent="holder")))
    session.receive_data(await ws.recv())
    await ws.send(session.send(Join(room=room, streams=("head",), rate=10.0)))
    while not any(isinstance(e, Joined) for e in session.receive_data(await ws.recv())):
        pass
    return ws, session


# A budget no relay with a member meets: its first CPU reading makes it full.
TINY = ServerConfig(host="127.0.0.1", port=0, capacity_cpu=1e-9, capacity_min_members=0)


async def _full_relay_refuses() -> None:
    async with running_server(TINY) as server:
        url = f"ws://127.0.0.1:{server.port}"
        holder, _ = await _member(url, "r")
        cap = server.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        ws = await ws_connect(url)
        session = ClientSession()
        await ws.send(session.send(Hello(agent="late", wants_retry_after=True)))
        events = session.receive_data(await ws.recv())
        with pytest.raises(ConnectionClosed):
            await ws.recv()
        assert ws.close_code == 1013 and "the relay is full" in (ws.close_reason or "")
        (err,) = events
        assert isinstance(err, ErrorMessage) and err.code == "server-full"
        assert err.retry_after == RETRY_AFTER
        assert len(server.rooms["r"].members) == 1
        metrics = server.metrics_text()
        assert 'posecast_joins_refused_total{code="server-full"} 1' in metrics
        assert 'posecast_capacity_used_ratio{signal="cpu"}' in metrics
        await holder.close()  # type: ignore[attr-defined]


def test_a_real_relay_over_its_measured_budget_refuses_server_full() -> None:
    """Its own CPU reading (budget set tiny) makes it full: a real client's hello gets
    server-full with retry_after, close 1013; its member stays; /metrics counts it."""
    asyncio.run(_full_relay_refuses())


async def _bot_moves_on() -> tuple[str, str, str, int]:
    async with running_server(TINY) as full, running_server() as free:
        url_full, url_free = (f"ws://127.0.0.1:{s.port}" for s in (full, free))
        holder, _ = await _member(url_full, "r")
        cap = full.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        cfg = BotConfig(
            urls=(url_full, url_free),
            room="r",
            rate=20,
            duration=1.0,
            methods=("soa",),
            motion="synthetic:orbit",
        )
        report = await run_bot(cfg)
        await holder.close()  # type: ignore[attr-defined]
        refused = full.core.capacity.joins_refused.get("server-full", 0)
        return report.relay, url_free, report.ending.kind, refused


def test_a_bot_given_two_relays_gets_onto_the_second_when_the_first_is_full() -> None:
    """The full relay refuses its hello (server-full); its URL list moves on."""
    relay, url_free, ending, refused = asyncio.run(_bot_moves_on())
    assert relay == url_free and ending == "complete" and refused == 1


# -- a relay too late for its rooms' rates ---------------------------------------------------


def test_overloaded_when_a_tenth_of_the_ticks_run_late_for_the_members() -> None:
    """Over PRESSURE_SHARE of a window's ticks (of at least PRESSURE_TICKS) later than the
    lag budget, on a loaded relay: it cannot carry its rooms at their rates. One late
    tick in a few, lateness for a join storm, a near-idle relay (its machine is busy:
    lower rates would not help) or a lag budget of 0 is no pressure."""

    def loaded(budget: CapacityBudget | None = None) -> Capacity:
        return measured(0.5, LAG_MIN_MEMBERS, budget)  # (read at t = 1.0)

    cap = loaded()
    for i in range(PRESSURE_TICKS - 1):
        cap.tick_lag(1.0 + 0.01 * i, 0.100)  # all late, but too few ticks to judge
    assert not cap.overloaded(1.1)
    cap.tick_lag(1.095, 0.100)
    assert cap.overloaded(1.1)
    assert not cap.overloaded(3.5)  # two windows later it is forgotten

    mild = loaded()
    for i in range(100):
        mild.tick_lag(1.0 + 0.005 * i, 0.100 if i < 10 else 0.001)  # 10 %: not over
    assert not mild.overloaded(1.6)
    mild.tick_lag(1.6, 0.100)
    assert mild.overloaded(1.6)

    storm = loaded()
    for i in range(20):
        t = 1.0 + 0.05 * i
        storm.join_work(t - 0.1, t, 0.1)  # join work ran since each tick was due
        storm.tick_lag(t, 0.100)
    assert not storm.overloaded(2.0) and storm.ticks_late == 20

    idle = measured(LAG_CPU_FLOOR - 0.05, 4, CapacityBudget(min_members=0))
    off = loaded(CapacityBudget(lag=0.0, min_members=0))
    for c in (idle, off):
        for i in range(20):
            c.tick_lag(1.0 + 0.01 * i, 0.100)
        assert not c.overloaded(1.2)
