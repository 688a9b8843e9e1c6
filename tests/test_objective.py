# SPDX-License-Identifier: Apache-2.0
"""The objective's schedule of the co-evolution's mesh terms (the proxy every ``mesh_every``-th iteration)."""

import contextlib
from types import SimpleNamespace

import pytest
import torch

from wtopo.fitting.config import FitConfig
from wtopo.fitting.objective import Objective
from wtopo.fitting.stages import Stage

H = W = 12
WARMUP_END = 10


class _Proxy:
    """Stand-in proxy: counts builds; its depth is the surfels' plus a fixed offset pattern."""

    def __init__(self):
        self.builds = 0

    def build(self, surfels):
        self.builds += 1
        return "mesh"

    def render(self, pm, cam):
        g = torch.Generator().manual_seed(1)
        depth = 1.0 + 0.1 * torch.rand(H, W, generator=g)
        normal = torch.nn.functional.normalize(torch.rand(H, W, 3, generator=g), dim=-1)
        return SimpleNamespace(mask=torch.ones(H, W, dtype=torch.bool), depth=depth, normal=normal)


def _render(surfels, cam, defer_count=False):
    d = surfels.depth
    return SimpleNamespace(rgb=torch.full((H, W, 3), 0.5) + 0 * d[..., None], alpha=torch.ones(H, W) + 0 * d,
                           median_depth=d, normal=torch.tensor([0.0, 0.0, -1.0]).expand(H, W, 3) + 0 * d[..., None],
                           distortion=torch.zeros(H, W), overflow=None)


def _objective(mesh_every):
    cfg = FitConfig()
    cfg.losses.normal = cfg.losses.distortion = cfg.losses.scale = 0.0
    cfg.losses.multiview = 0.0
    cfg.coevolution.enabled = True
    train = SimpleNamespace(cameras=[None], images=torch.full((1, H, W, 3), 0.4), masks=None)
    return Objective(cfg, train, render=_render, mask_weight=0.0, warmup_end=WARMUP_END,
                     timers=lambda name: contextlib.nullcontext(), mesh_every=mesh_every)


@pytest.mark.parametrize("mesh_every", [1, 2, 3])
def test_mesh_terms_every_kth_coevolution_iteration_weighted_k(mesh_every):
    """The proxy is built on the co-evolution's iterations 0, k, 2k, ... only, and its terms weigh k times
    the every-iteration terms (the same mean gradient); the warm-up never builds it."""
    surfels = SimpleNamespace(depth=torch.full((H, W), 1.02), scales=torch.ones(4, 2))
    once = _objective(1)(Stage.COEVOLUTION, WARMUP_END, 0, surfels, _Proxy()).losses
    obj, proxy = _objective(mesh_every), _Proxy()
    built = []
    for it in range(WARMUP_END - 2, WARMUP_END + 7):
        stage = Stage.WARMUP if it < WARMUP_END else Stage.COEVOLUTION
        before = proxy.builds
        t = obj(stage, it, 0, surfels, proxy)
        if proxy.builds > before:
            built.append(it - WARMUP_END)
            for name in ("mesh_depth", "mesh_normal"):
                torch.testing.assert_close(t.losses[name], mesh_every * once[name])
        else:
            assert "mesh_depth" not in t.losses and not t.proxy_built
    assert built == list(range(0, 7, mesh_every))
    assert float(once["mesh_depth"]) > 0 and float(once["mesh_normal"]) > 0
