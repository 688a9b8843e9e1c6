"""The CUDA branches of the rasterizer's warp helpers, run on the CPU under an emulated warp (``simt_harness``).

``warp_add_grads`` (a surfel's 22 gradient values summed over the warp by a transposed shuffle reduction, then one
atomic add per value by its own lane) and ``warp_count`` (a ballot) only run in a CUDA build; CI has no GPU. Their
own snippets are compiled as C++ with 32 threads standing in for a warp's lanes, and what they add is compared with
NumPy's sums, in float32 and float64, with and without ``coop``.
"""

import subprocess

import numpy as np
import pytest
from simt_harness import SHIMS, build, function_source

from wtopo.kernels import rasterize_warp as W

SLOTS = {  # warp_add_grads' values in slot order: (name, width), GRAD_SLOTS in all
    "c_color": 3, "c_nf": 3, "c_op": 1, "c_auv": 3, "c_uax": 3, "c_vax": 3, "c_nrm": 3, "c_m2": 2, "c_zc": 1}
TARGET = {"c_color": "d_color", "c_nf": "d_nrm_face", "c_op": "d_opacity", "c_auv": "d_auv", "c_uax": "d_uax",
          "c_vax": "d_vax", "c_nrm": "d_nrm", "c_m2": "d_m2", "c_zc": "d_zc"}
ROWS, COLS, ROW, COL = 2, 5, 1, 3  # the gradient buffers' shape and the (worker, surfel) entry added to


def _cxx_type(name: str, f: str) -> str:
    """The C++ type of a helper's argument, by its name (the helpers' names follow the kernels' roles)."""
    if name in ("w", "i", "coop", "lane", "nb", "mine", "j", "q"):
        return "int"
    if name in ("own", "branch3d", "hit"):
        return "bool"
    if name in ("c_op", "c_zc", "like"):
        return f
    if name == "c_m2":
        return f"wp::vec_t<2, {f}>"
    if name.startswith("c_"):
        return f"wp::vec_t<3, {f}>"
    if name == "dest":
        return "wp::array_t<wp::int32>"
    if name in ("d_opacity", "d_zc", "opacity"):
        return f"wp::array_t<{f}>"
    if name == "d_m2":
        return f"wp::array_t<wp::vec_t<2, {f}>>"
    if name.startswith("d_"):
        return f"wp::array_t<wp::vec_t<3, {f}>>"
    raise KeyError(name)


def _function(fn, f: str, ret: str = "void") -> str:
    params = [(_cxx_type(n, f), n) for n in fn.input_types]
    return function_source(fn.key.rsplit(".", 1)[-1], fn.native_snippet, ret, params)


