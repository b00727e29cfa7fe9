#!/usr/bin/env python3
"""Issue 24: a real DEM nobody in this project made, read and checked by GDAL (rasterio).

The DEM is R `terra`'s `ex/elev.tif` (SRTM-derived, int16, EPSG:4326, nodata -32768; GPL-3+, so
it is not copied into this repository): taken from $HB_ELEV_TIF, or extracted from the Debian
package r-cran-terra (`apt-get download` + `dpkg-deb -x`, no install). A float32 UTM version with
nodata -9999 is made here with rasterio.warp.reproject.

Checks, each against something we did not write (GDAL, pvlib's SPA, numpy references):
- refusals (exit 2, one line naming the fix): geographic CRS without cell_size, rotated grid,
  non-square cells, all-nodata map, NaN without nodata, ZSTD compression;
- GDAL reads angles.tif and svf.tif with the input's CRS, transform and nodata, one band per bin;
- every hole of the input is nodata in every output, and no valid texel is;
- `exact` angles match an independent bilinear line-of-sight written here (numpy, with the
  earth-curvature drop) within 0.01 degrees, and the SVF matches mean cos^2 of those angles;
- `azimuth_from=north_cw` renumbers the same rays; bake.json carries the georeferencing;
- `svf_model=tilted` is Dozier & Frew's equation for a slope, computed here with numpy from
  angles.tif and the DEM's central differences, within 1e-4;
- `horizon_distance` is the reference ray's arg max (95 % of the rays within one cell);
- positive and negative openness within 2 km match the signed reference ray within 0.01 deg.

Usage: check_dem.py HORIZON_BAKE_BINARY WORKDIR
"""
import glob
import json
import math
import os
import subprocess
import sys
import tempfile

import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.warp import Resampling, calculate_default_transform, reproject

BIN, WORK = sys.argv[1], sys.argv[2]
os.makedirs(WORK, exist_ok=True)
R_E = 6371000.0
failures = []


def check(cond, what):
    print(("ok   " if cond else "FAIL ") + what)
    if not cond:
        failures.append(what)


def run(*args):
    p = subprocess.run([BIN, *args], capture_output=True, text=True)
    return p.returncode, p.stderr.strip()


def elev_tif():
    if os.environ.get("HB_ELEV_TIF"):
        return os.environ["HB_ELEV_TIF"]
    d = os.path.join(WORK, "terra")
    found = glob.glob(os.path.join(d, "**", "ex", "elev.tif"), recursive=True)
    if found:
        return found[0]
    os.makedirs(d, exist_ok=True)
    subprocess.run(["apt-get", "download", "r-cran-terra"], cwd=d, check=True,
                   capture_output=True)
    deb = glob.glob(os.path.join(d, "r-cran-terra_*.deb"))[0]
    subprocess.run(["dpkg-deb", "-x", deb, os.path.join(d, "x")], check=True)
    return glob.glob(os.path.join(d, "**", "ex", "elev.tif"), recursive=True)[0]


SRC = elev_tif()
with rasterio.open(SRC) as s:
    check(s.crs.to_epsg() == 4326 and s.dtypes[0] == "int16" and s.nodata == -32768,
          "elev.tif is int16 EPSG:4326 with nodata -32768")
    src_arr = s.read(1)
    src_profile = s.profile

# --- a float32 UTM version (EPSG:32632, 250 m, nodata -9999) ---
UTM = os.path.join(WORK, "elev_utm.tif")
with rasterio.open(SRC) as s:
    dst_crs = "EPSG:32632"
    tr, w, h = calculate_default_transform(s.crs, dst_crs, s.width, s.height, *s.bounds,
                                          resolution=250.0)
    dst = np.full((h, w), -9999.0, dtype=np.float32)
    reproject(src_arr.astype(np.float32), dst, src_transform=s.transform, src_crs=s.crs,
              src_nodata=-32768, dst_transform=tr, dst_crs=dst_crs, dst_nodata=-9999,
              resampling=Resampling.bilinear)
    prof = dict(driver="GTiff", dtype="float32", width=w, height=h, count=1, crs=dst_crs,
                transform=tr, nodata=-9999, compress="deflate")
    with rasterio.open(UTM, "w", **prof) as d:
        d.write(dst, 1)
print(f"UTM DEM {w}x{h}, {np.mean(dst == -9999):.0%} nodata")


def write(path, arr, **kw):
    prof = dict(driver="GTiff", dtype=str(arr.dtype), width=arr.shape[1], height=arr.shape[0],
                count=1)
    prof.update(kw)
    with rasterio.open(path, "w", **prof) as d:
        d.write(arr, 1)
    return path


def refused(path, words, *extra):
    code, err = run("bake", path, "-o", os.path.join(WORK, "refused"), "--format", "geotiff",
                    "--outputs", "angles,svf", "--method", "exact", *extra)
    ok = code == 2 and all(w.lower() in err.lower() for w in words) and "\n" not in err
    check(ok, f"refused {os.path.basename(path)} (exit {code}): {err[:160]}")


# --- refusals ---
refused(SRC, ["EPSG:4326", "gdalwarp", "cell_size"])
small = np.arange(64, dtype=np.float32).reshape(8, 8)
rot = Affine(100.0, 20.0, 500000.0, 20.0, -100.0, 5500000.0)
refused(write(os.path.join(WORK, "rotated.tif"), small, crs="EPSG:32632", transform=rot),
        ["rotated", "gdalwarp"])
nsq = Affine(100.0, 0.0, 500000.0, 0.0, -50.0, 5500000.0)
refused(write(os.path.join(WORK, "nonsquare.tif"), small, crs="EPSG:32632", transform=nsq),
        ["not square", "gdalwarp -tr"])
sq = Affine(100.0, 0.0, 500000.0, 0.0, -100.0, 5500000.0)
refused(write(os.path.join(WORK, "allnodata.tif"), np.full((8, 8), -9999, np.float32),
              crs="EPSG:32632", transform=sq, nodata=-9999), ["every texel is nodata"])
withnan = small.copy()
withnan[3, 4] = np.nan
refused(write(os.path.join(WORK, "nan.tif"), withnan, crs="EPSG:32632", transform=sq),
        ["nan", "nodata=nan"])
refused(write(os.path.join(WORK, "zstd.tif"), small, crs="EPSG:32632", transform=sq,
              compress="zstd"), ["ZSTD", "gdal_translate"])
# With cell_size, the geographic DEM bakes (cell_size overrides the georeferencing).
code, err = run("bake", SRC, "-o", os.path.join(WORK, "geo"), "--format", "geotiff",
                "--outputs", "svf", "--method", "exact", "--radius", "unlimited",
                "--cell-size", "750")
check(code == 0, f"elev.tif bakes with --cell-size 750 (exit {code} {err[:200]})")
check("0.64" in err and "as wide as" in err and "gdalwarp -t_srs" in err,
      f"... with a warning that its cells are cos(49.7 deg) = 0.64x as wide as tall ({err[:200]})")
