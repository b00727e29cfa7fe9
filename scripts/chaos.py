#!/usr/bin/env python3
"""Replays issue 43's attacks and the load + kill -9 runs against the real binary on 127.0.0.1.

What an operator of an asset farm would try, each bounded in time, each checked:

- attacks on one embedded server, while a prober asks /healthz every 50 ms (its p99 must stay
  under --healthz-ms, its worst under 5x that) and a real submission is accepted during or
  right after each one:
  params_flood    two 1.8 MB `params` parts of 120k keys at once: 413 each
  slow_drip       16 uploads dripping a byte every 2 s: 408 body_too_slow; a real POST is
                  accepted once they are cut
  bombs           four deflated 8192^2 float32 TIFFs (~260 KB each) at once under a 600 MiB
                  decode budget: each 422 or 503, the server's peak resident memory within the
                  budget of its idle peak
  expect_100      Expect: 100-continue with Content-Length 10 GiB: 413 at once, no 100
  preview         a 4096^2 relief preview with 1024 steps: 503 preview_timeout at the deadline,
                  the next preview answered
  bad_georef      a NaN tie point and GDAL_NODATA "abc": 422 naming them
  drain           SIGTERM with a download nobody reads: the process exits after its grace
  disk_full       (as root: a tmpfs data directory) 507 insufficient_storage, /readyz 507,
                  nothing stored lost, both fine again once space is freed
- kill9: N distinct bakes submitted while the embedded server is killed with SIGKILL and
  restarted on its data directory; every accepted bake (202) ends succeeded, exactly once (the
  listing's total is N), and its layers are byte-identical to the CLI's.
- cluster (with --engines DIR from scripts/engines.sh): one API and two workers on PostgreSQL
  and S3; workers killed with SIGKILL and restarted, one stopped (SIGSTOP) past its lease and
  resumed, PostgreSQL restarted; the same checks.

Usage:
  python3 scripts/chaos.py --bin target/debug/horizon-bake            # short form (.ci/run)
  python3 scripts/chaos.py --bin target/release/horizon-bake --full --engines /tmp/eng
Prints one line per check and a table of figures; exits 1 if any check failed.
Only the standard library: it runs on a fresh machine beside the binary.
"""

import argparse
import http.client as httpclient
import json
import math
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
import zlib

FAILURES = []
FIGURES = []


def check(ok, what, detail=""):
    print(("ok    " if ok else "FAIL  ") + what + (f": {detail}" if detail else ""), flush=True)
    if not ok:
        FAILURES.append(what + (f": {detail}" if detail else ""))
    return ok


def figure(name, value):
    FIGURES.append((name, value))


# ---------------------------------------------------------------- inputs


def png16(w, h, seed):
    """A 16-bit grey PNG of smooth terrain-like waves, different for every seed."""
    rnd = random.Random(seed)
    waves = [(rnd.uniform(0.02, 0.2), rnd.uniform(0.02, 0.2), rnd.uniform(0, 6.3), rnd.uniform(0.2, 1))
             for _ in range(4)]
    raw = bytearray()
    for y in range(h):
        raw.append(0)
        for x in range(w):
            v = sum(a * math.sin(fx * x + fy * y + p) for fx, fy, p, a in waves)
            raw += struct.pack(">H", int(max(0, min(65535, 32768 + v * 12000))))
    return png_bytes(w, h, bytes(raw), bit_depth=16)


def noise_png16(w, h):
    """16-bit noise no filter compresses: large layers, for a download that takes a while."""
    row = w * 2
    data = os.urandom(row * h)
    raw = b"".join(b"\x00" + data[y * row:(y + 1) * row] for y in range(h))
    return png_bytes(w, h, raw, bit_depth=16, level=1)


def png_bytes(w, h, raw, bit_depth, level=6):
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, level))
            + chunk(b"IEND", b""))


