#!/usr/bin/env python3
"""Cut the eval's real-terrain excerpt out of a DEM that a package ships.

matplotlib (PyPI) ships `jacksboro_fault_dem.npz` in its sample data: a USGS 3-arc-second
elevation grid (int16 metres, 344 x 403) around the Jacksboro fault, Tennessee. This script
takes its top-left 128 x 128 texels and writes them as a 16-bit grayscale PNG whose value is
metres above the excerpt's lowest point. With 3 arc-seconds ~ 90 m per texel, the eval bakes it
with height_scale = 65535 / 90 (heights in texels = metres / 90).

    pip install numpy pillow matplotlib
    python3 scripts/extract_terrain.py docs/corpus/jacksboro_128.png
"""
import sys

import numpy as np
from matplotlib import cbook
from PIL import Image

SIZE = 128


def main(out):
    dem = cbook.get_sample_data("jacksboro_fault_dem.npz")
    elev = dem["elevation"].astype(np.int32)[:SIZE, :SIZE]
    rel = (elev - elev.min()).astype(np.uint16)
    Image.fromarray(rel).save(out)
    print(f"{out}: {SIZE}x{SIZE}, relief {int(rel.max())} m")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/corpus/jacksboro_128.png")
