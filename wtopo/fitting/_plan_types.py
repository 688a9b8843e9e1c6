# SPDX-License-Identifier: Apache-2.0
"""The stage plan's type: :class:`Plan` (frozen, typed, printable) and the builder :func:`~.plan.make_plan`
fills while it decides (:class:`_Decisions`)."""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from types import MappingProxyType

from .config import InitSource, Preset
from .scene_kind import SceneKind, SceneLayout

__all__ = ["Plan"]


@dataclass(frozen=True)
class Plan:
    """The stage plan of one fit: every decision that the scene, the device and the configuration settle,
    typed, each with its reason (:attr:`reasons`).

    A decision whose configuration field was set is that value (:attr:`overrides` names it); one left to the
    plan (``None``) is the plan's. :func:`resolve_config` copies every decision that has a configuration field
    into the resolved configuration, which the fit then reads; the fit reads from the plan only what has no
    field: :attr:`device`, :attr:`layout` (region of interest), :attr:`background_rule`, :attr:`eval_views`,
    :attr:`gt_metrics`. ``str(plan)`` says which stages run and why; :meth:`to_dict` is ``plan.json``.
    Lengths are in the internal frame (the scene normalised into the unit cube).
    """

    device: str
    """The device the fit runs on (``"cpu"``, ``"cuda:0"``)."""
    scene_kind: SceneKind
    """Object (closed mesh) or scene (background kept, open mesh); ``FitConfig.kind``."""
    region_of_interest: tuple[tuple[float, float, float], tuple[float, float, float]]
    """``(lower, upper)`` corners of the region of interest (internal frame, rounded to 1e-4)."""
    mesh_policy: str
    """``"watertight"`` (objects) or ``"open_roi"`` (scenes): what the final mesh keeps."""
    init_source: InitSource
    """Where the initial surfels come from; ``init.source``."""
    mask_loss: float
    """Alpha-vs-mask weight; ``losses.mask``."""
    background_rule: bool
    """Scenes: steps outside the region of interest are contracted, surfels on a lens pruned, background surfels
    spared by the geometry-aware prune, and a TSDF re-initialisation (when one runs) keeps those far from its mesh."""
    background_points: int
    """Background surfels on shells beyond the cameras; ``init.background_points``."""
    background: tuple[float, float, float]
    """RGB background colour in [0, 1]; ``FitConfig.background``."""
    sh_degree: int
    """SH degree of the colours; ``FitConfig.sh_degree``."""
    multiview: float
    """Multi-view NCC weight; ``losses.multiview``."""
    densify: bool
    """Screen-space clone/split in the warm-up; ``densify.enabled``."""
    preset: Preset
    """The preset whose budgets the plan started from (:mod:`wtopo.fitting.presets`); ``FitConfig.preset``."""
    image_scale: float
    """Factor the training images are resized by; ``runtime.image_scale``."""
    warmup_iterations: int
    """Warm-up iterations; ``warmup.iterations``."""
    coevolution_iterations: int
    """Co-evolution iterations; ``coevolution.iterations``."""
    densify_interval: int
    """Iterations between density-control steps; ``densify.interval``."""
    means_decay_iterations: int | None
    """Iterations of the means' decay (``None``: the whole fit); ``optim.means_decay_iterations``."""
    means_restart: float
    """The co-evolution's means restart, fraction of ``optim.means``; ``optim.means_restart``."""
    max_surfels: int
    """Surfel cap; ``runtime.max_surfels``."""
    filter_sigma: float
    """The renderer's screen-space low-pass [pixels]; ``FitConfig.filter_sigma``."""
    reinit_faces: int
    """Faces (one surfel each) of the TSDF re-initialisation mesh; ``tsdf.max_faces``."""
    reinit_resolution: int
    """TSDF voxels along the re-initialisation's fusion box; ``tsdf.resolution``."""
    proxy_resolution: int
    """Poisson nodes per side of the proxy mesh; ``mesh.resolution``."""
    final_resolution: int
    """TSDF voxels along the final fusion box; ``final.resolution``."""
    eval_views: int
    """Views held out for PSNR (the scene's test split, else ``runtime.eval_views`` with 12 views or more)."""
    tsdf_reinit: bool
    """The TSDF re-initialisation runs (not on a scene whose proxy-mesh loop is off); ``tsdf.enabled``."""
    mesh_loop: bool
    """The proxy-mesh loop runs in the co-evolution; ``coevolution.enabled``."""
    polish_iterations: int
    """Photometric iterations before the final mesh, after the co-evolution; ``polish.iterations``."""
    proxy_level_sigma: float
    """The proxy's zero level (0: global; > 0: local, in Poisson cells); ``mesh.level_sigma``."""
    proxy_clip: bool
    """The proxy is clipped to the region of interest; ``mesh.clip_to_region``."""
    expected_seconds: int
    """About how long the fit takes on this device [s] (:func:`~wtopo.fitting.presets.expected_seconds`)."""
    gt_metrics: bool
    """Chamfer / F-score at evaluations (a ground-truth mesh is given and ``runtime.eval_metrics``)."""
    reasons: Mapping[str, str] = field(default_factory=dict, repr=False)
    """Why, per decision name (the field names above)."""
    overrides: frozenset[str] = frozenset()
    """The decisions the configuration set instead of the plan."""
    layout: SceneLayout | None = field(default=None, repr=False, compare=False)
    """The :class:`~wtopo.fitting.scene_kind.SceneLayout` behind the scene-kind decisions."""

    def revised(self, name: str, value, reason: str) -> Plan:
        """This plan with decision ``name`` changed to ``value`` for ``reason``: what the fit found once it ran (the
        background shells, which the initial stereo decides)."""
        return replace(self, **{name: value}, reasons=MappingProxyType({**self.reasons, name: reason}))

    @classmethod
    def decision_names(cls) -> tuple[str, ...]:
        """The decisions in plan order (the keys of :meth:`to_dict`)."""
        return tuple(f.name for f in fields(cls) if f.name not in _NOT_DECISIONS)

    def to_dict(self) -> dict:
        """JSON-ready ``{name: {"value", "reason", "overridden"}}`` in decision order (``plan.json``)."""
        return {k: {"value": _json_value(getattr(self, k)), "reason": self.reasons.get(k, ""),
                    "overridden": k in self.overrides} for k in self.decision_names()}

    def __str__(self) -> str:
        names = self.decision_names()
        width = max(len(k) for k in names)
        kind = SceneKind(self.scene_kind).value
        loop = "with the proxy-mesh loop" if self.mesh_loop else "photometric only (no proxy-mesh loop)"
        co = (f"{self.coevolution_iterations} iterations, {loop}: {self.reasons.get('mesh_loop', '')}"
              if self.coevolution_iterations else "skipped: no co-evolution iterations")
        stages = [
            ("initial surfels", f"{InitSource(self.init_source).value}: {self.reasons.get('init_source', '')}"),
            ("warm-up", f"{self.warmup_iterations} iterations ({self.reasons.get('warmup_iterations', '')}); "
                        f"clone/split {'on' if self.densify else 'off'}"),
            ("TSDF re-init", (f"runs at {self.reinit_resolution} voxels: " if self.tsdf_reinit else "skipped: ")
                             + self.reasons.get("tsdf_reinit", "")),
            ("co-evolution", co),
            ("final mesh", f"TSDF fusion at {self.final_resolution} voxels, {self.mesh_policy}"),
            ("polish", f"{self.polish_iterations} iterations on the photographs alone: "
                       f"{self.reasons.get('polish_iterations', '')}" if self.polish_iterations else
                       f"skipped: {self.reasons.get('polish_iterations', '')}"),
        ]
        lines = [f"wtopo fit plan ({kind} on {self.device}): preset {Preset(self.preset).value}, about "
                 f"{_duration(self.expected_seconds)}", "  stages:"]
        lines += [f"    {i}. {name:<15} {what}" for i, (name, what) in enumerate(stages, 1)]
        lines.append("  decisions:")
        for k in names:
            mark = " (set)" if k in self.overrides else ""
            lines.append(f"    {k:<{width}}  {_json_value(getattr(self, k))!r:<14} {self.reasons.get(k, '')}{mark}")
        return "\n".join(lines)


