"""The monitor process: records every round (truth, the agents' estimates and
diagnostics), the membership and the counters, writes the run directory and streams the
dashboard (the protocol: :mod:`agents.net.protocol`)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.errors import TransportError
from transport.codec import MONITOR_ID, PLANT_ID, Message
from transport.keys import Keys
from transport.zenoh_bus import Bus

from .config import ACK_EVERY, MONITOR_LAG, RECONNECTS, TOKENS_SETTLE_S, UNHEARD_S, RunConfig
from .evidence_net import TOLD, convictions_for
from .figures import process_figures, unrecorded
from .protocol import Role
from .wire import Rejects, _msg, broadcast_to, diagnostics_from_meta, out_ids_of, who_name

if TYPE_CHECKING:
    from agents.recorder import MetricsStream
    from scenarios.build import Experiment

log = logging.getLogger("rse.net")


@dataclass
class _Round:
    est: np.ndarray  # (N, n) the reported estimates (NaN: none)
    present: np.ndarray  # (N,) bool: the agents that reported
    x: np.ndarray | None = None  # the truth, once the plant's came
    diag: dict[int, tuple[dict[str, float], bool | None]] = field(default_factory=dict)


@dataclass
class MonitorResult:
    summary: dict[str, Any]
    out_dir: Path | None
    estimates: np.ndarray | None = None
    truth: np.ndarray | None = None


class MonitorProcess(Role["Experiment"]):
    name = "monitor"

    def __init__(self, exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig, *, out_dir: Path | None = None,
                 progress: Callable[[str, Any], None] | None = None, dashboard: Any = None,
                 resume: bool = False) -> None:
        super().__init__(exp, bus, keys, cfg)
        from agents.monitor import Monitor

        self.mon = Monitor(exp)
        self.dashboard = dashboard
        self._last_flush = time.monotonic()
        if dashboard is not None:
            self._setup_dashboard(dashboard)
        self.out_dir = out_dir
        # a monitor that rejoins a running team: the rounds recorded before (the stream of
        # the earlier monitor(s) in out_dir) are loaded, and it records from the first
        # round it sees; the rounds in between are the gap
        self.resume = resume
        self.synced = not resume
        self.stream: MetricsStream | None = None
        if out_dir is not None:
            self._setup_stream(Path(out_dir))
        self.progress = progress or (lambda kind, data: None)
        self.rounds: dict[int, _Round] = {}
        self._listening_since = time.monotonic()
        self._last_join = self._listening_since  # a rejoining monitor waits for the tokens to settle
        self.next_k = 0
        self.max_truth = -1
        self.stop_round: int | None = None
        self.stats: dict[str, Message] = {}
        self.membership: list[dict[str, Any]] = []
        self.convictions = convictions_for(exp, cfg, keys.run)  # rse run --sign
        self.index = {aid: i for i, aid in enumerate(exp.agent_ids)}
        self._outs = out_ids_of(exp)  # a broadcast report's receivers (report_to)
        # a monitor that starts with the team expects every agent until it has seen each
        # one's token: the tokens can reach it after the plant's truth of the first rounds
        # (through a loaded router), and a round closed then would lack those agents
        self.unseen = set() if resume else set(self.index)
        self.t0 = time.monotonic()
        self._K = exp.n_rounds  # the last round (a property of the scenario: read once)
        K = exp.n_rounds + 1
        self.traj = np.full((K, exp.N, exp.n), np.nan) if cfg.save_estimates else None
        self.truth = np.full((K, exp.n), np.nan) if cfg.save_estimates else None
        self._last_progress = 0.0
        self._last_wait_log = time.monotonic()

    def after_batch(self) -> bool:
        # the rounds a batch completed are recorded here; the main loop only watches for the end
        self._close_rounds(final=False)
        if self._waiting is not None:
            return super().after_batch()
        return self.stop_round is not None or self.next_k == 0 or ("plant", 0) not in self.alive

    #: lockstep: how often the monitor takes the reports and the truth (polled), and how
    #: many of each its subscriptions hold meanwhile
    POLL_S = 0.05
    RING = 1 << 14

    def _setup_dashboard(self, dash: Any) -> None:
        """Stream to the Rerun dashboard as ``rse simulate`` does
        (:class:`agents.rounds.DashboardFeed`). The links delivered in a round and the link
        counters are reconstructed from the done reports (who sent what to whom, stamped
        when) with the channel model, as each receiver's node decides
        (:func:`agents.rounds.count_fate`)."""
        from agents.middleware import make_channel
        from agents.rounds import DashboardFeed, counters_array
        from transport.channel import LinkCounters

        exp, mon = self.exp, self.mon
        self._channel = make_channel(exp)
        self._counters = [LinkCounters() for _ in range(exp.N)]  # per receiver, over its in-links
        feed = self._feed = DashboardFeed(dash, exp.N, lambda: counters_array(self._counters))

        def on_chunk(rows: Any, xs: np.ndarray, ests: np.ndarray) -> None:
            try:
                feed.log(rows, mon, xs, ests)
            except Exception:  # the dashboard must not stop the monitor
                log.exception("monitor: could not log to the dashboard")

        mon.on_chunk = on_chunk

    def _setup_stream(self, out_dir: Path) -> None:
        """Metrics streamed to ``out_dir`` as the rounds are recorded (:mod:`agents.recorder`)."""
        from agents.recorder import MetricsStream, load_into, read_partial
        from agents.rounds import regular_mask

        out_dir.mkdir(parents=True, exist_ok=True)
        if self.resume:
            load_into(self.mon, read_partial(out_dir))
        stream = self.stream = MetricsStream(out_dir, self.exp, regular_mask(self.exp))
        mon, inner = self.mon, self.mon.on_chunk

        def on_chunk(rows: Any, xs: np.ndarray, ests: np.ndarray) -> None:
            stream.write(mon, rows)
            if inner is not None:
                inner(rows, xs, ests)

        mon.on_chunk = on_chunk

    def _links_of(self, sender: int, stamp: int, to: Any, stamps: Any) -> None:
        """Dashboard bookkeeping of one done report (see :meth:`_setup_dashboard`)."""
        from agents.rounds import count_fate

        fate, index, feed = self._channel.fate, self.index, self._feed
        s = index[sender]
        for t, st in zip(to, stamps):
            r = index.get(int(t))
            if r is None:
                continue
            when = fate(sender, int(t), int(st))
            count_fate(self._counters[r], when, int(st))
            if when is not None and when >= self.next_k and when <= self.exp.n_rounds and feed.wants(when):
                feed.frame(when)[r, s] = True

    def on_alive(self, role: str, i: int, alive: bool) -> None:
        if role == "agent":
            self.unseen.discard(i)
        if alive:
            self._last_join = time.monotonic()
        # after_stop: the plant has stopped the run (a process that ends then has finished, not left early)
        event = {"t_wall": round(time.monotonic() - self.t0, 3), "round": self.next_k, "role": role, "id": i,
                 "event": "join" if alive else "leave", "after_stop": self.stop_round is not None}
        self.membership.append(event)
        label = role if role != "agent" else f"agent {i}"
        log.info("monitor: %s %s (round %d)", label, "joined" if alive else "left", self.next_k)
        self.progress("member", event)

    def _rec(self, k: int) -> _Round:
        r = self.rounds.get(k)
        if r is None:
            r = self.rounds[k] = _Round(est=np.full((self.exp.N, self.exp.n), np.nan),
                                        present=np.zeros(self.exp.N, dtype=bool))
        return r

    def handle_data(self, key: str, payload: bytes) -> None:
        K = self._K
        if key.endswith("/plant/truth"):
            got = self.decode(key, payload, self.wire.truth)
            if got is None:
                return
            k = got[1].stamp
            if k > K or k < self.next_k:
                self.rejects.add(PLANT_ID, "range")
                return
            self._rec(k).x = got[1].arrays["x"]
            self.max_truth = max(self.max_truth, k)
        elif "/ctl/done/" in key:
            got = self.decode(key, payload, self.wire.done)
            if got is None:
                return
            p, m = got
            k = m.stamp
            if p.sender not in self.index or k > K:
                self.rejects.add(p.sender, "range")
                return
            if k < self.next_k:
                return  # too late for the record
            r = self._rec(k)
            i = self.index[p.sender]
            if not m.meta.get("nonfinite"):
                r.est[i] = m.arrays["x"]
            r.present[i] = True
            if m.meta:
                diag, flag = diagnostics_from_meta(m.meta)
                if diag or flag is not None:
                    r.diag[i] = (diag, flag)
            if self.dashboard is not None:
                to, stamps = (broadcast_to(self._outs[p.sender], k) if m.kind == "est"
                              else (m.arrays["to"], m.arrays["stamps"]))
                self._links_of(p.sender, k, to, stamps)
        elif "/ctl/stats/" in key:
            got = self.decode(key, payload, self.wire.stats)
            if got is not None:
                self.stats[who_name(got[0].sender)] = got[1]
        elif "/ctl/told/" in key and self.convictions is not None:
            got = self.decode(key, payload, self.convictions.schema)
            if got is not None and got[0].sender is not None:
                self.convictions.add(got[0].sender, got[1])
        elif "/ctl/stop/" in key:
            got = self.decode(key, payload, self.wire.ctl)
            if got is not None and got[0].sender == PLANT_ID:
                self.stop_round = got[1].stamp
        else:
            self.rejects.add(None, "key")

    def _sync(self, k: int) -> None:
        """A rejoining monitor records from round ``k``."""
        self.synced = True
        self.next_k = k
        for old in [j for j in self.rounds if j < k]:
            del self.rounds[old]
        log.info("monitor: rejoined the team at round %d", k)
        self.progress("member", {"t_wall": round(time.monotonic() - self.t0, 3), "round": k, "role": "monitor",
                                 "id": 0, "event": "rejoin"})

    def _not_synced_yet(self) -> None:
        """Every 5 s while a rejoining monitor has no whole round: what it is missing, as
        the number of rounds held with the truth that carry each live agent's report (an
        agent whose reports do not reach this monitor shows 0; the newest rounds' reports
        may still be in flight)."""
        now = time.monotonic()
        if now - self._last_wait_log < 5.0 or not self.rounds:
            return
        self._last_wait_log = now
        n, heard = self._reports_held()
        counts = ", ".join(f"{aid}: {c}" for aid, c in heard.items())
        log.info("monitor: no whole round yet to rejoin at: %d round(s) held with the truth (newest %d); "
                 "reports in them per live agent: %s%s", n, max(self.rounds), counts or "-",
                 "" if ("plant", 0) in self.alive else "; no plant token")

    def _reports_held(self) -> tuple[int, dict[int, int]]:
        """The rounds held with the truth, and how many of them carry each live agent's report."""
        with_truth = [r for r in self.rounds.values() if r.x is not None]
        live = sorted(aid for (role, aid) in self.alive if role == "agent" and aid in self.index)
        return len(with_truth), {aid: sum(bool(r.present[self.index[aid]]) for r in with_truth) for aid in live}

    def _reports_unheard(self) -> list[int]:
        """A rejoining monitor that has held at least 20 rounds with the truth for
        :data:`~agents.net.config.UNHEARD_S` without a report from some live agent: those
        agents (else []). Seen 3 times in 32 scripted rejoins: a restarted monitor got
        the plant's truth but no report from the agents that had run all along. Where that
        lasted, those agents had stopped getting measurements and sent nothing at all (they
        reconnect themselves: AgentProcess._measurements_stopped); a new session of the
        monitor is for a link of its own that does not deliver."""
        if self.synced or self.reconnects >= RECONNECTS or time.monotonic() - self._listening_since < UNHEARD_S:
            return []
        n, heard = self._reports_held()
        return [aid for aid, c in heard.items() if c == 0] if n >= 20 else []

    def _tokens_settled(self) -> bool:
        """A rejoining monitor learns the members from their tokens, which reach it peer by
        peer: it takes a round as whole only once no token has come for TOKENS_SETTLE_S and
        every agent it holds a report of has shown its token (else a round whole for the
        members seen so far would start the record, and every later round would lack the
        member whose link came up last)."""
        if time.monotonic() - self._last_join < TOKENS_SETTLE_S:
            return False
        live = {aid for (role, aid) in self.alive if role == "agent"}
        return all(aid in live for aid, i in self.index.items() if any(r.present[i] for r in self.rounds.values()))

    def _complete(self, r: _Round) -> bool:
        # not before the plant's token: until then this process does not know the team (a
        # monitor that subscribes late gets the tokens present in one batch, which through
        # a loaded router can come rounds after the first truth and done reports)
        if r.x is None or ("plant", 0) not in self.alive or self.unseen:
            return False
        for (role, aid) in self.alive:
            if role == "agent" and aid in self.index and not r.present[self.index[aid]]:
                return False
        return True

    def _close_rounds(self, final: bool) -> None:
        if not self.synced:
            # a rejoining monitor starts at the first round it has whole (truth and every
            # live agent's report): its subscriptions reach the team's peers one by one
            first = (next((k for k in sorted(self.rounds) if self._complete(self.rounds[k])), None)
                     if self._tokens_settled() else None)
            if first is None:
                self._not_synced_yet()
                return
            self._sync(first)
        closed = False
        while True:
            k = self.next_k
            if k > self.exp.n_rounds:
                break
            r = self.rounds.get(k)
            complete = r is not None and self._complete(r)
            if not complete and not final and self.max_truth < k + MONITOR_LAG:
                break
            if r is not None and r.x is not None:
                self.mon.record(k, r.x, r.est, r.present)
                for i, (diag, flag) in r.diag.items():
                    self.mon.record_diagnostics(k, i, diag, flag)
                if self.traj is not None and self.truth is not None:  # cfg.save_estimates
                    self.traj[k] = np.where(r.present[:, None], r.est, np.nan)
                    self.truth[k] = r.x
            self.rounds.pop(k, None)
            self.next_k = k + 1
            closed = True
            if self.next_k % ACK_EVERY == 0:
                self.bus.publish(self.keys.ctl("ack", MONITOR_ID), _msg("ctl", MONITOR_ID, self.next_k - 1, {}))
            if final and self.stop_round is not None and self.next_k > self.stop_round:
                break
        if closed:
            now = time.monotonic()
            if self.dashboard is not None and now - self._last_flush > 0.5:
                self._last_flush = now
                self.mon.flush()  # keep the live view fresh
            if now - self._last_progress > 0.1 or final:
                self._last_progress = now
                self.progress("round", (self.next_k - 1, self.mon.current_worst()))

    async def run(self) -> MonitorResult:
        keys, bus = self.keys, self.bus
        # lockstep: the truth and the reports wait, polled, and are recorded every POLL_S
        # (no callback per message; the plant waits only MAX_AHEAD rounds ahead)
        polled = self.cfg.mode == "lockstep"
        self.subscribe(keys.plant_truth(), polled=polled, capacity=self.RING)
        self.subscribe(keys.ctl_pattern("done"), polled=polled, capacity=self.RING)
        bus.subscribe(keys.ctl_pattern("stats"), self.queue)
        bus.subscribe(keys.ctl_pattern("stop"), self.queue)
        if self.convictions is not None:
            self.subscribe(keys.ctl_pattern(TOLD), polled=polled, capacity=self.RING)
        bus.watch(keys.alive_pattern(), self.queue)
        bus.announce(keys.alive("monitor", 0))
        consumer = asyncio.ensure_future(self.consume())
        poller = asyncio.ensure_future(self._poll()) if polled else None
        try:
            return await self._run()
        except BaseException as exc:  # a signal, the plant gone: keep what was recorded
            self._abort(exc)
            raise
        finally:
            consumer.cancel()
            if poller is not None:
                poller.cancel()
            if self.stream is not None:
                self.stream.close()

    async def _poll(self) -> None:
        while True:
            await asyncio.sleep(self.POLL_S)
            self.handle_batch([])

    def _abort(self, exc: BaseException) -> None:
        """The run ends early: the rounds received are recorded, and the run directory is
        written with ``complete: false`` and why (:mod:`agents.recorder`)."""
        from agents.net.exits import describe

        if self.out_dir is None:
            return
        try:
            if self.synced and self.max_truth >= self.next_k:
                self.stop_round = self.max_truth
                self._close_rounds(final=True)
            if ("plant", 0) not in self.alive and self.next_k > 0:
                reason = f"the plant left the team after round {self.mon.last_round}"
            elif isinstance(exc, (asyncio.CancelledError, KeyboardInterrupt)):
                reason = "interrupted"
            else:
                reason = describe(exc)
            if self.mon.last_round >= 0:
                self._finish(complete=False, reason=reason)
            else:  # nothing recorded: the header of a summary only
                from agents.recorder import write_incomplete
                from agents.rounds import regular_mask

                if self.stream is not None:
                    self.stream.close()
                write_incomplete(self.out_dir, self.exp, None, regular_mask(self.exp), reason=reason)
        except Exception:  # the original exception is what the caller must see
            log.exception("monitor: could not write the run directory")

    async def _run(self) -> MonitorResult:
        cfg = self.cfg
        # the whole run, bounded only by the plant: it stops the team (or leaves)
        while self.stop_round is None:
            if self.next_k == 0 and ("plant", 0) not in self.alive and time.monotonic() - self.t0 > cfg.startup_timeout:
                raise TransportError(f"no plant found within {cfg.startup_timeout:g} s")
            if self.next_k > 0 and ("plant", 0) not in self.alive:
                await asyncio.sleep(max(0.5, cfg.deadline))
                if self.stop_round is None and ("plant", 0) not in self.alive:
                    raise TransportError("the plant left before the end of the run")
            silent = self._reports_unheard()
            if silent:
                await self.reconnect(f"no report from agent(s) {', '.join(map(str, silent))} in the rounds held")
                self._listening_since = time.monotonic()
            self.changed.clear()
            try:
                await asyncio.wait_for(self.changed.wait(), 0.25)
            except TimeoutError:
                pass
        K = self.stop_round
        await self.wait_for(lambda: self.next_k > K or (K in self.rounds and self._complete(self.rounds[K])), cfg.deadline)
        self._close_rounds(final=True)
        agents_alive = lambda: {str(a) for (r, a) in self.alive if r == "agent"}
        await self.wait_for(lambda: "plant" in self.stats and agents_alive() <= set(self.stats), cfg.linger)
        if not self.synced:  # restarted, it never had a whole round: the record is incomplete (_abort)
            raise TransportError(f"this monitor did not rejoin the team before its last round {K}")
        return self._finish()

    def _finish(self, *, complete: bool = True, reason: str | None = None) -> MonitorResult:
        from agents.health import health_section, rate_line
        from agents.rounds import links_table, regular_mask
        from agents.summary import summarise_run

        exp, mon = self.exp, self.mon
        if self.dashboard is not None:  # the final rejected counts per receiver, for the last chunk
            for who, m in self.stats.items():
                if who.isdigit() and int(who) in self.index:
                    self._counters[self.index[int(who)]].rejected = int(np.sum(m.arrays["links"][:, 5]))
        mon.flush()
        if self.dashboard is not None:
            self.dashboard.flush()
        regular = regular_mask(exp)
        rejected: dict[str, dict[str, int]] = {}
        processes: dict[str, Any] = {"monitor": {**process_figures(), "batches": self.batches,
                                                 "rejected": Rejects.mine(rejected, self.rejects.as_array())}}
        perf: dict[str, Any] = {}
        for who, m in sorted(self.stats.items()):
            processes[who if who == "plant" else f"agent {who}"] = {**{k: v for k, v in m.meta.items() if k != "cmd"},
                                                                    "rejected": Rejects.mine(rejected, m.arrays["rejected"])}
            if who == "plant":
                perf = {"elapsed_s": m.meta.get("elapsed"), "rounds": m.meta.get("rounds"),
                        "deadline_misses": m.meta.get("missed"), "round0_at": m.meta.get("round0_at")}
        if perf.get("elapsed_s"):
            perf["rounds_per_s"] = perf["rounds"] / perf["elapsed_s"]
            perf["agent_rounds_per_s"] = perf["rounds_per_s"] * exp.N
        # each agent's link rows (agents.rounds.link_rows), by receiver index as the simulator's
        reports = [(aid, self.stats[str(aid)].arrays["links"]) for aid in exp.agent_ids if str(aid) in self.stats]
        summary, results = summarise_run(exp, mon, links_table(reports), rejected, complete=complete, reason=reason)
        summary["unrecorded_rounds"] = unrecorded(mon.truth_norm[: mon.last_round + 1, 0])
        summary["performance"] = perf
        summary["driver"] = "run"
        summary["mode"] = self.cfg.mode
        summary["membership"] = self.membership
        summary["processes"] = processes
        summary["health"] = health_section(self.stats, list(exp.agent_ids), summary["links"], mode=self.cfg.mode,
                                           rate=self.cfg.rate, deadline_misses=perf.get("deadline_misses"))
        if self.dashboard is not None and hasattr(self.dashboard, "log_health"):
            self.dashboard.log_health(summary["health"], mon.last_round, rate_line(summary))
        if self.convictions is not None:
            self.convictions.report(summary, self.out_dir, self.dashboard)
        if self.out_dir is not None:
            from agents.recorder import write_run

            if self.stream is not None:
                self.stream.close()
            write_run(self.out_dir, exp, mon, regular, summary)
            if self.traj is not None and self.truth is not None:  # cfg.save_estimates
                np.save(self.out_dir / "estimates.npy", self.traj[: mon.last_round + 1])
                np.save(self.out_dir / "truth.npy", self.truth[: mon.last_round + 1])
        return MonitorResult(summary, self.out_dir, self.traj, self.truth)


async def run_monitor(exp: Experiment, bus: Bus, keys: Keys, cfg: RunConfig, *, out_dir: Path | None = None,
                      progress: Callable[[str, Any], None] | None = None, dashboard: Any = None,
                      resume: bool = False) -> MonitorResult:
    """The monitor until the plant stops the team; writes metrics (as it goes) and the
    summary to ``out_dir``, also when the run ends early; streams to ``dashboard`` (an
    :class:`agents.dashboard.Dashboard`) when given. ``resume``: rejoin a running team
    whose earlier monitor left (see :class:`MonitorProcess`)."""
    return await MonitorProcess(exp, bus, keys, cfg, out_dir=out_dir, progress=progress, dashboard=dashboard,
                                resume=resume).run()
