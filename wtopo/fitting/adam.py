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

On CUDA the update is replayed as a CUDA graph (:data:`GRAPHS`): at DTU's 384 px the fit's iteration is bound by
the host, and the eager update's ~25 multi-tensor operations cost about a millisecond of it.
"""

from __future__ import annotations

import math
import warnings

import torch

from .._graphs import collector_off

__all__ = ["Adam", "GRAPHS"]

GRAPHS = True
"""False: the update runs eagerly on CUDA too (benchmarks, tests)."""
_GRAPHS_KEPT = 2  # captured updates kept per optimiser (the current tensors' and the one before)
_CHECK_RTOL, _CHECK_ATOL = 1e-4, 1e-6  # a graph's first replay farther than this from the eager update is not used

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
        self._graphs: dict[tuple, _StepGraph | None] = {}
        self._emulate = False  # tests: the graph's update (device rates, fixed buffers) without a capture
        self.graph_failure: str | None = None  # why the update runs eagerly on CUDA, when a capture failed

    @torch.no_grad()
    def step(self) -> torch.Tensor | None:
        """One update of every parameter that has a gradient, with no host synchronisation.

        A gradient's non-finite elements are zeroed first (in the gradient too). Returns a 0-dim bool tensor on the
        parameters' device, ``True`` when every gradient and updated parameter was finite by their norms (an
        overflowing norm of absurd values counts as not finite, so a gradient large enough to overflow the second
        moment does), or ``None`` when no parameter has a gradient.

        The parameters of the same betas, eps and dtype are updated together by torch's multi-tensor (``_foreach``)
        operations, each with its own step count and rate (``benchmarks/bench_optimizer.py``). On CUDA the update is
        a CUDA graph captured per set of parameters and moments (a new one after a densification step, whose first
        update runs eagerly): the rates travel in a device tensor, the gradients are copied into the graph's
        buffers, and each parameter's ``grad`` becomes that buffer (with its non-finite elements zeroed), valid
        until the next step. A graph's first replay is checked against the eager update of a copy of the state
        (host reads once per capture). A capture that fails or a replay that disagrees leaves the update eager, with
        a warning (:attr:`graph_failure`).
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
        if self.graph_failure is not None or not (self._emulate or (GRAPHS and items[0][0].is_cuda)):
            return _update(items)
        key = tuple((it[0].data_ptr(), it[1]["exp_avg"].data_ptr(), it[1]["exp_avg_sq"].data_ptr(),
                     tuple(it[0].shape), it[0].dtype, it[2], it[3], it[4]) for it in items)
        graph = self._graphs.get(key)
        if graph is None:
            out = _update(items)  # this step eagerly: it also warms up every operation the capture records
            while len(self._graphs) >= _GRAPHS_KEPT:
                self._graphs.pop(next(iter(self._graphs)))
            try:
                self._graphs[key] = _StepGraph(items, capture=not self._emulate)
            except Exception as e:  # noqa: BLE001 - any failure of the capture leaves the update eager
                self.graph_failure = f"{type(e).__name__}: {e}"
                self._graphs.clear()
                warnings.warn(f"wtopo: Adam's update runs eagerly on this device: {self.graph_failure}",
                              RuntimeWarning, stacklevel=2)
            return out
        if not graph.checked:
            return self._checked(graph, items)
        return graph(items)

    def _checked(self, graph: _StepGraph, items: list) -> torch.Tensor:
        """A graph's first replay, against the eager update of copies of the same state (host reads, once per
        capture); a disagreement leaves the update eager from here on, with the eager result kept."""
        before = [(it[0].detach().clone(), it[1]["exp_avg"].clone(), it[1]["exp_avg_sq"].clone(),
                   it[0].grad.clone()) for it in items]
        got = graph(items)
        ref = []
        for it, (p, m, v, g) in zip(items, before):
            p.grad = g
            ref.append((p, {"step": it[1]["step"], "exp_avg": m, "exp_avg_sq": v}, *it[2:]))
        want = _update(ref)
        pairs = [(a, b) for it, r in zip(items, ref)
                 for a, b in ((it[0], r[0]), (it[1]["exp_avg"], r[1]["exp_avg"]),
                              (it[1]["exp_avg_sq"], r[1]["exp_avg_sq"]))]
        if bool(got) == bool(want) and all(torch.allclose(a, b, rtol=_CHECK_RTOL, atol=_CHECK_ATOL, equal_nan=True)
                                           for a, b in pairs):
            graph.checked = True
            return got
        worst = max((float((a.detach() - b).abs().max()) for a, b in pairs if a.numel()), default=0.0)
        for a, b in pairs:
            a.detach().copy_(b)
        self._graphs.clear()
        self.graph_failure = f"a replay differs from the eager update (largest difference {worst:.3g})"
        warnings.warn(f"wtopo: Adam's update runs eagerly on this device: {self.graph_failure}", RuntimeWarning,
                      stacklevel=3)
        return want

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
    for (b1, b2, eps, _), group in _buckets(items).items():
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


