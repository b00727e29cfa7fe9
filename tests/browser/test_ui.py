"""Browser test of the web page (issue 13): the real server binary, Debian's chromium driven by
Python playwright, WebGL2 on SwiftShader.

What it checks: the page and its modules load without errors (and --no-ui turns them off); the
file's header is read before the upload (PNG, TIFF, OpenEXR, the server's limits); an upload
through the file input is accepted (202), shows a progress value strictly between 0 and 1 and
then `succeeded`, with the resolved radius, its reason and the timings; the WebGL2 canvas
matches the server's CPU preview within 2 levels on >= 99.9% of pixels at 8 lights near
cube-face edges, for horizon, fourier and none shading, edge=wrap/none, y_axis=up/down,
encoding=linear/sqrt and both Fourier ranges, with the decode of the shipped GLSL include
(GET /v1/shaders/horizon.glsl: an include without shadows stops matching); the tiled view
repeats the map; dragging the light changes the readout and the image, which still matches; error answers are shown (415
code and detail in an alert, a parameter's message next to its field, 429 with Retry-After);
Cancel stops a bake; every download link answers 200 with its content type; the list links to
bakes by `#id`; without WebGL2 the CPU preview is shown; with --api-key the page works once the
key is entered, progress included. Issue 24: a GeoTIFF DEM (made with rasterio) is sent
without height_scale/edge, gets the DEM defaults, shows its CRS and cell size, and its SVF and
the shadow of a sun the user sets are shown with the values of the server's GeoTIFFs. Issue 45:
the surface maps, ticked in the form, are shown as the server's PNGs.

Run: HORIZON_BIN=target/debug/horizon-bake python -m pytest -q tests/browser
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import time

import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import sync_playwright

from harness import TERRAIN, chromium_or_skip, compare, decode_rgba, launch, server

# The terrain at its true scale (metres / 90 m per texel, scripts/extract_terrain.py): about 6
# texels of relief, so low lights cast real shadows.
TRUE_SCALE = "728.2"
# A bake slow enough that the 250 ms event stream reports it mid-way: the exact kernel to the
# edge of the map on one thread, at the most bins allowed (with 64, a clean CI run showed
# only the 0.05 of the decode stage between 0 and 1).
SLOW = {"method": "exact", "radius": "unlimited", "bins": "256", "height_scale": TRUE_SCALE}
# Lights for the GPU/CPU comparison: within 2° of the cube's face edges (azimuth 45°+k·90° is
# the edge between side faces; elevation 45° at azimuth 0°/-90°/180° the edge with +Z), away
# from the cube corners (elevation 35.26° at azimuth 45°+k·90°), plus a low and a high light.
LIGHTS = [
    (44.0, 30.0),
    (46.0, 20.0),
    (134.5, 25.0),
    (0.0, 44.5),
    (-90.0, 45.8),
    (180.0, 46.5),
    (200.0, 12.0),
    (300.0, 65.0),
]
MIN_MATCH = 0.999
TOLERANCE = 2
# Chromium logs every non-2xx fetch as a console error; tests that provoke one allow these.
HTTP_ERROR_LOG = re.compile(r"Failed to load resource: the server responded with a status of 4\d\d")


@pytest.fixture(scope="session")
def browser():
    exe = chromium_or_skip()
    with sync_playwright() as p:
        b = launch(p, exe)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def srv():
    with server(extra=["--bake-threads", "1"]) as s:
        yield s


class Page:
    """A page with its errors recorded."""

    def __init__(self, browser, url: str):
        self.context = browser.new_context(viewport={"width": 1280, "height": 900})
        self.page = self.context.new_page()
        self.errors: list[str] = []
        self.page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))
        self.page.on(
            "console",
            lambda m: self.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None,
        )
        self.page.goto(url)
        self.page.wait_for_function("() => window.__horizon !== undefined")

    def assert_no_errors(self, allow_http_errors: bool = False):
        errs = [e for e in self.errors if not (allow_http_errors and HTTP_ERROR_LOG.search(e))]
        assert not errs, errs

    def close(self):
        self.context.close()


def set_params(page, params: dict):
    for k, v in params.items():
        if k == "radius" and v in ("auto", "unlimited"):
            page.select_option("#p-radius-mode", v)
        elif k == "radius":
            page.select_option("#p-radius-mode", "texels")
            page.fill("#p-radius", str(v))
        elif k == "outputs":
            page.set_checked("#p-out-horizon", "horizon" in v)
            page.set_checked("#p-out-fourier", "fourier" in v)
        elif page.locator(f"select#p-{k}").count():
            page.select_option(f"#p-{k}", str(v))
        else:
            page.fill(f"#p-{k}", str(v))


def upload(page, path_or_payload, params: dict | None = None):
    """Chooses a file, sets parameters, clicks Bake; returns the POST's playwright Response."""
    page.set_input_files("#file", path_or_payload)
    name = path_or_payload["name"] if isinstance(path_or_payload, dict) else path_or_payload.rsplit("/", 1)[-1]
    page.wait_for_function(
        "name => { const t = document.getElementById('file-info').textContent;"
        " return t.includes(name) && !t.endsWith('…'); }", arg=name)
    if params:
        set_params(page, params)
    with page.expect_response(
        lambda r: r.request.method == "POST" and "/v1/bakes" in r.url
    ) as info:
        page.click("#bake")
    return info.value


def bake_id_of(response) -> str:
    """The bake id from a POST's Location header (the page changes its URL's #fragment at once,
    after which playwright no longer has the response body)."""
    return response.header_value("location").rsplit("/", 1)[1]


def wait_loaded(page, bake_id: str, timeout_ms: int = 600_000):
    page.wait_for_function(
        "id => window.__horizon.loadedId === id", arg=bake_id, timeout=timeout_ms
    )


