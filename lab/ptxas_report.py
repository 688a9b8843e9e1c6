"""Registers, spills and stack of wtopo's CUDA kernels for one architecture, compiled here without a GPU.

Warp compiles a module to PTX with its own NVRTC (``wp.compile_aot_module``); the machine's ptxas then
assembles it with ``-v``. Warp's NVRTC writes a newer PTX ISA version than this ptxas (CUDA 13.0) reads,
so the header is rewritten to 9.0 (the kernels use nothing newer). Each entry is labelled with its
kernel name and the float type of its first float argument.

    .venv/bin/python lab/ptxas_report.py wtopo.kernels.rasterize_backward wtopo.kernels.rasterize [--arch 90]
"""

import argparse
import importlib
import re
import subprocess
import tempfile
from pathlib import Path

import warp as wp


def report(module_name: str, arch: int) -> list[tuple]:
    mod = importlib.import_module(module_name)
    with tempfile.TemporaryDirectory() as tmp:
        paths = wp.compile_aot_module(mod, arch=arch, module_dir=tmp, use_ptx=True)
        ptx = Path(paths[0]).read_bytes().replace(b"\0", b"").decode()
        ptx = re.sub(r"^\.version \d+\.\d+", ".version 9.0", ptx, count=1, flags=re.M)
        src = next(Path(tmp).glob("*.cu")).read_text()
        p = Path(tmp) / "m.ptx"
        p.write_text(ptx)
        out = subprocess.run(["ptxas", f"-arch=sm_{arch}", "-v", "-o", "/dev/null", str(p)], capture_output=True,
                             text=True).stderr
    rows = []
    for m in re.finditer(r"Compiling entry function '(\w+)'.*?\n.*?\n\s+(\d+) bytes stack frame, (\d+) bytes spill "
                         r"stores, (\d+) bytes spill loads\n.*?Used (\d+) registers", out):
        name, stack, st, ld, regs = m.groups()
        sig = re.search(re.escape(name) + r"\((.*?)\)", src, re.S)
        ftype = "float64" if sig and "float64" in sig.group(1) else "float32"
        rows.append((name.split("_cuda_kernel")[0], ftype, int(regs), int(stack), int(st), int(ld)))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("modules", nargs="+")
    ap.add_argument("--arch", type=int, default=90)
    a = ap.parse_args()
    print(f"{'kernel':<52} {'dtype':<8} {'regs':>5} {'stack B':>8} {'spill st':>9} {'spill ld':>9}")
    for name in a.modules:
        for k, ft, regs, stack, st, ld in report(name, a.arch):
            print(f"{k:<52} {ft:<8} {regs:>5} {stack:>8} {st:>9} {ld:>9}")


if __name__ == "__main__":
    main()
