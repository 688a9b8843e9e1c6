# SPDX-License-Identifier: Apache-2.0
"""The peers benchmark's exchange folder and its one scorer (``benchmarks/peers/``), on the CPU: a scene
written and read back, a perfect result scoring as one, and a shifted render and a scaled mesh scoring
worse in the measures they should move (held-out PSNR per view, Chamfer, F, silhouette IoU)."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

PEERS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "peers")
sys.path.insert(0, PEERS)

from _result import write_result  # noqa: E402
from exchange import export, load  # noqa: E402
from peers_fakes import fake_pgsr, small_exchange  # noqa: E402
from score import render_pictures, score  # noqa: E402


@pytest.fixture(scope="module")
def exch(tmp_path_factory):
    return small_exchange(tmp_path_factory)


def _result(ex, out, *, renders=None, mesh=None):
    renders = np.stack([ex.image(i) for i in ex.test]) if renders is None else renders
    write_result(str(out), system="test", mesh=ex.gt() if mesh is None else mesh, renders=renders,
                 run={"wall_s": 1.0, "iterations": 1})
    return score(ex.root, str(out))


def test_the_exchange_folder_reads_back(exch):
    """Train and test views split as asked, images, masks, cameras and ground truth present and consistent."""
    assert exch.meta["name"] == "bunny16" and exch.meta["masked"] and exch.meta["gt"]
    assert exch.test == [0, 4, 8, 12] and len(exch.train) == 12 and not set(exch.test) & set(exch.train)
    img, m = exch.image(exch.test[0]), exch.mask(exch.test[0])
    assert img.shape == (exch.height, exch.width, 3) and m.shape == img.shape[:2] and 0 < m.mean() < 1
    sparse = os.path.join(exch.root, "colmap", "sparse", "0")
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert os.path.isfile(os.path.join(sparse, name)), name
    # the peers train on the training views only: COLMAP's images are those
    assert len(os.listdir(os.path.join(exch.root, "colmap", "images"))) == len(exch.train)
    gt = exch.gt()
    cam = exch.camera(exch.test[0])
    uv, z = cam.project(np.asarray(gt.vertices))
    assert (z > 0).all()  # the object lies in front of a held-out camera, in the exchange's frame


def test_a_perfect_result_scores_as_one(exch, tmp_path):
    row = _result(exch, tmp_path / "perfect")
    assert row["scene"] == "bunny16" and row["psnr_on"] == "masks"
    assert len(row["psnr_views"]) == len(exch.test) and row["psnr"] > 45  # float16 storage of the renders
    assert row["ssim"] > 0.999 and row["f_score"] > 0.999 and row["chamfer_pct"] < 0.05
    assert row["silhouette_iou"] > 0.9 and row["watertight"] == exch.gt().is_watertight


def test_a_shifted_render_and_a_scaled_mesh_score_worse(exch, tmp_path):
    perfect = _result(exch, tmp_path / "perfect")
    shifted = np.stack([np.roll(exch.image(i), 2, axis=1) for i in exch.test])
    gt = exch.gt().copy()
    gt.apply_scale(1.05)  # about the frame's origin: moved and grown
    row = _result(exch, tmp_path / "worse", renders=shifted, mesh=gt)
    assert all(a < b - 5 for a, b in zip(row["psnr_views"], perfect["psnr_views"]))
    assert row["chamfer_pct"] > 20 * perfect["chamfer_pct"] and row["f_score"] < perfect["f_score"]
    assert row["silhouette_iou"] < perfect["silhouette_iou"]


def test_the_render_pictures_show_each_view_and_where_a_system_errs(exch, tmp_path):
    """One row per held-out view (photo, each render, each error); a perfect render's error tile is black and a
    shifted one's is not."""
    from PIL import Image

    _result(exch, tmp_path / "perfect")
    shifted = np.stack([np.roll(exch.image(i), 2, axis=1) for i in exch.test])
    _result(exch, tmp_path / "worse", renders=shifted)
    path = render_pictures(exch.root, [str(tmp_path / "perfect"), str(tmp_path / "worse")], str(tmp_path / "pics"))
    pic = np.asarray(Image.open(path).convert("RGB"), np.float32) / 255
    h, w = exch.height, exch.width
    assert pic.shape == (len(exch.test) * h, 5 * w, 3)  # photo, two renders, two errors
    label = (slice(0, 20), slice(0, w))  # the text drawn in a tile's corner
    for k in range(len(exch.test)):
        row = pic[k * h:(k + 1) * h]
        tiles = [row[:, j * w:(j + 1) * w].copy() for j in range(5)]
        for t in tiles:
            t[label] = 0
        assert np.abs(tiles[1] - tiles[0]).max() < 0.02  # the perfect render is the photo
        assert tiles[3].max() < 0.02 < tiles[4].max()  # its error is black; the shifted render's is not


