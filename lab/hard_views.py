"""Lab (nothing in the package imports it): an experiment in how each iteration's training view is drawn.

``install(power, seed)`` patches the fit of this process so that each iteration draws its view with probability
proportional to that view's photometric loss running average raised to ``power``. The package draws one permutation
of the views per epoch instead. A resumed fit does not draw the same views (the averages are not checkpointed). Used
by ``lab/dtu_view40.py --hard-views`` and ``HARD_VIEWS=power lab/heldout.py``.
"""


def install(power: float, seed: int) -> None:
    """Patch the fit (this process only) to draw each iteration's training view with probability proportional to
    its photometric loss's running average raised to ``power`` (every view starts at the largest average seen, so
    each is drawn early), instead of one permutation of the views per epoch."""
    import numpy as np

    from wtopo.fitting import loop, objective

    state = {"ema": {}, "view": None, "rng": np.random.default_rng(seed)}
    real_add = objective.LossLog.add

    def add(self, terms, *, first):
        v = state["view"]
        if v is not None and "photo" in terms:
            old = state["ema"].get(v)
            state["ema"][v] = terms["photo"] if old is None else 0.8 * old + 0.2 * terms["photo"]
        return real_add(self, terms, first=first)

    def view(self, it):
        n = len(self.train.cameras)
        top = max(state["ema"].values(), default=1.0)
        w = np.array([state["ema"].get(i, top) for i in range(n)]) ** power
        state["view"] = int(state["rng"].choice(n, p=w / w.sum()))
        return state["view"]

    objective.LossLog.add = add
    loop.FitRun._view = view
