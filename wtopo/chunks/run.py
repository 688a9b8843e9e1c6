# SPDX-License-Identifier: Apache-2.0
"""``torchrun``-launchable chunked fit: ``wtopo fit`` arguments, one process per GPU.

Example (one host, two GPUs)::

    torchrun --nproc-per-node 2 -m wtopo.chunks.run SCENE --out runs/x --chunks 4 --device cuda

Each rank joins the process group (gloo: only a broadcast of the plan and a gather of the reports
travel through it; the fits use their own GPU), fits its chunks on ``cuda:<LOCAL_RANK>`` and rank 0
merges. Without torchrun's environment it runs as ``wtopo fit --chunks ...`` in one process.
"""

from __future__ import annotations

import os
import sys
from datetime import timedelta

__all__ = ["main"]

# Chunk fits of one rank can take hours before the others reach the gather; the default 30 min
# collective timeout would end the run.
_TIMEOUT = timedelta(hours=24)


def main(argv: list[str] | None = None) -> int:
    """Join the torchrun process group (when launched by torchrun) and run ``wtopo fit`` with chunks."""
    import torch.distributed as dist

    from ..cli import main as cli_main

    args = list(sys.argv[1:] if argv is None else argv)
    if not any(a == "--chunks" or a.startswith("--chunks=") for a in args):
        args += ["--chunks", "auto"]
    launched = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if launched and not dist.is_initialized():
        dist.init_process_group("gloo", timeout=_TIMEOUT)
    try:
        code = cli_main(["fit", *args])
        if launched and dist.is_initialized():
            dist.barrier()  # rank 0 merges after the gather: no rank tears its gloo pairs down before it is done
        return code
    finally:
        if launched and dist.is_initialized():
            dist.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())
