# SPDX-License-Identifier: Apache-2.0
"""Timings and report of the fit- and chain-level stiff cases (design/stability.md).

The cases, and the one outcome each must have, live in ``tests/test_stability.py`` (:data:`CASES`),
where ``pytest`` checks them; this script runs the same table, times every case and writes
``benchmarks/stability.md`` with a coverage table saying where each design/stability.md case is
tested. A case is ``ok`` when it had its expected outcome (finite and checked, or the named error),
``FAILED`` otherwise.

Command (prints the table and writes benchmarks/stability.md)::

    .venv/bin/python benchmarks/stability.py
    .venv/bin/python benchmarks/stability.py --cases scale_1e-3 nan_pixels   # a subset, no file written
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
from _from_tests import TESTS, load, load_file  # noqa: E402  (beside this script)

load_file(TESTS / "fit_configs.py", "fit_configs")  # what test_stability.py imports from beside it
CASES = load("test_stability.py").CASES  # the case builders and their expected outcomes

__all__ = ["Outcome", "run_case", "markdown_table", "coverage_table", "main"]


@dataclass
class Outcome:
    """Result of one case: ``ok`` when it had its expected outcome; ``detail`` says what was measured."""

    case: str
    expected: str
    ok: bool
    detail: str
    seconds: float


def run_case(name: str) -> Outcome:
    """Run one case of :data:`CASES` and classify it (never raises)."""
    case = CASES[name]
    expected = "finite" if case.raises is None else case.raises.__name__
    t = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            detail, ok = case.check(), True
    except Exception as e:  # noqa: BLE001 - any other outcome is reported as a failure of the case
        detail, ok = f"{type(e).__name__}: {e}", False
    return Outcome(name, expected, ok, " ".join(detail.split()), time.perf_counter() - t)


def markdown_table(outcomes: list[Outcome]) -> str:
    """Markdown table of the outcomes."""
    lines = ["| case | expected | outcome | detail | s |", "|---|---|---|---|---|"]
    for o in outcomes:
        lines.append(f"| {o.case} | {o.expected} | {'ok' if o.ok else 'FAILED'} | {o.detail.replace('|', '/')} "
                     f"| {o.seconds:.1f} |")
    return "\n".join(lines)


COVERAGE_ROWS = (
    (
        "1 surfel parameters",
        "scale 1e-8 / 1e4, needles, quaternion 0 / unnormalised, opacity 0 / 1, N = 0, all culled, duplicates",
        "`tests/test_rasterize_stability.py` (`tiny_scales_render_through_the_filter`, "
        "`huge_scales_bounded_intersections`, `intersection_budget_raises`, `zero_surfels`, `all_culled`, "
        "`zero_opacity`, `needle_and_duplicates`), `tests/test_rasterize.py` (`quaternion_norm_is_irrelevant`, "
        "`zero_quaternion_is_identity`, `opacity_one_is_clamped`), `tests/test_oriented_points.py`; fit from "
        "surfels at 1e-8: `scales_1e-8`",
    ),
    (
        "2 ray-surfel geometry",
        "parallel / near-parallel rays, edge-on sweep, camera inside, near plane, scene scale, odd sizes",
        "`tests/test_rasterize_stability.py` (`grazing_*`, `edge_on_sweep_is_continuous`, `camera_inside_surfel`, "
        "`straddling_near_plane_skips_pixels`, `scene_scale_invariance`, `odd_image_sizes`); grazing rig "
        "through the fit: `grazing_rig`",
    ),
    (
        "3 scatter",
        "empty set, boundary / outside points, zero weights, NaN, one voxel, determinism",
        "`tests/test_scatter_trilinear.py`, `tests/test_poisson.py`",
    ),
    (
        "4 FFT Poisson",
        "resolutions 8-256, empty / zero divergence, padding leak, sigma 0 / large, fp32 vs fp64, gradcheck",
        "`tests/test_poisson.py`",
    ),
    (
        "5 marching cubes",
        "no crossing, values == iso, tiny edge differences, boundary, 2^3-256^3, sphere area, validation",
        "`tests/test_marching_cubes.py`",
    ),
    (
        "6 BVH ray cast",
        "0 faces, degenerate triangles, edges / vertices, parallel rays, camera inside, large mesh",
        "`tests/test_raycast.py`",
    ),
    (
        "7 losses",
        "log-depth masking, GT holes, zero normals, depth discontinuities, non-finite total loss",
        "`tests/test_losses.py`; non-finite loss skip / abort: "
        "`tests/test_fit.py::test_injected_nan_is_survived_and_persistent_nan_aborts`",
    ),
    (
        "8 cameras and inputs",
        "NaN pose, non-orthonormal, det -1, fx <= 0, one / duplicated / colinear cameras",
        "`tests/test_scene.py`, `tests/test_loaders.py::test_colmap_nan_pose_names_the_camera`",
    ),
    (
        "8",
        "scene scale 1e-3 / 1e3, offset 1e4 / 1e6 through the whole fit",
        "`scale_*`, `offset_*`; normalisation alone: `tests/test_scene.py`",
    ),
    (
        "8",
        "empty TSDF, NaN pixels / depths",
        "`tsdf_empty`, `empty_masks`, `nan_pixels`, `nan_depths`; `tests/test_tsdf_regression.py`",
    ),
    (
        "9 optimisation",
        "learning rate x1000, prune everything",
        "`lr_x1000`, `prune_everything`; `tests/test_densify.py` (`pruning_everything_keeps_a_minimum`, "
        "`prune_slices_adam_state_and_buffers_consistently`, `densification_respects_the_cap`)",
    ),
    (
        "9",
        "repeated backward / reentrancy",
        "per op: `tests/test_bridge.py`, `test_rasterize_stability.py`, `test_marching_cubes.py`, `test_raycast.py`; "
        "whole chain: `chain_gradcheck_fp64`, `chain_repeated_backward`, `repeated_backward_frozen_colors`",
    ),
    (
        "9",
        "determinism",
        "`tests/test_scatter_trilinear.py`, "
        "`tests/test_rasterize_stability.py::test_cpu_worker_count_does_not_change_results`; "
        "whole chain and whole fit: `chain_determinism`, `fit_determinism`",
    ),
)
"""(design/stability.md section, cases, where they are tested); a bare `name` is a case of
``tests/test_stability.py``."""


def coverage_table() -> str:
    """Markdown table of :data:`COVERAGE_ROWS`."""
    lines = ["## Where each design/stability.md case is tested", "", "| section | cases | tests |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in COVERAGE_ROWS]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="wtopo stability sweep: time the stiff cases of tests/test_stability.py")
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=None)
    ap.add_argument("--md", default=str(HERE / "stability.md"))
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    outcomes = []
    for name in args.cases or CASES:
        o = run_case(name)
        outcomes.append(o)
        print(f"{o.case:<32} {'ok' if o.ok else 'FAILED':<7} {o.detail} ({o.seconds:.1f} s)", flush=True)
    table = markdown_table(outcomes)
    if args.md and not args.cases:
        head = ["# Stability sweep", "", "Command: `.venv/bin/python benchmarks/stability.py` (the same cases run "
                "under pytest in `tests/test_stability.py`)", "",
                f"Machine: {platform.machine()}, {os.cpu_count()} shared CPU cores, torch {torch.__version__}.",
                "Each case has one expected outcome: `finite` (completes, every output finite, its own check "
                "passes) or the named exception with a matching message.", ""]
        Path(args.md).write_text("\n".join(head) + "\n" + table + "\n\n" + coverage_table())
    print(table)
    return 0 if all(o.ok for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
