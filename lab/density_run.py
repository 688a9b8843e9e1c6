"""benchmarks/peers/run_wtopo.py with the warm-up's density constants of one variant (a lab script).

    python lab/density_run.py VARIANT EXCH OUT [run_wtopo.py's arguments]

VARIANT as in lab/density_ab.py (base, 3dgs, grad2); the result folder is labelled "wtopo (density VARIANT)" so the
peers' scorer puts it beside the others."""
import os
import runpy
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from density_ab import VARIANTS  # noqa: E402
from wtopo.fitting import _strategy, densify  # noqa: E402


def main():
    variant = sys.argv.pop(1)
    v = VARIANTS[variant]
    if "grad" in v:
        densify.GRAD_THRESHOLD = v["grad"]
    if "prune" in v:
        _strategy.PRUNE_OPACITY = v["prune"]
    path = os.path.join(HERE, "..", "benchmarks", "peers", "run_wtopo.py")
    sys.argv = [path, *sys.argv[1:], "--label", f"wtopo (density {variant})"]
    runpy.run_path(path, run_name="__main__")


if __name__ == "__main__":
    main()
