"""GPU experiment: frame time of the posed 15k model versus launch block size and fast-math.

    python tools/launch_experiment.py
One JSON line per variant: block_dim, fast_math, ms per frame (median of 60 graph-replayed frames).
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import warp as wp

sys.path.insert(0, __file__.rsplit("/", 1)[0])
import profile_pbd  # noqa: E402

from wsim.device import quiet_warp  # noqa: E402
from wsim.kernels import pbd_contact as kc  # noqa: E402
from wsim.kernels import pbd as kp  # noqa: E402


def main() -> None:
    quiet_warp()
    for fast_math in (False, True):
        wp.set_module_options({"fast_math": fast_math}, kp)
        wp.set_module_options({"fast_math": fast_math}, kc)
        for block in (32, 64, 128, 256):
            world, body = profile_pbd.build("15k", True, "cuda:0")
            body._block_dim = block
            for _ in range(3):
                world.step()
            times = []
            for _ in range(60):
                t0 = time.perf_counter()
                world.step()
                times.append(time.perf_counter() - t0)
            print(json.dumps({"block_dim": block, "fast_math": fast_math, "ms_per_frame": 1e3 * statistics.median(times)}), flush=True)


if __name__ == "__main__":
    main()
