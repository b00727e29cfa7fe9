#!/usr/bin/env python3
"""Reads horizon-bake's KTX2 and DDS textures with readers that share no code with the writers.

Issue 21 / SPEC §8. Every check uses code we did not write for the parts that matter: BC7/BC5
blocks are decoded by PyPI `texture2ddecoder`, zstd levels by PyPI `zstandard`, DDS files by
Pillow (level 0) and by this script's own header parser (the header flags, every level), PNG
layers by Pillow. The container layout (KTX2 level index, DDS data order) is parsed here from the
specifications, independently of src/encode.

Usage: check_textures.py CASES.json
CASES.json is a list of cases, each:
  {"dir": DIR, "file": "horizon.ktx2" | "horizon.dds" | "horizon_0.ktx2" | "cubemap.ktx2" | …,
   "precision": "unorm8" | "bc7" | "bc5", "mips": bool,
   "filter": "box" | "min" | "max" | "rebake",
   "zstd": bool, "layers": [[png_index, [c0, c1, ...]], ...],   # expected image per layer
   "min_psnr": 40.0, "legacy": bool, "cube": bool}
DIR holds horizon_0.png and horizon_1.png (or cube_0.png … cube_5.png) as the CLI wrote them.
With "rebake" each level is a bake of its own (the Rust test proves it bit for bit against the
library's bake); here every level's size is checked and at least one level must differ from the
box filter of the level above.
Prints one line per case; exits non-zero on the first failure (with the reason).
"""

import json
import math
import struct
import sys

import texture2ddecoder
import zstandard
from PIL import Image

KTX2_ID = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])
VK = {37: "unorm8", 38: "snorm8", 141: "bc5", 145: "bc7"}
DXGI = {28: "unorm8", 31: "snorm8", 83: "bc5", 98: "bc7"}


def fail(msg):
    raise AssertionError(msg)


def level_size(w, h, l):
    return max(1, w >> l), max(1, h >> l)