if code == 0:
    with rasterio.open(os.path.join(WORK, "geo", "svf.tif")) as o, rasterio.open(SRC) as s:
        check(o.crs == s.crs and o.transform.almost_equals(s.transform, 1e-12),
              "svf.tif of elev.tif keeps EPSG:4326 and its transform")
        v = o.read(1)
        check(o.nodata == -32768 and np.all((v == -32768) == (src_arr == -32768)),
              "svf.tif of elev.tif: nodata -32768 exactly at the input's holes")

# --- the UTM DEM, DEM defaults (cell size, height_scale, edge=none, curvature on) ---
BINS = 32
OUT = os.path.join(WORK, "utm")
code, err = run("bake", UTM, "-o", OUT, "--format", "geotiff", "--outputs", "angles,svf",
                "--method", "exact", "--radius", "unlimited", "--bins", str(BINS))
check(code == 0, f"UTM DEM bakes with the DEM defaults (exit {code} {err[:200]})")
if code != 0:
    sys.exit(1)
bake = json.load(open(os.path.join(OUT, "bake.json")))
p = bake["params"]
check(p["cell_size"] == 250.0 and abs(p["height_scale"] - 1 / 250) < 1e-15
      and p["edge"] == "none" and p["earth_curvature"] == "on",
      f"DEM defaults resolved: cell_size {p['cell_size']}, height_scale {p['height_scale']}, "
      f"edge {p['edge']}, curvature {p['earth_curvature']}")
g = bake.get("georeferencing") or {}
check(g.get("epsg") == 32632 and g.get("units") == "metre"
      and np.allclose(g.get("transform"), list(tr.to_gdal()), rtol=0, atol=1e-6),
      f"bake.json georeferencing {g}")
check(len(bake["products"]["angles.tif"]["bands"]) == BINS, "bake.json lists 32 angle bands")
fmts = bake["output"]["formats"]
check(fmts["geotiff"] is True and not any(fmts[k] for k in ("png8", "png16", "exr", "ktx2", "dds")),
      f"bake.json formats say what a GeoTIFF-only bake wrote: {fmts}")

with rasterio.open(UTM) as s:
    dem = s.read(1).astype(np.float64)
    crs, transform = s.crs, s.transform
holes = dem == -9999
with rasterio.open(os.path.join(OUT, "angles.tif")) as a:
    check(a.count == BINS and a.dtypes[0] == "float32", "angles.tif: 32 float32 bands")
    check(a.crs == crs and a.transform.almost_equals(transform, 1e-9),
          f"angles.tif CRS {a.crs} and transform as the input's")
    check(a.nodata == -9999, f"angles.tif nodata {a.nodata}")
    check(a.profile.get("tiled") and a.block_shapes[0] == (512, 512)
          and a.profile.get("compress", "").lower() == "deflate"
          and a.tags(ns="IMAGE_STRUCTURE").get("PREDICTOR") == "3",
          f"angles.tif tiled 512, DEFLATE, predictor 3 ({a.profile.get('compress')}, "
          f"{a.tags(ns='IMAGE_STRUCTURE')})")
    ang = a.read().astype(np.float64)
    descr = a.descriptions
check(descr[1] is not None and "azimuth 11.25" in descr[1], f"band 2 described: {descr[1]}")
with rasterio.open(os.path.join(OUT, "svf.tif")) as o:
    check(o.crs == crs and o.transform.almost_equals(transform, 1e-9) and o.nodata == -9999,
          "svf.tif CRS, transform and nodata as the input's")
    svf = o.read(1).astype(np.float64)
check(np.all(ang[:, holes] == -9999) and np.all(svf[holes] == -9999),
      "every hole is nodata in every band")
check(np.all(ang[:, ~holes] >= 0) and np.all(ang[:, ~holes] <= 90)
      and np.all((svf[~holes] >= 0) & (svf[~holes] <= 1)), "no valid texel is nodata")

# --- SPEC 2: without --method and --radius a DEM is baked by a line of sight to the edge ---
OUTD = os.path.join(WORK, "utm_defaults")
code, err = run("bake", UTM, "-o", OUTD, "--format", "geotiff", "--outputs", "angles,svf",
                "--bins", str(BINS))
check(code == 0, f"UTM DEM bakes without --method (exit {code} {err[:200]})")
if code == 0:
    pd = json.load(open(os.path.join(OUTD, "bake.json")))["params"]
    check(pd["method"] == "sweep" and pd["radius"] == "unlimited"
          and pd["earth_curvature"] == "on",
          f"a DEM without --method: sweep, radius unlimited, curvature on "
          f"({pd['method']}, {pd['radius']}, {pd['earth_curvature']})")
    with rasterio.open(os.path.join(OUTD, "angles.tif")) as a:
        dflt = a.read().astype(np.float64)
    d = np.abs(dflt[:, ~holes] - ang[:, ~holes])
    print(f"DEM defaults (sweep, unlimited) vs exact unlimited: mean |d| {d.mean():.5f} deg, "
          f"p99 {np.percentile(d, 99):.5f}, max {d.max():.4f}")
    check(np.all(dflt[:, holes] == -9999) and d.mean() <= 0.05 and np.percentile(d, 99) <= 0.25,
          "the default bake is within sweep's tolerance of exact at unlimited radius "
          "(not lengyel at 16 texels)")
# ... and --bins 36 (not a multiple of 16) is taken for the terrain products, as for any ray method.
code, err = run("bake", UTM, "-o", os.path.join(WORK, "utm_b36"), "--format", "geotiff",
                "--outputs", "angles", "--bins", "36")
check(code == 0, f"a DEM without --method takes --bins 36 for angles (exit {code} {err[:200]})")

# --- issue 41 item 2: `sweep` streams `angles` band by band, so 720 bins fit at a size whose
# W*H*bins passes the 2^28 values a file held whole takes (`exact` still refuses there) ---
FINE = os.path.join(WORK, "elev_utm_90.tif")
with rasterio.open(SRC) as s:
    trf, wf, hf = calculate_default_transform(s.crs, "EPSG:32632", s.width, s.height, *s.bounds,
                                             resolution=90.0)
    fine = np.full((hf, wf), -9999.0, dtype=np.float32)
    reproject(src_arr.astype(np.float32), fine, src_transform=s.transform, src_crs=s.crs,
              src_nodata=-32768, dst_transform=trf, dst_crs="EPSG:32632", dst_nodata=-9999,
              resampling=Resampling.bilinear)
write(FINE, fine, crs="EPSG:32632", transform=trf, nodata=-9999)
fine_holes = fine == -9999
check(wf * hf * 720 > 1 << 28, f"the 90 m DEM ({wf}x{hf}) at 720 bins passes 2^28 values")
code, err = run("bake", FINE, "-o", os.path.join(WORK, "a720"), "--format", "geotiff",
                "--outputs", "angles", "--method", "sweep", "--bins", "720")
check(code == 0, f"sweep bakes 720 angle bands of {wf}x{hf} (exit {code} {err[:200]})")
code16, err16 = run("bake", FINE, "-o", os.path.join(WORK, "a16"), "--format", "geotiff",
                    "--outputs", "angles", "--method", "sweep", "--bins", "16")