def test_wtopo_s_held_out_renders_score_as_its_own_evaluation(exch, tmp_path):
    """``run_wtopo.py`` renders the held-out views as the fit does (its screen-space filter, its background): the
    scorer's PSNR of those renders is the fit's own report's, on the same views inside the same masks."""
    import json

    import run_wtopo

    out = tmp_path / "wtopo"
    run_wtopo.main([exch.root, str(out), "--device", "cpu", "--set", "preset=fast", "--set", "warmup.iterations=40",
                    "--set", "coevolution.iterations=40", "--set", "runtime.usd_every=0"])
    own = json.loads((out / "run.json").read_text())["own_report"]["psnr"]
    row = score(exch.root, str(out))
    assert row["psnr_on"] == "masks" and np.isfinite(own)
    assert abs(row["psnr"] - own) < 0.05, (row["psnr"], own)  # float16 storage of the renders


@pytest.fixture(scope="module")
def exch_env(tmp_path_factory):
    """The unbounded ``mug_torus_env`` of the benchmark's own scenes, at a size for a test."""
    import scenes as peer_scenes

    root = str(tmp_path_factory.mktemp("exch") / "env")
    scene = peer_scenes.load("mug_torus_env", n_views=9, resolution=(48, 36), n_test=2)
    export(scene, root, n_points=500)
    return load(root), scene


def test_an_unbounded_scene_carries_its_region_of_interest(exch_env):
    """The box the ROI F-score is taken over reaches the exchange's frame: it holds the objects' truth there."""
    ex, scene = exch_env
    assert not ex.masked and ex.meta["gt"] and len(ex.test) == 2
    lo, hi = ex.roi()
    sim = scene.normalization()
    want = [sim.to_internal(np.asarray(b, np.float64)) for b in scene.info["roi"]]
    np.testing.assert_allclose(lo, want[0], atol=1e-9)
    np.testing.assert_allclose(hi, want[1], atol=1e-9)
    v = np.asarray(ex.gt().vertices)
    inside = np.all((v >= lo) & (v <= hi), axis=1)
    assert 0 < inside.mean() < 1  # the truth runs past the box (ground, hills): only the box is scored


def test_the_roi_score_of_the_truth_is_one_and_of_a_moved_mesh_lower(exch_env, tmp_path):
    ex, _ = exch_env
    perfect = _result(ex, tmp_path / "perfect")
    assert perfect["psnr_on"] == "image" and perfect["roi_f1"] > 0.999 and "chamfer_pct" not in perfect
    moved = ex.gt().copy()
    lo, hi = ex.roi()
    moved.apply_translation([0.0, 0.0, 0.02 * float(np.linalg.norm(hi - lo))])  # 4 tau up
    row = _result(ex, tmp_path / "moved", mesh=moved)
    # the ground and every horizontal face miss by 4 tau; the sides of the mug and the torus slide along themselves
    assert row["roi_f1"] < 0.6 and row["roi_precision"] < 0.6 and row["roi_recall"] < 0.6