@pytest.fixture(scope="module")
def baked(browser, srv):
    """One page that uploaded the terrain through the file input and shows the finished bake."""
    p = Page(browser, srv.url + "/")
    res = upload(p.page, str(TERRAIN), SLOW)
    bake_id = bake_id_of(res)
    wait_loaded(p.page, bake_id)
    p.post_status = res.status
    p.bake_id = bake_id
    yield p
    p.close()


def light_matches(p: Page, srv, azimuth: float, elevation: float, hardness: float = 8):
    """Sets the light on the page; (fraction within tolerance, max diff) of the visible canvas."""
    p.page.evaluate("l => window.__horizon.setLight(l)",
                    {"azimuth": azimuth, "elevation": elevation, "hardness": hardness})
    gpu = decode_rgba(p.page.evaluate("() => window.__horizon.readCanvas()"))
    cpu = srv.preview(p.bake_id, azimuth, elevation, hardness)
    return compare(gpu, cpu, TOLERANCE)


# ---------------------------------------------------------------------------------------------


def test_page_and_modules_are_served(srv):
    status, headers, body = srv.request("/")
    assert status == 200
    assert headers["content-type"].startswith("text/html")
    html = body.decode()
    assert "__HORIZON_CONFIG__" not in html
    cfg = json.loads(re.search(r'<script type="application/json" id="config">(.*?)</script>', html, re.S)[1])
    assert {"version", "auth_required", "max_body_bytes", "max_dim", "max_texels"} <= cfg.keys()
    assert cfg["auth_required"] is False
    for name in re.findall(r'(?:src|href)="/ui/([^"]+)"', html):
        status, headers, _ = srv.request(f"/ui/{name}")
        assert status == 200, name
        want = "text/css" if name.endswith(".css") else "text/javascript"
        assert headers["content-type"].startswith(want), (name, headers["content-type"])
    # viewer.js is imported by app.js, not by the page
    status, headers, _ = srv.request("/ui/viewer.js")
    assert status == 200 and headers["content-type"].startswith("text/javascript")


def test_no_ui_turns_the_page_off():
    with server(extra=["--no-ui"]) as s:
        for path in ("/", "/ui/app.js", "/ui/viewer.js", "/ui/style.css"):
            status, headers, _ = s.request(path)
            assert status == 404, path
            assert headers["content-type"].startswith("application/problem+json"), path
        status, _, _ = s.request("/v1/bakes")
        assert status == 200


def test_upload_shows_progress_then_succeeds(baked):
    assert baked.post_status == 202
    page = baked.page
    log = page.evaluate("() => window.__horizon.progressLog")
    fractions = [e["fraction"] for e in log]
    print(f"\nprogress shown: {[(round(e['fraction'], 3), e['stage']) for e in log]}")
    assert any(0 < f < 1 for f in fractions), log
    assert log[-1]["status"] == "succeeded"
    assert page.locator("#progress").get_attribute("value") in ("1", "1.0")
    assert "succeeded" in page.text_content("#meta")
    # the map's size was read from the file before the upload
    assert "128 × 128" in page.text_content("#file-info")
    # the resolved radius and its reason, and the timings, are shown
    meta = page.text_content("#meta")
    assert re.search(r"radius\s*128 texels \(asked: unlimited\)", meta), meta
    assert "timings" in meta
    assert page.evaluate("() => window.__horizon.webgl2")
    assert page.text_content("#renderer").startswith("WebGL2: ")
    baked.assert_no_errors()


def test_canvas_matches_cpu_preview_near_cube_edges(baked, srv):
    gpu = decode_rgba(baked.page.evaluate("() => window.__horizon.readCanvas()"))
    assert gpu.shape == (128, 128, 4)
    assert gpu[..., :3].std() > 10 and len(np.unique(gpu[..., 0])) > 50, "blank canvas"
    results = []
    for az, el in LIGHTS:
        frac, worst = light_matches(baked, srv, az, el)
        results.append((az, el, frac, worst))
    print("\nGPU vs CPU preview (azimuth, elevation, fraction within 2 levels, max diff):")
    for r in results:
        print(f"  az {r[0]:7.2f} el {r[1]:6.2f}: {r[2]:.5f}  max {r[3]}")
    bad = [r for r in results if r[2] < MIN_MATCH]
    assert not bad, results
    baked.assert_no_errors()


def test_offscreen_render_hook_matches_too(baked, srv):
    shot = baked.page.evaluate("() => window.__horizon.render({azimuth: 45.5, elevation: 33})")
    frac, worst = compare(decode_rgba(shot), srv.preview(baked.bake_id, 45.5, 33), TOLERANCE)
    assert frac >= MIN_MATCH, (frac, worst)


def test_dragging_moves_the_light(baked, srv):
    page = baked.page
    baked.page.evaluate("() => window.__horizon.setLight({azimuth: 135, elevation: 30, hardness: 8})")
    before_text = page.text_content("#light")
    before = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
    box = page.locator("#canvas").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx - box["width"] * 0.1, cy + box["height"] * 0.1)
    page.mouse.down()
    page.mouse.move(cx + box["width"] * 0.35, cy + box["height"] * 0.25, steps=8)
    page.mouse.up()
    after_text = page.text_content("#light")
    assert after_text != before_text
    light = page.evaluate("() => window.__horizon.light")
    # right and down on the image: +x and -y (y_axis=up), low above the horizon
    assert -90 < light["azimuth"] < 0, light
    assert 0 < light["elevation"] < 60, light
    after = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
    assert np.abs(after.astype(int) - before.astype(int)).max() > 10, "the image did not change"
    cpu = srv.preview(baked.bake_id, light["azimuth"], light["elevation"], light["hardness"])
    frac, worst = compare(after, cpu, TOLERANCE)
    print(f"\ndragged light {light}: {frac:.5f} within 2 levels, max {worst}")
    assert frac >= MIN_MATCH, (light, frac, worst)
    baked.assert_no_errors()


