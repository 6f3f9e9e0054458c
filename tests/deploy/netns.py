"""Hosts on a virtual network for multi-host tests: Linux network namespaces on a bridge.

::

    with Net(hosts=4) as net:        # namespaces h0..h3 plus a switch namespace
        net.addr(0)                  # '10.A.B.1', host 0's address on the /24
        p = net.start(0, ["rse", "router", "--listen", f"tcp/{net.addr(0)}:7447"])
        net.link(3, up=False)        # unplug host 3's cable at the switch
        net.link(3, up=True)
        net.isolate([0, 2], on=True)  # host 2 and host 0 no longer reach each other

Layout: a *switch* namespace holds a Linux bridge ``br0``; each host namespace ``hI`` has
one interface ``eth0`` (address ``10.A.B.(I+1)/24``, ``A.B`` random per network), the
other end of its veth pair, ``pI``, is a port of the bridge. Nothing is added to the
caller's own namespace (no address, no route, no iptables rule). :meth:`Net.link` sets the
switch-side port down or up: the host keeps its address and its processes, but its frames
go nowhere (the host side sees NO-CARRIER), like a pulled cable. :meth:`Net.isolate` sets
the bridge's port isolation instead: a partition with every link up (frames silently
dropped between the isolated ports, as a misconfigured switch or firewall would).

Names are ``rsenet-{pid}-{random}-{sw|hI}``, unique per network; :meth:`Net.close`
(also called on ``with`` exit, and at interpreter exit for every network still open)
kills every process started with :meth:`Net.start` (whole process group), then every
process still inside the namespaces, then deletes the namespaces (which deletes their
interfaces and the bridge). :func:`reap_stale` deletes the namespaces of earlier test
processes that died without cleaning up (their pid is in the name).

Needs root and a kernel with network namespaces, veth and bridge; :func:`unavailable`
says why not, for a ``pytest.skip``.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import re
import secrets
import shutil
import signal
import subprocess
import time
from collections.abc import Sequence
from typing import Any

PREFIX = "rsenet"
_OPEN: list["Net"] = []
_NAME_RE = re.compile(rf"^{PREFIX}-(\d+)-[0-9a-f]+-(sw|h\d+)$")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if check and r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip() or r.returncode}")
    return r


def unavailable() -> str | None:
    """Why network namespaces cannot be used here (``None``: they can)."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root (ip netns add, veth pairs, a bridge)"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    probe = f"{PREFIX}-{os.getpid()}-{secrets.token_hex(3)}-h0"
    r = _ip("netns", "add", probe, check=False)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip() or r.returncode}"
    try:
        r = _ip("-n", probe, "link", "add", "br0", "type", "bridge", check=False)
        if r.returncode != 0:
            return f"cannot create a bridge in a namespace: {r.stderr.strip()}"
        r = _ip("-n", probe, "link", "add", "probe0", "type", "veth", "peer", "name", "probe1", check=False)
        if r.returncode != 0:
            return f"cannot create a veth pair in a namespace: {r.stderr.strip()}"
    finally:
        _delete_ns(probe)
    return None


def _ns_pids(ns: str) -> list[int]:
    r = _ip("netns", "pids", ns, check=False)
    return [int(x) for x in r.stdout.split()] if r.returncode == 0 else []


def _delete_ns(ns: str) -> None:
    """Kill what still runs inside ``ns`` (processes this test started there), delete it."""
    for _ in range(3):
        pids = _ns_pids(ns)
        if not pids:
            break
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)
    _ip("netns", "del", ns, check=False)


def reap_stale() -> list[str]:
    """Delete the namespaces of test processes that are gone (``rsenet-{pid}-...`` with a
    dead pid); returns their names."""
    r = _ip("netns", "list", check=False)
    gone = []
    for line in r.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        m = _NAME_RE.match(name)
        if not m:
            continue
        pid = int(m.group(1))
        try:
            os.kill(pid, 0)
            continue  # still running: not ours to touch
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        _delete_ns(name)
        gone.append(name)
    return gone


