# SPDX-License-Identifier: Apache-2.0
"""Run ``pgsr_dpsr``'s ``train.py`` with its DPSR frequency grid and spectral filter kept on the GPU.

python _dpsr_cache.py train.py ARGS...   (in the checkout, under ``_peak.py``: ``run_pgsr.py --cache-dpsr-grids``)

The authors' ``DPSR.forward`` (``nvdiffrast_utils/dpsr.py``, from Shape-as-Points) builds the frequency grid
[R, R, R/2+1, 3] (float32) again on the CPU with ``fftfreqs`` in every call, then copies it and the Gaussian
filter [R, R, R/2+1, 1, 1] to the GPU: at the mesh stage's R = 512, 771 MiB and 257 MiB of host work and copies an
iteration. Here the grid is built once per (resolution, dtype, device) and each call gets its own copy on the
device (the forward scales it in place), and the filter moves to the device once. The values are the same
tensors; only where they are made changes. The GPU holds the cached grid and the filter between calls (about
1 GiB at R = 512). ``DPSR.__init__`` keeps its own CPU grid, as before.
"""

from __future__ import annotations

import runpy
import sys

import torch


def install(dpsr) -> None:
    """Patch the module ``dpsr`` (the authors' ``nvdiffrast_utils.dpsr``) in place: ``DPSR.forward`` reads its
    frequency grid from a cache and moves its filter ``G`` to the points' device once."""
    make, forward = dpsr.fftfreqs, dpsr.DPSR.forward
    if getattr(forward, "_grids_cached", False):
        return
    cache: dict = {}

    def cached_forward(self, V, N):
        if self.G.device != V.device:
            self.G = self.G.to(V.device)

        def fftfreqs(res, dtype=torch.float32, exact=True):
            key = (tuple(res), dtype, exact, V.device)
            if key not in cache:
                cache[key] = make(res, dtype=dtype, exact=exact).to(V.device)
            return cache[key].clone()

        dpsr.fftfreqs = fftfreqs  # the forward looks the name up in its module
        try:
            return forward(self, V, N)
        finally:
            dpsr.fftfreqs = make

    cached_forward._grids_cached = True
    dpsr.DPSR.forward = cached_forward


if __name__ == "__main__":
    sys.argv = sys.argv[1:]
    from nvdiffrast_utils import dpsr as _dpsr  # the checkout, first on the path (``_peak.py``)

    install(_dpsr)
    runpy.run_path(sys.argv[0], run_name="__main__")