if code == 0 and code16 == 0:
    with rasterio.open(os.path.join(WORK, "a720", "angles.tif")) as a, \
            rasterio.open(os.path.join(WORK, "a16", "angles.tif")) as b:
        check(a.count == 720 and a.crs == b.crs and a.transform.almost_equals(trf, 1e-9)
              and a.nodata == -9999, f"GDAL reads 720 bands with the DEM's CRS and nodata "
                                     f"({a.count}, {a.crs}, {a.nodata})")
        worst, holes_ok = 0.0, True
        for k in range(16):
            x, y = a.read(k * 45 + 1).astype(np.float64), b.read(k + 1).astype(np.float64)
            holes_ok &= bool(np.all(x[fine_holes] == -9999) and np.all(x[~fine_holes] >= 0))
            worst = max(worst, float(np.abs(x - y).max()))
    # The same azimuths, up to the last bit of n * 2pi / bins.
    check(worst < 1e-4, f"every 45th of 720 bands is the 16-bin bake's band (max |d| {worst:.2e} deg)")
    check(holes_ok, "the 720-bin bands are nodata exactly at the holes")
code, err = run("bake", FINE, "-o", os.path.join(WORK, "a720x"), "--format", "geotiff",
                "--outputs", "angles", "--method", "exact", "--bins", "720")
check(code == 2 and "bins" in err and "limit" in err,
      f"exact, which holds the file whole, refuses 720 bins there naming bins ({err[:160]})")
# Bands streamed out of their order: compass bands of grid north (a plain TIFF with --cell-size)
# come bin after bin, band n from bin (bins/4 - n) mod bins; GDAL reads them where the IFD says.
PLAIN = write(os.path.join(WORK, "plain_90.tif"), np.where(fine_holes, -9999.0, fine).astype(np.float32))
common = ["--format", "geotiff", "--outputs", "angles", "--method", "sweep", "--bins", "16",
          "--cell-size", "90", "--height-scale", repr(1 / 90), "--nodata", "-9999",
          "--edge", "none", "--radius", "unlimited"]
c1, e1 = run("bake", PLAIN, "-o", os.path.join(WORK, "p_east"), *common)
c2, e2 = run("bake", PLAIN, "-o", os.path.join(WORK, "p_north"), *common, "--azimuth-from", "north_cw")
check(c1 == 0 and c2 == 0, f"a plain TIFF with --cell-size bakes both ways ({e1[:120]} {e2[:120]})")
if c1 == 0 and c2 == 0:
    with rasterio.open(os.path.join(WORK, "p_east", "angles.tif")) as a, \
            rasterio.open(os.path.join(WORK, "p_north", "angles.tif")) as b:
        same = all(np.array_equal(b.read(n + 1), a.read((4 - n) % 16 + 1)) for n in range(16))
    check(same, "north_cw band n is east_ccw band (4 - n) mod 16, bit for bit, as GDAL reads them")

# --- SPEC 2 "Units of a DEM": values that are not heights in the map unit are never baked
# as if they were: a GDAL band scale, heights in feet over metre cells (a compound CRS), a
# transform without a CRS. Each is refused naming the fix; the fix given is right. ---
r0, c0 = dem.shape[0] // 2 - 32, dem.shape[1] // 2 - 32
piece = dem[r0:r0 + 64, c0:c0 + 64].astype(np.float32)
piece[piece == -9999] = 0
ptr = tr * Affine.translation(c0, r0)
SCALED = os.path.join(WORK, "scaled.tif")
with rasterio.open(SCALED, "w", driver="GTiff", dtype="float32", width=64, height=64, count=1,
                   crs="EPSG:32632", transform=ptr) as d:
    d.write(piece / 0.2, 1)
    d.scales = (0.2,)
    d.offsets = (10.0,)
refused(SCALED, ["GDAL scale of 0.2", "gdal_translate -unscale", "height_scale=0.0008"])
PLAIN = write(os.path.join(WORK, "unscaled.tif"), piece, crs="EPSG:32632", transform=ptr)
FEET = os.path.join(WORK, "feet.tif")
with rasterio.open(FEET, "w", driver="GTiff", dtype="float32", width=64, height=64, count=1,
                   crs="EPSG:2056+8228", transform=ptr) as d:
    d.write(piece / 0.3048, 1)
refused(FEET, ["in foot", "gdal_calc.py", "A*0.3048"])
NOCRS = write(os.path.join(WORK, "nocrs.tif"), piece, transform=ptr)
refused(NOCRS, ["no CRS", "cell_size", "250", "gdal_edit.py -a_srs"])


def angles_of(path, name, *extra):
    out = os.path.join(WORK, name)
    code, err = run("bake", path, "-o", out, "--format", "geotiff", "--outputs", "angles",
                    "--method", "exact", "--radius", "unlimited", "--bins", "16",
                    "--earth-curvature", "off", *extra)
    check(code == 0, f"{name} bakes (exit {code} {err[:200]})")
    with rasterio.open(os.path.join(out, "angles.tif")) as a:
        return a.read().astype(np.float64), json.load(open(os.path.join(out, "bake.json")))


want, _ = angles_of(PLAIN, "u_plain")
got, _ = angles_of(SCALED, "u_scaled", "--height-scale", str(0.2 / 250))
check(np.abs(got - want).max() < 1e-3,
      f"a scaled band with the height_scale the refusal names = the unscaled DEM "
      f"(max {np.abs(got - want).max():.2e} deg)")
got, _ = angles_of(FEET, "u_feet", "--height-scale", str(0.3048 / 250))
check(np.abs(got - want).max() < 1e-3,
      f"heights in feet with the height_scale the refusal names = the metre DEM "
      f"(max {np.abs(got - want).max():.2e} deg)")
got, b = angles_of(NOCRS, "u_nocrs", "--cell-size", "250")
check(np.abs(got - want).max() < 1e-9 and b["params"]["edge"] == "none"
      and abs(b["params"]["height_scale"] - 1 / 250) < 1e-15,
      "a transform without a CRS and --cell-size bakes as the DEM it is (edge none, 1/cell)")
# A CRS in US survey feet (heights in the same unit): the curvature drop is computed in metres
# (before, d^2/(2 R_e) took feet for metres: 3.28x the drop).
FT = 1200.0 / 3937.0
USFT = os.path.join(WORK, "usft.tif")
with rasterio.open(USFT, "w", driver="GTiff", dtype="float32", width=64, height=64, count=1,
                   crs="EPSG:2227", transform=Affine(250 / FT, 0, 6e6, 0, -250 / FT, 2e6)) as d:
    d.write((piece / FT).astype(np.float32), 1)


def curved_angles(path, name):
    out = os.path.join(WORK, name)
    code, err = run("bake", path, "-o", out, "--format", "geotiff", "--outputs", "angles",
                    "--method", "exact", "--radius", "unlimited", "--bins", "16")
    check(code == 0, f"{name} bakes with the drop (exit {code} {err[:200]})")
    with rasterio.open(os.path.join(out, "angles.tif")) as a:
        return a.read().astype(np.float64), json.load(open(os.path.join(out, "bake.json")))


