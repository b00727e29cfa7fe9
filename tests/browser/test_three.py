"""three.js's own KTX2Loader reads our KTX2 files as they are (issue 45): npm `three` (pinned in
tests/browser/three/package.json, `npm ci` there) in Debian's chromium, WebGL2 on SwiftShader.

Every variant three.js can represent is loaded through `KTX2Loader` (with `detectSupport` on a
real `WebGLRenderer`), uploaded by three.js, drawn with `texelFetch` (one fragment per texel, a
float render target) and read back, so what is compared is what a three.js material samples:
- `texture_layout=separate` RGBA8: every texel equal to the PNG layers, and the surface maps
  (`normal.ktx2`, `ao.ktx2`, `bent_normal.ktx2`) equal to their PNGs; with `mips=full` and
  zstd, level k equal to the box filter of level k − 1 (mean rounding half up, SPEC §8)
  computed here from the PNG;
- float32: within half a 16-bit step of `--format png16`'s layers;
- BC7 with mips and BC5 (four RG files): every level equal to PyPI `texture2ddecoder`'s decode
  of the same blocks, level 0 within the block codec's error of the PNG layers;
- the cube map with `texture_precision=bc7`: a `CompressedCubeTexture`, every face sampled at
  its texel centres equal to `texture2ddecoder`'s decode, close to `cube_N.png`;
- what three.js cannot represent, pinned so the README's advice stays true: the default
  2-layer array loads as a plain 2D texture holding layer 0 only (three.js has no raw array
  textures; use `separate`), and the SNORM cube map is refused ("Unsupported vkFormat: 38"; use
  `texture_precision=bc7`).
npm `ktx-parse` (a reader we did not write) reads every file's key/value data: `KTXorientation`
`rd`, `KTXwriter`, and the `horizon-bake` conventions of the bake.

Run: HORIZON_BIN=target/debug/horizon-bake python -m pytest -q tests/browser/test_three.py
"""

from __future__ import annotations

import base64
import functools
import http.server
import json
import os
import struct
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import sync_playwright

from harness import ROOT, TERRAIN, chromium_or_skip, launch, server_binary

NODE_MODULES = ROOT / "tests" / "browser" / "three" / "node_modules"

