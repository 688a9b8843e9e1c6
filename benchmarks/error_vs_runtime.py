# SPDX-License-Identifier: Apache-2.0
"""Error against run time of ``wtopo.fit`` over a suite of scenes, with the three presets marked.

Every point is one fit in a fresh subprocess (its own peak memory, a cold process as a user's). The
points: the presets ``fast``, ``balanced`` and ``best`` (``FitConfig.preset``) and, between them,
``balanced`` at other iteration counts (``scale`` times the iterations its plan gives the scene), which
trace the front the presets are read from. The suite (``SUITE``):

- ``bunny``: the built-in object (32 views of 128 px, masks), the README's first command;
- ``ring_capsule``: a torus (genus one, a hole the views see through) beside a capsule, textured, 32
  views of 128 px with masks: shapes the bunny does not have;
- ``bunny_room``: the built-in scene (no masks, a textured room around the bunny).

Each row records wall and CPU time of ``wtopo.fit`` (scene rendering excluded), the plan's
``expected_seconds``, per-stage self times, peak RSS, Chamfer (% of the ground truth's bounding-box
diagonal), F-score at 0.5 % and held-out PSNR. Output: a CSV (appended as runs finish; ``--resume``
skips rows already there), a Markdown note and a PNG plot of Chamfer against wall time per scene, the
presets drawn as stars::

    .venv/bin/python benchmarks/error_vs_runtime.py                       # the whole suite, ~30-40 min on 2 cores
    .venv/bin/python benchmarks/error_vs_runtime.py --scenes bunny --resume
    .venv/bin/python benchmarks/error_vs_runtime.py --plot-only
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SUITE = ("bunny", "ring_capsule", "bunny_room")
PRESETS = ("fast", "balanced", "best")
SCALES = (0.5, 1.5)
"""Iteration scales of ``balanced`` between the presets (1.0 is ``balanced`` itself)."""
STAGES = {
    "rasterize": ("rasterize_binning", "rasterize_sort", "rasterize_forward", "render"),
    "rasterize_backward": ("rasterize_backward",),
    "losses": ("losses",),
    "backward": ("backward",),
    "optimizer": ("optimizer",),
    "proxy": ("oriented_points", "scatter", "poisson", "marching_cubes", "bvh_build", "raycast", "proxy", "guidance",
              "thin_parts"),
    "init": ("setup", "init", "init_setup", "init_seed", "init_shells", "stereo_sweep", "stereo_confirm"),
    "tsdf_final": ("tsdf", "tsdf_fusion", "tsdf_upload", "tsdf_blocks", "tsdf_integrate", "render_depths", "final",
                   "mesh_policy", "repair", "supported_components", "supported_faces", "outline"),
}
"""Reported stage -> the fit's timer names summed into it; the timers of :data:`OTHER` go to ``other``."""
OTHER = ("read", "statistics", "snapshot", "release", "evaluate", "densify", "checkpoint", "timeline", "timeline_copy",
         "timeline_send", "timeline_wait")
"""The fit's bookkeeping timers, reported together as ``other`` (a timer in neither map fails the tests: name it)."""
COLUMNS = ("scene", "preset", "scale", "iterations", "wall_s", "cpu_s", "expected_s",
           *(f"t_{s}" for s in STAGES), "t_other", "peak_rss_mb", "chamfer", "f_score", "psnr", "surfels", "faces",
           "watertight", "status", "error")
DEFAULT_CSV = HERE / "error_vs_runtime.csv"
DEFAULT_PNG = HERE / "error_vs_runtime.png"
DEFAULT_MD = HERE / "error_vs_runtime.md"


def points(scenes=SUITE) -> list[dict]:
    """The suite's runs: each preset, then ``balanced`` at :data:`SCALES`, per scene."""
    out = []
    for sc in scenes:
        out += [{"scene": sc, "preset": p, "scale": 1.0} for p in PRESETS]
        out += [{"scene": sc, "preset": "balanced", "scale": s} for s in SCALES]
    return out


