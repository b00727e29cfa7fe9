"""An artist's batch: bake every height map in a folder, one output folder per map.

    python examples/batch_bake.py textures/ baked/ --format png16,ktx2 --method exact

Each map gets what ``horizon-bake bake`` writes (the layers, bake.json), in BAKED/<name>/; a
map that fails is reported and the batch goes on. Extra ``--flag value`` pairs are the CLI's.
"""

import sys
from pathlib import Path

from tqdm import tqdm

import horizon_bake as hb


def main(argv):
    src, dst, *rest = argv
    flags = {}
    for flag, value in zip(rest[::2], rest[1::2]):
        flags[flag.lstrip("-").replace("-", "_")] = value
    maps = sorted(p for p in Path(src).iterdir()
                  if p.suffix.lower() in (".png", ".tif", ".tiff", ".exr"))
    failed = 0
    for path in tqdm(maps, unit="map"):
        out = Path(dst) / path.stem
        try:
            report = hb.bake_file(path, out, **flags)
        except hb.HorizonBakeError as e:
            failed += 1
            tqdm.write(f"{path.name}: {e}")
            continue
        tqdm.write(f"{path.name}: {', '.join(report['output']['files'])} "
                   f"in {report['timings_ms']['total']:.0f} ms")
    print(f"{len(maps) - failed} of {len(maps)} maps baked into {dst}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
