"""Real ``rse`` processes for the multi-process tests: each in its own process group,
all killed (SIGKILL to the group) at the end of a test whatever happened."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.conftest import ROOT


def rse_cmd(*args: str) -> list[str]:
    exe = shutil.which("rse")
    return [exe, *args] if exe else [sys.executable, "-c", "from agents.cli import main; main()", *args]


def child_env() -> dict:
    e = dict(os.environ)
    e.pop("RSE_DEBUG", None)
    e["COLUMNS"] = "200"
    return e


class Procs:
    """Processes started by a test; :meth:`kill_all` kills each one's process group."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], **kw) -> subprocess.Popen:
        p = subprocess.Popen(args, cwd=ROOT, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True, **kw)
        self.procs.append(p)
        return p

    def router(self, *args: str, timeout: float = 20.0) -> tuple[subprocess.Popen, str]:
        """Start ``rse router ARGS`` and return it with the endpoint it printed."""
        p = self.start(rse_cmd("router", *args))
        end = time.monotonic() + timeout
        lines = []
        while time.monotonic() < end:
            line = p.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.match(r"rse router: listening on (\S+)", line)
            if m:
                return p, m.group(1)
        p.kill()
        raise AssertionError(f"the router printed no endpoint: {''.join(lines)} {p.stderr.read()}")

    def kill_all(self) -> None:
        for p in self.procs:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            try:
                p.communicate(timeout=5)
            except Exception:
                pass


def wait_json(path: Path, timeout: float) -> dict:
    """The JSON in ``path`` once it is there and whole (a writer may still be writing it);
    an AssertionError after ``timeout`` seconds (only a hang reaches it)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            time.sleep(0.05)
    raise AssertionError(f"{path} did not appear within {timeout} s")


def until(cond, timeout: float, act=None) -> bool:
    """Whether ``cond()`` holds within ``timeout`` seconds (``act()`` before each look)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if act is not None:
            act()
        if cond():
            return True
        time.sleep(0.05)
    return cond()
