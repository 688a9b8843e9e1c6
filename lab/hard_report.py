# SPDX-License-Identifier: Apache-2.0
"""The hard suite's report (``lab/hard.py``): the rows, the ablation against ``no_loop`` and the
per-variant means as a ``## label`` section of ``lab/hard.md``."""

from __future__ import annotations

import math
import os
import platform

import numpy as np
import torch

from hard_scenes import DESCRIPTIONS


# -- report ----------------------------------------------------------------------------------------
def _f(x, spec: str) -> str:
    if x is None or (isinstance(x, float) and (math.isnan(x) or math.isinf(x))):
        return "-"
    return format(x, spec)


_COLUMNS = ("| scene | variant | Chamfer % | F@0.5 % | acc % | compl % | inward % (area inside %) | "
            "floaters % area (count) | "
            "holes % area | "
            "watertight | comp. | genus | PSNR dB | SSIM | time s | policy dropped (area %) | remeshed | "
            "observed Chamfer % (truth seen %) |")


def _scene_cell(r: dict) -> str:
    return r["scene"] + (f" (seed {r['seed']})" if "seed" in r else "")


def _remeshed(r: dict) -> str:
    """``yes`` / ``no``, and the re-mesh's components the support rule dropped (rows before that rule have none)."""
    if not r["remeshed"]:
        return "no"
    n = r.get("remesh_dropped", 0)
    return f"yes, {n} dropped" if n else "yes"


def _row_line(r: dict) -> str:
    if "error" in r:
        return f"| {_scene_cell(r)} | {r['variant']} | fit failed after {r['time']:.0f} s: {r['error']} |"
    return (f"| {_scene_cell(r)} | {r['variant']} | {_f(r['chamfer'], '.3f')} | {r['f_score']:.3f} | "
            f"{_f(r['accuracy'], '.3f')} | {_f(r['completeness'], '.3f')} | {_f(r.get('inward'), '+.3f')} "
            f"({_f(r.get('inside_frac'), '.0f')}) | {r['floater_frac']:.2f} "
            f"({r['floater_count']}) | {r['hole_frac']:.2f} | {'yes' if r['watertight'] else 'no'} | "
            f"{r['components']} | {_f(r['genus'], 'd')} | {_f(r['psnr'], '.2f')} | {_f(r['ssim'], '.3f')} | "
            f"{r['time']:.0f} | {r['policy_dropped']} ({100 * r['policy_dropped_share']:.2f}) | "
            f"{_remeshed(r)} | "
            f"{_f(r.get('obs_chamfer'), '.3f')} ({_f(r.get('observed'), '.0f')}) |")


_MEAN_KEYS = ("chamfer", "f_score", "accuracy", "completeness", "floater_frac", "floater_count", "hole_frac", "psnr",
              "ssim", "time")


def _case(r: dict) -> tuple[str, int]:
    return r["scene"], int(r.get("seed", 0))


def ablation(rows: list[dict], base: str = "no_loop", key: str = "chamfer") -> list[str]:
    """Per variant against ``base`` (the same scene and seed): the change of the mean Chamfer (``key``:
    ``chamfer`` or ``obs_chamfer``) over the cases both completed, per seed and over all, and the
    largest and smallest per-scene change of it averaged over seeds (the issue's rule: no scene more
    than 2 % worse)."""
    ok = {(r["variant"], *_case(r)): r[key] for r in rows if "error" not in r and r.get(key) is not None}
    if not any(k[0] == base for k in ok):
        return []
    seeds = sorted({k[2] for k in ok})
    what = "Chamfer" if key == "chamfer" else "observed Chamfer"
    lines = ["", f"Each variant against `{base}` on the same scene and seed ({what}; the per-scene change uses "
             f"it averaged over the seeds):", "",
             f"| variant | cases | mean {what} % | " + " | ".join(f"change, seed {s}" for s in seeds)
             + " | change, all | worst scene | best scene |", "|" + "---|" * (6 + len(seeds))]
    for v in dict.fromkeys(k[0] for k in ok):
        cases = [(sc, sd) for (vv, sc, sd) in ok if vv == v and (base, sc, sd) in ok]
        if not cases:
            continue

        def change(sel, v=v):
            a = np.mean([ok[(v, *c)] for c in sel])
            b = np.mean([ok[(base, *c)] for c in sel])
            return 100 * (a / b - 1) if sel else float("nan")

        per_seed = [change([c for c in cases if c[1] == s]) for s in seeds]
        scenes_ = list(dict.fromkeys(c[0] for c in cases))
        per_scene = {sc: change([c for c in cases if c[0] == sc]) for sc in scenes_}
        worst = max(per_scene, key=per_scene.get)
        best = min(per_scene, key=per_scene.get)
        lines.append(f"| {v} | {len(cases)} | {np.mean([ok[(v, *c)] for c in cases]):.3f} | "
                     + " | ".join(_f(x, '+.1f') + " %" for x in per_seed)
                     + f" | {change(cases):+.1f} % | {worst} {per_scene[worst]:+.1f} % | "
                     f"{best} {per_scene[best]:+.1f} % |")
    return lines