def tiff(w, h, strip_rows, strips, extra=()):
    """A little-endian float32 TIFF of deflated `strips` (`strip_rows` rows each); `extra` tags
    are (tag, type, count, payload bytes)."""
    n = len(strips)
    tags = [(256, 4, 1, struct.pack("<I", w)), (257, 4, 1, struct.pack("<I", h)),
            (258, 3, 1, struct.pack("<H", 32)), (259, 3, 1, struct.pack("<H", 8)),
            (262, 3, 1, struct.pack("<H", 1)), (273, 4, n, None), (277, 3, 1, struct.pack("<H", 1)),
            (278, 4, 1, struct.pack("<I", strip_rows)), (279, 4, n, struct.pack(f"<{n}I", *map(len, strips))),
            (339, 3, 1, struct.pack("<H", 3))] + list(extra)
    tags.sort(key=lambda t: t[0])
    ifd_at = 8
    ifd_len = 2 + 12 * len(tags) + 4
    data_at = ifd_at + ifd_len
    blobs = bytearray()
    strips_at = data_at  # the strips come first in the data area
    starts = []
    for strip in strips:
        starts.append(strips_at + len(blobs))
        blobs += strip
    offsets = struct.pack(f"<{n}I", *starts)
    entries = bytearray()
    for tag, typ, count, payload in tags:
        if payload is None:
            payload = offsets
        if len(payload) <= 4:
            entries += struct.pack("<HHI", tag, typ, count) + payload.ljust(4, b"\x00")
        else:
            if len(blobs) % 2:
                blobs += b"\x00"
            entries += struct.pack("<HHII", tag, typ, count, data_at + len(blobs))
            blobs += payload
    ifd = struct.pack("<H", len(tags)) + bytes(entries) + struct.pack("<I", 0)
    return b"II*\x00" + struct.pack("<I", ifd_at) + ifd + bytes(blobs)


