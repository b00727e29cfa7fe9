"""The README's three Python examples, run as written (the commands of its Python section, in a
folder holding the files they name: maps in textures/, a real DEM as dem.tif, a map as rock.png,
and a real server at the address the farm job names)."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from conftest import ROOT
from test_bake import rng_map, write_png
from test_terrain import utm_tif  # noqa: F401 (fixture)

rasterio = pytest.importorskip("rasterio")


def readme_commands():
    text = (ROOT / "README.md").read_text()
    section = text.split("### Python", 1)[1].split("\n## ", 1)[0]
    return [shlex.split(line) for line in section.splitlines()
            if line.startswith("python python/examples/")]


def test_the_readme_names_three_examples():
    names = [c[1].rsplit("/", 1)[1] for c in readme_commands()]
    assert names == ["batch_bake.py", "dem_svf_plot.py", "farm_job.py"]


def test_the_readme_examples_run_as_written(tmp_path, utm_tif, make_server):  # noqa: F811
    s = make_server()
    (tmp_path / "textures").mkdir()
    for i, shape in enumerate([(64, 64), (48, 80)]):
        write_png(tmp_path / "textures" / f"m{i}.png", rng_map(*shape, seed=i, dtype=np.uint16))
    shutil.copy(utm_tif, tmp_path / "dem.tif")
    write_png(tmp_path / "rock.png", rng_map(32, 32, seed=9, dtype=np.uint8))
    for cmd in readme_commands():
        argv = [sys.executable, str(ROOT / cmd[1])] + [
            s.url if a == "http://127.0.0.1:8080" else a for a in cmd[2:]]
        p = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=900,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
        assert p.returncode == 0, (cmd, p.stdout, p.stderr)
    # The batch: the CLI's files for each map, ktx2 included.
    for i in range(2):
        report = json.loads((tmp_path / "baked" / f"m{i}" / "bake.json").read_text())
        assert report["params"]["method"] == "exact"
        assert (tmp_path / "baked" / f"m{i}" / "horizon.ktx2").exists()
    # The plot: a real PNG of the sky-view factor.
    with Image.open(tmp_path / "svf.png") as im:
        assert im.size[0] > 100 and im.size[1] > 100
    # The farm job: the KTX2 the service encoded, and the layers.
    ktx = (tmp_path / "out" / "horizon_ktx2.ktx2").read_bytes()
    assert ktx[:12] == b"\xabKTX 20\xbb\r\n\x1a\n"
    assert (tmp_path / "out" / "horizon_0.png").exists()
