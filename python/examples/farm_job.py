"""A farm job script: submit a height map to a horizon-bake service, wait with a progress bar,
download the engine's files.

    python examples/farm_job.py http://127.0.0.1:8080 rock.png out/ --formats ktx2 --method exact

The service's address may also come from HORIZON_BAKE_URL and its key from HORIZON_BAKE_API_KEY.
A full queue (429) or a restarting server (503) is waited out; a bad parameter fails the job
with the service's own message.
"""

import os
import sys
from pathlib import Path

from tqdm import tqdm

import horizon_bake as hb


def main(argv):
    url, src, dst, *rest = argv
    params = {flag.lstrip("-").replace("-", "_"): value for flag, value in zip(rest[::2], rest[1::2])}
    client = hb.Client(os.environ.get("HORIZON_BAKE_URL", url),
                       api_key=os.environ.get("HORIZON_BAKE_API_KEY"))
    try:
        bake = client.submit(src, **params)
        with tqdm(total=100, unit="%", desc=bake["id"]) as bar:
            done = client.wait(bake, progress=lambda f: bar.update(round(f * 100) - bar.n))
    except hb.HorizonBakeError as e:
        print(f"job failed: {e}", file=sys.stderr)
        return 1
    out = Path(dst)
    out.mkdir(parents=True, exist_ok=True)
    wanted = [k for k in done["links"] if k not in ("self", "events")]
    for name in wanted:
        href = done["links"][name]
        result = href.split(f"/v1/bakes/{done['id']}/", 1)[1]
        data = client.fetch(done, result)
        ext = {"horizon_ktx2": ".ktx2", "horizon_dds": ".dds", "angles": ".tif", "svf": ".tif"}
        path = out / (name + ext.get(name, ".png"))
        path.write_bytes(data)
        print(f"{path}: {len(data)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