def test_every_download_answers_with_its_content_type(baked, srv):
    links = baked.page.eval_on_selector_all(
        "a.dl", "as => as.map(a => [a.getAttribute('href'), a.dataset.type, a.textContent])"
    )
    hrefs = [h for h, _, _ in links]
    base = f"/v1/bakes/{baked.bake_id}"
    for want in (f"{base}/horizon/0?format=png8", f"{base}/horizon/1?format=png16",
                 f"{base}/horizon/0?format=exr", f"{base}/horizon.ktx2", f"{base}/horizon.dds",
                 "/v1/cubemap/5?size=16", base):
        assert want in hrefs, (want, hrefs)
    for href, ctype, label in links:
        status, headers, body = srv.request(href)
        # A format the bake did not encode answers 202 + Retry-After at once, then the file.
        deadline = time.time() + 300
        while status == 202 and time.time() < deadline:
            assert headers["retry-after"], (label, href)
            time.sleep(0.1)
            status, headers, body = srv.request(href)
        assert status == 200, (label, href, status, body[:200])
        assert headers["content-type"].split(";")[0] == ctype, (label, headers["content-type"])
        assert body, label
        if href.endswith("/heights"):
            # what the viewer rebuilds the normals from: W·H little-endian f32, in texels
            assert (headers["x-width"], headers["x-height"]) == ("128", "128")
            h = np.frombuffer(body, dtype="<f4")
            assert h.size == 128 * 128 and np.isfinite(h).all() and 3 < np.ptp(h) < 10, np.ptp(h)


def test_recent_list_links_to_the_bake(baked, browser, srv):
    page = baked.page
    page.click("#refresh")
    link = page.locator(f'#recent a[href="#{baked.bake_id}"]')
    link.wait_for()
    other = Page(browser, f"{srv.url}/#{baked.bake_id}")
    try:
        wait_loaded(other.page, baked.bake_id, 60_000)
        assert baked.bake_id in other.page.text_content("#bake-id")
        other.assert_no_errors()
    finally:
        other.close()


def test_viewer_shades_with_the_shipped_glsl_include(baked, browser, srv):
    """Issue 21: the viewer's decode is the GLSL include the binary ships (GET
    /v1/shaders/horizon.glsl), not a copy of its own: the page fetches it, and with an include
    whose F is always 1 (no shadows) the canvas no longer matches the CPU preview where the
    real one does (test_canvas_matches_cpu_preview_near_cube_edges)."""
    status, headers, shipped = srv.request("/v1/shaders/horizon.glsl")
    assert status == 200 and headers["content-type"].startswith("text/plain")
    lit = shipped.decode().replace(
        "return clamp(hardness * (lz - s) + 1.0, 0.0, 1.0);", "return 1.0;")
    assert lit != shipped.decode(), "the include's F changed: update this test"
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    page = ctx.new_page()
    fetched = []

    def swap(route):
        res = route.fetch()
        fetched.append(res.body())
        route.fulfill(status=200, content_type="text/plain; charset=utf-8", body=lit)

    page.route("**/v1/shaders/horizon.glsl", swap)
    try:
        page.goto(f"{srv.url}/#{baked.bake_id}")
        page.wait_for_function("() => window.__horizon !== undefined")
        wait_loaded(page, baked.bake_id, 120_000)
        assert fetched == [shipped], "the viewer did not fetch the shipped include once"
        low = (200.0, 6.0)   # long shadows on this terrain
        page.evaluate("l => window.__horizon.setLight(l)",
                      {"azimuth": low[0], "elevation": low[1], "hardness": 8})
        gpu = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
        frac, _ = compare(gpu, srv.preview(baked.bake_id, *low), TOLERANCE)
        print(f"\n  viewer on an include without shadows: {frac:.5f} of pixels match")
        assert frac < 0.99, f"an include without shadows still matched on {frac:.4f} of pixels"
    finally:
        ctx.close()


def test_bad_file_shows_the_415_code_and_detail(browser, srv):
    payload = b"this is not an image, just text\n" * 4
    status, problem = srv.json("/v1/bakes", method="POST", body=payload,
                               headers={"Content-Type": "application/octet-stream"})
    assert status == 415
    p = Page(browser, srv.url + "/")
    try:
        res = upload(p.page, {"name": "notes.txt", "mimeType": "text/plain", "buffer": payload})
        assert res.status == 415
        alert = p.page.locator("[role=alert]").filter(has_text=problem["code"])
        alert.wait_for()
        text = alert.text_content()
        assert problem["code"] in text and problem["detail"] in text, text
        assert "not a PNG, TIFF or OpenEXR" in p.page.text_content("#file-info")
        p.assert_no_errors(allow_http_errors=True)
    finally:
        p.close()


def test_bad_parameter_is_shown_next_to_its_field(browser, srv):
    status, problem = srv.json("/v1/bakes?bins=17", method="POST", body=TERRAIN.read_bytes(),
                               headers={"Content-Type": "image/png"})
    assert status == 422 and problem["field"] == "bins", problem
    p = Page(browser, srv.url + "/")
    try:
        res = upload(p.page, str(TERRAIN), {"bins": "17"})
        assert res.status == 422
        assert res.url.endswith("/v1/bakes?bins=17"), res.url
        err = p.page.locator("#err-bins")
        err.wait_for()
        assert problem["detail"] in err.text_content()
        assert p.page.get_attribute("#p-bins", "aria-invalid") == "true"
        # the message sits beside the field, in the same form row
        assert p.page.evaluate(
            "() => document.getElementById('err-bins').parentElement.contains(document.getElementById('p-bins'))"
        )
        p.assert_no_errors(allow_http_errors=True)
    finally:
        p.close()