PAGE = """<!doctype html>
<html><head><meta charset="utf-8">
<script type="importmap">
{"imports": {"three": "/three/build/three.module.js", "three/addons/": "/three/examples/jsm/"}}
</script></head>
<body><canvas id="c" width="4" height="4"></canvas>
<script type="module">
import * as THREE from 'three';
import { KTX2Loader } from 'three/addons/loaders/KTX2Loader.js';
import { read } from '/ktx-parse/dist/ktx-parse.modern.js';

const renderer = new THREE.WebGLRenderer({ canvas: document.getElementById('c') });
const loader = new KTX2Loader().detectSupport(renderer);
const scene = new THREE.Scene();
const camera = new THREE.Camera();
const quad = new THREE.Mesh(new THREE.PlaneGeometry(2, 2));
quad.frustumCulled = false;
scene.add(quad);
const VS = `in vec3 position; void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }`;
const FS_2D = `precision highp float; precision highp int;
uniform highp sampler2D tex; uniform int lod; out vec4 o;
void main() { o = texelFetch(tex, ivec2(gl_FragCoord.xy), lod); }`;
// The cube map's texel centres: ((u + 1/2)·2/S − 1) on the face, the OpenGL face table.
const FS_CUBE = `precision highp float; precision highp int;
uniform highp samplerCube tex; uniform int face; uniform float size; out vec4 o;
void main() {
  vec2 c = gl_FragCoord.xy * 2.0 / size - 1.0;
  float sc = c.x, tc = c.y;
  vec3 d;
  if (face == 0) d = vec3(1.0, -tc, -sc);
  else if (face == 1) d = vec3(-1.0, -tc, sc);
  else if (face == 2) d = vec3(sc, 1.0, tc);
  else if (face == 3) d = vec3(sc, -1.0, -tc);
  else if (face == 4) d = vec3(sc, -tc, 1.0);
  else d = vec3(-sc, -tc, -1.0);
  o = textureLod(tex, d, 0.0);
}`;
const textures = {};

function b64(bytes) {
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) {
    s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  }
  return btoa(s);
}

// Loads `url` through KTX2Loader: what three.js made of it, or the error it gave.
window.load = async (url) => {
  try {
    const tex = await loader.loadAsync(url);
    textures[url] = tex;
    const img = tex.isCompressedCubeTexture ? tex.image[0] : tex.image;
    return {
      type: tex.constructor.name,
      cube: !!tex.isCubeTexture,
      array: !!(tex.isDataArrayTexture || tex.isCompressedArrayTexture),
      width: img.width, height: img.height,
      levels: tex.isCompressedCubeTexture ? tex.image[0].mipmaps.length : tex.mipmaps.length,
    };
  } catch (e) {
    return { error: String(e && e.message || e) };
  }
};

// Draws level `lod` (or cube face `face`) of a loaded texture, one fragment per texel, into a
// float target and reads it back: rows from texel row 0, RGBA float32, base64.
window.draw = (url, width, height, lod, face) => {
  const tex = textures[url];
  tex.minFilter = THREE.NearestFilter;
  tex.magFilter = THREE.NearestFilter;
  tex.needsUpdate = true;
  const cube = face !== null;
  quad.material = new THREE.RawShaderMaterial({
    glslVersion: THREE.GLSL3, vertexShader: VS, fragmentShader: cube ? FS_CUBE : FS_2D,
    uniforms: { tex: { value: tex }, lod: { value: lod }, face: { value: face ?? 0 },
                size: { value: width } },
  });
  const rt = new THREE.WebGLRenderTarget(width, height, {
    type: THREE.FloatType, depthBuffer: false,
    minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter,
  });
  renderer.setRenderTarget(rt);
  renderer.render(scene, camera);
  const out = new Float32Array(width * height * 4);
  renderer.readRenderTargetPixels(rt, 0, 0, width, height, out);
  renderer.setRenderTarget(null);
  rt.dispose();
  quad.material.dispose();
  return b64(new Uint8Array(out.buffer));
};

// ktx-parse's reading of the header and the key/value data.
window.parse = async (url) => {
  const c = read(new Uint8Array(await (await fetch(url)).arrayBuffer()));
  const kv = {};
  for (const [k, v] of Object.entries(c.keyValue)) {
    kv[k] = (typeof v === 'string' ? v : new TextDecoder().decode(v)).replace(/\\0+$/, '');
  }
  return { vkFormat: c.vkFormat, layerCount: c.layerCount, faceCount: c.faceCount,
           levels: c.levels.length, kv };
};
window.ready = true;
</script></body></html>
"""


def modules_or_skip() -> Path:
    """tests/browser/three/node_modules; skips (fails under CI=true) when `npm ci` was not run."""
    if (NODE_MODULES / "three" / "build" / "three.module.js").exists():
        return NODE_MODULES
    msg = f"{NODE_MODULES} is missing (npm ci --prefix tests/browser/three)"
    if os.environ.get("CI") == "true":
        pytest.fail(msg)
    pytest.skip(msg)


def run(*args: str) -> None:
    subprocess.run([str(server_binary()), *args], check=True, capture_output=True)


# name: the CLI flags of one bake of TERRAIN into its own directory.
BAKES = {
    "raw8": ["--format", "png8,ktx2", "--texture-layout", "separate",
             "--outputs", "horizon,normal,ao,bent_normal"],
    "mips_zstd": ["--format", "png8,ktx2", "--texture-layout", "separate", "--mips", "full",
                  "--supercompression", "zstd"],
    "float32": ["--format", "png16,ktx2", "--texture-layout", "separate",
                "--texture-precision", "float32", "--y-axis", "down", "--encoding", "sqrt"],
    "bc7": ["--format", "png8,ktx2", "--texture-layout", "separate", "--texture-precision", "bc7",
            "--mips", "full"],
    "bc5": ["--format", "png8,ktx2", "--texture-layout", "separate", "--texture-precision", "bc5"],
    "array": ["--format", "png8,ktx2"],
}


