# SPDX-License-Identifier: Apache-2.0
"""Error against run time of ``wtopo.fit``: what accuracy each setting buys for what time.

Sweeps the Poisson grid resolution (``mesh.resolution``), the iteration count, the image
resolution (the scene rendered at that size) and the oriented points per surfel (1 vs 5) on the
default scenes. Each run is a fresh subprocess (so its peak memory is its own) and records:

- ``wall_s``: wall time of ``wtopo.fit`` (scene loading and imports excluded; Warp kernels come
  from the kernel cache, which the first run fills) and ``cpu_s``, its CPU time (all threads;
  far less sensitive than wall time to other processes on a shared machine, so the plot uses it);
- per-stage self times from ``FitResult.report["stage_times_s"]`` (nested sections subtracted,
  so the stages add up to the timed part of the fit): ``rasterize``, ``oriented_points``,
  ``scatter``, ``poisson`` (FFT solve and normalisation, scatter excluded), ``marching_cubes``,
  ``bvh_build`` (build or refit), ``raycast``, ``backward``, ``densify_prune`` (screen-space
  clone/split/prune plus the mesh-guided sign/prune/spawn step), ``tsdf`` (TSDF
  re-initialisation plus the final mesh's extraction and clean-up), ``other`` (losses, optimiser,
  evaluation, remainder);
- ``peak_rss_mb``: the subprocess's maximum resident set size (``resource.getrusage``), and
  ``cuda_peak_mb`` (``torch.cuda.max_memory_allocated``) on CUDA;
- ``chamfer`` (% of the ground truth's bounding-box diagonal), ``f_score`` (threshold 0.5 % of
  the diagonal) and ``psnr`` (held-out views) of the final mesh / surfels.

The default sweep varies one factor at a time around a short base configuration on ``bunny``
and runs the base on ``bunny_room`` (about 20-25 minutes on a busy 2-core CPU); ``--full`` runs
the complete grid on both scenes. Results are appended to the CSV as each run ends, and
``--resume`` skips runs already in it, so the sweep can run in the background and be polled::

    nohup .venv/bin/python benchmarks/error_vs_runtime.py --resume > /tmp/evr.log 2>&1 &
    .venv/bin/python benchmarks/error_vs_runtime.py --full --csv benchmarks/error_vs_runtime_full.csv

:func:`pareto_plot` (used by ``wtopo report`` as well) draws error against time from the CSV
with each scene's Pareto front.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["AXES", "BASE", "STAGES", "default_sweep", "full_sweep", "make_config", "run_spec", "run_subprocess",
           "read_csv", "pareto_front", "pareto_plot", "markdown_table", "main"]

HERE = Path(__file__).resolve().parent
SCENES = ("bunny", "bunny_room")
BASE = {"scene": "bunny", "mesh_resolution": 64, "iterations": 160, "image_resolution": 64, "samples_per_surfel": 5}
"""Centre of the one-factor-at-a-time sweep (iterations: warm-up half, co-evolution half)."""
AXES = {
    "mesh_resolution": (32, 64, 128, 256),
    "iterations": (80, 240, 1200),
    "image_resolution": (64, 128, 256),
    "samples_per_surfel": (1, 5),
}
"""Values of each swept factor (``--full``: every combination)."""
DEFAULT_AXES = {
    "mesh_resolution": (32, 64, 128, 256),
    "iterations": (80, 160, 320),
    "image_resolution": (64, 128),
    "samples_per_surfel": (1, 5),
}
"""Values varied by the default (one-factor-at-a-time) sweep."""
STAGES = {
    "rasterize": ("render",),
    "oriented_points": ("oriented_points",),
    "scatter": ("scatter",),
    "poisson": ("poisson",),
    "marching_cubes": ("marching_cubes",),
    "bvh_build": ("bvh_build",),
    "raycast": ("raycast",),
    "backward": ("backward",),
    "densify_prune": ("densify", "guidance"),
    "tsdf": ("tsdf", "final"),
}
"""Reported stage -> the fit's timer names summed into it; every other timer goes to ``other``."""
METRICS = ("chamfer", "f_score", "psnr")
SPEC_KEYS = tuple(BASE)
COLUMNS = (*SPEC_KEYS, "wall_s", "cpu_s", *(f"t_{s}" for s in STAGES), "t_other", "peak_rss_mb", "cuda_peak_mb",
           *METRICS,
           "surfels", "faces", "watertight", "status", "device", "error")
