"""Docker for the container tests: a daemon that answers, a base image, the role images,
and compose runs that are always taken down.

::

    why = unavailable()              # None, or why no Docker daemon answers (for pytest.skip)
    base_image()                     # python:3.11-slim: present, pulled, or the stand-in below
    build_images()                   # the Dockerfile's targets, tagged as rse compose names them
    with ComposeRun(file) as run:    # docker-compose -p UNIQUE -f FILE ...
        run.up()                     # detached; run.wait_exit("plant"), run.restarts("agent-3")
    # on exit: docker-compose down --volumes --timeout 5, and the project's containers gone

**The daemon.** :func:`unavailable` asks ``docker info``; when nothing answers and this
process is root with ``dockerd`` installed (``apt-get install docker.io docker-compose``),
it starts ``dockerd`` in the background (its log in ``/var/log/rse-test-dockerd.log``) and
waits up to 30 s. That daemon is left running for the next tests (it is a system service,
not a test fixture).

**The base image.** The Dockerfile starts from ``python:3.11-slim``. Where that image is
neither present nor pullable (Docker Hub unreachable, as on the machine these tests were
first run on), :func:`build_standin_base` makes an image of that name from Debian's own
packages: ``debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,
ca-certificates bookworm`` (Debian 12 ships Python 3.11, as the official image does),
without ``EXTERNALLY-MANAGED`` (pip may install system-wide, as in the official image),
``python`` and ``pip`` linked into ``/usr/local/bin``, apt's caches, documentation and
locales removed, and the **host's CA bundle** copied in: where registries are reached
through a TLS-inspecting proxy, a bare Debian root does not trust it and pip in
``docker build`` fails. Then ``tar | docker import`` with the official image's ``ENV`` and
``CMD``. This fallback is a test helper only: the Dockerfile names the official image.

**pip in docker build** reaches the index as the host does: the ``PIP_INDEX_URL``,
``PIP_EXTRA_INDEX_URL`` and ``PIP_TRUSTED_HOST`` of this environment (network URLs only; a
``file://`` index on the host means nothing in a build) and the proxy variables are
passed as build arguments; nothing about this host is written into the Dockerfile.

**Compose.** Debian's ``docker-compose`` (1.29) or the ``docker compose`` plugin,
whichever is installed (:func:`compose_tool`). :class:`ComposeRun` uses a unique project
name, so parallel or earlier runs never collide, and takes everything down on exit
(containers, network, the ``runs`` volume), also when the test fails.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tests.conftest import ROOT

BASE = "python:3.11-slim"
#: the Dockerfile's targets and the tags rse compose gives their images (agents/compose.py)
TARGETS = {"agent": "resilient-state-estimation-agent:latest",
           "monitor": "resilient-state-estimation-monitor:latest",
           "full": "resilient-state-estimation:latest"}
DOCKERD_LOG = Path("/var/log/rse-test-dockerd.log")
_PIP_VARS = ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST")
_PROXY_VARS = ("HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY", "http_proxy", "https_proxy", "no_proxy")


def docker(*args: str, timeout: float = 120, check: bool = True, **kw: Any) -> subprocess.CompletedProcess:
    """``docker ARGS`` (text output captured); a non-zero status raises with its stderr."""
    r = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout, **kw)
    if check and r.returncode != 0:
        raise RuntimeError(f"docker {' '.join(args[:3])}...: {(r.stderr or r.stdout).strip()[-2000:]}")
    return r


def _answers() -> bool:
    try:
        return docker("info", "--format", "{{.ServerVersion}}", timeout=20, check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def unavailable() -> str | None:
    """Why no Docker daemon can be used here (``None``: one answers, maybe started now)."""
    if shutil.which("docker") is None:
        return "the docker command is not installed (apt-get install docker.io docker-compose)"
    if compose_tool() is None:
        return "neither docker-compose nor the docker compose plugin is installed (apt-get install docker-compose)"
    if _answers():
        return None
    dockerd = shutil.which("dockerd")
    if dockerd is None or not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "no Docker daemon answers (docker info failed) and this process cannot start dockerd (not root, or not installed)"
    with open(DOCKERD_LOG, "ab") as log:
        subprocess.Popen([dockerd], stdout=log, stderr=log, stdin=subprocess.DEVNULL, start_new_session=True)
    end = time.monotonic() + 30
    while time.monotonic() < end:
        if _answers():
            return None
        time.sleep(0.5)
    return f"dockerd was started but did not answer within 30 s (see {DOCKERD_LOG})"


def compose_tool() -> list[str] | None:
    """The compose command installed here: ``docker-compose`` or ``docker compose``, or None."""
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return None


def image_exists(tag: str) -> bool:
    return docker("image", "inspect", tag, check=False, timeout=30).returncode == 0


def image_size(tag: str) -> int:
    """The image's size in bytes (all its layers, base included)."""
    return int(docker("image", "inspect", "--format", "{{.Size}}", tag).stdout.strip())


