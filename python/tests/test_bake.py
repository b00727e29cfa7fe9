"""horizon_bake.bake and bake_file against the CLI: parameters, dtypes, sizes, output values and
bytes, errors, progress, cancellation and the GIL."""

from __future__ import annotations

import json
import pathlib
import re
import threading
import time
import _thread

import numpy as np
import pytest
from PIL import Image

import horizon_bake as hb
from conftest import ROOT, run_cli

rasterio = pytest.importorskip("rasterio")

# One non-default value of every parameter of SPEC §2, as a keyword and as the text the
# library resolves it to. The DEM-only ones (cell_size, max_distance, curvature, refraction)
# are given with a cell size so the library accepts them on a plain array.
NON_DEFAULT = {
    "height_scale": (3.5, "3.5"),
    "channel": ("r", "r"),
    "edge": ("none", "none"),
    "y_axis": ("down", "down"),
    "method": ("exact", "exact"),
    "radius": (5, "5"),
    "bins": (16, "16"),
    "reduce": ("point", "point"),
    "min_elevation_deg": (7.5, "7.5"),
    "encoding": ("sqrt", "sqrt"),
    "outputs": (["horizon", "fourier"], "horizon,fourier"),
    "fourier_terms": (7, "7"),
    "fourier_range": ("expanded", "expanded"),
    "nodata": (-5.0, "-5"),
    "cell_size": (2.0, "2"),
    "max_distance": (9.0, "9"),
    "earth_curvature": (True, "on"),
    "refraction": (0.13, "0.13"),
    "angle_unit": ("radians", "radians"),
    "azimuth_from": ("north_cw", "north_cw"),
    "svf_model": ("visual", "visual"),
    "band": (1, "1"),
    "normal_convention": ("directx", "directx"),
    "bent_normal_encoding": ("rgb_ao", "rgb_ao"),
}


def rng_map(h, w, seed=0, dtype=np.float32, scale=1.0):
    rng = np.random.default_rng(seed)
    base = rng.random((h, w))
    # Smooth relief so horizons are not all noise.
    for _ in range(2):
        base = (base + np.roll(base, 1, 0) + np.roll(base, 1, 1) + np.roll(base, -1, 0)) / 4
    base = (base - base.min()) / (base.max() - base.min())
    if np.dtype(dtype) == np.uint8:
        return (base * 255).round().astype(np.uint8)
    if np.dtype(dtype) == np.uint16:
        return (base * 65535).round().astype(np.uint16)
    return (base * scale).astype(dtype)


def write_png(path, a):
    Image.fromarray(a).save(path)


def write_tiff(path, a):
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1,
                      dtype=a.dtype.name) as dst:
        dst.write(a, 1)


def read_layer(path):
    """A horizon PNG as (H, W, 4), by GDAL (16-bit RGBA too)."""
    with rasterio.open(path) as ds:
        return np.moveaxis(ds.read(), 0, -1)


def test_parameter_names_are_the_librarys():
    # The days of the sun's products are reported only by bakes of those products (`date`
    # itself is reported as date_from and date_to).
    sun = ("date", "date_from", "date_to", "time_step_minutes", "latitude", "longitude")
    r = hb.bake(rng_map(9, 9), radius=2)
    assert tuple(r.params) == tuple(k for k in hb.PARAMETERS if k not in sun)


def test_every_parameter_round_trips():
    a = rng_map(21, 17, scale=4.0)
    base = hb.bake(a, radius=3).params
    for name, (value, text) in NON_DEFAULT.items():
        extra = {}
        if name in ("max_distance", "earth_curvature", "refraction"):
            extra = {"cell_size": 2.0, "method": "exact"}
        if name in ("reduce",):
            extra = {"method": "exact"}
        if name == "radius":
            pass
        elif name != "max_distance":
            extra.setdefault("radius", 3)
        r = hb.bake(a, **{name: value}, **extra)
        assert r.params[name] == text, name
        assert r.params[name] != base[name], f"{name}: the value given is the default"
        # Resolved parameters given back bake the same map the same way.
        again = hb.bake(a, **r.params)
        assert again.params == r.params, name
        for x, y in zip(r.layers, again.layers):
            assert np.array_equal(x, y), name