def key(spec: dict) -> tuple:
    return str(spec["scene"]), str(spec["preset"]), f"{float(spec['scale']):g}"


def load_scene(name: str):
    """A suite scene (the built-ins from :func:`wtopo.scenes.load`; ``ring_capsule`` made here)."""
    from wtopo import scenes

    if name != "ring_capsule":
        return scenes.load(name)
    import numpy as np
    import trimesh

    ring = trimesh.creation.torus(major_radius=0.55, minor_radius=0.16, major_sections=96, minor_sections=32)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    ring.apply_translation([-0.45, 0.0, 0.0])
    capsule = trimesh.creation.capsule(height=0.9, radius=0.28, count=[48, 48])
    capsule.apply_translation([0.75, 0.0, 0.0])
    mesh = trimesh.util.concatenate([ring, capsule])
    return scenes.from_mesh(mesh, n_views=32, resolution=128, rig="sphere", texture="coffee", background="black",
                            name="ring_capsule", seed=3)


def make_config(spec: dict, scene, device: str):
    """``FitConfig`` of one point: the preset, its plan's iterations times ``scale`` when it is not 1."""
    import torch

    from wtopo.fitting import FitConfig, Preset, iteration_budget

    cfg = FitConfig()
    cfg.preset = Preset(spec["preset"])
    cfg.runtime.device = device
    if float(spec["scale"]) != 1.0:
        dev = torch.device("cuda" if device != "cpu" and torch.cuda.is_available() else "cpu")
        warm, coevo, _ = iteration_budget(scene, dev, None, cfg.preset)
        cfg.warmup.iterations = max(1, round(warm * float(spec["scale"])))
        cfg.coevolution.iterations = max(1, round(coevo * float(spec["scale"])))
    cfg.runtime.eval_every = 0  # metrics once, on the final mesh
    cfg.runtime.usd_every = 0
    cfg.runtime.progress = False
    return cfg


def _peak_rss_mb() -> float:
    import resource

    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 2**20 if sys.platform == "darwin" else kb / 1024.0


def run_point(spec: dict, device: str, threads: int = 0) -> dict:
    """One fit in this process (``threads`` > 0: that many torch threads); its CSV row."""
    import tempfile

    import torch

    from wtopo.fitting import fit

    if threads > 0:
        torch.set_num_threads(threads)

    scene = load_scene(spec["scene"])
    cfg = make_config(spec, scene, device)
    with tempfile.TemporaryDirectory() as out:
        t, c = time.perf_counter(), time.process_time()
        res = fit(scene, cfg, out_dir=out, progress=False)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
    rep, st = res.report, res.report["stage_times_s"]
    row = {**spec, "iterations": int(rep["iterations"]), "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
           "expected_s": res.plan.expected_seconds, "peak_rss_mb": round(_peak_rss_mb())}
    used = set()
    for name, timers in STAGES.items():
        row[f"t_{name}"] = round(sum(float(st.get(k, 0.0)) for k in timers), 2)
        used.update(timers)
    row["t_other"] = round(sum(float(v) for k, v in st.items() if k not in used), 2)
    row.update(chamfer=100.0 * rep["chamfer"] if "chamfer" in rep else "", f_score=rep.get("f_score", ""),
               psnr=rep.get("psnr", ""), surfels=rep["surfels"], faces=rep["mesh"]["faces"],
               watertight=rep["mesh"]["watertight"], status=rep["status"], error="")
    return row


def run_subprocess(spec: dict, device: str, timeout: float, threads: int = 0) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec), "--device", device,
           "--threads", str(threads)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {**spec, "status": "timeout", "error": f"no result within {timeout:g} s"}
    for line in reversed(p.stdout.splitlines()):
        if line.startswith("ROW "):
            return json.loads(line[4:])
    tail = (p.stderr or p.stdout).strip().splitlines()[-1:] or [f"exit code {p.returncode}"]
    return {**spec, "status": "failed", "error": tail[0][:300]}


