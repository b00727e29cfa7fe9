#!/usr/bin/env python3
"""Issue 41 item 2: an 8192² DEM's sky-view factor by `sweep` at unlimited radius stays under
1.5 GB of peak resident memory, with no spill file, on a map without holes and on a real DEM
with them.

    python3 scripts/memory_check.py --bin target/debug/horizon-bake [--size 8192] [--limit-gb 1.5]

Each bake is `horizon-bake bake DEM --outputs svf --format geotiff` with the DEM defaults
(`sweep`, `radius=unlimited`, edge none, curvature on, 32 bins), run as a child of this script;
its peak resident memory is the child's own (`wait4`'s ru_maxrss, the kernel's VmHWM). The
maps:
- `fbm`: a synthetic terrain of a few octaves (UTM 32N, 20 m cells), no holes;
- `elev`: R terra's `elev.tif` (SRTM-derived, shipped in the Debian package r-cran-terra)
  reprojected to UTM 32N on a --size² grid, which leaves the nodata collar every warped DEM
  has (about two thirds of the grid).

No spill: every bake runs with TMPDIR on a path where no directory can be made (under /proc),
so a bake that spilled its far-field table would fail. The check proves that this catches a
spill: a `svf_model=tilted` bake of the half-size map (its horizons come through the
far-field table, 2 GiB at 4096², spilled above 512 MiB) must fail there naming the temporary
file. Each output is read back with GDAL (rasterio): the sky-view factor is in [0, 1] and
its nodata mask is the DEM's holes.

Exit 1 on any failed check. Times are one run on the machine at hand.
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import rasterio
from rasterio.transform import from_origin
from rasterio.warp import Resampling, calculate_default_transform, reproject

from holes_bench import elev_tif  # $HB_ELEV_TIF, or terra's elev.tif from its Debian package

NO_TMP = "/proc/horizon-bake-no-spill"


def fbm_dem(path, n):
    """A terrain of six octaves of products of sines, heights 0..~1500 m, row by row."""
    x = np.arange(n, dtype=np.float32)
    profile = dict(driver="GTiff", width=n, height=n, count=1, dtype="float32",
                   crs="EPSG:32632", transform=from_origin(500000, 5200000, 20, 20),
                   tiled=True, compress="deflate")
    with rasterio.open(path, "w", **profile) as d:
        step = 256
        for y0 in range(0, n, step):
            y = np.arange(y0, min(y0 + step, n), dtype=np.float32)[:, None]
            v = np.zeros((len(y), n), np.float32)
            f, a = 0.002, 120.0
            for _ in range(6):
                v += a * np.sin(x * f + 0.3 * np.sin(y * f * 1.7)) * np.cos(y * f * 1.3 + 0.7)
                f *= 2.1
                a *= 0.45
            d.write(v * 4 + 800, 1, window=((y0, y0 + len(y)), (0, n)))


def warped_elev(src_path, path, n):
    with rasterio.open(src_path) as src:
        t, w, h = calculate_default_transform(src.crs, "EPSG:32632", src.width, src.height,
                                              *src.bounds)
        cell = max(w * t.a, h * -t.e) / n
        tr = from_origin(t.c, t.f, cell, cell)
        dst = np.full((n, n), -32768, np.int16)
        reproject(rasterio.band(src, 1), dst, dst_transform=tr, dst_crs="EPSG:32632",
                  resampling=Resampling.bilinear, dst_nodata=-32768)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="int16",
                       crs="EPSG:32632", transform=tr, nodata=-32768, tiled=True,
                       compress="deflate") as d:
        d.write(dst, 1)
    return float((dst == -32768).mean())


def bake(binary, dem, out, extra=()):
    """Runs one bake as a child; returns (exit code, stderr, wall s, CPU s, peak RSS bytes)."""
    env = dict(os.environ, TMPDIR=NO_TMP)
    cmd = [binary, "bake", dem, "-o", out, "--outputs", "svf", "--format", "geotiff", *extra]
    t0 = time.monotonic()
    with tempfile.TemporaryFile() as err:
        p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        msg = err.read().decode(errors="replace")
    return (p.returncode, msg, time.monotonic() - t0, ru.ru_utime + ru.ru_stime,
            ru.ru_maxrss * 1024)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", required=True)
    ap.add_argument("--size", type=int, default=8192)
    ap.add_argument("--limit-gb", type=float, default=1.5)
    a = ap.parse_args()
    limit = a.limit_gb * 1e9
    failed = []
    with tempfile.TemporaryDirectory() as work:
        dems = {"fbm": os.path.join(work, "fbm.tif"), "elev": os.path.join(work, "elev.tif")}
        fbm_dem(dems["fbm"], a.size)
        holes = warped_elev(elev_tif(work), dems["elev"], a.size)
        print(f"map {a.size}², sweep, radius=unlimited, outputs=svf, 32 bins; "
              f"elev: {holes:.0%} nodata; limit {a.limit_gb} GB, TMPDIR={NO_TMP}")
        print(f"{'dem':<6} {'wall s':>8} {'CPU s':>8} {'Mtexel/s':>9} {'peak MB':>9}  result")
        for name, dem in dems.items():
            out = os.path.join(work, "out_" + name)
            rc, msg, wall, cpu, peak = bake(a.bin, dem, out)
            ok = rc == 0 and peak < limit
            note = "ok" if ok else f"FAILED (exit {rc}) {msg.strip()[-300:]}"
            if rc == 0:
                with rasterio.open(os.path.join(out, "svf.tif")) as s, rasterio.open(dem) as d:
                    v = s.read(1, masked=True)
                    src_holes = d.read_masks(1) == 0
                    if not np.array_equal(np.ma.getmaskarray(v), src_holes):
                        ok, note = False, "FAILED: the nodata mask is not the DEM's holes"
                    elif not (v.min() >= 0.0 and v.max() <= 1.0 and v.count() > 0):
                        ok, note = False, f"FAILED: svf outside [0, 1]: {v.min()}..{v.max()}"
            if peak >= limit:
                note = f"FAILED: peak {peak / 1e6:.0f} MB is above {limit / 1e6:.0f} MB"
            if not ok:
                failed.append(name)
            mt = a.size * a.size / wall / 1e6
            print(f"{name:<6} {wall:8.1f} {cpu:8.1f} {mt:9.2f} {peak / 1e6:9.0f}  {note}")
        # The control: a bake that must spill fails under this TMPDIR.
        half = os.path.join(work, "half.tif")
        fbm_dem(half, a.size // 2)
        # Bins enough for a table above the 512 MiB kept in memory (32 at 4096²).
        per_bin = (a.size // 2) ** 2 * 4
        bins = max(32, -(-((1 << 29) // per_bin + 1) // 16) * 16)
        rc, msg, wall, _, _ = bake(a.bin, half, os.path.join(work, "out_control"),
                                   ["--svf-model", "tilted", "--bins", str(bins)])
        caught = rc != 0 and "temporary file" in msg
        print(f"control: {a.size // 2}² svf_model=tilted at {bins} bins (table spilled) "
              f"{'failed as it must' if caught else 'FAILED: it did not fail on its spill'}"
              f" ({wall:.1f} s)")
        if not caught:
            failed.append("control")
            print(msg.strip()[-300:])
    if failed:
        print("memory check failed:", ", ".join(failed))
        sys.exit(1)


if __name__ == "__main__":
    main()
