"""Scenario files as pytest tests: ``pytest --rse PATH ...`` (a ``pytest11`` entry point).

Every ``.toml`` file with ``[[expect]]`` bounds under the paths is collected as a test file
whose items are its bounds, one each: the scenario is run once (the first of its items
runs it; the run directory is kept under pytest's temporary path) and each item passes or
fails on its own bound, with the measured value. A failure shows the file's table of
bounds (measured, bound, result) and the run directory; a bound that a shortened run
cannot judge is a skip with the reason; ``--junitxml`` carries ``measured``, ``bound``
and ``run_dir`` as properties of each test case.

Options: ``--rse-driver simulate|run`` (the in-process simulator, or plant, monitor and
agent processes over Zenoh on loopback, :func:`rse.run_team`), ``--rse-quick`` (each
run shortened to a quarter of its horizon) or ``--rse-rounds N`` (at most N rounds),
``--rse-set KEY=VALUE`` (repeatable; overrides as ``rse simulate --set``).

Runs go through the public API (:func:`rse.load`, :func:`rse.simulate`,
:func:`rse.run_team`); the module imports only pytest until ``--rse`` is given.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:  # pragma: no cover
    from _pytest._code.code import TerminalRepr
    from _pytest.terminal import TerminalReporter

    from agents.runs import RunResult
    from agents.summary import ExpectationResult

#: the lockstep deadline of a networked smoke run: a slow agent on a busy CI runner is
#: waited for (a crashed one is seen leaving at once), so the run equals the simulator's
TEAM_DEADLINE = 30.0
QUICK_FRACTION = 4  # --rse-quick: a quarter of each horizon

_LINES = pytest.StashKey[list[tuple[str, str, str, str]]]()
_INTERRUPTED = pytest.StashKey[int]()  # the session's exit status, once a signal interrupted a run


def pytest_addoption(parser: pytest.Parser) -> None:
    g = parser.getgroup("rse", "scenario files as tests (resilient-state-estimation)")
    g.addoption("--rse", action="store_true", default=False,
                help="collect every scenario file with [[expect]] bounds under the given paths: one test per bound")
    g.addoption("--rse-driver", choices=("simulate", "run"), default="simulate",
                help="simulate: the in-process simulator (default); run: plant, monitor and agent processes over Zenoh on loopback")
    g.addoption("--rse-quick", action="store_true", default=False,
                help="shorten each run to a quarter of its horizon; the bounds it cannot judge are skipped with the reason")
    g.addoption("--rse-rounds", type=int, default=None, metavar="N",
                help="shorten each run to at most N rounds; the bounds it cannot judge are skipped with the reason")
    g.addoption("--rse-set", action="append", default=[], metavar="KEY=VALUE",
                help="override a key of every scenario (repeatable), as rse simulate --set")


def pytest_configure(config: pytest.Config) -> None:
    if not config.getoption("rse"):
        return
    rounds = config.getoption("rse_rounds")
    if rounds is not None and rounds < 1:
        raise pytest.UsageError(f"--rse-rounds: expected a positive number of rounds, got {rounds}")
    if rounds is not None and config.getoption("rse_quick"):
        raise pytest.UsageError("--rse-quick and --rse-rounds: give one of them")
    from rse import pin_blas_threads

    pin_blas_threads()  # as the rse command does: one BLAS thread per process
    config.stash[_LINES] = []


def _has_expectations(path: Path) -> bool:
    """A scenario file for ``--rse``: a TOML file with ``[[expect]]`` tables (a file that
    says ``[[expect]]`` but does not parse is collected too, to fail with the reason)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    try:
        expect = tomllib.loads(text).get("expect")
    except tomllib.TOMLDecodeError:
        return "[[expect]]" in text
    return isinstance(expect, list) and bool(expect)


def pytest_collect_file(file_path: Path, parent: pytest.Collector) -> ScenarioFile | None:
    if file_path.suffix == ".toml" and parent.config.getoption("rse") and _has_expectations(file_path):
        return ScenarioFile.from_parent(parent, path=file_path)
    return None


