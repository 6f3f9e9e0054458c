"""The live Rerun dashboard of a run (the monitor's output, in both drivers).

One recording per run, its id the run id, so every process of a run (``rse run``) can write
into the same recording. Timelines: the round ``k`` (sequence) and the simulation time
``t`` (duration). Entities:

* ``errors/{block}``: ``log10`` of the 2-norm error of each agent (one series per agent,
  instance ``i`` = agent index ``i``) per state block (Rerun's plots have no log axis, so
  the value is the decade); ``relative_errors/{block}`` likewise for the relative error, logged when the plant is unstable (the absolute error
  of a growing state has a float64 floor of about 1e-15 |x|). Byzantine agents are drawn
  dashed-red-and-thin; attack start and stop are ``events/attacks`` markers;
* ``state/{name}/truth`` and ``state/{name}/agent{i}``: chosen linear combinations of the
  state against the estimates of chosen agents (``[[output.plots]]``);
* ``map/locations``, ``map/agents`` (current positions: mobile agents move along their
  patrols; adversaries red), ``map/links/delivered`` and ``map/links/dropped`` (the
  communication graph: the links whose message arrived this round, and the others grey);
* ``counters/agent{i}/{delivered,dropped,late,rejected}``: cumulative link counters.

Data is sent in column batches per chunk of rounds (``send_columns``), so logging costs
little per round; the map and graph are decimated to at most ``MAP_FRAMES`` frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.lti import dense

from .monitor import plot_rows

if TYPE_CHECKING:
    from scenarios.build import Experiment

MAP_FRAMES = 2000
REGULAR_COLORS = [
    (31, 119, 180), (44, 160, 44), (148, 103, 189), (23, 190, 207), (188, 189, 34), (140, 86, 75),
    (227, 119, 194), (127, 127, 127), (255, 127, 14), (57, 59, 121), (82, 84, 163), (107, 110, 207),
]
ADVERSARY = (214, 39, 40)
GREY = (170, 170, 170)
GREEN = (60, 170, 90)


@dataclass
class DashboardOptions:
    """Where the recording goes (``--rrd``, ``--viewer``, ``--serve-web``)."""

    rrd: Path | None = None
    viewer: bool = False
    serve_web: bool = False
    web_port: int | None = None
    grpc_port: int | None = None
    viewer_port: int = 9876
    #: address the gRPC server binds to; the printed URLs use ``public_host``
    bind_ip: str = "0.0.0.0"
    public_host: str = "127.0.0.1"
    urls: dict[str, str] = field(default_factory=dict)


def agent_layout(exp: Experiment) -> tuple[np.ndarray | None, np.ndarray]:
    """Map positions: ``(locations (L, 2) or None, static agent positions (N, 2))``.

    Static agents without a map sit on a circle; an agent reading located banks sits at
    the mean of their positions.
    """
    N = exp.N
    circle = np.stack([np.cos(2 * np.pi * np.arange(N) / N), np.sin(2 * np.pi * np.arange(N) / N)], axis=1)
    locs = exp.positions
    if locs is None:
        return None, circle
    pos = circle * (np.nanmax(np.abs(locs)) if np.isfinite(locs).any() else 1.0)
    for i in range(N):
        banks = [b for b, r in enumerate(exp.bank_rows) if np.isin(r, exp.agent_rows[i]).all() and len(exp.agent_rows[i])]
        p = locs[banks] if banks else np.zeros((0, 2))
        if len(p) and np.isfinite(p).all():
            pos[i] = p.mean(axis=0)
    return locs, pos


class Dashboard:
    """Streams a run to Rerun. Use as a context manager; ``log_chunk`` per chunk of rounds."""

    def __init__(self, exp: Experiment, *, run_id: str, options: DashboardOptions) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        self.exp = exp
        self.rr = rr
        self.opts = options
        self.rec = rr.RecordingStream("rse", recording_id=run_id)
        sinks: list[Any] = []
        if options.rrd is not None:
            options.rrd.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(options.rrd)))
        server = None
        if options.serve_web:
            server = rr.GrpcServerSink(bind_ip=options.bind_ip, port=options.grpc_port or 9876, cors_allow_origin=["*"])
            sinks.append(server)
        if options.viewer:
            port = options.viewer_port
            rr.spawn(port=port, connect=False)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        # relative errors are logged (and shown first) for unstable plants
        self._unstable = exp.n <= 2000 and bool(np.max(np.abs(np.linalg.eigvals(dense(exp.Ad)))) > 1.0 + 1e-9)
        blueprint = self.blueprint(rrb)
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=blueprint)
        self.rec.send_blueprint(blueprint)
        if server is not None:
            options.urls["grpc"] = server.uri
            web_port = options.web_port or 9090
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=server.uri)
            options.urls["web"] = f"http://{options.public_host}:{web_port}/?url={server.uri.replace('0.0.0.0', options.public_host)}"
        self._map_every = max(1, math.ceil((exp.n_rounds + 1) / MAP_FRAMES))
        self._static_logged = False
        self._unreported: np.ndarray | None = None  # per agent: rounds with no report (_log_unreported)
        dst, src = np.nonzero(exp.Adj)  # edge src -> dst (dst receives from src)
        self._src, self._dst = src, dst
        self.log_static()  # also imports the archetypes before the rounds start

    # ------------------------------------------------------------------ layout
    def blueprint(self, rrb: Any) -> Any:
        """Errors per block in tabs (relative errors first for unstable plants), the map
        with the links, the true state against estimates, and the link counters."""
        blocks = list(self.exp.blocks)
        order = [b for b in blocks if b != "x"] + ["x"] if len(blocks) > 1 else blocks

        whole = [rrb.VisibleTimeRange(tl, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
                 for tl in ("k", "t")]  # show the whole run, not a trailing window

        def tabs(root: str, label: str):
            return rrb.Tabs(*[rrb.TimeSeriesView(origin=f"/{root}/{b}", name=f"{label}: {b}", time_ranges=whole) for b in order])

        if self._unstable:
            left = [tabs("relative_errors", "log10 relative error"), tabs("errors", "log10 error")]
        else:
            left = [tabs("errors", "log10 error")]
        right = [
            rrb.Spatial2DView(origin="/map", name="map: agents, locations, links delivered (green) / dropped (grey)"),
            rrb.TimeSeriesView(origin="/state", name="true state vs estimates", time_ranges=whole),
            rrb.TimeSeriesView(origin="/counters", name="link counters", time_ranges=whole),
            rrb.TimeSeriesView(origin="/health", name="rounds without a report (realtime: skipped)", time_ranges=whole),
        ]
        return rrb.Blueprint(
            rrb.Horizontal(rrb.Vertical(*left), rrb.Vertical(*right), column_shares=[3, 2]),
            rrb.TimePanel(state="collapsed"),
            collapse_panels=True,
        )

    # ------------------------------------------------------------------ static data
    def log_static(self) -> None:
        rr, rec, exp = self.rr, self.rec, self.exp
        bad = [i in exp.byzantine for i in range(exp.N)]
        style = rr.SeriesLines(
            colors=[ADVERSARY if b else REGULAR_COLORS[i % len(REGULAR_COLORS)] for i, b in enumerate(bad)],
            widths=[1.0 if b else 2.0 for b in bad],
            names=[f"agent {aid}" + (" (Byzantine)" if b else "") for aid, b in zip(exp.agent_ids, bad)],
        )
        for b in exp.blocks:
            rec.log(f"errors/{b}", style, static=True)
            if self._unstable:
                rec.log(f"relative_errors/{b}", style, static=True)
        locs, pos = agent_layout(exp)
        self._static_pos = pos
        pts = pos if locs is None else np.vstack([pos, locs[np.isfinite(locs).all(axis=1)]])
        span = float(np.ptp(pts, axis=0).max()) or 1.0
        r_agent, r_loc, r_link = 0.02 * span, 0.008 * span, 0.003 * span
        colors = [ADVERSARY if i in exp.byzantine else REGULAR_COLORS[i % len(REGULAR_COLORS)] for i in range(exp.N)]
        rec.log("map/agents", rr.Points2D.from_fields(colors=colors, radii=r_agent, labels=[str(a) for a in exp.agent_ids]), static=True)
        rec.log("map/links/delivered", rr.Arrows2D.from_fields(colors=[GREEN], radii=r_link), static=True)
        rec.log("map/links/dropped", rr.Arrows2D.from_fields(colors=[GREY], radii=0.5 * r_link), static=True)
        if locs is not None:
            rec.log("map/locations", rr.Points2D(locs, radii=r_loc, colors=[(120, 120, 120)],
                                                 labels=[f"loc {b + 1}" for b in range(len(locs))]), static=True)
        marks = [a for a in exp.scenario.attacks]
        for a in marks:
            who = ("sensors " + ",".join(map(str, a.sensors))) if a.target == "sensor" else ("agents " + ",".join(map(str, a.agents)))
            for when, what in ((a.start, "start"), (a.stop, "stop")):
                if math.isfinite(when) and when <= exp.n_rounds * exp.dt:
                    k = int(round(when / exp.dt))
                    rec.set_time("k", sequence=k)
                    rec.set_time("t", duration=when)
                    rec.log("events/attacks", rr.TextLog(f"attack {a.kind} on {who}: {what}", level="WARN"))
        self._static_logged = True

    # ------------------------------------------------------------------ per chunk
    def log_chunk(self, rows: np.ndarray, mon: Any, *, x: np.ndarray, est: np.ndarray,
                  delivered: dict[int, np.ndarray] | None = None, counters: np.ndarray | None = None) -> None:
        """Log rounds ``rows`` (ints): ``x`` ``(c, n)`` truth, ``est`` ``(c, N, n)`` estimates,
        ``delivered`` ``{round: (N, N) bool}`` for the map frames (``[i, j]``: j's message
        became visible to i in that round),
        ``counters`` ``(N, 4)`` cumulative delivered/dropped/late/rejected at the last row."""
        if not self._static_logged:
            self.log_static()
        rr, rec, exp = self.rr, self.rec, self.exp
        rows = np.asarray(rows)
        times = [rr.TimeColumn("k", sequence=rows), rr.TimeColumn("t", duration=rows * exp.dt)]
        N = exp.N
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_rows = mon.relative_rows(rows) if self._unstable else None
            for b, name in enumerate(mon.block_names):
                # one entity per block, one series per agent (instance i = agent index i)
                e2 = np.log10(mon.error_2[rows, :, b])
                e2[~np.isfinite(e2)] = np.nan
                rec.send_columns(f"errors/{name}", indexes=times,
                                 columns=rr.Scalars.columns(scalars=e2.reshape(-1)).partition([N] * len(rows)))
                if rel_rows is not None:
                    rel = np.log10(rel_rows[:, :, b])
                    rel[~np.isfinite(rel)] = np.nan
                    rec.send_columns(f"relative_errors/{name}", indexes=times,
                                     columns=rr.Scalars.columns(scalars=rel.reshape(-1)).partition([N] * len(rows)))
        for plot in plot_rows(exp):
            name, row, agents = plot
            rec.send_columns(f"state/{name}/truth", indexes=times, columns=rr.Scalars.columns(scalars=x @ row))
            for aid in agents:
                i = exp.agent_ids.index(aid)
                rec.send_columns(f"state/{name}/agent{aid}", indexes=times, columns=rr.Scalars.columns(scalars=est[:, i] @ row))
        self._log_map(rows, delivered)
        self._log_unreported(rows, mon)
        if counters is not None:
            k = int(rows[-1])
            rec.set_time("k", sequence=k)
            rec.set_time("t", duration=k * exp.dt)
            for i, aid in enumerate(exp.agent_ids):
                for c, what in enumerate(("delivered", "dropped", "late", "rejected")):
                    rec.log(f"counters/agent{aid}/{what}", rr.Scalars(float(counters[i, c])))

    def _log_unreported(self, rows: np.ndarray, mon: Any) -> None:
        """``health/agentI``: the rounds so far with no report from agent I (no error
        recorded: a realtime agent that skipped the round, or whose report was lost)."""
        missing = np.isnan(mon.error_2[rows, :, 0]).sum(axis=0)
        if self._unreported is None:
            self._unreported = np.zeros(self.exp.N, dtype=np.int64)
        self._unreported += missing
        k = int(rows[-1])
        self.rec.set_time("k", sequence=k)
        self.rec.set_time("t", duration=k * self.exp.dt)
        for i, aid in enumerate(self.exp.agent_ids):
            self.rec.log(f"health/agent{aid}", self.rr.Scalars(float(self._unreported[i])))

    def log_health(self, health: dict[str, Any], k: int, line: str | None) -> None:
        """``health/summary``: the run's realtime health (``summary.json``'s ``health``) as
        a table at its last round ``k``, with the line that says the rate was not kept."""
        from .health import HEALTH_COLUMNS, health_rows

        rows = health_rows({"health": health})
        text = [f"**{line}**", ""] if line else []
        text += ["| " + " | ".join(HEALTH_COLUMNS) + " |", "|" + "---|" * len(HEALTH_COLUMNS)]
        text += ["| " + " | ".join(r) + " |" for r in rows]
        self.rec.set_time("k", sequence=int(k))
        self.rec.set_time("t", duration=k * self.exp.dt)
        self.rec.log("health/summary", self.rr.TextDocument("\n".join(text), media_type="text/markdown"))

    def _log_map(self, rows: np.ndarray, delivered: dict[int, np.ndarray] | None) -> None:
        """Agent positions and delivered / dropped links of the map frames in ``rows``, as
        one column batch per entity."""
        rr, rec, exp = self.rr, self.rec, self.exp
        ks = [int(k) for k in rows if self.is_map_frame(int(k))]
        if not ks:
            return
        pos_all = np.repeat(self._static_pos[None], len(ks), axis=0)
        for i, sch in enumerate(exp.schedules):
            if sch is not None:
                pos_all[:, i] = [sch.position(k) for k in ks]
        kcol = np.array(ks)
        idx = [rr.TimeColumn("k", sequence=kcol), rr.TimeColumn("t", duration=kcol * exp.dt)]
        rec.send_columns("map/agents", indexes=idx,
                         columns=rr.Points2D.columns(positions=pos_all.reshape(-1, 2)).partition([exp.N] * len(ks)))
        if delivered is None or not all(k in delivered for k in ks):
            return
        for path, want in (("delivered", True), ("dropped", False)):
            origins, vectors, lengths = [], [], []
            for f, k in enumerate(ks):
                mask = delivered[k][self._dst, self._src] == want
                o = pos_all[f, self._src[mask]]
                origins.append(o)
                vectors.append(pos_all[f, self._dst[mask]] - o)
                lengths.append(int(mask.sum()))
            rec.send_columns(f"map/links/{path}", indexes=idx,
                             columns=rr.Arrows2D.columns(origins=np.concatenate(origins), vectors=np.concatenate(vectors)).partition(lengths))

    def log_conviction(self, agent_id: int, k: int) -> None:
        """``events/convictions``: agent ``agent_id`` proven to equivocate, at round ``k``
        (:mod:`agents.evidence`)."""
        self.rec.set_time("k", sequence=int(k))
        self.rec.set_time("t", duration=k * self.exp.dt)
        self.rec.log("events/convictions", self.rr.TextLog(f"agent {agent_id} convicted of equivocation "
                                                           f"(evidence.jsonl)", level="ERROR"))

    def is_map_frame(self, k: int) -> bool:
        return k % self._map_every == 0 or k == self.exp.n_rounds

    def flush(self) -> None:
        self.rec.flush()

    def close(self) -> None:
        """Flush and close every sink (the file, a served gRPC endpoint, a viewer link)."""
        try:
            self.rec.flush()
        finally:
            self.rec.disconnect()

    def __enter__(self) -> "Dashboard":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def log_fault_marks(path: Path, *, run_id: str, dt: float, marks: list[tuple[int, str]]) -> None:
    """``events/faults`` markers (one ``TextLog`` per ``(round, text)``) on the timelines of
    the run ``run_id``, written to ``path`` (``rse chaos``: ``chaos.rrd``). The recording id is
    the run's: opened with the run's ``recording.rrd`` the faults sit on its timeline."""
    import rerun as rr

    rec = rr.RecordingStream("rse", recording_id=run_id)
    rec.set_sinks(rr.FileSink(str(path)))
    try:
        for k, text in sorted(marks):
            rec.set_time("k", sequence=int(k))
            rec.set_time("t", duration=k * dt)
            rec.log("events/faults", rr.TextLog(text, level="WARN"))
    finally:
        rec.flush()
        rec.disconnect()