def bomb(size=8192):
    """size^2 float32, deflated strip by strip: 256 MiB of heights from ~260 KB, every one
    decoded before the last strip's NaN makes it a 422 (so no bomb is baked)."""
    rows = 64
    zero = zlib.compress(struct.pack("<f", 0.0) * (size * rows), 9)
    nan = zlib.compress(struct.pack("<f", float("nan")) * (size * rows), 9)
    return tiff(size, size, rows, [zero] * (size // rows - 1) + [nan])


def geotiff(tiepoint, nodata=None):
    """A 32^2 float32 GeoTIFF (EPSG:32632) with the tie point given and GDAL_NODATA text."""
    strip = zlib.compress(b"".join(struct.pack("<f", float(x % 7)) for x in range(32 * 32)))
    keys = struct.pack("<16H", 1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32632)
    extra = [(33550, 12, 3, struct.pack("<3d", 30.0, 30.0, 0.0)),
             (33922, 12, 6, struct.pack("<6d", *tiepoint)),
             (34735, 3, 16, keys)]
    if nodata is not None:
        text = nodata.encode() + b"\x00"
        extra.append((42113, 2, len(text), text))
    return tiff(32, 32, 32, [strip], extra)


# ---------------------------------------------------------------- the server


class Node:
    """One `horizon-bake serve` process; `restart` keeps its data directory and flags."""

    def __init__(self, binary, workdir, name, flags, env=None, data=None):
        self.binary, self.name, self.flags = binary, name, list(flags)
        self.data = data or os.path.join(workdir, name)
        self.env = dict(os.environ, **(env or {}))
        self.env.pop("HORIZON_API_KEY", None)
        self.log_path = os.path.join(workdir, name + ".log")
        self.proc = None
        self.start()

    def start(self):
        addr_file = self.log_path + ".addr"
        if os.path.exists(addr_file):
            os.remove(addr_file)
        log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [self.binary, "serve", "--addr", "127.0.0.1:0", "--addr-file", addr_file,
             "--data-dir", self.data] + self.flags,
            stdout=log, stderr=log, env=self.env)
        t = time.time()
        while True:
            if os.path.exists(addr_file) and open(addr_file).read().strip():
                self.base = "http://" + open(addr_file).read().strip()
                return
            if self.proc.poll() is not None:
                tail = open(self.log_path, errors="replace").read()[-2000:]
                raise SystemExit(f"{self.name} exited at start:\n{tail}")
            if time.time() - t > 60:
                raise SystemExit(f"{self.name} did not start in 60 s")
            time.sleep(0.02)

    def kill9(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def restart(self):
        self.kill9()
        self.start()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.kill9()

    def status_kib(self, key):
        for line in open(f"/proc/{self.proc.pid}/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1])
        return 0

    @property
    def addr(self):
        host, port = self.base[len("http://"):].rsplit(":", 1)
        return host, int(port)


def http(method, url, body=None, headers=None, timeout=60):
    """(status, headers, body bytes); connection failures (a server killed mid-answer
    included) raise OSError."""
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        try:
            return e.code, dict(e.headers), e.read()
        except httpclient.HTTPException as x:
            raise OSError(repr(x)) from x
    except httpclient.HTTPException as e:
        raise OSError(repr(e)) from e


def submit(base, png, query="radius=4"):
    return http("POST", f"{base}/v1/bakes?{query}", png, {"content-type": "image/png"})


def raw_request(addr, head, body=b"", read_for=15.0, pace=None):
    """Sends `head` and `body` on a fresh socket (in 64 KiB pieces, `pace` s apart) and returns
    what the server answers within `read_for` s."""
    s = socket.create_connection(addr, timeout=read_for)
    try:
        s.sendall(head)
        for i in range(0, len(body), 64 << 10):
            s.sendall(body[i:i + (64 << 10)])
            if pace:
                time.sleep(pace)
        out = b""
        end = time.time() + read_for
        while time.time() < end:
            try:
                piece = s.recv(65536)
            except socket.timeout:
                break
            if not piece:
                break
            out += piece
            if b"\r\n\r\n" in out and len(out) > 200:
                break
        return out.decode("latin-1")
    finally:
        s.close()


class Prober(threading.Thread):
    """GET /healthz every 50 ms; keeps each answer's latency (a failure counts as 5 s)."""

    def __init__(self, node):
        super().__init__(daemon=True)
        self.node, self.lat, self.running = node, [], True

    def run(self):
        while self.running:
            t = time.time()
            try:
                ok = http("GET", self.node.base + "/healthz", timeout=5)[0] == 200
            except OSError:
                ok = False
            self.lat.append(time.time() - t if ok else 5.0)
            time.sleep(0.05)

    def stop(self):
        self.running = False
        self.join()
        lat = sorted(self.lat) or [0.0]
        return lat[min(len(lat) - 1, int(len(lat) * 0.99))] * 1e3, lat[-1] * 1e3, len(lat)


def real_submission(node, seed, within=30.0):
    """A real bake submitted (retried after 429/503 within `within` s) and finished: the seconds
    until it was accepted, or None."""
    t = time.time()
    png = png16(32, 32, seed)
    while time.time() - t < within:
        try:
            s, _, body = submit(node.base, png, "radius=2")
        except OSError:
            s = 0
        if s == 202:
            loc = json.loads(body)["id"]
            accepted = time.time() - t
            if wait_done(node.base, loc, 60) == "succeeded":
                return accepted
            return None
        time.sleep(0.5)
    return None


def wait_done(base, bake_id, within):
    t = time.time()
    while time.time() - t < within:
        try:
            s, _, body = http("GET", f"{base}/v1/bakes/{bake_id}")
            if s == 200:
                st = json.loads(body)["status"]
                if st in ("succeeded", "failed", "canceled"):
                    return st
        except OSError:
            pass
        time.sleep(0.1)
    return "timeout"


# ---------------------------------------------------------------- attacks


def attack(node, name, fn, args):
    prober = Prober(node)
    prober.start()
    t = time.time()
    try:
        fn(node, args)
    except Exception as e:  # a crash of the attack is a failed check, not the end of the run
        check(False, f"{name}: attack ran", repr(e))
    took = time.time() - t
    accepted = real_submission(node, sum(map(ord, name)))
    p99, worst, n = prober.stop()
    check(accepted is not None, f"{name}: a real submission is accepted and bakes",
          f"accepted after {accepted:.2f} s" if accepted is not None else "never")
    check(p99 <= args.healthz_ms and worst <= 5 * args.healthz_ms,
          f"{name}: /healthz answered throughout", f"p99 {p99:.0f} ms, worst {worst:.0f} ms over {n}")
    figure(f"{name}: attack s / healthz p99 ms / worst ms", f"{took:.1f} / {p99:.0f} / {worst:.0f}")


def params_flood(node, args):
    boundary = "chaos-boundary"
    members = ",".join(f'"k{i}":{i}' for i in range(120_000))
    png = png16(8, 8, 1)
    body = (f"--{boundary}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{{{members}}}\r\n"
            f"--{boundary}\r\ncontent-disposition: form-data; name=\"heightmap\"; filename=\"h.png\"\r\n"
            "content-type: image/png\r\n\r\n").encode() + png + f"\r\n--{boundary}--\r\n".encode()
    head = (f"POST /v1/bakes HTTP/1.1\r\nhost: x\r\ncontent-length: {len(body)}\r\n"
            f"content-type: multipart/form-data; boundary={boundary}\r\n\r\n").encode()
    out = [None, None]

    def one(i):
        t = time.time()
        out[i] = (raw_request(node.addr, head, body, pace=0.005), time.time() - t)
    ts = [threading.Thread(target=one, args=(i,)) for i in range(2)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    for text, took in out:
        check(text.startswith("HTTP/1.1 413") and "params" in text,
              "params_flood: a 1.8 MB params part is 413", f"{took:.2f} s: {text[:60]!r}")


def slow_drip(node, args):
    n = 16
    answers = [""] * n

    def drip(i):
        s = socket.create_connection(node.addr, timeout=3)
        s.sendall(b"POST /v1/bakes HTTP/1.1\r\nhost: x\r\ncontent-type: image/png\r\n"
                  b"content-length: 100000\r\n\r\n")
        got = b""
        for _ in range(20):
            try:
                s.sendall(b"x")
            except OSError:
                break
            try:
                piece = s.recv(4096)
                if not piece:
                    break
                got += piece
                break
            except socket.timeout:
                pass
        answers[i] = got.decode("latin-1")
        s.close()
    t = time.time()
    ts = [threading.Thread(target=drip, args=(i,)) for i in range(n)]
    for th in ts:
        th.start()
    for th in ts:
        th.join()
    cut = sum(a.startswith("HTTP/1.1 408") and "body_too_slow" in a for a in answers)
    check(cut == n, "slow_drip: every dripping upload is cut (408 body_too_slow)",
          f"{cut}/{n} in {time.time() - t:.1f} s")


def bombs(node, args):
    body = bomb()
    idle = node.status_kib("VmRSS")
    codes = [None] * 4

    def one(i):
        try:
            codes[i] = http("POST", node.base + "/v1/bakes", body, {"content-type": "image/tiff"},
                            timeout=120)[0]
        except OSError as e:
            codes[i] = repr(e)
    ts = [threading.Thread(target=one, args=(i,)) for i in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    peak = node.status_kib("VmHWM")
    check(all(c in (422, 503) for c in codes), "bombs: four decompression bombs are 422 or 503",
          f"{codes} ({len(body) // 1024} KB each)")
    grew = (peak - idle) / 1024
    check(grew <= 600, "bombs: peak memory within the 600 MiB decode budget",
          f"peak +{grew:.0f} MiB over the {idle / 1024:.0f} MiB resident before")
    figure("bombs: server VmHWM growth MiB (budget 600)", f"{grew:.0f}")


def expect_100(node, args):
    t = time.time()
    text = raw_request(node.addr, b"POST /v1/bakes HTTP/1.1\r\nhost: x\r\ncontent-type: image/png\r\n"
                       b"content-length: 10737418240\r\nexpect: 100-continue\r\n\r\n", read_for=10)
    took = time.time() - t
    check(text.startswith("HTTP/1.1 413") and "100 Continue" not in text and took < 5,
          "expect_100: 10 GiB announced with Expect is 413 at once", f"{took:.2f} s: {text[:40]!r}")


def preview(node, args):
    s, _, body = submit(node.base, png16(64, 64, 7), "radius=4")
    bake = json.loads(body)["id"]
    wait_done(node.base, bake, 60)
    slow = ("/preview?size=4096&parallax=relief&parallax_steps=1024&parallax_search_steps=64"
            "&view_elevation=15&shading=raytraced")
    t = time.time()
    s, _, body = http("GET", f"{node.base}/v1/bakes/{bake}{slow}", timeout=120)
    took = time.time() - t
    code = json.loads(body).get("code") if s == 503 else None
    check(s == 503 and code == "preview_timeout" and took < args.preview_deadline + 15,
          "preview: a minutes-long preview is 503 preview_timeout at the deadline", f"{s} {code} {took:.1f} s")
    t = time.time()
    s, _, _ = http("GET", f"{node.base}/v1/bakes/{bake}/preview?size=32")
    check(s == 200, "preview: the next preview is answered", f"{s} in {time.time() - t:.2f} s")


def bad_georef(node, args):
    nan = float("nan")
    for what, body, field in [
        ("a NaN tie point", geotiff((0, 0, 0, nan, 5e6, 0)), "ModelTiepoint"),
        ("GDAL_NODATA abc", geotiff((0, 0, 0, 5e5, 5e6, 0), "abc"), "GDAL_NODATA"),
        ("GDAL_NODATA 1e400", geotiff((0, 0, 0, 5e5, 5e6, 0), "1e400"), "GDAL_NODATA"),
    ]:
        s, _, text = http("POST", node.base + "/v1/bakes", body, {"content-type": "image/tiff"})
        text = text.decode("utf-8", "replace")
        check(s == 422 and field in text, f"bad_georef: {what} is 422 naming it", f"{s} {text[:120]}")


def drain(binary, workdir, args):
    node = Node(binary, workdir, "drain", ["--shutdown-grace-secs", "1"])
    s, _, body = submit(node.base, noise_png16(2048, 2048), "radius=2&formats=png16")
    bake = json.loads(body)["id"]
    wait_done(node.base, bake, 120)
    sock = socket.create_connection(node.addr)
    sock.sendall(f"GET /v1/bakes/{bake}/horizon/0?format=png16 HTTP/1.1\r\nhost: x\r\n\r\n".encode())
    head = sock.recv(64)
    t = time.time()
    node.proc.terminate()
    try:
        node.proc.wait(timeout=30)
        ok = True
    except subprocess.TimeoutExpired:
        ok = False
        node.kill9()
    sock.close()
    check(head.startswith(b"HTTP/1.1 200") and ok,
          "drain: SIGTERM with a download nobody reads exits after its grace", f"{time.time() - t:.1f} s")


def disk_full(binary, workdir, args):
    if os.geteuid() != 0:
        print("skip  disk_full: needs root to mount a tmpfs (tests/service/hostile.rs has it too)")
        return
    mnt = os.path.join(workdir, "full")
    os.makedirs(mnt)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", mnt]).returncode != 0:
        check(False, "disk_full: mount a tmpfs")
        return
    node = None
    try:
        node = Node(binary, workdir, "full", [], data=os.path.join(mnt, "data"))
        s, _, body = submit(node.base, png16(64, 64, 11))
        kept = json.loads(body)["id"]
        wait_done(node.base, kept, 60)
        _, _, before = http("GET", f"{node.base}/v1/bakes/{kept}/horizon/0")
        filler = os.path.join(mnt, "filler")
        with open(filler, "wb") as f:
            try:
                while True:
                    f.write(b"\0" * (1 << 20))
                    f.flush()
            except OSError:
                pass
        s, _, body = submit(node.base, png16(256, 256, 12))
        code = json.loads(body).get("code") if body.startswith(b"{") else None
        check(s == 507 and code == "insufficient_storage", "disk_full: a submission is 507", f"{s} {code}")
        s, _, _ = http("GET", node.base + "/readyz")
        check(s == 507, "disk_full: /readyz is not ready", f"{s}")
        _, _, after = http("GET", f"{node.base}/v1/bakes/{kept}/horizon/0")
        check(after == before, "disk_full: what was stored before is intact")
        os.remove(filler)
        s, _, body = submit(node.base, png16(256, 256, 12))
        check(s == 202, "disk_full: space freed, submissions accepted again", f"{s}")
        s, _, _ = http("GET", node.base + "/readyz")
        check(s == 200, "disk_full: /readyz ready again", f"{s}")
    finally:
        if node:
            node.stop()
        subprocess.run(["umount", "-l", mnt])


# ---------------------------------------------------------------- kill -9 under load


def cli_layers(binary, workdir, png, query):
    d = tempfile.mkdtemp(dir=workdir)
    src = os.path.join(d, "in.png")
    open(src, "wb").write(png)
    flags = []
    for pair in query.split("&"):
        k, v = pair.split("=")
        flags += ["--" + k.replace("_", "-"), v]
    subprocess.run([binary, "bake", src, "-o", os.path.join(d, "out"), "--format", "png8"] + flags,
                   check=True, stderr=subprocess.DEVNULL)
    out = [open(os.path.join(d, "out", f"horizon_{k}.png"), "rb").read() for k in range(2)]
    shutil.rmtree(d)
    return out


# Bakes long enough (a few tenths of a second each) that kills land in the middle of them.
LOAD_QUERY = "method=exact&radius=unlimited&edge=none"


def under_load(binary, workdir, api, n, disrupt, label, query=LOAD_QUERY):
    """Submits n distinct bakes to `api` while `disrupt(stop_event)` runs beside them; checks
    every accepted bake succeeded once, with the CLI's bytes."""
    inputs = [png16(192 + (i % 5) * 16, 192, 1000 + i) for i in range(n)]
    accepted = {}
    stop = threading.Event()
    chaos = threading.Thread(target=disrupt, args=(stop,), daemon=True)
    t0 = time.time()
    chaos.start()
    for i, png in enumerate(inputs):
        while True:
            try:
                s, _, body = submit(api.base, png, query)
            except OSError:
                time.sleep(0.2)
                continue
            if s == 202 or s == 200:
                accepted[i] = json.loads(body)["id"]
                break
            if s in (429, 503):
                time.sleep(0.3)
                continue
            check(False, f"{label}: submission {i}", f"{s} {body[:200]!r}")
            break
        if time.time() - t0 > 900:
            break
    ids = set(accepted.values())
    check(len(ids) == n, f"{label}: every submission accepted, once", f"{len(ids)} ids for {n} inputs")
    end = time.time() + 600
    states = {}
    for i, bake in accepted.items():
        while time.time() < end:
            try:
                states[i] = wait_done(api.base, bake, 5)
            except OSError:
                states[i] = "timeout"
            if states[i] != "timeout":
                break
    stop.set()
    chaos.join()
    done = time.time() - t0
    good = sum(s == "succeeded" for s in states.values())
    check(good == len(accepted), f"{label}: every accepted bake succeeded",
          f"{good}/{len(accepted)}; others {[s for s in states.values() if s != 'succeeded'][:5]}")
    s, _, body = http("GET", f"{api.base}/v1/bakes?limit=1")
    total = json.loads(body)["total"] if s == 200 else None
    check(total == n, f"{label}: the listing holds each bake once", f"total {total} for {n}")
    same = 0
    for i, bake in accepted.items():
        ours = [http("GET", f"{api.base}/v1/bakes/{bake}/horizon/{k}")[2] for k in range(2)]
        same += ours == cli_layers(binary, workdir, inputs[i], query)
    check(same == len(accepted), f"{label}: layers byte-identical to the CLI's", f"{same}/{len(accepted)}")
    figure(f"{label}: bakes / wall s", f"{n} / {done:.1f}")


def kill9(binary, workdir, args):
    node = Node(binary, workdir, "kill9", ["--max-concurrent-bakes", "2"])
    kills = []

    def disrupt(stop):
        rnd = random.Random(9)
        while not stop.wait(rnd.uniform(0.3, 1.2)) and len(kills) < args.kills:
            node.restart()
            kills.append(time.time())
    try:
        under_load(binary, workdir, node, args.bakes, disrupt, "kill9")
        figure("kill9: SIGKILLs of the embedded server", str(len(kills)))
    finally:
        node.stop()


def cluster(binary, workdir, args):
    env = {}
    for line in open(os.path.join(args.engines, "env")):
        for part in line.replace("export ", "").split():
            if "=" in part:
                k, v = part.split("=", 1)
                env[k] = v.strip("'\"")
    admin = env["HORIZON_TEST_DATABASE_URL"]
    db = f"chaos_{os.getpid()}"
    psql = shutil.which("psql") or next(
        (os.path.join("/usr/lib/postgresql", v, "bin", "psql")
         for v in sorted(os.listdir("/usr/lib/postgresql"), reverse=True)), "psql")
    subprocess.run([psql, admin, "-qc", f"CREATE DATABASE {db}"], check=True)
    url = admin.rsplit("/", 1)[0] + "/" + db
    shared = ["--database-url", url, "--s3-endpoint", env["HORIZON_TEST_S3_ENDPOINT"], "--s3-bucket",
              env["HORIZON_TEST_S3_BUCKET"], "--s3-prefix", db, "--lease-secs", "3", "--heartbeat-ms", "300"]
    creds = {k: env[k] for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY")}
    api = Node(binary, workdir, "api", ["--role", "api"] + shared, creds)
    workers = [Node(binary, workdir, f"w{i}", ["--role", "worker"] + shared, creds) for i in (1, 2)]
    events = []

    def disrupt(stop):
        rnd = random.Random(43)
        step = 0
        while not stop.wait(rnd.uniform(0.5, 1.5)) and step < args.kills:
            w = workers[step % 2]
            kind = ("kill9", "stop", "pg")[step % 3]
            if kind == "kill9":
                w.restart()
            elif kind == "stop":
                os.kill(w.proc.pid, signal.SIGSTOP)
                time.sleep(4)  # past its 3 s lease
                os.kill(w.proc.pid, signal.SIGCONT)
            else:
                engines = os.path.join(os.path.dirname(os.path.abspath(__file__)), "engines.sh")
                subprocess.run(["bash", engines, "pg-stop", args.engines], check=True,
                               stdout=subprocess.DEVNULL)
                time.sleep(1)
                subprocess.run(["bash", engines, "pg-start", args.engines], check=True,
                               stdout=subprocess.DEVNULL)
            events.append(kind)
            step += 1
    try:
        under_load(binary, workdir, api, args.cluster_bakes, disrupt, "cluster")
        figure("cluster: disruptions", ", ".join(events) or "none")
        lines = sum(" ERROR " in open(n.log_path, errors="replace").read() for n in [api] + workers)
        figure("cluster: nodes that logged an ERROR line", str(lines))
    finally:
        for n in [api] + workers:
            n.stop()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default="target/debug/horizon-bake")
    ap.add_argument("--full", action="store_true", help="the long form: 200 bakes, 10 kills")
    ap.add_argument("--engines", help="scripts/engines.sh's directory: run the cluster part too")
    ap.add_argument("--healthz-ms", type=float, default=100.0)
    ap.add_argument("--only", help="comma-separated parts to run (attack names, kill9, cluster)")
    args = ap.parse_args()
    args.bakes, args.kills, args.cluster_bakes = (200, 10, 40) if args.full else (24, 3, 12)
    args.preview_deadline = 3
    binary = os.path.abspath(args.bin)
    only = set(args.only.split(",")) if args.only else None
    want = lambda part: only is None or part in only  # noqa: E731
    t0 = time.time()
    workdir = tempfile.mkdtemp(prefix="hb-chaos-")
    try:
        node = Node(binary, workdir, "attacks", [
            "--decode-memory-bytes", str(600 << 20), "--max-decode-bytes", str(600 << 20),
            "--upload-wait-ms", "300", "--tile-above", str(1 << 28),
            "--preview-threads", "1", "--preview-timeout-secs", str(args.preview_deadline)])
        try:
            for name, fn in [("params_flood", params_flood), ("slow_drip", slow_drip), ("bombs", bombs),
                             ("expect_100", expect_100), ("preview", preview), ("bad_georef", bad_georef)]:
                if want(name):
                    attack(node, name, fn, args)
        finally:
            node.stop()
        for name, fn in [("drain", drain), ("disk_full", disk_full), ("kill9", kill9)]:
            if want(name):
                fn(binary, workdir, args)
        if args.engines and want("cluster"):
            cluster(binary, workdir, args)
    finally:
        if not FAILURES:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            print(f"logs kept in {workdir}")
    print(f"\n{'figure':<58} value")
    for k, v in FIGURES:
        print(f"{k:<58} {v}")
    print(f"\n{len(FAILURES)} failed checks, {time.time() - t0:.0f} s")
    sys.exit(1 if FAILURES else 0)


if __name__ == "__main__":
    main()
