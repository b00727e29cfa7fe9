"""horizon-bake on numpy arrays, and a client of the horizon-bake service.

Everything here runs the same Rust library as the ``horizon-bake`` CLI and service (the native
module ``horizon_bake._native``): the same parameters by the same names and defaults (see the
repository's SPEC.md and README), the same decoding rules, the same kernels, the same errors.

- :func:`bake` bakes a 2-D height array into horizon layers, Fourier coefficients and terrain
  products, returned as numpy arrays in a :class:`BakeResult`.
- :func:`terrain` is :func:`bake` for a DEM: a transform and CRS (rasterio's, or GDAL's six
  numbers and an EPSG code) give the cell size and the DEM defaults, as a GeoTIFF's tags do.
- :func:`bake_file` is ``horizon-bake bake PATH -o OUT_DIR`` with keyword flags.
- :func:`cube_map` is the channel-factor cube map.
- :class:`Client` talks to a running ``horizon-bake serve``.
- ``horizon_bake.dask``, ``horizon_bake.xarray``, ``horizon_bake.rasterio``: adapters, each
  importing its library only when used.

Height samples: for :func:`bake` without georeferencing, ``uint8`` and ``uint16`` arrays are
normalised to [0, 1] (v / 255, v / 65535) exactly as the image decoders normalise PNG and TIFF
samples, so an array and the same image in a file bake alike; every other dtype is taken as-is
(cast to float32, as the TIFF decoder casts float64 and integer samples). A DEM's samples
(:func:`terrain`, or :func:`bake` with ``transform``) are heights as-is in every dtype.

Bakes release the GIL. ``progress`` is called with the overall fraction done (0..1) a few times
a second from the calling thread; returning ``False`` from it, raising in it, or Ctrl-C cancels
the bake between bands of rows (:class:`Canceled`, or the exception raised).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native
from ._errors import (
    Canceled,
    HorizonBakeError,
    InputError,
    LimitError,
    NotFound,
    ParameterError,
    ServiceError,
)

__version__ = _native.CRATE_VERSION

__all__ = [
    "BakeResult",
    "Canceled",
    "Client",
    "HorizonBakeError",
    "InputError",
    "LimitError",
    "NotFound",
    "ParameterError",
    "ServiceError",
    "PARAMETERS",
    "bake",
    "bake_file",
    "cube_map",
    "terrain",
    "__version__",
]

#: Every bake parameter of SPEC §2, by the name the CLI, the service and this package share.
PARAMETERS = (
    "height_scale", "channel", "edge", "y_axis", "method", "radius", "bins", "reduce",
    "min_elevation_deg", "encoding", "outputs", "fourier_terms", "fourier_range", "nodata",
    "cell_size", "max_distance", "earth_curvature", "refraction", "angle_unit", "azimuth_from",
    "svf_model", "band", "normal_convention", "bent_normal_encoding", "date", "date_from",
    "date_to", "time_step_minutes", "latitude", "longitude",
)

ProgressCallback = Callable[[float], Optional[bool]]


def param_text(name: str, value: Any) -> Optional[str]:
    """A parameter value as the CLI's flags and the service's query strings spell it.

    ``True``/``False`` are ``on``/``off``, a list or tuple is comma-joined (``outputs``), NaN is
    ``nan``, ``None`` leaves the parameter at its default.
    """
    if value is None:
        return None
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (list, tuple, set, frozenset)):
        return ",".join(str(v) for v in value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value)
    if isinstance(value, (np.integer, np.floating)):
        return param_text(name, value.item())
    return str(value)


def param_pairs(params: Mapping[str, Any]) -> list:
    """``(name, text)`` pairs of the parameters given (``None`` ones left out)."""
    out = []
    for k, v in params.items():
        t = param_text(k, v)
        if t is not None:
            out.append((k, t))
    return out


_UNITS = {"metre": 9001, "meter": 9001, "m": 9001, "foot": 9002, "ft": 9002,
          "us survey foot": 9003, "us_survey_foot": 9003, "foot_us": 9003}


def _crs_parts(crs: Any) -> Tuple[str, int, int]:
    """(model, EPSG code or 0, EPSG linear unit code) of ``crs``.

    ``crs`` is a rasterio or pyproj CRS, an EPSG code (int), or a string either of them reads
    ("EPSG:32633", WKT). Without rasterio or pyproj to read it, an ``EPSG:`` code or int is
    geographic when it is in 4000..4999 (the EPSG geographic 2-D range), projected in metres
    otherwise.
    """
    if crs is None:
        return "none", 0, 0
    obj = crs
    if isinstance(crs, (int, np.integer, str)):
        obj = None
        for reader in (_rasterio_crs, _pyproj_crs):
            try:
                obj = reader(crs)
                break
            except ImportError:
                continue
        if obj is None:
            code = int(str(crs).upper().replace("EPSG:", "")) if not isinstance(crs, int) else crs
            if 4000 <= code <= 4999:
                return "geographic", code, 9001
            return "projected", code, 9001
    geographic = bool(getattr(obj, "is_geographic", False))
    epsg = None
    to_epsg = getattr(obj, "to_epsg", None)
    if to_epsg is not None:
        try:
            epsg = to_epsg()
        except Exception:  # a CRS with no EPSG code is user-defined
            epsg = None
    code = int(epsg) if epsg is not None and 0 < int(epsg) < 32767 else 0
    unit_name = None
    if hasattr(obj, "linear_units"):  # rasterio
        unit_name = obj.linear_units
    elif hasattr(obj, "axis_info") and obj.axis_info:  # pyproj
        unit_name = obj.axis_info[0].unit_name
    unit = _UNITS.get(str(unit_name or "metre").strip().lower(), 9001)
    return ("geographic" if geographic else "projected"), code, unit


def _rasterio_crs(crs: Any) -> Any:
    from rasterio.crs import CRS  # noqa: PLC0415 (optional dependency)

    return CRS.from_user_input(crs)


def _pyproj_crs(crs: Any) -> Any:
    from pyproj import CRS  # noqa: PLC0415 (optional dependency)

    return CRS.from_user_input(crs)


def gdal_transform(transform: Any) -> Tuple[float, ...]:
    """GDAL's six geotransform numbers of an ``affine.Affine`` (rasterio) or of six numbers
    already in GDAL's order ``(x0, dx, rx, y0, ry, dy)``."""
    to_gdal = getattr(transform, "to_gdal", None)
    if to_gdal is not None:
        return tuple(float(v) for v in to_gdal())
    t = tuple(float(v) for v in transform)
    if len(t) != 6:
        raise ParameterError(
            f"invalid parameter `transform`: {len(t)} numbers; GDAL's geotransform has six "
            "(x0, dx, rx, y0, ry, dy), or pass rasterio's Affine",
            code="invalid_parameter", field="transform")
    return t