class Net:
    """``hosts`` network namespaces on one bridge (see the module docstring)."""

    def __init__(self, hosts: int) -> None:
        if not 1 <= hosts <= 250:
            raise ValueError(f"hosts must be in 1..250, got {hosts}")
        self.tag = f"{PREFIX}-{os.getpid()}-{secrets.token_hex(3)}"
        self.switch = f"{self.tag}-sw"
        self.hosts = [f"{self.tag}-h{i}" for i in range(hosts)]
        self.subnet = f"10.{secrets.randbelow(200) + 50}.{secrets.randbelow(250) + 1}"
        self.procs: list[subprocess.Popen] = []
        self._created: list[str] = []
        self._closed = False

    # ------------------------------------------------------------------ set-up

    def __enter__(self) -> "Net":
        try:
            self.up()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def up(self) -> None:
        _OPEN.append(self)
        for ns in (self.switch, *self.hosts):
            _ip("netns", "add", ns)
            self._created.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        sw = self.switch
        _ip("-n", sw, "link", "add", "br0", "type", "bridge")
        _ip("-n", sw, "link", "set", "br0", "up")
        for i, ns in enumerate(self.hosts):
            _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", f"p{i}", "netns", sw)
            _ip("-n", sw, "link", "set", f"p{i}", "master", "br0")
            _ip("-n", sw, "link", "set", f"p{i}", "up")
            _ip("-n", ns, "addr", "add", f"{self.addr(i)}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def addr(self, i: int) -> str:
        """Host ``i``'s IPv4 address."""
        return f"{self.subnet}.{i + 1}"

    def port(self, i: int) -> str:
        """The bridge port (in the switch namespace) of host ``i``."""
        return f"p{i}"

    # ------------------------------------------------------------------ faults

    def link(self, i: int, up: bool) -> float:
        """Set host ``i``'s bridge port up or down; returns ``time.monotonic()`` after."""
        _ip("-n", self.switch, "link", "set", self.port(i), "up" if up else "down")
        return time.monotonic()

    def isolate(self, hosts: Sequence[int], on: bool) -> float:
        """Set the bridge's ``isolated`` flag on the ports of ``hosts``: hosts whose ports
        are isolated cannot reach each other (their frames are silently dropped; the links
        stay up, carrier and addresses unchanged) but still reach every other host. So
        ``isolate([0, 2], True)`` partitions host 2 from host 0 and nothing else. Returns
        ``time.monotonic()`` after."""
        for i in hosts:
            _ip("-n", self.switch, "link", "set", self.port(i), "type", "bridge_slave", "isolated", "on" if on else "off")
        return time.monotonic()

    def link_is_up(self, i: int) -> bool:
        r = _ip("-n", self.switch, "-o", "link", "show", self.port(i))
        flags = r.stdout.split("<", 1)[-1].split(">", 1)[0].split(",")
        return "UP" in flags

    # --------------------------------------------------------------- processes

    def command(self, i: int, args: Sequence[str]) -> list[str]:
        """``args`` run inside host ``i``'s namespace."""
        return ["ip", "netns", "exec", self.hosts[i], *args]

    def start(self, i: int, args: Sequence[str], **kw: Any) -> subprocess.Popen:
        """Start ``args`` in host ``i`` (own process group; killed by :meth:`close`)."""
        kw.setdefault("stdout", subprocess.PIPE)
        kw.setdefault("stderr", subprocess.PIPE)
        kw.setdefault("text", True)
        p = subprocess.Popen(self.command(i, args), start_new_session=True, **kw)
        self.procs.append(p)
        return p

    def run(self, i: int, args: Sequence[str], timeout: float = 20) -> subprocess.CompletedProcess:
        return subprocess.run(self.command(i, args), capture_output=True, text=True, timeout=timeout)

    def wait_tcp(self, i: int, host: str, port: int, timeout: float) -> float:
        """Wait until ``host:port`` accepts a TCP connection from inside host ``i``;
        returns the seconds it took. Raises ``TimeoutError``."""
        t0 = time.monotonic()
        code = ("import socket,sys,time\n"
                f"end=time.monotonic()+{timeout!r}\n"
                "while True:\n"
                f"  try: socket.create_connection(({host!r},{port}),0.5).close(); break\n"
                "  except OSError:\n"
                "    if time.monotonic()>end: sys.exit(1)\n"
                "    time.sleep(0.05)\n")
        import sys

        r = subprocess.run(self.command(i, [sys.executable, "-c", code]), capture_output=True, timeout=timeout + 10)
        if r.returncode != 0:
            raise TimeoutError(f"{host}:{port} not reachable from host {i} within {timeout} s")
        return time.monotonic() - t0

    # ------------------------------------------------------------------ clean-up

    def kill_all(self) -> None:
        """SIGKILL every process started here (whole process groups) and reap them."""
        for p in self.procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)
        for p in self.procs:
            with contextlib.suppress(Exception):
                p.communicate(timeout=5)

    def close(self) -> None:
        """Kill the processes, delete the namespaces (idempotent, never raises)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.kill_all()
        finally:
            for ns in reversed(self._created):
                with contextlib.suppress(Exception):
                    _delete_ns(ns)
            with contextlib.suppress(ValueError):
                _OPEN.remove(self)

    def exists(self) -> list[str]:
        """Which of this network's namespaces still exist (empty after :meth:`close`)."""
        r = _ip("netns", "list", check=False)
        have = {line.split()[0] for line in r.stdout.splitlines() if line.split()}
        return [ns for ns in (self.switch, *self.hosts) if ns in have]


def close_all() -> None:
    """Close every network still open in this process (session end, interpreter exit)."""
    for net in list(_OPEN):
        net.close()


atexit.register(close_all)

