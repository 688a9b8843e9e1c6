# SPDX-License-Identifier: Apache-2.0
"""The surfel parameter container: parameters, Adam groups and consistent prune / clone / split.

Surfels live in the internal frame (the scene normalised into the unit cube). Each surfel has a
centre, a rotation whose local +z axis is its normal, two tangent scales, an opacity and SH colour.
Per-surfel buffers that are not optimised (densification accumulators, normal signs, accumulated
view directions) are sliced together with the parameters and with Adam's moment estimates, so a
prune or a split never misaligns optimiser state.
"""

from __future__ import annotations

import math

import torch

from ..io._common import rgb_to_sh_dc, sh_dc_to_rgb
from .adam import Adam

__all__ = ["Surfels", "quat_to_matrix", "normals_to_quats"]

_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
_BUFFERS = {  # name -> (trailing shape, fill value)
    "grad_accum": ((), 0.0),
    "grad_count": ((), 0.0),
    "view_dirs": ((3,), 0.0),
    "normal_sign": ((), 1.0),
    # 1 where ``normal_sign`` came from a mesh triangle when the surfel was made (the TSDF scaffold, the
    # proxy face it was spawned on): a sign refresh keeps it; 0: a near proxy face or the cameras decide
    # (densify.align_normal_signs)
    "mesh_sign": ((), 0.0),
}
_EPS_SCALE = 1e-7  # log-scale floor: 1e-7 of the unit cube is far below any pixel footprint


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of quaternions ``q`` [N, 4] (w, x, y, z; any non-zero norm)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*q.shape[:-1], 3, 3)


def _matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    # Shepperd's method, branch on the largest diagonal combination for stability.
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cand = torch.stack([tr, m00, m11, m22], -1)
    k = cand.argmax(-1)
    q = torch.empty(m.shape[:-2] + (4,), dtype=m.dtype, device=m.device)
    s0 = torch.sqrt((1 + tr).clamp_min(1e-12)) * 2
    s1 = torch.sqrt((1 + m00 - m11 - m22).clamp_min(1e-12)) * 2
    s2 = torch.sqrt((1 + m11 - m00 - m22).clamp_min(1e-12)) * 2
    s3 = torch.sqrt((1 + m22 - m00 - m11).clamp_min(1e-12)) * 2
    opts = [
        torch.stack([s0 / 4, (m[..., 2, 1] - m[..., 1, 2]) / s0, (m[..., 0, 2] - m[..., 2, 0]) / s0,
                     (m[..., 1, 0] - m[..., 0, 1]) / s0], -1),
        torch.stack([(m[..., 2, 1] - m[..., 1, 2]) / s1, s1 / 4, (m[..., 0, 1] + m[..., 1, 0]) / s1,
                     (m[..., 0, 2] + m[..., 2, 0]) / s1], -1),
        torch.stack([(m[..., 0, 2] - m[..., 2, 0]) / s2, (m[..., 0, 1] + m[..., 1, 0]) / s2, s2 / 4,
                     (m[..., 1, 2] + m[..., 2, 1]) / s2], -1),
        torch.stack([(m[..., 1, 0] - m[..., 0, 1]) / s3, (m[..., 0, 2] + m[..., 2, 0]) / s3,
                     (m[..., 1, 2] + m[..., 2, 1]) / s3, s3 / 4], -1),
    ]
    for i in range(4):
        q = torch.where((k == i)[..., None], opts[i], q)
    return q


def normals_to_quats(normals: torch.Tensor, tangents: torch.Tensor | None = None) -> torch.Tensor:
    """Quaternions [N, 4] whose local +z axis is ``normals`` [N, 3] and +x axis ``tangents`` (projected).

    Without tangents an arbitrary perpendicular is chosen. Zero normals give +z.
    """
    n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    zero = normals.norm(dim=-1) < 1e-12
    n = torch.where(zero[:, None], torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype, device=n.device), n)
    if tangents is None:
        ref = torch.where((n[:, 0].abs() < 0.9)[:, None],
                          torch.tensor([1.0, 0, 0], dtype=n.dtype, device=n.device),
                          torch.tensor([0, 1.0, 0], dtype=n.dtype, device=n.device))
    else:
        ref = tangents
    t = ref - (ref * n).sum(-1, keepdim=True) * n
    bad = t.norm(dim=-1) < 1e-9
    alt = torch.cross(n, torch.tensor([0, 1.0, 0], dtype=n.dtype, device=n.device).expand_as(n), dim=-1)
    alt = torch.where((alt.norm(dim=-1) < 1e-6)[:, None],
                      torch.cross(n, torch.tensor([1.0, 0, 0], dtype=n.dtype, device=n.device).expand_as(n), dim=-1),
                      alt)
    t = torch.where(bad[:, None], alt, t)
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = torch.cross(n, t, dim=-1)
    return _matrix_to_quat(torch.stack([t, b, n], dim=-1))


