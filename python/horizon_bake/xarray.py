"""xarray in, xarray out: terrain products of a DEM ``DataArray`` with its coordinates, CRS and
nodata kept.

The transform, CRS and nodata come from rioxarray's ``.rio`` accessor when the array has them
(``rioxarray.open_rasterio``), else from ``transform=``/``crs=``/``nodata=`` or ``cell_size=``.
The products come back on the DEM's own ``y``/``x`` coordinates (``angles`` with an ``azimuth``
dimension in degrees, counted as ``azimuth_from`` says), with the CRS and the products' nodata
written back through ``.rio`` when rioxarray is installed and in ``attrs`` always
(``crs`` as WKT, ``transform`` as GDAL's six numbers, ``_FillValue``/``nodata``).
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from . import terrain as _terrain


def _rio(da: Any) -> Optional[Any]:
    try:
        import rioxarray  # noqa: F401, PLC0415 (registers .rio)
    except ImportError:
        return None
    return getattr(da, "rio", None)


def _grid(da: Any, transform: Any, crs: Any, nodata: Any) -> tuple:
    rio = _rio(da)
    if rio is not None:
        if crs is None:
            crs = rio.crs
        if transform is None and crs is not None:
            try:
                transform = rio.transform()
            except Exception:  # no spatial dims: the caller gives cell_size
                transform = None
        if nodata is None:
            nodata = rio.nodata
    if nodata is None:
        nodata = da.attrs.get("_FillValue", da.attrs.get("nodata"))
    return transform, crs, nodata


def terrain(da: Any, *, transform: Any = None, crs: Any = None, nodata: Any = None,
            outputs: Any = ("angles", "svf"), **params: Any) -> Any:
    """The terrain products of a 2-D DEM ``DataArray`` as an ``xarray.Dataset`` with
    ``angles`` (``azimuth``, y, x) and/or ``svf`` (y, x) on the DEM's coordinates. Parameters
    as :func:`horizon_bake.terrain`."""
    import xarray as xr  # noqa: PLC0415 (optional dependency)

    if da.ndim == 3 and da.shape[0] == 1:  # open_rasterio's band dimension
        da = da.isel({da.dims[0]: 0}, drop=True)
    if da.ndim != 2:
        raise ValueError(f"a DEM is a 2-D DataArray, not dims {da.dims}")
    transform, crs, nodata = _grid(da, transform, crs, nodata)
    r = _terrain(np.asarray(da.values), transform=transform, crs=crs, nodata=nodata,
                 outputs=outputs, **params)
    ydim, xdim = da.dims
    coords = {d: da.coords[d] for d in (ydim, xdim) if d in da.coords}
    fill = r.product_nodata
    attrs = {"_FillValue": fill, "nodata": fill}
    if r.transform is not None:
        attrs["transform"] = tuple(r.transform)
    out = {}
    if r.svf is not None:
        out["svf"] = xr.DataArray(r.svf, dims=(ydim, xdim), coords=coords,
                                  attrs=dict(attrs, long_name="sky-view factor",
                                             svf_model=r.params["svf_model"]))
    if r.angles is not None:
        bins = r.angles.shape[0]
        az = np.arange(bins) * 360.0 / bins
        out["angles"] = xr.DataArray(
            r.angles, dims=("azimuth", ydim, xdim), coords=dict(coords, azimuth=az),
            attrs=dict(attrs, long_name="horizon angle", units=r.params["angle_unit"],
                       azimuth_from=r.params["azimuth_from"]))
    ds = xr.Dataset(out, attrs={"horizon_bake_params": str(r.params)})
    rio = _rio(ds)
    for name in out:
        v = ds[name]
        if rio is not None and crs is not None:
            v = v.rio.write_crs(crs)
            if r.transform is not None:
                from affine import Affine  # noqa: PLC0415 (a rasterio dependency)

                v = v.rio.write_transform(Affine.from_gdal(*r.transform))
            v = v.rio.write_nodata(fill, encoded=False)
        elif crs is not None:
            v.attrs["crs"] = getattr(crs, "to_wkt", lambda: str(crs))()
        ds[name] = v
    if rio is not None and crs is not None:
        ds = ds.rio.write_crs(crs)
    return ds


def svf(da: Any, **params: Any) -> Any:
    """The sky-view factor of a DEM ``DataArray``, a ``DataArray`` on its coordinates."""
    return terrain(da, outputs="svf", **params)["svf"]


def angles(da: Any, **params: Any) -> Any:
    """The horizon angles of a DEM ``DataArray``: (``azimuth``, y, x)."""
    return terrain(da, outputs="angles", **params)["angles"]