def test_queue_full_shows_retry_after(browser, srv):
    p = Page(browser, srv.url + "/")
    try:
        problem = {"type": "urn:horizon-bake:problem:queue_full", "title": "Too Many Requests",
                   "status": 429, "code": "queue_full",
                   "detail": "the bake queue is full (64 waiting); retry later"}
        def full(route):
            if route.request.method != "POST":
                return route.continue_()
            return route.fulfill(status=429, body=json.dumps(problem), headers={
                "Retry-After": "7", "Content-Type": "application/problem+json"})

        p.page.route(lambda url: "/v1/bakes" in url, full)
        upload(p.page, str(TERRAIN), {"radius": "17"})
        alert = p.page.locator("[role=alert]")
        alert.wait_for()
        assert "queue_full" in alert.text_content() and "Retry-After: 7 s" in alert.text_content()
        assert p.page.locator("#bake").is_disabled()
        assert re.search(r"Retry in [67] s", p.page.text_content("#bake"))
        p.assert_no_errors(allow_http_errors=True)
    finally:
        p.close()


def test_cancel_stops_a_running_bake(browser, srv):
    # A map no earlier test baked (no deduplication), slow on one thread: 768² (exact, unlimited,
    # 64 bins), since a 192² bake on an idle machine finished before the page's Cancel was
    # clicked (the DELETE then answered 204, removing a finished bake).
    rng = np.random.default_rng(13)
    import io

    from PIL import Image

    img = (rng.random((768, 768)) * 65535).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    p = Page(browser, srv.url + "/")
    try:
        res = upload(p.page, {"name": "noise.png", "mimeType": "image/png", "buffer": buf.getvalue()},
                     {"method": "exact", "radius": "unlimited", "bins": "64"})
        assert res.status == 202
        bake_id = bake_id_of(res)
        p.page.wait_for_function("() => !document.getElementById('cancel').disabled")
        # Running, well into the kernel: the recent list says so (issue 25: it said "queued").
        p.page.wait_for_function(
            "() => Number(document.getElementById('progress').value) > 0.06", timeout=120_000)
        p.page.wait_for_function(
            "id => { const s = document.querySelector(`#recent li[data-id='${id}'] .st`);"
            " return s && s.textContent === 'running'; }", arg=bake_id, timeout=30_000)
        with p.page.expect_response(lambda r: r.request.method == "DELETE") as info:
            p.page.click("#cancel")
        assert info.value.status in (200, 202)
        p.page.wait_for_function(
            "() => window.__horizon.bake && window.__horizon.bake.status === 'canceled'", timeout=120_000)
        assert p.page.locator("#cancel").is_disabled()
        # The progress keeps the fraction it reached, on the page and in the resource.
        shown = float(p.page.locator("#progress").get_attribute("value"))
        assert shown > 0.05, shown
        status, res = srv.json(f"/v1/bakes/{bake_id}")
        assert res["status"] == "canceled" and res["progress"]["fraction"] > 0.05, res
        p.assert_no_errors()
    finally:
        p.close()


def test_api_key_makes_the_page_work(browser):
    key = "s3cret-ui-key"
    with server(api_key=key, extra=["--bake-threads", "1"]) as s:
        status, _, _ = s.request("/v1/bakes", auth=False)
        assert status == 401
        p = Page(browser, s.url + "/")
        try:
            assert p.page.evaluate("() => window.__horizon.config.auth_required") is True
            p.page.fill("#api-key", key)
            p.page.click("#key-form button")
            assert p.page.evaluate("() => localStorage.getItem('horizon-bake.api-key')") == key
            res = upload(p.page, str(TERRAIN), SLOW)
            assert res.status == 202
            bake_id = bake_id_of(res)
            wait_loaded(p.page, bake_id)
            log = p.page.evaluate("() => window.__horizon.progressLog")
            assert any(0 < e["fraction"] < 1 for e in log), log
            frac, worst = light_matches_on(p, s, bake_id, 46.0, 20.0)
            assert frac >= MIN_MATCH, (frac, worst)
            # "Copy as curl" repeats this upload: run it, the server answers with the same bake
            p.page.click("#curl")
            cmd = p.page.input_value("#curl-text")
            assert "$HORIZON_API_KEY" in cmd and key not in cmd, cmd
            out = subprocess.run(["bash", "-c", cmd], cwd=TERRAIN.parent, capture_output=True,
                                 text=True, timeout=60, env={**os.environ, "HORIZON_API_KEY": key})
            assert out.returncode == 0, out.stderr
            assert json.loads(out.stdout)["id"] == bake_id, out.stdout
            # the key survives a reload
            p.page.reload()
            p.page.wait_for_function("() => window.__horizon !== undefined")
            assert p.page.input_value("#api-key") == key
            # the page answered 401 before the key was entered: allow only that
            p.assert_no_errors(allow_http_errors=True)
            assert not [e for e in p.errors if "status of 4" in e and "401" not in e], p.errors
        finally:
            p.close()


def light_matches_on(p: Page, s, bake_id: str, azimuth: float, elevation: float):
    p.page.evaluate("l => window.__horizon.setLight(l)", {"azimuth": azimuth, "elevation": elevation})
    gpu = decode_rgba(p.page.evaluate("() => window.__horizon.readCanvas()"))
    return compare(gpu, s.preview(bake_id, azimuth, elevation), TOLERANCE)


def test_without_webgl2_the_cpu_preview_is_shown(baked, browser, srv):
    ctx = browser.new_context()
    page = ctx.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    # A browser without WebGL2: getContext('webgl2') answers null.
    page.add_init_script(
        "const g = HTMLCanvasElement.prototype.getContext;"
        "HTMLCanvasElement.prototype.getContext = function (t, o) {"
        " return t === 'webgl2' ? null : g.call(this, t, o); };")
    try:
        page.goto(f"{srv.url}/#{baked.bake_id}")
        page.wait_for_function(
            "() => { const i = document.getElementById('cpu-image');"
            " return i.src.startsWith('blob:') && i.complete && i.naturalWidth === 128; }",
            timeout=120_000)
        assert page.is_visible("#cpu-image")
        assert not page.is_visible("#canvas")
        assert "WebGL2 is not available" in page.text_content("#viewer-note")
        assert page.evaluate("() => window.__horizon.webgl2") is False
        assert not errors, errors
    finally:
        ctx.close()