class Surfels:
    """Gaussian surfels as torch leaf tensors plus per-surfel buffers.

    Args:
        means: centres [N, 3], internal frame.
        quats: rotations [N, 4] (w, x, y, z), local +z = normal.
        log_scales: log of the two tangent standard deviations [N, 2].
        opacity_logits: logit of the opacity [N].
        sh_dc: degree-0 SH [N, 1, 3].
        sh_rest: higher SH bands [N, (d+1)^2 - 1, 3] (may have 0 bands).

    All parameters are float32 leaves with ``requires_grad``; :meth:`optimizer` builds Adam with
    one named group per parameter; :meth:`prune`, :meth:`append`, :meth:`clone` and :meth:`split`
    keep that optimiser's moments aligned with the surfels.
    """

    def __init__(self, *, means, quats, log_scales, opacity_logits, sh_dc, sh_rest, buffers=None):
        self.params: dict[str, torch.Tensor] = {}
        for name, value in zip(_PARAMS, (means, quats, log_scales, opacity_logits, sh_dc, sh_rest)):
            self.params[name] = value.detach().clone().float().requires_grad_(True)
        n = self.params["means"].shape[0]
        dev = self.params["means"].device
        self.buffers: dict[str, torch.Tensor] = {}
        for name, (shape, fill) in _BUFFERS.items():
            given = None if buffers is None else buffers.get(name)
            self.buffers[name] = (given.detach().clone().float() if given is not None
                                  else torch.full((n, *shape), fill, device=dev))
        self._optimizer: Adam | None = None

    # -- construction -------------------------------------------------------------------------
    @staticmethod
    def from_points(points: torch.Tensor, colors: torch.Tensor, *, scales: torch.Tensor,
                    normals: torch.Tensor | None = None, tangents: torch.Tensor | None = None,
                    opacity: float = 0.1, sh_degree: int = 0, generator: torch.Generator | None = None) -> Surfels:
        """Surfels at ``points`` [N, 3] with colours [N, 3] in [0, 1] and scales [N] or [N, 2].

        Without ``normals``, rotations are uniformly random (seeded by ``generator``).
        """
        n = points.shape[0]
        dev = points.device
        if normals is None:
            q = torch.randn(n, 4, generator=generator, device="cpu").to(dev)
        else:
            q = normals_to_quats(normals.float(), None if tangents is None else tangents.float())
        s = scales.float()
        if s.ndim == 1:
            s = s[:, None].expand(n, 2)
        k = (sh_degree + 1) ** 2 - 1
        logit = math.log(opacity / (1 - opacity))
        return Surfels(means=points.float(), quats=q, log_scales=torch.log(s.clamp_min(_EPS_SCALE)),
                       opacity_logits=torch.full((n,), logit, device=dev),
                       sh_dc=rgb_to_sh_dc(colors.float().clamp(0, 1))[:, None, :],
                       sh_rest=torch.zeros(n, k, 3, device=dev))

    # -- views ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        """Centres [N, 3], internal units (the parameter itself, differentiable)."""
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        """Rotations [N, 4] (w, x, y, z; any norm; the parameter itself, differentiable)."""
        return self.params["quats"]

    @property
    def scales(self) -> torch.Tensor:
        """Linear tangent scales [N, 2]."""
        return torch.exp(self.params["log_scales"])

    @property
    def opacities(self) -> torch.Tensor:
        """Opacities [N] in (0, 1)."""
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def sh(self) -> torch.Tensor:
        """All SH coefficients [N, (d+1)^2, 3]."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    @property
    def sh_degree(self) -> int:
        """SH degree ``d`` of the colours."""
        return int(round(math.sqrt(self.params["sh_rest"].shape[1] + 1))) - 1

    @property
    def device(self) -> torch.device:
        """Device of the parameters."""
        return self.params["means"].device

    def normals(self) -> torch.Tensor:
        """Unit normals [N, 3] (local +z), detached."""
        return quat_to_matrix(self.params["quats"].detach())[:, :, 2]

    def rotations(self) -> torch.Tensor:
        """Rotation matrices [N, 3, 3] (columns: tangent u, tangent v, normal), detached."""
        return quat_to_matrix(self.params["quats"].detach())

    def colors(self) -> torch.Tensor:
        """View-independent colours [N, 3] in [0, 1] (degree-0 SH), detached."""
        return sh_dc_to_rgb(self.params["sh_dc"].detach()[:, 0])

    # -- optimiser ------------------------------------------------------------------------
    def optimizer(self, lrs: dict[str, float]) -> Adam:
        """Adam (:class:`~wtopo.fitting.adam.Adam`) with one group per parameter (``lrs`` maps parameter name ->
        learning rate)."""
        groups = [{"params": [self.params[k]], "lr": float(lrs[k]), "name": k} for k in _PARAMS]
        self._optimizer = Adam(groups, eps=1e-15)
        return self._optimizer

    def _replace(self, fn_param, fn_state) -> None:
        """Rebuild every parameter with ``fn_param(old)`` and Adam moments with ``fn_state(old, name)``."""
        opt = self._optimizer
        for name in _PARAMS:
            old = self.params[name]
            new = fn_param(old.detach(), name).contiguous().requires_grad_(True)
            if opt is not None:
                group = next(g for g in opt.param_groups if g["name"] == name)
                state = opt.state.pop(old, None)
                group["params"][0] = new
                if state:
                    for key in ("exp_avg", "exp_avg_sq"):
                        state[key] = fn_state(state[key], name).contiguous()
                    opt.state[new] = state
            self.params[name] = new

    def prune(self, keep: torch.Tensor) -> None:
        """Keep the surfels where ``keep`` [N] bool is True (parameters, moments, buffers)."""
        if keep.dtype != torch.bool or keep.shape != (len(self),):
            raise TypeError(f"keep must be a bool tensor [{len(self)}], got {keep.dtype} {list(keep.shape)}")
        # one host synchronisation (the count) for every tensor: a boolean index syncs once per tensor (about 25)
        idx = torch.nonzero(keep.to(self.device)).flatten()
        self._replace(lambda p, _: p.index_select(0, idx), lambda s, _: s.index_select(0, idx))
        for k in self.buffers:
            self.buffers[k] = self.buffers[k].index_select(0, idx)

    def append(self, new: dict[str, torch.Tensor], buffers: dict[str, torch.Tensor] | None = None) -> None:
        """Append surfels given as parameter tensors (same names as :attr:`params`); moments start at 0."""
        m = new["means"].shape[0]
        if m == 0:
            return
        self._replace(lambda p, name: torch.cat([p, new[name].to(p)], 0),
                      lambda s, name: torch.cat([s, torch.zeros((m, *s.shape[1:]), dtype=s.dtype, device=s.device)], 0))
        for k, (shape, fill) in _BUFFERS.items():
            extra = None if buffers is None else buffers.get(k)
            if extra is None:
                extra = torch.full((m, *shape), fill, device=self.device)
            self.buffers[k] = torch.cat([self.buffers[k], extra.to(self.buffers[k])], 0)

    def take(self, index: torch.Tensor) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Detached copies of the parameters and buffers of the surfels at ``index``."""
        return ({k: v.detach()[index].clone() for k, v in self.params.items()},
                {k: v[index].clone() for k, v in self.buffers.items()})

    def clone(self, mask: torch.Tensor) -> int:
        """Duplicate the surfels in ``mask`` (3DGS clone). Returns how many were added."""
        idx = torch.nonzero(mask.to(self.device)).flatten()
        p, b = self.take(idx)
        self.append(p, b)
        return int(idx.numel())

    def split(self, mask: torch.Tensor, *, copies: int = 2, shrink: float = 1.6,
              generator: torch.Generator | None = None) -> int:
        """Replace each surfel in ``mask`` by ``copies`` smaller ones sampled from its Gaussian (3DGS split)."""
        idx = torch.nonzero(mask.to(self.device)).flatten()
        if idx.numel() == 0:
            return 0
        p, b = self.take(idx)
        rot = quat_to_matrix(p["quats"])
        sc = torch.exp(p["log_scales"])
        parts = {k: [] for k in p}
        bparts = {k: [] for k in b}
        for _ in range(copies):
            z = torch.randn(idx.numel(), 2, generator=generator, device="cpu").to(self.device) * sc
            offs = rot[:, :, 0] * z[:, :1] + rot[:, :, 1] * z[:, 1:]
            for k in p:
                v = p[k]
                if k == "means":
                    v = v + offs
                elif k == "log_scales":
                    v = v - math.log(shrink)
                parts[k].append(v)
            for k in b:
                bparts[k].append(b[k])
        keep = torch.ones(len(self), dtype=torch.bool, device=self.device)
        keep[idx] = False
        self.append({k: torch.cat(v, 0) for k, v in parts.items()}, {k: torch.cat(v, 0) for k, v in bparts.items()})
        keep = torch.cat([keep, torch.ones(idx.numel() * copies, dtype=torch.bool, device=self.device)])
        self.prune(keep)
        return int(idx.numel()) * (copies - 1)

    def set_param(self, name: str, value: torch.Tensor, *, reset_state: bool = True) -> None:
        """Overwrite one parameter's values in place (e.g. an opacity reset); zero its moments."""
        with torch.no_grad():
            self.params[name].copy_(value)
        opt = self._optimizer
        if opt is not None and reset_state:
            st = opt.state.get(self.params[name])
            if st:
                st["exp_avg"].zero_()
                st["exp_avg_sq"].zero_()

    # -- (de)serialisation ---------------------------------------------------------------------
    def state_dict(self, device: torch.device | str = "cpu") -> dict:
        """Detached copies of the parameters and buffers on ``device`` (the fit's own device keeps its
        in-memory snapshots there: no host transfer, no synchronisation)."""
        return {"params": {k: v.detach().to(device, copy=True) for k, v in self.params.items()},
                "buffers": {k: v.to(device, copy=True) for k, v in self.buffers.items()}}

    @staticmethod
    def from_state_dict(state: dict, device: torch.device | str = "cpu") -> Surfels:
        """Inverse of :meth:`state_dict` (no optimiser attached)."""
        p = {k: v.to(device) for k, v in state["params"].items()}
        return Surfels(**p, buffers={k: v.to(device) for k, v in state["buffers"].items()})
