# SPDX-License-Identifier: Apache-2.0
"""Fit- and chain-level STABILITY.md cases: finite results or a clear error, never a crash or NaN.

The cases live in ``benchmarks/stability.py`` (which also prints the full table); these tests run
the cheap ones on the tiny ``sphere`` scene with a few iterations. Kernel-level cases are in each
op's tests; camera validation (NaN pose, det -1, colinear cameras) is in ``tests/test_scene.py``.
"""

import importlib.util
import sys
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "stability.py"
_spec = importlib.util.spec_from_file_location("wtopo_bench_stability", _PATH)
stability = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = stability
_spec.loader.exec_module(stability)


def _expect(name: str, *kinds: str) -> stability.Outcome:
    o = stability.run_case(name)
    assert o.kind in kinds, f"{name}: {o.kind}: {o.detail}"
    return o


@pytest.mark.parametrize("case", ["scale_1e-3", "offset_1e4"])  # 1e3 and 1e6: benchmarks/stability.py
def test_scaled_and_offset_scene_gives_the_same_internal_mesh(case):
    """Fit a scaled or shifted copy of the sphere scene to the same internal-frame mesh."""
    _expect(case, "finite")


def test_grazing_rig_is_finite():
    """Fit a slab seen at 3 to 47 degrees with finite results."""
    _expect("grazing_rig", "finite")


def test_surfels_with_scales_1e_8_are_finite():
    """Fit from surfels whose scales are all 1e-8 with finite results."""
    _expect("scales_1e-8", "finite")


def test_learning_rate_1000x_is_finite_or_aborts_clearly():
    """Survive learning rates 1000x too large: finite results or FitAborted, never NaN."""
    _expect("lr_x1000", "finite", "clear error")


def test_pruning_everything_keeps_surfels():
    """Keep a minimum of surfels when every threshold would prune them all."""
    o = _expect("prune_everything", "finite")
    assert " 0 surfels" not in o.detail


def test_empty_tsdf_falls_back_with_a_warning():
    """Fall back (warm-up surfels, proxy mesh) when no pixel reaches the TSDF, and say so."""
    o = _expect("tsdf_empty", "finite", "clear error")
    if o.kind == "finite":
        assert "TSDF" in o.detail


def test_empty_scene_is_finite_or_a_clear_error():
    """Fit black images with empty masks: finite results or a clear error."""
    _expect("empty_scene", "finite", "clear error")


def test_nan_pixels_are_rejected_by_the_scene():
    """Reject images with NaN pixels at the Scene boundary, naming the index."""
    o = _expect("nan_pixels", "clear error")
    assert "nan" in o.detail and "image 3" in o.detail


def test_nan_depths_are_invalid_pixels():
    """Read NaN/inf depths as invalid (0) pixels."""
    _expect("nan_depths", "finite")


def test_proxy_chain_gradcheck_float64():
    """Pass a float64 gradcheck (reentrancy included) of oriented points -> Poisson -> MC."""
    _expect("chain_gradcheck_fp64", "finite")


def test_repeated_backward_through_the_chain_is_exactly_twice():
    """Accumulate exactly 2x the gradient on a second backward through rasterize, chain and ray cast."""
    _expect("chain_repeated_backward", "finite")


def test_repeated_backward_with_frozen_colors_within_rounding():
    """Stay within float32 rounding of 2x on a second backward when colours need no gradient."""
    _expect("repeated_backward_frozen_colors", "finite")


def test_chain_is_bit_identical_across_runs():
    """Give bit-identical outputs and gradients for two identical CPU runs of the whole chain."""
    _expect("chain_determinism", "finite")


def test_two_fits_in_one_process_are_bit_identical():
    """Fit the sphere twice in one process and get bit-identical surfels."""
    _expect("fit_determinism", "finite")
