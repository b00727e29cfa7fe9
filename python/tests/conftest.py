"""Fixtures of the package's tests: the CLI the outputs are compared with, a real
``horizon-bake serve`` on 127.0.0.1, and a real DEM nobody here made.

``HB_CLI`` names the CLI binary (default: ../target/debug/horizon-bake, which ``cargo test``
builds); ``HB_ELEV_TIF`` R terra's elev.tif (.ci/run unpacks it from Debian's r-cran-terra).
Under ``CI=true`` a missing one fails the tests that need it; elsewhere they skip.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import time
import urllib.request

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
CI = os.environ.get("CI") == "true"


def _need(what: str, why: str) -> None:
    if CI:
        pytest.fail(f"{what} is missing under CI=true: {why}")
    pytest.skip(f"{what} is missing: {why}")


@pytest.fixture(scope="session")
def cli() -> str:
    path = os.environ.get("HB_CLI", str(ROOT / "target" / "debug" / "horizon-bake"))
    if not os.path.exists(path):
        _need("the horizon-bake CLI", f"build it (cargo build) or set HB_CLI; looked at {path}")
    return path


@pytest.fixture(scope="session")
def elev_tif() -> str:
    path = os.environ.get("HB_ELEV_TIF", "")
    if not path or not os.path.exists(path):
        _need("HB_ELEV_TIF", "R terra's elev.tif from Debian's r-cran-terra (see .ci/run)")
    return path


def run_cli(cli: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([cli, *args], capture_output=True, text=True, timeout=600)


class Server:
    def __init__(self, cli: str, tmp: pathlib.Path, *extra: str):
        addr_file = tmp / "addr"
        self.log = open(tmp / "server.log", "w")
        self.proc = subprocess.Popen(
            [cli, "serve", "--addr", "127.0.0.1:0", "--addr-file", str(addr_file),
             "--data-dir", str(tmp / "data"), *extra],
            stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        while not (addr_file.exists() and addr_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the server did not start: {(tmp / 'server.log').read_text()}")
            time.sleep(0.05)
        self.url = "http://" + addr_file.read_text().strip()
        while True:
            try:
                urllib.request.urlopen(self.url + "/readyz", timeout=2).close()
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


@pytest.fixture(scope="module")
def server(cli, tmp_path_factory):
    s = Server(cli, tmp_path_factory.mktemp("serve"))
    yield s
    s.stop()


@pytest.fixture()
def make_server(cli, tmp_path):
    made = []

    def make(*extra: str) -> Server:
        s = Server(cli, tmp_path / f"s{len(made)}", *extra)
        made.append(s)
        return s

    (tmp_path / "s0").mkdir()
    for i in range(1, 4):
        (tmp_path / f"s{i}").mkdir()
    yield make
    for s in made:
        s.stop()