def image_bytes(fmt, w, h):
    if fmt in ("bc7", "bc5"):
        return ((w + 3) // 4) * ((h + 3) // 4) * 16
    return w * h * 4


def decode(fmt, data, w, h):
    """RGBA samples (ints; signed for snorm8) of one image."""
    if fmt == "bc7":
        bgra = texture2ddecoder.decode_bc7(bytes(data), w, h)
    elif fmt == "bc5":
        bgra = texture2ddecoder.decode_bc5(bytes(data), w, h)
    elif fmt == "unorm8":
        return list(data)
    elif fmt == "snorm8":
        return [b - 256 if b > 127 else b for b in data]
    else:
        fail(f"no decoder for {fmt}")
    out = bytearray(len(bgra))
    out[0::4], out[1::4], out[2::4], out[3::4] = bgra[2::4], bgra[1::4], bgra[0::4], bgra[3::4]
    if fmt == "bc5":
        # Only R and G are data; compare them alone (B and A set to what the writer fed: 0, 255).
        out[2::4] = bytes(len(out) // 4)
        out[3::4] = b"\xff" * (len(out) // 4)
    return list(out)


def downsample(src, w, h, filt):
    """SPEC §8 / src/encode/mips.rs, written again from the definition."""
    dw, dh = max(1, w // 2), max(1, h // 2)
    out = []
    for y in range(dh):
        ys = (min(2 * y, h - 1), min(2 * y + 1, h - 1))
        for x in range(dw):
            xs = (min(2 * x, w - 1), min(2 * x + 1, w - 1))
            for c in range(4):
                v = [src[(yy * w + xx) * 4 + c] for yy in ys for xx in xs]
                if filt == "box":
                    out.append((sum(v) + 2) // 4)
                elif filt == "min":
                    out.append(min(v))
                else:
                    out.append(max(v))
    return out


def psnr(a, b, peak=255.0):
    if len(a) != len(b):
        fail(f"sizes differ: {len(a)} vs {len(b)}")
    se = sum((x - y) ** 2 for x, y in zip(a, b))
    if se == 0:
        return math.inf
    return 10 * math.log10(peak * peak * len(a) / se)


def read_ktx2(raw):
    """(fmt, w, h, images per level, levels[level][image] bytes, zstd?)"""
    if raw[:12] != KTX2_ID:
        fail("not a KTX2 file")
    vk, type_size, w, h, depth, layers, faces, nlevels, scheme = struct.unpack_from("<9I", raw, 12)
    if vk not in VK:
        fail(f"unexpected vkFormat {vk}")
    fmt = VK[vk]
    if depth != 0:
        fail("pixelDepth must be 0")
    if type_size != (1 if fmt in ("bc7", "bc5", "unorm8", "snorm8") else 0):
        fail(f"typeSize {type_size} for {fmt}")
    if scheme not in (0, 2):
        fail(f"supercompression scheme {scheme}")
    images = max(layers, 1) * faces
    index = []
    for l in range(nlevels):
        index.append(struct.unpack_from("<3Q", raw, 80 + 24 * l))
    # Levels are stored smallest first: offsets must decrease with the level number.
    offs = [i[0] for i in index]
    if offs != sorted(offs, reverse=True):
        fail(f"levels not stored smallest first: {offs}")
    levels = []
    for l, (off, length, ulen) in enumerate(index):
        data = raw[off:off + length]
        if scheme == 2:
            data = zstandard.ZstdDecompressor().decompress(data, max_output_size=ulen)
        elif off % 4:
            fail(f"level {l} at an unaligned offset {off}")
        lw, lh = level_size(w, h, l)
        per = image_bytes(fmt, lw, lh)
        if len(data) != ulen or ulen != per * images:
            fail(f"level {l}: {len(data)} bytes, uncompressed {ulen}, want {per * images}")
        levels.append([data[i * per:(i + 1) * per] for i in range(images)])
    return fmt, w, h, images, levels, scheme == 2, faces == 6


def read_dds(raw, legacy):
    """(fmt, w, h, images, levels, header checks done)"""
    if raw[:4] != b"DDS ":
        fail("not a DDS file")
    (size, flags, h, w, pitch, depth, mips) = struct.unpack_from("<7I", raw, 4)
    if size != 124:
        fail("header size")
    if flags & 0x1007 != 0x1007 or not flags & 0x20000:
        fail(f"header flags {flags:#x}: CAPS|HEIGHT|WIDTH|PIXELFORMAT|MIPMAPCOUNT")
    pf_size, pf_flags = struct.unpack_from("<2I", raw, 76)
    fourcc = raw[84:88]
    bits, rm, gm, bm, am = struct.unpack_from("<5I", raw, 88)
    caps, caps2 = struct.unpack_from("<2I", raw, 108)
    cube = bool(caps2 & 0x200)
    if pf_size != 32:
        fail("pixel format size")
    if not legacy:
        if pf_flags != 0x4 or fourcc != b"DX10" or (bits, rm, gm, bm, am) != (0, 0, 0, 0, 0):
            fail(f"DX10 pixel format: flags {pf_flags:#x} FourCC {fourcc} masks {bits, rm, gm, bm, am}")
        dxgi, dim, misc, array, _alpha = struct.unpack_from("<5I", raw, 128)
        if dxgi not in DXGI or dim != 3:
            fail(f"DXGI format {dxgi}, dimension {dim}")
        fmt = DXGI[dxgi]
        if cube != bool(misc & 0x4):
            fail("cube flag in caps2 and in the DX10 misc flag differ")
        images = 6 * array if cube else array
        data_at = 148
    else:
        if pf_flags == 0x4 and fourcc == b"ATI2":
            fmt = "bc5"
        elif pf_flags == 0x41 and (bits, rm, gm, bm, am) == (32, 0xFF, 0xFF00, 0xFF0000, 0xFF000000):
            fmt = "unorm8"
        elif pf_flags == 0x80000 and bits == 32:
            fmt = "snorm8"
        else:
            fail(f"legacy pixel format: flags {pf_flags:#x} FourCC {fourcc}")
        images = 6 if cube else 1
        data_at = 128
    levels = [[None] * images for _ in range(mips)]
    at = data_at
    for i in range(images):
        for l in range(mips):
            lw, lh = level_size(w, h, l)
            n = image_bytes(fmt, lw, lh)
            levels[l][i] = raw[at:at + n]
            at += n
    if at != len(raw):
        fail(f"{len(raw) - at} bytes after the last level")
    return fmt, w, h, images, levels, False, cube


def expected_layers(case):
    """The images a texture's layers must hold (level 0), from the PNGs."""
    d = case["dir"]
    out = []
    cache = {}
    for png, channels in case["layers"]:
        if png not in cache:
            img = Image.open(f"{d}/{png}").convert("RGBA")
            cache[png] = (img.size, list(img.tobytes()))
        (w, h), px = cache[png]
        want = []
        for t in range(w * h):
            texel = [px[t * 4 + c] for c in channels]
            if case["precision"] == "bc5":
                texel = texel + [0, 255]
            want.extend(texel)
        out.append(want)
    return out


def check(case):
    path = f"{case['dir']}/{case['file']}"
    raw = open(path, "rb").read()
    legacy = case.get("legacy", False)
    if path.endswith(".ktx2"):
        fmt, w, h, images, levels, zstd, cube = read_ktx2(raw)
    else:
        fmt, w, h, images, levels, zstd, cube = read_dds(raw, legacy)
        if not cube:
            # Pillow reads level 0 of the first image on its own (it reads no SNORM cube).
            pil = Image.open(path)
            pil.load()
            if pil.size != (w, h):
                fail(f"Pillow reads {pil.size}, the header says {(w, h)}")
            got = list(pil.convert("RGBA").tobytes())
            if fmt == "bc5":
                got[2::4] = [0] * (w * h)
                got[3::4] = [255] * (w * h)
            want = expected_layers(case)[0]
            p = psnr(got, want)
            if p < case["min_psnr"]:
                fail(f"Pillow's level 0 of layer 0: {p:.1f} dB against the PNG layer")
    want_fmt = "snorm8" if case.get("cube") else case["precision"]
    if fmt != want_fmt:
        fail(f"format {fmt}, want {want_fmt}")
    if zstd != case.get("zstd", False):
        fail(f"zstd {zstd}")
    if cube != case.get("cube", False):
        fail("cube map flag")
    n_levels = (max(w, h).bit_length()) if case["mips"] else 1
    if len(levels) != n_levels:
        fail(f"{len(levels)} levels, want {n_levels}")
    if images != len(case["layers"]):
        fail(f"{images} images, want {len(case['layers'])}")
    exact = fmt in ("unorm8", "snorm8")
    worst0, worst_mip = math.inf, math.inf
    for i in range(images):
        decoded = [decode(fmt, levels[l][i], *level_size(w, h, l)) for l in range(len(levels))]
        if case.get("cube"):
            # Face i against cube_i.png: UNORM u ↔ SNORM s within a step of each.
            img = Image.open(f"{case['dir']}/cube_{i}.png").convert("RGBA")
            for k, (s, u) in enumerate(zip(decoded[0], img.tobytes())):
                if abs(s / 127 - (u / 255 * 2 - 1)) > 1.5 / 127 + 1 / 255:
                    fail(f"face {i} value {k}: snorm {s} vs unorm {u}")
        else:
            want = expected_layers(case)[i]
            p = psnr(decoded[0], want)
            worst0 = min(worst0, p)
            if exact and p != math.inf:
                fail(f"layer {i} level 0 differs from its PNG layer ({p:.1f} dB)")
            if p < case["min_psnr"]:
                fail(f"layer {i} level 0: {p:.1f} dB against its PNG layer")
            # Layer order: another layer's PNG must not match as well (smooth maps differ).
            for j, other in enumerate(expected_layers(case)):
                if j != i and other != want and psnr(decoded[0], other) >= p:
                    fail(f"layer {i} matches PNG layer {j} better than its own")
        # Each level against the filter of the level above. Uncompressed: the decoded level
        # above, exactly. Blocks: the level above as it was before compression (the filter
        # applied down the chain from the PNG layer), so one level's block error is measured,
        # not two.
        above = decoded[0] if exact or case.get("cube") else expected_layers(case)[i]
        if case["filter"] == "rebake":
            boxed_everywhere = True
            for l in range(1, len(levels)):
                lw, lh = level_size(w, h, l)
                if len(decoded[l]) != lw * lh * 4:
                    fail(f"image {i} level {l}: {len(decoded[l])} samples, want {lw}x{lh} RGBA")
                pw, ph = level_size(w, h, l - 1)
                if downsample(decoded[l - 1], pw, ph, "box") != decoded[l]:
                    boxed_everywhere = False
            if len(levels) > 1 and boxed_everywhere:
                fail(f"image {i}: every rebaked level is the box filter of the level above")
            continue
        for l in range(1, len(levels)):
            pw, ph = level_size(w, h, l - 1)
            filt = downsample(decoded[l - 1] if exact else above, pw, ph, case["filter"])
            p = psnr(decoded[l], filt)
            worst_mip = min(worst_mip, p)
            if exact and p != math.inf:
                fail(f"image {i} level {l} is not the {case['filter']} filter of level {l - 1}")
            if p < case.get("min_mip_psnr", 35.0):
                fail(f"image {i} level {l}: {p:.1f} dB against the {case['filter']} filter of the level above")
            above = filt
    print(f"ok {path}: {fmt}, {w}x{h}, {images} images, {len(levels)} levels, zstd={zstd}, "
          f"level 0 >= {worst0:.1f} dB, mips >= {worst_mip:.1f} dB")


def main():
    cases = json.load(open(sys.argv[1]))
    for case in cases:
        try:
            check(case)
        except AssertionError as e:
            print(f"FAIL {case['dir']}/{case['file']}: {e}")
            sys.exit(1)


if __name__ == "__main__":
    main()