@pytest.mark.parametrize("dtype,shape", [
    (np.uint8, (31, 45)), (np.uint16, (17, 64)), (np.float32, (64, 33)), (np.float64, (1, 7)),
    (np.int16, (13, 1)), (np.float32, (3, 2)),
])
def test_dtypes_and_odd_sizes_equal_the_cli(cli, tmp_path, dtype, shape):
    """The array and the same samples in a PNG (8/16-bit) or TIFF (others) bake to the values
    the CLI writes (png8 and png16), for a method and the Fourier layers."""
    a = rng_map(*shape, seed=shape[0], dtype=dtype, scale=20.0)
    if dtype in (np.uint8, np.uint16):
        src = tmp_path / "in.png"
        write_png(src, a)
    else:
        src = tmp_path / "in.tif"
        write_tiff(src, a)
    for method, params in [("lengyel", {"radius": 4}), ("exact", {"radius": 6, "edge": "none"})]:
        for fmt, dt in [("png8", "uint8"), ("png16", "uint16")]:
            out = tmp_path / f"{method}-{fmt}"
            flags = [f"--{k.replace('_', '-')}={v}" for k, v in params.items()]
            p = run_cli(cli, "bake", str(src), "-o", str(out), "--method", method, "--format",
                        fmt, "--outputs", "horizon,fourier", *flags)
            assert p.returncode == 0, p.stderr
            r = hb.bake(a, method=method, dtype=dt, outputs="horizon,fourier", **params)
            assert r.layers[0].dtype == np.dtype(dt)
            assert r.layers[0].shape == (shape[0], shape[1], 4)
            for i in (0, 1):
                assert np.array_equal(r.layers[i], read_layer(out / f"horizon_{i}.png")), (fmt, i)
            assert np.array_equal(r.fourier["bands"], read_layer(out / "fourier_0.png"))
            with Image.open(out / "fourier_1.png") as im:
                assert np.array_equal(r.fourier["constant"], np.asarray(im))
            report = json.loads((out / "bake.json").read_text())
            assert r.resolved_radius["texels"] == report["params"]["resolved_radius"]["texels"]


def test_surface_maps_are_the_clis_pngs(cli, tmp_path):
    """normal, ao and bent_normal (SPEC §3.8) as arrays hold the values of the CLI's PNGs, in
    both conventions and every bent-normal encoding."""
    a = rng_map(23, 30, seed=45, dtype=np.uint16)
    src = tmp_path / "in.png"
    write_png(src, a)
    for conv, enc in [("opengl", "rgb"), ("directx", "rgb_ao"), ("opengl", "rg")]:
        out = tmp_path / f"{conv}-{enc}"
        p = run_cli(cli, "bake", str(src), "-o", str(out), "--method", "exact", "--radius", "8",
                    "--outputs", "normal,ao,bent_normal", "--normal-convention", conv,
                    "--bent-normal-encoding", enc)
        assert p.returncode == 0, p.stderr
        r = hb.bake(a, method="exact", radius=8, outputs=("normal", "ao", "bent_normal"),
                    normal_convention=conv, bent_normal_encoding=enc)
        assert r.layers is None
        for name in ("normal", "ao", "bent_normal"):
            with Image.open(out / f"{name}.png") as im:
                assert np.array_equal(getattr(r, name), np.asarray(im)), (conv, enc, name)
        assert r.bent_normal.shape == (23, 30, 4 if enc == "rgb_ao" else 3)
        if enc == "rg":
            assert not r.bent_normal[..., 2].any()
    # Relief occludes: the AO is below 1 somewhere and never above it.
    assert r.ao.min() < 255


def test_float32_layers_are_the_unquantised_values():
    a = rng_map(40, 40, scale=10.0)
    f = hb.bake(a, radius=8, dtype="float32")
    q = hb.bake(a, radius=8, dtype="uint16")
    assert f.layers[0].dtype == np.float32
    assert np.array_equal(np.floor(f.layers[0].astype(np.float64) * 65535 + 0.5).clip(0, 65535)
                          .astype(np.uint16), q.layers[0])
    assert 0.0 <= f.layers[0].min() and f.layers[1].max() <= 1.0 and f.layers[0].max() > 0.0


