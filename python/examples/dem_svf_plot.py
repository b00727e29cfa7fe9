"""A notebook's DEM → sky-view factor plot (run it as a script, or paste it into a cell).

    python examples/dem_svf_plot.py dem.tif svf.png

Reads the DEM with rasterio (its transform, CRS and nodata), bakes the sky-view factor with a
3 km horizon, and plots it with matplotlib beside the DEM.
"""

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from horizon_bake import rasterio as hbr  # noqa: E402

dem_path, out = sys.argv[1], sys.argv[2]
with tqdm(total=100, unit="%") as bar:
    def progress(fraction):
        bar.update(round(fraction * 100) - bar.n)

    r = hbr.terrain(dem_path, outputs="svf", max_distance=3000, progress=progress)
svf = np.where(r.svf == r.product_nodata, np.nan, r.svf)
print(f"sky-view factor of {dem_path}: {r.width}×{r.height}, cell {r.params['cell_size']}, "
      f"{r.params['method']} to {r.resolved_radius['texels']} texels, "
      f"mean {np.nanmean(svf):.3f}, min {np.nanmin(svf):.3f}")
fig, ax = plt.subplots(1, 1, figsize=(6, 6 * r.height / r.width))
im = ax.imshow(svf, cmap="gray", vmin=np.nanpercentile(svf, 1), vmax=1.0)
fig.colorbar(im, ax=ax, label="sky-view factor")
ax.set_title("sky-view factor")
ax.set_axis_off()
fig.savefig(out, dpi=100, bbox_inches="tight")
print(f"wrote {out}")
