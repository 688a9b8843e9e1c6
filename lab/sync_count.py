"""Count the host synchronisations torch reports per fit iteration on CUDA (a lab script).

    python lab/sync_count.py EXCH [--set KEY=VALUE ...]

Runs a short fit with ``torch.cuda.set_sync_debug_mode("warn")`` and prints, per source line, how many
synchronising calls torch saw, and their total divided by the iteration count. Warp's own synchronisations
(``wp.synchronize``, host reads of Warp arrays) are not seen by torch's mode."""
import collections
import os
import sys
import traceback
import warnings

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "peers"))


def main():
    ex_dir, *rest = sys.argv[1:]
    from exchange import load

    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig

    cfg = FitConfig()
    for item in [rest[i + 1] for i in range(len(rest)) if rest[i] == "--set"] + ["runtime.device=cuda:0"]:
        _apply_set(cfg, item)
    counts = collections.Counter()
    root = os.path.dirname(os.path.dirname(wtopo.__file__))

    def hook(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" not in str(message):
            return
        stack = [f for f in traceback.extract_stack()[:-1]
                 if f.filename.startswith(root) and "/torch/" not in f.filename]
        where = f"{os.path.relpath(stack[-1].filename, root)}:{stack[-1].lineno}" if stack else filename
        counts[where] += 1

    warnings.showwarning = hook
    warnings.simplefilter("always")
    torch.cuda.set_sync_debug_mode("warn")
    res = wtopo.fit(load(ex_dir).scene(), cfg, out_dir="/tmp/sync_count_run", progress=False)
    torch.cuda.set_sync_debug_mode(0)
    its = res.report.get("iterations") or 1
    for where, n in counts.most_common(40):
        print(f"{n:8d}  {n / its:7.2f}/it  {where}")
    print(f"total {sum(counts.values())} over {its} iterations: {sum(counts.values()) / its:.2f} per iteration")


if __name__ == "__main__":
    main()