def test_layers_are_zero_copy_views_of_the_bakes_buffers():
    r = hb.bake(rng_map(16, 24), radius=4)
    lay = r.layers[0]
    assert lay.flags["C_CONTIGUOUS"] and not lay.flags["OWNDATA"]
    assert lay.base is not None and lay.base.size == lay.size


def test_bake_file_writes_the_clis_bytes(cli, tmp_path):
    a = rng_map(33, 29, dtype=np.uint16)
    src = tmp_path / "in.png"
    write_png(src, a)
    flags = {"method": "exact", "radius": 7, "format": "png16,exr,ktx2", "edge": "none"}
    report = hb.bake_file(src, tmp_path / "py", **flags)
    p = run_cli(cli, "bake", str(src), "-o", str(tmp_path / "cli"), "--method", "exact",
                "--radius", "7", "--format", "png16,exr,ktx2", "--edge", "none")
    assert p.returncode == 0, p.stderr
    names = sorted(f.name for f in (tmp_path / "cli").iterdir())
    assert names == sorted(f.name for f in (tmp_path / "py").iterdir())
    for n in names:
        if n != "bake.json":
            assert (tmp_path / "py" / n).read_bytes() == (tmp_path / "cli" / n).read_bytes(), n
    theirs = json.loads((tmp_path / "cli" / "bake.json").read_text())
    assert report["params"] == theirs["params"]
    assert report["output"] == theirs["output"]


def test_bake_file_errors_are_the_clis(cli, tmp_path):
    src = tmp_path / "in.png"
    write_png(src, rng_map(8, 8, dtype=np.uint8))
    p = run_cli(cli, "bake", str(src), "-o", str(tmp_path / "a"), "--radius", "-2")
    with pytest.raises(hb.ParameterError) as e:
        hb.bake_file(src, tmp_path / "b", radius=-2)
    assert p.returncode == 2
    assert p.stderr.strip() == f"horizon-bake: {e.value}"
    assert e.value.field == "radius"
    with pytest.raises(hb.ParameterError) as e:
        hb.bake_file(src, tmp_path / "c", no_such_flag=3)
    assert "--no-such-flag" in str(e.value)
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_errors_carry_the_clis_messages(cli, tmp_path):
    bad = np.ones((6, 5), np.float32)
    bad[2, 3] = np.nan
    src = tmp_path / "nan.tif"
    write_tiff(src, bad)
    p = run_cli(cli, "bake", str(src), "-o", str(tmp_path / "o"))
    with pytest.raises(hb.InputError) as e:
        hb.bake(bad)
    assert p.stderr.strip() == f"horizon-bake: {e.value}"
    assert e.value.code == "invalid_input"
    # Declared, the NaN is a hole and the bake goes through.
    assert hb.bake(bad, nodata="nan", radius=2).holes == 1
    p = run_cli(cli, "bake", str(src), "-o", str(tmp_path / "o2"), "--bins", "0")
    with pytest.raises(hb.ParameterError) as e:
        hb.bake(bad, bins=0)
    assert p.stderr.strip() == f"horizon-bake: {e.value}"
    assert (e.value.field, e.value.code) == ("bins", "invalid_parameter")
    assert isinstance(e.value, ValueError)
    with pytest.raises(hb.ParameterError, match="unknown parameter") as e:
        hb.bake(bad, radious=3)
    assert e.value.field == "radious"
    with pytest.raises(hb.InputError, match="2-D"):
        hb.bake(np.zeros((2, 3, 4), np.float32))
    with pytest.raises(hb.InputError, match="values do not make"):
        hb.bake(np.zeros((0, 3), np.float32))
    with pytest.raises(hb.InputError, match="dtype"):
        hb.bake(np.array([["a", "b"]]))
    with pytest.raises(hb.ParameterError, match="dtype"):
        hb.bake(np.zeros((4, 4), np.float32), dtype="int8")
    with pytest.raises(hb.InputError, match="every texel is nodata"):
        hb.bake(np.full((4, 4), -9, np.float32), nodata=-9)


def test_noncontiguous_arrays_bake_as_their_copies():
    a = rng_map(40, 60, scale=5.0)
    view = a[::2, 1::3]
    assert not view.flags["C_CONTIGUOUS"]
    r1 = hb.bake(view, radius=4)
    r2 = hb.bake(np.ascontiguousarray(view), radius=4)
    assert np.array_equal(r1.layers[0], r2.layers[0])
    assert hb.bake(a.T, radius=2).width == 40