def _values(rng, f: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per lane: 22 values (zero where the lane has no contribution, as the kernel passes), own, branch3d."""
    own = rng.random(32) < 0.6
    own[0] = own[31] = True
    b3 = rng.random(32) < 0.5
    vals = rng.normal(size=(32, W.GRAD_SLOTS)) * np.where(own, 1.0, 0.0)[:, None]
    # a lane's 3D-branch values are zero in the filter branch and the reverse (the kernel's c_* start at zero)
    vals[:, 7:19] *= b3[:, None]
    vals[:, 19:22] *= ~b3[:, None]
    vals[:, 13] = 0.0  # a slot whose warp sum is zero: no atomic add at all
    return vals.astype(np.float32 if f == "float" else np.float64), own, b3


def _driver(f: str, vals: np.ndarray, own: np.ndarray, b3: np.ndarray, coop: int) -> str:
    lines = [f"static const {f} VALS[32][{W.GRAD_SLOTS}] = {{"]
    lines += ["  {" + ", ".join(repr(float(v)) for v in row) + "}," for row in vals]
    lines.append("};")
    lines.append("static const bool OWN[32] = {" + ", ".join("true" if o else "false" for o in own) + "};")
    lines.append("static const bool B3[32] = {" + ", ".join("true" if o else "false" for o in b3) + "};")
    bufs = []
    for c, width in SLOTS.items():
        d = TARGET[c]
        bufs.append(f"  std::vector<{f}> {d}_mem({ROWS * COLS * width});")
        elem = f if width == 1 else f"wp::vec_t<{width}, {f}>"
        bufs.append(f"  auto {d} = view(reinterpret_cast<{elem}*>({d}_mem.data()), {ROWS}, {COLS});")
    vec_args, k = [], 0
    for width in SLOTS.values():
        if width == 1:
            vec_args.append(f"VALS[l][{k}]")
        else:
            vec_args.append(f"wp::vec_t<{width}, {f}>(" + ", ".join(f"VALS[l][{k + m}]" for m in range(width)) + ")")
        k += width
    call = (f"warp_add_grads({ROW}, {COL}, {', '.join(vec_args)}, "
            + ", ".join(TARGET[c] for c in SLOTS) + f", OWN[l], B3[l], {coop});")
    prints = [f'  std::printf("{TARGET[c]}"); for (auto v : {TARGET[c]}_mem) std::printf(" %.17g", double(v)); '
              'std::printf("\\n");' for c in SLOTS]
    count = [
        "  std::vector<wp::int32> cnt(ROWS_COLS, 0);".replace("ROWS_COLS", str(ROWS * COLS)),
        f"  auto dest = view(cnt.data(), {ROWS}, {COLS});",
        f"  run_warp(1, [&](int l) {{ warp_count(dest, {ROW}, {COL}, OWN[l], {coop}); }});",
        '  std::printf("count"); for (auto v : cnt) std::printf(" %d", v); std::printf("\\n");',
    ]
    return "\n".join([*lines, "int main() {", *bufs, f"  run_warp(1, [&](int l) {{ {call} }});", *prints, *count,
                      "  return 0;", "}"])


def _expected(vals: np.ndarray, own: np.ndarray, b3: np.ndarray, coop: int) -> dict:
    out, k = {}, 0
    for c, width in SLOTS.items():
        part = vals[:, k:k + width].astype(np.float64)
        if not coop:  # each lane adds its own, where it owns them (3D terms in the 3D branch, the filter's not)
            take = own & (b3 if 7 <= k < 19 else ~b3 if k >= 19 else True)
            part = part * take[:, None]
        buf = np.zeros((ROWS, COLS, width))
        buf[ROW, COL] = part.sum(axis=0)
        out[TARGET[c]] = buf.reshape(-1)
        k += width
    cnt = np.zeros((ROWS, COLS))
    cnt[ROW, COL] = own.sum()
    out["count"] = cnt.reshape(-1)
    return out


@pytest.mark.parametrize("coop", [1, 0])
@pytest.mark.parametrize("f", ["float", "double"])
def test_warp_add_grads_and_count_sum_the_warp(tmp_path, f, coop):
    """Add the warp's sum of every gradient slot to its own entry (one add per non-zero slot) and count the lanes
    that hit; without ``coop``, each lane's own terms."""
    rng = np.random.default_rng(7 if f == "float" else 8)
    vals, own, b3 = _values(rng, f)
    src = "\n".join([SHIMS, _function(W.warp_add_grads, f), _function(W.warp_count, f),
                     _driver(f, vals, own, b3, coop)])
    exe = build(src, tmp_path / "grads")
    if exe is None:
        pytest.skip("no g++ to build the warp emulation")
    res = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60, check=True)
    got = {line.split()[0]: np.array([float(x) for x in line.split()[1:]]) for line in res.stdout.splitlines()}
    want = _expected(vals, own, b3, coop)
    rtol = 1e-5 if f == "float" else 1e-12
    for name, w in want.items():
        np.testing.assert_allclose(got[name], w, rtol=rtol, atol=rtol, err_msg=name)
    assert np.count_nonzero(got["d_vax"]) == 2  # slot 13 (vax's first component) summed to zero: never added


def _overload(fn, f: str):
    """The float32 or float64 overload of a helper (``f``: its C++ float type)."""
    if not fn.user_overloads:
        return fn
    tag = "f4" if f == "float" else "f8"
    return next(o for sig, o in fn.user_overloads.items() if tag in sig)


