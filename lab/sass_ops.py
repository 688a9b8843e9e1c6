"""Instruction mix of wtopo's CUDA kernels (SASS) for one architecture, compiled here without a GPU.

As ``lab/ptxas_report.py``, then ``cuobjdump -sass`` (``CUOBJDUMP``, with ``NVDISASM_PATH`` set: both from PyPI's
nvidia-cuda-cuobjdump and nvidia-cuda-nvdisasm wheels) and a count of the memory, warp and special-function
instructions of each kernel whose name contains the filter.

    CUOBJDUMP=... NVDISASM_PATH=... .venv/bin/python lab/sass_ops.py wtopo.kernels.rasterize render_forward
"""

import collections
import importlib
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import warp as wp


def main():
    module_name, filt = sys.argv[1], sys.argv[2]
    mod = importlib.import_module(module_name)
    with tempfile.TemporaryDirectory() as tmp:
        paths = wp.compile_aot_module(mod, arch=90, module_dir=tmp, use_ptx=True)
        ptx = Path(paths[0]).read_bytes().replace(b"\0", b"").decode()
        ptx = re.sub(r"^\.version \d+\.\d+", ".version 9.0", ptx, count=1, flags=re.M)
        p = Path(tmp) / "m.ptx"
        p.write_text(ptx)
        subprocess.run(["ptxas", "-arch=sm_90", "-o", f"{tmp}/m.cubin", str(p)], check=True)
        sass = subprocess.run([os.environ.get("CUOBJDUMP", "cuobjdump"), "-sass", f"{tmp}/m.cubin"],
                              capture_output=True, text=True, check=True).stdout
    for block in sass.split("Function : ")[1:]:
        name = block.split("\n", 1)[0].strip()
        if filt not in name:
            continue
        ops = re.findall(r"/\*[0-9a-f]{4,}\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_.]*)", block)
        c = collections.Counter(o for o in ops if re.match(r"(LD|ST|RED|ATOM|SHFL|VOTE|MUFU|BAR|WARPSYNC|CALL)", o))
        print(f"{name}: {len(ops)} instructions; " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))


if __name__ == "__main__":
    main()
