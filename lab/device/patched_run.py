"""benchmarks/peers/run_wtopo.py with lab/hard_views.py installed first when HARD_VIEWS is set (its power), and
without the unseen-background prune when UNSEEN=0, with the prune's two-epoch window (branch ``windowed``,
1823ddf: background surfels no view has shown for two epochs of views go, not only those never shown) when
WINDOW=1: the same arguments, the same result folder (for lab/device/d40.sh)."""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "..", "benchmarks", "peers"))



def install_window() -> None:
    """The window of branch ``windowed`` as a patch: each surfel records the last step (counted per rendered
    training view) that showed it, and a due prune takes the background surfels not shown for two epochs."""
    import torch

    from wtopo.fitting import _strategy as st
    from wtopo.fitting import surfels as sf

    sf._BUFFERS["seen_at"] = ((), -1.0)
    post, end, since = st.DensityStrategy.step_post_backward, st.DensityStrategy.step_end, [None]

    def step_post_backward(self, surfels, info):
        self._steps = getattr(self, "_steps", 0) + 1
        with torch.no_grad():
            surfels.buffers["seen_at"].masked_fill_(info.render.visibility > 0, float(self._steps))
        post(self, surfels, info)

    def step_end(self, stage, it, surfels):
        since[0] = None if self.views is None else getattr(self, "_steps", 0) - st.UNSEEN_AFTER_EPOCHS * self.views
        return end(self, stage, it, surfels)

    def prune_background(surfels, state, *, unseen=False):
        gone = near = state.near_cameras(surfels.means)
        counts = [near.sum()]
        if unseen:
            stale = ~near & state.outside_roi(surfels.means) & (surfels.buffers["seen_at"] < since[0])
            gone = near | stale
            counts.append(stale.sum())
        counts = [int(c) for c in torch.stack(counts).tolist()]
        k_near, k_stale = counts[0], (counts[1] if unseen else 0)
        if k_near + k_stale in (0, len(surfels)):
            return 0, 0
        surfels.prune(~gone)
        return k_near, k_stale

    st.DensityStrategy.step_post_backward = step_post_backward
    st.DensityStrategy.step_end = step_end
    st.prune_background = prune_background


if __name__ == "__main__":
    if os.environ.get("HARD_VIEWS"):
        import hard_views

        seed = next((int(a.split("=", 1)[1]) for a in sys.argv if a.startswith("runtime.seed=")), 0)
        hard_views.install(float(os.environ["HARD_VIEWS"]), seed)
    # hard_views.py draws views with replacement, so two epochs of iterations need not show every view twice:
    # the unseen-shell prune is off with it unless UNSEEN=1
    if os.environ.get("UNSEEN") == "0" or (os.environ.get("HARD_VIEWS") and os.environ.get("UNSEEN") != "1"):
        from wtopo.fitting import _strategy

        _strategy.UNSEEN_AFTER_EPOCHS = 10**9
    if os.environ.get("WINDOW") == "1":
        install_window()
    import run_wtopo

    run_wtopo.main(sys.argv[1:])
