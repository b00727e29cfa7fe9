#!/usr/bin/env python3
"""Side by side with the GIS peers: GRASS GIS r.horizon, Whitebox Workflows horizon_angle, and
horizon-bake (`exact` and `lengyel`), on the same maps, the same azimuths, in one run.

    python3 scripts/peers.py                       # installs what is missing, writes docs/peers.md
    python3 scripts/peers.py --bin /path/to/horizon-bake --out /tmp/peers.md

What it does (docs/peers.md says the same at more length):
  1. Installs what is missing: the Python packages numpy, pillow, tifffile, OpenEXR and
     whitebox-workflows with pip; GRASS GIS (Debian `grass-core`) with apt-get.
  2. Maps: docs/corpus/jacksboro_128.png (real terrain, height_scale 65535/90) and a seeded fBm
     (512^2 by default), each written as a 16-bit PNG for horizon-bake and as a float32 GeoTIFF
     (cell size 1, north up) holding the heights in texels (value x height_scale) for the peers,
     so every tool sees the same surface in the same units.
  3. Runs every tool at 32 azimuths for the timing (each tool's own compute, wall and CPU time),
     and compares the horizon elevation at the 8 channel azimuths 0, 45, ..., 315 degrees with
     horizon-bake `--method exact --radius unlimited --reduce point --edge none` (SPEC 3.2).
  4. Checks the exact reference itself (and so the orientation mapping) against a brute-force march
     of the bilinear surface at random texels, and fails if they disagree.
  5. Writes the report (Markdown) with the machine, the tables and the conventions.

The times are from one run on whatever machine runs it; on a shared machine they move by +-30%.
"""
import argparse
import datetime
import hashlib
import importlib
import json
import math
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHANNELS = [45.0 * c for c in range(8)]  # our phi, degrees, from +x toward +y (y up)
DIRECTIONS = 32  # azimuths every tool computes for the timing
JACKSBORO_SCALE = 65535.0 / 90.0  # as the eval bakes it: heights in texels = metres / 90

PY_PACKAGES = [  # (module, PyPI name)
    ("numpy", "numpy"),
    ("PIL", "pillow"),
    ("tifffile", "tifffile"),
    ("OpenEXR", "OpenEXR"),
    ("whitebox_workflows", "whitebox-workflows"),
    ("rasterio", "rasterio"),  # the terrain section: GDAL reads our GeoTIFFs, reprojects the DEM
]


def log(msg):
    print(f"[peers] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# 1. installs


def ensure_python_packages():
    missing = []
    for mod, pkg in PY_PACKAGES:
        try:
            importlib.import_module(mod)
        except ImportError:
            missing.append(pkg)
    if missing:
        log(f"pip install {' '.join(missing)}")
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", *missing], check=True)
        importlib.invalidate_caches()


def ensure_grass():
    if shutil.which("grass"):
        return
    if os.geteuid() != 0:
        sys.exit("GRASS GIS is missing: install the Debian package grass-core (as root: "
                 "apt-get update && apt-get install -y grass-core)")
    log("apt-get install grass-core (a few minutes)")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    subprocess.run(["apt-get", "update", "-qq"], check=True, env=env)
    subprocess.run(["apt-get", "install", "-y", "-qq", "grass-core"], check=True, env=env,
                   stdout=subprocess.DEVNULL)
    if not shutil.which("grass"):
        sys.exit("grass is still not on PATH after installing grass-core")


def find_bin(arg):
    cands = [arg] if arg else [os.path.join(REPO, "target", "release", "horizon-bake"),
                               os.path.join(REPO, "target", "debug", "horizon-bake")]
    for c in cands:
        if c and os.path.isfile(c) and os.access(c, os.X_OK):
            return os.path.abspath(c)
    sys.exit(f"no horizon-bake binary at {' or '.join(cands)} (build it with "
             "`cargo build --release` or pass --bin)")


# ---------------------------------------------------------------------------------------------
# 2. maps


def fbm(n, seed, beta=3.0):
    """Seeded spectral fBm (power spectrum ~ 1/f^beta), normalised to [0, 1]."""
    import numpy as np

    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape))
    h = np.fft.irfft2(spec, s=(n, n))
    h -= h.min()
    return h / h.max()


def write_geotiff(path, heights):
    """float32 GeoTIFF, north up, cell size 1 (origin: top-left corner at (0, H)), UTM 16N."""
    import numpy as np
    import tifffile

    h, w = heights.shape
    geokeys = [1, 1, 0, 4,
               1024, 0, 1, 1,  # GTModelTypeGeoKey = projected
               1025, 0, 1, 1,  # GTRasterTypeGeoKey = PixelIsArea
               3072, 0, 1, 32616,  # ProjectedCSTypeGeoKey = WGS 84 / UTM 16N (metres)
               3076, 0, 1, 9001]  # ProjLinearUnitsGeoKey = metre
    tifffile.imwrite(path, heights.astype(np.float32), extratags=[
        (33550, "d", 3, (1.0, 1.0, 0.0), False),  # ModelPixelScale
        (33922, "d", 6, (0.0, 0.0, 0.0, 0.0, float(h), 0.0), False),  # ModelTiepoint
        (34735, "H", len(geokeys), geokeys, False),  # GeoKeyDirectory
    ])


class Map:
    def __init__(self, name, png, scale, desc, work):
        import numpy as np
        from PIL import Image

        self.name, self.png, self.scale, self.desc = name, png, scale, desc
        v = np.asarray(Image.open(png))
        if v.dtype != np.uint16:
            v = np.asarray(Image.open(png).convert("I;16"))
        assert v.ndim == 2 and v.dtype == np.uint16, f"{png}: want 16-bit gray"
        # SPEC 2: value/65535, height in texels = value x height_scale (computed in f32 like the
        # crate; the GeoTIFF holds exactly these f32 numbers)
        self.heights = (v.astype(np.float32) / np.float32(65535.0)) * np.float32(scale)
        self.h, self.w = self.heights.shape
        self.tif = os.path.join(work, f"{name}.tif")
        write_geotiff(self.tif, self.heights)
        self.sha = hashlib.sha256(open(png, "rb").read()).hexdigest()[:16]


def make_maps(args, work):
    import numpy as np
    from PIL import Image

    maps = [Map("jacksboro_128", os.path.join(REPO, "docs", "corpus", "jacksboro_128.png"),
                JACKSBORO_SCALE, "real terrain (USGS DEM, 90 m/texel), edge=none", work)]
    n = args.size
    png = os.path.join(work, f"fbm_{n}.png")
    h = fbm(n, args.seed)
    Image.fromarray(np.round(h * 65535.0).astype(np.uint16)).save(png)
    maps.append(Map(f"fbm_{n}", png, args.fbm_scale,
                    f"spectral fBm, beta 3.0, seed {args.seed}, height_scale {args.fbm_scale:g}",
                    work))
    return maps


# ---------------------------------------------------------------------------------------------
# 3. tools. Each returns ({phi in degrees: alpha in degrees, clamped at 0, H x W} for the azimuths
#    it has (ours: the 8 channels; peers: all 32), {wall, cpu, kernel: seconds, cmd})


def child_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def read_exr_rgba(path):
    import numpy as np
    import OpenEXR

    with OpenEXR.File(path) as f:
        ch = f.channels()
        if "RGBA" in ch:
            px = np.asarray(ch["RGBA"].pixels, dtype=np.float64)
            return [px[..., k] for k in range(4)]
        return [np.asarray(ch[k].pixels, dtype=np.float64) for k in "RGBA"]