def test_tiled_split_and_side_by_side_views(baked):
    page = baked.page
    page.evaluate("() => window.__horizon.setLight({azimuth: 150, elevation: 14, hardness: 8})")
    single = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
    page.select_option("#layout", "tiled")
    tiled = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
    assert tiled.shape == (256, 256, 4)
    for ty in (0, 128):
        for tx in (0, 128):
            assert np.array_equal(tiled[ty:ty + 128, tx:tx + 128], single), (tx, ty)
    for layout, image in (("split", "#overlay"), ("side", "#cpu-image")):
        page.select_option("#layout", layout)
        page.wait_for_function(
            "sel => { const i = document.querySelector(sel);"
            " return !i.closest('[hidden]') && !i.hidden && i.src.startsWith('blob:')"
            " && i.complete && i.naturalWidth === 128; }", arg=image, timeout=60_000)
    page.select_option("#layout", "single")
    baked.assert_no_errors()


def test_display_resolution_filters_like_the_preview_size(baked, srv):
    """Rendered at the displayed size (2x zoom: 256 px for 128 texels), the layers and normals
    are filtered bilinearly between texel centres, as the CPU preview's `size=` does."""
    page = baked.page
    page.select_option("#zoom", "2")
    page.select_option("#resolution", "display")
    try:
        for az, el in ((46.0, 20.0), (150.0, 12.0)):
            page.evaluate("l => window.__horizon.setLight(l)", {"azimuth": az, "elevation": el})
            gpu = decode_rgba(page.evaluate("() => window.__horizon.readCanvas()"))
            assert gpu.shape == (256, 256, 4)
            frac, worst = compare(gpu, srv.preview(baked.bake_id, az, el, size=256), TOLERANCE)
            print(f"\nsize=256 az {az} el {el}: {frac:.5f} within 2 levels, max {worst}")
            assert frac >= MIN_MATCH, (az, el, frac, worst)
    finally:
        page.select_option("#resolution", "texel")
        page.select_option("#zoom", "fit")
    baked.assert_no_errors()


@pytest.mark.parametrize("params", [
    {"edge": "none", "y_axis": "down", "encoding": "sqrt", "outputs": "horizon,fourier",
     "fourier_terms": "7", "radius": "24"},
    {"outputs": "horizon,fourier", "fourier_terms": "9", "fourier_range": "expanded",
     "radius": "12"},
    {"outputs": "fourier", "fourier_terms": "3", "bins": "64"},
], ids=["none-down-sqrt-f7", "wrap-f9-expanded", "fourier-only-f3"])
def test_other_conventions_match_the_cpu(browser, srv, params):
    """The other conventions: CLAMP_TO_EDGE layers and clamped normals, the row step of
    y_axis=down, encoding=sqrt squared on decode, and SPEC §3.4's Fourier shader for both
    `fourier_range`s and every term count, also when only the Fourier layers were baked."""
    p = Page(browser, srv.url + "/")
    try:
        res = upload(p.page, str(TERRAIN), {**params, "height_scale": TRUE_SCALE})
        assert res.status == 202
        bake_id = bake_id_of(res)
        wait_loaded(p.page, bake_id)
        shadings = ["fourier", "none"] if params["outputs"] == "fourier" else ["horizon", "fourier", "none"]
        results = []
        for shading in shadings:
            p.page.select_option("#shading", shading)
            for az, el in ((46.0, 20.0), (225.5, 10.0), (90.0, 44.0)):
                p.page.evaluate("l => window.__horizon.setLight(l)", {"azimuth": az, "elevation": el})
                gpu = decode_rgba(p.page.evaluate("() => window.__horizon.readCanvas()"))
                cpu = srv.preview(bake_id, az, el, shading=shading)
                results.append((shading, az, el, *compare(gpu, cpu, TOLERANCE)))
        print(f"\n{params}:")
        for r in results:
            print(f"  {r[0]:8s} az {r[1]:6.1f} el {r[2]:5.1f}: {r[3]:.5f}  max {r[4]}")
        assert all(r[3] >= MIN_MATCH for r in results), results
        # the tiled view is only offered for edge=wrap
        assert p.page.evaluate(
            "() => document.querySelector('#layout option[value=tiled]').disabled") is (
                params.get("edge") == "none")
        if params["outputs"] == "fourier":
            assert p.page.evaluate(
                "() => document.querySelector('#shading option[value=horizon]').disabled") is True
        p.assert_no_errors()
    finally:
        p.close()


