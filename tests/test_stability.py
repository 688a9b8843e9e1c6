# SPDX-License-Identifier: Apache-2.0
"""Fit- and chain-level stiff cases of ``design/stability.md``, each with its one expected outcome.

Every case in :data:`CASES` either completes with finite outputs (and its own measured check) or
raises one named exception whose message is matched; nothing else passes. The cases run on the
tiny embedded ``sphere`` scene with a fit of a few iterations. Kernel-level cases are in each op's
tests; camera validation (NaN pose, det -1, colinear cameras) is in ``tests/test_scene.py``.
``benchmarks/stability.py`` runs the same :data:`CASES` and writes their timings to
``benchmarks/stability.md``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
import torch

SCALE_TOL = 1e-4
"""Largest symmetric mean vertex-to-surface distance (internal units: the region of interest spans
0.8) between the internal-frame meshes of a scaled / offset copy of the sphere scene and of the
original. The float64 normalisation maps both to the same internal scene up to ~1e-9, below float32
rounding of the kernels' inputs: measured, the fitted surfels are bit-identical and the meshes differ
by 0 to ~1e-10 (the float64 round trip through the world frame). A fit that diverged would differ by
about a TSDF voxel (0.8 / 40 = 0.02); 1e-4 separates the two by orders of magnitude either way."""

FROZEN_RTOL = 1e-5
"""With colours that do not require grad, ``rasterize_surfels``'s first backward of a graph may round
differently from the later ones (measured 0 to 6e-6 relative; both agree with the float64 gradient
to the same float32 rounding): the tolerance is float32 rounding of the per-surfel sums."""


# -- scenes and configurations ----------------------------------------------------------------------
_CACHE: dict = {}


def sphere_scene():
    """The embedded tiny ``"sphere"`` scene (12 views of 40 px, masks, ground-truth mesh), cached."""
    if "sphere" not in _CACHE:
        from wtopo import scenes

        _CACHE["sphere"] = scenes.load("sphere")
    return _CACHE["sphere"]


def tiny_config(warmup: int = 12, coevolution: int = 6):
    """A fit of a few seconds on the sphere scene: every stage runs (warm-up with density control,
    TSDF re-initialisation, co-evolution with the proxy mesh and mesh guidance, final TSDF)."""
    from fit_configs import small_fit_config

    # a cadence in iterations: 3 density steps in the warm-up
    cfg = small_fit_config(warmup, coevolution, points=300, grids=(40, 40, 24), max_faces=800,
                           density_every=max(1, warmup // 3), eval_every=0)
    cfg.runtime.device = "cpu"
    return cfg


def _assert_finite(name: str, x) -> None:
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)
    assert np.all(np.isfinite(a)), f"{name} holds {int((~np.isfinite(a)).sum())} non-finite values"


_ROUTINE_EVENTS = {"densify", "densify_skipped", "tsdf_reinit", "mesh_guidance"}


def _check_fit(res) -> str:
    """Assert a FitResult is finite everywhere and has a mesh; return a one-line summary."""
    _assert_finite("mesh vertices", np.asarray(res.mesh.vertices))
    assert len(res.mesh.faces) > 0, "the fit returned an empty mesh"
    for k, p in res.surfels.params.items():
        _assert_finite(f"surfel {k}", p)
    for rec in res.history:
        _assert_finite("history losses", [float(v) for v in rec.get("losses", {}).values()])
        for m in ("chamfer", "f_score", "psnr"):
            if m in rec:
                _assert_finite(f"history {m}", [rec[m]])
    r = res.report
    parts = [f"{r['mesh']['faces']} faces", "watertight" if r["mesh"]["watertight"] else "not watertight",
             f"{r['surfels']} surfels", f"{r['non_finite_steps']} skipped steps"]
    if "chamfer" in r:
        parts.append(f"Chamfer {100 * r['chamfer']:.2f} %")
    notable = sorted({e["event"] for e in r.get("events", []) if e["event"] not in _ROUTINE_EVENTS})
    if notable:
        parts.append("events: " + " ".join(notable))
    return ", ".join(parts)


def _fit(scene, cfg):
    from wtopo.fitting import fit

    return fit(scene, cfg, progress=False)


def _base_fit():
    if "base" not in _CACHE:
        sc = sphere_scene()
        res = _fit(sc, tiny_config())
        _CACHE["base"] = (res, sc.normalization().to_internal(res.mesh))
    return _CACHE["base"]


def surface_distance(a, b) -> float:
    """Symmetric mean distance from each mesh's vertices to the other mesh's surface (no sampling noise)."""
    from wtopo.raycast import closest_faces

    def one_way(src, dst) -> float:
        v = torch.as_tensor(np.asarray(dst.vertices), dtype=torch.float64)
        f = torch.as_tensor(np.asarray(dst.faces), dtype=torch.int32)
        p = torch.as_tensor(np.asarray(src.vertices), dtype=torch.float64)
        return float(closest_faces(v, f, p)[1].mean())

    return 0.5 * (one_way(a, b) + one_way(b, a))


# -- fit-level cases (design/stability.md 1, 8, 9) ------------------------------------------------------
def _transformed_case(scale: float, offset: float) -> Callable[[], str]:
    def case() -> str:
        """A scaled or shifted copy of the sphere scene fits to the same internal-frame mesh."""
        from wtopo.scene import Similarity

        base, base_mesh = _base_fit()
        sc = sphere_scene().transformed(Similarity(scale, (offset, -offset, 0.5 * offset)))
        res = _fit(sc, tiny_config())
        detail = _check_fit(res)
        d = surface_distance(sc.normalization().to_internal(res.mesh), base_mesh)
        assert d <= SCALE_TOL, f"internal-frame distance to the unscaled fit {d:.2e} > {SCALE_TOL:.0e} ({detail})"
        assert len(res.surfels) == len(base.surfels), f"{len(res.surfels)} surfels, unscaled fit {len(base.surfels)}"
        dm = float((res.surfels.means - base.surfels.means).detach().abs().max())
        return (f"internal-frame distance to the unscaled fit {d:.1e} (tol {SCALE_TOL:.0e}), max abs difference of "
                f"the surfel means {dm:.1e}; {detail}")

    return case


def case_grazing_rig() -> str:
    """A thin slab tilted so an orbit rig sees its faces at 3 to 47 degrees fits with finite results."""
    import trimesh

    from wtopo import scenes

    slab = trimesh.creation.box((2.0, 2.0, 0.05))
    slab.apply_transform(trimesh.transformations.rotation_matrix(math.radians(22), (1, 0, 0)))
    sc = scenes.from_mesh(slab, n_views=10, resolution=32, rig="orbit", texture="coffee", name="grazing")
    return _check_fit(_fit(sc, tiny_config()))


def case_tiny_scales() -> str:
    """A fit from surfels whose scales are all 1e-8 (internal units) is finite."""
    from wtopo.fitting import loop

    orig = loop.scene_surfels

    def collapsed(*a, **kw):
        s = orig(*a, **kw)
        with torch.no_grad():
            s.params["log_scales"].fill_(math.log(1e-8))
        return s

    loop.scene_surfels = collapsed
    try:
        return _check_fit(_fit(sphere_scene(), tiny_config()))
    finally:
        loop.scene_surfels = orig


def case_huge_lr() -> str:
    """Every learning rate 1000x the default: the fit stays finite and either makes a mesh or aborts with the typed
    error that says nothing is left to mesh, its surfels finite when it gave up (the shared STABILITY.md: "restore
    last good state or abort; never write NaN"). Which of the two is
    chance: at these steps the surfels scatter, and over seeds 0-3 the fit kept enough of them for a mesh in 3 of 4
    runs before the photometric term's halo ring and in 1 of 4 after it (seed 0 had kept 60 surfels and 100 faces)."""
    cfg = tiny_config()
    from unittest import mock

    from wtopo.fitting import loop
    from wtopo.fitting.tsdf import TSDFEmptyError

    for f in ("means", "means_final", "quats", "scales", "opacities", "sh_dc"):
        setattr(cfg.optim, f, 1000.0 * getattr(cfg.optim, f))
    meshed = []  # the surfels the final mesh was made from
    final_mesh = loop.final_mesh

    def recording_final_mesh(surfels, *args, **kwargs):
        meshed.append(surfels)
        return final_mesh(surfels, *args, **kwargs)

    with mock.patch.object(loop, "_SH_REST_LR", 1000.0 * loop._SH_REST_LR), \
            mock.patch.object(loop, "final_mesh", recording_final_mesh):
        try:
            res = _fit(sphere_scene(), cfg)
        except TSDFEmptyError as e:
            assert "the TSDF fusion and the proxy mesh are both empty" in str(e), str(e)
            assert meshed, "the fit gave up before its final mesh"
            for k, p in meshed[-1].params.items():
                _assert_finite(f"surfel {k}", p)
            return f"{len(meshed[-1])} finite surfels, then the typed abort: {e}"
    return _check_fit(res)


def case_prune_everything() -> str:
    """Pruning thresholds every surfel falls under still leave surfels and a mesh."""
    from unittest import mock

    from wtopo.fitting import _strategy as strategy

    cfg = tiny_config()
    with mock.patch.multiple(strategy, PRUNE_OPACITY=1.0, _GEOMETRY_PRUNE_OPACITY=1.0, _GEOMETRY_PRUNE_DISTANCE=0.0):
        res = _fit(sphere_scene(), cfg)
    assert len(res.surfels) > 0, "every surfel was pruned"
    return _check_fit(res)


def case_tsdf_empty() -> str:
    """No pixel passes the TSDF opacity threshold: the fit keeps the warm-up surfels and returns the proxy
    mesh, and warns about both fallbacks."""
    from unittest import mock

    from wtopo.fitting import stages

    cfg = tiny_config()
    with warnings.catch_warnings(record=True) as caught, mock.patch.object(stages, "ALPHA_THRESHOLD", 1.5):
        warnings.simplefilter("always")
        detail = _check_fit(_fit(sphere_scene(), cfg))
    msgs = sorted({str(w.message).split(":")[0] for w in caught if issubclass(w.category, RuntimeWarning)})
    for want in ("TSDF re-initialisation skipped", "final TSDF empty"):
        assert any(m.startswith(want) for m in msgs), f"no warning {want!r}; warned: {msgs}"
    return f"{detail}; warned: {'; '.join(msgs)}"


def case_empty_masks() -> str:
    """Black images with empty masks (nothing to reconstruct) are refused before the fit starts."""
    sc = sphere_scene()
    empty = sc._replace(images=torch.zeros_like(sc.images), masks=torch.zeros_like(sc.masks), depths=None,
                        normals=None)
    return _check_fit(_fit(empty, tiny_config()))


def case_nan_pixels() -> str:
    """Images with a NaN pixel are refused by the scene, naming the index and the image."""
    from wtopo import Scene

    sc = sphere_scene()
    img = sc.images.clone()
    img[3, 5, 7, 1] = float("nan")
    Scene(sc.cameras, img, masks=sc.masks)
    return "accepted"


def case_nan_depths() -> str:
    """Depth maps with NaN / inf holes (sensor dropouts) are read as invalid (0) pixels."""
    from wtopo import Scene

    sc = sphere_scene()
    d = sc.depths.clone()
    d[:, ::3, ::3] = float("nan")
    d[:, 1::5, ::4] = float("inf")
    out = Scene(sc.cameras, sc.images, masks=sc.masks, depths=d, gt_mesh=sc.gt_mesh)
    _assert_finite("depths", out.depths)
    holes = int((out.depths == 0).sum() - (sc.depths == 0).sum())
    expected = int((~torch.isfinite(d) & (sc.depths > 0)).sum())
    assert holes == expected, f"{holes} new invalid pixels, expected {expected}"
    return f"{holes} NaN/inf depths read as invalid (0)"


# -- the differentiable chain (design/stability.md 9) --------------------------------------------------
def _chain_inputs(dtype=torch.float64, n: int = 24, seed: int = 0):
    """Surfels tangent to a sphere of radius 0.25 in the unit cube, normals outward."""
    from wtopo.fitting.surfels import normals_to_quats

    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    means = (0.5 + 0.25 * d).to(dtype)
    quats = normals_to_quats(d).to(dtype)
    scales = torch.full((n, 2), 0.12, dtype=dtype)
    opac = torch.full((n,), 0.9, dtype=dtype)
    return means, quats, scales, opac


def _chain(means, quats, scales, opac, *, resolution=16, camera=None):
    """Oriented points -> Poisson -> marching cubes (-> ray cast depth when a camera is given)."""
    from wtopo.ops import marching_cubes, oriented_points, poisson_indicator, raycast_mesh

    op = oriented_points(means, quats, scales, opac, samples=5)
    f = poisson_indicator(op.points, op.normals, op.weights, resolution, sigma=1.0, padding=0.1)
    verts, faces = marching_cubes(f.chi, lower=f.lower, upper=f.upper)
    assert faces.shape[0] > 0, "the chain produced no faces (nothing exercised)"
    out = (verts ** 2).sum() / verts.shape[0]
    hit = 0
    if camera is not None:
        r = raycast_mesh(verts, faces, camera)
        hit = int(r.mask.sum())
        out = out + r.depth.sum() / max(hit, 1)
    return out, int(faces.shape[0]), hit


def _chain_camera(size=24):
    from wtopo import Camera

    return Camera.look_at([0.5, 0.5, -1.5], [0.5, 0.5, 0.5], [0, -1, 0], fov_x=0.5, width=size, height=size)


def case_chain_gradcheck() -> str:
    """Oriented points -> Poisson -> MC passes a float64 gradcheck (reentrancy included, nondet_tol 0)."""
    means, quats, scales, opac = _chain_inputs(n=6)
    means.requires_grad_(True)
    faces = []

    def f(m):
        out, nf, _ = _chain(m, quats, scales, opac, resolution=12)
        faces.append(nf)
        return out

    torch.autograd.gradcheck(f, (means,), eps=1e-6, atol=1e-6, rtol=1e-4, nondet_tol=0.0, raise_exception=True)
    return f"gradcheck passed w.r.t. {means.numel()} mean coordinates, {max(faces)} faces"


def _repeated_backward(train_colors: bool) -> tuple[float, str]:
    """Backward twice (retain_graph) through rasterize + the proxy chain + ray cast.

    Returns the largest deviation of the accumulated gradient from twice the first, relative to
    the first gradient's largest entry, and a description of what was exercised.
    """
    from wtopo.ops import rasterize_surfels

    means, quats, scales, opac = _chain_inputs(torch.float32)
    params = [t.requires_grad_(True) for t in (means, quats, scales, opac)]
    colors = torch.rand(means.shape[0], 3, generator=torch.Generator().manual_seed(1)).requires_grad_(train_colors)
    cam = _chain_camera()
    img = rasterize_surfels(*params, colors, cam)
    pixels = int((img.alpha > 0.01).sum())
    loss, nf, hit = _chain(*params, camera=cam)
    loss = loss + img.rgb.sum() + img.depth.sum()
    loss.backward(retain_graph=True)
    g1 = [p.grad.clone() for p in params]
    loss.backward()
    worst = 0.0
    for name, p, g in zip(("means", "quats", "scales", "opacities"), params, g1):
        _assert_finite(f"{name} grad", p.grad)
        assert bool(g.abs().sum() > 0), f"{name} gradient is zero: nothing exercised"
        worst = max(worst, float((p.grad - 2 * g).abs().max() / g.abs().max()))
    return worst, f"{pixels} surfel pixels, {nf} faces, {hit} mesh pixels"


def case_chain_repeated_backward() -> str:
    """A second backward through rasterize (trainable colours, as in the fit) + chain + ray cast gives exactly 2x."""
    worst, what = _repeated_backward(True)
    assert worst == 0.0, f"second backward deviates from 2x the first by {worst:.1e} (relative); {what}"
    return f"exactly 2x on every parameter ({what})"


def case_repeated_backward_frozen_colors() -> str:
    """The same with colours that need no gradient stays within float32 rounding of 2x."""
    worst, what = _repeated_backward(False)
    assert worst <= FROZEN_RTOL, f"second backward deviates from 2x by {worst:.1e} > {FROZEN_RTOL:.0e}; {what}"
    return f"2x within {worst:.1e} relative ({what})"


def case_chain_determinism() -> str:
    """Two CPU forward + backward passes of rasterize + proxy chain + ray cast are bit-identical."""
    from wtopo.ops import rasterize_surfels

    runs = []
    cam = _chain_camera()
    for _ in range(2):
        means, quats, scales, opac = _chain_inputs(torch.float32)
        params = [t.requires_grad_(True) for t in (means, quats, scales, opac)]
        colors = torch.rand(means.shape[0], 3, generator=torch.Generator().manual_seed(1))
        img = rasterize_surfels(*params, colors, cam)
        loss, nf, hit = _chain(*params, camera=cam)
        (loss + img.rgb.sum() + img.depth.sum()).backward()
        runs.append([img.rgb.detach(), loss.detach()] + [p.grad for p in params])
    diff = [i for i, (a, b) in enumerate(zip(*runs)) if not torch.equal(a, b)]
    assert not diff, f"outputs {diff} differ between two identical runs"
    return f"bit-identical image, chain output and 4 gradients ({nf} faces, {hit} mesh pixels)"


def case_fit_determinism() -> str:
    """Two tiny CPU fits with the same seed in one process give bit-identical surfels (a process's first
    launches must not round differently from later ones)."""
    a = _base_fit()[0]
    b = _fit(sphere_scene(), tiny_config())
    assert len(a.surfels) == len(b.surfels), f"surfel counts differ ({len(a.surfels)} vs {len(b.surfels)})"
    for k in a.surfels.params:
        assert torch.equal(a.surfels.params[k], b.surfels.params[k]), f"surfel {k} differs between two identical fits"
    return f"bit-identical surfels ({len(b.surfels)}) in two fits of one process"


# -- the table -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    """One stiff case and its one expected outcome.

    Attributes:
        run: builds and runs the case; returns what it measured, raises ``AssertionError`` when a
            check fails.
        raises: the exception the case must raise (``None``: it must complete, every output finite).
        match: regular expression the exception's message must match.
        slow: the case runs whole fits (5 to 25 s each on a shared 2-core CPU; marked ``slow``).
    """

    run: Callable[[], str]
    raises: type[Exception] | None = None
    match: str | None = None
    slow: bool = False

    def check(self) -> str:
        """Run the case and assert its expected outcome; return the detail."""
        if self.raises is None:
            return self.run()
        with pytest.raises(self.raises, match=self.match) as info:
            self.run()
        return f"{info.type.__name__}: {info.value}"


CASES: dict[str, Case] = {
    "scale_1e-3": Case(_transformed_case(1e-3, 0.0), slow=True),
    "scale_1e3": Case(_transformed_case(1e3, 0.0), slow=True),
    "offset_1e4": Case(_transformed_case(1.0, 1e4), slow=True),
    "offset_1e6": Case(_transformed_case(1.0, 1e6), slow=True),
    "grazing_rig": Case(case_grazing_rig, slow=True),
    "scales_1e-8": Case(case_tiny_scales, slow=True),
    # finite, and a mesh or the typed abort (which one is chance at these steps: the case's docstring)
    "lr_x1000": Case(case_huge_lr, slow=True),
    "prune_everything": Case(case_prune_everything, slow=True),
    "tsdf_empty": Case(case_tsdf_empty, slow=True),
    "empty_masks": Case(case_empty_masks, ValueError, r"masks\[0\] is empty"),
    "nan_pixels": Case(
        case_nan_pixels, ValueError, r"images must be finite, got nan at index \[3, 5, 7, 1\] \(image 3\)"),
    "nan_depths": Case(case_nan_depths),
    "chain_gradcheck_fp64": Case(case_chain_gradcheck),
    "chain_repeated_backward": Case(case_chain_repeated_backward),
    "repeated_backward_frozen_colors": Case(case_repeated_backward_frozen_colors),
    "chain_determinism": Case(case_chain_determinism),
    "fit_determinism": Case(case_fit_determinism, slow=True),
}
"""Case name -> :class:`Case`; ``benchmarks/stability.py`` times the same table."""


@pytest.mark.parametrize("name", [pytest.param(k, marks=pytest.mark.slow) if c.slow else k for k, c in CASES.items()])
def test_stiff_case_has_its_expected_outcome(name):
    """Run one stiff case and get exactly its expected outcome (finite and checked, or the named error)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the fallbacks warn by design; tsdf_empty checks them
        CASES[name].check()
