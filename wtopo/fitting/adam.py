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
        groups: the parameter groups; every parameter a floating-point leaf tensor.
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
            if not all(isinstance(p, torch.Tensor) and p.is_floating_point() for p in params):
                raise TypeError(f"group {g.get('name')!r}: params must be floating-point tensors")
            self.param_groups.append({**self.defaults, **{k: v for k, v in g.items() if k != "params"},
                                      "params": params})
        self.state: dict[torch.Tensor, dict] = {}

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient.

        The parameters of every group with the same betas and eps are updated together by torch's multi-tensor
        (``_foreach``) operations, each with its own step count and rate: on CUDA seven launches in all instead of
        seven per parameter; on the CPU torch loops over the tensors itself (4x faster than from Python at 20k
        surfels, ``benchmarks/bench_optimizer.py``).
        """
        buckets: dict[tuple, list] = {}
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
                buckets.setdefault((b1, b2, eps, p.device, p.dtype), []).append(
                    (p, p.grad, st, lr / (1 - b1 ** t), math.sqrt(1 - b2 ** t)))
        for (b1, b2, eps, _, _), items in buckets.items():
            params = [it[0] for it in items]
            grads = [it[1] for it in items]
            m = [it[2]["exp_avg"] for it in items]
            v = [it[2]["exp_avg_sq"] for it in items]
            torch._foreach_lerp_(m, grads, 1 - b1)
            torch._foreach_mul_(v, b2)
            torch._foreach_addcmul_(v, grads, grads, value=1 - b2)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, [it[4] for it in items])
            torch._foreach_add_(denom, eps)
            torch._foreach_addcdiv_(params, m, denom, [-it[3] for it in items])

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