def test_cube_map_is_the_clis(cli, tmp_path):
    c = hb.cube_map(8)
    assert c.shape == (6, 8, 8, 4) and c.dtype == np.float32
    p = run_cli(cli, "cubemap", "--size", "8", "-o", str(tmp_path / "cube"))
    assert p.returncode == 0, p.stderr
    for face in range(6):
        with Image.open(tmp_path / "cube" / f"cube_{face}.png") as im:
            png = np.asarray(im.convert("RGBA"))
        # png8 stores the signed factors biased: (f · 0.5 + 0.5) as 8-bit UNORM.
        q = np.floor((c[face].astype(np.float64) * 0.5 + 0.5) * 255 + 0.5).clip(0, 255)
        q = q.astype(np.uint8)
        assert np.array_equal(q, png), face
    with pytest.raises(hb.ParameterError):
        hb.cube_map(0)


def test_progress_is_reported_and_rises_to_done():
    seen = []
    r = hb.bake(rng_map(768, 768, scale=30.0), method="exact", radius=64, bins=32,
                outputs="horizon,fourier", progress=seen.append)
    assert r.layers is not None
    assert len(seen) >= 2, seen
    assert all(0.0 <= f <= 1.0 for f in seen)
    assert seen == sorted(seen), "overall progress never goes back between products"


def test_a_callback_returning_false_cancels():
    calls = []

    def stop(f):
        calls.append(f)
        return False

    t = time.monotonic()
    with pytest.raises(hb.Canceled) as e:
        hb.bake(rng_map(1024, 1024, scale=40.0), method="exact", radius=128, progress=stop)
    assert e.value.code == "canceled"
    assert len(calls) >= 1
    assert time.monotonic() - t < 30


def test_a_raising_callback_cancels_with_its_exception():
    class Stop(Exception):
        pass

    def boom(f):
        raise Stop()

    with pytest.raises(Stop):
        hb.bake(rng_map(1024, 1024, scale=40.0), method="exact", radius=128, progress=boom)


def test_ctrl_c_cancels_the_bake():
    """A real SIGINT (interrupt_main) during a bake: KeyboardInterrupt, within moments."""
    timer = threading.Timer(0.3, _thread.interrupt_main)
    timer.start()
    t = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        hb.bake(rng_map(1536, 1536, scale=40.0), method="exact", radius=256)
    assert time.monotonic() - t < 30
    timer.cancel()


def test_the_gil_is_released_during_a_bake():
    ticks = []
    stop = threading.Event()

    def count():
        while not stop.is_set():
            ticks.append(1)
            time.sleep(0.001)

    th = threading.Thread(target=count)
    th.start()
    t = time.monotonic()
    hb.bake(rng_map(512, 512, scale=30.0), method="exact", radius=64)
    took = time.monotonic() - t
    stop.set()
    th.join()
    # A bake holding the GIL would leave the counter at zero or one; released, the thread
    # ticks every millisecond or so even on a loaded machine.
    assert took > 0.05
    assert len(ticks) >= 20 and len(ticks) > 0.05 * took / 0.0011, (len(ticks), took)


def test_version_is_the_crates():
    text = (ROOT / "Cargo.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', text, re.M).group(1)
    assert hb.__version__ == version
    py = (ROOT / "python" / "Cargo.toml").read_text()
    assert re.search(r'^version = "([^"]+)"', py, re.M).group(1) == version
    import importlib.metadata as md
    assert md.version("horizon-bake") == version


def test_type_stubs_cover_the_public_api():
    pkg = pathlib.Path(hb.__file__).parent
    assert (pkg / "py.typed").exists()
    stub = (pkg / "__init__.pyi").read_text()
    for name in ("def bake(", "def terrain(", "def bake_file(", "def cube_map(",
                 "class BakeResult", "Client as Client"):
        assert name in stub, name
    assert "class Client" in (pkg / "client.pyi").read_text()
    for mod in ("dask", "xarray", "rasterio"):
        assert "def " in (pkg / f"{mod}.pyi").read_text(), mod
    native = (pkg / "_native.pyi").read_text()
    for name in ("def bake_array(", "def cube_map(", "def run_cli(", "def resolve("):
        assert name in native, name