def test_the_authors_mesh_stage_starts_from_an_earlier_warmup(exch, tmp_path, monkeypatch):
    """``run_pgsr.py --from-warmup``: the mesh stage of the TopoSurfel authors' code, in a second lease, from an
    earlier ``--no-mesh-stage`` run's result folder. No warm-up trains again, the mesh stage starts from that
    warm-up's TSDF mesh, and its time and peak memory count in the result's."""
    import json

    for name in ("pgsr_dpsr", "pgsr_init"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "train.py").write_text("")
    ck = ["--checkout", str(tmp_path / "pgsr_dpsr"), "--init-checkout", str(tmp_path / "pgsr_init")]
    calls = []
    run_pgsr = fake_pgsr(monkeypatch, calls, mesh_scale=0.5)
    run_pgsr.main([exch.root, str(tmp_path / "warm"), *ck, "--no-mesh-stage", "--warmup-iterations", "300"])
    first = json.loads((tmp_path / "warm" / "run.json").read_text())
    assert first["warmup_iterations"] == 300 and first["mesh_stage_iterations"] is None
    assert [c[0] for c in calls] == ["pgsr_init"] * 3  # train, mesh, held-out views of plain PGSR
    first["wall_s"] = 1234.0  # as if the warm-up had taken a lease's worth
    first["peak_gpu_bytes"] = 5000  # and more memory than the mesh stage
    (tmp_path / "warm" / "run.json").write_text(json.dumps(first))

    calls.clear()
    run_pgsr = fake_pgsr(monkeypatch, calls, mesh_scale=2.0)
    run_pgsr.main([exch.root, str(tmp_path / "whole"), *ck, "--from-warmup", str(tmp_path / "warm"),
                   "--iterations", "100"])
    assert [c[0] for c in calls] == ["pgsr_dpsr"] * 3  # no warm-up: the mesh stage, its mesh, its views
    train = calls[0][1]
    assert train[3] == "train.py" and train[train.index("--iterations") + 1] == "100"
    src = train[train.index("-s") + 1]
    with open(os.path.join(src, "mesh_init.ply"), "rb") as f, \
            open(tmp_path / "warm" / "warmup" / "mesh" / "tsdf_fusion_post.ply", "rb") as g:
        assert f.read() == g.read()  # the earlier warm-up's mesh, as it left it
    whole = json.loads((tmp_path / "whole" / "run.json").read_text())
    assert whole["warmup_iterations"] == 300 and whole["mesh_stage_iterations"] == 100
    assert whole["iterations"] == 400 and whole["system"] == "PGSR+DPSR (authors', 300 + 100 it.)"
    assert whole["wall_s"] >= 1234.0 and whole["warmup_train_s"] == first["warmup_train_s"]
    assert whole["peak_gpu_bytes"] == 5000 and "an earlier run" in whole["warmup_from"]
    assert not (tmp_path / "whole" / "warmup").exists()  # nothing of the warm-up was run or copied here
    assert "device" in whole and "warmup_device" in whole  # which GPU each stage ran on (None on this CPU machine)

    # a short check of the DPSR half: more mesh-stage arguments, named in the system; no warm-up checkout needed
    calls.clear()
    ck_no_init = ["--checkout", str(tmp_path / "pgsr_dpsr"), "--init-checkout", str(tmp_path / "absent")]
    run_pgsr.main([exch.root, str(tmp_path / "smoke"), *ck_no_init, "--from-warmup", str(tmp_path / "warm"),
                   "--iterations", "100", "--mesh-train-args", "--mesh_from_iter 20"])
    train = calls[0][1]
    assert train[-2:] == ["--mesh_from_iter", "20"] and "--mesh_from_iter" not in calls[1][1]  # not render.py
    smoke = json.loads((tmp_path / "smoke" / "run.json").read_text())
    assert smoke["system"] == "PGSR+DPSR (authors', 300 + 100 it.) [--mesh_from_iter 20]"
    assert smoke["mesh_train_args"] == "--mesh_from_iter 20"
    with pytest.raises(SystemExit) as e:  # the warm-up alone has no mesh stage to pass them to
        run_pgsr.main([exch.root, str(tmp_path / "o"), *ck, "--no-mesh-stage", "--mesh-train-args", "--x 1"])
    assert e.value.code == 2

    # the DPSR grids kept on the GPU: the mesh stage's train.py runs under _dpsr_cache.py, render.py does not
    calls.clear()
    run_pgsr.main([exch.root, str(tmp_path / "cached"), *ck, "--from-warmup", str(tmp_path / "warm"),
                   "--iterations", "100", "--cache-dpsr-grids"])
    train, render = calls[0][1], calls[1][1]
    assert train[3].endswith("_dpsr_cache.py") and train[4] == "train.py" and render[3] == "render.py"
    cached = json.loads((tmp_path / "cached" / "run.json").read_text())
    assert cached["system"] == "PGSR+DPSR (authors', 300 + 100 it.) [DPSR grids on the GPU]"
    assert cached["dpsr_grids_cached"] is True and cached["peak_gpu_bytes"] == 5000
    with pytest.raises(SystemExit) as e:
        run_pgsr.main([exch.root, str(tmp_path / "o"), *ck, "--no-mesh-stage", "--cache-dpsr-grids"])
    assert e.value.code == 2