def append_csv(path, row: dict) -> None:
    new = not os.path.exists(path) or os.path.getsize(path) == 0
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        if new:
            w.writeheader()
        w.writerow({k: row.get(k, "") for k in COLUMNS})


def read_csv(path) -> list[dict]:
    """Rows of a results CSV; numeric cells as floats, empty cells dropped."""
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            row = {}
            for k, v in r.items():
                if v in (None, ""):
                    continue
                try:
                    row[k] = v if k in ("scene", "preset", "status", "error") else float(v)
                except ValueError:
                    row[k] = v
            rows.append(row)
    return rows


def _done(r: dict) -> bool:
    return isinstance(r.get("wall_s"), float) and isinstance(r.get("chamfer"), float) and math.isfinite(r["chamfer"])


def label(r: dict) -> str:
    return r["preset"] if float(r.get("scale", 1.0)) == 1.0 else f"balanced x{float(r['scale']):g}"


def plot(rows: list[dict], out_png) -> str:
    """Chamfer and 1 - F against wall time, one colour per scene, presets as stars, points in between as dots."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    rows = [r for r in rows if _done(r)]
    if not rows:
        raise ValueError("no finished run to plot")
    fig = Figure(figsize=(11.0, 4.2), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    for ax, (y, title) in zip(fig.subplots(1, 2), (("chamfer", "Chamfer [% of bbox diagonal]"),
                                                   ("f_score", "1 - F-score (0.5 %)"))):
        for k, sc in enumerate(dict.fromkeys(r["scene"] for r in rows)):
            pts = sorted((r for r in rows if r["scene"] == sc), key=lambda r: r["wall_s"])
            val = [r[y] if y == "chamfer" else 1.0 - r[y] for r in pts]
            ax.plot([r["wall_s"] for r in pts], val, color=f"C{k}", linewidth=0.8, alpha=0.6)
            for r, v in zip(pts, val):
                star = float(r.get("scale", 1.0)) == 1.0
                ax.scatter([r["wall_s"]], [v], color=f"C{k}", marker="*" if star else "o", s=90 if star else 18,
                           zorder=3, label=sc if r is pts[0] else None)
                if star:
                    ax.annotate(r["preset"], (r["wall_s"], v), fontsize=7, xytext=(4, 4), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_formatter(ScalarFormatter())  # seconds as plain numbers, unlabelled minor ticks
        ax.xaxis.set_minor_formatter(NullFormatter())
        lo, hi = ax.get_xlim()
        ax.set_xticks([t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000) if lo <= t <= hi])
        ax.set_xlim(lo, hi)
        ax.set_xlabel("wall time of wtopo.fit [s]")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    tmp = f"{out_png}.tmp.png"
    fig.savefig(tmp, format="png")
    os.replace(tmp, out_png)
    return os.fspath(out_png)


def _f(v, d=2) -> str:
    return f"{v:.{d}f}" if isinstance(v, float) else ("" if v is None else str(v))


def table(rows: list[dict]) -> str:
    head = ["scene", "point", "iterations", "wall s", "plan's estimate s", "CPU s",
            *(s for s in STAGES), "other", "RSS MB", "Chamfer %", "F", "PSNR", "closed"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["scene"], label(r), _f(r.get("iterations"), 0), _f(r.get("wall_s"), 1), _f(r.get("expected_s"), 0),
                 _f(r.get("cpu_s"), 1), *(_f(r.get(f"t_{s}"), 1) for s in STAGES), _f(r.get("t_other"), 1),
                 _f(r.get("peak_rss_mb"), 0), _f(r.get("chamfer"), 3), _f(r.get("f_score"), 3), _f(r.get("psnr"), 2),
                 {"True": "yes", "False": "no"}.get(str(r.get("watertight")), "") if r.get("status") == "completed"
                 else f"{r.get('status')}: {r.get('error', '')}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Per preset: mean wall time and mean Chamfer / F over the scenes that finished every preset, and the
    mean Chamfer against ``best``'s."""
    done = [r for r in rows if _done(r) and float(r.get("scale", 1.0)) == 1.0]
    scenes = [s for s in dict.fromkeys(r["scene"] for r in done)
              if {r["preset"] for r in done if r["scene"] == s} >= set(PRESETS)]
    if not scenes:
        return ""
    by = {(r["scene"], r["preset"]): r for r in done}
    lines = ["| preset | mean wall s | mean Chamfer % | mean F | Chamfer against best (mean of ratios) |",
             "|---|---|---|---|---|"]
    for p in PRESETS:
        rs = [by[(s, p)] for s in scenes]
        ratio = sum(by[(s, p)]["chamfer"] / by[(s, "best")]["chamfer"] for s in scenes) / len(scenes)
        lines.append(f"| {p} | {sum(r['wall_s'] for r in rs) / len(rs):.1f} | "
                     f"{sum(r['chamfer'] for r in rs) / len(rs):.3f} | {sum(r['f_score'] for r in rs) / len(rs):.3f} "
                     f"| {ratio:.3f} |")
    return f"Over {', '.join(scenes)}:\n\n" + "\n".join(lines)