m_curved, _ = curved_angles(PLAIN, "c_metre")
f_curved, bf = curved_angles(USFT, "c_usft")
drop = np.abs(m_curved - want).max()
off = np.abs(f_curved - m_curved).max()
check(bf["georeferencing"]["units"] == "us_survey_foot" and bf["params"]["earth_curvature"] == "on",
      f"EPSG:2227 is read in US survey feet ({bf['georeferencing']['units']})")
check(drop > 0.01 and off < 1e-3,
      f"in US survey feet the drop is the metre DEM's: max {off:.2e} deg apart (the drop "
      f"itself moves angles by up to {drop:.3f} deg)")

# Several bands: heights are one of them, named by --band; without it, refused naming band
# (before: band 1 read as grey, band 2 as alpha). Band-interleaved files name their rewrite.
two = np.stack([np.full_like(piece, 7.0), piece])
for inter in ("pixel", "band"):
    path = os.path.join(WORK, f"two_{inter}.tif")
    with rasterio.open(path, "w", driver="GTiff", dtype="float32", width=64, height=64, count=2,
                       crs="EPSG:32632", transform=ptr, interleave=inter) as d:
        d.write(two)
    if inter == "pixel":
        refused(path, ["2 bands", "band=1..2", "gdal_translate -b 1"])
        got, _ = angles_of(path, "u_band2", "--band", "2")
        check(np.abs(got - want).max() < 1e-9, "--band 2 reads the heights of band 2 exactly")
        refused(path, ["band 3", "2 bands"], "--band", "3")
    else:
        refused(path, ["separate colour planes", "INTERLEAVE=PIXEL"])
# An undeclared -9999 on the border (a warp without -dstnodata) is baked as a height, with a
# warning naming --nodata; declared, no warning.
edged = piece.copy()
edged[:, :3] = -9999
UNDECL = write(os.path.join(WORK, "undeclared.tif"), edged, crs="EPSG:32632", transform=ptr)
code, err = run("bake", UNDECL, "-o", os.path.join(WORK, "u_undecl"), "--format", "geotiff",
                "--outputs", "svf", "--method", "exact", "--radius", "8")
check(code == 0 and "warning" in err and "--nodata -9999" in err,
      f"an undeclared -9999 on the border is warned about, naming --nodata ({err[:200]})")
code, err = run("bake", UNDECL, "-o", os.path.join(WORK, "u_decl"), "--format", "geotiff",
                "--outputs", "svf", "--method", "exact", "--radius", "8", "--nodata", "-9999")
check(code == 0 and "warning" not in err, f"declared, no warning ({err[:200]})")
code, err = run("bake", SCALED, "-o", os.path.join(WORK, "u_curved"), "--format", "geotiff",
                "--outputs", "angles", "--method", "exact", "--height-scale", "0.0008")
check(code == 2 and "earth_curvature" in err, f"a read scale with the drop on is refused ({err[:160]})")

# --- the independent reference: bilinear line of sight in metres, curvature drop, holes ---
H, W = dem.shape
cell = 250.0
# Cells (i, j) = square between texel centres (i..i+1, j..j+1), closed; not surface if a corner
# is a hole.
bad = holes[:-1, :-1] | holes[1:, :-1] | holes[:-1, 1:] | holes[1:, 1:]


def horizon_deg(col, row, phi, curvature=True, radius=math.inf, distance=False, signed=False,
                surface=None):
    dx, dy = math.cos(phi), -math.sin(phi)  # y up = north = toward row 0
    if abs(dx) < 1e-12:
        dx = 0.0
    if abs(dy) < 1e-12:
        dy = 0.0

    def to_edge(p, d, last):
        return (last - p) / d if d > 0 else (p / -d if d < 0 else math.inf)

    s_end = min(to_edge(col, dx, W - 1), to_edge(row, dy, H - 1), radius)
    if s_end <= 0:
        return None if signed else ((0.0, 0.0) if distance else 0.0)
    z_ = dem if surface is None else surface
    h0 = z_[row, col]

    def ratio(s):
        x, y = col + s * dx, row + s * dy
        i = np.clip(np.floor(x).astype(int), 0, W - 2)
        j = np.clip(np.floor(y).astype(int), 0, H - 2)
        fx, fy = x - i, y - j
        z = (z_[j, i] * (1 - fx) * (1 - fy) + z_[j, i + 1] * fx * (1 - fy)
             + z_[j + 1, i] * (1 - fx) * fy + z_[j + 1, i + 1] * fx * fy)
        d = s * cell
        r = (z - h0 - (d * d / (2 * R_E) if curvature else 0.0)) / d
        # On a grid line the point is on the edge of the cells on both sides: surface if
        # either has no hole corner (a ray along a row or column beside a hole).
        on_x, on_y = (fx == 0) & (i > 0), (fy == 0) & (j > 0)
        i1, j1 = np.maximum(i - 1, 0), np.maximum(j - 1, 0)
        no = (bad[j, i] & (~on_x | bad[j, i1]) & (~on_y | bad[j1, i])
              & (~(on_x & on_y) | bad[j1, i1]))
        return np.where(no, -np.inf, r)

    s = np.arange(1, int(s_end / 0.02) + 1) * 0.02
    s = np.append(s[s < s_end], s_end)
    r = ratio(s)
    k = int(np.argmax(r))
    best = r[k]
    # Refine around the best sample (the ratio is smooth there).
    lo, hi = max(s[k] - 0.03, 1e-6), min(s[k] + 0.03, s_end)
    fine = np.linspace(lo, hi, 601)
    rf = ratio(fine)
    at = s[k]
    if float(np.max(rf)) > best:
        best, at = float(np.max(rf)), float(fine[int(np.argmax(rf))])
    if signed:  # a ray that meets no surface (holes only) has no beta
        return math.degrees(math.atan(best)) if np.isfinite(best) else None
    deg = math.degrees(math.atan(max(best, 0.0)))
    if distance:
        return deg, (at * cell if best > 0 else 0.0)
    return deg


# True azimuths (compass bands, every sun) through GDAL's projection (PROJ), not ours: the
# texel centre to longitude/latitude, a 10 m step along azimuth theta on the WGS84 ellipsoid
# (meridional and prime-vertical radii), back to the map; phi is that step's direction from
# the grid's x axis (y north = up the image).
from rasterio.warp import transform as warp_points  # noqa: E402

A_WGS, E2_WGS = 6378137.0, 0.00669437999014


def true_phi(col, row, theta_deg):
    x = transform.c + (col + 0.5) * transform.a
    y = transform.f + (row + 0.5) * transform.e
    (lon,), (lat,) = warp_points(crs, "EPSG:4326", [x], [y])
    sl = math.sin(math.radians(lat))
    w_ = math.sqrt(1 - E2_WGS * sl * sl)
    m_r, n_r = A_WGS * (1 - E2_WGS) / w_ ** 3, A_WGS / w_
    th = math.radians(theta_deg)
    lat2 = lat + math.degrees(10.0 * math.cos(th) / m_r)
    lon2 = lon + math.degrees(10.0 * math.sin(th) / (n_r * math.cos(math.radians(lat))))
    (x2,), (y2,) = warp_points("EPSG:4326", crs, [lon2], [lat2])
    return math.atan2(y2 - y, x2 - x)


