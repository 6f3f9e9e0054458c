"""Terminal output shared by the sub-commands: progress bars, tables, errors (rich)."""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


def fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.{digits}g}"
    return str(v)


@contextmanager
def round_progress(total: int | None, label: str, *, enabled: bool = True) -> Iterator[Any]:
    """A progress bar over rounds showing rounds/s and the worst current error.

    Yields ``update(k, worst_error)``.
    """
    if not enabled:
        yield lambda k, worst: None
        return
    prog = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("rounds"),
        TextColumn("{task.fields[rate]}"),
        TextColumn("worst |e|_inf {task.fields[worst]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err,
        transient=False,
    )
    with prog:
        task = prog.add_task(label, total=total, rate="", worst="-")

        def update(k: int, worst: float) -> None:
            speed = prog.tasks[task].speed
            prog.update(task, completed=k + 1, worst=fmt(worst, 3), rate=f"{speed:,.0f}/s" if speed else "")

        yield update


def summary_table(summary: dict, *, block: str = "x", title: str | None = None) -> Table:
    t = Table(title=title, title_justify="left")
    for col in ("agent", "regular", "final |e|_inf", "final |e|_2 / |x|_2", "window max |e|_inf", "converged at round"):
        t.add_column(col, justify="right")
    for aid, rec in summary["agents"].items():
        b = rec["blocks"].get(block, {})
        t.add_row(aid, fmt(rec["regular"]), fmt(b.get("final_error_inf")), fmt(b.get("final_relative_error_2")),
                  fmt(b.get("window_max_error_inf")), fmt(b.get("convergence_round")))
    w = summary["worst_regular"].get(block, {})
    if w:
        t.add_row("[bold]worst regular", "", fmt(w.get("final_error_inf")), fmt(w.get("final_relative_error_2")),
                  fmt(w.get("window_max_error_inf")), fmt(w.get("convergence_round")), end_section=True)
    det = summary.get("detected_attacks")
    if det is not None:
        by = det.get("by_agent", {})
        who = [f"agent {a} (t = {fmt(by[str(a)]['first_t'])} .. {fmt(by[str(a)]['last_t'])})" for a in det.get("agents", [])]
        t.caption = "attack flags: " + (", ".join(who) if who else "none raised")
        t.caption_justify = "left"
    return t


def expectations_table(results: list) -> Table:
    """The ``[[expect]]`` bounds: ok, FAIL, or not evaluated (with the reason)."""
    t = Table(title="expectations", title_justify="left")
    t.add_column("")
    t.add_column("expectation")
    t.add_column("measured", justify="right")
    t.add_column("bound", justify="right")
    for r in results:
        bound = " and ".join(x for x in ((f"<= {fmt(r.max)}" if r.max is not None else ""), (f">= {fmt(r.min)}" if r.min is not None else "")) if x)
        if r.ok is None:
            t.add_row("[yellow]not evaluated", f"{r.label}\n[dim]{r.reason or ''}", "-", bound)
        else:
            t.add_row("[green]ok" if r.ok else "[red]FAIL", r.label, fmt(r.value), bound)
    skipped = sum(r.ok is None for r in results)
    if skipped:
        t.caption = f"{skipped} of {len(results)} expectation(s) not evaluated (they do not fail the run)"
        t.caption_justify = "left"
    return t


def error(msg: str) -> None:
    err.print(f"[bold red]error:[/] {msg}", soft_wrap=True)


def is_tty() -> bool:
    return sys.stderr.isatty()


def health_table(summary: dict[str, Any]) -> Table | None:
    """A networked run's realtime health (:mod:`agents.health`), a row per agent; None when
    the summary has none (a simulator run)."""
    from .health import HEALTH_COLUMNS, health_rows

    rows = health_rows(summary)
    if not rows:
        return None
    h = summary["health"]
    rate = f" at {h['rate_hz']:g} Hz" if h.get("rate_hz") else ""
    t = Table(title=f"health ({h.get('mode')}{rate}; plant deadline misses: {fmt(h.get('deadline_misses'))})",
              title_justify="left")
    for c in HEALTH_COLUMNS:
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(*r)
    return t