def write_note(rows: list[dict], md, png, command: str) -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=HERE).stdout.strip()
    import torch

    text = ["# Error against run time: the presets", "",
            f"Command: `{command}` at `{commit or 'unknown'}`, {platform.machine()}, "
            f"{torch.get_num_threads()} torch threads on {os.cpu_count()} cores. Plot: "
            f"[`{Path(png).name}`]({Path(png).name}). Each point is one fit in a fresh process; times are of "
            "`wtopo.fit` alone (scene rendering excluded), stage columns are self times in seconds. Chamfer and "
            "F-score (0.5 % of the ground truth's diagonal) of the final mesh; PSNR on the held-out views "
            "(inside the masks for masked scenes).", "", summary(rows), "", table(rows), ""]
    Path(md).write_text("\n".join(text))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SUITE), choices=SUITE)
    ap.add_argument("--presets-only", action="store_true", help="only the three presets (no points between)")
    ap.add_argument("--csv", default=str(DEFAULT_CSV))
    ap.add_argument("--png", default=str(DEFAULT_PNG))
    ap.add_argument("--md", default=str(DEFAULT_MD))
    ap.add_argument("--resume", action="store_true", help="keep the CSV's rows and skip their runs")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per-run limit [s]")
    ap.add_argument("--plot-only", action="store_true", help="redraw the plot and note from the CSV")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per fit (0: torch's default)")
    ap.add_argument("--jobs", type=int, default=1, help="fits at once (with --threads 1 on a shared machine)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print("ROW " + json.dumps(run_point(json.loads(args.worker), args.device, args.threads)), flush=True)
        return 0
    specs = [s for s in points(args.scenes) if not args.presets_only or s["scale"] == 1.0]
    if not args.plot_only:
        if not args.resume and os.path.exists(args.csv):
            os.remove(args.csv)
        done = {key(r) for r in read_csv(args.csv)} if os.path.exists(args.csv) else set()
        todo = [s for s in specs if key(s) not in done]

        import threading

        lock = threading.Lock()

        def one(spec):
            row = run_subprocess(spec, args.device, args.timeout, args.threads)
            with lock:
                append_csv(args.csv, row)
            print(f"{label(row)} on {spec['scene']}: wall {row.get('wall_s', '-')} s "
                  f"(plan {row.get('expected_s', '-')}), "
                  f"Chamfer {row.get('chamfer', '-')}, F {row.get('f_score', '-')}, {row.get('status')} "
                  f"{row.get('error', '')}", flush=True)

        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            list(pool.map(one, todo))
    rows = read_csv(args.csv)
    plot(rows, args.png)
    write_note(rows, args.md, args.png, "python benchmarks/error_vs_runtime.py " + " ".join(argv or sys.argv[1:]))
    print(summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