rng = np.random.default_rng(24)
valid = np.argwhere(~holes)
pick = valid[rng.choice(len(valid), 120, replace=False)]
errs = []
svf_errs = []
for row, col in pick:
    ref = np.array([horizon_deg(col, row, 2 * math.pi * n / BINS) for n in range(BINS)])
    errs.append(np.abs(ang[:, row, col] - ref))
    ref_svf = np.mean(np.cos(np.radians(ref)) ** 2)
    svf_errs.append(abs(svf[row, col] - ref_svf))
errs = np.array(errs)
print(f"exact vs reference on {len(pick)} texels x {BINS} azimuths: mean |d| "
      f"{errs.mean():.5f} deg, max {errs.max():.5f} deg; svf max |d| {max(svf_errs):.2e}")
check(errs.max() <= 0.01, f"exact angles within 0.01 deg of the reference (max {errs.max():.5f})")
check(max(svf_errs) <= 5e-4, f"svf = mean cos^2 of the reference angles (max {max(svf_errs):.2e})")

# --- without the curvature drop (the vectorised near field of `exact`) ---
OUT1 = os.path.join(WORK, "utm_flat")
code, err = run("bake", UTM, "-o", OUT1, "--format", "geotiff", "--outputs", "angles",
                "--method", "exact", "--radius", "unlimited", "--bins", str(BINS),
                "--earth-curvature", "off")
check(code == 0, f"UTM DEM bakes with earth_curvature=off (exit {code} {err[:200]})")
if code == 0:
    with rasterio.open(os.path.join(OUT1, "angles.tif")) as a:
        flat = a.read().astype(np.float64)
    e1 = np.array([[abs(flat[n, row, col] - horizon_deg(col, row, 2 * math.pi * n / BINS, False))
                    for n in range(BINS)] for row, col in pick[:60]])
    print(f"exact (no curvature) vs reference: mean {e1.mean():.5f} deg, max {e1.max():.5f} deg")
    check(e1.max() <= 0.01, f"exact without curvature within 0.01 deg (max {e1.max():.5f})")
    check(np.all(flat[:, ~holes] >= ang[:, ~holes] - 1e-4),
          "the curvature drop only lowers horizons")

# --- the horizon profile at one point (CLI `profile`, 360 compass azimuths) ---
row, col = pick[0]
e_map = transform.c + (col + 0.5) * transform.a
n_map = transform.f + (row + 0.5) * transform.e
p = subprocess.run([BIN, "profile", UTM, "--at-map", f"{e_map},{n_map}", "--json",
                    "--azimuth-from", "north_cw"], capture_output=True, text=True)
check(p.returncode == 0, f"profile at ({e_map:.1f}, {n_map:.1f}) (exit {p.returncode} {p.stderr})")
if p.returncode == 0:
    prof = json.loads(p.stdout)
    check((prof["x"], prof["y"]) == (col, row), f"--at-map lands on texel ({col}, {row})")
    az = np.array([q["azimuth"] for q in prof["profile"]])
    el = np.array([q["elevation"] for q in prof["profile"]])
    ref = np.array([horizon_deg(col, row, true_phi(col, row, a)) for a in az])
    check(len(az) == 360 and np.abs(el - ref).max() <= 0.01,
          f"profile: 360 azimuths within 0.01 deg of the reference (max {np.abs(el - ref).max():.5f})")
    csv = subprocess.run([BIN, "profile", UTM, "--at", f"{col},{row}", "--bins", "8"],
                         capture_output=True, text=True).stdout.splitlines()
    check(csv[0] == "azimuth_deg,elevation_deg" and len(csv) == 9
          and abs(float(csv[1].split(",")[1]) - horizon_deg(col, row, 0.0)) <= 0.01,
          f"profile CSV, 8 azimuths east_ccw: {csv[:3]}")

# --- sun shadow (CLI `shadow`): uint8 GeoTIFF, one exact ray per texel at the sun's azimuth ---
SUN_AZ, SUN_EL = 203.7, 2.5  # compass degrees: a low sun from the south-south-west
SHADOW = os.path.join(WORK, "shadow.tif")
code, err = run("shadow", UTM, "-o", SHADOW, "--sun-azimuth", str(SUN_AZ), "--sun-elevation",
                str(SUN_EL), "--azimuth-from", "north_cw")
check(code == 0, f"shadow (exit {code} {err[:200]})")
if code == 0:
    with rasterio.open(SHADOW) as o:
        check(o.dtypes[0] == "uint8" and o.crs == crs and o.transform.almost_equals(transform, 1e-9)
              and o.nodata == 255, f"shadow.tif uint8, CRS, transform, nodata {o.nodata}")
        sh = o.read(1)
    check(np.all(sh[holes] == 255) and np.all(np.isin(sh[~holes], [0, 1])),
          "shadow.tif: 255 exactly at holes, 0/1 elsewhere")
    # The sun's azimuth is true (SPEC 3.7): 2.19 deg off grid north here, so before the
    # conversion the grid ray put texels on the wrong side of the terminator.
    agree = total = 0
    for row, col in pick:
        ref = horizon_deg(col, row, true_phi(col, row, SUN_AZ))
        if abs(ref - SUN_EL) < 0.01:
            continue
        total += 1
        agree += int(sh[row, col] == (1 if SUN_EL > ref else 0))
    print(f"shadow agrees with the reference on {agree}/{total} texels; "
          f"{np.mean(sh[~holes] == 0):.1%} of the map in shadow")
    check(agree == total, "shadow = (sun above the reference horizon at the sun's azimuth)")
    # What the grid's azimuth (the sun's compass azimuth read as a grid one, as before true
    # north) would give: 90 - az counter-clockwise from the grid's x axis.
    GRIDSH = os.path.join(WORK, "shadow_grid.tif")
    code, err = run("shadow", UTM, "-o", GRIDSH, "--sun-azimuth", str(90.0 - SUN_AZ),
                    "--sun-elevation", str(SUN_EL))
    with rasterio.open(GRIDSH) as o:
        flips = int(np.sum(o.read(1)[~holes] != sh[~holes]))
    print(f"true vs grid north at {math.degrees(true_phi(W // 2, H // 2, 0.0)) - 90:.2f} deg of "
          f"convergence: {flips} of {int((~holes).sum())} texels flip")
    check(code == 0 and flips > 0, "the shadow at the true azimuth is not the grid azimuth's")

# --- the sun of a time and place (NREL SPA) against pvlib's SPA, and its shadow ---
import pandas as pd  # noqa: E402  (pvlib brings it)
import pvlib  # noqa: E402

SUN_TIME, LAT, LON = "2026-12-21T09:10:00+01:00", 49.75, 6.1
SHADOW2 = os.path.join(WORK, "shadow_time.tif")
p = subprocess.run([BIN, "shadow", UTM, "-o", SHADOW2, "--sun-time", SUN_TIME, "--latitude",
                    str(LAT), "--longitude", str(LON)], capture_output=True, text=True)