def base_image(tag: str = BASE) -> str:
    """Make sure ``tag`` exists: present, pulled (60 s at most), or the Debian stand-in.
    Returns how: ``"present"``, ``"pulled"`` or ``"stand-in"``."""
    if image_exists(tag):
        return "present"
    try:
        if docker("pull", tag, check=False, timeout=60).returncode == 0:
            return "pulled"
    except subprocess.TimeoutExpired:
        pass
    build_standin_base(tag)
    return "stand-in"


def build_standin_base(tag: str = BASE, suite: str = "bookworm",
                       mirror: str = "http://deb.debian.org/debian") -> None:
    """Import a Debian ``suite`` root with Python 3.11 and pip as image ``tag`` (root, debootstrap)."""
    if shutil.which("debootstrap") is None:
        raise RuntimeError(f"{tag} is neither present nor pullable, and debootstrap is not installed "
                           "to build a stand-in (apt-get install debootstrap)")
    with tempfile.TemporaryDirectory(prefix="rse-base-") as tmp:
        root = Path(tmp) / "rootfs"
        r = subprocess.run(["debootstrap", "--variant=minbase",
                            "--include=python3,python3-venv,python3-pip,ca-certificates", suite, str(root), mirror],
                           capture_output=True, text=True, timeout=900)
        if r.returncode != 0:
            raise RuntimeError(f"debootstrap failed: {(r.stderr or r.stdout).strip()[-2000:]}")
        for marker in root.glob("usr/lib/python3*/EXTERNALLY-MANAGED"):
            marker.unlink()
        for name, target in (("python", "/usr/bin/python3"), ("pip", "/usr/bin/pip3")):
            (root / "usr/local/bin" / name).symlink_to(target)
        for junk in ("var/cache/apt", "var/lib/apt/lists", "usr/share/doc", "usr/share/man", "usr/share/locale",
                     "usr/share/info"):
            shutil.rmtree(root / junk, ignore_errors=True)
            (root / junk).mkdir(parents=True, exist_ok=True)
        host_ca = Path("/etc/ssl/certs/ca-certificates.crt")
        if host_ca.is_file():  # the proxy's CA, if any, is in the host's bundle
            shutil.copyfile(host_ca, root / "etc/ssl/certs/ca-certificates.crt")
        tar = subprocess.Popen(["tar", "-C", str(root), "--numeric-owner", "-c", "."], stdout=subprocess.PIPE)
        try:
            docker("import", "--change", "ENV LANG=C.UTF-8", "--change", 'CMD ["python3"]',
                   "--message", f"stand-in for {tag}: debootstrap {suite} (tests/deploy/docker.py)",
                   "-", tag, stdin=tar.stdout, timeout=600)
        finally:
            tar.stdout.close()
            tar.wait(timeout=60)


def build_args() -> list[str]:
    """``--build-arg`` options for pip's index and the proxy, from this environment."""
    out = []
    for var in _PIP_VARS:
        value = " ".join(u for u in os.environ.get(var, "").split() if not u.startswith("file:"))
        if value:
            out += ["--build-arg", f"{var}={value}"]
    for var in _PROXY_VARS:
        if os.environ.get(var):
            out += ["--build-arg", f"{var}={os.environ[var]}"]
    return out


def build_images(targets: Sequence[str] | None = None, *, timeout: float = 1800) -> dict[str, float]:
    """Build the Dockerfile's ``targets`` (default: all of :data:`TARGETS`) with their tags,
    layer cache on. Returns the wall time of each build in seconds."""
    base_image()
    times = {}
    for target in targets or TARGETS:
        t0 = time.monotonic()
        docker("build", "--target", target, "-t", TARGETS[target], *build_args(), str(ROOT),
               timeout=timeout)
        times[target] = time.monotonic() - t0
    return times


