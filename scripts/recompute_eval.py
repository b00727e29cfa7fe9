#!/usr/bin/env python3
"""Recompute the eval's numbers for the default model from the baked files, independently.

`horizon-bake eval --dump DIR` writes, per corpus map, DIR/<map>/:
  horizon_0.png, horizon_1.png  the default model's 8-bit RGBA layers, as `bake` writes them
  truth.f32                     the ground truth s, little-endian f32, H*W*192, texel-major,
                                bin n at azimuth n*2*pi/192 (exact kernel, radius=unlimited)
  meta.json                     the numbers the eval reported for these layers

This script shares no code with the Rust crate: it decodes the PNGs with Pillow, rebuilds the
channel factors of SPEC section 3.3 from the azimuth, blends, and applies SPEC section 4:
  shadow error  = fraction of texels where (L_z > s) differs from (L_z > s_true), per elevation
                  (5, 10, 20, 30, 45, 60 deg) as the mean over 24 azimuths (0, 15, ..., 345)
  horizon error = mean |asin(s(phi)) - asin(s_true(phi))| in degrees over 64 azimuths.
It exits non-zero if any number differs from the eval's by more than the tolerance.

    pip install numpy pillow
    python3 scripts/recompute_eval.py DIR [--tol 1e-4]

With --check-truth N it also re-derives the ground truth at N random texels by marching the
bilinear surface (SPEC section 3.2) in small steps, and fails if the largest difference exceeds
--truth-tol (0.02 in s by default; measured differences are 0.001-0.008).
"""
import argparse
import json
import math
import os
import sys

import numpy as np
from PIL import Image


def factors(phi):
    """Signed 4-slot channel factors for light azimuth phi (radians), SPEC section 3.3."""
    pos = (phi / (math.pi / 4)) % 8.0
    c = int(math.floor(pos))
    t = pos - c
    if c >= 8:
        c, t = 0, 0.0
    f = np.zeros(4)
    for ch, w in ((c, 1.0 - t), ((c + 1) % 8, t)):
        f[ch % 4] += -w if ch >= 4 else w
    return f


def blend(f, layer0, layer1):
    """s = sum max(f,0)*layer0 + max(-f,0)*layer1 over the 4 slots (Lengyel eq. 5.3)."""
    return layer0 @ np.maximum(f, 0.0) + layer1 @ np.maximum(-f, 0.0)