def _georef(transform: Any, crs: Any) -> Optional[tuple]:
    if transform is None:
        if crs is not None:
            raise ParameterError(
                "invalid parameter `crs`: a CRS without a transform places nothing; give "
                "transform too (rasterio's dataset.transform, or GDAL's six numbers)",
                code="invalid_parameter", field="crs")
        return None
    model, code, unit = _crs_parts(crs)
    return (gdal_transform(transform), model, code, unit)


def _heights(heights: Any) -> np.ndarray:
    a = np.asarray(heights)
    if a.ndim != 2:
        raise InputError(
            f"invalid height map: an array of shape {a.shape}; heights are a 2-D array "
            "(rows, columns)", code="invalid_input")
    if a.dtype in (np.uint8, np.uint16, np.float32):
        return a
    if a.dtype.kind not in "biuf":
        raise InputError(
            f"unsupported input: heights of dtype {a.dtype}; use integers or floats",
            code="unsupported_media_type")
    return a.astype(np.float32)


@dataclass
class BakeResult:
    """What :func:`bake` made. Arrays are row-major from the top row; ``None`` for a product
    ``outputs`` did not ask for."""

    width: int
    height: int
    #: The two RGBA horizon layers, ``(H, W, 4)`` each, in ``dtype`` (uint8: the png8 files'
    #: values, uint16: png16's, float32: the unquantised values). Channel c of layer l is
    #: direction 4·l + c (SPEC §3.1).
    layers: Optional[Tuple[np.ndarray, np.ndarray]] = None
    #: The Fourier encoding (SPEC §3.4): ``bands`` ``(H, W, 4)`` and ``constant`` ``(H, W)``
    #: uint8, ``high`` ``(H, W, 4)`` for more than 5 terms, ``terms``.
    fourier: Optional[Dict[str, Any]] = None
    #: Horizon angles ``(bins, H, W)`` float32, band n at n·360°/bins from ``azimuth_from``,
    #: in ``angle_unit``; holes hold ``product_nodata``.
    angles: Optional[np.ndarray] = None
    #: Sky-view factor ``(H, W)`` float32; holes hold ``product_nodata``.
    svf: Optional[np.ndarray] = None
    #: ``outputs`` ``horizon_distance``: ``(bins, H, W)`` float32, in ``angles``' band order,
    #: the distance in map units to the point that sets each horizon (``product_nodata`` where
    #: the horizon is 0 and at holes).
    horizon_distance: Optional[np.ndarray] = None
    #: ``outputs`` ``openness``: positive and negative openness ``(H, W)`` float32, degrees.
    openness_positive: Optional[np.ndarray] = None
    openness_negative: Optional[np.ndarray] = None
    #: ``outputs`` ``sun_hours`` / ``insolation`` over ``date`` (or ``date_from``..``date_to``):
    #: hours of direct sun and the clear-sky direct beam on the surface in Wh/m², ``(H, W)``.
    sun_hours: Optional[np.ndarray] = None
    insolation: Optional[np.ndarray] = None
    #: The surface maps (SPEC §3.8), the values of ``normal.png``, ``ao.png`` and
    #: ``bent_normal.png``: ``normal`` ``(H, W, 3)`` uint8 ((n + 1) / 2, y as
    #: ``normal_convention``), ``ao`` ``(H, W)`` uint8, ``bent_normal`` ``(H, W, 3)`` (``(H, W,
    #: 4)`` with the AO in alpha for ``bent_normal_encoding="rgb_ao"``); holes 0.
    normal: Optional[np.ndarray] = None
    ao: Optional[np.ndarray] = None
    bent_normal: Optional[np.ndarray] = None
    #: The parameters the bake ran with, every one resolved (DEM defaults, method fitted), as
    #: the CLI's bake.json and the service report them.
    params: Dict[str, str] = field(default_factory=dict)
    #: The radius the kernel used: ``{"texels": int, "reason": str}``.
    resolved_radius: Optional[Dict[str, Any]] = None
    #: decode (array → heights), bake and total time, ms.
    timings_ms: Dict[str, float] = field(default_factory=dict)
    #: The DEM warnings the CLI prints (undeclared nodata, a degree grid's cells).
    warnings: Sequence[str] = ()
    #: Texels that were nodata holes.
    holes: int = 0
    #: The nodata value in effect (NaN for ``nan``), ``None`` without one.
    nodata: Optional[float] = None
    #: The value written at holes of ``angles`` and ``svf`` (NaN unless nodata was declared).
    product_nodata: Optional[float] = None
    #: The georeferencing the array came with (terrain): GDAL geotransform and the CRS as given.
    transform: Optional[Tuple[float, ...]] = None
    crs: Any = None

    def cube_map(self, size: int = 64) -> np.ndarray:
        """The channel-factor cube map that decodes these layers (see :func:`cube_map`)."""
        return cube_map(size)


