# SPDX-License-Identifier: Apache-2.0
"""Lab tool (nothing imports it): registers and stack frame (spills) per kernel of a cubin.

Read from the ELF's ``.nv.info`` sections, so neither CUDA's tools nor a GPU are needed. Compile a kernel module
for a GPU on any machine first (``wp.compile_aot_module(module, arch=90, module_dir=DIR)`` of, for instance,
``wtopo.kernels.rasterize``), then::

    python lab/cubin_regs.py DIR/wp_wtopo.kernels.rasterize_HASH.sm90.cubin [NAME_PART ...]
"""

import struct
import sys

_ATTRS = {0x2F: "regs", 0x11: "frame", 0x12: "stack"}  # EIATTR_REGCOUNT, _FRAME_SIZE, _MIN_STACK_SIZE


def _sections(data: bytes):
    ehdr = struct.unpack_from("<16sHHIQQQIHHHHHH", data, 0)
    shoff, shentsize, shnum, shstrndx = ehdr[6], ehdr[11], ehdr[12], ehdr[13]
    secs = []
    for i in range(shnum):
        f = struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize)
        secs.append([f[0], f[1], f[4], f[5], f[6]])  # name, type, offset, size, link

    def cstr(o: int) -> str:
        return data[o:data.index(b"\0", o)].decode()

    for s in secs:
        s[0] = cstr(secs[shstrndx][2] + s[0])
    return secs, cstr


def kernel_resources(path: str) -> dict:
    """``{symbol: {"regs": n, "frame": bytes, "stack": bytes}}`` of the kernels (and device functions) in a cubin."""
    with open(path, "rb") as fh:
        data = fh.read()
    secs, cstr = _sections(data)
    symtab = next(s for s in secs if s[1] == 2)
    strtab = secs[symtab[4]]
    syms = [cstr(strtab[2] + struct.unpack_from("<I", data, symtab[2] + 24 * k)[0]) for k in range(symtab[3] // 24)]
    out: dict = {}
    for s in secs:
        if not s[0].startswith(".nv.info"):
            continue
        o, end = s[2], s[2] + s[3]
        while o < end:
            fmt, attr = data[o], data[o + 1]
            if fmt == 0x04:  # EIFMT_SVAL: a sized payload
                size = struct.unpack_from("<H", data, o + 2)[0]
                if attr in _ATTRS and size >= 8:
                    sym, val = struct.unpack_from("<II", data, o + 4)
                    out.setdefault(syms[sym] if sym < len(syms) else str(sym), {})[_ATTRS[attr]] = val
                o += 4 + size
            elif fmt == 0x03:  # EIFMT_HVAL
                o += 4
            elif fmt in (0x01, 0x02):
                o += 2 if fmt == 0x01 else 4
            else:
                break
    return out


def main() -> None:
    parts = sys.argv[2:]
    for name, v in sorted(kernel_resources(sys.argv[1]).items()):
        if not parts or any(p in name for p in parts):
            print(f"{v.get('regs', '?'):>4} regs  frame {v.get('frame', '?'):>5}  {name[:110]}")


if __name__ == "__main__":
    main()