def recompute(sub):
    meta = json.load(open(os.path.join(sub, "meta.json")))
    w, h, nb = meta["width"], meta["height"], meta["truth_bins"]
    layers = [
        np.asarray(Image.open(os.path.join(sub, f"horizon_{k}.png")).convert("RGBA"), dtype=np.float64)
        .reshape(h * w, 4)
        / 255.0
        for k in range(2)
    ]
    truth = np.fromfile(os.path.join(sub, "truth.f32"), dtype="<f4").astype(np.float64).reshape(h * w, nb)
    n_az = meta["shadow_azimuths"]
    shadow = []
    for el in meta["elevations_deg"]:
        lz = math.sin(math.radians(el))
        wrong = 0
        for a in range(n_az):
            phi = 2 * math.pi * a / n_az
            s = blend(factors(phi), *layers)
            s_true = truth[:, a * (nb // n_az)]
            wrong += np.count_nonzero((lz > s) != (lz > s_true))
        shadow.append(wrong / (w * h * n_az))
    n_h = meta["horizon_azimuths"]
    err = 0.0
    for a in range(n_h):
        phi = 2 * math.pi * a / n_h
        s = np.clip(blend(factors(phi), *layers), 0.0, 1.0)
        a_true = np.arcsin(np.clip(truth[:, a * (nb // n_h)], 0.0, 1.0))
        err += np.abs(np.arcsin(s) - a_true).sum()
    horizon = math.degrees(err / (w * h * n_h))
    return meta, shadow, horizon


def march_truth(heights, w, h, edge, x, y, phi, step=0.05):
    """sin of the line-of-sight horizon at texel (x, y) (image coords, y_axis=up), by marching."""
    h0 = heights[y, x]
    ux, uy = math.cos(phi), -math.sin(phi)  # tangent +y is toward the top row
    radius = max(w, h)
    best = 0.0
    s = step
    while s <= radius + 1e-9:
        px, py = x + s * ux, y + s * uy
        if edge == "none" and not (0 <= px <= w - 1 and 0 <= py <= h - 1):
            break
        x0, y0 = math.floor(px), math.floor(py)
        fx, fy = px - x0, py - y0

        def at(i, j):
            if edge == "wrap":
                return heights[j % h, i % w]
            return heights[min(max(j, 0), h - 1), min(max(i, 0), w - 1)]

        v = (at(x0, y0) * (1 - fx) * (1 - fy) + at(x0 + 1, y0) * fx * (1 - fy)
             + at(x0, y0 + 1) * (1 - fx) * fy + at(x0 + 1, y0 + 1) * fx * fy)
        best = max(best, math.atan2(v - h0, s))
        s += step
    return math.sin(best)


def check_truth(sub, n, rng):
    meta = json.load(open(os.path.join(sub, "meta.json")))
    w, h, nb = meta["width"], meta["height"], meta["truth_bins"]
    heights = np.fromfile(os.path.join(sub, "heights.f32"), dtype="<f4").astype(np.float64).reshape(h, w)
    truth = np.fromfile(os.path.join(sub, "truth.f32"), dtype="<f4").reshape(h * w, nb)
    worst = 0.0
    for _ in range(n):
        x, y, b = rng.integers(w), rng.integers(h), rng.integers(nb)
        got = truth[y * w + x, b]
        want = march_truth(heights, w, h, meta["edge"], x, y, 2 * math.pi * b / nb)
        worst = max(worst, abs(float(got) - want))
    return worst


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir")
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--check-truth", type=int, default=0, metavar="N")
    ap.add_argument("--truth-tol", type=float, default=0.02,
                    help="largest |s_truth - s_march| accepted (the 0.05-texel march undershoots)")
    args = ap.parse_args()
    subs = sorted(d for d in os.listdir(args.dir) if os.path.exists(os.path.join(args.dir, d, "meta.json")))
    if not subs:
        sys.exit(f"{args.dir}: no <map>/meta.json found (run `horizon-bake eval --dump {args.dir}`)")
    bad = 0
    checks = 0
    rng = np.random.default_rng(1)
    for d in subs:
        sub = os.path.join(args.dir, d)
        meta, shadow, horizon = recompute(sub)
        want = meta["metrics"]
        diffs = [abs(a - b) for a, b in zip(shadow, want["shadow_by_elevation"])]
        diffs.append(abs(sum(shadow) / len(shadow) - want["shadow_error"]))
        diffs.append(abs(horizon - want["horizon_error_deg"]))
        ok = max(diffs) <= args.tol
        bad += not ok
        checks += 1
        print(
            f"{'ok ' if ok else 'BAD'} {d:<12} {meta['model']}: shadow {100 * sum(shadow) / len(shadow):.4f}% "
            f"(eval {100 * want['shadow_error']:.4f}%), horizon {horizon:.5f} deg "
            f"(eval {want['horizon_error_deg']:.5f}), max |diff| {max(diffs):.2e}"
        )
        if args.check_truth:
            worst = check_truth(sub, args.check_truth, rng)
            ok_truth = worst <= args.truth_tol
            bad += not ok_truth
            checks += 1
            print(f"    {'ok ' if ok_truth else 'BAD'} ground truth vs a fine march at {args.check_truth} "
                  f"texel/azimuths: max |ds| {worst:.4f} (tolerance {args.truth_tol})")
    print(f"{checks - bad} passed, {bad} failed")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
