"""Shared helpers of the browser test and the screenshot script: start the real server binary,
launch Debian's chromium through Python playwright, talk HTTP, compare images.

Environment:
- HORIZON_BIN: the server binary (default target/debug/horizon-bake, what `cargo test` builds);
- HORIZON_UI_DIR: serve the page from this directory instead of the built-in copies (to work on
  the page without rebuilding);
- CHROMIUM: the browser (default /usr/bin/chromium). Under CI=true a missing browser is an error.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
TERRAIN = ROOT / "docs" / "corpus" / "jacksboro_128.png"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def _die_with_parent() -> None:
    """In the child: SIGTERM when the test process dies, even by SIGKILL (Linux prctl), so no
    server outlives a killed test run."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def server_binary() -> Path:
    p = Path(os.environ.get("HORIZON_BIN", "target/debug/horizon-bake"))
    return p if p.is_absolute() else ROOT / p


class Server:
    """One `horizon-bake serve` on 127.0.0.1 with a temporary data directory."""

    def __init__(self, api_key: str | None = None, extra: list[str] | None = None):
        self.api_key = api_key
        self.tmp = Path(tempfile.mkdtemp(prefix="hb-ui-"))
        addr_file = self.tmp / "addr"
        cmd = [
            str(server_binary()), "serve", "--addr", "127.0.0.1:0",
            "--addr-file", str(addr_file), "--data-dir", str(self.tmp / "data"),
        ]
        if api_key:
            cmd += ["--api-key", api_key]
        ui_dir = os.environ.get("HORIZON_UI_DIR")
        if ui_dir:
            cmd += ["--ui-dir", ui_dir]
        cmd += extra or []
        self.log_path = self.tmp / "server.log"
        self.log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=subprocess.STDOUT,
                                     preexec_fn=_die_with_parent)
        deadline = time.time() + 30
        while time.time() < deadline:
            if addr_file.exists() and addr_file.read_text().strip():
                break
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.log_path.read_text()}")
            time.sleep(0.05)
        else:
            self.close()
            raise RuntimeError("server did not write its address in 30 s")
        self.url = f"http://{addr_file.read_text().strip()}"

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def request(self, path: str, method: str = "GET", body: bytes | None = None,
                headers: dict | None = None, auth: bool = True):
        """(status, headers, body bytes) of one request; the API key is sent when `auth`."""
        h = dict(headers or {})
        if auth and self.api_key:
            h["Authorization"] = f"Bearer {self.api_key}"
        req = urllib.request.Request(self.url + path, data=body, method=method, headers=h)
        try:
            with urllib.request.urlopen(req, timeout=300) as r:
                return r.status, r.headers, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.headers, e.read()

    def json(self, path: str, **kw):
        status, _, body = self.request(path, **kw)
        return status, json.loads(body) if body else None

    def preview(self, bake_id: str, azimuth: float, elevation: float, hardness: float = 8,
                shading: str = "horizon", size: int | None = None) -> np.ndarray:
        """The server's CPU preview (RGB, uint8, rows from the top) at one light."""
        q = f"shading={shading}&azimuth={azimuth!r}&elevation={elevation!r}&hardness={hardness!r}"
        if size:
            q += f"&size={size}"
        status, headers, body = self.request(f"/v1/bakes/{bake_id}/preview?{q}")
        assert status == 200, (status, body[:300])
        return np.asarray(Image.open(io.BytesIO(body)).convert("RGB"))


@contextlib.contextmanager
def server(api_key: str | None = None, extra: list[str] | None = None):
    s = Server(api_key, extra)
    try:
        yield s
    finally:
        s.close()


def chromium_or_skip():
    """The browser path; skips (fails under CI=true) when it is not installed."""
    if Path(CHROMIUM).exists():
        return CHROMIUM
    msg = f"{CHROMIUM} is missing (apt-get install chromium)"
    if os.environ.get("CI") == "true":
        import pytest

        pytest.fail(msg)
    import pytest

    pytest.skip(msg)


def launch(playwright, executable: str):
    return playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS, headless=True)


def decode_rgba(shot: dict) -> np.ndarray:
    """A `window.__horizon.readCanvas()`/`render()` answer as an (H, W, 4) uint8 array."""
    raw = base64.b64decode(shot["rgba"])
    return np.frombuffer(raw, dtype=np.uint8).reshape(shot["height"], shot["width"], 4)


def compare(gpu_rgba: np.ndarray, cpu_rgb: np.ndarray, tolerance: int = 2):
    """(fraction of pixels whose RGB all lie within `tolerance` levels, max abs difference)."""
    assert gpu_rgba.shape[:2] == cpu_rgb.shape[:2], (gpu_rgba.shape, cpu_rgb.shape)
    d = np.abs(gpu_rgba[..., :3].astype(np.int16) - cpu_rgb.astype(np.int16))
    per_pixel = d.max(axis=2)
    return float((per_pixel <= tolerance).mean()), int(per_pixel.max())
