# SPDX-License-Identifier: Apache-2.0
"""Shared test shapes: a sphere tiled by surfels."""

from __future__ import annotations

import numpy as np


def sphere_lattice(n: int, radius: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``n`` points of a Fibonacci lattice on the unit sphere: ``(unit normals [n, 3] float64, the same
    as points on a sphere of ``radius`` around the origin, sigma)``, where ``sigma`` is one lattice
    spacing on that sphere (discs of that standard deviation overlap their neighbours: no holes)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    nrm = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    return nrm, radius * nrm, float(radius * np.sqrt(4 * np.pi / n))
