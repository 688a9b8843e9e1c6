# SPDX-License-Identifier: Apache-2.0
"""Surfels as 3DGS-compatible binary PLY, and meshes as PLY / OBJ.

Surfel PLY layout (graphdeco-inria/gaussian-splatting ``save_ply``): one binary
little-endian ``vertex`` element, all ``float32``, properties in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3(K-1)-1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

* ``nx ny nz``: the surfel normal (local +z axis of the rotation); 3DGS writes zeros there and
  ignores it on load, Open3D reads it as the point normal.
* ``f_dc_*``: degree-0 SH coefficients (base colour ``0.5 + 0.28209479 * f_dc``); ``f_rest_*`` the
  higher-order coefficients **channel-major** (all red coefficients, then green, then blue).
* ``opacity``: the logit of the opacity; opacities are clamped to
  ``[OPACITY_EPS, 1 - OPACITY_EPS]`` first so 0 and 1 write finite values (+-13.8).
* ``scale_0, scale_1``: log of the two tangent scales; ``scale_2`` = :data:`FLAT_LOG_SCALE`
  (``log(1e-7)``), the "appended zero scale" the 2DGS README recommends so 3DGS viewers
  (SuperSplat, antimatter15/splat, Open3D) open the file as flat Gaussians.
* ``rot_*``: the rotation quaternion, **w first**, normalised.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ._common import SH_C0, as_array, atomic_write, normalize_quats, quat_normal, rgb_to_sh_dc, sh_dc_to_rgb

__all__ = ["SurfelArrays", "surfel_arrays", "write_surfels_ply", "read_surfels_ply", "export_mesh", "OPACITY_EPS",
           "FLAT_LOG_SCALE", "SH_C0"]

OPACITY_EPS = 1e-6
"""Opacities are clamped to ``[OPACITY_EPS, 1 - OPACITY_EPS]`` before the logit.

1e-6 keeps ``1 - eps`` exactly representable apart from 1 in float32 (spacing 6e-8 near 1) so the
logit stays finite, and a read-back opacity differs from 0 or 1 by at most 1e-6."""

FLAT_LOG_SCALE = float(np.log(1e-7))
"""Log of the third (normal-direction) scale written for 3DGS viewers: a surfel is a Gaussian of
thickness 1e-7 scene units.  :func:`read_surfels_ply` drops it."""


@dataclass
class SurfelArrays:
    """Plain surfel parameters on the host (all float32 NumPy arrays).

    Attributes:
        means: centres, shape [N, 3], scene units.
        quats: unit rotations (w, x, y, z), shape [N, 4]; the local +z axis is the normal.
        scales: linear tangent scales (standard deviations), shape [N, 2], scene units.
        opacities: opacities in [0, 1], shape [N].
        sh: SH coefficients, shape [N, K, 3] with ``K = (degree + 1) ** 2``; ``sh[:, 0]`` is the DC term.
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    @property
    def colors(self) -> np.ndarray:
        """Base colour in [0, 1] from the DC term, shape [N, 3]."""
        return sh_dc_to_rgb(self.sh[:, 0]).astype(np.float32)

    @property
    def sh_degree(self) -> int:
        """SH degree ``d`` with ``K = (d + 1) ** 2``."""
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def __len__(self) -> int:
        return int(self.means.shape[0])


def surfel_arrays(means, quats, scales, opacities, colors_or_sh) -> SurfelArrays:
    """Validate surfel parameters (torch tensors or arrays) and return host :class:`SurfelArrays`.

    Args:
        means: [N, 3] centres.
        quats: [N, 4] rotations (w, x, y, z), any norm; zero quaternions become the identity.
        scales: [N, 2] linear tangent scales, >= 0.
        opacities: [N] opacities in [0, 1].
        colors_or_sh: [N, 3] RGB in [0, 1] (converted to the DC term) or [N, K, 3] SH
            coefficients with ``K`` a perfect square.

    Raises:
        TypeError, ValueError: wrong type, shape, non-finite values or out-of-range values.
    """
    means = as_array("means", means, shape=(None, 3))
    n = means.shape[0]
    quats = normalize_quats(as_array("quats", quats, shape=(n, 4)))
    scales = as_array("scales", scales, shape=(n, 2))
    if np.any(scales < 0):
        raise ValueError(f"scales must be >= 0 (linear, not log), got min {scales.min()}")
    opacities = as_array("opacities", opacities, shape=(n,))
    if np.any((opacities < 0) | (opacities > 1)):
        raise ValueError(f"opacities must lie in [0, 1] (not logits), got range [{opacities.min()}, {opacities.max()}]")
    c = colors_or_sh.detach().cpu().numpy() if hasattr(colors_or_sh, "detach") else np.asarray(colors_or_sh)
    if c.ndim == 2:
        sh = rgb_to_sh_dc(as_array("colors_or_sh", c, shape=(n, 3)))[:, None, :]
    else:
        sh = as_array("colors_or_sh", c, shape=(n, None, 3))
        k = sh.shape[1]
        if int(round(np.sqrt(k))) ** 2 != k:
            raise ValueError(f"colors_or_sh must have K = (degree + 1)^2 coefficients, got K = {k}")
    return SurfelArrays(means, quats, scales, opacities, np.ascontiguousarray(sh, dtype=np.float32))