def _png_header(width: int, height: int) -> bytes:
    """Just a PNG signature and IHDR (16-bit gray): enough for the page's header probe."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))


def _exr_header(width: int, height: int) -> bytes:
    """An OpenEXR header (one half channel `Y`, dataWindow), no pixels."""
    import struct

    def attr(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    chlist = b"Y\0" + struct.pack("<iBBBBii", 1, 0, 0, 0, 0, 1, 1) + b"\0"
    box = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    return (b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + attr("channels", "chlist", chlist)
            + attr("dataWindow", "box2i", box) + attr("displayWindow", "box2i", box) + b"\0")


def test_file_header_probe_and_tiff_upload(browser, srv):
    import io

    from PIL import Image

    rng = np.random.default_rng(7)
    tiff = io.BytesIO()
    Image.fromarray((rng.random((48, 80)) * 4).astype(np.float32), mode="F").save(tiff, format="TIFF")
    p = Page(browser, srv.url + "/")
    try:
        info = p.page.locator("#file-info")
        cases = [
            # Over the default --max-dim (65 536, since tiled bakes take maps that large).
            ({"name": "huge.png", "mimeType": "image/png", "buffer": _png_header(70000, 300)},
             ["70000 × 300", "PNG gray 16-bit", "over the server's limits", "a side exceeds 65536"]),
            ({"name": "h.exr", "mimeType": "image/x-exr", "buffer": _exr_header(64, 32)},
             ["64 × 32", "EXR Y 16-bit float"]),
            ({"name": "h.tif", "mimeType": "image/tiff", "buffer": tiff.getvalue()},
             ["80 × 48", "TIFF gray 32-bit float"]),
        ]
        for payload, wants in cases:
            p.page.set_input_files("#file", payload)
            p.page.wait_for_function(
                "n => { const t = document.getElementById('file-info').textContent;"
                " return t.includes(n) && !t.endsWith('…'); }", arg=payload["name"])
            text = info.text_content()
            for want in wants:
                assert want in text, (want, text)
        assert "limits" in p.page.text_content("#limits")
        # the TIFF goes up as image/tiff and bakes
        with p.page.expect_request(lambda r: r.method == "POST") as req:
            p.page.click("#bake")
        assert req.value.headers["content-type"] == "image/tiff"
        res = req.value.response()
        assert res.status == 202
        wait_loaded(p.page, bake_id_of(res))
        assert "80 × 48 tiff" in p.page.text_content("#meta")
        p.assert_no_errors()
    finally:
        p.close()


def test_a_failed_bake_shows_its_error(browser, srv):
    """A file whose header passes but whose pixels do not decode is accepted, then fails: the
    page shows the failure's code and message."""
    p = Page(browser, srv.url + "/")
    try:
        res = upload(p.page, {"name": "cut.png", "mimeType": "image/png", "buffer": _png_header(64, 64)})
        assert res.status == 202
        bake_id = bake_id_of(res)
        p.page.wait_for_function(
            "id => window.__horizon.bake && window.__horizon.bake.id === id"
            " && window.__horizon.bake.status === 'failed'", arg=bake_id, timeout=60_000)
        _, rec = srv.json(f"/v1/bakes/{bake_id}")
        alert = p.page.locator("#error")
        alert.wait_for()
        assert rec["error"]["code"] in alert.text_content(), (rec["error"], alert.text_content())
        assert "failed" in p.page.text_content("#meta")
        p.assert_no_errors()
    finally:
        p.close()


def test_opening_a_bake_loads_its_parameters(browser, srv):
    """Opening a bake by #id, or from the recent list, puts its parameters into the form (issue
    25: the form stayed at the defaults and Bake re-baked with them); the method list is the
    server's."""
    from PIL import Image

    rng = np.random.default_rng(25)
    img = (rng.random((40, 40)) * 60000).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    q = ("method=exact&radius=5&bins=48&reduce=point&height_scale=12.5&edge=none&y_axis=down"
         "&encoding=sqrt&outputs=horizon,fourier&fourier_terms=7&fourier_range=expanded")
    status, bake = srv.json(f"/v1/bakes?{q}", method="POST", body=buf.getvalue(),
                            headers={"Content-Type": "image/png"})
    assert status == 202, bake
    status, other = srv.json("/v1/bakes?radius=3", method="POST", body=buf.getvalue(),
                             headers={"Content-Type": "image/png"})
    assert status == 202, other
    for b in (bake, other):
        deadline = time.time() + 120
        while srv.json(f"/v1/bakes/{b['id']}")[1]["status"] != "succeeded":
            assert time.time() < deadline
            time.sleep(0.1)
    p = Page(browser, f"{srv.url}/#{bake['id']}")
    try:
        wait_loaded(p.page, bake["id"], 120_000)
        methods = p.page.eval_on_selector_all("#p-method option", "os => os.map(o => o.value)")
        assert methods == p.page.evaluate("() => window.__horizon.config.methods"), methods
        assert "march" in methods, methods
        assert "sweep" in methods, methods
        want = {"#p-method": "exact", "#p-radius-mode": "texels", "#p-radius": "5", "#p-bins": "48",
                "#p-reduce": "point", "#p-height_scale": "12.5", "#p-edge": "none",
                "#p-y_axis": "down", "#p-encoding": "sqrt", "#p-fourier_terms": "7",
                "#p-fourier_range": "expanded"}
        for sel, v in want.items():
            assert p.page.input_value(sel) == v, (sel, p.page.input_value(sel), v)
        assert p.page.is_checked("#p-out-horizon") and p.page.is_checked("#p-out-fourier")
        # The form builds the same query: Bake would make the same bake (200, same id).
        with p.page.expect_response(lambda r: r.request.method == "POST" and "/v1/bakes" in r.url) as info:
            p.page.set_input_files("#file", {"name": "n.png", "mimeType": "image/png",
                                             "buffer": buf.getvalue()})
            p.page.wait_for_function("() => document.getElementById('file-info').textContent.includes('n.png')"
                                     " && !document.getElementById('file-info').textContent.endsWith('…')")
            p.page.click("#bake")
        assert info.value.status == 200
        assert info.value.header_value("location").endswith(bake["id"])
        # Another bake from the recent list: its parameters replace these.
        p.page.click("#refresh")
        link = p.page.locator(f'#recent a[href="#{other["id"]}"]')
        link.wait_for()
        link.click()
        p.page.wait_for_function("id => window.__horizon.bake && window.__horizon.bake.id === id",
                                 arg=other["id"])
        assert p.page.input_value("#p-method") == "lengyel"
        assert p.page.input_value("#p-radius") == "3"
        assert p.page.input_value("#p-edge") == "wrap"
        assert not p.page.is_checked("#p-out-fourier")
        p.assert_no_errors()
    finally:
        p.close()


def test_relief_is_shown_before_the_bake(browser, srv):
    """After a file is chosen and before the bake: the relief in texels, with a warning below
    about 1 texel (the tester's 16-bit DEM spanning 236..1076 of 65535: 0.1 texel) and above
    the map's size."""
    from PIL import Image

    ramp = np.linspace(236, 1076, 64 * 64).reshape(64, 64).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(ramp).save(buf, format="PNG")
    p = Page(browser, srv.url + "/")
    try:
        p.page.set_input_files("#file", {"name": "dem.png", "mimeType": "image/png",
                                         "buffer": buf.getvalue()})
        p.page.wait_for_function("() => document.getElementById('relief').dataset.texels")
        texels = float(p.page.get_attribute("#relief", "data-texels"))
        assert abs(texels - (1076 - 236) / 65535 * 8) < 1e-4, texels
        assert p.page.get_attribute("#relief", "class") == "warn"
        assert "Below 1 texel" in p.page.text_content("#relief")
        p.page.fill("#p-height_scale", "400")
        texels = float(p.page.get_attribute("#relief", "data-texels"))
        assert 5 < texels < 6 and p.page.get_attribute("#relief", "class") == "muted", texels
        p.page.fill("#p-height_scale", "40000")
        assert p.page.get_attribute("#relief", "class") == "warn"
        assert "map's size" in p.page.text_content("#relief")
        p.assert_no_errors()
    finally:
        p.close()