def _one_line(exc: BaseException) -> str:
    from agents.net.exits import describe

    return describe(exc)


def _is_ours(exc: BaseException) -> bool:
    from estimation.errors import RSEError

    return isinstance(exc, RSEError | OSError)


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM interrupts a run as Ctrl-C does (as it does ``rse simulate`` and ``rse run``):
    the team's processes are stopped and the run directory is completed before pytest ends
    (pytest's own default for SIGTERM is to die at once, leaving the processes behind)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt("SIGTERM")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@dataclass
class _Outcome:
    result: RunResult | None
    error: BaseException | None
    run_dir: Path
    overrides: list[str]


class ScenarioFile(pytest.File):
    """A scenario file: one item per ``[[expect]]`` bound; the run is shared by its items."""

    _outcome: _Outcome | None = None

    def _overrides(self) -> list[str]:
        """``--rse-set`` and the shortening (``run.rounds``, or ``run.duration`` where the
        file gives its horizon in seconds)."""
        from scenarios.loader import load

        cfg = self.config
        ov = list(cfg.getoption("rse_set"))
        sc, _ = load(self.path, ov)
        n = sc.run.n_rounds
        want = cfg.getoption("rse_rounds")
        if cfg.getoption("rse_quick"):
            want = max(1, math.ceil(n / QUICK_FRACTION))
        if want is not None and want < n:
            ov.append(f"run.rounds={want}" if sc.run.rounds is not None else f"run.duration={want * sc.run.dt!r}")
        return ov

    def collect(self) -> list[ExpectationItem]:
        from agents.summary import describe
        from scenarios.loader import load

        sc, _ = load(self.path, self.config.getoption("rse_set"))
        at = [n for n, text in enumerate(self.path.read_text(encoding="utf-8").splitlines()) if text.strip() == "[[expect]]"]
        items, seen = [], set()
        for i, e in enumerate(sc.expect):
            name = describe(e).replace("::", ":")
            if name in seen:
                name = f"{name} #{i + 1}"
            seen.add(name)
            line = at[i] if len(at) == len(sc.expect) else 0
            items.append(ExpectationItem.from_parent(self, name=name, index=i, line=line))
        return items

    def outcome(self) -> _Outcome:
        """The run of this file (done once, by the first item that asks)."""
        if self._outcome is None:
            import rse

            factory: pytest.TempPathFactory = self.config._tmp_path_factory  # type: ignore[attr-defined]
            run_dir = factory.mktemp(self.path.stem)
            ov: list[str] = []
            try:
                ov = self._overrides()
                exp = rse.load(self.path, set=ov)
                with _sigterm_interrupts():
                    if self.config.getoption("rse_driver") == "run":
                        res = rse.run_team(exp, out=run_dir, deadline=TEAM_DEADLINE)
                    else:
                        res = rse.simulate(exp, out=run_dir)
                self._outcome = _Outcome(res, None, run_dir, ov)
            except KeyboardInterrupt:
                self.config.stash[_INTERRUPTED] = pytest.ExitCode.INTERRUPTED
                raise
            except Exception as exc:  # every item of the file reports it
                self._outcome = _Outcome(None, exc, run_dir, ov)
        return self._outcome

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException]) -> str | TerminalRepr:  # type: ignore[override]
        if _is_ours(excinfo.value):
            return _one_line(excinfo.value)
        return super().repr_failure(excinfo)


def _fmt(v: float | None) -> str:
    return "-" if v is None else ("nan" if math.isnan(v) else f"{v:.4g}")


def bound_text(r: ExpectationResult) -> str:
    """``<= 0.25``, ``>= 0.3`` or both."""
    parts = ([f"<= {_fmt(r.max)}"] if r.max is not None else []) + ([f">= {_fmt(r.min)}"] if r.min is not None else [])
    return " and ".join(parts)


def _status(r: ExpectationResult) -> str:
    return "not judged" if r.ok is None else ("ok" if r.ok else "FAIL")