DEFAULT_CSV = HERE / "error_vs_runtime.csv"
DEFAULT_PNG = HERE / "error_vs_runtime.png"
DEFAULT_MD = HERE / "error_vs_runtime.md"


# -- sweeps -----------------------------------------------------------------------------------------
def _spec(**kw) -> dict:
    return {**BASE, **kw}


def default_sweep() -> list[dict]:
    """One factor at a time around :data:`BASE` on ``bunny``, plus the base on ``bunny_room``."""
    specs = [_spec()]
    for axis, values in DEFAULT_AXES.items():
        specs += [_spec(**{axis: v}) for v in values if v != BASE[axis]]
    specs.append(_spec(scene="bunny_room"))
    return specs


def full_sweep(scenes=SCENES) -> list[dict]:
    """Every combination of :data:`AXES` on each scene."""
    return [dict(zip(("scene", *AXES), combo)) for combo in itertools.product(scenes, *AXES.values())]


def spec_key(spec: dict) -> tuple:
    """Identity of a run (numbers read back from a CSV as floats compare equal to the ints)."""
    return tuple(str(int(spec[k])) if isinstance(spec[k], (int, float)) else str(spec[k]) for k in SPEC_KEYS)


def make_config(spec: dict, *, device: str = "auto"):
    """The :class:`wtopo.FitConfig` of one run: defaults, the iterations split evenly between the stages.

    Milestones are fractions of their stage and follow the iteration counts; only the density-control
    cadence, a count, is set so that short runs still get about six density steps.
    """
    from wtopo.fitting import FitConfig

    cfg = FitConfig()
    it = int(spec["iterations"])
    warm = it // 2
    cfg.warmup.iterations, cfg.coevolution.iterations = warm, it - warm
    cfg.densify.interval = max(10, warm // 6)
    cfg.mesh.resolution = int(spec["mesh_resolution"])
    cfg.mesh.samples_per_surfel = int(spec["samples_per_surfel"])
    cfg.runtime.device = device
    cfg.runtime.eval_every = 0  # metrics once, on the final mesh
    cfg.runtime.usd_every = 0
    cfg.runtime.checkpoint_every = 0
    cfg.runtime.progress = False
    return cfg


# -- one run ----------------------------------------------------------------------------------------
def _peak_rss_mb() -> float:
    import resource

    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kilobytes on Linux, bytes on macOS
    return kb / (1024.0 * 1024.0) if sys.platform == "darwin" else kb / 1024.0


def stage_columns(stage_times: dict[str, float]) -> dict[str, float]:
    """Fit timers (``report["stage_times_s"]``) grouped into the reported stages plus ``other``."""
    out, used = {}, set()
    for name, timers in STAGES.items():
        out[f"t_{name}"] = round(sum(float(stage_times.get(t, 0.0)) for t in timers), 3)
        used.update(timers)
    out["t_other"] = round(sum(float(v) for k, v in stage_times.items() if k not in used), 3)
    return out


def run_spec(spec: dict, *, device: str = "auto") -> dict:
    """Run one fit in this process and return its CSV row (see :data:`COLUMNS`)."""
    import torch

    from wtopo import scenes
    from wtopo.fitting import fit

    scene = scenes.load(spec["scene"], resolution=int(spec["image_resolution"]))
    cfg = make_config(spec, device=device)
    cuda = torch.cuda.is_available() and device != "cpu"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    t, c = time.perf_counter(), time.process_time()
    res = fit(scene, cfg, progress=False)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    rep = res.report
    row = {**spec, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3), **stage_columns(rep["stage_times_s"]),
           "peak_rss_mb": round(_peak_rss_mb(), 1),
           "cuda_peak_mb": round(torch.cuda.max_memory_allocated() / 2**20, 1) if cuda else "",
           "chamfer": 100.0 * rep["chamfer"] if "chamfer" in rep else "", "f_score": rep.get("f_score", ""),
           "psnr": rep.get("psnr", ""), "surfels": rep["surfels"], "faces": rep["mesh"]["faces"],
           "watertight": rep["mesh"]["watertight"], "status": rep["status"], "device": rep["device"], "error": ""}
    return row


