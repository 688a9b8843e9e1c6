"""benchmarks/peers/run_wtopo.py with lab/hard_views.py installed first when HARD_VIEWS is set (its power), and
lab/fit_patches.py's patches by their variables: the same arguments, the same result folder (for lab/device/d40.sh
and bias_all.sh); with KEEP_PRE_OUTLINE, also the result folder OUT_pre of the mesh before the outline offset
(lab/pre_outline.py); with SCENE_FUSION, a result folder per fusion variant (lab/scene_fusion.py)."""
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
    import fit_patches

    fit_patches.install_from_env()
    import run_wtopo

    run_wtopo.main(sys.argv[1:])
    if os.environ.get("KEEP_PRE_OUTLINE"):
        import pre_outline

        pre_outline.write_result(sys.argv[2])  # run_wtopo.py's OUT: its arguments begin EXCH OUT (bias_all.sh)
    if os.environ.get("SCENE_FUSION"):
        import scene_fusion

        scene_fusion.write_results(sys.argv[2])