def _ply_properties(k: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_surfels_ply(path: str | os.PathLike, means, quats, scales, opacities, colors_or_sh, *,
                      sh_degree: int | None = None) -> str:
    """Write surfels as a 3DGS-compatible binary PLY (layout in the module docstring).

    Args:
        path: output ``.ply`` path; written to a temporary sibling, then renamed.
        means: centres [N, 3] (torch or NumPy, any float dtype), scene units.
        quats: rotations [N, 4], (w, x, y, z), any norm.
        scales: linear tangent scales [N, 2] (not log).
        opacities: opacities [N] in [0, 1] (not logits).
        colors_or_sh: RGB [N, 3] in [0, 1] or SH coefficients [N, K, 3].
        sh_degree: pad the SH with zeros to this degree (viewers built for degree 3 expect 45
            ``f_rest``); must be >= the given degree.  ``None`` keeps the given degree.

    Returns:
        ``path`` as a string.

    Raises:
        TypeError, ValueError: invalid arrays (see :func:`surfel_arrays`) or ``sh_degree``.
    """
    s = surfel_arrays(means, quats, scales, opacities, colors_or_sh)
    sh = s.sh
    if sh_degree is not None:
        if int(sh_degree) != sh_degree or sh_degree < s.sh_degree:
            raise ValueError(f"sh_degree must be an integer >= the given degree {s.sh_degree}, got {sh_degree!r}")
        k = (int(sh_degree) + 1) ** 2
        sh = np.concatenate([sh, np.zeros((len(s), k - sh.shape[1], 3), np.float32)], axis=1)
    n, k = len(s), sh.shape[1]
    names = _ply_properties(k)
    data = np.empty((n, len(names)), dtype="<f4")
    data[:, 0:3] = s.means
    data[:, 3:6] = quat_normal(s.quats)
    data[:, 6:9] = sh[:, 0]
    data[:, 9:9 + 3 * (k - 1)] = sh[:, 1:].transpose(0, 2, 1).reshape(n, -1)  # channel-major
    o = np.clip(s.opacities.astype(np.float64), OPACITY_EPS, 1 - OPACITY_EPS)
    col = 9 + 3 * (k - 1)
    data[:, col] = np.log(o) - np.log1p(-o)
    with np.errstate(divide="ignore"):  # zero scales: log -> -inf, clamped just below
        data[:, col + 1:col + 3] = np.maximum(np.log(s.scales.astype(np.float64)), FLAT_LOG_SCALE)
    data[:, col + 3] = FLAT_LOG_SCALE
    data[:, col + 4:col + 8] = s.quats
    header = ("ply\nformat binary_little_endian 1.0\ncomment wtopo surfels (3DGS layout, third scale = log(1e-7))\n"
              f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in names) + "end_header\n")

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(data.tobytes())

    return atomic_write(path, write, suffix=".ply")


_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
              "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2",
              "int32": "<i4", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}


