# SPDX-License-Identifier: Apache-2.0
"""Run a peer's script as ``__main__`` and record its peak torch GPU memory.

python _peak.py OUT.json SCRIPT ARGS...
"""

import atexit
import json
import os
import runpy
import sys

import torch


def _write(path: str) -> None:
    peak = torch.cuda.max_memory_allocated() if torch.cuda.is_available() else 0
    with open(path, "w") as f:
        json.dump({"peak_gpu_bytes": int(peak)}, f)


if __name__ == "__main__":
    out, script = sys.argv[1], sys.argv[2]
    atexit.register(_write, out)
    sys.argv = [script, *sys.argv[3:]]
    sys.path.insert(0, os.getcwd())
    runpy.run_path(script, run_name="__main__")