def bake(
    heights: Any,
    *,
    dtype: str = "uint8",
    progress: Optional[ProgressCallback] = None,
    transform: Any = None,
    crs: Any = None,
    **params: Any,
) -> BakeResult:
    """Bakes a 2-D height array with the parameters of SPEC §2 (keyword arguments by the same
    names: ``method="exact"``, ``radius=32``, ``outputs=("horizon", "svf")``, ...).

    ``dtype`` is the horizon layers' type: ``uint8`` (what ``--format png8`` writes),
    ``uint16`` (``png16``) or ``float32``. ``transform`` and ``crs`` make the array a DEM (see
    :func:`terrain`).

    Raises :class:`ParameterError` for a bad parameter, :class:`InputError` for unusable
    heights, :class:`Canceled` when ``progress`` returned ``False``; the messages are the CLI's.
    """
    # Unknown names are the library's to refuse, with the CLI's and the service's message.
    a = _heights(heights)
    georef = _georef(transform, crs)
    out = _native.bake_array(a, param_pairs(params), georef, True, dtype, progress)
    return _result(out, transform=georef[0] if georef else None, crs=crs)


def _result(out: Dict[str, Any], **extra: Any) -> BakeResult:
    known = set(BakeResult.__dataclass_fields__)
    r = BakeResult(**{k: v for k, v in out.items() if k in known}, **extra)
    r.warnings = tuple(r.warnings)
    return r


