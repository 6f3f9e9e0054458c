"""The container health check: is this container's ``rse`` process on the Zenoh network?

The image's ``HEALTHCHECK`` runs ``python -m agents.healthcheck``. It finds the ``rse``
process of the container (the entry point, PID 1, or the child of ``init: true``'s
``docker-init``), reads the endpoints of its command line and checks the sockets behind
them:

* ``--listen PROTO/HOST:PORT`` (the router, a peer): a socket listens on ``PORT`` (on
  some port for ``PORT`` 0);
* ``--connect PROTO/HOST:PORT`` (a client of the router, a peer): a TCP connection to one of
  those ports is established, i.e. the process's Zenoh session is connected;
* no endpoint on the command line (e.g. ``rse router`` with its default, or a
  non-network command): ``rse router`` must listen on 7447, anything else must merely be
  running.

A process that is stopped or a zombie is unhealthy. Exit status 0 healthy, 1 unhealthy,
with one line saying why (``docker inspect`` shows it). A role still building its
scenario has no session yet: the image gives it a start period before failures count.

Usage::

    python -m agents.healthcheck              # the rse process of this container
    python -m agents.healthcheck --pid 4242   # a given process (tests)
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

#: what ``rse router`` listens on without --listen (agents.net.router.DEFAULT_LISTEN)
ROUTER_DEFAULT_PORT = 7447
_PORT_RE = re.compile(r"^[a-z-]+/.*:(\d{1,5})(?:[?#].*)?$")


@dataclass
class Expected:
    """The sockets an ``rse`` command line implies.

    Attributes
    ----------
    command : str
        The sub-command (``router``, ``agent``, ...; ``""`` if none).
    listen : list of int
        Ports it must listen on.
    connect : list of int
        Ports of which it must have at least one established connection.
    """

    command: str = ""
    listen: list[int] = field(default_factory=list)
    connect: list[int] = field(default_factory=list)


def endpoint_port(endpoint: str) -> int | None:
    """The port of a Zenoh endpoint ``PROTO/HOST:PORT`` (``HOST:PORT`` means tcp), or None."""
    ep = endpoint if "/" in endpoint else f"tcp/{endpoint}"
    m = _PORT_RE.match(ep.strip())
    return int(m.group(1)) if m else None


def expected_sockets(argv: Sequence[str]) -> Expected:
    """What the ``rse`` command line ``argv`` (after the program name) should have open.

    ``--listen X`` / ``--listen=X`` and ``--connect X`` / ``--connect=X`` (repeatable) give
    the ports; ``rse router`` without ``--listen`` listens on :data:`ROUTER_DEFAULT_PORT`.
    """
    exp = Expected()
    args = list(argv)
    exp.command = next((a for a in args if not a.startswith("-")), "")
    for i, a in enumerate(args):
        for flag, into in (("--listen", exp.listen), ("--connect", exp.connect)):
            value = None
            if a == flag and i + 1 < len(args):
                value = args[i + 1]
            elif a.startswith(flag + "="):
                value = a[len(flag) + 1:]
            if value is not None and (port := endpoint_port(value)) is not None:
                into.append(port)
    if exp.command == "router" and not exp.listen:
        exp.listen.append(ROUTER_DEFAULT_PORT)
    return exp


def rse_argv(cmdline: Sequence[str]) -> list[str] | None:
    """The arguments after ``rse`` in a process's command line, or None if it is not ``rse``.

    Matches ``rse ...``, ``python /usr/local/bin/rse ...`` and ``python -m agents.cli ...``;
    not an init that starts it (``docker-init -- rse ...``), whose sockets are not rse's.
    """
    args = list(cmdline)
    if args and os.path.basename(args[0]) == "rse":
        return args[1:]
    if not args or not os.path.basename(args[0]).startswith("python"):
        return None
    if len(args) > 1 and os.path.basename(args[1]) == "rse":
        return args[2:]
    if args[1:3] == ["-m", "agents.cli"]:
        return args[3:]
    return None


def find_rse(processes: Iterable, me: int) -> tuple | None:
    """The first ``(process, argv)`` of ``processes`` (psutil) running ``rse``, skipping ``me``."""
    import psutil

    for p in processes:
        if p.pid == me:
            continue
        try:
            argv = rse_argv(p.cmdline())
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
        if argv is not None:
            return p, argv
    return None


def check(pid: int | None = None) -> tuple[bool, str]:
    """Check the ``rse`` process ``pid`` (default: the first one in this container).

    Returns
    -------
    (healthy, reason) : tuple of bool and str
    """
    import psutil

    label = ""
    try:
        if pid is not None:
            proc = psutil.Process(pid)
            argv = rse_argv(proc.cmdline())
            if argv is None:  # not rse: check the endpoints of its command line all the same
                argv, label = list(proc.cmdline()[1:]), f"process {pid}"
        else:
            found = find_rse(psutil.process_iter(), os.getpid())
            if found is None:
                return False, "no rse process in this container"
            proc, argv = found
        status = proc.status()
        if status in (psutil.STATUS_ZOMBIE, psutil.STATUS_STOPPED, psutil.STATUS_DEAD):
            return False, f"rse process {proc.pid} is {status}"
        conns = (getattr(proc, "net_connections", None) or proc.connections)(kind="inet")
    except psutil.NoSuchProcess:
        return False, f"process {pid} does not exist"
    except psutil.AccessDenied as exc:
        return False, f"cannot inspect process {exc.pid or pid}: access denied"
    exp = expected_sockets(argv)
    what = label or f"rse {exp.command}".rstrip()
    listening = {c.laddr.port for c in conns if c.status == psutil.CONN_LISTEN and c.laddr}
    established = {c.raddr.port for c in conns if c.status == psutil.CONN_ESTABLISHED and c.raddr}
    missing = [p for p in exp.listen if p not in listening and not (p == 0 and listening)]  # 0: any port
    if missing:
        return False, f"{what}: not listening on port {', '.join(map(str, missing))}"
    shown = sorted({p for p in exp.listen if p} | (listening if 0 in exp.listen else set()))
    if exp.connect and not established & set(exp.connect):
        return False, f"{what}: no connection to port {' or '.join(map(str, sorted(set(exp.connect))))} (its Zenoh session is not connected)"
    parts = [f"listening on {', '.join(map(str, shown))}"] if exp.listen else []
    if exp.connect:
        parts.append(f"connected to port {', '.join(str(p) for p in sorted(established & set(exp.connect)))}")
    return True, f"{what}: " + ("; ".join(parts) if parts else "running")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m agents.healthcheck``; prints one line, returns 0 or 1."""
    parser = argparse.ArgumentParser(prog="python -m agents.healthcheck",
                                     description="Health of this container's rse process (exit 0 healthy, 1 not).")
    parser.add_argument("--pid", type=int, default=None, help="check this process (default: the rse process found)")
    args = parser.parse_args(argv)
    ok, reason = check(args.pid)
    print(("healthy: " if ok else "unhealthy: ") + reason)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