def table(path: Path, out: _Outcome) -> str:
    """The file's bounds, measured values and results, and where the run is."""
    assert out.result is not None
    rows = [("", "expectation", "measured", "bound")]
    rows += [(_status(r), r.label + (f" ({r.reason})" if r.reason else ""), _fmt(r.value) if r.evaluated else "-",
              bound_text(r)) for r in out.result.expectations()]
    w = [max(len(row[c]) for row in rows) for c in range(4)]
    lines = [f"{a:<{w[0]}}  {b:<{w[1]}}  {c:>{w[2]}}  {d}" for a, b, c, d in rows]
    head = f"{path.name} ({out.result.driver}" + (f", --set {' '.join(out.overrides)}" if out.overrides else "") + ")"
    return "\n".join([head, *lines, f"run directory: {out.run_dir}"])


class BoundFailed(Exception):
    """An ``[[expect]]`` bound of a scenario does not hold (the message is the table)."""


class ExpectationItem(pytest.Item):
    """One ``[[expect]]`` bound of a scenario file."""

    def __init__(self, *, index: int, line: int = 0, **kw: Any) -> None:
        super().__init__(**kw)
        self.index = index
        self.line = line  # of its [[expect]] table in the file (0-based, as pytest reports)

    def runtest(self) -> None:
        assert isinstance(self.parent, ScenarioFile)
        out = self.parent.outcome()
        self.user_properties.append(("run_dir", str(out.run_dir)))
        if out.error is not None:
            self._line("ERROR", "-", "-")
            raise out.error
        assert out.result is not None
        r = out.result.expectations()[self.index]
        self.user_properties.append(("bound", bound_text(r)))
        if r.ok is None:
            self._line("SKIP", "-", bound_text(r))
            # reported at the bound's line of the scenario file, as pytest's skip marks are
            raise pytest.skip.Exception(f"{r.label}: not judged: {r.reason}", _use_item_location=True)
        self.user_properties.append(("measured", repr(r.value)))
        self._line("PASS" if r.ok else "FAIL", _fmt(r.value), bound_text(r))
        if not r.ok:
            raise BoundFailed(f"measured {_fmt(r.value)}, bound {bound_text(r)}\n\n{table(self.path, out)}")

    def _line(self, status: str, measured: str, bound: str) -> None:
        lines = self.config.stash.get(_LINES, None)
        if lines is not None:
            lines.append((status, measured, bound, self.nodeid))

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException], style: Any = None) -> str | TerminalRepr:
        if isinstance(excinfo.value, BoundFailed):
            return str(excinfo.value)
        if _is_ours(excinfo.value):
            assert isinstance(self.parent, ScenarioFile)
            out = self.parent.outcome()
            return f"{self.path.name}: {_one_line(excinfo.value)}\nrun directory: {out.run_dir}"
        return super().repr_failure(excinfo, style=style)

    def reportinfo(self) -> tuple[Path, int | None, str]:
        return self.path, self.line, f"{self.path.name}: {self.name}"


def pytest_terminal_summary(terminalreporter: TerminalReporter, exitstatus: int, config: pytest.Config) -> None:
    """The per-bound report: every bound judged, with its measured value."""
    lines = config.stash.get(_LINES, None)
    if not lines or config.get_verbosity() < -1:
        return
    terminalreporter.section("rse scenario bounds")
    w = max(len(m) for _, m, _, _ in lines)
    wb = max(len(b) for _, _, b, _ in lines)
    for status, measured, bound, nodeid in lines:
        terminalreporter.write_line(f"{status:<5} {measured:>{w}} {bound:<{wb}}  {nodeid}")


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    """After Ctrl-C or SIGTERM stopped a run (its processes stopped, its run directory
    completed, pytest's report written): exit at once, as the ``rse`` command does, instead
    of the interpreter's teardown of numpy, scipy and the rest, which takes seconds on a
    loaded machine (a command ends within 2 s of a signal)."""
    status = config.stash.get(_INTERRUPTED, None)
    if status is None:
        return
    import atexit
    import os
    import sys

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(int(status))