def variant_means(rows: list[dict]) -> dict[str, dict]:
    """Per variant, the mean of each figure over the scenes every listed variant completed (so the
    means compare like with like), with the number of scenes and of watertight meshes."""
    ok = [r for r in rows if "error" not in r]
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    common = set.intersection(*({_case(r) for r in ok if r["variant"] == v} for v in variants)) if variants else set()
    out = {}
    for v in variants:
        sel = [r for r in ok if r["variant"] == v and _case(r) in common]
        if sel:
            out[v] = {k: float(np.mean([r[k] for r in sel])) for k in _MEAN_KEYS}
            out[v]["scenes"] = len(sel)
            out[v]["watertight"] = sum(bool(r["watertight"]) for r in sel)
    return out


def markdown(label: str, command: str, rows: list[dict], loads: tuple[float, float]) -> str:
    """The ``## label`` section of lab/hard.md."""
    lines = [f"## {label}", "", f"Command: `{command}`", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
             f"{loads[0]:.1f} at start and {loads[1]:.1f} at end (shared cores: times are noisy); "
             f"torch {torch.__version__}.", "",
             "Relative figures in % of the truth's bounding-box diagonal; tau = 0.5 % of it for F, floaters, holes. "
             "Inward: mean signed distance of the mesh along the truth's normals (positive inside) and the % of "
             "its area inside. "
             "Floaters: % of the mesh's area farther than tau from the truth (detached components with no point "
             "within tau); holes: % of the truth's area farther than tau from the mesh. Policy dropped: "
             "components the final meshing policy removed (no switch turns it off) and their area share. "
             "Observed Chamfer: the Chamfer on the part of the truth two training views see (and the mesh's "
             "area nearest to it), with that part's share of the truth's area (DTU scores only the observed "
             "region; a sparse capture leaves the inside of a cup unseen).", "",
             "Scenes: " + "; ".join(f"`{k}` {DESCRIPTIONS[k]}" for k in dict.fromkeys(r["scene"] for r in rows)) + ".",
             "", _COLUMNS, "|" + "---|" * (_COLUMNS.count("|") - 1)]
    lines += [_row_line(r) for r in rows]
    lines += ablation(rows)
    lines += ablation(rows, key="obs_chamfer")
    means = variant_means(rows)
    if means:
        lines += ["", "Means per variant over the scenes every variant completed:", "",
                  "| variant | scenes | Chamfer % | F@0.5 % | acc % | compl % | floaters % | floater count | holes % | "
                  "PSNR dB | SSIM | time s | watertight |", "|" + "---|" * 13]
        for v, m in means.items():
            lines.append(f"| {v} | {m['scenes']} | {m['chamfer']:.3f} | {m['f_score']:.3f} | {m['accuracy']:.3f} | "
                         f"{m['completeness']:.3f} | {m['floater_frac']:.2f} | {m['floater_count']:.2f} | "
                         f"{m['hole_frac']:.2f} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['time']:.0f} | "
                         f"{m['watertight']}/{m['scenes']} |")
    return "\n".join(lines)


def write_section(path: str, section: str, label: str) -> None:
    """Put ``section`` in ``path`` in place of its ``## label`` section (appended when new)."""
    text = "# Hard-scene suite (issue 15)\n\nSee `lab/hard.py` for the scenes, variants and measures.\n"
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
    head, *sections = text.split("\n## ")
    sections = [s for s in sections if s.partition("\n")[0].strip() != label]
    body = [head.rstrip()] + ["## " + s.rstrip() for s in sections] + [section.rstrip()]
    with open(path, "w") as f:
        f.write("\n\n".join(body) + "\n")