def run_subprocess(spec: dict, *, device: str = "auto", timeout: float | None = None) -> dict:
    """Run one fit in a fresh Python process (its own peak memory); failures become rows with ``error``."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec), "--device", device]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE.parent), os.environ.get("PYTHONPATH", "")])}
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {**spec, "status": "timeout", "error": f"no result within {timeout} s"}
    for line in reversed(p.stdout.splitlines()):
        if line.startswith("ROW "):
            return json.loads(line[4:])
    tail = (p.stderr or p.stdout).strip().splitlines()[-1:] or [f"exit code {p.returncode}"]
    return {**spec, "status": "failed", "error": tail[0][:300]}


# -- files ------------------------------------------------------------------------------------------
def append_csv(path: str | os.PathLike, row: dict) -> None:
    path = Path(path)
    new = not path.exists() or path.stat().st_size == 0
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        if new:
            w.writeheader()
        w.writerow({k: row.get(k, "") for k in COLUMNS})


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a results CSV; numeric cells as floats, empty cells dropped."""
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            row = {}
            for k, v in r.items():
                if v in (None, ""):
                    continue
                try:
                    row[k] = float(v)
                except ValueError:
                    row[k] = v
            rows.append(row)
    return rows


def _ok(r: dict, y: str, x: str = "wall_s") -> bool:
    return isinstance(r.get(x), float) and isinstance(r.get(y), float) and math.isfinite(r[y])


def pareto_front(rows: list[dict], *, x: str = "wall_s", y: str = "chamfer") -> list[dict]:
    """Rows not dominated in (smaller ``x``, smaller ``y``), sorted by ``x``."""
    pts = sorted((r for r in rows if _ok(r, y, x)), key=lambda r: (r[x], r[y]))
    front, best = [], math.inf
    for r in pts:
        if r[y] < best:
            front.append(r)
            best = r[y]
    return front


def _label(r: dict) -> str:
    diff = [f"{k.split('_')[0]}={int(r[k])}" for k in SPEC_KEYS[1:] if isinstance(r.get(k), float) and r[k] != BASE[k]]
    return ",".join(diff) or "base"