def _read_vertex_table(path: str) -> np.ndarray:
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path} is not a PLY file (missing 'ply' magic)")
        fmt, count, props, element = None, None, [], None
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header")
            tok = line.decode("ascii", errors="replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "end_header":
                break
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                element = tok[1]
                if element == "vertex":
                    count = int(tok[2])
                elif count is not None:
                    break  # the vertex element must come first; later elements are not read
            elif tok[0] == "property" and element == "vertex":
                if tok[1] == "list":
                    raise ValueError(f"{path}: list properties in the vertex element are not supported")
                if tok[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {tok[1]!r}")
                props.append((tok[2], _PLY_TYPES[tok[1]]))
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: surfel PLY must be binary_little_endian, got {fmt!r}")
        if count is None:
            raise ValueError(f"{path}: PLY has no vertex element")
        if element != "vertex":  # skip to end_header when later elements were declared
            while line.strip() != b"end_header":
                line = f.readline()
                if not line:
                    raise ValueError(f"{path}: PLY header has no end_header")
        dtype = np.dtype(props)
        raw = f.read(dtype.itemsize * count)
    if len(raw) != dtype.itemsize * count:
        raise ValueError(f"{path}: expected {count} vertices ({dtype.itemsize * count} bytes), got {len(raw)} bytes")
    return np.frombuffer(raw, dtype=dtype, count=count)


def read_surfels_ply(path: str | os.PathLike) -> SurfelArrays:
    """Read a 3DGS / 2DGS PLY written by :func:`write_surfels_ply` (or by 3DGS / 2DGS themselves).

    Opacities are passed through the sigmoid, scales through ``exp``; the third scale of a 3DGS
    file is dropped (surfels keep the two tangent scales), quaternions are normalised.

    Returns:
        :class:`SurfelArrays` (float32 NumPy).

    Raises:
        ValueError: not a binary little-endian PLY, or a required property is missing.
    """
    path = os.fspath(path)
    v = _read_vertex_table(path)
    names = v.dtype.names
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [p for p in need if p not in names]
    if missing:
        raise ValueError(f"{path}: not a Gaussian-splat PLY, missing properties {missing}")
    col = lambda *ps: np.stack([np.asarray(v[p], np.float64) for p in ps], axis=1)  # noqa: E731
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    k = 1 + n_rest // 3
    if n_rest % 3 or int(round(np.sqrt(k))) ** 2 != k:
        raise ValueError(f"{path}: {n_rest} f_rest properties do not form a full SH degree")
    sh = np.empty((len(v), k, 3), np.float32)
    sh[:, 0] = col("f_dc_0", "f_dc_1", "f_dc_2")
    if n_rest:
        sh[:, 1:] = col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(len(v), 3, k - 1).transpose(0, 2, 1)
    logit = np.asarray(v["opacity"], np.float64)
    return SurfelArrays(
        means=col("x", "y", "z").astype(np.float32),
        quats=normalize_quats(col("rot_0", "rot_1", "rot_2", "rot_3")).astype(np.float32),
        scales=np.exp(col("scale_0", "scale_1")).astype(np.float32),
        opacities=(0.5 * (1 + np.tanh(0.5 * logit))).astype(np.float32),  # overflow-free sigmoid
        sh=sh,
    )


def export_mesh(mesh, path: str | os.PathLike) -> str:
    """Write a triangle mesh with trimesh; the format follows the suffix (``.ply``, ``.obj``, ``.stl``, ``.glb``).

    Args:
        mesh: a ``trimesh.Trimesh`` or a ``(verts [V, 3], faces [F, 3])`` pair (torch or NumPy).
        path: output path; written to a temporary sibling, then renamed.

    Returns:
        ``path`` as a string.

    Raises:
        ValueError: unsupported suffix, bad shapes, face indices out of range, non-finite vertices.
    """
    import trimesh

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".ply", ".obj", ".stl", ".glb", ".off"):
        raise ValueError(f"path must end in .ply, .obj, .stl, .glb or .off, got {path!r}")
    if isinstance(mesh, trimesh.Trimesh):
        verts, faces = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        verts, faces = mesh
    else:
        raise TypeError(f"mesh must be a trimesh.Trimesh or a (verts, faces) pair, got {type(mesh).__name__}")
    verts = as_array("verts", verts, shape=(None, 3), dtype=np.float64)
    faces = as_array("faces", faces, shape=(None, 3), dtype=np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"faces must index [0, {len(verts)}), got range [{faces.min()}, {faces.max()}]")
    tm = trimesh.Trimesh(verts, faces, process=False)
    atomic_write(path, lambda tmp: tm.export(tmp, file_type=ext[1:]), suffix=ext)
    return path