def test_progress_and_errors_are_in_view_at_1280x900(browser, srv):
    """At 1280×900 (the Page's viewport) the progress bar and an error are on screen with the
    Bake button that caused them (they were below the fold)."""
    p = Page(browser, srv.url + "/")
    try:
        p.page.set_input_files("#file", {"name": "x.png", "mimeType": "image/png",
                                         "buffer": b"not an image at all" * 8})
        p.page.click("#bake")
        p.page.wait_for_function("() => !document.getElementById('error').hidden")
        # Where the click on Bake left the page: the button, the progress bar and the error
        # all on screen at once.
        for sel in ("#bake", "#progress", "#error"):
            box = p.page.evaluate(
                "s => { const r = document.querySelector(s).getBoundingClientRect();"
                " return [r.top, r.bottom, window.innerHeight]; }", sel)
            top, bottom, height = box
            assert 0 <= top and bottom <= height, (sel, box)
        p.assert_no_errors(allow_http_errors=True)
    finally:
        p.close()


def _dem_geotiff() -> bytes:
    """A small projected DEM as a GIS user has it: float32, EPSG:32632, 30 m cells, nodata -9999
    in one corner; a north-south ridge so a low sun casts a shadow."""
    import rasterio
    from rasterio.io import MemoryFile
    from rasterio.transform import from_origin

    h, w = 40, 48
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    dem = (300.0 + 250.0 * np.exp(-((x - 20.0) ** 2) / 10.0) + 1.5 * y).astype(np.float32)
    dem[:3, :4] = -9999.0
    with MemoryFile() as mem:
        with mem.open(driver="GTiff", width=w, height=h, count=1, dtype="float32",
                      crs=rasterio.crs.CRS.from_epsg(32632), nodata=-9999.0,
                      transform=from_origin(500000.0, 5500000.0, 30.0, 30.0)) as ds:
            ds.write(dem, 1)
        return mem.read()


def _shown_image(page, img_id: str) -> np.ndarray:
    """What the page shows in <img id=img_id>, drawn to a canvas at its natural size: (grey,
    alpha) per pixel, rows from the top."""
    rgba = _shown_rgba(page, img_id)
    assert np.array_equal(rgba[..., 0], rgba[..., 1]) and np.array_equal(rgba[..., 0], rgba[..., 2])
    return np.stack([rgba[..., 0], rgba[..., 3]], axis=-1)


def _shown_rgba(page, img_id: str) -> np.ndarray:
    """What the page shows in <img id=img_id>, drawn to a canvas at its natural size: RGBA per
    pixel, rows from the top."""
    from harness import decode_rgba

    px = page.evaluate(
        """id => {
          const img = document.getElementById(id);
          const c = document.createElement('canvas');
          c.width = img.naturalWidth;
          c.height = img.naturalHeight;
          const g = c.getContext('2d');
          g.drawImage(img, 0, 0);
          const b = g.getImageData(0, 0, c.width, c.height).data;
          let s = '';
          for (let i = 0; i < b.length; i += 0x8000) s += String.fromCharCode(...b.subarray(i, i + 0x8000));
          return { width: c.width, height: c.height, rgba: btoa(s) };
        }""", img_id)
    return decode_rgba(px)


def test_surface_maps_are_shown_as_the_server_wrote_them(browser, srv):
    """Issue 45: ticking "surface maps" bakes outputs normal,ao,bent_normal; the page then shows
    each map, pixel for pixel the server's PNG, with its convention; a bake without them hides
    the panel."""
    p = Page(browser, srv.url + "/")
    page = p.page
    res = upload(page, str(TERRAIN), {"method": "exact", "radius": "8", "height_scale": TRUE_SCALE})
    bake_id = bake_id_of(res)
    wait_loaded(page, bake_id)
    assert page.is_hidden("#surface")
    page.set_checked("#p-out-surface", True)
    with page.expect_response(lambda r: r.request.method == "POST" and "/v1/bakes" in r.url) as info:
        page.click("#bake")
    res = info.value
    assert res.status == 202, res.text()
    assert "outputs=horizon%2Cnormal%2Cao%2Cbent_normal" in res.request.url, res.request.url
    bake_id = bake_id_of(res)
    wait_loaded(page, bake_id)
    for name in ["normal", "ao", "bent_normal"]:
        page.wait_for_function(
            "id => !document.getElementById(id + '-fig').hidden", arg=name, timeout=60_000)
        status, _, body = srv.request(f"/v1/bakes/{bake_id}/{name}")
        assert status == 200, name
        want = np.asarray(Image.open(io.BytesIO(body)).convert("RGBA"))
        assert np.array_equal(_shown_rgba(page, f"{name}-image"), want), name
    assert "normal_convention opengl" in page.text_content("#surface-note")
    assert page.is_checked("#p-out-surface")
    p.assert_no_errors()
    p.close()


def _read_geotiff(body: bytes):
    from rasterio.io import MemoryFile

    with MemoryFile(body) as mem, mem.open() as ds:
        return ds.read(1), ds.nodata, ds.crs.to_epsg()


