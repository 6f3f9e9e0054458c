"""The agent process: one :class:`~agents.node.AgentNode` driven by the plant's
measurement messages and its in-neighbours' estimates (the protocol:
:mod:`agents.net.protocol`)."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.rounds import addressed, link_rows
from estimation.errors import MessageError, RSEError, TransportError
from transport.codec import PLANT_ID, Schema, decode
from transport.keys import Keys
from transport.zenoh_bus import Bus

from .config import LAZY, RunConfig
from .evidence_net import signing_for
from .health import LinkHealth
from .protocol import Role
from .rejoin import RejoinChecks
from .schedule import schedule_for
from .view import NetworkView, reads_view
from .wire import _msg, broadcast_to, diagnostics_meta, receivers_of

if TYPE_CHECKING:
    from scenarios.build import Experiment

    from .slices import AgentSlice

log = logging.getLogger("rse.net")

POLL_S = 0.001  # lockstep: how soon a round missing a polled message looks again (_poll_later; libuv counts whole ms)


class AgentProcess(RejoinChecks, Role["AgentSlice"]):
    name = "agent"

    def __init__(self, part: AgentSlice, bus: Bus, keys: Keys, cfg: RunConfig,
                 *, node_hook: Callable[[Any], None] | None = None, rejoin: bool = False) -> None:
        super().__init__(part, bus, keys, cfg)
        #: joining a running team: see _plant_unheard
        self.rejoin = rejoin
        self._first_ready = 0.0  # when this agent first asked to join
        self.part = part
        self.id = agent_id = part.agent_id
        self.name = f"agent {agent_id}"
        self.node = node = part.node
        self.est_schema = Schema({"est": {"x": tuple(part.payload_shape)}})
        if node_hook is not None:
            node_hook(self.node)
        self.in_ids = list(part.in_ids)
        self.out_ids = list(part.out_ids)
        #: how rounds are scheduled (agents.net.schedule): lockstep or realtime
        self.schedule = schedule_for(cfg.mode)
        #: lockstep: this agent's done report carries its broadcast estimate, and those of
        #: the in-neighbours in part.merged carry theirs (see agents.net.slices.merges)
        self._merge_in = self.schedule.merges
        self._merge = self._merge_in and part.agent_id in part.merged and node.strategy is None
        self.member = False
        self.meas: dict[int, tuple[np.ndarray | None, np.ndarray, float]] = {}
        self.arrived: dict[int, set[int]] = {}
        self.last = -1
        self.stop: tuple[int, np.ndarray, float] | None = None
        self.finished = asyncio.Event()
        self.plant_seen_at: float | None = None
        self.running_team = False
        self.rounds_run = 0
        self.skipped = 0
        self.waited_out = 0
        self._timer: asyncio.TimerHandle | None = None
        self._poll: asyncio.TimerHandle | None = None  # _poll_later
        self.polls = 0
        from agents.monitor import has_diagnostics

        self._diagnostics = has_diagnostics(self.node.estimator)
        self._est_key = keys.est(agent_id)
        self._done_key = keys.ctl("done", agent_id)
        self._ready_key = keys.ctl("ready", agent_id)
        self._loc_key = keys.plant_loc(agent_id)
        self._last_ready = 0.0
        self._last_loc = 0.0  # when the last message came on the measurement key
        self.silent_until = 0
        #: an omniscient Byzantine strategy's view of its receivers (see NetworkView)
        self.view: NetworkView | None = None
        self._held: tuple[int, np.ndarray, float] | None = None  # lockstep: a round waiting for the view
        self._error: Exception | None = None  # raised in the consumer's _step
        if node.strategy is not None and reads_view(node.strategy):
            if part.view is None:
                raise RSEError(f"agent {agent_id}: an omniscient adversary without its view in the slice")
            self.view = NetworkView(part.view, node.channel)
            node.view = self.view
            self._done_schema = self.wire.done
        self.health = LinkHealth(list(self.in_ids), 1.0 / cfg.rate if cfg.rate else part.dt)
        self.signing = signing_for(part, cfg, keys.run, regular=node.strategy is None)  # rse run --sign

    def on_reject(self, sender: int | None) -> None:
        if sender is not None:
            self.node.reject(sender)

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        if role == "plant":
            if alive:
                self.plant_seen_at = time.monotonic()
            elif self.stop is None:
                log.warning("agent %d: the plant left", self.id)

    def lazy_items(self) -> Callable[[Any], bool] | None:
        # lockstep: what the next round needs comes before its measurement, which wakes
        # this agent; an omniscient adversary (a view) then sleeps until as many messages
        # came as its view still misses (_release_held)
        return self.schedule.lazy(self._loc_key)

    def handle_data(self, key: str, payload: bytes) -> None:
        if key == self._loc_key:
            got = self.decode(key, payload, self.wire.loc)
            if got is None:
                return
            m = got[1]
            wait = m.arrays["wait"]
            if len(wait) > 64 * max(1, len(self.in_ids)):
                self.rejects.add(PLANT_ID, "range")
                return
            now = time.monotonic()
            self._last_loc = now
            if m.kind == "ctl":
                if m.meta.get("cmd") == "stop":
                    self.stop = (m.stamp, wait, now)
                return
            self.running_team = True
            member = bool(m.meta.get("member", False))
            if member and not self.member:
                self.member = True
                if m.stamp > 0:
                    self.silent_until = m.stamp + int(math.ceil(self.cfg.warmup / self.part.dt))
                log.info("agent %d: joined the team at round %d", self.id, m.stamp)
            elif not member and self.member:
                self.member = False
                self.wake_at(1)
                log.warning("agent %d: the plant no longer counts this agent; rejoining", self.id)
            if not self.member or m.stamp <= self.last:
                return
            y = m.arrays["y"]
            if y.size > self.wire.ny:
                self.rejects.add(PLANT_ID, "range")
                return
            self.meas[m.stamp] = (None if m.meta.get("nomeas") else y, wait, now)
            self.health.measured(m.stamp, now)
            return
        if self.view is not None:
            self._handle_view(self.view, key, payload)
            return
        if "/ctl/done/" in key:
            self._merged_done(key, payload)
            return
        got = self.decode(key, payload, self.est_schema)
        if got is None:
            return
        p, m = got
        j = p.sender
        if j is None or j not in self.node.links:
            self.rejects.add(j, "neighbour")
            return
        self._take(j, m.stamp, m.arrays["x"], m)

    def _merged_done(self, key: str, payload: bytes) -> tuple[int, int, np.ndarray, list[int] | None] | None:
        """The done report of an in-neighbour whose report carries its estimate (see
        :attr:`~agents.net.slices.AgentSlice.merged`): handed to the node as its estimate
        message when it names this agent among its receivers. Returns ``(sender, stamp, x,
        receivers)`` of a valid report; receivers None: a broadcast report (kind "est",
        :func:`~agents.net.wire.report_to`), to every out-neighbour stamped with its round."""
        got = self.decode(key, payload, self.wire.done)
        if got is None:
            return None
        p, m = got
        j = p.sender
        if j not in self.part.merged:
            self.rejects.add(j, "range")
            return None
        if m.kind == "est":
            if j in self.node.links:  # an in-neighbour: this agent is one of its receivers
                self._take(j, m.stamp, m.arrays["x"], m)
            return j, m.stamp, m.arrays["x"], None
        got_to = receivers_of(m, self.part.N)
        if got_to is None:
            self.rejects.add(j, "range")
            return None
        receivers, stamps = got_to
        if self.id in receivers:
            if j not in self.node.links:
                self.rejects.add(j, "neighbour")
            else:
                self._take(j, stamps[receivers.index(self.id)], m.arrays["x"])
        return j, m.stamp, m.arrays["x"], receivers

    def _take(self, j: int, stamp: int, x: np.ndarray, m: Any = None) -> None:
        """Hand a decoded estimate of in-neighbour ``j`` to the node (its channel decides)
        and note its arrival for the lockstep wait lists (and its signed copy, ``m``)."""
        self.node.receive(j, stamp, x)
        self.health.arrived(j, stamp, self.last)
        self.signing.note(j, m)
        if stamp >= self.last - 2 and len(self.arrived) < 4096:
            self.arrived.setdefault(stamp, set()).add(j)

    def _handle_view(self, view: NetworkView, key: str, payload: bytes) -> None:
        """A Byzantine agent with a view hears every estimate of the run and the done
        reports of the agents it depends on: its own inbox, and the view's store."""
        try:
            p = self.keys.parse(key)
        except MessageError:
            self.rejects.add(None, "key")
            return
        if p.kind == "ctl" and p.sender in self.part.merged and self._merge_in:
            got = self._merged_done(key, payload)  # an estimate too: for my inbox and for the view
            if got is not None:
                src, stamp, x, receivers = got
                if (receivers is None or receivers) and view.wants(src, None):
                    view.add(src, None, stamp, x)
                view.add_done(src, stamp, [(r, stamp) for r in receivers or ()])
            return
        if p.kind == "ctl":
            try:
                m = decode(payload, schema=self._done_schema, expected_sender=p.sender)
            except MessageError as exc:
                self.rejects.add(p.sender, exc.reason)
                return
            # a broadcast report comes only from an agent whose report is its estimate
            got_to = receivers_of(m, self.part.N) if m.kind == "done" and p.sender in view.index_of else None
            if got_to is None or p.sender is None:
                self.rejects.add(p.sender, "type" if m.kind != "done" else "range")
                return
            view.add_done(p.sender, m.stamp, list(zip(*got_to)))
            return
        j, receiver = p.sender, p.receiver
        mine = receiver == self.id or (receiver is None and j in self.node.links)
        if j is None or not (mine or view.wants(j, receiver)):  # (an estimate key names its sender)
            return
        try:
            m = decode(payload, schema=self.est_schema, expected_sender=j, expected_receiver=receiver)
        except MessageError as exc:
            self.rejects.add(j, exc.reason)
            if mine:
                self.node.reject(j)
            return
        if view.wants(j, receiver):
            view.add(j, receiver, m.stamp, m.arrays["x"])
        if not mine:
            return
        if j not in self.node.links:
            self.rejects.add(j, "neighbour")
            return
        self._take(j, m.stamp, m.arrays["x"])

    def _release_held(self, now: float) -> bool:
        """Lockstep, phase two of round k for an omniscient adversary: publish once the
        view is complete (or the deadline passed). Returns whether it was published."""
        if (held := self._held) is None or (view := self.view) is None:
            return True  # nothing held: only an adversary with a view holds a round
        k, out, t0 = held
        missing = view.missing(k, lambda s: ("agent", s) in self.alive)
        if missing:
            if now < t0 + self.cfg.deadline:
                self.wake_at(missing)  # the messages still to come before it is complete
                self._tick_at(t0 + self.cfg.deadline)
                return False
            if self._lazy_n > 1:  # the deadline: first take what waits in the bridge
                self.wake_at(1)
                self._tick_at(now)
                return False
            self.went_on_without(k, "published without a complete view")
        self._held = None
        self._publish_round(k, out)
        return True

    def _arrived_all(self, wait: np.ndarray) -> bool:
        arrived = self.arrived
        return all(int(j) in arrived.get(int(s), ()) for j, s in wait)

    def _poll_later(self) -> None:
        # lockstep: a round misses messages of polled subscriptions (their arrival wakes nobody)
        if self._poll is None and self._polled:
            self._poll = asyncio.get_running_loop().call_later(POLL_S, self._poll_now)

    def _poll_now(self) -> None:
        self._poll, self.polls = None, self.polls + 1
        self.handle_batch([])

    def _tick_at(self, when: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        loop = asyncio.get_running_loop()
        self._timer = loop.call_at(loop.time() + max(0.0, when - time.monotonic()), self.changed.set)

    def _publish_round(self, k: int, out: np.ndarray) -> None:
        node, bus = self.node, self.bus
        if self.view is not None:
            self.view.forget(k)
        own = node.estimate(out)
        msg = node.publish(k, out) if node.strategy is not None else out
        aid = self.id
        drop = self.schedule.droppable
        sig = self.signing.begin(bus, self.keys, k)  # rse run --sign: the report of what this agent was told
        try:
            if k < self.silent_until:  # warming up after a late join: listen only
                to, stamps = broadcast_to((), k)
            elif isinstance(msg, dict):
                to, stamps = [], []
                for tgt, stamp, value in addressed(msg, k, self.out_ids):
                    bus.publish(self.keys.est(aid, tgt), _msg("est", aid, stamp, {"x": value}, receiver=tgt, meta=sig(tgt, stamp, value)),
                                droppable=drop)
                    to.append(tgt)
                    stamps.append(stamp)
            elif self._merge:  # the done report below carries the estimate (one message, not two)
                finite = bool(np.all(np.isfinite(msg)))
                to, stamps = (self.out_ids, [k] * len(self.out_ids)) if finite else ([], [])
                if not finite:
                    log.warning("agent %d: round %d message not sent: a non-finite estimate", aid, k)
            else:
                bus.publish(self._est_key, _msg("est", aid, k, {"x": msg}, meta=sig(None, k, msg)), droppable=drop)
                to, stamps = self.out_ids, [k] * len(self.out_ids)
        except MessageError as exc:  # a non-finite estimate cannot go on the wire
            log.warning("agent %d: round %d message not sent: %s", aid, k, exc)
            to, stamps = [], []
        self.health.sent(to)
        meta: dict[str, Any] = {}
        if not np.all(np.isfinite(own)):
            own, meta = np.zeros_like(own), {"nonfinite": True}
        if self._diagnostics:
            meta.update(diagnostics_meta(node.estimator))
        if self._merge and to:  # a broadcast report: the estimate, to every out-neighbour stamped k
            meta.update(sig(None, k, own) or {})
            bus.publish(self._done_key, _msg("est", aid, k, {"x": own}, meta=meta or None))
            return
        arrays = {"x": own, "to": np.array(to, dtype=float), "stamps": np.array(stamps, dtype=float)}
        bus.publish(self._done_key, _msg("done", aid, k, arrays, meta=meta or None))

    def went_on_without(self, k: int, what: str = "went on without some neighbours' messages") -> None:
        """Lockstep: round ``k`` ran after its deadline without some neighbours' messages (an
        omniscient adversary's: without a complete view)."""
        self.waited_out += 1
        if self.waited_out in (1, 10, 100, 1000):
            log.warning("agent %d: round %d %s (%d time(s))", self.id, k, what, self.waited_out)

    def _step(self) -> None:
        """Run every round that can run now (which: the schedule's choice)."""
        schedule = self.schedule
        now = time.monotonic()
        if self._held is not None and not self._release_held(now):
            return
        while self.meas:
            taken = schedule.next_round(self, now)
            if taken is None:
                return
            k, y = taken
            self.health.used(now)
            for j in self.health.stalled(k, now, lambda j: ("agent", j) in self.alive):
                log.warning("agent %d: nothing from agent %d for a second though its token is there", self.id, j)
            out = self.node.run_round(k, y)
            self.last = k
            self.rounds_run += 1
            for s in [s for s in self.arrived if s < k - 2]:
                del self.arrived[s]
            if self.view is not None and schedule.holds_for_view and k >= self.silent_until:
                self._held = (k, out, now)
                if not self._release_held(now):
                    return
            else:
                self._publish_round(k, out)
        if self.stop is not None and not self.meas:
            if schedule.waits_before_stop(self, now):
                return
            self.finished.set()
        elif self.member and not self.meas:
            self.wake_at(LAZY)  # until the next measurement

    def after_batch(self) -> bool:
        # a member runs its rounds right here (the main loop wakes only when it must)
        if not self.member or self._error is not None or ("plant", 0) not in self.alive:
            return True
        try:
            self._step()
        except Exception as exc:  # re-raised by the main loop
            self._error = exc
            return True
        return self.finished.is_set() or not self.member

    def _maybe_ready(self) -> None:
        # a team that is running goes on without a monitor: an agent may rejoin it then
        if self.member or self.plant_seen_at is None or (("monitor", 0) not in self.alive and not self.running_team):
            return
        now = time.monotonic()
        neighbours = set(self.in_ids) | set(self.out_ids)
        seen = {i for (r, i) in self.alive if r == "agent"}
        if not neighbours <= seen and not (self.running_team and now - self.plant_seen_at > 1.0):
            return
        if now - self._last_ready >= 0.1:
            if not self._first_ready:
                self._first_ready = now
            if not self._last_ready:
                log.debug("agent %d: ready", self.id)
            self._last_ready = now
            self.bus.publish(self._ready_key, _msg("ctl", self.id, 0, {}))

    async def run(self) -> dict[str, Any]:
        keys, bus, cfg = self.keys, self.bus, self.cfg
        bus.subscribe(self._loc_key, self.queue)
        merged_ins = [j for j in self.in_ids if j in self.part.merged] if self._merge_in else []
        if self.view is None:
            # lockstep: the measurement wakes it; what its in-neighbours sent waits, polled
            polled = self.schedule.polled
            for j in self.in_ids:
                if j not in merged_ins:  # a merged in-neighbour sends its estimate in its report only
                    self.subscribe(keys.est(j), polled=polled)
            self.subscribe(keys.est_pattern(to=self.id), polled=polled)
            for j in merged_ins:  # their estimates come in their done reports
                self.subscribe(keys.ctl("done", j), polled=polled)
        else:  # also the estimates its receivers will use, and the reports it waits for
            for j in sorted(set(self.in_ids) | set(self.view.needed)):
                bus.subscribe(keys.est(j), self.queue)
            bus.subscribe(keys.est_pattern(to=self.id), self.queue)
            # a receiver's addressed messages from the senders the view reads, by name: a
            # pattern (agent/*/est/{j}) would bring back this agent's own messages to j too,
            # one local delivery each (2 of the 5 ms between the last honest report and
            # this agent's round on mitra_cells.toml)
            for j in sorted(self.view.out_set):
                for s in self.view.before.get(j, ()):
                    bus.subscribe(keys.est(s, j), self.queue)
            for s in sorted(set(self.view.needed) | set(merged_ins)):
                bus.subscribe(keys.ctl("done", s), self.queue)
        # the channel's first draws on the links this agent decides (its in-links; an
        # omniscient adversary's view: every link it reads) before round 0, not in it
        links = [(j, self.id) for j in self.in_ids]
        if self.view is not None:
            links += [(s, j) for j, senders in sorted(self.view.before.items()) for s in senders]
        self.node.channel.prepare(links)
        bus.watch(keys.alive_pattern(), self.queue)
        bus.announce(keys.alive("agent", self.id))
        consumer = asyncio.ensure_future(self.consume())
        t_start = time.monotonic()
        try:
            while not self.finished.is_set():
                self.changed.clear()
                if self._error is not None:
                    raise self._error
                self._step()
                if self.finished.is_set():
                    break
                if not self.member:
                    self._maybe_ready()
                    if self._plant_unheard():
                        why = f"nothing from the plant {time.monotonic() - self._first_ready:.1f} s after asking to join"
                        if await self.reconnect(why):
                            self._first_ready = self._last_ready = 0.0
                    if self.stop is not None:
                        break
                    if not self.running_team and time.monotonic() - t_start > cfg.startup_timeout:
                        raise TransportError(f"agent {self.id}: no plant found within {cfg.startup_timeout:g} s")
                    timeout: float | None = 0.1  # (None: wait until a change comes)
                else:
                    timeout = await self.schedule.idle(self)
                if ("plant", 0) not in self.alive and self.plant_seen_at is not None and self.stop is None:
                    # the plant left without stopping the team: give it a moment, then leave
                    await asyncio.sleep(max(0.5, cfg.deadline))
                    if ("plant", 0) not in self.alive and self.stop is None:
                        raise TransportError(f"agent {self.id}: the plant left before the end of the run")
                try:
                    await asyncio.wait_for(self.changed.wait(), timeout)
                except TimeoutError:
                    pass
            self.send_stats(self.id, link_rows(self.node.links), health=(self.health.ages_rows(), self.health.out_rows()),
                            rounds=self.rounds_run, skipped=self.skipped, waited_out=self.waited_out, polls=self.polls,
                            rejoined=self.rejoin)
            await asyncio.sleep(0.05)
            return {"rounds": self.rounds_run}
        finally:
            consumer.cancel()
            for handle in filter(None, (self._timer, self._poll)):
                handle.cancel()


async def run_agent(exp: Experiment, agent_id: int, bus: Bus, keys: Keys, cfg: RunConfig,
                    *, node_hook: Callable[[Any], None] | None = None, node: Any = None) -> dict[str, Any]:
    """Agent ``agent_id`` (1-based) of ``exp`` until the plant stops the team (``node``: its
    AgentNode if already built). A process that runs one agent uses :func:`run_agent_slice`."""
    from .slices import agent_slice

    return await run_agent_slice(agent_slice(exp, agent_id, node), bus, keys, cfg, node_hook=node_hook)


async def run_agent_slice(part: AgentSlice, bus: Bus, keys: Keys, cfg: RunConfig,
                          *, node_hook: Callable[[Any], None] | None = None, rejoin: bool = False) -> dict[str, Any]:
    """The agent of slice ``part`` (:mod:`agents.net.slices`) until the plant stops the team
    (``rejoin``: it joins a running team, and reconnects when the plant is not heard)."""
    return await AgentProcess(part, bus, keys, cfg, node_hook=node_hook, rejoin=rejoin).run()
