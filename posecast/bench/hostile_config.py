"""What ``posecast bench hostile`` runs: its settings, and the runs they make.

:class:`HostileConfig` holds the honest room and every attack's bounds (the CLI's
flags); :class:`RunSpec` is one run of the bench (an attack and its variant, or
the clean run). The controller is :mod:`posecast.bench.hostile`, the attacker
process :mod:`posecast.bench.hostile_attacker`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from posecast.bench.hostile_attacks import ATTACKS, AttackConfig

__all__ = ["WAIT_FOR_BOTS", "HostileConfig", "RunSpec", "victim_seconds"]

#: Attacks that start once the honest bots are in (``go``): a newcomer's join during
#: them is another matter (the relay may refuse it ``server-full`` while members
#: come and go), measured by none of them.
WAIT_FOR_BOTS = ("fuzz-in-room", "events-reconnect", "churn")


@dataclass(frozen=True)
class RunSpec:
    """One run: the attack (None: clean), its variant (a churn rate, a liar's lag in
    s), and the name the tables show."""

    kind: str | None
    variant: float | None = None

    @property
    def label(self) -> str:
        if self.kind is None:
            return "clean"
        if self.kind == "churn" and self.variant is not None:
            return f"churn {self.variant:g}/s"
        if self.kind == "lag-liar" and self.variant is not None:
            return f"lag-liar {1e3 * self.variant:g} ms"
        return self.kind


def victim_seconds(cfg: HostileConfig) -> float:
    """How long the blackhole run's bots play: long enough for the blackholed one to notice
    (keepalive: 5 s) and resume, with a few seconds more to see it back."""
    return max(cfg.duration, cfg.blackhole_after + 12.0)


@dataclass
class HostileConfig:
    """What ``posecast bench hostile`` runs: the honest room and each attack's bounds."""

    bots: int = 4
    rate: float = 20.0
    send_rate: float = 30.0
    duration: float = 10.0
    motion: str = "traces:sample"
    method: str = "soa"
    room: str = "lobby"
    attacks: tuple[str, ...] = ATTACKS
    attacker_nice: int = 10
    address: str = "127.0.0.2"
    addresses: int = 1
    stamp_age: float = 2.0
    fuzz_frames: int = 200_000
    fuzz_connections: int = 8
    flood_connections: int = 2000
    flood_rate: float = 250.0
    rooms: int = 300
    rooms_rate: float = 100.0
    sample_interval: float = 0.25
    server_args: tuple[str, ...] = field(default_factory=tuple)
    # -- issue 29 -------------------------------------------------------------------
    room_fuzzers: int = 10
    event_rate: float = 10_000.0
    churn_rates: tuple[float, ...] = (57.0, 30.0)
    liar_lags: tuple[float, ...] = (0.03, 0.09, 0.3)
    slowloris_connections: int = 3000
    slowloris_rate: float = 1000.0
    slowloris_addresses: int = 64
    hijack_attempts: int = 20
    blackhole_after: float = 3.0

    def check(self) -> None:
        """ValueError (one line) for a bad setting."""
        unknown = [a for a in self.attacks if a not in ATTACKS]
        if unknown:
            raise ValueError(f"unknown attack {unknown[0]!r}: one of {', '.join(ATTACKS)}")
        if self.bots < 2:
            raise ValueError("bots must be at least 2 (each scores what the others send)")
        if min(self.rate, self.send_rate, self.duration, self.sample_interval) <= 0:
            raise ValueError("rate, send rate, duration and sample interval must be positive")
        counts = (self.fuzz_frames, self.fuzz_connections, self.flood_connections, self.rooms)
        if min(*counts, self.addresses) < 1 or min(self.flood_rate, self.rooms_rate) <= 0:
            raise ValueError("attack counts and rates must be positive")
        more = (self.room_fuzzers, self.slowloris_connections, self.slowloris_addresses)
        rates = (self.event_rate, self.slowloris_rate, *self.churn_rates, *self.liar_lags)
        if min(*more, self.hijack_attempts) < 1 or min(rates, default=0) <= 0:
            raise ValueError("attack counts, rates and lags must be positive")
        if not self.churn_rates or not self.liar_lags or self.blackhole_after < 0:
            raise ValueError("give a churn rate and a liar lag; blackhole-after must be >= 0")

    def attack(self, run: RunSpec, url: str, secret_file: Path | None = None) -> AttackConfig:
        kind = run.kind
        assert kind is not None
        lag = run.variant if kind == "lag-liar" else None
        seconds = self.duration + 15.0
        if kind == "blackhole":  # it cuts the path on the controller's word (hostile_runs.Signal)
            seconds = victim_seconds(self) + 15.0
        return AttackConfig(
            kind=kind,
            url=url,
            room=self.room,
            seconds=seconds,
            address=self.address,
            addresses=self.slowloris_addresses if kind == "slowloris" else self.addresses,
            # Spread over the bots' run (plus their start), not all in its first seconds.
            fuzz_rate=self.fuzz_frames / (self.duration + 1.0),
            stamp_age=self.stamp_age if lag is None else lag,
            fuzz_frames=self.fuzz_frames,
            fuzz_connections=self.fuzz_connections,
            flood_connections=self.flood_connections,
            flood_rate=self.flood_rate,
            rooms=self.rooms,
            rooms_rate=self.rooms_rate,
            room_fuzzers=self.room_fuzzers,
            event_rate=self.event_rate,
            churn_rate=run.variant if kind == "churn" and run.variant else 57.0,
            slowloris_connections=self.slowloris_connections,
            slowloris_rate=self.slowloris_rate,
            secret_file=None if secret_file is None else str(secret_file),
            hijack_attempts=self.hijack_attempts,
            blackhole_after=-1.0,
            wait_for="go" if kind in WAIT_FOR_BOTS else None,
        )