# The authors' DPSR forward as it handles its grids (``nvdiffrast_utils/dpsr.py``): the frequency grid made anew
# on the CPU each call, scaled in place, moved to the points' device, and the filter moved there each call too.
_FAKE_DPSR = '''
import numpy as np
import torch

MADE = [0]


def fftfreqs(res, dtype=torch.float32, exact=True):
    MADE[0] += 1
    f = [torch.tensor(np.fft.fftfreq(r, d=1 / r), dtype=dtype) for r in res[:-1]]
    f.append(torch.tensor(np.fft.rfftfreq(res[-1], d=1 / res[-1]), dtype=dtype))
    return torch.stack(torch.meshgrid(f, indexing="ij"), dim=-1)


class DPSR(torch.nn.Module):
    def __init__(self, res, sig=2.0):
        super().__init__()
        self.res = res
        w = fftfreqs(res, dtype=torch.float64)
        self.G = torch.exp(-0.5 * (sig * 2 * w.norm(dim=-1) / res[0]) ** 2).float()[..., None, None]
        self.omega = fftfreqs(res)

    def forward(self, V, N):
        idx = (V.clamp(0, 0.999) * torch.tensor(self.res, dtype=V.dtype, device=V.device)).long()
        flat = (idx[..., 0] * self.res[1] + idx[..., 1]) * self.res[2] + idx[..., 2]
        grid = torch.zeros(V.shape[0], 3, int(np.prod(self.res)), dtype=V.dtype, device=V.device)
        grid = grid.index_add(2, flat[0], N[0].T[None]).view(V.shape[0], 3, *self.res)
        spec = torch.fft.rfftn(grid, dim=(2, 3, 4)).permute(0, 2, 3, 4, 1)[..., None] * self.G.to(V.device)
        omega = fftfreqs(self.res, dtype=torch.float32).unsqueeze(-1)
        omega *= 2 * np.pi
        omega = omega.to(V.device)
        div = (1j * spec[..., 0] * omega[..., 0]).sum(-1)
        phi = div / (-(omega[..., 0] ** 2).sum(-1) + 1e-6)
        return torch.fft.irfftn(phi, s=self.res, dim=(1, 2, 3))
'''


def _fake_dpsr_package(root):
    (root / "nvdiffrast_utils").mkdir()
    (root / "nvdiffrast_utils" / "__init__.py").write_text("")
    (root / "nvdiffrast_utils" / "dpsr.py").write_text(_FAKE_DPSR)


