"""Horizon angles and sky-view factor of a DEM that is a Dask array, block by block.

:func:`angles` and :func:`svf` run :func:`horizon_bake.terrain` on every block of the array
through dask's overlap (``dask.array.overlap.overlap``, what ``map_overlap`` is built on) with a halo of the radius + 1 texels around each block (no
padding beyond the map's own edges), so every texel sees every texel within its radius, as in
one bake of the whole map. The parameters are resolved once for the whole map (the DEM
defaults, the method, ``cell_size``) and every block bakes with them, so at a finite radius
(``radius`` in texels, or ``max_distance`` in map units) the result equals the untiled bake's;
``radius=unlimited`` and ``auto`` (which depends on the whole map's heights) are refused.

With ``method=sweep`` (the DEM default) a block equals the untiled bake within ``sweep``'s
stated tolerance; ``method=exact`` is equal to the value. A block with a nodata hole bakes it
as the whole map does (holes cast no horizon and are not occluders).

Chunks should be several times the halo wide: each block computes its halo again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import ParameterError, _crs_parts, _georef, _native, gdal_transform, param_pairs, terrain


def _plan(shape: tuple, transform: Any, crs: Any, params: dict) -> tuple:
    """(every resolved parameter as text, radius in texels, georef tuple) for the whole map."""
    h, w = shape
    if transform is None and crs is None:
        cell = params.get("cell_size")
        if cell is None:
            raise ParameterError(
                "invalid parameter `cell_size`: a DEM without a transform needs cell_size "
                "(or pass transform= and crs=)", code="invalid_parameter", field="cell_size")
        georef = ((0.0, float(cell), 0.0, 0.0, 0.0, -float(cell)), "none", 0, 0)
    else:
        georef = _georef(transform, crs)
    resolved, texels = _native.resolve(param_pairs(params), w, h, georef)
    if resolved["radius"] == "unlimited" and resolved["max_distance"] == "auto":
        raise ParameterError(
            "invalid parameter `radius`: blocks need a finite reach; give radius (texels) or "
            "max_distance (map units) — unlimited needs the whole map in one bake",
            code="invalid_parameter", field="radius")
    if texels is None:
        raise ParameterError(
            "invalid parameter `radius`: `auto` depends on the whole map's heights; give "
            "radius (texels) or max_distance (map units)",
            code="invalid_parameter", field="radius")
    return resolved, int(texels), georef


def _blocks(dem: Any, product: str, transform: Any = None, crs: Any = None, nodata: Any = None,
            **params: Any) -> Any:
    import dask.array as da  # noqa: PLC0415 (optional dependency)

    dem = da.asarray(dem)
    if dem.ndim != 2:
        raise ValueError(f"a DEM is a 2-D array, not shape {dem.shape}")
    params = dict(params, outputs=product, nodata=nodata)
    resolved, texels, georef = _plan(dem.shape, transform, crs, params)
    depth = texels + 1
    # Every block bakes with the whole map's resolved parameters (every one given, so the DEM
    # defaults do not re-resolve on the block) and its cell size.
    fixed = {k: v for k, v in resolved.items() if k not in ("nodata",)}
    fixed["nodata"] = param_pairs({"nodata": nodata})[0][1] if nodata is not None else "none"
    t = georef[0]

    def one(block: np.ndarray) -> np.ndarray:
        # A float block may hold NaN holes the caller did not declare: as terrain() does.
        nd = fixed["nodata"]
        if nd == "none" and block.dtype.kind == "f" and np.isnan(block).any():
            nd = "nan"
        if nd != "none":
            holes = np.isnan(block) if nd == "nan" else block == np.float64(nd)
            if holes.all():
                # A block with no height left (the sea, a clipped corner) is all holes, as
                # the whole map's bake writes them; alone it would be refused as empty.
                fill = np.float32(np.nan if nd == "nan" else float(nd))
                shape = ((bins_of(),) if product == "angles" else ()) + block.shape
                return np.full(shape, fill, dtype=np.float32)
        out = terrain(block, transform=t, crs=_crs_of(georef), **dict(fixed, nodata=nd))
        a = out.angles if product == "angles" else out.svf
        return a.astype(np.float32, copy=False)

    def bins_of() -> int:
        return int(resolved["bins"])

    # The halo by hand (dask's overlap, no padding at the map's own edges) and the trim in the
    # block: map_overlap cannot trim an output with a dimension the input has not (azimuth).
    rows, cols = dem.numblocks
    grown = da.overlap.overlap(dem, depth={0: depth, 1: depth}, boundary="none")

    def trimmed(block: np.ndarray, block_info: Any = None) -> np.ndarray:
        i, j = block_info[0]["chunk-location"]
        y0 = depth if i > 0 else 0
        x0 = depth if j > 0 else 0
        y1 = block.shape[0] - (depth if i < rows - 1 else 0)
        x1 = block.shape[1] - (depth if j < cols - 1 else 0)
        out = one(block)
        return out[..., y0:y1, x0:x1]

    if product == "angles":
        bins = int(resolved["bins"])
        return da.map_blocks(trimmed, grown, dtype=np.float32, new_axis=0,
                             chunks=((bins,),) + dem.chunks)
    return da.map_blocks(trimmed, grown, dtype=np.float32, chunks=dem.chunks)


def _crs_of(georef: tuple) -> Any:
    """The CRS to hand a block: the EPSG code the whole map resolved to (model kept)."""
    model, code = georef[1], georef[2]
    if model == "none":
        return None
    return _BlockCrs(model, code, georef[3])


class _BlockCrs:
    """A CRS already read: its model, EPSG code and linear unit, passed through unchanged."""

    def __init__(self, model: str, code: int, unit: int):
        self.is_geographic = model == "geographic"
        self._code = code
        self.linear_units = {9002: "foot", 9003: "US survey foot"}.get(unit, "metre")

    def to_epsg(self) -> int:
        return self._code


def angles(dem: Any, *, transform: Any = None, crs: Any = None, nodata: Any = None,
           **params: Any) -> Any:
    """Horizon angles of a Dask DEM: a ``(bins, H, W)`` float32 Dask array, band n at
    n·360°/bins (``azimuth_from``), in ``angle_unit``. Needs ``radius`` (texels) or
    ``max_distance`` (map units); other parameters as :func:`horizon_bake.terrain`."""
    return _blocks(dem, "angles", transform, crs, nodata, **params)


def svf(dem: Any, *, transform: Any = None, crs: Any = None, nodata: Any = None,
        **params: Any) -> Any:
    """Sky-view factor of a Dask DEM: an ``(H, W)`` float32 Dask array (as :func:`angles`)."""
    return _blocks(dem, "svf", transform, crs, nodata, **params)


__all__ = ["angles", "svf", "gdal_transform", "_crs_parts"]
