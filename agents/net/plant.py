"""The plant process: publishes the truth and each agent's measurement per round and
paces the team (the protocol: :mod:`agents.net.protocol`)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.rounds import Reads
from estimation.errors import TransportError
from transport.codec import MONITOR_ID, PLANT_ID
from transport.keys import Keys
from transport.zenoh_bus import Bus

from .config import MAX_AHEAD, RunConfig
from .protocol import Role
from .wire import _msg, out_ids_of, report_to

if TYPE_CHECKING:
    from agents.rounds import PlantTeam

log = logging.getLogger("rse.net")

STOP_LINGER_S = 2.0  # after the stop messages, how long the plant waits for the agents to leave
_EMPTY, _NOWAIT = np.zeros(0), np.zeros((0, 2))


@dataclass
class _NextRound:
    """Lockstep: round ``k``, prepared while round ``k - 1`` runs (measurement ``y``, the
    truth message not yet sent) and the agents it has not gone to yet."""

    k: int
    y: np.ndarray
    truth: bytes | None
    pending: set[int]


class PlantProcess(Role["PlantTeam"]):
    name = "plant"

    def __init__(self, exp: PlantTeam, bus: Bus, keys: Keys, cfg: RunConfig) -> None:
        super().__init__(exp, bus, keys, cfg)
        from agents.plant import PlantRole

        self.plant = PlantRole(exp)
        self.ready: set[int] = set()  # agents that asked to join
        self.members: set[int] = set()
        self.done: dict[int, dict[int, list[tuple[int, int]]]] = {}  # round -> agent -> (receiver, stamp)
        self.monitor_ack = -1
        self.k = 0  # the round being run
        self.missed: Counter[int] = Counter()
        self._counting: dict[int, list[tuple[int, int]]] | None = None  # the reports the round waits for
        self._expected: set[int] = set()  # the members the round waits for (those it started with)
        self._out_lists = out_ids_of(exp)  # a broadcast report's receivers (report_to)
        out_ids = self.out_ids = {aid: set(outs) for aid, outs in self._out_lists.items()}
        self.in_ids = {r: sorted(s for s, outs in out_ids.items() if r in outs) for r in exp.agent_ids}
        self._next: _NextRound | None = None  # lockstep: round k + 1, released agent by agent
        self._reads, self._index = Reads(exp), {aid: i for i, aid in enumerate(exp.agent_ids)}
        self._loc_keys = {aid: keys.plant_loc(aid) for aid in exp.agent_ids}
        self._truth_key = keys.plant_truth()

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        if role == "monitor":
            log.info("plant: the monitor %s", "joined" if alive else "left; the team goes on without it")
            if alive:  # a monitor (re)joining records from now on: acknowledged up to here
                self.monitor_ack = max(self.monitor_ack, self.k - 1)
        if role == "agent" and not alive:
            self.ready.discard(i)
            if i in self.members:
                self.members.discard(i)
                log.info("plant: agent %d left", i)

    def handle_data(self, key: str, payload: bytes) -> None:
        if "/ctl/done/" in key:
            got = self.decode(key, payload, self.wire.done)
            if got is None:
                return
            p, m = got
            sender = p.sender
            allowed = None if sender is None else self.out_ids.get(sender)
            got_to = None if sender is None or allowed is None else report_to(m, self._out_lists[sender], len(allowed))
            # a broadcast report's receivers are the out-neighbours themselves (report_to)
            if sender is None or allowed is None or got_to is None or (m.kind != "est" and not allowed.issuperset(got_to[0])):
                self.rejects.add(sender, "range")
                return
            rnd = self.done.get(m.stamp)
            if rnd is not None:
                rnd[sender] = list(zip(*got_to))
        elif "/ctl/ready/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender in self.ids:
                self.ready.add(got[0].sender)
        elif "/ctl/ack/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender == MONITOR_ID:
                self.monitor_ack = max(self.monitor_ack, got[1].stamp)
        else:
            self.rejects.add(None, "key")

    def lazy_items(self) -> Callable[[Any], bool] | None:
        # lockstep: a round's reports wake the plant together (wake_at: the ones still due)
        return (lambda item: type(item[1]) is bytes) if self.cfg.mode == "lockstep" else None

    def after_batch(self) -> bool:
        rnd = self._counting
        if rnd is not None:
            owed = {a for a in self._expected if a not in rnd and a in self.members}  # the reports still due
            due = len(owed)
            nxt = self._next
            if nxt is not None and nxt.pending:
                # round k + 1 goes to each agent once its in-neighbours reported round k. The
                # plant wakes once all but one report came (the last is often the one the
                # omniscient adversary sends after the honest ones), then at the last
                self._release(nxt, rnd, owed)
                if nxt.pending and due > 1:
                    due -= 1
            self.wake_at(max(1, due))
        return super().after_batch()

    def _release(self, nxt: _NextRound, rnd: dict[int, list[tuple[int, int]]], owed: set[int] | None) -> None:
        """Publish round ``nxt.k``'s measurement to each pending agent none of whose
        in-neighbours still owes its round ``nxt.k - 1`` report (``owed``; None: to every
        pending agent, with what came), with its wait list from ``rnd``, those reports."""
        for aid in list(nxt.pending):
            if owed is not None and any(j in owed for j in self.in_ids[aid]):
                continue
            if nxt.truth is not None:
                self.bus.publish(self._truth_key, nxt.truth)
                nxt.truth = None
            nxt.pending.discard(aid)
            self._publish_meas(nxt.k, aid, nxt.y, self._wait_list(aid, rnd))

    def _wait_list(self, aid: int, prev: dict[int, list[tuple[int, int]]]) -> np.ndarray:
        """The (sender, stamp) pairs of the messages sent to ``aid`` in the round of ``prev``'s
        reports (a report names only its sender's out-neighbours: only in-neighbours count)."""
        rows = sorted((j, st) for j in self.in_ids[aid] if j in prev for r, st in prev[j] if r == aid)
        return np.array(rows, dtype=float).reshape(-1, 2)

    def _wait_lists(self, prev: dict[int, list[tuple[int, int]]]) -> dict[int, np.ndarray]:
        """Per receiver, :meth:`_wait_list`."""
        return {aid: self._wait_list(aid, prev) for aid in self.exp.agent_ids}

    async def run(self) -> dict[str, Any]:
        exp, keys, bus, cfg = self.exp, self.keys, self.bus, self.cfg
        bus.subscribe(keys.ctl_pattern("done"), self.queue)
        bus.subscribe(keys.ctl_pattern("ready"), self.queue)
        bus.subscribe(keys.ctl_pattern("ack"), self.queue)
        bus.watch(keys.alive_pattern(), self.queue)
        consumer = asyncio.ensure_future(self.consume())
        try:
            bus.announce(keys.alive("plant", 0))
            everyone = set(exp.agent_ids)
            ok = await self.wait_for(lambda: ("monitor", 0) in self.alive and self.ready >= everyone, cfg.startup_timeout)
            if not ok:
                missing = sorted(everyone - self.ready)
                what = ([f"agent(s) {', '.join(map(str, missing))}"] if missing else []) + \
                       (["the monitor"] if ("monitor", 0) not in self.alive else [])
                raise TransportError(f"{' and '.join(what)} did not join within {cfg.startup_timeout:g} s")
            log.debug("plant: the team is complete")
            return await self._rounds()
        finally:
            consumer.cancel()

    def _admit(self, k: int) -> None:
        joined = (self.ready & {a for (r, a) in self.alive if r == "agent"}) - self.members
        if joined:
            self.members |= joined
            log.info("plant: agent(s) %s joined at round %d", ", ".join(map(str, sorted(joined))), k)

    def _publish_meas(self, k: int, aid: int, y: np.ndarray, wait: np.ndarray) -> None:
        # realtime: a measurement an agent cannot take now is dropped for it alone
        # (an unreachable agent must not hold up the others' measurements)
        rows = self._reads.rows(self._index[aid], k)
        member = aid in self.members
        self.bus.publish(self._loc_keys[aid], _msg("meas", PLANT_ID, k, {"y": _EMPTY if rows is None else y[rows],
                                                                          "wait": wait if member else _NOWAIT},
                                                   meta={"member": member, "nomeas": rows is None}),
                         droppable=self.cfg.mode != "lockstep")

    def _missed_deadline(self, k: int, late: list[int]) -> None:
        """Lockstep: the agents whose round-``k`` reports missed the deadline (counted, said
        at the 1st, 10th, 100th and 1000th time)."""
        for a in late:
            self.missed[a] += 1
            if self.missed[a] in (1, 10, 100, 1000):
                log.warning("plant: agent %d missed the %g s deadline in round %d (%d time(s))",
                            a, self.cfg.deadline, k, self.missed[a])

    async def _monitor_catches_up(self, k: int) -> None:
        """Lockstep: the monitor only records; without it the team goes on, and a live monitor
        more than MAX_AHEAD rounds behind is waited for as it catches up."""
        monitor = ("monitor", 0)
        if monitor in self.alive and k - self.monitor_ack > MAX_AHEAD:
            if not await self.wait_for(lambda: k - self.monitor_ack <= MAX_AHEAD // 2 or monitor not in self.alive,
                                       self.cfg.startup_timeout):
                raise TransportError(f"the monitor stopped acknowledging rounds (last {self.monitor_ack})")

    async def _rounds(self) -> dict[str, Any]:
        exp, keys, bus, cfg, plant = self.exp, self.keys, self.bus, self.cfg, self.plant
        K = exp.n_rounds
        ids = exp.agent_ids
        lockstep = cfg.mode == "lockstep"
        period = 1.0 / cfg.rate if cfg.rate else None
        loc_keys, truth_key = self._loc_keys, self._truth_key
        prev: dict[int, list[tuple[int, int]]] = {}
        t0 = time.monotonic()
        round0_at = time.time()  # wall clock: start-up figures (command to round 0)
        for k in range(K + 1):
            self.k = k
            nxt, self._next = self._next, None
            if nxt is None:  # the whole round here (realtime, paced lockstep, round 0)
                self._admit(k)
                self.done[k] = {}
                y = plant.measure(k)
                bus.publish(truth_key, _msg("truth", PLANT_ID, k, {"x": plant.x}))
                waits = self._wait_lists(prev) if lockstep else {}
                for aid in ids:
                    self._publish_meas(k, aid, y, waits.get(aid, _NOWAIT))
            else:  # lockstep: the agents round k did not reach while round k - 1 ran
                self._release(nxt, prev, None)
            if lockstep:
                expected = self._expected = set(self.members)
                rnd = self._counting = self.done[k]
                if k < K and period is None:
                    # round k + 1 goes out agent by agent while round k runs: to an agent once
                    # its in-neighbours reported round k (its wait list is complete then; the
                    # plant's trajectory does not depend on the agents)
                    plant.advance(k)
                    self._admit(k + 1)
                    self.done[k + 1] = {}
                    self._next = _NextRound(k + 1, plant.measure(k + 1), _msg("truth", PLANT_ID, k + 1, {"x": plant.x}), set(ids))
                self.after_batch()  # releases what can go now, and counts what wakes the plant

                def finished_(rnd: dict = rnd, expected: set = expected) -> bool:
                    return all(a in rnd or a not in self.members for a in expected)

                finished = await self.wait_for(finished_, cfg.deadline)
                self._counting = None
                self.wake_at(1)
                if not finished:  # what waited for the rest of the round's reports comes in now
                    await asyncio.sleep(0)
                    finished = finished_()
                if not finished:
                    self._missed_deadline(k, sorted(a for a in expected if a not in rnd and a in self.members))
                await self._monitor_catches_up(k)
            if period is not None:
                delay = t0 + (k + 1) * period - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
            prev = self.done[k]
            self.done.pop(k - 1, None)
            if k < K and self._next is None:
                plant.advance(k)
        elapsed = time.monotonic() - t0
        # the end: final wait lists (messages stamped K), then stop
        waits = self._wait_lists(self.done.get(K, {})) if lockstep else {}
        self.send_stats(PLANT_ID, elapsed=elapsed, rounds=K + 1, missed=int(sum(self.missed.values())),
                        round0_at=round0_at)
        for aid in ids:
            bus.publish(loc_keys[aid], _msg("ctl", PLANT_ID, K, {"wait": waits.get(aid, _NOWAIT)}, meta={"cmd": "stop"}))
        bus.publish(keys.ctl("stop", PLANT_ID), _msg("ctl", PLANT_ID, K, {}, meta={"cmd": "stop"}))
        # closing the session drops what is still queued toward a slow peer, and an agent that
        # sees the plant's token go before its stop message waits out its deadline: stay until
        # the agents left (each leaves once stopped), at most STOP_LINGER_S
        await asyncio.sleep(0.05)
        await self.wait_for(lambda: not any(r == "agent" for r, _ in self.alive), STOP_LINGER_S)
        return {"elapsed": elapsed, "rounds": K + 1}


async def run_plant(exp: PlantTeam, bus: Bus, keys: Keys, cfg: RunConfig) -> dict[str, Any]:
    """The plant process (see the module docstring); returns elapsed time and rounds."""
    return await PlantProcess(exp, bus, keys, cfg).run()