def _staging_driver(f: str, geo: np.ndarray, opacity: np.ndarray, batches: list[np.ndarray], coop: int) -> str:
    n = geo.shape[0]
    q = "wp::vec4" if f == "float" else "wp::vec4d"
    lines = [f"static {f} GEO[{n} * 16] = {{" + ", ".join(repr(float(v)) for v in geo.reshape(-1)) + "};",
             f"static {f} OPA[{n}] = {{" + ", ".join(repr(float(v)) for v in opacity) + "};", "int main() {",
             f"  auto geo4 = view(reinterpret_cast<{q}*>(GEO), {n}, 4);",
             f"  auto opacity = view(OPA, 1, {n}); opacity.strides[0] = sizeof({f});",
             "  static int IDS[32];"]
    for b, ids in enumerate(batches):
        nb = len(ids)
        lines += [f"  {{ const int ids[{nb}] = {{" + ", ".join(str(int(i)) for i in ids) + "};",
                  f"    std::vector<{f}> out(32 * {nb} * 17);",
                  "    run_warp(3, [&](int l) {",
                  f"      const wp::uint64 slab = staging_slab({f}(0));",
                  # coop: lane l stages surfel l of the batch, then reads every surfel j from slot j; else each
                  # thread stages its own (lane 0 of a batch of 1) and reads it at every step
                  f"      const int mine = {coop} ? (l < {nb} ? ids[l] : 0) : ids[l % {nb}];",
                  f"      stage_batch(slab, geo4, opacity, mine, {coop} ? l : 0, {coop} ? {nb} : 1, {coop});",
                  f"      for (int j = 0; j < {nb}; ++j) {{",
                  f"        {f}* o = &out[(l * {nb} + j) * 17];",
                  f"        const int i = {coop} ? ids[j] : mine, jj = {coop} ? j : 0;",
                  "        for (int k = 0; k < 4; ++k) {",
                  f"          const {q} v = staged_quad(slab, geo4, i, jj, k, {coop});",
                  "          for (int m = 0; m < 4; ++m) o[4 * k + m] = v[m];",
                  "        }",
                  f"        o[16] = staged_opacity(slab, geo4, opacity, i, jj, {coop});",
                  "      }",
                  "    });",
                  f'    std::printf("batch{b}"); for (auto v : out) std::printf(" %.17g", double(v)); '
                  'std::printf("\\n"); }']
    return "\n".join([*lines, "  return 0;", "}"])


@pytest.mark.parametrize("coop", [1, 0])
@pytest.mark.parametrize("f", ["float", "double"])
def test_staged_records_are_the_batch_surfels(tmp_path, f, coop):
    """With ``coop`` every lane reads, at step j, surfel ids[j]'s four quads and opacity from its warp's shared slots
    after ``stage_batch`` (lanes past the batch stage nothing; a second batch overwrites the first); without it each
    thread reads back the surfel it staged in its own slot."""
    rng = np.random.default_rng(9)
    dt = np.float32 if f == "float" else np.float64
    geo = rng.normal(size=(40, 16)).astype(dt)
    opacity = rng.random(40).astype(dt)
    batches = [rng.choice(40, size=27, replace=False), rng.choice(40, size=32, replace=False)]
    quads = "wp::array_t<wp::vec4>" if f == "float" else "wp::array_t<wp::vec4d>"
    typed = {"slab": "wp::uint64", "geo4": quads, "quad": quads}

    def cxx(name):
        return typed.get(name) or _cxx_type(name, f)

    funcs = []
    for fn, ret in ((W.staging_slab, "wp::uint64"), (W.stage_batch, "void"),
                    (W.staged_quad, "wp::vec4" if f == "float" else "wp::vec4d"), (W.staged_opacity, f)):
        o = _overload(fn, f)
        funcs.append(function_source(fn.key, o.native_snippet, ret, [(cxx(n), n) for n in o.input_types]))
    exe = build("\n".join([SHIMS, *funcs, _staging_driver(f, geo, opacity, batches, coop)]), tmp_path / "stage")
    if exe is None:
        pytest.skip("no g++ to build the warp emulation")
    res = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60, check=True)
    for b, line in enumerate(res.stdout.splitlines()):
        ids = batches[b]
        got = np.array([float(x) for x in line.split()[1:]]).reshape(32, len(ids), 17)
        rec = np.concatenate([geo, opacity[:, None]], axis=1)
        for lane in range(32):
            want = rec[ids] if coop else np.repeat(rec[ids[lane % len(ids)]][None], len(ids), axis=0)
            np.testing.assert_array_equal(got[lane], want, err_msg=f"batch {b}, lane {lane}")
