"""--serve-web: the web viewer page and the gRPC endpoint answer while a run is served,
headless Chromium loads the page (where Debian's chromium is installed), and Ctrl-C stops
the server promptly."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import pytest

from tests.conftest import ROOT, SCENARIOS


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.2)
    return False


def answers(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


class Lines:
    """The lines a process prints, read on a thread; :meth:`wait_for` waits for one."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        self._cv = threading.Condition()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cv:
                self.lines.append(line)
                self._cv.notify_all()
        with self._cv:
            self.lines.append(None)
            self._cv.notify_all()

    def wait_for(self, text: str, timeout: float) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: any(ln is None or text in ln for ln in self.lines), timeout) and any(
                ln is not None and text in ln for ln in self.lines)

    @property
    def text(self) -> str:
        with self._cv:
            return "".join(ln for ln in self.lines if ln is not None)


@pytest.mark.multiprocess
def test_serve_web_serves_the_viewer_and_stops_on_ctrl_c(tmp_path):
    web, grpc = free_port(), free_port()
    exe = shutil.which("rse")
    cmd = [exe] if exe else [sys.executable, "-m", "agents.cli"]
    cmd += ["simulate", str(SCENARIOS / "mitra_cells.toml"), "--out", str(tmp_path / "run"), "--no-progress",
            "--serve-web", "--web-port", str(web), "--grpc-port", str(grpc)]
    env = dict(os.environ, COLUMNS="200")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=env,
                            start_new_session=True)
    out = Lines(proc.stdout)
    try:
        # the run is over and the viewer still serves it: the event itself, not a file size
        assert out.wait_for("still serving", 120), out.text
        assert answers(web) and answers(grpc)
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as r:
            body = r.read().decode("utf-8", "replace")
            assert r.status == 200
        assert "rerun" in body.lower()
        url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy"
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        if chromium:
            shot = tmp_path / "viewer.png"
            subprocess.run([chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                            "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                            "--disable-sync", f"--user-data-dir={tmp_path / 'chromium'}", "--window-size=1600,900",
                            "--virtual-time-budget=10000", f"--screenshot={shot}", url],
                           capture_output=True, timeout=90)
            assert shot.exists() and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["complete"] is True
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
        assert rc == 0, out.text
        assert time.monotonic() - t0 < 3.0
        assert f"http://127.0.0.1:{web}/?url=" in out.text.replace("\n", "")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)


@pytest.mark.multiprocess
def test_rse_run_serve_web_streams_from_the_monitor_and_stops_on_ctrl_c(tmp_path):
    """rse run --serve-web: the monitor process serves the viewer and the recording (the run
    id is the recording id), keeps serving after the run, and Ctrl-C stops every process."""
    web, grpc = free_port(), free_port()
    exe = shutil.which("rse")
    cmd = [exe] if exe else [sys.executable, "-m", "agents.cli"]
    cmd += ["run", str(SCENARIOS / "mitra_cells.toml"), "--out", str(tmp_path / "run"), "--no-progress",
            "--serve-web", "--web-port", str(web), "--grpc-port", str(grpc)]
    env = dict(os.environ, COLUMNS="200")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=env,
                            start_new_session=True)
    try:
        assert wait_for(lambda: answers(web) and answers(grpc), 50), "viewer ports never opened"
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as r:
            assert r.status == 200 and "rerun" in r.read().decode("utf-8", "replace").lower()
        summary = tmp_path / "run" / "summary.json"
        assert wait_for(summary.exists, 50), "the run did not finish"
        time.sleep(1.0)
        assert proc.poll() is None  # still serving after the run
        assert answers(web) and answers(grpc)
        assert (tmp_path / "run" / "recording.rrd").stat().st_size > 10_000
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
        assert time.monotonic() - t0 < 3.0
        out = proc.stdout.read()
        assert rc == 0, out
        assert f"http://127.0.0.1:{web}/?url=" in out.replace("\n", "")
        assert "still serving" in out and "Traceback" not in out
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
