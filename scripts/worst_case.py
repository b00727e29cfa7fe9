#!/usr/bin/env python3
"""`method=sweep` on the maps no terrain has, against Whitebox `horizon_angle` (SPEC §3.2a).

SPEC §3.2a lets `sweep` state a worst case on white noise and on fields of single-texel spikes,
on one condition: its mean error there stays below the most accurate GIS peer's, Whitebox
Workflows `horizon_angle`, on the same map. This script measures both against our `exact`
(the line-of-sight horizon of SPEC §3.2, unlimited radius, edge=none) and fails (exit 1) if the
sweep's mean |Δα| is not below Whitebox's on every map. CI runs it at a small size; the table in
docs/peers.md ("`method=sweep` on the maps no terrain has") comes from a run at 512².

Maps (the recipes of tests/kernels/sweep.rs, drawn with numpy's default_rng(seed)):
- **white noise**: heights uniform in 0..12 texels (slopes up to 12);
- **spikes**: 1 % of texels are spikes 4–24 texels tall on a flat plane.
horizon-bake reads a 16-bit PNG (value / 65535 × height_scale texels); Whitebox reads a float32
GeoTIFF of exactly those heights, cell size 1, north up, so one height unit is one texel for both.

Azimuths: all 32 bins, φ = k · 11.25° counter-clockwise from east (ours, `--outputs angles`);
Whitebox's azimuth is clockwise from north, (90° − φ) mod 360. Angles below 0 are clamped to 0
for every tool (the horizon maps' convention); the `--margin` texels along the border are left
out, where the tools' edge conventions differ rather than their accuracy.

Needs numpy, pillow, rasterio and whitebox-workflows (pip). Usage:
    python3 scripts/worst_case.py --bin target/debug/horizon-bake --size 128
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

BINS = 32


def make_maps(size, seed):
    import numpy as np

    rng = np.random.default_rng(seed)
    noise = rng.random((size, size)) * 12.0
    spikes = np.where(rng.random((size, size)) < 0.01, 4.0 + 20.0 * rng.random((size, size)), 0.0)
    # (name, heights in texels, height_scale): the PNG stores heights / scale.
    return [("white noise", noise, 12.0), ("spikes", spikes, 24.0)]


def write_inputs(work, name, heights, scale):
    """The 16-bit PNG ours reads and the float32 GeoTIFF of the same quantised heights."""
    import numpy as np
    import rasterio
    from PIL import Image
    from rasterio.transform import from_origin

    slug = name.replace(" ", "_")
    v = np.round(np.clip(heights / scale, 0.0, 1.0) * 65535.0).astype(np.uint16)
    png = os.path.join(work, f"{slug}.png")
    Image.fromarray(v).save(png)
    # Computed in f32 as the crate does (SPEC §2: value / 65535 × height_scale).
    z = (v.astype(np.float32) / np.float32(65535.0)) * np.float32(scale)
    tif = os.path.join(work, f"{slug}.tif")
    h, w = z.shape
    with rasterio.open(tif, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32",
                       crs="EPSG:32616", transform=from_origin(0.0, float(h), 1.0, 1.0)) as d:
        d.write(z, 1)
    return png, tif


def ours(binary, png, scale, method, work):
    """Per-bin horizon angles in degrees, shape (32, H, W), and the bake's wall seconds."""
    import numpy as np
    import rasterio

    out = os.path.join(work, f"{os.path.basename(png)[:-4]}_{method}")
    cmd = [binary, "bake", png, "-o", out, "--method", method, "--radius", "unlimited",
           "--edge", "none", "--bins", str(BINS), "--outputs", "angles", "--format", "geotiff",
           "--height-scale", repr(scale)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    secs = time.perf_counter() - t0
    if p.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}")
    with rasterio.open(os.path.join(out, "angles.tif")) as d:
        a = d.read().astype(np.float64)
    assert a.shape[0] == BINS, a.shape
    return np.maximum(a, 0.0), secs


def whitebox(tif, shape):
    """horizon_angle at the 32 azimuths, degrees, shape (32, H, W), and its wall seconds."""
    import numpy as np
    import whitebox_workflows as wbw

    wbe = wbw.WbEnvironment()
    wbe.verbose = False
    dem = wbe.read_raster(tif)
    nodata = dem.metadata().nodata
    t0 = time.perf_counter()
    outs = [wbe.horizon_angle(dem, azimuth=(90.0 - 360.0 * k / BINS) % 360.0) for k in range(BINS)]
    secs = time.perf_counter() - t0
    a = []
    for r in outs:
        g = np.asarray(r.to_numpy(), dtype=np.float64).reshape(shape)
        g = np.where(g == nodata, 0.0, g)
        a.append(np.maximum(np.nan_to_num(g, nan=0.0), 0.0))
    return np.stack(a), secs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default="target/debug/horizon-bake", help="horizon-bake binary")
    ap.add_argument("--size", type=int, default=128, help="side of each map (default 128)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--margin", type=int, default=2, help="border texels left out (default 2)")
    ap.add_argument("--markdown", action="store_true", help="print the table as markdown")
    args = ap.parse_args()
    import numpy as np

    binary = os.path.abspath(args.bin)
    failed = []
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name, heights, scale in make_maps(args.size, args.seed):
            png, tif = write_inputs(work, name, heights, scale)
            ref, t_exact = ours(binary, png, scale, "exact", work)
            sw, t_sweep = ours(binary, png, scale, "sweep", work)
            wb, t_wb = whitebox(tif, ref.shape[1:])
            m = args.margin
            inner = (slice(None), slice(m, ref.shape[1] - m), slice(m, ref.shape[2] - m))
            row = {"map": name, "exact_s": t_exact}
            for tool, a, t in (("sweep", sw, t_sweep), ("whitebox", wb, t_wb)):
                d = np.abs(a[inner] - ref[inner]).ravel()
                row[tool] = (d.mean(), np.percentile(d, 99), d.max(), t)
            rows.append(row)
            if not row["sweep"][0] < row["whitebox"][0]:
                failed.append(name)
    n = args.size
    if args.markdown:
        print(f"| map ({n}², 32 azimuths, edge none) | sweep mean / p99 / max | "
              f"Whitebox `horizon_angle` mean / p99 / max | sweep s | Whitebox s |")
        print("|---|---|---|---:|---:|")
    for r in rows:
        s, w = r["sweep"], r["whitebox"]
        if args.markdown:
            print(f"| {r['map']} | {s[0]:.3f}° / {s[1]:.2f}° / {s[2]:.1f}° | "
                  f"{w[0]:.3f}° / {w[1]:.2f}° / {w[2]:.1f}° | {s[3]:.2f} | {w[3]:.2f} |")
        else:
            print(f"{r['map']:12} {n}²: |Δα| against exact: sweep mean {s[0]:.4f}° p99 "
                  f"{s[1]:.3f}° max {s[2]:.2f}° ({s[3]:.2f} s); Whitebox mean {w[0]:.4f}° p99 "
                  f"{w[1]:.3f}° max {w[2]:.2f}° ({w[3]:.2f} s)")
    if failed:
        print(f"FAIL: the sweep's mean error is not below Whitebox's on: {', '.join(failed)}",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