def run_ours(binary, m, work, method, reduce_, read_layers):
    import numpy as np

    out = os.path.join(work, f"ours_{m.name}_{method}_{reduce_}")
    shutil.rmtree(out, ignore_errors=True)
    cmd = [binary, "bake", m.png, "-o", out, "--method", method, "--bins", str(DIRECTIONS),
           "--edge", "none", "--format", "exr", "--height-scale", repr(m.scale)]
    if method in ("exact", "sweep"):
        cmd += ["--radius", "unlimited", "--reduce", reduce_]
    c0, t0 = child_cpu(), time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, child_cpu() - c0
    if p.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}")
    bake = json.load(open(os.path.join(out, "bake.json")))
    t = bake.get("timings_ms", {})
    alpha = None
    if read_layers:
        l0 = read_exr_rgba(os.path.join(out, "horizon_0.exr"))
        l1 = read_exr_rgba(os.path.join(out, "horizon_1.exr"))
        s = l0 + l1
        alpha = {CHANNELS[c]: np.degrees(np.arcsin(np.clip(s[c], 0.0, 1.0))) for c in range(8)}
    return alpha, {"wall": wall, "cpu": cpu, "kernel": t.get("bake", float("nan")) / 1e3,
                   "total_ms": t.get("total"), "cmd": " ".join(cmd[1:]).replace(work + "/", "")}


GRASS_SCRIPT = r"""set -e
r.in.gdal -o --quiet input="$PEERS_TIF" output=dem
g.region raster=dem
TIMEFORMAT='%R %U %S'
{ time r.horizon -d --quiet elevation=dem step="$PEERS_STEP" start=0 end=360 \
    maxdistance="$PEERS_MAXDIST" output=hor ; } 2> "$PEERS_OUT/time.txt"
g.list raster pattern='hor_*' > "$PEERS_OUT/names.txt"
k=0
for m in $(cat "$PEERS_OUT/names.txt"); do
  r.out.gdal --quiet -c -f input="$m" output="$PEERS_OUT/az$(printf %02d $k).tif" format=GTiff type=Float32
  k=$((k + 1))
done
"""