def terrain(
    dem: Any,
    *,
    transform: Any = None,
    crs: Any = None,
    nodata: Any = None,
    outputs: Union[str, Iterable[str]] = ("angles", "svf"),
    progress: Optional[ProgressCallback] = None,
    **params: Any,
) -> BakeResult:
    """Terrain products (SPEC §3.7) of a DEM array: horizon ``angles`` and the sky-view factor
    ``svf`` by default.

    With ``transform`` (an ``affine.Affine`` or GDAL's six numbers) and ``crs`` (a rasterio or
    pyproj CRS, an EPSG code or string) the DEM defaults of a GeoTIFF apply: ``cell_size`` from
    the transform, ``height_scale`` = 1 / cell size, ``method=sweep`` at ``radius=unlimited``,
    ``edge=none``, earth curvature on; a geographic CRS needs ``cell_size`` in metres. Without a
    transform give ``cell_size``. ``nodata`` is the nodata value (a number or ``nan``); a float
    DEM with NaN in it and no ``nodata`` has NaN holes. Heights are taken as-is in every dtype.
    """
    a = _heights(dem)
    if nodata is None and a.dtype.kind == "f" and np.isnan(a).any():
        nodata = float("nan")
    if transform is None and crs is None:
        cell = params.get("cell_size")
        if cell is None:
            raise ParameterError(
                "invalid parameter `cell_size`: a DEM without a transform needs cell_size, its "
                "cells' size in map units (or pass transform= and crs=)",
                code="invalid_parameter", field="cell_size")
        georef = ((0.0, float(cell), 0.0, 0.0, 0.0, -float(cell)), "none", 0, 0)
    else:
        georef = _georef(transform, crs)
    params = dict(params, outputs=outputs, nodata=nodata)
    out = _native.bake_array(a, param_pairs(params), georef, False, "float32", progress)
    return _result(out, transform=georef[0] if transform is not None else None, crs=crs)


def bake_file(path: Union[str, os.PathLike], out_dir: Union[str, os.PathLike], **flags: Any) -> Dict[str, Any]:
    """``horizon-bake bake PATH -o OUT_DIR --flag value ...``, in this process: the same files,
    the same bake.json, the same refusals (OUT_DIR must not exist or be empty).

    Flags are keyword arguments with ``-`` as ``_`` (``format="png16,exr"``,
    ``max_distance=5000``, ``texture_layout="..."``); lists are comma-joined, ``True`` is
    ``on`` for a bake parameter and a bare switch for any other flag. Returns bake.json, parsed.
    """
    import json

    args = ["bake", os.fspath(path), "-o", os.fspath(out_dir)]
    for k, v in flags.items():
        if v is None or v is False:
            continue
        flag = "--" + k.replace("_", "-")
        if v is True and k not in PARAMETERS:
            args.append(flag)
        else:
            args.extend([flag, param_text(k, v) or ""])
    _native.run_cli(args)
    with open(os.path.join(os.fspath(out_dir), "bake.json"), encoding="utf-8") as f:
        return json.load(f)


def cube_map(size: int = 64) -> np.ndarray:
    """The channel-factor cube map (SPEC §4) of face size ``size``: ``(6, size, size, 4)``
    float32, faces +X, −X, +Y, −Y, +Z, −Z, the values ``horizon-bake cubemap`` writes."""
    return _native.cube_map(int(size))


from .client import Client  # noqa: E402  (needs the errors above)
