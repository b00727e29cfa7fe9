"""A client of a running ``horizon-bake serve`` (openapi.yaml), for farm job scripts.

Standard library only (``urllib``), so a job script needs nothing beyond this package. It
submits a height map (bytes, a path, or a numpy array sent as an uncompressed TIFF), waits for
the bake with progress from the bake's Server-Sent Events, downloads any result, cancels and
lists. 429 and 503 answers (a full queue, a busy decode budget, a server shutting down) are
retried after their ``Retry-After`` up to ``retries`` times; a download the server still
encodes (202) is asked again after its ``Retry-After``. Every other problem+json answer raises
the exception of its ``code`` (:mod:`horizon_bake._errors`) with the server's ``detail`` as
the message, so a script handles a bad parameter from the service and from the library alike.
"""

from __future__ import annotations

import json
import os
import struct
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Callable, Dict, Iterator, List, Optional, Union

from ._errors import BY_CODE, Canceled, HorizonBakeError, NotFound, ServiceError

#: Statuses retried after Retry-After.
RETRY_STATUSES = (429, 503)


def array_tiff(a: Any) -> bytes:
    """A 2-D numpy array as a one-band uncompressed little-endian TIFF: uint8, uint16 (read as
    normalised integers, as PNG samples are) or float32 (heights as-is; other dtypes are cast
    to float32)."""
    import numpy as np  # noqa: PLC0415

    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"heights are a 2-D array, not shape {a.shape}")
    if a.dtype not in (np.uint8, np.uint16, np.float32):
        a = a.astype(np.float32)
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    h, w = a.shape
    bits = a.dtype.itemsize * 8
    fmt = 3 if a.dtype.kind == "f" else 1
    data = a.tobytes()
    entries = [
        (256, 4, 1, w), (257, 4, 1, h), (258, 3, 1, bits), (259, 3, 1, 1), (262, 3, 1, 1),
        (273, 4, 1, 0), (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, len(data)),
        (284, 3, 1, 1), (339, 3, 1, fmt),
    ]
    ifd_at = 8
    data_at = ifd_at + 2 + 12 * len(entries) + 4
    out = bytearray(b"II*\x00" + struct.pack("<I", ifd_at))
    out += struct.pack("<H", len(entries))
    for tag, typ, count, value in entries:
        if tag == 273:
            value = data_at
        if typ == 3:
            out += struct.pack("<HHIHH", tag, typ, count, value, 0)
        else:
            out += struct.pack("<HHII", tag, typ, count, value)
    out += struct.pack("<I", 0)
    out += data
    return bytes(out)


