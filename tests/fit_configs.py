# SPDX-License-Identifier: Apache-2.0
"""Small fit configurations for tests: every stage runs, in seconds, on scenes of 24-48 px."""

from __future__ import annotations

from wtopo.fitting import FitConfig


def small_fit_config(warmup: int, coevolution: int, *, points: int, grids: tuple[int, int, int],
                     max_faces: int, density_every: int, eval_every: int, checkpoint_every: int = 0,
                     polish: int = 0) -> FitConfig:
    """A short CPU-sized fit: no opacity reset, no USD timeline, no progress bars.

    Args:
        warmup: warm-up iterations (milestones are fractions of it).
        coevolution: co-evolution iterations.
        points: initial surfels drawn in the cameras' common volume.
        grids: ``(tsdf.resolution, final.resolution, mesh.resolution)``.
        max_faces: faces of the TSDF re-initialisation mesh (one surfel each).
        density_every: ``densify.interval``, a cadence in iterations (3DGS's 100 is too slow here).
        eval_every: iterations between history records (0: only at stage ends).
        checkpoint_every: iterations between checkpoints (0: none on a cadence).
        polish: iterations after the co-evolution, before the final mesh (0: none; tests/test_polish.py tests
            the stage).
    """
    cfg = FitConfig()
    cfg.warmup.iterations, cfg.coevolution.iterations = warmup, coevolution
    cfg.init.num_points = points
    cfg.densify.interval = density_every
    cfg.densify.opacity_reset_fraction = 0.0
    cfg.tsdf.resolution, cfg.final.resolution, cfg.mesh.resolution = grids
    cfg.tsdf.max_faces = max_faces
    # the mesh terms always run here: a 30-iteration warm-up leaves a rough, double-walled proxy (the tiny
    # sphere reads a thin share of 0.58) that the thin-part rule would turn them off for; test_thin_parts.py
    # tests the rule itself
    cfg.losses.mesh_thin_limit = 1.0
    cfg.polish.iterations = polish
    cfg.runtime.eval_every = eval_every
    cfg.runtime.usd_every = 0
    cfg.runtime.checkpoint_every = checkpoint_every
    cfg.runtime.progress = False
    return cfg


def fit_with_loss_term(term: str, **losses):
    """Fit a small textured sphere (8 views of 32 px, 30 warm-up iterations) with ``losses`` set on
    ``FitConfig.losses`` and return ``(the values history recorded for loss ``term``, the result)``."""
    import trimesh

    import wtopo
    from wtopo import scenes

    sc = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=3), n_views=8, resolution=32, texture="coffee",
                          seed=0)
    cfg = small_fit_config(30, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=10)
    for k, v in losses.items():
        setattr(cfg.losses, k, v)
    res = wtopo.fit(sc, cfg, progress=False)
    return [h["losses"][term] for h in res.history if term in h.get("losses", {})], res
