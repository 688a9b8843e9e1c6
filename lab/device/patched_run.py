"""benchmarks/peers/run_wtopo.py with lab/hard_views.py installed first when HARD_VIEWS is set (its power), and with
the mask term kept through the warm-up only when MASK_WARMUP_ONLY is set (lab/mask_warmup_only.py), and with the
final fusion's truncation at FINAL_TRUNCATION voxels when that is set (lab/final_truncation.py): the same
arguments, the same result folder (for lab/device/d40.sh and bias_all.sh)."""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "..", "benchmarks", "peers"))

if __name__ == "__main__":
    if os.environ.get("HARD_VIEWS"):
        import hard_views

        seed = next((int(a.split("=", 1)[1]) for a in sys.argv if a.startswith("runtime.seed=")), 0)
        hard_views.install(float(os.environ["HARD_VIEWS"]), seed)
    if os.environ.get("MASK_WARMUP_ONLY"):
        import mask_warmup_only
        from wtopo.fitting import objective

        objective.Objective.__call__ = mask_warmup_only._warmup_mask_only
    if os.environ.get("FINAL_TRUNCATION"):
        import final_truncation

        final_truncation.install()
    import run_wtopo

    run_wtopo.main(sys.argv[1:])