def _buckets(items: list) -> dict[tuple, list]:
    buckets: dict[tuple, list] = {}
    for it in items:
        buckets.setdefault((it[2], it[3], it[4], it[0].dtype), []).append(it)
    return buckets


class _StepGraph:
    """:func:`_update` for one fixed set of parameters and moments, as a CUDA graph (``capture=False``: the same
    operations run at every call, for tests on any device). The rates are a device tensor per bucket
    (``[2, k]``: minus the step size, the root correction), written from pinned memory before each replay; the
    update divides by them as ``torch.optim.Adam``'s capturable path does."""

    def __init__(self, items: list, *, capture: bool):
        dev = items[0][0].device
        self.grads = [torch.empty_like(it[0]) for it in items]
        index = {id(it): k for k, it in enumerate(items)}
        self.buckets = []
        self.members = []  # per bucket, its items' positions in ``items`` (the order of its rates)
        for (b1, b2, eps, dtype), group in _buckets(items).items():
            rates = torch.ones(2, len(group), dtype=dtype, device=dev)
            self.members.append([index[id(it)] for it in group])
            self.buckets.append(([it[0] for it in group], [self.grads[k] for k in self.members[-1]],
                                 [it[1]["exp_avg"] for it in group], [it[1]["exp_avg_sq"] for it in group],
                                 b1, b2, eps, rates))
        self.params = [it[0] for it in items]
        self.pinned = dev.type == "cuda"
        self.graph = None
        self.checked = False  # whether a replay was compared with the eager update
        if not capture:
            return
        graph = torch.cuda.CUDAGraph()
        side = torch.cuda.Stream(dev)
        side.wait_stream(torch.cuda.current_stream(dev))
        with collector_off(), torch.cuda.device(dev), torch.cuda.stream(side):
            graph.capture_begin()
            try:
                self.flag = self._body()
            finally:
                graph.capture_end()
        torch.cuda.current_stream(dev).wait_stream(side)
        self.graph = graph

    def _body(self) -> torch.Tensor:
        finite = torch.isfinite(torch.stack(torch._foreach_norm(self.grads))).all()
        for g in self.grads:
            g.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
        for params, grads, m, v, b1, b2, eps, rates in self.buckets:
            steps, roots = list(rates[0].unbind()), list(rates[1].unbind())
            torch._foreach_lerp_(m, grads, 1 - b1)
            torch._foreach_mul_(v, b2)
            torch._foreach_addcmul_(v, grads, grads, value=1 - b2)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, roots)
            torch._foreach_add_(denom, eps)
            torch._foreach_div_(denom, steps)  # (sqrt(v) / root + eps) / (-step): one addcdiv adds the update
            torch._foreach_addcdiv_(params, m, denom)
        return torch.isfinite(torch.stack(torch._foreach_norm([p.detach() for p in self.params]))).all() & finite

    def __call__(self, items: list) -> torch.Tensor:
        torch._foreach_copy_(self.grads, [it[0].grad for it in items])
        for it, g in zip(items, self.grads):
            it[0].grad = g
        for bucket, members in zip(self.buckets, self.members):
            r = [[-items[k][5] for k in members], [items[k][6] for k in members]]  # -step size, root correction
            # pinned: the copy does not wait for the device, and torch's host allocator keeps the block until it ran
            bucket[-1].copy_(torch.tensor(r, dtype=bucket[-1].dtype, pin_memory=self.pinned), non_blocking=True)
        if self.graph is None:
            return self._body()
        self.graph.replay()
        return self.flag.clone()
