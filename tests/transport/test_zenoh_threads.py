"""Zenoh's threads in a role process (``transport.zenoh_session.one_zenoh_thread``).

Each case runs in a fresh interpreter: Zenoh reads ``ZENOH_RUNTIME`` once per process,
when it starts its runtimes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from transport.zenoh_session import HANDED_OVER

ROOT = Path(__file__).resolve().parents[2]

# two peers in one process exchange 20 messages, then the names of the process's threads
THREADS = textwrap.dedent(
    """
    import json, os, sys, time
    from transport.zenoh_session import SessionOptions, free_tcp_port, one_zenoh_thread, open_session, tcp_endpoint
    applied = one_zenoh_thread() if sys.argv[1] == "role" else None
    port = free_tcp_port()
    got = []
    with open_session(SessionOptions(mode="peer", listen=(tcp_endpoint(port),))) as a, \\
            open_session(SessionOptions(mode="peer", connect=(tcp_endpoint(port),))) as b:
        sub = a.declare_subscriber("rse/test/threads", lambda s: got.append(1))
        deadline = time.monotonic() + 10
        while len(got) < 20 and time.monotonic() < deadline:
            b.put("rse/test/threads", b"x")
            time.sleep(0.02)
        names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task"))
    print(json.dumps({"applied": applied, "env": os.environ.get("ZENOH_RUNTIME"), "got": len(got), "threads": names}))
    """
)


def _run(mode: str, env_value: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if env_value is not None:
        env["ZENOH_RUNTIME"] = env_value
    proc = subprocess.run([sys.executable, "-c", THREADS, mode], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _zenoh_threads(names: list[str]) -> set[str]:
    return {n.rpartition("-")[0] for n in names if n.rpartition("-")[0] in {"app", *HANDED_OVER}}


pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="thread names are read from /proc (Linux)")


def test_a_role_process_runs_zenoh_on_its_application_runtime_only():
    out = _run("role", None)
    assert out["applied"] is True and out["got"] >= 20
    assert "handover: app" in out["env"]
    assert _zenoh_threads(out["threads"]) == {"app"}, out["threads"]


def test_zenoh_keeps_its_own_threads_elsewhere_and_when_the_user_sets_zenoh_runtime():
    plain = _run("plain", None)  # a process that is not a role (the bench's skeletons): Zenoh's defaults
    assert plain["got"] >= 20 and plain["env"] is None
    assert {"rx", "tx"} <= _zenoh_threads(plain["threads"]), plain["threads"]
    user = _run("role", "()")  # the user's setting wins: '()' is Zenoh's defaults
    assert user["applied"] is False and user["env"] == "()"
    assert {"rx", "tx"} <= _zenoh_threads(user["threads"]), user["threads"]


def test_a_bad_zenoh_runtime_is_a_one_line_transport_error():
    code = ("from estimation.errors import TransportError\nfrom transport.zenoh_session import open_session\n"
            "try:\n    open_session()\nexcept TransportError as exc:\n    print('ERR', exc)\n")
    env = dict(os.environ, ZENOH_RUNTIME="(rx: (worker_thread: 1))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("ERR Zenoh failed to start"), proc.stdout
    assert "ZENOH_RUNTIME='(rx: (worker_thread: 1))'" in proc.stdout and len(proc.stdout.strip().splitlines()) == 1