def test_dem_gets_its_defaults_crs_svf_and_shadow(browser, srv):
    """Issue 24: a GeoTIFF DEM dropped on the page is sent without height_scale/edge (the server
    resolves 1/30 and none), the page shows its CRS and cell size, and the SVF and the shadow of
    a sun the user sets appear with the values of the server's GeoTIFFs (read by GDAL)."""
    if os.environ.get("CI") == "true":
        import rasterio  # noqa: F401  (CI installs it: .ci/run)
    else:
        pytest.importorskip("rasterio")
    p = Page(browser, srv.url + "/")
    page = p.page
    payload = {"name": "dem_utm.tif", "mimeType": "image/tiff", "buffer": _dem_geotiff()}
    page.set_input_files("#file", payload)
    page.wait_for_function("() => document.getElementById('file-info').textContent.includes('48 × 40')")
    assert "DEM: defaults from the file" in page.text_content("#dem-info")
    assert page.is_checked("#p-dem")
    assert page.is_disabled("#p-height_scale") and page.is_disabled("#p-edge")
    # Issue 44: the form shows the DEM defaults (a line of sight to the edge, the terrain
    # products) and sends neither method nor radius, so the server's resolution (sweep,
    # unlimited) is what bakes; the details read as a person writes numbers.
    assert page.input_value("#p-method") == "sweep"
    assert page.input_value("#p-radius-mode") == "unlimited"
    assert page.is_checked("#p-out-terrain")
    with page.expect_response(lambda r: r.request.method == "POST" and "/v1/bakes" in r.url) as info:
        page.click("#bake")
    res = info.value
    assert res.status == 202, res.text()
    query = res.request.url.split("?", 1)[-1]
    assert "method" not in query and "radius" not in query, query
    first = srv.json(f"/v1/bakes/{bake_id_of(res)}")[1]
    assert (first["params"]["method"], first["params"]["radius"]) == ("sweep", "unlimited"), first
    page.wait_for_function(
        "() => document.getElementById('dem-info').dataset.epsg === '32632'", timeout=60_000)
    first_text = page.text_content("#dem-info")
    assert "cell size 30 m;" in first_text and "height_scale 0.03333333333," in first_text, first_text
    assert "sweep, radius unlimited" in first_text, first_text
    set_params(page, {"method": "exact", "radius": "unlimited"})
    page.set_checked("#p-out-terrain", True)
    with page.expect_response(lambda r: r.request.method == "POST" and "/v1/bakes" in r.url) as info:
        page.click("#bake")
    res = info.value
    assert res.status == 202, res.text()
    query = res.request.url.split("?", 1)[1]
    assert "height_scale" not in query and "edge" not in query, query
    assert "outputs=horizon%2Cangles%2Csvf" in query, query
    bake_id = bake_id_of(res)
    status, bake = srv.json(f"/v1/bakes/{bake_id}")
    assert status == 200
    assert bake["params"]["edge"] == "none", bake["params"]
    assert abs(bake["params"]["height_scale"] - 1 / 30) < 1e-12, bake["params"]
    assert bake["georeferencing"]["epsg"] == 32632, bake
    # The page shows the server's CRS and cell size.
    page.wait_for_function(
        "() => document.getElementById('dem-info').dataset.epsg === '32632'", timeout=60_000)
    dem_text = page.text_content("#dem-info")
    assert "EPSG:32632" in dem_text and "cell size 30 m;" in dem_text, dem_text
    assert "edge none" in dem_text, dem_text
    meta = page.text_content("#meta")
    assert "EPSG:32632" in meta and "30 m" in meta, meta

    # The SVF appears once the bake succeeded; its pixels are the GeoTIFF's values on 8 bits.
    page.wait_for_selector("#svf-image[data-query]", state="visible", timeout=600_000)
    shown = _shown_image(page, "svf-image")
    status, _, body = srv.request(f"/v1/bakes/{bake_id}/svf")
    assert status == 200
    svf, nodata, epsg = _read_geotiff(body)
    assert epsg == 32632 and nodata == -9999.0
    assert shown.shape == svf.shape + (2,), (shown.shape, svf.shape)
    hole = svf == nodata
    assert hole[0, 0] and hole[2, 3] and not hole[10, 10]
    want = np.floor(svf.astype(np.float64) * 255 + 0.5).clip(0, 255).astype(np.uint8)
    for r, c in [(0, 0), (2, 3), (10, 10), (20, 20), (39, 47), (5, 30)]:
        if hole[r, c]:
            assert shown[r, c, 1] == 0, (r, c, shown[r, c])
        else:
            assert tuple(shown[r, c]) == (want[r, c], 255), (r, c, shown[r, c], svf[r, c])
    assert np.array_equal(shown[..., 1] == 0, hole)
    assert np.array_equal(shown[..., 0][~hole], want[~hole])
    assert want[~hole].min() < 250, "the ridge occludes part of the sky"

    # The shadow of a low sun from the west (azimuth 180° counted from east).
    page.fill("#sun-azimuth", "180")
    page.fill("#sun-elevation", "10")
    page.click("#show-shadow")
    page.wait_for_selector("#shadow-image[data-query*='sun_elevation=10']", state="visible",
                           timeout=120_000)
    shown = _shown_image(page, "shadow-image")
    status, _, body = srv.request(f"/v1/bakes/{bake_id}/shadow?sun_azimuth=180&sun_elevation=10")
    assert status == 200
    shadow, nodata, epsg = _read_geotiff(body)
    assert epsg == 32632 and nodata == 255
    want = np.where(shadow == 1, 255, 0).astype(np.uint8)
    for r, c in [(0, 0), (10, 10), (20, 25), (20, 30), (39, 47)]:
        if shadow[r, c] == 255:
            assert shown[r, c, 1] == 0, (r, c)
        else:
            assert tuple(shown[r, c]) == (want[r, c], 255), (r, c, shown[r, c], shadow[r, c])
    assert np.array_equal(shown[..., 1] == 0, shadow == 255)
    ok = shadow != 255
    assert np.array_equal(shown[..., 0][ok], want[ok])
    assert (shadow == 0).sum() > 0 and (shadow == 1).sum() > 0, "a 10° sun shadows part of it"
    assert "azimuth 180°, elevation 10°" in page.text_content("#shadow-caption")
    p.assert_no_errors()
    p.close()
