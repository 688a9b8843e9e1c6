# SPDX-License-Identifier: Apache-2.0
"""The loop against no loop from a device batch: every ``rows.json`` of ``lab/hard.py`` and every
row of ``lab/heldout.py`` under the given folders (an unpacked ``results.tgz`` of
``lab/device/wait.sh``), repeated fits of one scene, variant and seed averaged first, then the
seeds; per scene the change against no loop (whole truth and the part two training views see), and the
suite's figures as the issue states its target: the mean Chamfer over the scenes and its change, the
change averaged over the scenes, and the worst scene; the same on the observed region (the part of the truth two
training views see, as DTU scores), where every pair carries it.

    python3 lab/device/collect.py DIR [DIR ...] [--match LABEL] [--loop default] [--base no_loop] \
        [--scenes S ...] [--adjust]

``--pairs`` adds, per scene, the change within pairs of fits that branched from one warm-up (their reports'
``started_from``), averaged over the pairs with its standard error, for the Chamfer, accuracy, completeness,
observed Chamfer, floaters and F-score: the measurement a paired batch (``hard.py --paired``,
``suite_jobs.sh`` ``SPLIT=1``) is made for.

``--adjust`` adds, per scene, the loop's effect at equal TSDF re-initialisation: a least-squares fit of
every fit's Chamfer on its re-initialisation's face count (the ``tsdf_reinit`` event of the fit's
``report.json``) and whether it is the measured variant. On the GPU two fits of one seed do not share their
warm-up, and on the ten-view cup the re-initialisation sets most of a fit's error in both variants alike
(``hard.md`` ``gpu_cup_seeds``); the adjusted effect takes that spread out (``hard.py --paired`` removes it
at the source).

A ``hard.py`` row's variant is its ``variant`` (``default``, ``no_loop``, ...); a held-out row's is its
``mode`` mapped to the same names (``noloop`` -> ``no_loop``; a mode named after a ``hard.py`` variant is that
variant) and its scene is named with its views and resolution (``vase_v10_r512``); a held-out row that branched
from a warm-up (``heldout.py``, ``SPLIT=1 HELDOUT=1``) carries its ``started_from`` and pairs as a suite row
does. A row carries no sure record of the settings it was fitted with (``hard.py`` rows none at all), so a
candidate measured beside the default in one batch is told apart by its label: ``--match LABEL`` keeps only
the files whose path contains ``LABEL`` (``lab/device/suite_jobs.sh`` puts the label in every run folder
and held-out file name).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
from collections import defaultdict

import numpy as np

_MODES = {"default": "default", "noloop": "no_loop"}


def _read(path: str):
    with open(path) as f:
        return json.load(f)


def _report_facts(rows_file: str, row: dict) -> dict:
    """From the ``report.json`` of the fit behind a ``hard.py`` row (beside ``rows_file``:
    ``[seed<S>/]<scene>_<variant>/``): ``reinit_faces``, the face count of its TSDF re-initialisation, and
    ``started_from``, the warm-up checkpoint it branched from (``runtime.start_from``); ``None`` where absent."""
    sub = f"seed{row['seed']}" if row.get("seed") is not None else ""
    path = os.path.join(os.path.dirname(rows_file), sub, f"{row['scene']}_{row['variant']}", "report.json")
    facts: dict = {"reinit_faces": None, "started_from": None}
    if not os.path.exists(path):
        return facts
    for e in _read(path).get("events", []):
        if e.get("event") == "tsdf_reinit":
            facts["reinit_faces"] = e.get("reinit_faces")
        elif e.get("event") == "started_from":
            facts["started_from"] = e.get("from")
    return facts


def load_rows(dirs: list[str], match: str = "") -> list[dict]:
    """Every suite and held-out row under ``dirs`` whose file path contains ``match`` (a suite row with its
    fit's ``reinit_faces`` and ``started_from`` when its report is there)."""
    rows = []
    for d in dirs:
        for f in sorted(glob.glob(os.path.join(d, "**", "rows.json"), recursive=True)):
            if match in f:
                rows += [{**r, **_report_facts(f, r)} for r in _read(f) if "error" not in r]
        for f in sorted(glob.glob(os.path.join(d, "**", "h_*.json"), recursive=True)):
            r = _read(f)
            if match in f and "error" not in r and r.get("mode"):
                rows.append({**r, "variant": _MODES.get(r["mode"], r["mode"]),
                             "scene": f"{r['scene']}_v{r['views']}_r{r['resolution']}"})
    return rows


def pooled(rows: list[dict], key: str) -> dict[tuple[str, str], dict[int, float]]:
    """``(scene, variant) -> {seed: mean of key over that seed's fits}``."""
    acc: dict[tuple[str, str, int], list[float]] = defaultdict(list)
    for r in rows:
        if r.get(key) is not None:
            acc[(r["scene"], r["variant"], int(r.get("seed", 0)))].append(float(r[key]))
    out: dict[tuple[str, str], dict[int, float]] = defaultdict(dict)
    for (sc, v, sd), xs in acc.items():
        out[(sc, v)][sd] = float(np.mean(xs))
    return out


def table(rows: list[dict], loop: str = "default", base: str = "no_loop", scenes: list[str] | None = None) -> str:
    """The markdown table and the suite's summary lines."""
    ch, ob = pooled(rows, "chamfer"), pooled(rows, "obs_chamfer")
    fits = defaultdict(int)  # fits with a Chamfer, per scene and variant
    for r in rows:
        if r.get("chamfer") is not None:
            fits[(r["scene"], r["variant"])] += 1
    names = scenes or sorted({sc for sc, v in ch if v == loop and (sc, base) in ch})
    lines = [f"| scene | seeds | fits {loop} / {base} | {loop} | {base} | change | observed change |",
             "|---|---|---|---|---|---|---|"]
    whole, observed = {}, {}  # scene -> (loop's mean, base's mean); observed: scenes whose pairs all carry it
    for sc in names:
        la, ba = ch.get((sc, loop), {}), ch.get((sc, base), {})
        seeds = sorted(set(la) & set(ba))
        if not seeds:
            lines.append(f"| {sc} | 0 | {fits[(sc, loop)]} / {fits[(sc, base)]} | - | - | no pair | - |")
            continue
        a, b = whole[sc] = np.mean([la[s] for s in seeds]), np.mean([ba[s] for s in seeds])
        lo, bo = ob.get((sc, loop), {}), ob.get((sc, base), {})
        so = [s for s in seeds if s in lo and s in bo]
        oa, obm = (np.mean([lo[s] for s in so]), np.mean([bo[s] for s in so])) if so else (np.nan, np.nan)
        if len(so) == len(seeds):
            observed[sc] = (oa, obm)
        lines.append(f"| {sc} | {len(seeds)} | {fits[(sc, loop)]} / {fits[(sc, base)]} | {a:.4f} | {b:.4f} | "
                     f"{100 * (a / b - 1):+.1f} % | {100 * (oa / obm - 1):+.1f} % |")
    if whole:
        lines += ["", _suite_line(f"Mean Chamfer over {len(whole)} paired scenes", whole)]
    if observed:  # the rules scored as DTU scores: only the part of the truth two training views see
        lines.append(_suite_line(f"On the observed region, over {len(observed)} scenes", observed))
    return "\n".join(lines)


def _suite_line(head: str, means: dict[str, tuple[float, float]]) -> str:
    """The suite's summary of ``scene -> (loop's mean, base's mean)``: the mean over the scenes and its change,
    the change averaged over the scenes, and the worst scene."""
    per = {sc: 100 * (a / b - 1) for sc, (a, b) in means.items()}
    worst = max(per, key=per.get)
    mean_a, mean_b = np.mean([a for a, _ in means.values()]), np.mean([b for _, b in means.values()])
    return (f"{head}: {mean_a:.4f} % against {mean_b:.4f} % ({100 * (mean_a / mean_b - 1):+.1f} %); per scene "
            f"{np.mean(list(per.values())):+.1f} %; worst scene {worst} {per[worst]:+.1f} %.")


def adjusted(rows: list[dict], loop: str = "default", base: str = "no_loop", key: str = "chamfer") -> dict:
    """Per scene, the loop's effect on ``key`` at equal re-initialisation: ``scene -> (effect %, standard
    error %, fits, correlation)``, the effect and its error in % of ``base``'s mean, the correlation that of
    ``key`` with the re-initialisation's face count over both variants' fits. Ordinary least squares of
    ``key`` on ``[1, faces, is loop]``; a scene needs 4 fits with a face count, both variants and two
    distinct counts."""
    by = defaultdict(list)
    for r in rows:
        if r.get("variant") in (loop, base) and r.get(key) is not None and r.get("reinit_faces") is not None:
            by[r["scene"]].append((float(r["reinit_faces"]), float(r["variant"] == loop), float(r[key])))
    out = {}
    for sc, fits in sorted(by.items()):
        a = np.array(fits)
        if len(a) < 4 or len(set(a[:, 1])) < 2 or len(set(a[:, 0])) < 2:
            continue
        x = np.c_[np.ones(len(a)), a[:, 0] / 1e3, a[:, 1]]
        coef, *_ = np.linalg.lstsq(x, a[:, 2], rcond=None)
        resid = a[:, 2] - x @ coef
        dof = max(len(a) - 3, 1)
        se = float(np.sqrt(resid @ resid / dof * np.linalg.pinv(x.T @ x)[2, 2]))
        mean_base = float(a[a[:, 1] == 0, 2].mean())
        corr = float(np.corrcoef(a[:, 0], a[:, 2])[0, 1]) if a[:, 2].std() > 0 else float("nan")
        out[sc] = (100 * coef[2] / mean_base, 100 * se / mean_base, len(a), corr)
    return out


def adjusted_table(rows: list[dict], loop: str = "default", base: str = "no_loop") -> str:
    """The markdown lines of :func:`adjusted` for the Chamfer and the observed Chamfer."""
    ch, ob = adjusted(rows, loop, base), adjusted(rows, loop, base, "obs_chamfer")
    lines = ["", f"At equal re-initialisation ({loop} against {base}):", "",
             "| scene | fits | change | observed change | correlation with re-initialisation faces |",
             "|---|---|---|---|---|"]
    for sc, (e, se, n, corr) in ch.items():
        o = f"{ob[sc][0]:+.1f} +- {ob[sc][1]:.1f} %" if sc in ob else "-"
        lines.append(f"| {sc} | {n} | {e:+.1f} +- {se:.1f} % | {o} | {corr:.2f} |")
    return "\n".join(lines)


PAIR_KEYS = (("chamfer", "Chamfer"), ("accuracy", "accuracy"), ("completeness", "completeness"),
             ("obs_chamfer", "observed Chamfer"), ("floater_frac", "floaters"), ("f_score", "F"))
"""The measures :func:`paired` compares, with their column titles."""


def paired(rows: list[dict], loop: str = "default", base: str = "no_loop") -> dict:
    """Per scene, ``loop`` against ``base`` over the pairs of fits that branched from one warm-up (rows with
    the same ``started_from``: ``hard.py --paired`` or ``suite_jobs.sh SPLIT=1``): ``scene -> {"pairs": n,
    "seeds": [...], key: (mean change %, standard error %) for each of PAIR_KEYS, "chamfer_each": [...]}``,
    each change ``100 (loop / base - 1)`` within a pair. Several fits of one variant from one warm-up are
    averaged first; a pair needs both variants; the standard error needs two pairs (``nan`` below)."""
    groups: dict = defaultdict(lambda: defaultdict(list))
    for r in rows:
        if r.get("started_from") and r.get("variant") in (loop, base):
            groups[(r["scene"], r["started_from"])][r["variant"]].append(r)
    by: dict = defaultdict(list)
    for (sc, _), g in sorted(groups.items()):
        if g[loop] and g[base]:
            by[sc].append(g)
    out = {}
    for sc, pairs in by.items():
        res: dict = {"pairs": len(pairs), "seeds": [int(p[loop][0].get("seed") or 0) for p in pairs]}
        for key, _ in PAIR_KEYS:
            d = []
            for p in pairs:
                a = [float(r[key]) for r in p[loop] if r.get(key) is not None]
                b = [float(r[key]) for r in p[base] if r.get(key) is not None]
                if a and b and np.mean(b) != 0:
                    d.append(100 * (np.mean(a) / np.mean(b) - 1))
            if d:
                se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
                res[key] = (float(np.mean(d)), se)
            if key == "chamfer":
                res["chamfer_each"] = d
        out[sc] = res
    return out


def paired_table(rows: list[dict], loop: str = "default", base: str = "no_loop") -> str:
    """The markdown lines of :func:`paired`."""
    pr = paired(rows, loop, base)
    lines = ["", f"Pairs from one warm-up ({loop} against {base}; mean change +- standard error over the pairs):", "",
             "| scene | pairs | " + " | ".join(t for _, t in PAIR_KEYS) + " | Chamfer change per pair |",
             "|---|---|" + "---|" * len(PAIR_KEYS) + "---|"]
    for sc, res in pr.items():
        cells = [f"{res[k][0]:+.1f} +- {res[k][1]:.1f} %" if k in res else "-" for k, _ in PAIR_KEYS]
        each = " ".join(f"{x:+.1f}" for x in res.get("chamfer_each", []))
        lines.append(f"| {sc} | {res['pairs']} | " + " | ".join(cells) + f" | {each} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dirs", nargs="+", help="folders holding the batch's rows.json / h_*.json")
    ap.add_argument("--match", default="", help="only files whose path contains this (a batch's label)")
    ap.add_argument("--loop", default="default", help="the variant measured (default: the plan's loop)")
    ap.add_argument("--base", default="no_loop", help="the variant it is measured against")
    ap.add_argument("--scenes", nargs="*", help="scenes to list, in this order (default: every paired scene)")
    ap.add_argument("--adjust", action="store_true", help="add the effect at equal TSDF re-initialisation")
    ap.add_argument("--pairs", action="store_true",
                    help="add the change within pairs of fits that branched from one warm-up, with its standard error")
    args = ap.parse_args(argv)
    rows = load_rows(args.dirs, args.match)
    print(table(rows, args.loop, args.base, args.scenes))
    if args.adjust:
        print(adjusted_table(rows, args.loop, args.base))
    if args.pairs:
        print(paired_table(rows, args.loop, args.base))


if __name__ == "__main__":
    main()
