"""``serve --rerun-web PORT`` in a real browser: headless Chromium loads the page, the 3D map appears.

Chromium is Debian's ``chromium`` package, installed here when missing (as root); the test is skipped, saying
why, only when it cannot be installed. The browser is driven over the DevTools protocol on a pipe (stdlib only)
and may resolve no host but 127.0.0.1: the page must work with nothing but this machine.
"""

from __future__ import annotations

import base64
import fcntl
import io
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.viewer import OPTIMISED
from service.viewer_connect import reachable
from tests.conftest import free_port

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
SCENE = "synthetic:room?seed=0&frames=90&width=320&height=240"


def chromium() -> str:
    """The Chromium executable, installed from Debian's packages when missing."""
    found = shutil.which("chromium")
    if found is None and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", "-q", "chromium"]
        if subprocess.run(install, env=env, capture_output=True, timeout=900).returncode != 0:
            subprocess.run(["apt-get", "update", "-q"], env=env, capture_output=True, timeout=600)
            subprocess.run(install, env=env, capture_output=True, timeout=900)
        found = shutil.which("chromium")
    if found is None:
        pytest.skip("Debian's chromium is not installed and cannot be installed here (needs root and apt-get)")
    return found


def _above_4(fd: int) -> int:
    high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return high


class Browser:
    """Headless Chromium driven over ``--remote-debugging-pipe`` (fd 3: commands, fd 4: replies, NUL-ended)."""

    def __init__(self, exe: str, profile: Path, size: tuple[int, int] = (1280, 800)):
        cmd_r, self._cmd_w = os.pipe()
        self._out_r, out_w = os.pipe()
        cmd_r, out_w = (_above_4(fd) for fd in (cmd_r, out_w))  # so `3<&R 4>&W` clobbers neither (bash)
        flags = [
            "--headless=new",
            "--no-sandbox",
            "--remote-debugging-pipe",
            "--enable-unsafe-swiftshader",
            "--use-angle=swiftshader",
            f"--window-size={size[0]},{size[1]}",
            "--no-first-run",
            f"--user-data-dir={profile}",
            "--disable-component-update",
            "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
            "about:blank",
        ]
        shell = f"exec {shlex.join([exe, *flags])} 3<&{cmd_r} 4>&{out_w}"
        self.process = subprocess.Popen(
            ["bash", "-c", shell], pass_fds=(cmd_r, out_w), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        os.close(cmd_r)
        os.close(out_w)
        self._buffer, self._id, self.session = b"", 0, None

    def send(self, method: str, params: dict | None = None) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if self.session is not None and not method.startswith(("Target.", "Browser.")):
            message["sessionId"] = self.session
        os.write(self._cmd_w, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self._buffer:
                chunk = os.read(self._out_r, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its pipe")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def open(self, url: str) -> None:
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.send("Page.enable")
        self.send("Page.navigate", {"url": url})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])

    def close(self) -> None:
        try:
            self.send("Browser.close")
            self.process.wait(timeout=10)
        except (RuntimeError, OSError, subprocess.TimeoutExpired):
            self.process.kill()
        os.close(self._cmd_w)
        os.close(self._out_r)


def trajectory_pixels(png: bytes) -> tuple[int, float]:
    """Pixels of the optimised trajectory's colour, and the grey-level spread of the whole screenshot."""
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int((np.abs(rgb - OPTIMISED).sum(axis=-1) < 40).sum()), float(rgb.std())


def objslam(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "service", *args], cwd=ROOT, **kw)


def wait_for_url(serve: subprocess.Popen, log: Path, timeout: float = 60.0) -> str:
    """The web viewer's page, from the line ``viewer: http://...`` that serve logs."""
    deadline, text = time.monotonic() + timeout, ""
    while time.monotonic() < deadline and serve.poll() is None:
        text = log.read_text(errors="replace")
        for line in text.splitlines():
            if "viewer: http://127.0.0.1:" in line:
                return line.split("viewer: ", 1)[1].split(",")[0].strip()
        time.sleep(0.2)
    raise AssertionError(f"serve logged no web viewer url: {text[-2000:]}")


def test_serve_shows_the_live_map_in_headless_chromium(tmp_path):
    exe = chromium()
    port, web = free_port(), free_port()
    log = tmp_path / "serve.log"
    with log.open("wb") as err:
        serve = objslam("serve", "--listen", f"tcp/127.0.0.1:{port}", "--rerun-web", str(web), stderr=err)
    browser = None
    try:
        url = wait_for_url(serve, log)
        assert url.startswith(f"http://127.0.0.1:{web}/")
        replay = ["replay", SCENE, "--connect", f"tcp/127.0.0.1:{port}", "--mode", "client", "--max-rate"]
        assert objslam(*replay).wait(timeout=120) == 0
        browser = Browser(exe, tmp_path / "chromium")
        browser.open(url)
        deadline, found, spread, png = time.monotonic() + 150.0, 0, 0.0, b""
        while time.monotonic() < deadline and not (found >= 30 and spread > 20.0):
            time.sleep(2.0)
            png = browser.screenshot()
            found, spread = trajectory_pixels(png)
        (tmp_path / "viewer.png").write_bytes(png)
        assert spread > 20.0, f"a blank page (pixel spread {spread:.1f}): {tmp_path / 'viewer.png'}"
        assert found >= 30, f"no trajectory in the 3D view ({found} pixels of its colour): {tmp_path / 'viewer.png'}"
    finally:
        if browser is not None:
            browser.close()
        serve.send_signal(signal.SIGINT)
        code = serve.wait(timeout=60)
    assert code == 0
    assert not reachable("127.0.0.1", web), "the web viewer outlived serve"
