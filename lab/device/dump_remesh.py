"""benchmarks/peers/run_wtopo.py with the final Poisson re-mesh's input and output saved (#59: in runs of bunny64
alone on an H100 the fused mesh came out open, and in one of them the re-mesh's hole fill sagged up to 3 % of the
diagonal inside the truth; rows_2026-12-07c). Same arguments as run_wtopo.py; writes $OUT/remesh_in.npz and
$OUT/remesh_out.npz (``v`` [V, 3] float32, ``f`` [F, 3] int32, the fit's internal frame: report.json's
``normalization`` maps them back) when the re-mesh runs. For lab/gap_regions.py and a hole-fill study offline."""
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "benchmarks", "peers"))


def _save(path, mesh):
    np.savez_compressed(path, v=np.asarray(mesh.vertices, np.float32), f=np.asarray(mesh.faces, np.int32))


if __name__ == "__main__":
    from wtopo.fitting import _final_mesh as fm

    out, remesh = os.environ["OUT"], fm.poisson_remesh

    def dumped(mesh, cfg, **kw):
        _save(os.path.join(out, "remesh_in.npz"), mesh)
        res = remesh(mesh, cfg, **kw)
        _save(os.path.join(out, "remesh_out.npz"), res)
        return res

    fm.poisson_remesh = dumped
    import run_wtopo

    run_wtopo.main(sys.argv[1:])
