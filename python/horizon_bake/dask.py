"""Horizon angles and sky-view factor of a DEM that is a Dask array, block by block.

:func:`angles` and :func:`svf` bake every block of the array, as a tile of the whole map,
through ``dask.array.map_overlap`` with a halo of the radius + 1 texels around each block (no
padding beyond the map's own edges), so every texel sees every texel within its radius, as in
one bake of the whole map. The parameters are resolved once for the whole map (the DEM
defaults, the method, ``cell_size``) and every block bakes with them, so at a finite radius
(``radius`` in texels, or ``max_distance`` in map units) the result equals the untiled bake's;
``radius=unlimited`` and ``auto`` (which depends on the whole map's heights) are refused.

Each block is baked as a tile of a tiled bake is (SPEC §7.1): with the whole map's hole fill
and height range, so the values are the whole map's to the bit. One caveat, the library's own:
``method=sweep`` on a window with a nodata hole runs ``exact`` there (as it does on a whole map
with holes), so with ``sweep`` a block that holds a hole while the whole map runs ``sweep``, or
the reverse, agrees within ``sweep``'s stated tolerance rather than to the bit.

Chunks should be several times the halo wide: each block computes its halo again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import ParameterError, _errors as hb_errors, _georef, _native, param_pairs


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
    # Every block bakes with the whole map's resolved parameters (every one given, so nothing
    # re-resolves on the block), radius, hole fill and height range (the kernels' reference
    # height), as the tiles of a tiled bake do: so each texel gets the whole map's value.
    fixed = dict(resolved)
    if nodata is None and np.dtype(dem.dtype).kind == "f":
        # As terrain(): NaN in a float DEM without a declared nodata are holes.
        fixed["nodata"] = "nan" if bool(da.isnan(dem).any().compute()) else "none"
    elif nodata is None:
        fixed["nodata"] = "none"
    else:
        fixed["nodata"] = param_pairs({"nodata": nodata})[0][1]
    # Blocks at least as large as the halo (dask's overlap would otherwise re-chunk on its own
    # and the output's chunks would no longer be the input's).
    heights = dem.astype(np.float32).rechunk(tuple(_at_least(c, depth) for c in dem.chunks))
    nd = fixed["nodata"]
    if nd == "none":
        holes = da.zeros(dem.shape, dtype=bool, chunks=dem.chunks)
    elif nd == "nan":
        holes = da.isnan(heights)
    else:
        holes = heights == np.float32(float(nd))
    lo, hi, any_hole = da.compute(da.where(holes, np.inf, heights).min(),
                                  da.where(holes, -np.inf, heights).max(), holes.any())
    if not np.isfinite(lo):
        raise hb_errors.InputError(
            f"invalid height map: every texel is nodata ({nd}): the map has no height left to "
            "bake", code="invalid_input")
    stats = (float(lo), float(hi), bool(any_hole))
    pairs = list(fixed.items())
    bins = int(resolved["bins"])
    fill = np.float32(np.nan if nd in ("nan", "none") else float(nd))

    # map_overlap adds the halo (no padding at the map's own edges); the block trims it itself
    # (trim=False), as map_overlap cannot trim an output with a dimension its input has not
    # (azimuth), and a block at the map's edge has no halo on that side.
    rows, cols = heights.numblocks

    def trimmed(block: np.ndarray, block_info: Any = None) -> np.ndarray:
        i, j = block_info[0]["chunk-location"]
        y0 = depth if i > 0 else 0
        x0 = depth if j > 0 else 0
        y1 = block.shape[0] - (depth if i < rows - 1 else 0)
        x1 = block.shape[1] - (depth if j < cols - 1 else 0)
        interior = (x0, y0, x1 - x0, y1 - y0)
        block = np.ascontiguousarray(block, dtype=np.float32)
        if nd != "none":
            bh = np.isnan(block) if nd == "nan" else block == np.float32(float(nd))
            if bh.all():
                # No height left in the window (the sea, a clipped corner): all holes, as the
                # whole map's bake writes them; alone it would be refused as empty.
                shape = ((bins,) if product == "angles" else ()) + (y1 - y0, x1 - x0)
                return np.full(shape, fill, dtype=np.float32)
        angles, svf = _native.bake_block(block, interior, pairs, stats, texels, georef)
        return angles if product == "angles" else svf

    common = dict(depth={0: depth, 1: depth}, boundary="none", trim=False, dtype=np.float32)
    if product == "angles":
        return da.map_overlap(trimmed, heights, new_axis=0, chunks=((bins,),) + heights.chunks,
                              **common)
    return da.map_overlap(trimmed, heights, chunks=heights.chunks, **common)


def _at_least(chunks: tuple, size: int) -> tuple:
    """``chunks`` with every chunk smaller than ``size`` merged into its neighbour."""
    out = list(chunks)
    i = 0
    while len(out) > 1 and i < len(out):
        if out[i] < size:
            j = i - 1 if i == len(out) - 1 else i + 1
            out[min(i, j)] = out[i] + out[j]
            del out[max(i, j)]
            i = 0
        else:
            i += 1
    return tuple(out)


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


__all__ = ["angles", "svf"]
