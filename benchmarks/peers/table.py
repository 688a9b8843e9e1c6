# SPDX-License-Identifier: Apache-2.0
"""The peers table: score rows (``score.py``) as Markdown, one block per scene, the best of each column in bold.

python benchmarks/peers/table.py rows.json [rows2.json ...]
"""

from __future__ import annotations

import json
import sys

# (key, header, format, better): better is min, max or None (not ranked)
COLUMNS = [
    ("roi_f1", "ROI F1", "{:.3f}", max),
    ("roi_precision", "ROI P", "{:.3f}", max),
    ("roi_recall", "ROI R", "{:.3f}", max),
    ("chamfer_pct", "Chamfer %", "{:.3f}", min),
    ("f_score", "F", "{:.3f}", max),
    ("accuracy_pct", "acc. %", "{:.3f}", min),
    ("completeness_pct", "comp. %", "{:.3f}", min),
    ("psnr", "PSNR dB", "{:.2f}", max),
    ("ssim", "SSIM", "{:.3f}", max),
    ("silhouette_iou", "mask IoU", "{:.3f}", max),
    ("wall_s", "time s", "{:.0f}", min),
    ("peak_gpu_gib", "GPU GiB", "{:.2f}", min),
    ("faces", "faces", "{:,}", None),
    ("watertight", "closed", "{}", None),
]


def table(rows: list[dict]) -> str:
    """Markdown for ``rows`` (dicts with ``scene``, ``system`` and the COLUMNS' keys; absent keys are blank)."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        block = [r for r in rows if r["scene"] == scene]
        cols = [c for c in COLUMNS if any(r.get(c[0]) is not None for r in block)]
        on = {r.get("psnr_on") for r in block if r.get("psnr_on")}
        out.append(f"**{scene}**" + (f" (PSNR / SSIM on the {'masks' if on == {'masks'} else 'whole image'})"
                                      if on else ""))
        out.append("")
        out.append("| system | " + " | ".join(c[1] for c in cols) + " |")
        out.append("|---|" + "---|" * len(cols))
        best = {}
        for key, _, _, better in cols:
            vals = [r[key] for r in block if r.get(key) is not None]
            if better and len(vals) > 1:
                best[key] = better(vals)
        for r in block:
            cells = []
            for key, _, fmt, _ in cols:
                v = r.get(key)
                if v is None:
                    cells.append("")
                    continue
                s = fmt.format(v)
                cells.append(f"**{s}**" if key in best and v == best[key] else s)
            out.append(f"| {r['system']} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> None:
    rows = []
    for path in (argv if argv is not None else sys.argv[1:]):
        with open(path) as f:
            rows += json.load(f)
    print(table(rows))


if __name__ == "__main__":
    main()