check(p.returncode == 0, f"shadow --sun-time (exit {p.returncode} {p.stderr[:200]})")
if p.returncode == 0:
    words = p.stderr.replace("°", " ").split()
    our_az = float(words[words.index("azimuth") + 1])
    our_el = float(words[words.index("elevation") + 1])
    sp = pvlib.solarposition.spa_python(pd.DatetimeIndex([pd.Timestamp(SUN_TIME)]), LAT, LON,
                                        altitude=0, pressure=101325, temperature=12)
    pv_az, pv_el = float(sp["azimuth"].iloc[0]), float(sp["apparent_elevation"].iloc[0])
    print(f"sun: ours {our_az:.4f}/{our_el:.4f}, pvlib SPA {pv_az:.4f}/{pv_el:.4f}")
    check(abs(our_az - pv_az) < 0.01 and abs(our_el - pv_el) < 0.01,
          "SPA sun position within 0.01 deg of pvlib's")
    with rasterio.open(SHADOW2) as o:
        sh2 = o.read(1)
    agree = total = 0
    for row, col in pick:
        ref = horizon_deg(col, row, true_phi(col, row, pv_az))
        total += 1
        agree += int(sh2[row, col] == (1 if pv_el > ref else 0))
    print(f"shadow at pvlib's sun: {agree}/{total} texels agree; "
          f"{np.mean(sh2[~holes] == 0):.1%} of the map in shadow")
    check(agree >= 0.995 * total, "shadow at the SPA sun agrees with the reference on >= 99.5%")

# --- compass bands are the same rays renumbered ---
OUT2 = os.path.join(WORK, "utm_north")
code, err = run("bake", UTM, "-o", OUT2, "--format", "geotiff", "--outputs", "angles",
                "--method", "exact", "--radius", "unlimited", "--bins", str(BINS),
                "--azimuth-from", "north_cw", "--angle-unit", "radians")