@pytest.fixture(scope="module")
def site():
    """A loopback HTTP server for the page, three.js, ktx-parse and the baked files."""
    modules = modules_or_skip()
    root = Path(tempfile.mkdtemp(prefix="hb-three-"))
    (root / "index.html").write_text(PAGE)
    (root / "three").symlink_to(modules / "three")
    (root / "ktx-parse").symlink_to(modules / "ktx-parse")
    for name, flags in BAKES.items():
        run("bake", str(TERRAIN), "-o", str(root / name), *flags)
    run("cubemap", "-o", str(root / "cube_bc7"), "--format", "png8,ktx2", "--texture-precision", "bc7")
    run("cubemap", "-o", str(root / "cube"), "--format", "ktx2")
    handler = functools.partial(_Quiet, directory=str(root))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def page(site):
    exe = chromium_or_skip()
    root, url = site
    with sync_playwright() as p:
        b = launch(p, exe)
        pg = b.new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(url + "/index.html")
        pg.wait_for_function("() => window.ready === true", timeout=60_000)
        try:
            yield pg, root, errors
        finally:
            b.close()
    assert not errors, errors


def png(path: Path) -> np.ndarray:
    """RGBA8 samples of a PNG (Pillow)."""
    return np.asarray(Image.open(path).convert("RGBA"))


def png16(path: Path) -> np.ndarray:
    """A 16-bit RGBA PNG's samples, read by GDAL (rasterio): Pillow reads them as 8-bit."""
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # NotGeoreferencedWarning
        with rasterio.open(path) as ds:
            assert ds.dtypes[0] == "uint16", ds.dtypes
            return np.moveaxis(ds.read(), 0, -1)


def drawn(pg, url: str, w: int, h: int, lod: int = 0, face: int | None = None) -> np.ndarray:
    b = base64.b64decode(pg.evaluate("([u, w, h, l, f]) => draw(u, w, h, l, f)", [url, w, h, lod, face]))
    return np.frombuffer(b, np.float32).reshape(h, w, 4)


def loaded(pg, url: str) -> dict:
    info = pg.evaluate("(u) => load(u)", url)
    assert "error" not in info, f"three.js refused {url}: {info['error']}"
    return info


def ktx2_levels(path: Path) -> list[bytes]:
    """Each level's stored bytes (KTX2 level index at byte 80: offset, length, uncompressed)."""
    b = path.read_bytes()
    count = struct.unpack_from("<I", b, 40)[0]
    return [b[o:o + n] for o, n, _ in (struct.unpack_from("<QQQ", b, 80 + 24 * k) for k in range(count))]


def bgra_to_rgba(raw: bytes, w: int, h: int) -> np.ndarray:
    return np.frombuffer(raw, np.uint8).reshape(h, w, 4)[..., [2, 1, 0, 3]]


