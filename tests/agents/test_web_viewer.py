"""--serve-web: the web viewer page and the gRPC endpoint answer while a run is served,
Ctrl-C stops the server promptly, and headless Chromium (Debian's chromium driven by
Python's playwright package, no browser download) shows the run's plots: skipped, with the
reason, where either is absent."""

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.conftest import ROOT, SCENARIOS


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_web(tmp_path: Path, web: int, grpc: int, *extra: str) -> subprocess.Popen:
    """``rse simulate --serve-web`` in its own process group, its output merged."""
    exe = shutil.which("rse")
    cmd = [exe] if exe else [sys.executable, "-m", "agents.cli"]
    cmd += ["simulate", *extra, "--out", str(tmp_path / "run"), "--no-progress",
            "--serve-web", "--web-port", str(web), "--grpc-port", str(grpc)]
    env = dict(os.environ, COLUMNS="200")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, env=env,
                            start_new_session=True)


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


def page(port: int, timeout: float = 30.0) -> tuple[int, str]:
    """The viewer's page: its status and text. A server that already accepts connections may
    close the first ones unanswered while it starts on a loaded machine: asked again then."""
    end = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
                return r.status, r.read().decode("utf-8", "replace")
        except (ConnectionError, urllib.error.URLError):  # RemoteDisconnected is a ConnectionError
            if time.monotonic() > end:
                raise
            time.sleep(0.5)


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
    proc = serve_web(tmp_path, web, grpc, str(SCENARIOS / "mitra_cells.toml"))
    out = Lines(proc.stdout)
    try:
        # the run is over and the viewer still serves it: the event itself, not a file size
        assert out.wait_for("still serving", 120), out.text
        assert answers(web) and answers(grpc)
        status, body = page(web)
        assert status == 200 and "rerun" in body.lower()
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
    out = Lines(proc.stdout)
    try:
        assert wait_for(lambda: answers(web) and answers(grpc), 120), "viewer ports never opened"
        status, text = page(web)
        assert status == 200 and "rerun" in text.lower()
        # the run is over and the monitor still serves it: the line it prints then
        assert out.wait_for("still serving", 240), out.text
        assert (tmp_path / "run" / "summary.json").exists()
        assert proc.poll() is None
        assert answers(web) and answers(grpc)
        assert (tmp_path / "run" / "recording.rrd").stat().st_size > 10_000
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
        assert time.monotonic() - t0 < 3.0  # the feature: stopped within 2 s of Ctrl-C (+ 1 s margin)
        out.wait_for("\0", 5)  # the whole output (the reader thread ends with the stream)
        assert rc == 0, out.text
        assert f"http://127.0.0.1:{web}/?url=" in out.text.replace("\n", "")
        assert "Traceback" not in out.text
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)


def _chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")


def _plot_pixels(png: bytes) -> tuple[int, float]:
    """The number of distinct colours of a screenshot, and the share of strongly coloured
    pixels (max - min channel > 80) below the viewer's top bar and panel titles: the
    plots' lines and the map's agents are coloured, the welcome page, an empty layout and
    the loading screen are grey but for a button or two."""
    import io

    from PIL import Image

    img = Image.open(io.BytesIO(png)).convert("RGB")
    colours = img.getcolors(maxcolors=1 << 24)
    w, h = img.size
    import numpy as np

    a = np.asarray(img.crop((0, 120, w, h)), dtype=np.int16)
    coloured = (a.max(axis=2) - a.min(axis=2)) > 80
    return len(colours) if colours else 1 << 24, float(coloured.mean())


@pytest.mark.multiprocess
@pytest.mark.slow
@pytest.mark.needs("playwright", "driving Debian's chromium (pip install '.[browser]')")
@pytest.mark.needs("PIL", "reading the screenshot")
def test_the_web_viewer_draws_the_run_in_chromium(tmp_path):
    """Headless Chromium opens the viewer's URL as printed and the viewer draws the run:
    the screenshot is not one flat colour, and its plots are there (coloured pixels:
    2.0 to 2.2% of the area measured, against 0% for the blank page, the welcome page and
    the empty layout before the data arrive, 0.5% with only the legends and the map drawn). Waits for the drawing itself
    (a screenshot every 2 s), not for a time budget: ``chromium --headless --screenshot
    --virtual-time-budget`` gave a blank page (the WASM viewer had not drawn yet)."""
    chromium = _chromium()
    from playwright.sync_api import sync_playwright

    web, grpc = free_port(), free_port()
    proc = serve_web(tmp_path, web, grpc, str(SCENARIOS / "lee_kim_shim.toml"), "--set", "run.duration=4",
                     "--set", "expect=[]", "--set", "output.window=[0, 4]")
    out = Lines(proc.stdout)
    try:
        assert out.wait_for("still serving", 120), out.text
        m = re.search(r"still serving the recording at (\S+)", out.text)
        assert m and m.group(1).startswith(f"http://127.0.0.1:{web}/?url="), out.text
        url = m.group(1)  # as printed
        shots: list[tuple[float, int, float]] = []
        with sync_playwright() as pw:
            # WebGL through SwiftShader: a headless machine has no GPU
            browser = pw.chromium.launch(executable_path=chromium, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-quic",
                "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"])
            try:
                page = browser.new_page(viewport={"width": 1600, "height": 900})
                t0 = time.monotonic()
                page.goto(url, timeout=120_000)
                png = b""
                while time.monotonic() - t0 < 300:  # only a hang reaches it (measured: 40 to 150 s under load)
                    png = page.screenshot()
                    n_colours, coloured = _plot_pixels(png)
                    shots.append((round(time.monotonic() - t0, 1), n_colours, round(coloured, 5)))
                    if coloured >= 0.01:
                        break
                    time.sleep(2.0)
            finally:
                browser.close()
        (tmp_path / "viewer.png").write_bytes(png)
        print(f"\nviewer screenshots (s, colours, coloured share): {shots[-5:]}")
        n_colours, coloured = _plot_pixels(png)
        assert n_colours > 1, "the page is one flat colour"
        assert coloured >= 0.01, f"the viewer drew no plots: {shots[-5:]} (last screenshot {tmp_path / 'viewer.png'})"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0, out.text
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