def pareto_plot(rows_or_csv, out_png: str | os.PathLike, *, x: str = "cpu_s") -> str:
    """PNG of Chamfer and 1 - F-score against run time, one colour per scene, Pareto fronts drawn.

    Args:
        rows_or_csv: a results CSV path or a list of rows (as :func:`read_csv` returns).
        out_png: output path.
        x: ``"cpu_s"`` (CPU time of the fit: robust to other processes sharing the machine) or
            ``"wall_s"``; rows without ``cpu_s`` fall back to ``wall_s``.

    Returns:
        ``out_png`` as a string.

    Raises:
        ValueError: no row holds a wall time and a Chamfer distance.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = read_csv(rows_or_csv) if isinstance(rows_or_csv, (str, os.PathLike)) else list(rows_or_csv)
    rows = [dict(r, one_minus_f=1.0 - r["f_score"]) if isinstance(r.get("f_score"), float) else r for r in rows]
    if x == "cpu_s" and not any(isinstance(r.get("cpu_s"), float) for r in rows):
        x = "wall_s"
    if not any(_ok(r, "chamfer", x) for r in rows):
        raise ValueError(f"no run with a {x} time and a Chamfer distance to plot")
    fig = Figure(figsize=(11.0, 4.2), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    scenes = sorted({str(r.get("scene")) for r in rows})
    panels = (("chamfer", "Chamfer [% of bbox diagonal]"), ("one_minus_f", "1 - F-score (0.5 %)"))
    for ax, (y, title) in zip(axes, panels):
        for k, sc in enumerate(scenes):
            pts = [r for r in rows if str(r.get("scene")) == sc and _ok(r, y, x)]
            if not pts:
                continue
            color = f"C{k}"
            ax.scatter([r[x] for r in pts], [r[y] for r in pts], color=color, s=22, label=sc, zorder=3)
            for r in pts:
                ax.annotate(_label(r), (r[x], r[y]), fontsize=6, xytext=(3, 3), textcoords="offset points",
                            color="0.25")
            front = pareto_front(pts, x=x, y=y)
            ax.step([r[x] for r in front], [r[y] for r in front], where="post", color=color, linewidth=1.0,
                    alpha=0.7)
        ax.set_xscale("log")
        if y == "chamfer":
            ax.set_yscale("log")  # scenes differ by an order of magnitude
        ax.set_xlabel("CPU time of wtopo.fit [s]" if x == "cpu_s" else "wall time of wtopo.fit [s]")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    out_png = os.fspath(out_png)
    tmp = f"{out_png}.tmp.png"
    fig.savefig(tmp, format="png")
    os.replace(tmp, out_png)
    return out_png


def _fmt(v, digits=2) -> str:
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return "" if v is None else str(v)


def _untimed(r: dict, stage_cols: list[str]) -> float | None:
    """Wall time outside every fit timer (plan, initialisation, per-iteration bookkeeping)."""
    if not isinstance(r.get("wall_s"), float):
        return None
    return r["wall_s"] - sum(float(r.get(c, 0.0)) for c in stage_cols)


def markdown_table(rows: list[dict]) -> str:
    """Markdown table: settings, wall time, stage times, memory, metrics."""
    stage_cols = [f"t_{s}" for s in STAGES] + ["t_other"]
    head = ["scene", "grid", "iters", "image", "pts/surfel", "wall s", "CPU s", *[c[2:] for c in stage_cols], "untimed",
            "RSS MB",
            "Chamfer %", "F", "PSNR", "status"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r.get("scene", "")), *(_fmt(r.get(k), 0) for k in SPEC_KEYS[1:]), _fmt(r.get("wall_s"), 1),
                 _fmt(r.get("cpu_s"), 1), *(_fmt(r.get(c), 1) for c in stage_cols), _fmt(_untimed(r, stage_cols), 1),
                 _fmt(r.get("peak_rss_mb"), 0),
                 _fmt(r.get("chamfer"), 3),
                 _fmt(r.get("f_score"), 3), _fmt(r.get("psnr"), 2),
                 str(r.get("status", "")) + (f": {r['error']}" if r.get("error") else "")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_markdown(rows: list[dict], md: str | os.PathLike, png: str | os.PathLike, command: str) -> None:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=HERE, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    text = [
        "# Error against run time of `wtopo.fit`",
        "",
        f"Command: `{command}` (code at `{commit or 'unknown'}`).",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU cores shared with other busy processes "
        f"(1-minute load average {load:.1f} when the table was written: timings are noisy, compare rows "
        f"of one sweep). Plot: [`{Path(png).name}`]({Path(png).name}).",
        "",
        f"Base run: {BASE}. Iterations are split half warm-up, half co-evolution, with the "
        "density-control and loss milestones scaled accordingly (`make_config`). Stage columns are "
        "self times in seconds (nested sections subtracted): `tsdf` is the TSDF re-initialisation plus "
        "the final mesh's extraction and clean-up (its Poisson, marching cubes and oriented points are in "
        "their own columns), `densify_prune` the screen-space and mesh-guided density control, `other` losses, "
        "optimiser and final evaluation, `untimed` the wall time outside every fit timer (stage plan, "
        "initialisation, per-iteration bookkeeping). Backward passes of all ops are in `backward`. "
        "Chamfer and F-score compare the final mesh with the ground truth in the internal frame (F-score "
        "threshold 0.5 % of the ground truth's bounding-box diagonal); PSNR is on the held-out views.",
        "",
        markdown_table(rows),
        "",
    ]
    Path(md).write_text("\n".join(text))


# -- driver -------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="the complete grid on both scenes")
    ap.add_argument("--scenes", nargs="+", default=None, help="restrict to these scenes")
    ap.add_argument("--csv", default=str(DEFAULT_CSV))
    ap.add_argument("--png", default=str(DEFAULT_PNG))
    ap.add_argument("--md", default=str(DEFAULT_MD))
    ap.add_argument("--resume", action="store_true", help="skip runs already in the CSV")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--timeout", type=float, default=1800.0, help="per-run limit, seconds")
    ap.add_argument("--plot-only", action="store_true", help="only redraw the plot and table from the CSV")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print("ROW " + json.dumps(run_spec(json.loads(args.worker), device=args.device)), flush=True)
        return 0
    specs = full_sweep() if args.full else default_sweep()
    if args.scenes:
        specs = [s for s in specs if s["scene"] in args.scenes]
    if not args.plot_only:
        if not args.resume and os.path.exists(args.csv):
            os.remove(args.csv)
        done = {spec_key(r) for r in read_csv(args.csv)} if os.path.exists(args.csv) else set()
        for i, spec in enumerate(specs):
            if spec_key(spec) in done:
                continue
            t = time.perf_counter()
            row = run_subprocess(spec, device=args.device, timeout=args.timeout)
            append_csv(args.csv, row)
            print(f"[{i + 1}/{len(specs)}] {spec} -> wall {row.get('wall_s', '-')} s, "
                  f"chamfer {row.get('chamfer', '-')}, "
                  f"{row.get('status')} {row.get('error', '')} ({time.perf_counter() - t:.0f} s)", flush=True)
    rows = read_csv(args.csv)
    pareto_plot(rows, args.png)
    cmd = "python benchmarks/error_vs_runtime.py" + (" --full" if args.full else "")
    write_markdown(rows, args.md, args.png, cmd)
    print(markdown_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
