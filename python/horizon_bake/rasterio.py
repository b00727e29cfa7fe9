"""rasterio in, GeoTIFF out: terrain products of a DEM file or open dataset.

:func:`terrain` reads one band with its transform, CRS and nodata and bakes it;
:func:`write` writes a product as a GeoTIFF with the DEM's georeferencing and the products'
nodata (the CLI's ``--format geotiff`` writes the same values, with its own tags).
"""

from __future__ import annotations

import os
from typing import Any, Union

import numpy as np

from . import BakeResult
from . import terrain as _terrain


def terrain(src: Union[str, os.PathLike, Any], *, band: int = 1, **params: Any) -> BakeResult:
    """The terrain products of ``band`` of ``src`` (a path or an open rasterio dataset), with
    its transform, CRS and nodata (``nodata=`` overrides the file's). The result keeps
    ``transform`` (GDAL order) and ``crs`` (the dataset's)."""
    import rasterio  # noqa: PLC0415 (optional dependency)

    if isinstance(src, (str, os.PathLike)):
        with rasterio.open(src) as ds:
            return terrain(ds, band=band, **params)
    nodata = params.pop("nodata", None)
    if nodata is None:
        nodata = src.nodatavals[band - 1]
    return _terrain(src.read(band), transform=src.transform, crs=src.crs, nodata=nodata,
                    **params)


def write(result: BakeResult, path: Union[str, os.PathLike], product: str = "svf") -> None:
    """Writes ``result.svf`` or ``result.angles`` (one band per azimuth) as a float32 GeoTIFF
    with the result's transform, CRS and products' nodata."""
    import rasterio  # noqa: PLC0415
    from affine import Affine  # noqa: PLC0415

    data = getattr(result, product)
    if data is None:
        raise ValueError(f"the result has no {product}; bake it with outputs including it")
    data = data[np.newaxis] if data.ndim == 2 else data
    profile = {
        "driver": "GTiff", "width": data.shape[2], "height": data.shape[1],
        "count": data.shape[0], "dtype": "float32", "nodata": result.product_nodata,
        "compress": "deflate", "tiled": True,
    }
    if result.transform is not None:
        profile["transform"] = Affine.from_gdal(*result.transform)
    if result.crs is not None:
        profile["crs"] = result.crs
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data.astype(np.float32, copy=False))