def box(level: np.ndarray) -> np.ndarray:
    """SPEC §8 `box`: the mean of the 2×2 parent texels, rounding half up (even sizes here)."""
    a = level.astype(np.int32)
    s = a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]
    return ((s + 2) // 4).astype(np.uint8)


def test_separate_rgba8_layers_are_the_png_layers(page):
    pg, root, _ = page
    for i in range(2):
        want = png(root / "raw8" / f"horizon_{i}.png")
        info = loaded(pg, f"/raw8/horizon_{i}.ktx2")
        assert (info["type"], info["width"], info["height"]) == ("DataTexture", 128, 128), info
        got = np.rint(drawn(pg, f"/raw8/horizon_{i}.ktx2", 128, 128) * 255).astype(np.int32)
        assert np.array_equal(got, want.astype(np.int32)), f"layer {i}: max {np.abs(got - want).max()}"


def test_surface_maps_load_as_2d_textures(page):
    pg, root, _ = page
    for name in ["normal", "ao", "bent_normal"]:
        img = Image.open(root / "raw8" / f"{name}.png")
        want = np.asarray(img.convert("RGBA")).astype(np.int32)
        if img.mode == "L":
            want[..., :3] = np.asarray(img)[..., None]
        info = loaded(pg, f"/raw8/{name}.ktx2")
        assert (info["type"], info["width"]) == ("DataTexture", 128), info
        got = np.rint(drawn(pg, f"/raw8/{name}.ktx2", 128, 128) * 255).astype(np.int32)
        assert np.array_equal(got, want), f"{name}: max {np.abs(got - want).max()}"


def test_zstd_mip_chain_loads_level_by_level(page):
    pg, root, _ = page
    for i in range(2):
        url = f"/mips_zstd/horizon_{i}.ktx2"
        info = loaded(pg, url)
        assert info["levels"] == 8, info  # 128² down to 1×1
        want = png(root / "mips_zstd" / f"horizon_{i}.png")
        for lod in range(8):
            n = 128 >> lod
            got = np.rint(drawn(pg, url, n, n, lod) * 255).astype(np.int32)
            assert np.array_equal(got, want.astype(np.int32)), f"layer {i} level {lod}"
            want = box(want)


def test_float32_layers_are_the_16_bit_layers(page):
    pg, root, _ = page
    for i in range(2):
        url = f"/float32/horizon_{i}.ktx2"
        assert loaded(pg, url)["type"] == "DataTexture"
        want = png16(root / "float32" / f"horizon_{i}.png").astype(np.float64) / 65535
        got = drawn(pg, url, 128, 128).astype(np.float64)
        assert np.abs(got - want).max() <= 0.5 / 65535 + 1e-7, f"layer {i}"


def test_bc7_and_bc5_blocks_decode_as_texture2ddecoder_does(page):
    import texture2ddecoder as t2d

    pg, root, _ = page
    for i in range(2):
        url = f"/bc7/horizon_{i}.ktx2"
        info = loaded(pg, url)
        assert (info["type"], info["levels"]) == ("CompressedTexture", 8), info
        levels = ktx2_levels(root / "bc7" / f"horizon_{i}.ktx2")
        for lod, blocks in enumerate(levels):
            n = 128 >> lod
            want = bgra_to_rgba(t2d.decode_bc7(blocks, n, n), n, n).astype(np.int32)
            got = np.rint(drawn(pg, url, n, n, lod) * 255).astype(np.int32)
            assert np.abs(got - want).max() <= 1, f"bc7 layer {i} level {lod}"
        layer = png(root / "bc7" / f"horizon_{i}.png").astype(np.float64)
        level0 = bgra_to_rgba(t2d.decode_bc7(levels[0], 128, 128), 128, 128).astype(np.float64)
        psnr = 10 * np.log10(255**2 / np.mean((level0 - layer) ** 2))
        assert psnr >= 35, f"bc7 layer {i}: {psnr:.1f} dB against the PNG layer"
    for k in range(4):
        url = f"/bc5/horizon_{k}.ktx2"
        assert loaded(pg, url)["type"] == "CompressedTexture"
        blocks = ktx2_levels(root / "bc5" / f"horizon_{k}.ktx2")[0]
        # texture2ddecoder writes BC5's red and green into its BGRA output's R and G.
        want = bgra_to_rgba(t2d.decode_bc5(blocks, 128, 128), 128, 128)[..., :2].astype(np.int32)
        got = np.rint(drawn(pg, url, 128, 128) * 255).astype(np.int32)[..., :2]
        assert np.abs(got - want).max() <= 1, f"bc5 file {k}"
        layer = png(root / "bc5" / f"horizon_{k // 2}.png")[..., 2 * (k % 2):2 * (k % 2) + 2]
        err = np.abs(got - layer.astype(np.int32))
        assert err.mean() < 1.0, f"bc5 file {k}: mean {err.mean():.2f} levels off the PNG"


def test_bc7_cube_map_is_a_cube_texture_with_the_faces(page):
    import texture2ddecoder as t2d

    pg, root, _ = page
    url = "/cube_bc7/cubemap.ktx2"
    info = loaded(pg, url)
    assert (info["type"], info["cube"], info["width"]) == ("CompressedCubeTexture", True, 16), info
    level = ktx2_levels(root / "cube_bc7" / "cubemap.ktx2")[0]
    face_bytes = len(level) // 6
    errors = []
    for face in range(6):
        blocks = level[face * face_bytes:(face + 1) * face_bytes]
        want = bgra_to_rgba(t2d.decode_bc7(blocks, 16, 16), 16, 16).astype(np.int32)
        got = np.rint(drawn(pg, url, 16, 16, 0, face) * 255).astype(np.int32)
        assert np.abs(got - want).max() <= 1, f"face {face}"
        errors.append(np.abs(got - png(root / "cube_bc7" / f"cube_{face}.png").astype(np.int32)))
    # As tests/encode/textures.rs measures the codec: the +Z face, where every azimuth meets at
    # the zenith, is the worst (mean 1.5 levels); no horizon shadows a light there.
    err = np.stack(errors)
    assert err.mean() < 1.0, f"mean {err.mean():.2f} levels off the PNG faces"


def test_what_three_cannot_represent_is_what_the_readme_says(page):
    pg, root, _ = page
    # The default 2-layer array: a plain 2D texture of layer 0 (layer 1 is lost).
    info = loaded(pg, "/array/horizon.ktx2")
    assert (info["type"], info["array"]) == ("DataTexture", False), info
    got = np.rint(drawn(pg, "/array/horizon.ktx2", 128, 128) * 255).astype(np.int32)
    assert np.array_equal(got, png(root / "array" / "horizon_0.png").astype(np.int32))
    # The SNORM cube map is refused by name.
    info = pg.evaluate("(u) => load(u)", "/cube/cubemap.ktx2")
    assert "Unsupported vkFormat: 38" in info.get("error", ""), info


def test_ktx_parse_reads_orientation_writer_and_conventions(page):
    pg, root, _ = page
    files = sorted(p.relative_to(root).as_posix() for p in root.glob("*/*.ktx2"))
    assert len(files) == 2 + 3 + 2 + 2 + 2 + 4 + 1 + 2, files
    for f in files:
        c = pg.evaluate("(u) => parse(u)", "/" + f)
        kv = c["kv"]
        assert kv["KTXorientation"] == "rd", (f, kv)
        assert kv["KTXwriter"].startswith("horizon-bake "), (f, kv)
        meta = json.loads(kv["horizon-bake"])
        if f.startswith("cube"):
            assert (meta["content"], c["faceCount"], c["layerCount"]) == ("cube_factors", 6, 0), (f, c)
            continue
        if meta["content"] in ("normal", "ao", "bent_normal"):
            assert f.startswith("raw8/") and c["layerCount"] == 0, (f, c)
            assert f.endswith(meta["content"] + ".ktx2"), (f, meta)
            continue
        assert meta["content"] == "horizon", (f, meta)
        sep = not f.startswith("array/")
        assert c["layerCount"] == (0 if sep else 2), (f, c)
        assert meta["layout"] == ("separate" if sep else "array"), (f, meta)
        down = f.startswith("float32/")
        assert (meta["y_axis"], meta["encoding"]) == (("down", "sqrt") if down else ("up", "linear")), (f, meta)
        k = int(f.split("_")[-1].split(".")[0]) if sep else None
        if f.startswith("bc5/"):
            assert meta["channels"] == [[2 * k, 2 * k + 1]], (f, meta)
        elif sep:
            assert meta["channels"] == [list(range(4 * k, 4 * k + 4))], (f, meta)
        else:
            assert meta["channels"] == [[0, 1, 2, 3], [4, 5, 6, 7]], (f, meta)