check(code == 0, f"north_cw bake (exit {code} {err[:200]})")
if code == 0:
    with rasterio.open(os.path.join(OUT2, "angles.tif")) as a:
        north = a.read().astype(np.float64)
    # Band n is the horizon at true azimuth n * 360 / bins: the reference ray at GDAL's phi
    # of that azimuth at each texel (2.2 deg off the grid's bins/4 - n here).
    b = json.load(open(os.path.join(OUT2, "bake.json")))
    nb = b["products"]["angles.tif"]
    check(nb["north"] == "true" and "true north" in nb["bands"][0],
          f"north_cw bands say true north: {nb['north']}, {nb['bands'][0]}")
    tn = np.array([[abs(math.degrees(north[n, row, col])
                        - horizon_deg(col, row, true_phi(col, row, n * 360.0 / BINS)))
                    for n in range(BINS)] for row, col in pick[:40]])
    renumbered = max(np.abs(north[n][~holes] - np.radians(ang[(BINS // 4 - n) % BINS][~holes])).max()
                     for n in range(BINS))
    print(f"north_cw true-north bands vs reference on 40 texels: max {tn.max():.5f} deg; "
          f"from the renumbered grid bins up to {math.degrees(renumbered):.3f} deg")
    check(tn.max() <= 0.01, f"north_cw bands = the reference at true azimuths (max {tn.max():.5f})")
    check(math.degrees(renumbered) > 0.05, "north_cw bands are not the grid's bins renumbered")

# --- 7 azimuths (not a multiple of 16) with march, and SVF visual ---
OUT3 = os.path.join(WORK, "utm_march")
code, err = run("bake", UTM, "-o", OUT3, "--format", "geotiff", "--outputs", "angles,svf",
                "--method", "march", "--max-distance", "5000", "--bins", "9",
                "--svf-model", "visual")
check(code == 0, f"march, 9 bins, max_distance 5000 m (exit {code} {err[:200]})")
if code == 0:
    b3 = json.load(open(os.path.join(OUT3, "bake.json")))
    check(b3["params"]["resolved_radius"]["texels"] == 20,
          f"max_distance 5000 m / 250 m = 20 texels ({b3['params']['resolved_radius']})")
    with rasterio.open(os.path.join(OUT3, "angles.tif")) as a, \
            rasterio.open(os.path.join(OUT3, "svf.tif")) as o:
        a9 = a.read().astype(np.float64)
        s9 = o.read(1).astype(np.float64)
    check(a9.shape[0] == 9, "9 bands")
    vis = 1 - np.mean(np.sin(np.radians(a9[:, ~holes])), axis=0)
    check(np.allclose(s9[~holes], vis, atol=1e-5), "visual svf = 1 - mean sin of its angles")

# --- march with the earth-curvature drop (a DEM default for the ray methods) ---
OUT4 = os.path.join(WORK, "utm_march_curved")
R4 = max(W, H)
code, err = run("bake", UTM, "-o", OUT4, "--format", "geotiff", "--outputs", "angles",
                "--method", "march", "--max-distance", str(R4 * cell), "--bins", str(BINS))
check(code == 0, f"march, 32 bins, max_distance {R4 * cell:.0f} m (exit {code} {err[:200]})")
if code == 0:
    b4 = json.load(open(os.path.join(OUT4, "bake.json")))
    check(b4["params"]["earth_curvature"] == "on", "march on a DEM: earth_curvature=on by default")
    with rasterio.open(os.path.join(OUT4, "angles.tif")) as a:
        a4 = a.read().astype(np.float64)
    curved, flat = [], []
    for row, col in pick[:40]:
        for n in range(BINS):
            phi = 2 * math.pi * n / BINS
            got = a4[n, row, col]
            curved.append(abs(got - horizon_deg(col, row, phi, True, R4)))
            flat.append(abs(got - horizon_deg(col, row, phi, False, R4)))
    curved, flat = np.array(curved), np.array(flat)
    print(f"march + curvature against the curved reference: mean {curved.mean():.4f}, "
          f"p99 {np.percentile(curved, 99):.4f}, max {curved.max():.3f} deg; against the flat "
          f"one: mean {flat.mean():.4f}")
    check(curved.mean() <= 0.1 and np.percentile(curved, 99) <= 0.5,
          "march + curvature within SPEC 3.2a's tolerance of the curved reference")
    check(curved.mean() < 0.5 * flat.mean(), "march models the drop: closer to the curved reference")

# --- lengyel shadow (CLI): L_z > s of SPEC 3.3 decoded from the stored 8-bit layers ---
OUT5 = os.path.join(WORK, "utm_lengyel")
code, err = run("bake", UTM, "-o", OUT5, "--method", "lengyel")
SHADOW3 = os.path.join(WORK, "shadow_lengyel.tif")
EL3 = 3.0
code2, err2 = run("shadow", UTM, "-o", SHADOW3, "--method", "lengyel", "--sun-azimuth",
                  str(SUN_AZ), "--sun-elevation", str(EL3), "--azimuth-from", "north_cw")
check(code == 0 and code2 == 0, f"lengyel bake and shadow (exit {code} {err[:200]}; {code2} {err2[:200]})")
if code == 0 and code2 == 0:
    import warnings  # noqa: E402

    warnings.filterwarnings("ignore", category=rasterio.errors.NotGeoreferencedWarning)
    with rasterio.open(os.path.join(OUT5, "horizon_0.png")) as l0, \
            rasterio.open(os.path.join(OUT5, "horizon_1.png")) as l1, \
            rasterio.open(SHADOW3) as o:
        ch = np.concatenate([l0.read(), l1.read()]).astype(np.float64) / 255.0  # 8 channels
        sh3 = o.read(1)
    # SPEC 2: channel c at c*45 deg, east_ccw, y up; the layers are decoded for one light, the
    # sun's true azimuth turned to the grid at the map's centre.
    pos = (math.degrees(true_phi(W // 2, H // 2, SUN_AZ)) % 360.0) / 45.0
    c, t = int(pos) % 8, pos - int(pos)
    s = (1 - t) * ch[c] + t * ch[(c + 1) % 8]
    want = (math.sin(math.radians(EL3)) > s).astype(np.uint8)
    sure = ~holes & (np.abs(math.sin(math.radians(EL3)) - s) > 1e-5)
    print(f"lengyel shadow: {np.mean(sh3[~holes] == 0):.1%} in shadow, "
          f"{int(np.sum(sh3[sure] != want[sure]))} of {int(sure.sum())} texels off the decode")
    check(np.all(sh3[sure] == want[sure]) and np.all(sh3[holes] == 255),
          "lengyel shadow = (sin e > s decoded from horizon_0/1.png), holes nodata")

# --- horizon_distance (issue 44): the distance to the point that sets each horizon ---
# Against the reference's arg max on the same texels as the angles (where the horizon is above
# 0.5 degrees, so the point is well defined); a ray whose two highest points nearly tie may pick
# either, so most, not all, must agree to a cell.
OUTH = os.path.join(WORK, "hdist")
code, err = run("bake", UTM, "-o", OUTH, "--format", "geotiff", "--outputs", "horizon_distance",
                "--method", "sweep", "--radius", "unlimited", "--bins", str(BINS))
check(code == 0, f"outputs=horizon_distance bakes (exit {code} {err[:200]})")
if code == 0:
    with rasterio.open(os.path.join(OUTH, "horizon_distance.tif")) as o:
        dist = o.read().astype(np.float64)
        d_descr = o.descriptions
        check(o.count == BINS and o.crs == crs and o.nodata == -9999,
              f"horizon_distance.tif: {o.count} bands, CRS {o.crs}, nodata {o.nodata}")
    check("metre" in (d_descr[0] or ""), f"horizon_distance band 1 described: {d_descr[0]}")
    check(np.all(dist[:, holes] == -9999), "horizon_distance: holes nodata")
    agree, total, zeros, zero_ok = 0, 0, 0, 0
    for row, col in pick[:40]:
        for n_ in range(BINS):
            deg, ref_d = horizon_deg(col, row, 2 * math.pi * n_ / BINS, distance=True)
            got = dist[n_, row, col]
            if deg == 0.0:
                zeros += 1
                zero_ok += bool(got == -9999)
            elif deg > 0.5:
                total += 1
                agree += abs(got - ref_d) <= cell
    print(f"horizon_distance: {agree} of {total} rays within one cell of the reference")
    check(total > 100 and agree >= 0.95 * total,
          f"horizon_distance at the reference's arg max ({agree}/{total} within 250 m)")
    # (A sampled reference can miss a sliver above 0 that the exact walk finds.)
    check(zero_ok >= 0.95 * zeros,
          f"horizon_distance is nodata where the horizon is 0 ({zero_ok}/{zeros})")

# --- openness (issue 44): Yokoyama's positive and negative openness within 2 km ---
# The reference: the same bilinear ray, signed (no clamp at 0), without the curvature drop, on
# the DEM and on -DEM; mean over the bins of 90 - beta, azimuths whose ray meets no surface
# (no length, or holes only) left out.
OUTO = os.path.join(WORK, "openness")
code, err = run("bake", UTM, "-o", OUTO, "--format", "geotiff", "--outputs", "openness",
                "--max-distance", "2000", "--bins", "16")
check(code == 0, f"outputs=openness bakes within max_distance (exit {code} {err[:200]})")
code_u, err_u = run("bake", UTM, "-o", os.path.join(WORK, "open-u"), "--format", "geotiff",
                    "--outputs", "openness")
check(code_u == 2 and "max_distance" in err_u,
      f"openness to the edge of the map is refused naming max_distance ({err_u[:160]})")
if code == 0:
    with rasterio.open(os.path.join(OUTO, "openness_positive.tif")) as o, \
            rasterio.open(os.path.join(OUTO, "openness_negative.tif")) as g:
        opos, oneg = o.read(1).astype(np.float64), g.read(1).astype(np.float64)
        check(o.crs == crs and g.nodata == -9999, f"openness GeoTIFFs keep CRS and nodata")
    radius_t = math.ceil(2000 / cell)
    oerr, near = [], []
    for row, col in pick[:40]:
        by_hole = bool(holes[max(row - radius_t, 0):row + radius_t + 1,
                             max(col - radius_t, 0):col + radius_t + 1].any())
        for plane, surf in ((opos, dem), (oneg, -dem)):
            betas = [horizon_deg(col, row, 2 * math.pi * n_ / 16, curvature=False,
                                 radius=radius_t, signed=True, surface=surf) for n_ in range(16)]
            betas = [b for b in betas if b is not None]
            (near if by_hole else oerr).append(abs(plane[row, col] - np.mean([90 - b for b in betas])))
    oerr, near = np.array(oerr), np.array(near)
    print(f"openness vs reference: {len(oerr)} values, mean |d| {oerr.mean():.5f} deg, "
          f"max {oerr.max():.5f}; {len(near)} within reach of a hole: max {near.max():.5f}; "
          f"positive mean {np.mean(opos[~holes]):.2f}, negative mean {np.mean(oneg[~holes]):.2f}")
    check(oerr.max() <= 0.01, f"openness within 0.01 deg of the numpy reference (max {oerr.max():.5f})")
    # Beside holes the two differ in where a ray along a hole's edge still sees surface.
    check(near.max() <= 0.5, f"openness beside holes within 0.5 deg (max {near.max():.5f})")
    check(np.all(opos[holes] == -9999) and np.all(oneg[holes] == -9999), "openness: holes nodata")

# --- svf_model=tilted (issue 44): Dozier & Frew's equation for a slope, computed here ---
# V = mean_n [cos S sin^2 H_n + sin S cos(phi_n - A) (H_n - sin H_n cos H_n)], H_n the zenith
# angle of the higher of the horizon (angles.tif, exact) and the slope's own plane, S and A the
# slope and aspect of numpy's central differences of the DEM in metres (texels whose four
# neighbours are all there); against svf.tif of the same bake.
OUTT = os.path.join(WORK, "tilted")
code, err = run("bake", UTM, "-o", OUTT, "--format", "geotiff", "--outputs", "angles,svf",
                "--method", "exact", "--radius", "unlimited", "--bins", str(BINS),
                "--svf-model", "tilted")
check(code == 0, f"svf_model=tilted bakes (exit {code} {err[:200]})")
if code == 0:
    with rasterio.open(os.path.join(OUTT, "angles.tif")) as a, \
            rasterio.open(os.path.join(OUTT, "svf.tif")) as o:
        ang_t = np.radians(a.read().astype(np.float64))
        svf_t = o.read(1).astype(np.float64)
        descr_t = o.descriptions[0] or ""
    cell = 250.0
    gx = np.zeros_like(dem)
    gy = np.zeros_like(dem)
    gx[:, 1:-1] = (dem[:, 2:] - dem[:, :-2]) / (2 * cell)
    gy[1:-1, :] = (dem[:-2, :] - dem[2:, :]) / (2 * cell)  # +y = north = row - 1
    inner = np.zeros_like(holes)
    inner[1:-1, 1:-1] = ~(holes[1:-1, 1:-1] | holes[:-2, 1:-1] | holes[2:, 1:-1]
                          | holes[1:-1, :-2] | holes[1:-1, 2:])
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gy, -gx)  # where the normal (-gx, -gy, 1) leans: downslope
    phis = np.arange(BINS) * 2 * math.pi / BINS
    v = np.zeros_like(dem)
    for n_, phi in enumerate(phis):
        rise = np.maximum(0.0, np.arctan(-np.tan(slope) * np.cos(phi - aspect)))
        h_ = np.minimum(math.pi / 2 - ang_t[n_], math.pi / 2 - rise)
        v += (np.cos(slope) * np.sin(h_) ** 2
              + np.sin(slope) * np.cos(phi - aspect) * (h_ - np.sin(h_) * np.cos(h_)))
    v /= BINS
    d = np.abs(svf_t[inner] - v[inner])
    flat_d = np.abs(svf_t[inner] - svf[inner])
    print(f"svf tilted: {int(inner.sum())} texels, max |tilted - D&F| {d.max():.2e}, "
          f"mean {d.mean():.2e}; differs from radiative by up to {flat_d.max():.3f}")
    check(d.max() <= 1e-4, f"svf_model=tilted = Dozier & Frew's slope equation (max {d.max():.2e})")
    check(flat_d.max() > 1e-3, "the tilted SVF is not the horizontal one")
    check(np.all(svf_t[holes] == -9999), "tilted svf: holes nodata")
    check("tilted" in descr_t, f"svf.tif says tilted: {descr_t}")

# --- sun hours and insolation (issue 44): pvlib's SPA and clear sky, the reference ray ---
# One local mean solar day sampled every 10 min at the middle of each step, at the DEM's centre
# (GDAL's inverse projection of it); a step counts where pvlib's apparent elevation is above 0
# and above the reference horizon at GDAL's phi of pvlib's azimuth. Insolation adds pvlib's
# simplified Solis DNI at the texel's pressure (alt2pres) times the cosine of incidence on
# numpy's central-difference normal.
OUTS = os.path.join(WORK, "sun")
DAY = "2026-06-21"
code, err = run("bake", UTM, "-o", OUTS, "--format", "geotiff", "--outputs",
                "sun_hours,insolation", "--date", DAY)
check(code == 0, f"sun_hours,insolation bake (exit {code} {err[:200]})")
if code == 0:
    bs = json.load(open(os.path.join(OUTS, "bake.json")))
    place = bs["products"]["sun_hours.tif"]["place"]
    cx = transform.c + W / 2 * transform.a
    cy = transform.f + H / 2 * transform.e
    (clon,), (clat,) = warp_points(crs, "EPSG:4326", [cx], [cy])
    check(abs(place["latitude"] - clat) < 1e-5 and abs(place["longitude"] - clon) < 1e-5,
          f"the sun's place is the DEM's centre ({place}, GDAL {clat:.6f}, {clon:.6f})")
    with rasterio.open(os.path.join(OUTS, "sun_hours.tif")) as o, \
            rasterio.open(os.path.join(OUTS, "insolation.tif")) as q:
        hours = o.read(1).astype(np.float64)
        ins = q.read(1).astype(np.float64)
        check(o.crs == crs and o.nodata == -9999, "sun_hours.tif keeps the CRS and nodata")
    midnight = pd.Timestamp(DAY, tz="UTC") - pd.Timedelta(hours=clon / 15.0)
    times = pd.DatetimeIndex([midnight + pd.Timedelta(minutes=10 * (k + 0.5)) for k in range(144)])
    sp = pvlib.solarposition.spa_python(times, clat, clon, altitude=0, pressure=101325,
                                        temperature=12)
    up = sp[sp["apparent_elevation"] > 0]
    az_s, el_s = up["azimuth"].to_numpy(), up["apparent_elevation"].to_numpy()
    gx = np.zeros_like(dem)
    gy = np.zeros_like(dem)
    gx[:, 1:-1] = (dem[:, 2:] - dem[:, :-2]) / (2 * cell)
    gy[1:-1, :] = (dem[:-2, :] - dem[2:, :]) / (2 * cell)
    inner = np.zeros_like(holes)
    inner[1:-1, 1:-1] = ~(holes[1:-1, 1:-1] | holes[:-2, 1:-1] | holes[2:, 1:-1]
                          | holes[1:-1, :-2] | holes[1:-1, 2:])
    cand = np.argwhere(inner)
    sample = cand[rng.choice(len(cand), 20, replace=False)]
    h_err, e_err = [], []
    for row, col in sample:
        nrm = np.array([-gx[row, col], -gy[row, col], 1.0])
        nrm /= np.linalg.norm(nrm)
        pres = pvlib.atmosphere.alt2pres(float(dem[row, col]))
        lit_n, wh, one_step = 0, 0.0, 0.0
        for a_, e_ in zip(az_s, el_s):
            phi = true_phi(col, row, a_)
            if e_ <= horizon_deg(col, row, phi):
                continue
            lit_n += 1
            dni = float(pvlib.clearsky.simplified_solis(e_, pressure=pres)["dni"])
            ce = math.cos(math.radians(e_))
            sun_v = np.array([ce * math.cos(phi), ce * math.sin(phi), math.sin(math.radians(e_))])
            part = dni * max(0.0, float(nrm @ sun_v)) / 6.0
            wh += part
            one_step = max(one_step, part)
        h_err.append(abs(hours[row, col] - lit_n / 6.0))
        e_err.append(abs(ins[row, col] - wh) - one_step)
    h_err, e_err = np.array(h_err), np.array(e_err)
    print(f"sun hours vs pvlib + reference ray on {len(sample)} texels: max |d| {h_err.max():.3f} h "
          f"(one step 0.167 h); insolation max |d| - one step {e_err.max():.1f} Wh/m2; "
          f"map mean {hours[~holes].mean():.2f} h, {ins[~holes].mean():.0f} Wh/m2")
    check(h_err.max() <= 1 / 6 + 1e-6, f"sun hours within one 10-min step (max {h_err.max():.3f} h)")
    check(e_err.max() <= 0.01 * 8000, f"insolation within one step + 1 % of pvlib's (max {e_err.max():.1f})")
    check(np.all(hours[holes] == -9999) and np.all(ins[holes] == -9999), "sun products: holes nodata")
    code, err = run("bake", UTM, "-o", os.path.join(WORK, "sun_nodate"), "--format", "geotiff",
                    "--outputs", "sun_hours")
    check(code == 2 and "date" in err, f"sun_hours without a date is refused naming date ({err[:120]})")

if failures:
    print(f"{len(failures)} check(s) failed")
    sys.exit(1)
print("all terrain checks passed")
