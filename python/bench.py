"""The package's cost against the CLI's, on one 2048² map (issue 42: within 1.1×).

    cargo build --profile python --bin horizon-bake      # the CLI with the wheel's codegen
    pip install ./python                                 # the wheel (profile `python`)
    python python/bench.py [--cli target/python/horizon-bake] [--size 2048] [--repeat 3]

For each case it times, in the same run, on the same map:
- the CLI: `horizon-bake bake map.png -o DIR --format png8`, the whole process (wall), and the
  bake alone as its bake.json reports it (`timings_ms.bake`: kernel + the PNG rows it streams);
- the package: `horizon_bake.bake(array)` (wall, from the numpy array to the numpy layers).
Best of `--repeat` runs each. Prints a table: ms, Mtexel/s, and the package's time as a ratio of
the CLI's bake and of the CLI's whole run.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import tempfile
import time

import sys

import numpy as np
from PIL import Image

# The installed package, never the source folder beside this script (whose _native module is
# whatever `maturin develop` last built, a debug build by default): Python puts the script's
# folder first on sys.path.
HERE = pathlib.Path(__file__).resolve().parent
sys.path = [p for p in sys.path if pathlib.Path(p or ".").resolve() != HERE]
import horizon_bake as hb  # noqa: E402

ROOT = HERE.parent

CASES = [
    ("lengyel R16 (default)", {}, []),
    ("sweep unlimited", {"method": "sweep", "radius": "unlimited"},
     ["--method", "sweep", "--radius", "unlimited"]),
]


def terrain(n: int) -> np.ndarray:
    rng = np.random.default_rng(42)
    f = np.fft.fftfreq(n)
    k = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    k[0, 0] = 1.0
    spec = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / k ** 1.1
    h = np.real(np.fft.ifft2(spec))
    h = (h - h.min()) / (h.max() - h.min())
    return (h * 65535).round().astype(np.uint16)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cli", default=str(ROOT / "target" / "python" / "horizon-bake"))
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    n = args.size
    a = terrain(n)
    tmp = pathlib.Path(tempfile.mkdtemp())
    src = tmp / "map.png"
    Image.fromarray(a).save(src)
    mtex = n * n / 1e6
    print(f"{n}×{n} 16-bit map, best of {args.repeat}; CLI {args.cli}; package {hb.__version__} "
          f"at {pathlib.Path(hb.__file__).parent} ({os.cpu_count()} cores)")
    print("| case | CLI bake ms | CLI whole ms | package ms | package Mtexel/s | "
          "package / CLI bake | package / CLI whole |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, kw, flags in CASES:
        cli_bake, cli_whole, lib = [], [], []
        for i in range(args.repeat):
            out = tmp / f"out{i}"
            t = time.perf_counter()
            subprocess.run([args.cli, "bake", str(src), "-o", str(out), "--format", "png8",
                            *flags], check=True, capture_output=True)
            cli_whole.append((time.perf_counter() - t) * 1e3)
            cli_bake.append(json.loads((out / "bake.json").read_text())["timings_ms"]["bake"])
            shutil.rmtree(out)
            t = time.perf_counter()
            r = hb.bake(a, **kw)
            lib.append((time.perf_counter() - t) * 1e3)
            assert r.layers[0].shape == (n, n, 4)
        b, w, p = min(cli_bake), min(cli_whole), min(lib)
        print(f"| {name} | {b:.0f} | {w:.0f} | {p:.0f} | {mtex / (p / 1e3):.2f} | "
              f"{p / b:.3f} | {p / w:.3f} |")
    shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
