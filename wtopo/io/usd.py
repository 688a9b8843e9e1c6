# SPDX-License-Identifier: Apache-2.0
"""USD timeline of the surfel / proxy-mesh co-evolution.

Stage layout (default prim ``/World``; time code = iteration)::

    /World/Cameras/<cam>          UsdGeom.Camera per scene camera (static)
    /World/Meshes/<name>          static UsdGeom.Mesh (ground truth, final mesh, ...)
    /World/ProxyMesh              one UsdGeom.Mesh whose points, faceVertexCounts,
                                  faceVertexIndices, normals and extent are time-sampled
    /World/Surfels                UsdGeom.PointInstancer of a disk prototype
    /World/Surfels/Prototypes/Disk
    /World/Splats                 UsdVol.ParticleField3DGaussianSplat (when usd-core has it)

Conventions:
    * Coordinates are written as given (the caller's world or internal frame); ``up_axis`` and
      ``meters_per_unit`` only describe them.
    * Meshes: ``subdivisionScheme = none``, right-handed winding, per-vertex area-weighted
      normals; no GeomSubsets (they hide topology changes in Hydra, OpenUSD#1044).  Arrays of
      different lengths at neighbouring samples play back held (step animation).
    * Surfels: the disk prototype has radius 1 in the surfel's tangent plane (local z = 0, normal
      +z), so with per-instance ``scales = (s0, s1, 1)`` it draws the 1-sigma ellipse.
      Per-instance primvars (``vertex`` interpolation, one value per instance): ``opacity``,
      ``displayColor`` (SH DC base colour), ``weight`` (oriented-point weight), ``distance_to_mesh``
      and ``events`` (int flags, :class:`SurfelEvent`).
    * Splats: linear values (``opacities`` in [0, 1], linear ``scales`` with a third scale of
      ``FLAT_SCALE``), ``radiance:sphericalHarmonicsCoefficients`` holds ``N * (d + 1)^2`` float3,
      particle-major (all coefficients of particle 0, then particle 1, ...).
    * Cameras (:func:`camera_to_usd` / :func:`camera_from_usd`): the focal length and apertures
      are in tenths of a scene unit (UsdGeomCamera's unit) on a virtual film
      ``FILM_WIDTH = 36`` tenths wide: pixel pitch ``36 / W`` horizontally and
      ``focalLength / fy`` vertically, so ``fx, fy, cx, cy`` round-trip exactly; skew and
      distortion (which UsdGeomCamera cannot express) are stored in ``wtopo:skew`` and
      ``wtopo:distortion``.  The pose is a double-precision ``xformOp:transform`` equal to
      ``camera_to_world`` with the y and z camera axes negated (OpenCV +y down / +z forward to
      USD's +y up / -z forward).
    * Samples are never authored twice in a row with the same value: an unchanged array is
      skipped.  When a float array changes after skipped samples and keeps its length, the held
      value is written once more at the last skipped time so linear interpolation does not blend
      across the skipped interval.
    * Size (measured): the instancer costs about 48 bytes per surfel per
      sample, the splats about ``28 + 12 K`` more (``K`` SH coefficients kept, 1 by default:
      ``splat_sh_degree=0``); the mesh about 26 bytes per vertex (usdc compresses the face
      indices), only when it changes.  Above ``max_surfels`` surfels (50 000 by default, so at most
      ~4.5 MB of surfels per sample, ~450 MB per 100 samples) a sample keeps an evenly strided
      subset of ``max_surfels`` (``np.linspace`` indices, so the subset is deterministic).

Limitations:
    The stage lives in memory until :meth:`TimelineWriter.flush` / :meth:`TimelineWriter.close`
    (each writes the whole file atomically); memory grows with the file size.
"""

from __future__ import annotations

import os

import numpy as np

from ._common import as_array, atomic_write, sh_dc_to_rgb
from ._usd_camera import FILM_WIDTH, camera_from_usd, camera_to_usd, read_cameras
from ._usd_common import (
    HAS_SPLAT_SCHEMA,
    TimelineVerificationError,
    _extent,
    _identifier,
    _mesh_arrays,
    _pxr,
    _UsdVol,
    _vertex_normals,
)
from ._usd_read import Timeline, TimelineSample, _verify_file, mesh_at, read_surfels, read_timeline
from ._usd_write import SurfelEvent, TimelineStats, _Track