def run_grass(m, work):
    """r.horizon at 32 directions (step 11.25 deg, counter-clockwise from east), degrees."""
    import numpy as np
    import tifffile

    out = os.path.join(work, f"grass_{m.name}")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    script = os.path.join(out, "run.sh")
    open(script, "w").write(GRASS_SCRIPT)
    # r.horizon names its maps hor_<angle> (GRASS 8.2, step 11.25: hor_000_00, hor_011_25, ...),
    # which g.list sorts by angle; they are exported in that order as az00.tif ... az31.tif
    azimuths = [360.0 * k / DIRECTIONS for k in range(DIRECTIONS)]
    names = [f"az{k:02d}" for k in range(DIRECTIONS)]
    maxdist = math.ceil(math.hypot(m.w, m.h)) + 1  # past every cell: rays go to the map edge
    env = dict(os.environ, PEERS_TIF=m.tif, PEERS_OUT=out, PEERS_STEP=repr(360.0 / DIRECTIONS),
               PEERS_MAXDIST=str(maxdist))
    # a projected location (UTM 16N, metres): r.horizon refuses an XY location
    cmd = ["grass", "--tmp-location", "EPSG:32616", "--exec", "bash", script]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if p.returncode != 0:
        sys.exit(f"GRASS failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    listed = open(os.path.join(out, "names.txt")).read().split()
    if len(listed) != DIRECTIONS:
        sys.exit(f"r.horizon wrote {len(listed)} maps, expected {DIRECTIONS}: {listed}")
    real, user, sys_ = (float(x) for x in open(os.path.join(out, "time.txt")).read().split()[-3:])
    want = [f"hor_{int(a):03d}_{round(a % 1 * 100):02d}" for a in azimuths]
    if listed != want:
        sys.exit(f"unexpected r.horizon map names {listed} (expected {want})")
    alpha = {}
    for a, n in zip(azimuths, names):
        g = tifffile.imread(os.path.join(out, f"{n}.tif")).astype(np.float64)
        alpha[a] = np.maximum(np.nan_to_num(g, nan=0.0), 0.0)
    return alpha, {"wall": real, "cpu": user + sys_, "kernel": real,
                   "cmd": f"r.horizon -d elevation=dem step={360.0 / DIRECTIONS} start=0 end=360 "
                          f"maxdistance={maxdist} output=hor"}


def run_whitebox(m):
    """horizon_angle once per azimuth (degrees clockwise from north), 32 azimuths, in memory."""
    import numpy as np
    import whitebox_workflows as wbw

    wbe = wbw.WbEnvironment()
    wbe.verbose = False
    dem = wbe.read_raster(m.tif)
    md = dem.metadata()
    assert abs(md.resolution_x - 1) < 1e-9 and abs(md.resolution_y - 1) < 1e-9, "cell size 1"
    outs = {}
    c0, t0 = time.process_time(), time.perf_counter()
    for k in range(DIRECTIONS):
        phi = 360.0 * k / DIRECTIONS
        outs[phi] = wbe.horizon_angle(dem, azimuth=(90.0 - phi) % 360.0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    alpha = {}
    for a in outs:
        g = np.asarray(outs[a].to_numpy(), dtype=np.float64).reshape(m.h, m.w)
        g = np.where(g == md.nodata, 0.0, g)
        alpha[a] = np.maximum(np.nan_to_num(g, nan=0.0), 0.0)
    return alpha, {"wall": wall, "cpu": cpu, "kernel": wall, "max_procs": wbe.max_procs,
                   "cmd": f"wbe.horizon_angle(dem, azimuth=(90 - phi) % 360), "
                          f"max_dist=None, {DIRECTIONS} azimuths"}


# ---------------------------------------------------------------------------------------------
# 4. reference check: brute-force march on the bilinear surface (SPEC 3.2, edge=none)


def march_alpha(heights, row, col, phi_deg, step=0.005):
    import numpy as np

    h, w = heights.shape
    dx, dy = math.cos(math.radians(phi_deg)), -math.sin(math.radians(phi_deg))  # y up = row down
    # distance to the last point inside the hull of the texel centres
    lim = []
    for p, d, hi in ((col, dx, w - 1), (row, dy, h - 1)):
        if d > 1e-12:
            lim.append((hi - p) / d)
        elif d < -1e-12:
            lim.append(-p / d)
    smax = min(lim)
    if smax <= 0:
        return 0.0
    # fine steps in the first 2 texels, where a steep bilinear patch can put the maximum slope
    # a small fraction of a texel from the origin; `step` beyond
    near = np.arange(step / 10.0, min(2.0, smax), step / 10.0)
    s = np.concatenate([near, np.arange(min(2.0, smax), smax + 1e-9, step)])
    x, y = col + s * dx, row + s * dy
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    z = (heights[y0, x0] * (1 - fx) * (1 - fy) + heights[y0, x0 + 1] * fx * (1 - fy)
         + heights[y0 + 1, x0] * (1 - fx) * fy + heights[y0 + 1, x0 + 1] * fx * fy)
    t = np.max((z - heights[row, col]) / s)
    return max(0.0, math.degrees(math.atan(t)))


def spot_check(m, tools, n, seed):
    """|alpha_tool - alpha_march| at n random texels at the channel azimuths and n at the other
    24 azimuths; per tool {"ch": (mean, max), "other": (mean, max) or None}."""
    import numpy as np

    rng = np.random.default_rng(seed)
    hd = m.heights.astype(np.float64)
    others = [360.0 * k / DIRECTIONS for k in range(DIRECTIONS) if k % (DIRECTIONS // 8)]
    res = {}
    for group, azs in (("ch", CHANNELS), ("other", others)):
        diffs = {name: [] for name, _ in tools}
        for _ in range(n):
            r, c = int(rng.integers(m.h)), int(rng.integers(m.w))
            a = azs[int(rng.integers(len(azs)))]
            t = march_alpha(hd, r, c, a)
            for name, alpha in tools:
                if a in alpha:
                    diffs[name].append(abs(float(alpha[a][r, c]) - t))
        for name, d in diffs.items():
            res.setdefault(name, {})[group] = (float(np.mean(d)), float(np.max(d))) if d else None
    return res


# ---------------------------------------------------------------------------------------------
# 6. terrain products (issue 24): a real DEM in metres, angles and sky-view factor at 32
#    azimuths, unlimited radius, against GRASS r.horizon (+ the SVF formula on its output) and
#    Whitebox Workflows horizon_angle / sky_view_factor


def elev_tif(work):
    """R terra's ex/elev.tif (SRTM-derived, int16, EPSG:4326, GPL-3+): $HB_ELEV_TIF, else
    extracted from the Debian package r-cran-terra (apt-get download + dpkg-deb -x, no install),
    as tests/terrain/check_dem.py obtains it."""
    import glob

    if os.environ.get("HB_ELEV_TIF"):
        return os.environ["HB_ELEV_TIF"]
    d = os.path.join(work, "terra")
    found = glob.glob(os.path.join(d, "**", "ex", "elev.tif"), recursive=True)
    if found:
        return found[0]
    os.makedirs(d, exist_ok=True)
    p = subprocess.run(["apt-get", "download", "r-cran-terra"], cwd=d, capture_output=True)
    if p.returncode != 0:
        subprocess.run(["apt-get", "update", "-qq"], check=True)
        subprocess.run(["apt-get", "download", "r-cran-terra"], cwd=d, check=True,
                       capture_output=True)
    deb = glob.glob(os.path.join(d, "r-cran-terra_*.deb"))[0]
    subprocess.run(["dpkg-deb", "-x", deb, os.path.join(d, "x")], check=True)
    return glob.glob(os.path.join(d, "**", "ex", "elev.tif"), recursive=True)[0]


def largest_valid_square(valid):
    """(row, col, side) of the largest square of True cells (dynamic programming)."""
    import numpy as np

    h, w = valid.shape
    best = (0, 0, 0)
    dp = np.zeros((h + 1, w + 1), dtype=np.int32)
    for r in range(h):
        for c in range(w):
            if valid[r, c]:
                dp[r + 1, c + 1] = 1 + min(dp[r, c + 1], dp[r + 1, c], dp[r, c])
                if dp[r + 1, c + 1] > best[2]:
                    k = int(dp[r + 1, c + 1])
                    best = (r - k + 1, c - k + 1, k)
    return best


class TerrainDem:
    """elev.tif reprojected to UTM 32N at its native resolution to find the largest square with
    no nodata, then that square resampled (GDAL cubic) to size² cells in metres, written as a
    float32 GeoTIFF in a location where every tool's north is the grid's (see docs/peers.md)."""

    def __init__(self, size, work, holes=False):
        import numpy as np
        import rasterio
        from rasterio.transform import Affine
        from rasterio.warp import Resampling, calculate_default_transform, reproject

        self.holes = holes
        self.keep = None  # the texels the errors are taken over (None: every texel)

        src_path = elev_tif(work)
        utm = "EPSG:32632"
        with rasterio.open(src_path) as s:
            tr, w, h = calculate_default_transform(s.crs, utm, s.width, s.height, *s.bounds)
            native = np.full((h, w), -9999.0, dtype=np.float64)
            reproject(rasterio.band(s, 1), native, dst_transform=tr, dst_crs=utm,
                      resampling=Resampling.bilinear, dst_nodata=-9999.0)
            src_crs, src_tr, src_data = s.crs, s.transform, s.read(1)
            src_nodata = s.nodata
            self.src_shape = (s.height, s.width)
        self.native_cell = tr.a
        if holes:
            # The whole warped grid, squared, with the nodata collar the warp leaves (every
            # reprojected DEM has one): bilinear, so no kernel reaches across a hole.
            r, c, k = 0, 0, max(w, h)
            resampling = Resampling.bilinear
        else:
            # one native cell of margin, so the cubic kernel never reaches a hole
            r, c, k = largest_valid_square(native > -9000.0)
            r, c, k = r + 1, c + 1, k - 2
            resampling = Resampling.cubic
        self.extent = k * tr.a
        self.cell = self.extent / size
        x0, y0 = tr * (c, r)
        dst_tr = Affine(self.cell, 0.0, x0, 0.0, -self.cell, y0)
        dem = np.full((size, size), np.nan, dtype=np.float64)
        reproject(src_data.astype(np.float64), dem, src_transform=src_tr, src_crs=src_crs,
                  src_nodata=src_nodata, dst_transform=dst_tr, dst_crs=utm,
                  resampling=resampling, dst_nodata=np.nan)
        valid = np.isfinite(dem)
        if holes:
            self.keep = valid
            self.nodata_share = float(1.0 - valid.mean())
            self.heights = np.where(valid, dem, -9999.0).astype(np.float32)
            self.range = (float(dem[valid].min()), float(dem[valid].max()))
        else:
            if not np.all(valid):
                sys.exit(f"the {size}² crop of elev.tif has {int(np.sum(~valid))} holes")
            self.heights = dem.astype(np.float32)
            self.range = (float(dem.min()), float(dem.max()))
        self.size, self.native_side = size, k
        self.src = src_path
        self.sha = hashlib.sha256(open(src_path, "rb").read()).hexdigest()[:16]
        self.tif = os.path.join(work, f"elev_{size}{'_holes' if holes else ''}.tif")
        write_geotiff_m(self.tif, self.heights, self.cell, -9999.0 if holes else None)


def write_geotiff_m(path, heights, cell, nodata=None):
    """float32 GeoTIFF in metres, cell `cell` m, north up, UTM 16N (EPSG:32616) at easting
    500 000 (its central meridian) and northings 0..H·cell (the equator): grid north is true
    north there, so GRASS's rays (turned to true north) run along our grid directions. With
    `nodata`, a GDAL_NODATA tag (42113) every tool reads."""
    import numpy as np
    import tifffile

    h, w = heights.shape
    geokeys = [1, 1, 0, 4,
               1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32616, 3076, 0, 1, 9001]
    tags = [
        (33550, "d", 3, (cell, cell, 0.0), False),
        (33922, "d", 6, (0.0, 0.0, 0.0, 500000.0, h * cell, 0.0), False),
        (34735, "H", len(geokeys), geokeys, False),
    ]
    if nodata is not None:
        tags.append((42113, "s", 0, f"{nodata:g}", False))
    tifffile.imwrite(path, heights.astype(np.float32), extratags=tags)


class Acc:
    """|Δα| (degrees) accumulated azimuth by azimuth: the mean, and the 99th percentile from a
    histogram of 1e-4° bins (exact to 1e-4°), so 2048² × 32 values never sit in memory."""
    STEP, N = 1e-4, 900_001

    def __init__(self, keep=None):
        import numpy as np

        self.hist = np.zeros(self.N, dtype=np.int64)
        self.sum, self.n = 0.0, 0
        self.keep = keep  # a mask of the texels counted (None: all)

    def add(self, d):
        import numpy as np

        d = np.asarray(d, dtype=np.float64)
        if self.keep is not None:
            d = d[self.keep]
        d = np.abs(d).ravel()
        self.sum += float(d.sum())
        self.n += d.size
        self.hist += np.bincount(np.minimum((d / self.STEP).astype(np.int64), self.N - 1),
                                 minlength=self.N)

    def mean(self):
        return self.sum / self.n

    def p99(self):
        import numpy as np

        cum = np.cumsum(self.hist)
        return (int(np.searchsorted(cum, 0.99 * self.n)) + 1) * self.STEP


def svf_visual(sin_sum, n):
    return 1.0 - sin_sum / n


def accepts_sweep(binary, work):
    """Whether this binary bakes with --method sweep (the sweep kernel lands separately)."""
    import numpy as np
    from PIL import Image

    png = os.path.join(work, "probe.png")
    Image.fromarray((np.arange(64, dtype=np.uint16) * 1000).reshape(8, 8)).save(png)
    out = os.path.join(work, "probe_out")
    shutil.rmtree(out, ignore_errors=True)
    p = subprocess.run([binary, "bake", png, "-o", out, "--method", "sweep", "--radius",
                        "unlimited", "--edge", "none"], capture_output=True, text=True)
    return p.returncode == 0, p.stderr.strip().splitlines()[-1:] if p.returncode else []


def run_ours_terrain(binary, dem, work, name, extra):
    out = os.path.join(work, f"terrain_{name}")
    shutil.rmtree(out, ignore_errors=True)
    cmd = [binary, "bake", dem.tif, "-o", out, "--bins", str(DIRECTIONS), "--outputs",
           "angles,svf", "--svf-model", "visual", "--format", "geotiff", *extra]
    c0, t0 = child_cpu(), time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, child_cpu() - c0
    if p.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}")
    bake = json.load(open(os.path.join(out, "bake.json")))
    pr = bake["params"]
    log(f"    {name}: {wall:.1f} s wall; method {pr['method']}, radius "
        f"{pr.get('resolved_radius')}, curvature {pr['earth_curvature']}, edge {pr['edge']}")
    return out, {"wall": wall, "cpu": cpu, "kernel": bake["timings_ms"]["bake"] / 1e3,
                 "params": pr, "cmd": " ".join(cmd[1:]).replace(work + "/", "")}


def read_band(path, k):
    import rasterio

    with rasterio.open(path) as a:
        return a.read(k + 1).astype("float64")


def terrain_section(args, binary, work):
    import numpy as np

    dem = TerrainDem(args.terrain_size, work, holes=args.terrain_holes)
    n = dem.size
    log(f"terrain: elev.tif {dem.src_shape} -> UTM 32N, {dem.native_side}² native cells of "
        f"{dem.native_cell:.1f} m -> {n}² at {dem.cell:.3f} m; heights "
        f"{dem.range[0]:.1f}..{dem.range[1]:.1f} m"
        + (f"; {dem.nodata_share:.0%} nodata" if dem.holes else ""))
    dirs = [360.0 * k / DIRECTIONS for k in range(DIRECTIONS)]
    rows = []  # (name, threads, timing, acc or None, svf array or None, note)

    # the reference: exact, unlimited radius, DEM defaults (edge none, curvature on)
    ref_dir, t_ref = run_ours_terrain(binary, dem, work, "exact", ["--method", "exact",
                                                                   "--radius", "unlimited"])
    ref_angles = os.path.join(ref_dir, "angles.tif")
    ref_svf = read_band(os.path.join(ref_dir, "svf.tif"), 0)

    def ours_row(name, label, extra, note):
        d, t = run_ours_terrain(binary, dem, work, name, extra)
        acc = Acc(dem.keep)
        for k in range(DIRECTIONS):
            acc.add(read_band(os.path.join(d, "angles.tif"), k) - read_band(ref_angles, k))
        svf = read_band(os.path.join(d, "svf.tif"), 0)
        rows.append((label, "2", t, acc, svf, note))

    rows.append(("horizon-bake `exact` (reference)", "2", t_ref, None, None,
                 "`--method exact --radius unlimited`; DEM defaults: edge none, curvature on"))
    pad = n + 2
    tile = (1 + 2 * pad) * (2 * pad + n + 64)
    fallback = ("its band tile exceeds MAX_TILE: runs as the exact kernel" if tile > 1 << 24
                else "its own kernel")
    ours_row("march", "horizon-bake `march`",
             ["--method", "march", "--max-distance", repr(n * dem.cell)],
             f"`--max-distance` {n * dem.cell:.0f} m = {n} texels; {fallback}")
    ok, why = accepts_sweep(binary, work)
    sweep_note = None
    if ok:
        ours_row("sweep", "horizon-bake `sweep`", ["--method", "sweep", "--radius", "unlimited"],
                 "`--method sweep --radius unlimited`")
    else:
        sweep_note = f"this binary does not accept `--method sweep` yet ({' '.join(why)})"
        log(f"  sweep skipped: {sweep_note}")
    ours_row("exact_flat", "horizon-bake `exact`, earth_curvature=off", [
        "--method", "exact", "--radius", "unlimited", "--earth-curvature", "off"],
        "the size of the curvature drop itself (Whitebox has none)")

    # GRASS r.horizon, maxdistance past every cell, degrees; always applies the curvature drop
    log("  GRASS r.horizon")
    out = os.path.join(work, "terrain_grass")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    script = os.path.join(out, "run.sh")
    open(script, "w").write(GRASS_SCRIPT)
    maxdist = (math.ceil(math.hypot(n, n)) + 1) * dem.cell
    env = dict(os.environ, PEERS_TIF=dem.tif, PEERS_OUT=out,
               PEERS_STEP=repr(360.0 / DIRECTIONS), PEERS_MAXDIST=repr(maxdist))
    c0, t0 = child_cpu(), time.perf_counter()
    p = subprocess.run(["grass", "--tmp-location", "EPSG:32616", "--exec", "bash", script],
                       capture_output=True, text=True, env=env)
    if p.returncode != 0:
        sys.exit(f"GRASS failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    real, user, sys_ = (float(x) for x in open(os.path.join(out, "time.txt")).read().split()[-3:])
    listed = open(os.path.join(out, "names.txt")).read().split()
    want = [f"hor_{int(a):03d}_{round(a % 1 * 100):02d}" for a in dirs]
    if listed != want:
        sys.exit(f"unexpected r.horizon map names {listed} (expected {want})")
    acc, sin_sum = Acc(dem.keep), np.zeros((n, n))
    import tifffile
    for k in range(DIRECTIONS):
        g = tifffile.imread(os.path.join(out, f"az{k:02d}.tif")).astype(np.float64)
        g = np.maximum(np.nan_to_num(g, nan=0.0), 0.0)
        acc.add(g - read_band(ref_angles, k))
        sin_sum += np.sin(np.radians(g))
    t_gr = {"wall": real, "cpu": user + sys_, "kernel": real,
            "cmd": f"r.horizon -d elevation=dem step={360.0 / DIRECTIONS} start=0 end=360 "
                   f"maxdistance={maxdist:.1f} output=hor"}
    rows.append(("GRASS `r.horizon` (+ SVF formula)", "1", t_gr, acc,
                 svf_visual(sin_sum, DIRECTIONS),
                 "the process: reads the map, 32 rasters out; SVF = 1 − mean sin max(α, 0)"))

    # Whitebox Workflows: horizon_angle per azimuth, then its own sky_view_factor
    import whitebox_workflows as wbw

    wbe = wbw.WbEnvironment()
    wbe.verbose = False
    wdem = wbe.read_raster(dem.tif)
    md = wdem.metadata()
    log("  Whitebox horizon_angle x32")
    acc, sin_sum, secs, cpu = Acc(dem.keep), np.zeros((n, n)), 0.0, 0.0
    for k, phi in enumerate(dirs):
        c0, t0 = time.process_time(), time.perf_counter()
        r = wbe.horizon_angle(wdem, azimuth=(90.0 - phi) % 360.0)
        secs += time.perf_counter() - t0
        cpu += time.process_time() - c0
        g = np.asarray(r.to_numpy(), dtype=np.float64).reshape(n, n)
        del r
        g = np.maximum(np.nan_to_num(np.where(g == md.nodata, 0.0, g), nan=0.0), 0.0)
        acc.add(g - read_band(ref_angles, k))
        sin_sum += np.sin(np.radians(g))
    rows.append(("Whitebox `horizon_angle` (+ SVF formula)",
                 f"{os.cpu_count()} (max_procs {wbe.max_procs})",
                 {"wall": secs, "cpu": cpu, "kernel": secs}, acc, svf_visual(sin_sum, DIRECTIONS),
                 "32 calls on a raster in memory, no curvature drop; SVF = 1 − mean sin max(α, 0)"))
    log("  Whitebox sky_view_factor")
    c0, t0 = time.process_time(), time.perf_counter()
    r = wbe.sky_view_factor(wdem, az_fraction=360.0 / DIRECTIONS, observer_hgt_offset=0.0)
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    g = np.asarray(r.to_numpy(), dtype=np.float64).reshape(n, n)
    g = np.where(g == md.nodata, np.nan, g)
    rows.append(("Whitebox `sky_view_factor`", f"{os.cpu_count()} (max_procs {wbe.max_procs})",
                 {"wall": secs, "cpu": cpu, "kernel": secs}, None, g,
                 f"az_fraction {360.0 / DIRECTIONS}, observer_hgt_offset 0; its own SVF"))
    return dem, rows, ref_svf, sweep_note


def terrain_table(dem, rows, ref_svf):
    import numpy as np

    n = dem.size
    out = ["| tool | threads | compute s | wall s | CPU s | Mtexel/s @32 | mean \\|Δα\\| ° "
           "| p99 \\|Δα\\| ° | mean \\|Δsvf\\| | p99 \\|Δsvf\\| | note |",
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for name, threads, tm, acc, svf, note in rows:
        mts = n * n / 1e6 / tm["kernel"]
        err = "— | —" if acc is None else f"{acc.mean():.4f} | {acc.p99():.4f}"
        if svf is None:
            serr = "— | —"
        else:
            d = np.abs(svf - ref_svf)
            if dem.keep is not None:
                d = d[dem.keep]
            d = d[np.isfinite(d)]
            serr = f"{float(d.mean()):.5f} | {float(np.percentile(d, 99)):.5f}"
        out.append(f"| {name} | {threads} | {tm['kernel']:,.1f} | {tm['wall']:,.1f} "
                   f"| {tm['cpu']:,.1f} | {mts:.3f} "
                   f"| {err} | {serr} | {note} |")
    return "\n".join(out)


TERRAIN_HEAD = """## Terrain products (generated)

Generated {date} by `python3 scripts/peers.py --terrain-only --terrain-size {n}`: one run on a
**shared, noisy** machine ({nproc} cores, {cpu}); tools: {grass}; {wb}; {ours}{binnote}.

DEM: R `terra`'s `ex/elev.tif` (SRTM-derived, Luxembourg, int16, EPSG:4326, {src_w}×{src_h}
cells; sha256 `{sha}…`), reprojected to UTM 32N (bilinear) at its native {native:.1f} m, the
largest square with no nodata found ({side}² native cells, one cell of margin), and that square
**upsampled** by GDAL's cubic resampling to **{n}² cells of {cell:.3f} m** ({factor:.1f}× finer
than the source: the fine relief is the cubic interpolant's, the large relief is real). Heights
{hmin:.1f} to {hmax:.1f} m. Every tool reads the same float32 GeoTIFF in metres.

Reference: `horizon-bake bake elev_{n}.tif --method exact --radius unlimited --bins 32
--outputs angles,svf --svf-model visual --format geotiff`, with the DEM defaults (cell size
from the file, `height_scale` = 1/cell, `edge=none`, `earth_curvature=on`, refraction 0):
SPEC §3.2 with the drop d²/(2·6 371 km), the drop GRASS applies. |Δα| over every texel and all
32 azimuths against it (α clamped at 0 for the peers, as SPEC §3.2 defines it); |Δsvf| in the
visual form 1 − mean sin α (Whitebox's form) over every texel. *Mtexel/s @32*: texels / compute
time, every row at 32 azimuths (SVF alone for `sky_view_factor`). Compute: ours
`timings_ms.bake` (kernel, products and their GeoTIFF encode, without the decode), GRASS the
`r.horizon` process, Whitebox its calls on a raster in memory.
"""

TERRAIN_HOLES_HEAD = """## Terrain products on a DEM with nodata (generated)

Generated {date} by `python3 scripts/peers.py --terrain-only --terrain-holes --terrain-size {n}`:
one run on a **shared, noisy** machine ({nproc} cores, {cpu}); tools: {grass}; {wb}; {ours}{binnote}.

DEM: R `terra`'s `ex/elev.tif` (SRTM-derived, Luxembourg, int16, EPSG:4326, {src_w}×{src_h}
cells; sha256 `{sha}…`), reprojected to UTM 32N (bilinear) as a whole: the square around the
warped grid ({side}² native cells of {native:.1f} m) resampled (GDAL bilinear) to **{n}² cells
of {cell:.3f} m**, with the nodata collar the warp leaves (**{holes:.0%} of the cells**, GDAL_NODATA
−9999), as every reprojected or clipped DEM has one. Heights {hmin:.1f} to {hmax:.1f} m on the
valid cells. Every tool reads the same float32 GeoTIFF in metres with its nodata tag.

Reference and columns as in the block above, and *CPU s* (user + system of our process and of
GRASS's, the Python process's own for Whitebox, which computes in its threads); the errors over
the valid cells only (each tool writes nodata, or a value we ignore, on the holes; a hole casts
no horizon for ours, SPEC §2); *Mtexel/s* over every cell, holes included.
"""

TERRAIN_PROSE = """
Conventions made equal, so the numbers compare like with like:

- **Directions.** GRASS counts counter-clockwise from east (our `east_ccw`), Whitebox clockwise
  from north (called with (90° − φ) mod 360°). GRASS turns each ray to *true* north through the
  projection; the GeoTIFF therefore sits in UTM 16N on the central meridian at the equator
  (easting 500 000, northings 0..size·cell), where grid convergence is zero, so its rays run
  along ours. (On elev.tif's own UTM 32N grid they would be off by about 2°.)
- **Radius and border.** Unlimited for all: ours `--radius unlimited` with `edge=none`, GRASS
  `maxdistance` past the map's diagonal, Whitebox `max_dist` unset. `march` is given
  `--max-distance` = the map's side (its note says whether its padded band tile, (1 + 2·(R+2))
  rows of 2·(R+2) + W + 64 floats, exceeds `MAX_TILE` = 2²⁴, where it runs as the exact kernel
  with the same drop: the documented fallback for huge radii).
- **Curvature.** Ours and GRASS lower a point d away by d²/(2·6 371 km); Whitebox has no drop:
  the `earth_curvature=off` row is the drop's own size in angle, the part of Whitebox's Δα that
  is convention rather than error.
- **Negative angles.** GRASS writes −90° where a ray leaves the map at once and keeps negative
  angles; Whitebox keeps them too: both are clamped at 0 for |Δα| and for the SVF formula on
  their angles. Whitebox's `sky_view_factor` is its own (visual form, observer offset set to 0
  instead of its Python default 0.05).
"""


def write_terrain_report(args, mach, vers, dem, rows, ref_svf, sweep_note):
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    head = TERRAIN_HOLES_HEAD if dem.holes else TERRAIN_HEAD
    body = head.format(holes=getattr(dem, "nodata_share", 0.0),
        date=now, n=dem.size, nproc=mach["nproc"], cpu=mach["cpu"], grass=vers["grass"],
        wb=vers["whitebox"], ours=vers["ours"],
        binnote=(" (" + args.bin_note + ")") if args.bin_note else "",
        src_h=dem.src_shape[0], src_w=dem.src_shape[1], sha=dem.sha, native=dem.native_cell,
        side=dem.native_side, cell=dem.cell, factor=dem.native_cell / dem.cell,
        hmin=dem.range[0], hmax=dem.range[1])
    body += "\n" + terrain_table(dem, rows, ref_svf) + "\n"
    if sweep_note:
        body += f"\n`sweep`: not measured, {sweep_note}.\n"
    if not dem.holes:
        body += TERRAIN_PROSE
    old = open(args.out).read() if os.path.exists(args.out) else ""
    tag = "peers-terrain-holes" if dem.holes else "peers-terrain"
    begin, end = f"<!-- {tag}:begin -->", f"<!-- {tag}:end -->"
    if begin in old and end in old:
        text = old[:old.index(begin) + len(begin)] + "\n" + body + "\n" + old[old.index(end):]
    else:
        block = begin + "\n" + body + "\n" + end + "\n"
        anchor = "<!-- peers:end -->"
        if dem.holes and "\n## Reading\n" in old:
            # After the hole-free block and its reading, before the general reading.
            i = old.index("\n## Reading\n") + 1
            text = old[:i] + block + "\n" + old[i:]
        elif anchor in old:
            i = old.index(anchor) + len(anchor)
            text = old[:i] + "\n\n" + block + old[i:]
        else:
            text = old + "\n" + block
    open(args.out, "w").write(text)
    log("\n" + terrain_table(dem, rows, ref_svf))


# ---------------------------------------------------------------------------------------------
# 5. statistics and report


def stats(alpha, ref, margin):
    import numpy as np

    d = np.stack([alpha[a] - ref[a] for a in CHANNELS])
    if margin:
        d = d[:, margin:-margin, margin:-margin]
    ad = np.abs(d)
    return {"mean": float(ad.mean()), "p99": float(np.percentile(ad, 99)),
            "bias": float(d.mean()), "max": float(ad.max()),
            "axis": float(ad[0::2].mean()), "diag": float(ad[1::2].mean())}


def machine():
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    flags = ""
    try:
        txt = open("/proc/cpuinfo").read()
        fl = re.search(r"^flags\s*:(.*)$", txt, re.M).group(1).split()
        flags = ", ".join(f for f in ("avx2", "avx512f") if f in fl)
    except (OSError, AttributeError):
        pass
    return {"nproc": os.cpu_count(), "cpu": cpu, "simd": flags or "no AVX2",
            "python": platform.python_version(), "kernel": platform.release()}


def tool_versions(binary):
    import numpy as np
    import whitebox_workflows as wbw

    v = {}
    try:
        p = subprocess.run(["grass", "--version"], capture_output=True, text=True)
        g = re.search(r"GRASS GIS \S+", p.stdout + p.stderr)
        v["grass"] = g.group(0) if g else "GRASS GIS ?"
    except OSError:
        v["grass"] = "GRASS GIS ?"
    try:
        v["whitebox"] = "whitebox-workflows " + wbw.WbEnvironment().version()
    except Exception:  # noqa: BLE001 - version string only
        v["whitebox"] = "whitebox-workflows ?"
    try:
        p = subprocess.run([binary, "--version"], capture_output=True, text=True)
        v["ours"] = (p.stdout or p.stderr).strip() or "?"
    except OSError:
        v["ours"] = "?"
    v["numpy"] = np.__version__
    return v


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", help="horizon-bake binary (default target/release/horizon-bake, "
                    "else target/debug/horizon-bake)")
    ap.add_argument("--bin-note", default="", help="free text on the binary's build, for the report")
    ap.add_argument("--out", default=os.path.join(REPO, "docs", "peers.md"))
    ap.add_argument("--work", help="keep the intermediate files here (default: a temp dir, removed)")
    ap.add_argument("--size", type=int, default=512, help="side of the fBm map (default 512)")
    ap.add_argument("--seed", type=int, default=12, help="fBm and spot-check seed (default 12)")
    ap.add_argument("--fbm-scale", type=float, default=24.0,
                    help="height_scale of the fBm map: its relief in texels (default 24)")
    ap.add_argument("--margin", type=int, default=2,
                    help="border texels left out of the 'interior' error columns (default 2)")
    ap.add_argument("--check", type=int, default=200,
                    help="random texels per azimuth group at which every tool is compared with a "
                         "brute-force march of the bilinear surface (default 200; 0 = skip)")
    ap.add_argument("--check-tol", type=float, default=0.25,
                    help="fail if the reference is further than this from the march, degrees")
    ap.add_argument("--no-install", action="store_true", help="fail instead of installing")
    ap.add_argument("--terrain", action="store_true",
                    help="also run the terrain-products comparison (issue 24; see docs/peers.md)")
    ap.add_argument("--terrain-only", action="store_true",
                    help="run only the terrain-products comparison (keeps the other block)")
    ap.add_argument("--terrain-holes", action="store_true",
                    help="the terrain comparison on the whole warped DEM, its nodata collar kept")
    ap.add_argument("--terrain-size", type=int, default=2048,
                    help="side of the upsampled DEM of the terrain comparison (default 2048)")
    args = ap.parse_args()

    if not args.no_install:
        ensure_python_packages()
        ensure_grass()
    binary = find_bin(args.bin)
    work = args.work or tempfile.mkdtemp(prefix="hb-peers-")
    os.makedirs(work, exist_ok=True)
    log(f"work dir {work}, binary {binary}")

    mach = machine()
    vers = tool_versions(binary)
    if args.terrain or args.terrain_only:
        dem, rows, ref_svf, sweep_note = terrain_section(args, binary, work)
        write_terrain_report(args, mach, vers, dem, rows, ref_svf, sweep_note)
        log(f"wrote the terrain block of {args.out}")
        if args.terrain_only:
            if not args.work:
                shutil.rmtree(work, ignore_errors=True)
            return
    maps = make_maps(args, work)
    results = []
    for m in maps:
        log(f"{m.name}: {m.w}x{m.h}")
        # the reference: exact, unlimited, edge none, the bin at each channel azimuth
        ref, t_ref = run_ours(binary, m, work, "exact", "point", True)
        t_ref["dirs"] = 8  # reduce=point casts only the 8 channel azimuths
        # the same kernel casting all 32 azimuths (reduce=average), for the 32-direction timing
        _, t_ex32 = run_ours(binary, m, work, "exact", "average", False)
        t_ex32["dirs"] = DIRECTIONS
        # the default model: lengyel R16 B32 (channel = mean of 5 bins)
        a_len, t_len = run_ours(binary, m, work, "lengyel", "average", True)
        t_len["dirs"] = DIRECTIONS
        # sweep at the same radius: all 32 azimuths for the timing, the channel azimuths
        # (reduce=point, as the reference) for its error
        sweep_rows = []
        if accepts_sweep(binary, work)[0]:
            _, t_sw32 = run_ours(binary, m, work, "sweep", "average", False)
            t_sw32["dirs"] = DIRECTIONS
            a_sw, t_sw = run_ours(binary, m, work, "sweep", "point", True)
            t_sw["dirs"] = 8
            sweep_rows = [
                ("horizon-bake `sweep`, 32 azimuths", "2", t_sw32, None, None,
                 "`--method sweep --radius unlimited --reduce average`: timing only"),
                ("horizon-bake `sweep`", "2", t_sw, stats(a_sw, ref, 0),
                 stats(a_sw, ref, args.margin),
                 "`--reduce point`: the channel azimuths, so Mtexel/s counts 8/32"),
            ]
        log("  GRASS r.horizon")
        a_gr, t_gr = run_grass(m, work)
        t_gr["dirs"] = DIRECTIONS
        log("  Whitebox horizon_angle")
        a_wb, t_wb = run_whitebox(m)
        t_wb["dirs"] = DIRECTIONS
        rows = [
            ("horizon-bake `exact`, 32 azimuths", "2", t_ex32, None, None,
             "`--reduce average`: every bin cast; timing only"),
            ("horizon-bake `exact` = reference", "2", t_ref, None, None,
             "`--reduce point`: casts only the 8 channel azimuths, so Mtexel/s counts 8/32"),
            *sweep_rows,
            ("horizon-bake `lengyel` (default)", "2", t_len,
             stats(a_len, ref, 0), stats(a_len, ref, args.margin),
             "R16 B32: channel = mean of 5 splatted bins"),
            ("GRASS `r.horizon`", "1", t_gr, stats(a_gr, ref, 0), stats(a_gr, ref, args.margin),
             "the r.horizon process: reads the map, writes 32 rasters"),
            ("Whitebox `horizon_angle`", f"{mach['nproc']} (max_procs {t_wb['max_procs']})", t_wb,
             stats(a_wb, ref, 0), stats(a_wb, ref, args.margin),
             "32 calls on a raster in memory"),
        ]
        spot = None
        if args.check:
            log("  brute-force march at random texels")
            models = [("horizon-bake `exact` (reference)", ref),
                      ("horizon-bake `lengyel`", a_len),
                      ("GRASS `r.horizon`", a_gr),
                      ("Whitebox `horizon_angle`", a_wb)]
            if sweep_rows:
                models.insert(1, ("horizon-bake `sweep`", a_sw))
            spot = spot_check(m, models, args.check, args.seed)
            worst = spot["horizon-bake `exact` (reference)"]["ch"][1]
            log(f"  reference vs march: worst {worst:.4f} deg")
            if worst > args.check_tol:
                sys.exit(f"{m.name}: the exact reference differs from a brute-force march by "
                         f"{worst:.3f} deg: an orientation or convention mismatch")
        results.append((m, rows, spot))
        log("\n" + table(m, rows))

    write_report(args, mach, vers, maps, results)
    log(f"wrote {args.out}")
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


def table(m, rows):
    out = ["| tool | threads | compute ms | wall ms | CPU ms | Mtexel/s @32 | Mtexel/CPU-s @32 | "
           "mean \\|Δα\\| ° | p99 \\|Δα\\| ° | bias ° | mean at 0/90/180/270 ° | "
           "mean at 45/135/225/315 ° | interior mean ° | note |",
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
           "| --- |"]
    for name, threads, tm, st, sti, note in rows:
        mtex = m.w * m.h * tm["dirs"] / DIRECTIONS / 1e6
        mts, mtc = mtex / tm["kernel"], mtex / tm["cpu"]
        if st is None:
            err = "— | — | — | — | — | —"
        else:
            err = (f"{st['mean']:.3f} | {st['p99']:.2f} | {st['bias']:+.3f} | {st['axis']:.3f} | "
                   f"{st['diag']:.3f} | {sti['mean']:.3f}")
        out.append(f"| {name} | {threads} | {tm['kernel'] * 1e3:,.0f} | {tm['wall'] * 1e3:,.0f} "
                   f"| {tm['cpu'] * 1e3:,.0f} | {mts:.3f} | {mtc:.3f} | {err} | {note} |")
    return "\n".join(out)


def spot_table(spot, n):
    out = [f"| tool | channel azimuths: mean ° | max ° | other 24 azimuths: mean ° | max ° |",
           "| --- | ---: | ---: | ---: | ---: |"]
    for name, g in spot.items():
        cells = []
        for k in ("ch", "other"):
            cells += ["—", "—"] if g.get(k) is None else [f"{g[k][0]:.3f}", f"{g[k][1]:.2f}"]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def write_report(args, mach, vers, maps, results):
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = [GENERATED_HEAD.format(
        date=now, nproc=mach["nproc"], cpu=mach["cpu"], simd=mach["simd"],
        python=mach["python"], kern=mach["kernel"], grass=vers["grass"], wb=vers["whitebox"],
        ours=vers["ours"], binnote=(" (" + args.bin_note + ")") if args.bin_note else "",
        numpy=vers["numpy"], margin=args.margin)]
    for m, rows, spot in results:
        L.append(f"### {m.name} ({m.w}×{m.h}): {m.desc}\n")
        L.append(f"PNG sha256 `{m.sha}…`; heights {float(m.heights.min()):.2f} to "
                 f"{float(m.heights.max()):.2f} texels (height_scale {m.scale:.6g}).\n")
        L.append(table(m, rows) + "\n")
        if spot:
            L.append(f"Against a brute-force march of the bilinear surface (0.0005-texel steps in the first 2 texels, 0.005 beyond, "
                     f"SPEC §3.2) at {args.check} random texels at the channel azimuths and "
                     f"{args.check} at the other 24 of the 32, |Δα| in degrees:\n")
            L.append(spot_table(spot, args.check) + "\n")
    body = "\n".join(L)
    old = open(args.out).read() if os.path.exists(args.out) else ""
    begin, end = "<!-- peers:begin -->", "<!-- peers:end -->"
    if begin in old and end in old:
        text = old[:old.index(begin) + len(begin)] + "\n" + body + "\n" + old[old.index(end):]
    else:
        text = DOC_HEAD + begin + "\n" + body + "\n" + end + "\n" + DOC_TAIL
    open(args.out, "w").write(text)


GENERATED_HEAD = """## Results (generated)

Generated {date} by `python3 scripts/peers.py`: one run, on a **shared, noisy** machine (other
builds were running; times move by ±30% or more between runs). {nproc} cores (`nproc`), {cpu}
({simd}), Linux {kern}, Python {python}, numpy {numpy}. Tools: {grass}; {wb}; {ours}{binnote}.

Columns: *compute ms*: each tool's own computation (ours: `timings_ms.bake` from `bake.json`, the
kernel without PNG decode and EXR encode; GRASS: the `r.horizon` process, which also reads the map
and writes its 32 rasters; Whitebox: the 32 `horizon_angle` calls on a raster already in memory).
*wall ms*: ours as a whole process (start, decode, bake, encode), the same span as compute for the
peers. *CPU ms*: user + system time of the wall span (CPU/wall shows how many cores a tool kept
busy). *Mtexel/s @32* = texels × directions / 32 / compute time: every tool ran at 32 azimuths
except the `--reduce point` reference, which casts 8 and so counts as 8/32 of its texels.
*Mtexel/CPU-s @32*: the same texels over the CPU time of the wall span (for ours that span
includes process start, decode and encode, so it is a lower bound of the kernel's); it moves less
than wall time when other work shares the machine.
Errors: |Δα| in degrees against the reference (`--method exact --radius unlimited --reduce point
--edge none`, α = asin s) at the 8 channel azimuths 0°, 45°, …, 315°, over all texels; *bias* is
the signed mean (positive = the tool's horizon is higher); the two next columns split the mean
between the axis-aligned and the diagonal channel azimuths; *interior* leaves out the {margin}
texels nearest the border.
"""

DOC_HEAD = """# horizon-bake and the GIS peers

How the exact and the default horizon kernels compare, in time and in horizon angle, with the two
open-source GIS tools that compute the same quantity today: GRASS GIS `r.horizon` and Whitebox
Workflows `horizon_angle`. Same maps, same surface in the same units, same azimuths, one run.
The block between the `peers:begin` / `peers:end` markers is generated by the script; the rest of
this file is prose and is kept when the script rewrites the block.

## Run it

```sh
cargo build --release                 # the script uses target/release/horizon-bake (else target/debug)
python3 scripts/peers.py              # rewrites the generated block of docs/peers.md
python3 scripts/peers.py --bin PATH --out /tmp/peers.md --work /tmp/peers-work   # other binary, keep files
python3 scripts/peers.py --terrain-only --terrain-size 2048   # only the terrain products (issue 24)
```

The terrain comparison (`--terrain` adds it to a full run, `--terrain-only` runs it alone and
keeps the other block) reads R terra's `elev.tif` (from `$HB_ELEV_TIF`, or `apt-get download
r-cran-terra`), needs `rasterio` (pip) and writes its own block between the `peers-terrain`
markers. At 2048² × 32 azimuths the peers take most of half an hour on 2 cores (Whitebox
`horizon_angle` the longest); `--terrain-size 1024` is four times quicker.

It installs what is missing: numpy, pillow, tifffile, OpenEXR and whitebox-workflows with `pip`,
and GRASS GIS with `apt-get install grass-core` (as root; a few minutes the first time). Nothing
else is downloaded: GRASS runs headless in a temporary location (`grass --tmp-location EPSG:32616
--exec ...`), Whitebox runs in-process. A run takes about 2–3 minutes on 2 cores, almost all of
it in the peers on the 512² map. `--size`, `--seed` and `--fbm-scale` change the synthetic map,
`--check N` the number of brute-force spot checks, `--margin` the border left out of the
*interior* columns.

## What runs

- **Maps.** `docs/corpus/jacksboro_128.png`, the real-terrain excerpt of the eval (USGS DEM,
  ≈90 m per texel, `height_scale` 65535/90 so that heights in texels = metres / 90, 6 texels of
  relief), and a spectral fBm generated by the script (numpy `default_rng(seed)`, power spectrum
  ∝ 1/f³, i.e. Hurst 0.5, 512², normalised to [0,1], stored as 16-bit PNG, `height_scale` 24:
  median slope ≈ 24°, 99th percentile ≈ 49°). horizon-bake reads the PNG; the peers read a
  float32 GeoTIFF of the *same* heights in texels (PNG value / 65535 × height_scale, computed in
  f32 as the crate does), north up, cell size 1 (ModelPixelScale 1, tie point at (0, H), UTM 16N
  metres). So one height unit = one cell = one texel for every tool.
- **Reference**: `horizon-bake bake MAP -o DIR --method exact --radius unlimited --bins 32
  --reduce point --edge none --format exr --height-scale S`: sin α at φ = 0°, 45°, …, 315° in
  `horizon_0.exr` (channels 0..3 in R,G,B,A) and `horizon_1.exr` (4..7), f32; α = asin(s).
  It is SPEC §3.2 (the line-of-sight horizon on the bilinear surface through the texel centres).
  The script does not take that on trust: it re-derives α by a brute-force march of the bilinear
  surface (0.0005-texel steps in the first 2 texels, 0.005 beyond) at random texels and stops if
  the reference is more than 0.25° off, which is what a wrong axis or azimuth convention would give.
- **Timing at 32 azimuths for everyone.** `--reduce point` casts only the 8 channel azimuths,
  so the same exact kernel is also run with `--reduce average` (all 32 bins cast) for the time.
  `--method lengyel` (the default model, R16 B32) runs on the same map. GRASS runs
  `r.horizon -d step=11.25 start=0 end=360` (32 maps), Whitebox 32 `horizon_angle` calls.
- **Errors** at the 8 channel azimuths, over all texels and over the interior, and a spot check of
  every tool at the other 24 azimuths against the brute-force march (the reference only has the
  channel azimuths).

## Conventions mapped

| | horizon-bake | GRASS `r.horizon` | Whitebox `horizon_angle` |
| --- | --- | --- | --- |
| azimuth | φ from +x (image right) toward +y (image top with `y_axis=up`, the default); channel c at c·45° | `direction`/`start`/`step` in degrees counter-clockwise from east (`-c` would switch to compass; not used) | `azimuth` in degrees clockwise from north |
| mapping | φ | φ (north = top of a north-up raster = our +y, east = +x) | (90° − φ) mod 360° |
| output | sin α in [0,1] (clamped at 0) | horizon angle, radians by default, degrees with `-d` (used); negative below the horizontal, −90° where the ray leaves the map at once | horizon angle in degrees; negative below the horizontal ("exposed"), 0 where the ray leaves the map at once |
| to compare | α = asin(s) | max(angle, 0) | max(angle, 0) |
| units | heights in texels = value × height_scale, 1 texel apart | cell size 1 m, heights in m: the same numbers | cell size 1, heights in the same unit |
| radius | `--radius unlimited`: to the edge of the map | `maxdistance` = ⌈√(W²+H²)⌉+1 (past every cell); `distance` (step coefficient) 1.0, the default | `max_dist` unset: each ray to the edge of the DEM |
| border | `--edge none`: nothing outside occludes; rays end at the last texel centres | the region is the map, no `bufferzone`: rays end at the map edge | rays end at the DEM edge |
| sampling | exact maximum over the bilinear surface between the texel centres | steps of `distance` × cell size along the ray; at each step the height of the cell the point falls in, at the distance of that cell's centre (no interpolation); subtracts the Earth-curvature drop L²/2R | every crossing of the ray with a grid line through the cell centres, height interpolated linearly along that line (its manual: "each location in which the DEM grid is intersected by the ray") |

Consequences worth knowing when reading the numbers:

- At 0°, 90°, 180°, 270° the three surfaces coincide along the ray: it runs along a row or a
  column of texel centres, where the bilinear surface is linear between centres, so the maximum
  slope is reached at a centre, which both peers sample. Any difference there is the border or the
  near field.
- At 45°, 135°, 225°, 315° the ray passes through the diagonal texel centres, and both peers
  sample essentially only those (every grid-line crossing of a diagonal is a centre). The bilinear
  surface between two diagonal centres is a parabola that rises above their chord when the two
  off-diagonal neighbours are high (its midpoint is the mean of the four corners), so the peers
  miss that rise and read the horizon *lower* than SPEC §3.2, most of all in the near field, where
  one high neighbour dominates. Measured: all of the peers' error at the channel azimuths is at the
  diagonals (the axis-aligned column is 0.000). There GRASS and Whitebox also differ slightly from
  each other (mean 0.01–0.08°, GRASS mostly higher): its nearest-cell steps do not always land on
  the diagonal centres, and a step up to one cell past the left or bottom border still reads the
  border cell (`(int)` truncates a negative index toward zero).
- At the other azimuths GRASS snaps each step to a cell while Whitebox interpolates: the spot-check
  table shows what that costs.
- GRASS writes −90° on border texels that look straight out of the map; Whitebox writes 0;
  SPEC's `edge=none` gives α = 0 there too, and after clamping at 0 the three agree. Both peers
  can read a little past the border on a diagonal ray (see above), which the *interior* column
  leaves out.
- GRASS `r.horizon` refuses an XY (unprojected) location ("Can't get projection info of current
  location"); hence the temporary UTM 16N location and `r.in.gdal -o`. r.horizon turns each
  azimuth into a grid direction through the projection (true north), and subtracts the Earth's
  curvature (drop L²/2R, R ≈ 6371 km). The GeoTIFF puts the map at northings 0..H, on the
  equator, where UTM's grid convergence is zero, so the directions are the grid's; and with 1 m
  cells the curvature drop is at most 0.04 texel at 725 texels, ~0.003° of elevation. Measured: at
  the axis-aligned azimuths GRASS and Whitebox (which corrects neither) agree to ~1e-4° on
  average, and moving the map to UTM's central meridian changes GRASS's 45° map on <0.1% of
  texels.
- Threads: horizon-bake uses a rayon pool of `nproc` threads; `r.horizon` in GRASS 8.2 has no
  threads option (one core); Whitebox's `max_procs` is −1 (all cores). The CPU column shows what
  each actually used.

"""

DOC_TAIL = """
## Reading

(written by hand after a run; see the tables above)
"""


if __name__ == "__main__":
    main()
