"""horizon_bake.Client against a real ``horizon-bake serve`` on 127.0.0.1: submit (array, path,
bytes), progress from SSE, results equal to the library's, cancel, list, 429 retried after
Retry-After, problem+json as the library's exceptions."""

from __future__ import annotations

import io
import threading
import time

import numpy as np
import pytest
from PIL import Image

import horizon_bake as hb
from test_bake import rng_map, write_png

rasterio = pytest.importorskip("rasterio")


def png8(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGBA"))


def test_submit_an_array_wait_with_progress_and_fetch_the_librarys_values(server):
    c = hb.Client(server.url)
    a = rng_map(96, 80, dtype=np.uint16)
    seen = []
    bake = c.submit(a, method="exact", radius=12, outputs="horizon,fourier")
    assert bake["status"] in ("queued", "running", "succeeded")
    done = c.wait(bake, progress=seen.append)
    assert done["status"] == "succeeded" and seen[-1] == 1.0
    assert all(0.0 <= f <= 1.0 for f in seen)
    lib = hb.bake(a, method="exact", radius=12, outputs="horizon,fourier")
    for i in (0, 1):
        assert np.array_equal(png8(c.fetch(bake, f"horizon/{i}")), lib.layers[i]), i
    assert np.array_equal(png8(c.fetch(bake, "fourier/0")), lib.fourier["bands"])
    # A format not stored with the bake is encoded on request (202, then the file).
    lib16 = hb.bake(a, method="exact", radius=12, dtype="uint16")
    with rasterio.open(io.BytesIO(c.fetch(bake, "horizon/1", format="png16"))) as ds:
        assert np.array_equal(np.moveaxis(ds.read(), 0, -1), lib16.layers[1])
    assert done["params"]["method"] == lib.params["method"] == "exact"
    assert c.get(bake["id"])["id"] == bake["id"]


def test_paths_and_bytes_submit_the_same_bake(server, tmp_path):
    c = hb.Client(server.url)
    a = rng_map(40, 40, dtype=np.uint8)
    src = tmp_path / "m.png"
    write_png(src, a)
    b1 = c.bake(src, radius=5)
    b2 = c.submit(src.read_bytes(), radius=5)
    assert b2["id"] == b1["id"], "an identical submission is the same bake"
    assert np.array_equal(png8(c.fetch(b1, "horizon/0")), hb.bake(a, radius=5).layers[0])
    ids = [b["id"] for b in c.list(status="succeeded", limit=1)]
    assert b1["id"] in ids and len(ids) == len(set(ids)) >= 2


def test_terrain_products_equal_the_librarys(server, elev_tif):
    c = hb.Client(server.url)
    done = c.bake(elev_tif, outputs="svf,angles", cell_size=800,
                  max_distance=4000, bins=8)
    from horizon_bake import rasterio as hbr

    lib = hbr.terrain(elev_tif, cell_size=800, max_distance=4000, bins=8)
    with rasterio.open(io.BytesIO(c.fetch(done, "svf"))) as ds:
        assert np.array_equal(ds.read(1), lib.svf, equal_nan=True)
        assert ds.crs == lib.crs and ds.transform.to_gdal() == lib.transform
        assert ds.nodata == lib.product_nodata
    with rasterio.open(io.BytesIO(c.fetch(done, "angles"))) as ds:
        assert np.array_equal(ds.read(), lib.angles, equal_nan=True)


def test_problems_are_the_librarys_exceptions(server):
    c = hb.Client(server.url)
    a = rng_map(8, 8)
    with pytest.raises(hb.ParameterError) as e:
        c.submit(a, radius=-3)
    with pytest.raises(hb.ParameterError) as lib:
        hb.bake(a, radius=-3)
    assert (e.value.field, e.value.code, e.value.status) == ("radius", "invalid_parameter", 422)
    assert str(e.value) == str(lib.value)
    with pytest.raises(hb.InputError) as e:
        c.submit(b"not an image")
    assert e.value.status == 415
    with pytest.raises(hb.NotFound):
        c.get("0" * 20)
    with pytest.raises(hb.ServiceError):
        hb.Client("http://127.0.0.1:9", retries=0).get("x")


def test_cancel_a_running_bake(server):
    c = hb.Client(server.url)
    bake = c.submit(rng_map(1024, 1024, seed=5, scale=50.0), method="exact", radius=400,
                    edge="none")
    deadline = time.monotonic() + 60
    while c.get(bake)["status"] == "queued" and time.monotonic() < deadline:
        time.sleep(0.05)
    c.cancel(bake)
    with pytest.raises(hb.Canceled):
        c.wait(bake, timeout=60)
    assert c.get(bake)["status"] == "canceled"


def test_a_full_queue_is_retried_after_retry_after(make_server):
    s = make_server("--queue-capacity", "1", "--max-concurrent-bakes", "1")
    c = hb.Client(s.url, max_retry_wait=0.5, retries=200)
    slow = dict(method="exact", radius=400, edge="none")
    running = c.submit(rng_map(1024, 1024, seed=1, scale=50.0), **slow)
    queued = c.submit(rng_map(1024, 1024, seed=2, scale=50.0), **slow)
    strict = hb.Client(s.url, retries=0)
    small = rng_map(16, 16, seed=3)
    with pytest.raises(hb.ServiceError) as e:
        strict.submit(small, radius=2)
    assert (e.value.status, e.value.code) == (429, "queue_full")

    def free():
        time.sleep(1.5)
        strict.cancel(queued)
        strict.cancel(running)

    t = threading.Thread(target=free)
    t.start()
    done = c.bake(small, radius=2, timeout=120)
    t.join()
    assert c.retried >= 1
    assert done["status"] == "succeeded"
    assert np.array_equal(png8(c.fetch(done, "horizon/0")), hb.bake(small, radius=2).layers[0])


def test_api_key(make_server):
    s = make_server("--api-key", "s3cret")
    with pytest.raises(hb.HorizonBakeError) as e:
        hb.Client(s.url).submit(rng_map(8, 8), radius=2)
    assert e.value.status == 401
    done = hb.Client(s.url, api_key="s3cret").bake(rng_map(8, 8), radius=2)
    assert done["status"] == "succeeded"