__all__ = ["TimelineWriter", "TimelineStats", "TimelineVerificationError", "SurfelEvent", "Timeline",
           "TimelineSample", "read_timeline", "read_cameras", "read_surfels", "mesh_at", "camera_to_usd",
           "camera_from_usd", "FILM_WIDTH", "FLAT_SCALE", "HAS_SPLAT_SCHEMA"]

FLAT_SCALE = 1e-7
"""Linear third (normal) scale of surfels written as 3D Gaussian splats (PLY: ``log(FLAT_SCALE)``)."""

DISK_SEGMENTS = 16
"""Polygon sides of the disk prototype (a regular 16-gon inscribed in the unit circle)."""


def _export_layer(layer, path: str) -> None:
    """Write ``layer`` to ``path`` (a separate function so tests can simulate a silent failed save)."""
    if not layer.Export(path):
        raise TimelineVerificationError(f"Sdf.Layer.Export reported failure writing {path}")


class TimelineWriter:
    """Writes the co-evolution timeline as a ``.usdc`` stage (layout and conventions: module docstring).

    Args:
        path: output file (``.usdc``, ``.usda`` or ``.usd``); only written by :meth:`flush` /
            :meth:`close`, atomically.
        up_axis: ``"Y"`` or ``"Z"``, the up axis of the given coordinates.
        meters_per_unit: size of one scene unit in metres (e.g. 0.001 for DTU millimetres).
        time_codes_per_second: playback rate, in iterations per second (time code = iteration).
        max_surfels: surfels per sample above which an evenly strided subset is written.
        splats: also write ``UsdVol.ParticleField3DGaussianSplat`` (ignored when usd-core lacks it).
        splat_sh_degree: SH degree kept in the splats (higher coefficients are dropped; ``None``
            keeps all).  The default 0 keeps the timeline small (full degree-3 SH is 192 bytes
            per surfel per sample); write the final full-SH surfels with
            :func:`wtopo.io.write_surfels_ply`.

    Example::

        w = TimelineWriter(out_dir / "timeline.usdc")
        w.add_cameras(scene.cameras)
        for it in ...:
            w.add_sample(it, mesh_verts=v, mesh_faces=f, means=m, quats=q, scales=s,
                         opacities=o, colors_or_sh=sh)
        w.add_mesh("final", v, f)
        stats = w.close()

    Limitations:
        The whole stage is kept in memory until written (see the module docstring for sizes).
    """

    MAX_SURFELS = 50_000
    """The default ``max_surfels``."""

    def __init__(self, path: str | os.PathLike, *, up_axis: str = "Y", meters_per_unit: float = 1.0,
                 time_codes_per_second: float = 100.0, max_surfels: int = MAX_SURFELS, splats: bool = True,
                 splat_sh_degree: int | None = 0):
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        self.path = os.fspath(path)
        if os.path.splitext(self.path)[1] not in (".usdc", ".usda", ".usd"):
            raise ValueError(f"path must end in .usdc, .usda or .usd, got {self.path!r}")
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not (meters_per_unit > 0 and np.isfinite(meters_per_unit)):
            raise ValueError(f"meters_per_unit must be > 0 and finite, got {meters_per_unit!r}")
        if not (time_codes_per_second > 0 and np.isfinite(time_codes_per_second)):
            raise ValueError(f"time_codes_per_second must be > 0 and finite, got {time_codes_per_second!r}")
        if isinstance(max_surfels, bool) or int(max_surfels) != max_surfels or max_surfels < 1:
            raise ValueError(f"max_surfels must be a positive integer, got {max_surfels!r}")
        self.max_surfels = int(max_surfels)
        d = splat_sh_degree
        if d is not None and (isinstance(d, bool) or int(d) != d or d < 0):
            raise ValueError(f"splat_sh_degree must be a non-negative integer or None, got {splat_sh_degree!r}")
        self._splat_k_max = None if splat_sh_degree is None else (int(splat_sh_degree) + 1) ** 2
        self.stage = Usd.Stage.CreateInMemory()
        st = self.stage
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, float(meters_per_unit))
        st.SetTimeCodesPerSecond(float(time_codes_per_second))
        st.SetFramesPerSecond(float(time_codes_per_second))
        world = UsdGeom.Xform.Define(st, "/World")
        st.SetDefaultPrim(world.GetPrim())
        self._iterations: list[int] = []
        self._cam_names: set[str] = set()
        self._closed = False
        self._proxy = None
        self._instancer = None
        self._splat = None
        self._splat_k = None
        self._tracks: dict[str, _Track] = {}
        self._splats = bool(splats) and HAS_SPLAT_SCHEMA

    # -- static content ------------------------------------------------------------------------
    def add_cameras(self, cameras, images=None, *, clipping_range=(0.01, 1000.0)) -> list[str]:
        """Add scene cameras as ``UsdGeom.Camera`` prims under ``/World/Cameras``.

        Args:
            cameras: list of :class:`wtopo.Camera`.
            images: optional [N, H, W, 3] (or list of [H, W, 3]) float in [0, 1] or uint8 images,
                one per camera; saved as PNG in ``<stem>_images/`` beside the output file and
                referenced from each camera's ``wtopo:image`` asset attribute (relative path).
            clipping_range: (near, far) in scene units.

        Returns:
            The prim paths written.
        """
        from ..camera import Camera

        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        self._check_open()
        cameras = list(cameras)
        for i, c in enumerate(cameras):
            if not isinstance(c, Camera):
                raise TypeError(f"cameras[{i}] must be a wtopo.Camera, got {type(c).__name__}")
        if images is not None and len(images) != len(cameras):
            raise ValueError(f"images must hold one image per camera ({len(cameras)}), got {len(images)}")
        UsdGeom.Scope.Define(self.stage, "/World/Cameras")
        paths = []
        for i, c in enumerate(cameras):
            base = _identifier(os.path.splitext(os.path.basename(c.name))[0] if c.name else f"camera_{i:04d}")
            name, k = base, 1
            while name in self._cam_names:
                name, k = f"{base}_{k}", k + 1
            self._cam_names.add(name)
            cam = camera_to_usd(self.stage, f"/World/Cameras/{name}", c, clipping_range=clipping_range)
            if images is not None:
                rel = self._save_image(images[i], name)
                cam.GetPrim().CreateAttribute("wtopo:image", Sdf.ValueTypeNames.Asset, custom=True).Set(
                    Sdf.AssetPath(rel))
            paths.append(str(cam.GetPath()))
        return paths

    def _save_image(self, image, name: str) -> str:
        from PIL import Image

        img = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise ValueError(f"images must be [H, W, 3|4] each, got shape {list(img.shape)}")
        if img.dtype != np.uint8:
            img = (np.clip(np.nan_to_num(img.astype(np.float64)), 0, 1) * 255 + 0.5).astype(np.uint8)
        stem = os.path.splitext(os.path.basename(self.path))[0]
        folder = os.path.join(os.path.dirname(os.path.abspath(self.path)), f"{stem}_images")
        os.makedirs(folder, exist_ok=True)
        Image.fromarray(img).save(os.path.join(folder, f"{name}.png"))
        return f"./{stem}_images/{name}.png"

    def add_mesh(self, name: str, verts, faces, *, color=(0.7, 0.7, 0.7)) -> str:
        """Add a static (untimed) mesh at ``/World/Meshes/<name>`` (e.g. ``"ground_truth"``, ``"final"``).

        Args:
            name: prim name (invalid characters become ``_``).
            verts: [V, 3] float vertices, scene units.
            faces: [F, 3] int vertex indices.
            color: display colour (3 floats in [0, 1]).

        Returns:
            The prim path.
        """
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        self._check_open()
        verts, faces = _mesh_arrays(verts, faces, "")
        UsdGeom.Scope.Define(self.stage, "/World/Meshes")
        mesh = UsdGeom.Mesh.Define(self.stage, f"/World/Meshes/{_identifier(name)}")
        self._mesh_schema(mesh, color)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(verts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(_vertex_normals(verts, faces)))
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(_extent(verts)))
        return str(mesh.GetPath())

    @staticmethod
    def _mesh_schema(mesh, color) -> None:
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*(float(c) for c in color))]))

    # -- time samples --------------------------------------------------------------------------
    def _track(self, key: str, attr, make_vt, interpolates: bool) -> _Track:
        if key not in self._tracks:
            self._tracks[key] = _Track(attr, make_vt, interpolates)
        return self._tracks[key]

    def _ensure_proxy(self):
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        if self._proxy is None:
            m = UsdGeom.Mesh.Define(self.stage, "/World/ProxyMesh")
            self._mesh_schema(m, (0.8, 0.6, 0.3))
            v3, ia = Vt.Vec3fArray.FromNumpy, Vt.IntArray.FromNumpy
            self._track("mesh.points", m.CreatePointsAttr(), v3, True)
            self._track("mesh.counts", m.CreateFaceVertexCountsAttr(), ia, False)
            self._track("mesh.indices", m.CreateFaceVertexIndicesAttr(), lambda a: ia(a.reshape(-1)), False)
            self._track("mesh.normals", m.CreateNormalsAttr(), v3, True)
            self._track("mesh.extent", m.CreateExtentAttr(), v3, True)
            self._proxy = m
        return self._proxy

    def _ensure_instancer(self):
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        if self._instancer is not None:
            return self._instancer
        inst = UsdGeom.PointInstancer.Define(self.stage, "/World/Surfels")
        UsdGeom.Scope.Define(self.stage, "/World/Surfels/Prototypes")
        disk = UsdGeom.Mesh.Define(self.stage, "/World/Surfels/Prototypes/Disk")
        a = np.linspace(0, 2 * np.pi, DISK_SEGMENTS, endpoint=False)
        ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1).astype(np.float32)
        disk.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        disk.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(ring))
        disk.CreateFaceVertexCountsAttr(Vt.IntArray([DISK_SEGMENTS]))
        disk.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.arange(DISK_SEGMENTS, dtype=np.int32)))
        disk.CreateNormalsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 1)]))
        disk.SetNormalsInterpolation(UsdGeom.Tokens.constant)
        disk.CreateDoubleSidedAttr(True)
        disk.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1, -1, 0), Gf.Vec3f(1, 1, 0)]))
        inst.CreatePrototypesRel().SetTargets([disk.GetPath()])
        v3, fa, ia = Vt.Vec3fArray.FromNumpy, Vt.FloatArray.FromNumpy, Vt.IntArray.FromNumpy
        self._track("inst.positions", inst.CreatePositionsAttr(), v3, True)
        self._track("inst.orientations", inst.CreateOrientationsAttr(), Vt.QuathArray.FromNumpy, True)
        self._track("inst.scales", inst.CreateScalesAttr(), v3, True)
        self._track("inst.protoIndices", inst.CreateProtoIndicesAttr(), ia, False)
        self._track("inst.extent", inst.CreateExtentAttr(), v3, True)
        pv = UsdGeom.PrimvarsAPI(inst)
        vtx = UsdGeom.Tokens.vertex
        names = Sdf.ValueTypeNames
        self._track("inst.opacity", pv.CreatePrimvar("opacity", names.FloatArray, vtx).GetAttr(), fa, True)
        self._track("inst.color", pv.CreatePrimvar("displayColor", names.Color3fArray, vtx).GetAttr(), v3, True)
        self._track("inst.weight", pv.CreatePrimvar("weight", names.FloatArray, vtx).GetAttr(), fa, True)
        self._track("inst.distance", pv.CreatePrimvar("distance_to_mesh", names.FloatArray, vtx).GetAttr(), fa, True)
        self._track("inst.events", pv.CreatePrimvar("events", names.IntArray, vtx).GetAttr(), ia, False)
        self._instancer = inst
        return inst

    def _ensure_splat(self, k: int):
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        if self._splat is None:
            sp = _UsdVol.ParticleField3DGaussianSplat.Define(self.stage, "/World/Splats")
            sp.CreateRadianceSphericalHarmonicsDegreeAttr(int(round(np.sqrt(k))) - 1)
            v3 = Vt.Vec3fArray.FromNumpy
            self._track("splat.positions", sp.CreatePositionsAttr(), v3, True)
            self._track("splat.orientations", sp.CreateOrientationsAttr(), Vt.QuatfArray.FromNumpy, True)
            self._track("splat.scales", sp.CreateScalesAttr(), v3, True)
            self._track("splat.opacities", sp.CreateOpacitiesAttr(), Vt.FloatArray.FromNumpy, True)
            self._track("splat.sh", sp.CreateRadianceSphericalHarmonicsCoefficientsAttr(),
                        lambda a: v3(a.reshape(-1, 3)), True)
            self._track("splat.extent", sp.CreateExtentAttr(), v3, True)
            self._splat, self._splat_k = sp, k
        elif k != self._splat_k:
            raise ValueError(f"colors_or_sh must keep K = {self._splat_k} SH coefficients across samples "
                             f"(radiance:sphericalHarmonicsDegree is uniform), got K = {k}")
        return self._splat

    def add_sample(self, iteration: int, *, mesh_verts=None, mesh_faces=None, means=None, quats=None, scales=None,
                   opacities=None, colors_or_sh=None, point_weight=None, distance_to_mesh=None,
                   events=None) -> None:
        """Record the state at ``iteration`` (time code = iteration; must increase).

        Pass the mesh (``mesh_verts`` and ``mesh_faces``) and/or the surfels (``means``, ``quats``,
        ``scales``, ``opacities``, ``colors_or_sh`` together); a part left out is unchanged since
        the previous sample.  Values equal to the previous sample are not authored again.

        Args:
            iteration: non-negative int, larger than the previous sample's.
            mesh_verts: proxy-mesh vertices [V, 3] float, scene units.
            mesh_faces: proxy-mesh faces [F, 3] int.
            means: surfel centres [N, 3].
            quats: surfel rotations [N, 4] (w, x, y, z), any norm.
            scales: linear tangent scales [N, 2].
            opacities: opacities [N] in [0, 1].
            colors_or_sh: RGB [N, 3] in [0, 1] or SH coefficients [N, K, 3] (K fixed for the run).
            point_weight: oriented-point weight per surfel [N] (default 1).
            distance_to_mesh: unsigned distance from each surfel centre to the proxy mesh [N]
                (default 0).
            events: :class:`SurfelEvent` flags per surfel [N] int (default 0).

        Raises:
            TypeError, ValueError: bad shapes, non-finite values, a non-increasing iteration, or
                only part of the mesh / surfel arrays given.
        """
        from .ply import surfel_arrays

        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        self._check_open()
        if isinstance(iteration, bool) or int(iteration) != iteration or iteration < 0:
            raise ValueError(f"iteration must be a non-negative integer, got {iteration!r}")
        it = int(iteration)
        if self._iterations and it <= self._iterations[-1]:
            raise ValueError(f"iteration must increase, got {it} after {self._iterations[-1]}")
        if (mesh_verts is None) != (mesh_faces is None):
            raise ValueError("mesh_verts and mesh_faces must be given together")
        surf = (means, quats, scales, opacities, colors_or_sh)
        if any(a is None for a in surf) and not all(a is None for a in surf):
            raise ValueError("means, quats, scales, opacities and colors_or_sh must be given together")
        mesh = None if mesh_verts is None else _mesh_arrays(mesh_verts, mesh_faces, "mesh_")
        s = extras = None
        if means is not None:
            s = surfel_arrays(means, quats, scales, opacities, colors_or_sh)
            n = len(s)
            extras = [
                np.ones(n, np.float32) if point_weight is None else as_array("point_weight", point_weight, shape=(n,)),
                np.zeros(n, np.float32) if distance_to_mesh is None
                else as_array("distance_to_mesh", distance_to_mesh, shape=(n,)),
                np.zeros(n, np.int32) if events is None else as_array("events", events, shape=(n,), dtype=np.int32),
            ]
        elif any(a is not None for a in (point_weight, distance_to_mesh, events)):
            raise ValueError("point_weight, distance_to_mesh and events need the surfel arrays (means, ...)")
        t = float(it)
        if mesh is not None:  # prims are defined outside the change block (UsdStage cannot inside it)
            self._ensure_proxy()
        if s is not None:
            self._ensure_instancer()
            if self._splats:
                self._ensure_splat(self._splat_k_of(s.sh.shape[1]))
        with Sdf.ChangeBlock():
            self._write_mesh(mesh, t)
            self._write_surfels(s, extras, t)
        self._iterations.append(it)

    def _write_mesh(self, mesh, t: float) -> None:
        if mesh is None:
            for key in ("points", "counts", "indices", "normals", "extent"):
                if f"mesh.{key}" in self._tracks:
                    self._tracks[f"mesh.{key}"].unchanged(t)
            return
        verts, faces = mesh
        tr = self._tracks
        tr["mesh.points"].set(verts, t)
        tr["mesh.counts"].set(np.full(len(faces), 3, np.int32), t)
        tr["mesh.indices"].set(faces, t)
        tr["mesh.normals"].set(_vertex_normals(verts, faces), t)
        tr["mesh.extent"].set(_extent(verts), t)

    def _write_surfels(self, s, extras, t: float) -> None:
        keys = [k for k in self._tracks if k.startswith(("inst.", "splat."))]
        if s is None:
            for k in keys:
                self._tracks[k].unchanged(t)
            return
        weight, dist, events = extras
        if len(s) > self.max_surfels:  # documented decimation: deterministic strided subset
            idx = np.linspace(0, len(s) - 1, self.max_surfels).round().astype(np.int64)
            s = type(s)(s.means[idx], s.quats[idx], s.scales[idx], s.opacities[idx], s.sh[idx])
            weight, dist, events = weight[idx], dist[idx], events[idx]
        n = len(s)
        tr = self._tracks
        xyzw = np.ascontiguousarray(s.quats[:, [1, 2, 3, 0]])  # Gf quaternions are (imaginary, real) in NumPy
        scale3 = np.concatenate([s.scales, np.ones((n, 1), np.float32)], axis=1)
        radius = float(s.scales.max()) if n else 0.0
        tr["inst.positions"].set(s.means, t)
        tr["inst.orientations"].set(xyzw.astype(np.float16), t)
        tr["inst.scales"].set(scale3, t)
        tr["inst.protoIndices"].set(np.zeros(n, np.int32), t)
        tr["inst.extent"].set(_extent(s.means, radius), t)
        tr["inst.opacity"].set(s.opacities, t)
        tr["inst.color"].set(sh_dc_to_rgb(s.sh[:, 0]).astype(np.float32), t)
        tr["inst.weight"].set(weight, t)
        tr["inst.distance"].set(dist, t)
        tr["inst.events"].set(events, t)
        if self._splats:
            scale3[:, 2] = FLAT_SCALE
            tr["splat.positions"].set(s.means, t)
            tr["splat.orientations"].set(xyzw, t)
            tr["splat.scales"].set(scale3, t)
            tr["splat.opacities"].set(s.opacities, t)
            tr["splat.sh"].set(np.ascontiguousarray(s.sh[:, :self._splat_k_of(s.sh.shape[1])]), t)
            tr["splat.extent"].set(_extent(s.means, 3 * radius), t)

    def _splat_k_of(self, k: int) -> int:
        return k if self._splat_k_max is None else min(k, self._splat_k_max)

    # -- output --------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"TimelineWriter for {self.path} is closed")

    @property
    def iterations(self) -> list[int]:
        """Iterations sampled so far."""
        return list(self._iterations)

    def flush(self) -> TimelineStats:
        """Write the stage so far to :attr:`path`: temporary file, reopen and verify, rename.

        Raises:
            TimelineVerificationError: the reopened file differs from what was authored (prim
                count, per-sample array lengths, face indices out of range, non-finite values,
                sample counts); the temporary file is removed and ``path`` left untouched.
        """
        self._check_open()
        st = self.stage
        if self._iterations:
            st.SetStartTimeCode(float(self._iterations[0]))
            st.SetEndTimeCode(float(self._iterations[-1]))
        st.GetRootLayer().customLayerData = {"wtopo:samples": len(self._iterations)}
        expected_prims = sum(1 for _ in st.TraverseAll())
        expected_counts = {k: tr.count for k, tr in self._tracks.items()}
        attr_paths = {k: tr.attr.GetPath() for k, tr in self._tracks.items()}
        ext = os.path.splitext(self.path)[1]

        def verify(tmp: str) -> None:
            _verify_file(tmp, expected_prims, {str(attr_paths[k]): c for k, c in expected_counts.items()})

        atomic_write(self.path, lambda tmp: _export_layer(st.GetRootLayer(), tmp), verify=verify, suffix=ext)
        size = os.path.getsize(self.path)
        n = len(self._iterations)
        return TimelineStats(self.path, n, size, 100.0 * size / n if n else float(size))

    def close(self) -> TimelineStats:
        """:meth:`flush`, then release the in-memory stage; later calls raise ``RuntimeError``."""
        stats = self.flush()
        self._closed = True
        self.stage = None
        self._tracks = {}
        return stats

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None and not self._closed:
            self.close()
