"""Lab (nothing imports it): benchmarks/peers/run_wtopo.py with the initial surfels' plane sweep replaced by the
coarse-to-fine sweep of ``lab/stereo_c2f.py`` (smoothed field, each side of a depth edge: its best row; #60: stereo
10.8 s of DTU's 101 s on an H200, goal 3 s), to measure what it does to the held-out PSNR and ROI F1 on the GPU before
anything lands. Views smaller than ``MIN_SIDE`` pixels on a side (the unbounded region's own sweep at reduced size)
keep the fit's sweep. Prints the sweep's time.

    python3 lab/run_c2f.py EXCH OUT [run_wtopo.py's arguments]
"""
import os
import runpy
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import stereo_c2f  # noqa: E402
from wtopo.geometry import mvs  # noqa: E402

MIN_SIDE = 100
_full = mvs.plane_sweep_points


def plane_sweep_points(cameras, images, roi_lower, roi_upper, *, near, device="cpu", max_views=None):
    t = time.perf_counter()
    small = min(min(c.height, c.width) for c in cameras) < MIN_SIDE
    if small:
        out = _full(cameras, images, roi_lower, roi_upper, near=near, device=device, max_views=max_views)
    else:
        out = stereo_c2f.c2f_points(cameras, images, roi_lower, roi_upper, near=near, device=device,
                                    max_views=max_views, edges=True)
    print(f"[c2f] {'full' if small else 'coarse to fine'} sweep of {len(cameras)} views: "
          f"{len(out.points)} points in {time.perf_counter() - t:.2f} s", flush=True)
    return out


mvs.plane_sweep_points = plane_sweep_points

if __name__ == "__main__":
    sys.argv = [os.path.join(HERE, "..", "benchmarks", "peers", "run_wtopo.py"), *sys.argv[1:]]
    runpy.run_path(sys.argv[0], run_name="__main__")
