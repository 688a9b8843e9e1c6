# SPDX-License-Identifier: Apache-2.0
"""Reading and verifying USD timelines written by :class:`wtopo.io.TimelineWriter`."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ._common import normalize_quats, rgb_to_sh_dc
from ._usd_camera import read_cameras
from ._usd_common import HAS_SPLAT_SCHEMA, TimelineVerificationError, _all_times, _pxr, _UsdVol

__all__ = ["Timeline", "TimelineSample", "read_timeline", "read_surfels", "mesh_at", "earlier_samples"]


def _check_finite(what: str, value) -> None:
    a = np.asarray(value)
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise TimelineVerificationError(f"{what} holds non-finite values")


def _verify_file(path: str, expected_prims: int, expected_counts: dict[str, int]) -> None:
    """Reopen ``path`` and check it holds what the writer authored (see :meth:`TimelineWriter.flush`)."""
    _, Sdf, Usd, UsdGeom, _ = _pxr()
    if os.path.getsize(path) == 0:
        raise TimelineVerificationError(f"{path} is empty after saving (OpenUSD#3659)")
    layer = Sdf.Layer.OpenAsAnonymous(path)  # bypass the layer registry: read what is on disk
    if layer is None:
        raise TimelineVerificationError(f"{path} cannot be reopened as a USD layer")
    stage = Usd.Stage.Open(layer)
    prims = list(stage.TraverseAll())
    if len(prims) != expected_prims:
        raise TimelineVerificationError(f"{path} holds {len(prims)} prims, expected {expected_prims}")
    for attr_path, count in expected_counts.items():
        attr = stage.GetAttributeAtPath(attr_path)
        got = attr.GetNumTimeSamples() if attr else -1
        if got != count:
            raise TimelineVerificationError(f"{attr_path} has {got} time samples, expected {count}")
    for prim in prims:
        if prim.IsA(UsdGeom.Mesh):
            _verify_mesh(UsdGeom.Mesh(prim))
        elif prim.IsA(UsdGeom.PointInstancer):
            _verify_lengths(prim, ["positions", "orientations", "scales", "protoIndices", "primvars:opacity",
                                   "primvars:displayColor", "primvars:weight", "primvars:distance_to_mesh",
                                   "primvars:events"], {})
        elif HAS_SPLAT_SCHEMA and prim.IsA(_UsdVol.ParticleField3DGaussianSplat):
            k = (prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get() + 1) ** 2
            _verify_lengths(prim, ["positions", "orientations", "scales", "opacities"],
                            {"radiance:sphericalHarmonicsCoefficients": k})
        elif prim.IsA(UsdGeom.Camera):
            xf = UsdGeom.Camera(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
            _check_finite(f"{prim.GetPath()} transform", np.array(xf))


def _verify_mesh(mesh) -> None:
    attrs = [mesh.GetPointsAttr(), mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr(),
             mesh.GetNormalsAttr(), mesh.GetExtentAttr()]
    from pxr import Usd

    for t in _all_times(attrs) or [Usd.TimeCode.Default()]:
        pts, counts, idx, nrm, ext = (np.asarray(a.Get(t)) if a.Get(t) is not None else None for a in attrs)
        where = f"{mesh.GetPath()} at time {t}"
        if pts is None or counts is None or idx is None:
            raise TimelineVerificationError(f"{where}: points / faceVertexCounts / faceVertexIndices missing")
        if int(counts.sum()) != len(idx):
            raise TimelineVerificationError(f"{where}: faceVertexCounts sum {counts.sum()} != {len(idx)} indices")
        if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
            raise TimelineVerificationError(f"{where}: face indices [{idx.min()}, {idx.max()}] outside "
                                            f"[0, {len(pts)}) points")
        if nrm is not None and len(nrm) not in (len(pts), 1):
            raise TimelineVerificationError(f"{where}: {len(nrm)} normals for {len(pts)} points")
        for nm, v in (("points", pts), ("normals", nrm), ("extent", ext)):
            if v is not None:
                _check_finite(f"{where} {nm}", v)


def _verify_lengths(prim, names: list[str], multiples: dict[str, int]) -> None:
    attrs = [prim.GetAttribute(n) for n in names + list(multiples)]
    for t in _all_times(attrs):
        values = [np.asarray(a.Get(t)) for a in attrs]
        n = len(values[0])
        for name, v in zip(names + list(multiples), values):
            want = n * multiples.get(name, 1)
            if len(v) != want:
                raise TimelineVerificationError(f"{prim.GetPath()} at time {t}: {name} has {len(v)} values, "
                                                f"expected {want}")
            _check_finite(f"{prim.GetPath()} {name} at time {t}", v)


@dataclass
class TimelineSample:
    """The proxy mesh and surfel count at one sampled iteration.

    Attributes:
        iteration: the time code.
        verts: [V, 3] float32 (empty when no mesh has been sampled yet).
        faces: [F, 3] int32.
        num_surfels: surfels written at this sample (after decimation).
    """

    iteration: int
    verts: np.ndarray
    faces: np.ndarray
    num_surfels: int


@dataclass
class Timeline:
    """What :func:`read_timeline` returns.

    Attributes:
        samples: one :class:`TimelineSample` per sampled iteration, ascending.
        meshes: static meshes by prim name, each ``(verts [V, 3] float32, faces [F, 3] int32)``.
        cameras: the scene cameras (:class:`wtopo.Camera`).
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: stage metersPerUnit.
        time_codes_per_second: stage timeCodesPerSecond.
    """

    samples: list[TimelineSample]
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    cameras: list = field(default_factory=list)
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    time_codes_per_second: float = 24.0

    @property
    def iterations(self) -> list[int]:
        """Sampled iterations, ascending."""
        return [s.iteration for s in self.samples]


def _read_mesh(mesh, t) -> tuple[np.ndarray, np.ndarray]:
    pts = mesh.GetPointsAttr().Get(t)
    idx = mesh.GetFaceVertexIndicesAttr().Get(t)
    counts = mesh.GetFaceVertexCountsAttr().Get(t)
    verts = np.asarray(pts, np.float32).reshape(-1, 3) if pts is not None else np.zeros((0, 3), np.float32)
    idx = np.asarray(idx, np.int32) if idx is not None else np.zeros(0, np.int32)
    counts = np.asarray(counts, np.int32) if counts is not None else np.zeros(0, np.int32)
    if np.all(counts == 3):
        return verts, idx.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])  # fan-triangulate polygons from other tools
    tris = [[idx[s], idx[s + j], idx[s + j + 1]] for s, c in zip(starts, counts) for j in range(1, c - 1)]
    return verts, np.asarray(tris, np.int32).reshape(-1, 3)


def _open_stage(Usd, path: str):
    """The USD stage of the file at ``path``: FileNotFoundError without one, ValueError where it is no stage."""
    if not os.path.exists(path):
        raise FileNotFoundError(path)
    stage = Usd.Stage.Open(path)
    if stage is None:
        raise ValueError(f"{path} is not a USD stage")
    return stage


def read_timeline(path: str | os.PathLike) -> Timeline:
    """Read a timeline written by :class:`TimelineWriter`: per-sample proxy meshes, static meshes, cameras.

    Every time code at which anything (mesh or surfels) was sampled gives one
    :class:`TimelineSample`, with the mesh value held from the latest mesh sample.
    """
    _, Sdf, Usd, UsdGeom, _ = _pxr()
    path = os.fspath(path)
    stage = _open_stage(Usd, path)
    proxy = stage.GetPrimAtPath("/World/ProxyMesh")
    proxy = UsdGeom.Mesh(proxy) if proxy and proxy.IsA(UsdGeom.Mesh) else None
    inst = stage.GetPrimAtPath("/World/Surfels")
    inst = UsdGeom.PointInstancer(inst) if inst and inst.IsA(UsdGeom.PointInstancer) else None
    attrs = []
    if proxy is not None:
        attrs += [proxy.GetPointsAttr(), proxy.GetFaceVertexIndicesAttr()]
    if inst is not None:
        attrs += [inst.GetPositionsAttr()]
    mesh_times = _all_times(attrs[:2]) if proxy is not None else []
    samples = []
    for t in _all_times(attrs):
        if proxy is not None and mesh_times and t >= mesh_times[0]:
            verts, faces = _read_mesh(proxy, Usd.TimeCode(t))
        else:
            verts, faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
        pos = inst.GetPositionsAttr().Get(Usd.TimeCode(t)) if inst is not None else None
        samples.append(TimelineSample(int(round(t)), verts, faces, 0 if pos is None else len(pos)))
    meshes = {}
    scope = stage.GetPrimAtPath("/World/Meshes")
    if scope:
        for child in scope.GetChildren():
            if child.IsA(UsdGeom.Mesh):
                meshes[child.GetName()] = _read_mesh(UsdGeom.Mesh(child), Usd.TimeCode.Default())
    up = UsdGeom.GetStageUpAxis(stage)
    return Timeline(samples, meshes, read_cameras(stage), "Z" if up == UsdGeom.Tokens.z else "Y",
                    float(UsdGeom.GetStageMetersPerUnit(stage)), float(stage.GetTimeCodesPerSecond()))


def _sample_time(times: list[float], iteration: int | None, what: str) -> float:
    """The latest sample time at or before ``iteration`` (the last one when ``None``)."""
    if not times:
        raise ValueError(f"the timeline has no {what} samples")
    if iteration is None:
        return times[-1]
    before = [t for t in times if t <= iteration]
    if not before:
        raise ValueError(f"iteration {iteration} precedes the first {what} sample ({int(times[0])})")
    return before[-1]


def earlier_samples(path: str | os.PathLike, until: int):
    """The samples of a timeline written by :class:`TimelineWriter` at iterations up to ``until``, as
    :meth:`TimelineWriter.add_sample`'s arguments: ``(iteration, kwargs)`` ascending, the surfels at every time
    anything was sampled (:func:`read_surfels`' arrays; SH keep the file's degree) and the proxy mesh from its first
    sample on. A resumed fit's writer authors them before its own (``wtopo.io._timeline_process``).

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: ``path`` is not a USD stage.
    """
    _, _, Usd, UsdGeom, _ = _pxr()
    path = os.fspath(path)
    stage = _open_stage(Usd, path)
    prims = [stage.GetPrimAtPath(p) for p in ("/World/ProxyMesh", "/World/Surfels", "/World/Splats")]
    proxy = UsdGeom.Mesh(prims[0]) if prims[0] and prims[0].IsA(UsdGeom.Mesh) else None
    mesh_times = _all_times([proxy.GetPointsAttr(), proxy.GetFaceVertexIndicesAttr()]) if proxy is not None else []
    times = _all_times([a for p in prims if p for a in p.GetAttributes()])
    surfel_times = _all_times([p.GetAttribute("positions") for p in prims[1:] if p])
    for t in (t for t in times if t <= until):
        kwargs = {}
        if surfel_times and t >= surfel_times[0]:
            s = read_surfels(path, int(round(t)), stage=stage)
            kwargs.update(means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities, colors_or_sh=s.sh)
        if mesh_times and t >= mesh_times[0]:
            kwargs["mesh_verts"], kwargs["mesh_faces"] = _read_mesh(proxy, Usd.TimeCode(t))
        if kwargs:  # (a time with neither, before the first of both, carries nothing)
            yield int(round(t)), kwargs


def read_surfels(path: str | os.PathLike, iteration: int | None = None, *, stage=None):
    """The surfels of a timeline at ``iteration`` (latest sample at or before it; last when ``None``).

    Reads ``/World/Splats`` (full SH) when present, else the point instancer (colour from
    ``displayColor`` as the SH DC term).  Decimated samples return the written subset. ``stage``: the file's
    stage, opened already (``path`` then names it in errors).

    Returns:
        :class:`wtopo.io.SurfelArrays`.
    """
    from .ply import SurfelArrays

    _, _, Usd, UsdGeom, _ = _pxr()
    if stage is None:
        stage = Usd.Stage.Open(os.fspath(path))
    splat = stage.GetPrimAtPath("/World/Splats")
    inst = stage.GetPrimAtPath("/World/Surfels")
    src = splat if splat and splat.GetAttribute("positions").GetNumTimeSamples() else inst
    if not src:
        raise ValueError(f"{path} holds no surfels (/World/Splats or /World/Surfels)")
    pos_attr = src.GetAttribute("positions")
    tc = Usd.TimeCode(_sample_time(list(pos_attr.GetTimeSamples()), iteration, "surfel"))
    get = lambda name: np.asarray(src.GetAttribute(name).Get(tc))  # noqa: E731
    means = get("positions").astype(np.float32).reshape(-1, 3)
    n = len(means)
    quats = normalize_quats(get("orientations").astype(np.float32).reshape(n, 4)[:, [3, 0, 1, 2]])
    scales = get("scales").astype(np.float32).reshape(n, 3)[:, :2]
    if src == splat:
        opac = get("opacities").astype(np.float32)
        sh = get("radiance:sphericalHarmonicsCoefficients").astype(np.float32).reshape(n, -1, 3)
    else:
        opac = get("primvars:opacity").astype(np.float32)
        sh = rgb_to_sh_dc(get("primvars:displayColor").astype(np.float32).reshape(n, 3))[:, None, :]
    return SurfelArrays(means, quats, np.ascontiguousarray(scales), opac, np.ascontiguousarray(sh, np.float32))


def mesh_at(timeline: Timeline, iteration: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The proxy mesh of ``timeline`` at ``iteration`` (latest sample at or before it; last when ``None``)."""
    times = [s.iteration for s in timeline.samples if len(s.faces)]
    t = _sample_time(times, iteration, "mesh")
    s = next(s for s in timeline.samples if s.iteration == t)
    return s.verts, s.faces