def test_the_dpsr_grid_cache_gives_the_authors_values_and_gradients(tmp_path, monkeypatch, device):
    """``_dpsr_cache.install``: the patched forward returns the same field and gradients as the authors' on
    every call (the in-place scaling does not reach the cache), for two grids of different resolutions, builds
    each grid once, moves the filter to the points' device once, and leaves ``__init__``'s own grid alone;
    installing twice changes nothing. The points sit in distinct cells, so no two scatter into one sum and the
    forward is deterministic on any device."""
    import importlib

    import _dpsr_cache
    import torch

    _fake_dpsr_package(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("nvdiffrast_utils", "nvdiffrast_utils.dpsr"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    dpsr = importlib.import_module("nvdiffrast_utils.dpsr")
    gen = torch.Generator().manual_seed(0)

    def inputs(res):
        cells = torch.randperm(int(np.prod(res)), generator=gen)[:40]
        ijk = torch.stack([cells // (res[1] * res[2]), cells // res[2] % res[1], cells % res[2]], -1)
        V = ((ijk + 0.5) / torch.tensor(res))[None].to(device)
        N = torch.nn.functional.normalize(torch.randn(1, 40, 3, generator=gen), dim=-1).to(device)
        return V, N.requires_grad_()

    def field(model, V, N):
        N.grad = None
        phi = model(V, N)
        (phi * torch.linspace(-1, 1, phi.numel(), device=device).view_as(phi)).sum().backward()
        return phi.detach(), N.grad.clone()

    runs = [(dpsr.DPSR(res), *inputs(res)) for res in ((8, 8, 6), (6, 4, 8))]
    want = [field(*r) for r in runs]
    _dpsr_cache.install(dpsr)
    _dpsr_cache.install(dpsr)
    made = dpsr.MADE[0]
    for _ in range(3):
        for r, w in zip(runs, want):
            got = field(*r)
            assert torch.equal(got[0], w[0]) and torch.equal(got[1], w[1])
    assert dpsr.MADE[0] == made + 2  # one grid per resolution for the six calls
    assert all(r[0].G.device == r[1].device for r in runs)  # the filter moved once, to the points' device
    assert dpsr.fftfreqs.__name__ == "fftfreqs" and dpsr.fftfreqs.__module__ == "nvdiffrast_utils.dpsr"
    dpsr.DPSR((4, 4, 4))
    assert dpsr.MADE[0] == made + 4  # __init__ makes its filter's and its own grid as the authors' code does


def test_the_dpsr_grid_cache_runs_the_script_as_main(tmp_path):
    """``_peak.py OUT _dpsr_cache.py train.py ARGS`` in a checkout: ``train.py`` runs as ``__main__`` with its own
    arguments and finds the checkout's ``DPSR`` patched."""
    import json
    import subprocess

    _fake_dpsr_package(tmp_path)
    (tmp_path / "train.py").write_text(
        "import json, sys\n"
        "from nvdiffrast_utils import dpsr\n"
        "if __name__ == '__main__':\n"
        "    json.dump({'argv': sys.argv, 'cached': getattr(dpsr.DPSR.forward, '_grids_cached', False)},\n"
        "              open('seen.json', 'w'))\n")
    subprocess.run([sys.executable, os.path.join(PEERS, "_peak.py"), str(tmp_path / "peak.json"),
                    os.path.join(PEERS, "_dpsr_cache.py"), "train.py", "-s", "src", "--iterations", "7"],
                   cwd=tmp_path, check=True)
    seen = json.loads((tmp_path / "seen.json").read_text())
    assert seen == {"argv": ["train.py", "-s", "src", "--iterations", "7"], "cached": True}
    assert "peak_gpu_bytes" in json.loads((tmp_path / "peak.json").read_text())


def test_a_mesh_stage_without_a_whole_warmup_of_its_scene_is_refused(exch, exch_env, tmp_path, monkeypatch):
    """Before anything runs: no warm-up there, a result that is not a whole warm-up's (a mesh stage's, no time, no
    peak), a warm-up of another scene, and --from-warmup beside an option that leaves the mesh stage out."""
    import json

    calls = []
    run_pgsr = fake_pgsr(monkeypatch, calls)
    (tmp_path / "pgsr_dpsr").mkdir()
    (tmp_path / "pgsr_dpsr" / "train.py").write_text("")
    ck = ["--checkout", str(tmp_path / "pgsr_dpsr"), "--init-checkout", str(tmp_path / "pgsr_dpsr")]
    with pytest.raises(SystemExit, match="no run.json"):
        run_pgsr.main([exch.root, str(tmp_path / "o"), *ck, "--from-warmup", str(tmp_path)])
    (tmp_path / "w" / "warmup" / "mesh").mkdir(parents=True)
    (tmp_path / "w" / "warmup" / "mesh" / "tsdf_fusion_post.ply").write_text("ply")
    whole = {"warmup_iterations": 30000, "mesh_stage_iterations": None, "wall_s": 5.0, "peak_gpu_bytes": 7,
             "warmup_train_s": 4.0, "warmup_mesh_s": 1.0, "exchange": run_pgsr._exchange_id(exch.root)}
    for bad, what in (({"mesh_stage_iterations": 10000}, "mesh_stage_iterations=10000"),
                      ({"wall_s": None}, "wall_s=None"), ({"peak_gpu_bytes": None}, "peak_gpu_bytes=None")):
        (tmp_path / "w" / "run.json").write_text(json.dumps({**whole, **bad}))
        with pytest.raises(SystemExit, match=what):
            run_pgsr.main([exch.root, str(tmp_path / "o"), *ck, "--from-warmup", str(tmp_path / "w")])
    (tmp_path / "w" / "run.json").write_text(json.dumps(whole))
    with pytest.raises(SystemExit, match="not of 'mug_torus_env:"):  # the warm-up is the bunny's
        run_pgsr.main([exch_env[0].root, str(tmp_path / "o"), *ck, "--from-warmup", str(tmp_path / "w")])
    for other in (["--no-mesh-stage"], ["--mesh-only", "300"], ["--nomesh-out", str(tmp_path / "n")]):
        with pytest.raises(SystemExit) as e:  # argparse's refusal, with a warm-up that would otherwise do
            run_pgsr.main([exch.root, str(tmp_path / "o"), *ck, "--from-warmup", str(tmp_path / "w"), *other])
        assert e.value.code == 2
    assert calls == []  # nothing ran


def test_2dgs_reads_a_masked_capture_s_masks_as_its_images_alpha(exch, tmp_path):
    """``run_2dgs.py``'s source folder: on a masked capture the training images are RGBA, their colours the
    exchange's byte for byte and their alpha its masks (2DGS keeps an RGBA image's alpha as the view's mask and its
    TSDF fuses no depth outside it); the COLMAP model is copied, not linked (2DGS writes beside it)."""
    import run_2dgs
    from PIL import Image

    src = run_2dgs.source_folder(exch.root, str(tmp_path / "source"))
    names = sorted(os.listdir(os.path.join(src, "images")))
    assert names == [f"{i:04d}.png" for i in exch.train]
    for name in names[:3]:
        im = Image.open(os.path.join(src, "images", name))
        assert im.mode == "RGBA"
        rgba = np.asarray(im)
        want = np.asarray(Image.open(os.path.join(exch.root, "colmap", "images", name)).convert("RGB"))
        np.testing.assert_array_equal(rgba[..., :3], want)
        np.testing.assert_array_equal(rgba[..., 3] > 127, exch.mask(int(name[:4])))
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        path = os.path.join(src, "sparse", "0", name)
        assert not os.path.islink(path) and os.path.getsize(path) > 0


def test_2dgs_reads_a_capture_without_masks_from_the_exchange_s_own_model(exch_env, tmp_path):
    import run_2dgs

    ex, _ = exch_env
    src = run_2dgs.source_folder(ex.root, str(tmp_path / "source"))
    assert src == os.path.abspath(os.path.join(ex.root, "colmap")) and not (tmp_path / "source").exists()
