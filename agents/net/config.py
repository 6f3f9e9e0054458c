"""How a team runs: the run configuration handed to every process, and the protocol's
timing constants (queues, flow control, when a silent peer is reconnected)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["RunConfig", "MODES", "QUEUE_SIZE", "MONITOR_LAG", "ACK_EVERY", "UNHEARD_S", "TOKENS_SETTLE_S", "RECONNECTS", "LAZY",
           "MAX_AHEAD"]

MODES = ("lockstep", "realtime")
QUEUE_SIZE = 1 << 16
MONITOR_LAG = 128  # the monitor closes round k once truth k + LAG arrived
ACK_EVERY = 32
#: a process that rejoined a running team and hears nothing from some peer for this long
#: opens a new session (transport.zenoh_bus.ZenohBus.reconnect), at most RECONNECTS times
UNHEARD_S = 3.0
TOKENS_SETTLE_S = 1.0  # a rejoining monitor: no new token for this long before its record starts
RECONNECTS = 5
#: lazy items wake a role that set no other bound once this many wait (see Role.lazy_items)
LAZY = QUEUE_SIZE // 2
MAX_AHEAD = 512  # lockstep: the plant waits when the monitor is this many rounds behind


@dataclass(frozen=True)
class RunConfig:
    """How the team runs (picklable: handed to spawned processes).

    mode : "lockstep" or "realtime"
    rate : Hz; required for realtime (the plant's wall-clock tick); in lockstep an
        optional upper bound on the round rate (pacing)
    deadline : seconds a lockstep round waits for a missing agent or message
    startup_timeout : seconds to wait for the team to assemble
    save_estimates : the monitor also writes ``estimates.npy`` and ``truth.npy``
    linger : seconds the monitor waits for the final counters after the last round
    warmup : scenario seconds an agent that joins a running team (round > 0) listens
        before it publishes (its estimate converges first instead of disturbing its
        neighbours); the monitor records it from its first round
    deliveries : each agent process writes the delivery record (:mod:`agents.deliveries`)
        into the run directory (off: benchmarks measuring its cost)
    sign : the directory of the team's signing keys (``rse certs``): every estimate is
        signed and equivocation becomes evidence (:mod:`agents.net.evidence_net`); None: off
    """

    mode: str = "lockstep"
    rate: float | None = None
    deadline: float = 1.0
    startup_timeout: float = 60.0
    save_estimates: bool = False
    linger: float = 2.0
    warmup: float = 3.0
    deliveries: bool = True
    sign: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.mode == "realtime" and not self.rate:
            raise ValueError("realtime mode needs --rate HZ")
        if self.rate is not None and not (self.rate > 0 and math.isfinite(self.rate)):
            raise ValueError(f"rate must be a positive number of Hz, got {self.rate!r}")
        if not self.deadline > 0:
            raise ValueError(f"deadline must be > 0 s, got {self.deadline!r}")
