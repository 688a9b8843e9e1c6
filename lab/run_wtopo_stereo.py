"""Lab (nothing imports it): ``benchmarks/peers/run_wtopo.py`` with the plane-sweep stereo capped at
``--stereo-pixels`` pixels per view (``wtopo.fitting._init_surfels._STEREO_MAX_PIXELS``), for the A/B of
lab/stereo_res.py's question on whole fits.

    python lab/run_wtopo_stereo.py --stereo-pixels 32768 EXCH OUT [run_wtopo.py's arguments]
"""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

if __name__ == "__main__":
    import run_wtopo

    from wtopo.fitting import _init_surfels

    args = sys.argv[1:]
    i = args.index("--stereo-pixels")
    _init_surfels._STEREO_MAX_PIXELS = int(args[i + 1])
    del args[i:i + 2]
    run_wtopo.main(args)