class Client:
    """A horizon-bake service at ``url`` (``http://127.0.0.1:8080``).

    ``api_key`` is sent as ``Authorization: Bearer``; ``timeout`` bounds each request (s);
    ``retries`` is how many times a 429/503 is retried, each after its ``Retry-After`` (at most
    ``max_retry_wait`` s).
    """

    def __init__(self, url: str, api_key: Optional[str] = None, *, timeout: float = 60.0,
                 retries: int = 8, max_retry_wait: float = 30.0):
        self.url = url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.retries = retries
        self.max_retry_wait = max_retry_wait
        #: How many 429/503 answers were retried (for scripts that log it).
        self.retried = 0

    # -- plumbing ---------------------------------------------------------------------------

    def _request(self, method: str, path: str, *, query: Optional[List[tuple]] = None,
                 body: Optional[bytes] = None, headers: Optional[Dict[str, str]] = None,
                 stream: bool = False) -> Any:
        url = self.url + path
        if query:
            url += "?" + urllib.parse.urlencode(query)
        hdrs = dict(headers or {})
        if self.api_key:
            hdrs["Authorization"] = f"Bearer {self.api_key}"
        attempt = 0
        while True:
            req = urllib.request.Request(url, data=body, method=method, headers=hdrs)
            try:
                resp = urllib.request.urlopen(req, timeout=self.timeout)  # noqa: S310
            except urllib.error.HTTPError as e:
                if e.code in RETRY_STATUSES and attempt < self.retries:
                    attempt += 1
                    self.retried += 1
                    time.sleep(self._retry_after(e.headers))
                    e.close()
                    continue
                raise self._problem(e) from None
            except urllib.error.URLError as e:
                raise ServiceError(f"cannot reach {self.url}: {e.reason}", code="unreachable") from None
            return resp if stream else _Answer(resp)

    def _retry_after(self, headers: Any) -> float:
        try:
            wait = float(headers.get("Retry-After", "1"))
        except (TypeError, ValueError):
            wait = 1.0
        return max(0.0, min(wait, self.max_retry_wait))

    @staticmethod
    def _problem(e: urllib.error.HTTPError) -> HorizonBakeError:
        raw = e.read()
        e.close()
        try:
            p = json.loads(raw)
        except ValueError:
            p = {"detail": raw.decode("utf-8", "replace") or e.reason}
        code = p.get("code")
        cls = BY_CODE.get(code)
        if cls is None:
            cls = NotFound if e.code == 404 else (ServiceError if e.code >= 500 or e.code == 429
                                                  else HorizonBakeError)
        return cls(p.get("detail") or str(e.reason), code=code, field=p.get("field"),
                   status=e.code)

    # -- the API ----------------------------------------------------------------------------

    def submit(self, heightmap: Union[bytes, str, os.PathLike, Any], **params: Any) -> Dict[str, Any]:
        """Submits a height map; returns the bake resource (``id``, ``status``, ...).

        ``heightmap`` is the bytes of a PNG, TIFF or OpenEXR file, a path to one, or a 2-D
        numpy array (sent as a TIFF by :func:`array_tiff`). ``params`` are the bake parameters
        and the submission's other keys (``formats="png16,ktx2"``, texture options) by their
        API names; lists are comma-joined, booleans ``on``/``off``.
        """
        from . import param_pairs  # noqa: PLC0415

        if isinstance(heightmap, (bytes, bytearray, memoryview)):
            body = bytes(heightmap)
        elif isinstance(heightmap, (str, os.PathLike)):
            with open(heightmap, "rb") as f:
                body = f.read()
        else:
            body = array_tiff(heightmap)
        ans = self._request("POST", "/v1/bakes", query=param_pairs(params), body=body,
                            headers={"Content-Type": "application/octet-stream"})
        return ans.json()

    def get(self, bake: Union[str, Dict[str, Any]]) -> Dict[str, Any]:
        """The bake resource now."""
        return self._request("GET", f"/v1/bakes/{_id(bake)}").json()

    def events(self, bake: Union[str, Dict[str, Any]]) -> Iterator[tuple]:
        """The bake's Server-Sent Events as ``(event, data)`` pairs, until the stream ends."""
        resp = self._request("GET", f"/v1/bakes/{_id(bake)}/events",
                             headers={"Accept": "text/event-stream"}, stream=True)
        with resp:
            event, data = "message", []
            for raw in resp:
                line = raw.decode("utf-8").rstrip("\r\n")
                if not line:
                    if data:
                        text = "\n".join(data)
                        try:
                            yield event, json.loads(text)
                        except ValueError:
                            yield event, text
                    event, data = "message", []
                elif line.startswith(":"):
                    continue
                elif line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].lstrip())

    def wait(self, bake: Union[str, Dict[str, Any]], *,
             progress: Optional[Callable[[float], Any]] = None,
             timeout: Optional[float] = None) -> Dict[str, Any]:
        """Waits for the bake to finish, calling ``progress(fraction)`` on each progress event;
        returns the final resource of a succeeded bake. A failed bake raises the exception of
        its error code, a canceled one :class:`Canceled`; ``timeout`` (s) raises TimeoutError.
        """
        bid = _id(bake)
        deadline = None if timeout is None else time.monotonic() + timeout
        final = None
        while final is None:
            try:
                for event, data in self.events(bid):
                    if deadline is not None and time.monotonic() > deadline:
                        raise TimeoutError(f"bake {bid} did not finish in {timeout} s")
                    if event == "progress" and progress is not None and isinstance(data, dict):
                        progress(float(data.get("progress", {}).get("fraction", 0.0)))
                    elif event == "done":
                        final = data
                        break
                    elif event == "deleted":
                        raise NotFound(f"bake `{bid}` was deleted", code="bake_not_found")
            except (ConnectionError, TimeoutError) as e:
                if isinstance(e, TimeoutError) and deadline is not None and time.monotonic() > deadline:
                    raise
            if final is None:
                # The stream ended without `done` (a restart): the resource says where it is.
                now = self.get(bid)
                if now.get("status") in ("succeeded", "failed", "canceled"):
                    final = now
                elif deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"bake {bid} did not finish in {timeout} s")
        status = final.get("status")
        if status == "succeeded":
            if progress is not None:
                progress(1.0)
            return final
        if status == "canceled":
            raise Canceled(f"bake `{bid}` was canceled", code="canceled")
        err = final.get("error") or {}
        cls = BY_CODE.get(err.get("code"), HorizonBakeError)
        raise cls(err.get("message") or f"bake `{bid}` {status}", code=err.get("code"))

    def fetch(self, bake: Union[str, Dict[str, Any]], result: str, **query: Any) -> bytes:
        """The bytes of a result: ``result`` is the path under the bake (``horizon/0``,
        ``horizon.ktx2``, ``fourier/1``, ``angles``, ``svf``, ``shadow``, ``preview``, ...), with
        its query (``format="png16"``, ``sun_azimuth=135``). A result the server encodes on
        request (202) is asked again after its ``Retry-After`` until it is ready."""
        from . import param_pairs  # noqa: PLC0415

        path = f"/v1/bakes/{_id(bake)}/{result.lstrip('/')}"
        waited = 0.0
        while True:
            ans = self._request("GET", path, query=param_pairs(query))
            if ans.status != 202:
                return ans.body
            wait = self._retry_after(ans.headers)
            waited += wait
            if waited > max(self.timeout, 600.0):
                raise ServiceError(f"{result} of bake `{_id(bake)}` was still encoding after "
                                   f"{waited:.0f} s", code="encoding")
            time.sleep(max(wait, 0.1))

    def cancel(self, bake: Union[str, Dict[str, Any]]) -> Optional[Dict[str, Any]]:
        """Cancels a queued or running bake (its resource), or removes a finished one
        (``None``)."""
        ans = self._request("DELETE", f"/v1/bakes/{_id(bake)}")
        return ans.json() if ans.body else None

    def list(self, *, status: Optional[Union[str, List[str]]] = None,
             limit: int = 50) -> Iterator[Dict[str, Any]]:
        """Every bake (optionally of ``status``), following the pages."""
        query: List[tuple] = [("limit", str(limit))]
        if status:
            query.append(("status", status if isinstance(status, str) else ",".join(status)))
        cursor = None
        while True:
            q = query + ([("cursor", cursor)] if cursor else [])
            page = self._request("GET", "/v1/bakes", query=q).json()
            yield from page.get("items", [])
            nxt = page.get("next")
            if not nxt:
                return
            cursor = nxt["cursor"]

    def bake(self, heightmap: Union[bytes, str, os.PathLike, Any], *,
             progress: Optional[Callable[[float], Any]] = None,
             timeout: Optional[float] = None, **params: Any) -> Dict[str, Any]:
        """:meth:`submit` then :meth:`wait`: the succeeded bake's resource."""
        return self.wait(self.submit(heightmap, **params), progress=progress, timeout=timeout)


class _Answer:
    """A whole response read at once."""

    def __init__(self, resp: Any):
        with resp:
            self.status = resp.status
            self.headers = resp.headers
            self.body = resp.read()

    def json(self) -> Any:
        return json.loads(self.body)


def _id(bake: Union[str, Dict[str, Any]]) -> str:
    return bake["id"] if isinstance(bake, dict) else str(bake)
