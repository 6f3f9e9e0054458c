"""Who records a team's run directory, and leaving it consistent whatever happened
(:mod:`agents.recorder`): the monitor process that records the run names itself in
``RUN_DIR/monitor.pid`` (a monitor that rejoins with ``rse monitor --team`` too), and the
launcher, once the team has stopped, waits for such a monitor, completes a directory whose
monitor is gone from the metrics it streamed, and names a failed plant as the reason."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from scenarios.build import Experiment

log = logging.getLogger("rse.net")

#: the file in the run directory naming the process id of the monitor recording the run
MONITOR_PID = "monitor.pid"
#: how long the launcher waits for a rejoined monitor to finish after the team stopped
REJOINED_MONITOR_S = 30.0


def claim(out: Path) -> None:
    """This process (a monitor) records ``out`` from now on."""
    out.mkdir(parents=True, exist_ok=True)
    (out / MONITOR_PID).write_text(f"{os.getpid()}\n")


def release(out: Path, exp: Experiment) -> None:
    """This monitor stops recording ``out``; stopped before its rounds began, it leaves what
    earlier monitors recorded, or a summary header (``complete: false``)."""
    if not (out / "summary.json").exists():
        from agents.recorder import salvage

        with contextlib.suppress(Exception):
            salvage(out, exp, reason="interrupted")
    with contextlib.suppress(OSError):
        if (out / MONITOR_PID).read_text().strip() == str(os.getpid()):
            (out / MONITOR_PID).unlink()


def complete_run_dir(run_dir: Path, exp: Experiment, *, plant_failed: str | None, stopping: bool, children: set[int]) -> None:
    """Leave the run directory consistent whatever happened (:mod:`agents.recorder`).

    A monitor that rejoined the team (``rse monitor --team``, not a child) is given
    :data:`REJOINED_MONITOR_S` to finish; a run whose monitor is gone is completed from the
    metrics it streamed (``complete: false``); a plant failure is named as the reason.
    """
    from agents.recorder import salvage
    from agents.rundir import write_json

    pid_file = run_dir / MONITOR_PID
    end = time.monotonic() + REJOINED_MONITOR_S
    while not stopping and not (run_dir / "summary.json").exists() and time.monotonic() < end:
        try:
            pid = int(pid_file.read_text().strip())
            os.kill(pid, 0)
        except (OSError, ValueError):
            break  # no monitor is running
        if pid in children:
            break  # our own monitor, already stopped
        time.sleep(0.1)
    with contextlib.suppress(OSError):
        pid_file.unlink()
    reason = plant_failed or ("interrupted" if stopping else "no monitor was running at the end of the run")
    try:
        if salvage(run_dir, exp, reason=reason):
            return
        if plant_failed:
            summary = json.loads((run_dir / "summary.json").read_text())
            if summary.get("complete") is False:
                summary["reason"] = f"{plant_failed} after round {summary.get('last_round')}"
                write_json(run_dir / "summary.json", summary)
    except (OSError, ValueError) as exc:
        log.warning("could not complete the run directory %s: %s", run_dir, exc)