class ComposeRun:
    """One ``docker compose`` project of a compose file, taken down on exit.

    Parameters
    ----------
    file : Path
        The compose file (its directory is the project directory: relative mounts).
    """

    def __init__(self, file: Path) -> None:
        self.file = Path(file)
        self.project = f"rsetest{os.getpid()}{secrets.token_hex(3)}"
        tool = compose_tool()
        if tool is None:
            raise RuntimeError("no compose tool installed")
        self.cmd = [*tool, "-p", self.project, "-f", str(self.file)]

    def __enter__(self) -> "ComposeRun":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.down()

    def run(self, *args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
        r = subprocess.run([*self.cmd, *args], capture_output=True, text=True, timeout=timeout,
                           cwd=self.file.parent)
        if check and r.returncode != 0:
            raise RuntimeError(f"{' '.join(self.cmd[:2])} {' '.join(args)}: {(r.stderr or r.stdout).strip()[-3000:]}")
        return r

    def watch_health(self) -> None:
        """Start recording this project's ``health_status`` events (call before ``up``: the
        daemon keeps only its last events, a health check makes several). Read them with
        :meth:`healthy_at`."""
        self.health: dict[str, tuple[float, str]] = {}  # container id -> (first time, status)
        self.unhealthy: list[str] = []
        self._events = subprocess.Popen(
            ["docker", "events", "--filter", f"label=com.docker.compose.project={self.project}",
             "--filter", "event=health_status", "--format", "{{json .}}"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

        def read() -> None:
            for line in self._events.stdout:
                ev = json.loads(line)
                status = ev.get("status") or ev.get("Action", "")
                cid = ev.get("id") or ev.get("Actor", {}).get("ID")
                if status.endswith(": unhealthy"):
                    self.unhealthy.append(cid)
                elif status.endswith(": healthy") and cid not in self.health:
                    self.health[cid] = (ev["timeNano"] / 1e9, status)

        threading.Thread(target=read, daemon=True).start()

    def healthy_at(self, service: str) -> float | None:
        """POSIX time of ``service``'s first ``health_status: healthy`` event, or None."""
        cid = self.container(service)
        return next((t for c, (t, _) in self.health.items() if c.startswith(cid)), None)

    def up(self, timeout: float = 180) -> float:
        """``up -d`` (every service started; returns once the router is healthy and the rest
        started, as ``depends_on`` orders it). Returns the wall time of ``up`` itself."""
        t0 = time.monotonic()
        self.run("up", "-d", "--no-build", timeout=timeout)
        return time.monotonic() - t0

    def container(self, service: str) -> str:
        """The id of ``service``'s container."""
        return self.run("ps", "-q", service).stdout.strip()

    def inspect(self, service: str) -> dict:
        return json.loads(docker("inspect", self.container(service)).stdout)[0]

    def state(self, service: str) -> dict:
        """``State`` of ``service``'s container: Status, ExitCode, Health, ..."""
        return self.inspect(service)["State"]

    def wait(self, pred: Any, timeout: float, what: str, period: float = 0.5) -> float:
        """Poll ``pred()`` until true; returns the seconds it took or raises naming ``what``."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if pred():
                return time.monotonic() - t0
            time.sleep(period)
        raise AssertionError(f"{what}: not within {timeout} s\n{self.logs()}")

    def wait_exit(self, service: str, timeout: float) -> int:
        """Wait until ``service`` has exited; its exit code."""
        self.wait(lambda: self.state(service)["Status"] == "exited", timeout, f"{service} exits")
        return int(self.state(service)["ExitCode"])

    def logs(self, *services: str, tail: int = 40) -> str:
        return self.run("logs", "--no-color", "--tail", str(tail), *services, check=False, timeout=60).stdout

    def containers(self) -> list[str]:
        """Ids of every container of this project, running or not."""
        r = docker("ps", "-aq", "--filter", f"label=com.docker.compose.project={self.project}")
        return r.stdout.split()

    def copy_out(self, service: str, src: str, dest: Path) -> Path:
        """``docker cp`` from ``service``'s container (running or exited) to ``dest``."""
        docker("cp", f"{self.container(service)}:{src}", str(dest), timeout=120)
        return dest

    def down(self) -> None:
        """Containers, network and volumes of the project removed, whatever state they are in."""
        if getattr(self, "_events", None) is not None:
            self._events.kill()
            self._events.wait()
            self._events = None
        with contextlib.suppress(Exception):
            self.run("down", "--volumes", "--remove-orphans", "--timeout", "5", timeout=180, check=False)
        # whatever down left (it failed, or took too long on a loaded machine)
        label = f"label=com.docker.compose.project={self.project}"
        with contextlib.suppress(Exception):
            left = self.containers()
            if left:
                docker("rm", "-f", "-v", *left, check=False, timeout=300)
        for kind in ("network", "volume"):
            with contextlib.suppress(Exception):
                names = docker(kind, "ls", "-q", "--filter", label, timeout=60).stdout.split()
                if names:
                    docker(kind, "rm", *names, check=False, timeout=120)