_NOT_DECISIONS = ("reasons", "overrides", "layout")


def _duration(seconds: float) -> str:
    """``"45 s"``, ``"3 min"``, ``"1 h 20 min"``."""
    s = max(0, int(round(seconds)))
    if s < 90:
        return f"{s} s"
    m = int(round(s / 60))
    return f"{m} min" if m < 90 else f"{m // 60} h {m % 60} min"


def _json_value(v):
    """A decision's value as JSON holds it: enums as their values, tuples as lists."""
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, tuple):
        return [_json_value(x) for x in v]
    return v


class _Decisions:
    """The plan while :func:`make_plan` decides it: values and reasons by name, in decision order."""

    def __init__(self):
        self.values: dict[str, object] = {}
        self.reasons: dict[str, str] = {}
        self.overrides: set[str] = set()
        self.layout = None

    def __getitem__(self, name: str):
        return self.values[name]

    def set(self, name: str, value, reason: str, override=None) -> None:
        """Record a decision; a non-``None`` ``override`` (the configuration's value) replaces ``value``."""
        if override is not None:
            self.values[name] = override
            self.reasons[name] = f"set in the configuration (plan: {_json_value(value)!r}, {reason})"
            self.overrides.add(name)
        else:
            self.values[name] = value
            self.reasons[name] = reason

    def build(self) -> Plan:
        v = self.values
        typed = dict(v, scene_kind=SceneKind(v["scene_kind"]), init_source=InitSource(v["init_source"]),
                     preset=Preset(v["preset"]), background=tuple(float(c) for c in v["background"]),
                     region_of_interest=tuple(tuple(float(x) for x in c) for c in v["region_of_interest"]))
        return Plan(**typed, reasons=MappingProxyType(dict(self.reasons)), overrides=frozenset(self.overrides),
                    layout=self.layout)
