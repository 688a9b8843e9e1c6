# SPDX-License-Identifier: Apache-2.0
"""Adam for the surfel parameters, without ``torch.optim``.

``torch.optim.Optimizer.add_param_group`` is wrapped to disable TorchDynamo, and its first call imports
``torch._dynamo``: about 1.6 s on a 2-core CPU, paid by every fit for a compiler it never uses. This class is
the update of ``torch.optim.Adam`` (no weight decay, no AMSGrad; the single-tensor path's operations in the
same order, as torch's multi-tensor operations) with the parts of its interface the fit uses:
``param_groups`` (one dict per group with ``"params"``, ``"lr"``, ``"name"``), ``state`` (per parameter
``"step"``, ``"exp_avg"``, ``"exp_avg_sq"``), :meth:`step`, :meth:`zero_grad`, and :meth:`state_dict` /
:meth:`load_state_dict` in ``torch.optim.Adam``'s layout, so checkpoints written by either load into the
other.
"""

from __future__ import annotations

import math

import torch

__all__ = ["Adam"]

# what torch.optim.Adam's groups also hold (its defaults): written into state_dict() so that torch's Adam
# loads it too; ignored on load
_TORCH_GROUP = {"weight_decay": 0.0, "amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
                "differentiable": False, "fused": None, "decoupled_weight_decay": False}


class Adam:
    """Adam over parameter groups (``[{"params": [tensor, ...], "lr": float, "name": str}, ...]``).

    Args:
        groups: the parameter groups; every parameter a contiguous float32 or float64 leaf tensor, all on one device.
        betas: the moments' decay rates.
        eps: added to the second moment's root (after bias correction), as ``torch.optim.Adam``.
    """

    def __init__(self, groups: list[dict], *, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        b1, b2 = (float(b) for b in betas)
        if not (0.0 <= b1 < 1.0 and 0.0 <= b2 < 1.0):
            raise ValueError(f"betas must lie in [0, 1), got {betas!r}")
        if not eps >= 0.0:
            raise ValueError(f"eps must be >= 0, got {eps!r}")
        self.defaults = {"betas": (b1, b2), "eps": float(eps)}
        self.param_groups: list[dict] = []
        for g in groups:
            params = list(g["params"])
            if not all(isinstance(p, torch.Tensor) and p.dtype in (torch.float32, torch.float64) for p in params):
                raise TypeError(f"group {g.get('name')!r}: params must be floating-point tensors (float32 or float64)")
            if not all(p.is_contiguous() for p in params):
                raise ValueError(f"group {g.get('name')!r}: params must be contiguous")
            self.param_groups.append({**self.defaults, **{k: v for k, v in g.items() if k != "params"},
                                      "params": params})
        devices = {p.device for g in self.param_groups for p in g["params"]}
        if len(devices) > 1:
            raise ValueError(f"params must lie on one device, got {sorted(map(str, devices))}")
        self.state: dict[torch.Tensor, dict] = {}

    @torch.no_grad()
    def step(self) -> torch.Tensor | None:
        """One update of every parameter that has a gradient, with no host synchronisation.

        A gradient's non-finite elements are zeroed first (in the gradient too). Returns a 0-dim bool tensor on the
        parameters' device, ``True`` when every gradient and updated parameter was finite by their norms (an
        overflowing norm of absurd values counts as not finite, so a gradient large enough to overflow the second
        moment does), or ``None`` when no parameter has a gradient.

        The parameters of the same betas, eps and dtype are updated together by torch's multi-tensor (``_foreach``)
        operations, each with its own step count and rate (``benchmarks/bench_optimizer.py``).
        """
        items = []
        for g in self.param_groups:
            b1, b2 = g["betas"]
            lr, eps = float(g["lr"]), float(g["eps"])
            for p in g["params"]:
                if p.grad is None:
                    continue
                st = self.state.get(p)
                if not st:
                    st = self.state[p] = {"step": torch.tensor(0.0), "exp_avg": torch.zeros_like(p),
                                          "exp_avg_sq": torch.zeros_like(p)}
                st["step"] += 1
                t = float(st["step"])
                items.append((p, st, b1, b2, eps, lr / (1 - b1 ** t), math.sqrt(1 - b2 ** t)))
        if not items:
            return None
        return _update(items)

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop (or zero) every parameter's gradient."""
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    def state_dict(self) -> dict:
        """``{"state": {index: {...}}, "param_groups": [{..., "params": [index, ...]}]}``, parameters numbered in
        group order (``torch.optim``'s layout); the tensors are the live ones, as there."""
        index, groups, n = {}, [], 0
        for g in self.param_groups:
            ids = []
            for p in g["params"]:
                index[p] = n
                ids.append(n)
                n += 1
            groups.append({**_TORCH_GROUP, **{k: v for k, v in g.items() if k != "params"}, "params": ids})
        return {"state": {index[p]: st for p, st in self.state.items() if p in index}, "param_groups": groups}

    def load_state_dict(self, sd: dict) -> None:
        """Load a :meth:`state_dict` (or ``torch.optim.Adam``'s) for the same groups: moments and steps are copied
        onto each parameter's device and dtype, the groups' settings (rates, betas, eps) taken over."""
        groups = sd["param_groups"]
        if len(groups) != len(self.param_groups) or any(
                len(a["params"]) != len(b["params"]) for a, b in zip(groups, self.param_groups)):
            raise ValueError("optimiser state does not match the parameter groups (count or sizes differ)")
        self.state = {}
        for g, saved in zip(self.param_groups, groups):
            for k in ("lr", "betas", "eps"):
                if k in saved:
                    g[k] = tuple(saved[k]) if k == "betas" else saved[k]
            for p, i in zip(g["params"], saved["params"]):
                st = sd["state"].get(i)
                if not st:
                    continue
                self.state[p] = {"step": torch.as_tensor(st["step"], dtype=torch.float32).detach().clone().cpu(),
                                 **{k: st[k].detach().to(device=p.device, dtype=p.dtype, copy=True)
                                    for k in ("exp_avg", "exp_avg_sq")}}


def _update(items: list) -> torch.Tensor:
    """:meth:`Adam.step`'s update by torch's multi-tensor operations, parameters of the same betas, eps and dtype
    together (the single-tensor path's operations in the same order, per-parameter rates as scalar lists; ``items``:
    ``(param, state, b1, b2, eps, step size, root correction)``), with the checks; returns whether all was finite."""
    grads = [it[0].grad for it in items]
    finite = torch.isfinite(torch.stack(torch._foreach_norm(grads))).all()
    for g in grads:
        g.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
    buckets: dict[tuple, list] = {}
    for it in items:
        buckets.setdefault((it[2], it[3], it[4], it[0].dtype), []).append(it)
    for (b1, b2, eps, _), group in buckets.items():
        params = [it[0] for it in group]
        grads = [it[0].grad for it in group]
        m = [it[1]["exp_avg"] for it in group]
        v = [it[1]["exp_avg_sq"] for it in group]
        torch._foreach_lerp_(m, grads, 1 - b1)
        torch._foreach_mul_(v, b2)
        torch._foreach_addcmul_(v, grads, grads, value=1 - b2)
        denom = torch._foreach_sqrt(v)
        torch._foreach_div_(denom, [it[6] for it in group])
        torch._foreach_add_(denom, eps)
        torch._foreach_addcdiv_(params, m, denom, [-it[5] for it in group])
    return torch.isfinite(torch.stack(torch._foreach_norm([it[0].detach() for it in items]))).all() & finite
