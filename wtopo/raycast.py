# SPDX-License-Identifier: Apache-2.0
"""Differentiable ray casting of a triangle mesh through a Warp BVH, and nearest-face queries.

The proxy mesh is rendered by casting one ray per pixel (:meth:`wtopo.Camera.pixel_rays`, so any
pinhole or OpenCV-distorted camera works) against a :class:`warp.Mesh` BVH. The first hit is found
without gradients (a conservative sweep of the mesh's BVH per 2x2 pixel packet and Woop's
watertight ray-triangle test, in float32: rays through shared edges and vertices hit exactly
once, which ``wp.mesh_query_ray`` does not guarantee, see ``kernels/raycast.py``); depth and normal are
then recomputed from the hit triangle's three vertices in the caller's precision, so they are
differentiable w.r.t. the vertex positions (the hit face itself is discrete: gradients do not see
silhouettes moving).

:func:`raycast_mesh` and :func:`closest_faces` are stateless; :class:`MeshRaycaster` keeps the BVH
between calls, refitting it when only the positions change and rebuilding it when the faces do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from wtopo import _bridge
from wtopo._profile import section
from wtopo._validate import require_finite, require_same_device, require_tensor, value_checks
from wtopo.camera import Camera
from wtopo.kernels import raycast as _k

__all__ = ["MeshRender", "MeshRaycaster", "raycast_mesh", "closest_faces"]

_MAX_T = float(np.finfo(np.float32).max)  # "no far limit" for the float32 BVH traversal
# Inflation of the BVH boxes in the conservative sweep, relative to the coordinate scale: float32
# slab tests round at ~6e-8 relative, 1e-6 covers their error with margin yet adds few candidates.
_PAD_REL = 1e-6
_BVH_CONSTRUCTORS = ("sah", "median", "lbvh")


@dataclass
class MeshRender:
    """What a mesh looks like from a camera, per ray (``[H, W]`` for one camera, ``[N, H, W]`` for
    ``N`` cameras of one size, the rays' leading shape when ``rays`` are given).

    Attributes:
        depth: z-depth of the first hit in the camera [world units], shape [..., H, W], the dtype of
            ``verts``; 0 on misses. With explicit ``rays`` it is the ray parameter ``t`` (in
            multiples of the direction's length). Differentiable w.r.t. ``verts`` (0 on misses).
        normal: unit face normal in the world frame, oriented by the face winding (outward for
            ``marching_cubes`` output, so it points away from a camera that sees a back face),
            shape [..., H, W, 3], dtype of ``verts``; 0 on misses. Differentiable w.r.t. ``verts``.
        mask: whether the ray hit the mesh, bool, shape [..., H, W]. Discrete.
        face_id: index of the hit face, int32, shape [..., H, W]; -1 on misses. Discrete.
        bary: barycentric weights of the hit face's first and second vertex (the third is
            ``1 - b0 - b1``), shape [..., H, W, 2], dtype of ``verts``; 0 on misses. Discrete
            (from the float32 hit search).
    """

    depth: torch.Tensor
    normal: torch.Tensor
    mask: torch.Tensor
    face_id: torch.Tensor
    bary: torch.Tensor


def _validate_mesh(verts, faces) -> tuple[torch.Tensor, torch.Tensor]:
    require_tensor("verts", verts, shape=(None, 3))
    require_tensor("faces", faces, shape=(None, 3), dtypes=(torch.int32, torch.int64))
    require_same_device(verts=verts, faces=faces)
    require_finite("verts", verts)
    if faces.shape[0] > 0 and value_checks():
        lo, hi = int(faces.min()), int(faces.max())  # host sync: validation only
        if lo < 0 or hi >= verts.shape[0]:
            bad = lo if lo < 0 else hi
            raise ValueError(f"faces must index verts in [0, {verts.shape[0] - 1}], got index {bad}")
    return verts, faces.to(torch.int32).contiguous()


def _spread_bits(x: torch.Tensor) -> torch.Tensor:
    """The low 10 bits of each of ``x`` (int64) spread to every third bit (a 3-D Morton code's lane)."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def _morton3(v: torch.Tensor) -> torch.Tensor:
    """30-bit Morton codes (int64 [M]) of points [M, 3] quantised over their own bounding box."""
    lo, hi = v.min(dim=0).values, v.max(dim=0).values
    q = ((v - lo) / (hi - lo).clamp_min(1e-30) * 1023.0).to(torch.int64).clamp_(0, 1023)
    return _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)


def _coherent_order(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """A permutation (int64 [M]) of the rays ``o``, ``d`` [M, 3] that puts rays of one origin together
    and, within it, neighbouring directions next to each other (Morton order of origin, then of
    direction): a packet of four unrelated rays would sweep most of the BVH."""
    return torch.argsort((_morton3(o) << 30) | _morton3(d))


def _fours(order: torch.Tensor) -> torch.Tensor:
    """Ray indices [P, 4] (int32, -1 = unused): ``order`` (int [M]) cut into packets of four."""
    n = order.shape[0]
    table = torch.full((n + (-n) % 4,), -1, dtype=torch.int32, device=order.device)
    table[:n] = order.to(torch.int32)
    return table.reshape(-1, 4)


def _list_packets(o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Ray indices [P, 4] (int32, -1 = unused) grouping a 1-D ray list ``o``, ``d`` [M, 3] in fours of
    :func:`_coherent_order` (the sweep writes each ray's hit at its own index, so nothing is put back)."""
    return _fours(_coherent_order(o, d))


def _camera_rays(camera, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    if isinstance(camera, Camera):
        return camera.pixel_rays(device, dtype)
    if isinstance(camera, Sequence) and not isinstance(camera, str) and len(camera) > 0 \
            and all(isinstance(c, Camera) for c in camera):
        sizes = {(c.height, c.width) for c in camera}
        if len(sizes) != 1:
            raise ValueError(f"camera: a batch of cameras must share one image size, got sizes {sorted(sizes)}")
        rays = [c.pixel_rays(device, dtype) for c in camera]
        return torch.stack([r[0] for r in rays]), torch.stack([r[1] for r in rays])
    raise TypeError(f"camera must be a wtopo.Camera or a non-empty sequence of them, got {type(camera).__name__}")


def _validate_rays(rays, device) -> tuple[torch.Tensor, torch.Tensor]:
    if not isinstance(rays, (tuple, list)) or len(rays) != 2:
        raise TypeError(f"rays must be a pair (origins, directions), got {type(rays).__name__}")
    o, d = rays
    require_tensor("rays[0] (origins)", o)
    require_tensor("rays[1] (directions)", d)
    if o.ndim < 1 or o.shape[-1] != 3 or o.shape != d.shape:
        raise ValueError(f"rays must be origins and directions of one shape [..., 3], got {list(o.shape)} "
                         f"and {list(d.shape)}")
    if o.device != torch.device(device) or d.device != torch.device(device):
        raise ValueError(f"rays must be on the device of verts ({device}), got {o.device} and {d.device}")
    require_finite("rays[0] (origins)", o)
    require_finite("rays[1] (directions)", d)
    return o, d


class _Launcher:
    """Runs discrete launches on the torch device (and torch's current CUDA stream)."""

    def __init__(self, device: torch.device):
        self.wdev = _bridge.warp_device(device)
        self.stream = wp.stream_from_torch(device) if self.wdev.is_cuda else None

    def __enter__(self):
        self._ctx = [wp.ScopedDevice(self.wdev)]
        if self.stream is not None:
            self._ctx.append(wp.ScopedStream(self.stream))
        for c in self._ctx:
            c.__enter__()
        return self

    def __exit__(self, *exc):
        for c in reversed(self._ctx):
            c.__exit__(*exc)


def _shade_run(verts, faces, face_id, origins, directions):
    n = face_id.shape[0]
    tape = _bridge.active_tape()  # None: nothing differentiates this call, no gradient arrays
    depth = _bridge.empty(n, verts.dtype._wp_scalar_type_, verts.device, requires_grad=tape is not None, zero=True)
    normal = _bridge.empty(n, verts.dtype, verts.device, requires_grad=tape is not None, zero=True)
    inputs = [verts, faces, face_id, origins, directions]
    # per-ray disjoint writes: split over CPU threads; the adjoint scatters into verts.grad with
    # atomics, so it is one launch, registered on the bridge's tape by hand
    _bridge.launch_split(_k.shade_hits_kernel, n, inputs, [depth, normal], device=verts.device, min_chunk=16384)
    if tape is not None and verts.requires_grad:

        def backward():
            _bridge.launch(_k.shade_hits_kernel, dim=n, inputs=[0, *inputs], outputs=[depth, normal],
                      adj_inputs=[0, verts.grad, None, None, None, None], adj_outputs=[depth.grad, normal.grad],
                      adjoint=True, device=verts.device)

        tape.record_func(backward, [verts, depth, normal])
    return depth, normal


_SHADE_OPS = {
    dt: _bridge.WarpOp(
        name="raycast_mesh.shade",
        run=_shade_run,
        in_dtypes=(vec, wp.int32, wp.int32, vec, vec),
        differentiable_inputs=(True, False, False, False, False),
        differentiable_outputs=(True, True),
    )
    for dt, vec in ((torch.float32, wp.vec3), (torch.float64, wp.vec3d))
}


def _empty_like_graph(verts: torch.Tensor, shape) -> torch.Tensor:
    """Zeros of ``shape`` that still depend on ``verts`` (zero gradient, EMPTY case)."""
    z = torch.zeros(shape, dtype=verts.dtype, device=verts.device)
    return z + (verts * 0).sum() if verts.requires_grad else z


class MeshRaycaster:
    """Ray casting and nearest-face context that keeps a :class:`warp.Mesh` BVH between calls.

    Each call hands over the current ``verts`` and ``faces``: when the faces (topology) or the
    vertex count differ from the previous call the BVH is rebuilt, otherwise the positions are
    copied into the BVH's own float32 buffer and the BVH is refitted (much cheaper). A mesh with no
    faces never builds a :class:`warp.Mesh` (an empty one corrupts Warp's CUDA allocator, Warp
    #1765).

    Args:
        bvh_constructor: ``"sah"`` (CPU default), ``"median"`` or ``"lbvh"`` (CUDA default; Warp
            falls back to SAH on CPU); ``None`` takes Warp's default for the device.
        bvh_leaf_size: triangles per BVH leaf; ``None`` takes Warp's default (4).
        conservative: find hits with the conservative packet sweep (watertight: rays through shared
            edges and vertices hit exactly once). ``False`` uses ``wp.mesh_query_ray`` per ray,
            whose rounding in box tests can let such rays miss or reach a farther surface.

    Limitations:
        The BVH and the hit search are float32 whatever the dtype of ``verts``: keep coordinates
        centred and scaled (the pipeline's internal frame) so float32 resolves the triangles.
        A hit is accepted for ray parameter ``t >= 0``: a camera inside a closed mesh sees the
        back faces of the surrounding surface (``normal`` then points away from the camera), a
        ray starting exactly on a triangle may hit it at ``t = 0``.
    """

    def __init__(self, *, bvh_constructor: str | None = None, bvh_leaf_size: int | None = None,
                 conservative: bool = True):
        if bvh_constructor is not None and bvh_constructor not in _BVH_CONSTRUCTORS:
            raise ValueError(f"bvh_constructor must be one of {_BVH_CONSTRUCTORS} or None, got {bvh_constructor!r}")
        if bvh_leaf_size is not None and (isinstance(bvh_leaf_size, bool) or not isinstance(bvh_leaf_size, int)
                                          or bvh_leaf_size < 1):
            raise ValueError(f"bvh_leaf_size must be an int >= 1 or None, got {bvh_leaf_size!r}")
        self.bvh_constructor = bvh_constructor
        self.bvh_leaf_size = bvh_leaf_size
        self.conservative = bool(conservative)
        self._bounds: torch.Tensor | None = None  # float32 [2, 3] lower, upper of the mesh
        self._packets: dict = {}  # ray-shape -> int32 [P, 4] ray indices of 2x2 packets
        self._mesh: wp.Mesh | None = None
        self._points: torch.Tensor | None = None  # float32 [V, 3], aliased by the wp.Mesh
        self._faces: torch.Tensor | None = None  # int32 [F, 3], aliased by the wp.Mesh
        self.builds = 0
        """Number of BVH builds so far (refits are not counted)."""
        self.refits = 0
        """Number of BVH refits so far."""

    # -- BVH -------------------------------------------------------------------------------------
    def update(self, verts: torch.Tensor, faces: torch.Tensor) -> MeshRaycaster:
        """Bring the BVH up to date with ``verts`` [V, 3] and ``faces`` [F, 3] (rebuild or refit).

        Args:
            verts: vertex positions [world units], shape [V, 3], float32 or float64.
            faces: vertex indices, shape [F, 3], int32 or int64.

        Returns:
            ``self``.
        """
        verts, faces = _validate_mesh(verts, faces)
        self._update(verts, faces)
        return self

    def _update(self, verts: torch.Tensor, faces: torch.Tensor) -> None:
        with section("bvh_build"):
            self._update_bvh(verts, faces)

    def _update_bvh(self, verts: torch.Tensor, faces: torch.Tensor) -> None:
        pts = verts.detach().to(torch.float32)
        same = (self._faces is not None and self._points is not None and self._faces.device == faces.device
                and self._points.shape == pts.shape and self._faces.shape == faces.shape
                and torch.equal(self._faces, faces))
        if same:
            if self._mesh is not None:
                self._points.copy_(pts)
                with _Launcher(verts.device):
                    self._mesh.refit()
                self._bounds = torch.stack([self._points.min(0).values, self._points.max(0).values])
                self.refits += 1
            return
        self._mesh = None
        self._points = pts.contiguous().clone()
        self._faces = faces.clone()
        if faces.shape[0] == 0:
            return  # never build an empty wp.Mesh (Warp #1765)
        with _Launcher(verts.device):
            kwargs = {}
            if self.bvh_constructor is not None:
                kwargs["bvh_constructor"] = self.bvh_constructor
            if self.bvh_leaf_size is not None:
                kwargs["bvh_leaf_size"] = self.bvh_leaf_size
            self._mesh = wp.Mesh(points=wp.from_torch(self._points, dtype=wp.vec3),
                                 indices=wp.from_torch(self._faces.view(-1), dtype=wp.int32), **kwargs)
        self._bounds = torch.stack([self._points.min(0).values, self._points.max(0).values])
        self.builds += 1

    # -- queries ---------------------------------------------------------------------------------
    def raycast(self, verts: torch.Tensor, faces: torch.Tensor, camera=None, *, rays=None) -> MeshRender:
        """Cast rays from ``camera`` (or explicit ``rays``) at the mesh; see :func:`raycast_mesh`."""
        verts, faces = _validate_mesh(verts, faces)
        if rays is None:
            if camera is None:
                raise TypeError("raycast_mesh needs a camera or rays, got neither")
            o, d = _camera_rays(camera, verts.device, verts.dtype)
            o32, d32 = _camera_rays(camera, verts.device, torch.float32)
        else:
            o, d = _validate_rays(rays, verts.device)
            o, d = o.to(verts.dtype), d.to(verts.dtype)
            o32, d32 = o.to(torch.float32), d.to(torch.float32)
        shape = tuple(o.shape[:-1])
        n = int(np.prod(shape, dtype=np.int64))
        self._update(verts, faces)
        device = verts.device
        if self._mesh is None or n == 0:
            face_id = torch.full((n,), -1, dtype=torch.int32, device=device)
            bary32 = torch.zeros((n, 2), dtype=torch.float32, device=device)
            return MeshRender(
                depth=_empty_like_graph(verts, shape),
                normal=_empty_like_graph(verts, (*shape, 3)),
                mask=torch.zeros(shape, dtype=torch.bool, device=device),
                face_id=face_id.reshape(shape),
                bary=bary32.to(verts.dtype).reshape(*shape, 2),
            )
        face_id = torch.empty((n,), dtype=torch.int32, device=device)  # every ray is written
        bary32 = torch.empty((n, 2), dtype=torch.float32, device=device)
        o32, d32 = o32.reshape(-1, 3).contiguous(), d32.reshape(-1, 3).contiguous()
        o_w = wp.from_torch(o32, dtype=wp.vec3)
        d_w = wp.from_torch(d32, dtype=wp.vec3)
        outs = [wp.from_torch(face_id, dtype=wp.int32), wp.from_torch(bary32, dtype=wp.vec2)]
        with _Launcher(device) as launcher:
            if self.conservative:
                packets = self._packet_table(shape, device) if len(shape) >= 2 else _list_packets(o32, d32)
                _bridge.launch_split(
                    _k.cast_packets_kernel, packets.shape[0],
                    [self._mesh.id, wp.from_torch(packets), o_w, d_w,
                     wp.from_torch(self._bounds, dtype=wp.vec3), _PAD_REL],
                    outs, device=launcher.wdev, min_chunk=256)
            else:
                _bridge.launch_split(_k.cast_rays_kernel, n, [self._mesh.id, o_w, d_w, _MAX_T], outs,
                                     device=launcher.wdev, min_chunk=1024)
        depth, normal = _bridge.apply(_SHADE_OPS[verts.dtype], verts, faces.reshape(-1), face_id,
                                      o.reshape(-1, 3), d.reshape(-1, 3))
        return MeshRender(
            depth=depth.reshape(shape),
            normal=normal.reshape(*shape, 3),
            mask=(face_id >= 0).reshape(shape),
            face_id=face_id.reshape(shape),
            bary=bary32.to(verts.dtype).reshape(*shape, 2),
        )

    def _packet_table(self, shape: tuple, device) -> torch.Tensor:
        """Ray indices [P, 4] (int32, -1 = unused) grouping the rays of images ``shape`` = [..., H, W]
        in 2x2 tiles; cached per shape (a 1-D ray list is grouped by :func:`_list_packets`)."""
        key = (shape, str(device))
        if key not in self._packets:
            n = int(np.prod(shape, dtype=np.int64))
            idx = torch.arange(n, dtype=torch.int32, device=device)
            h, w = shape[-2], shape[-1]
            hp, wp_ = h + h % 2, w + w % 2
            grid = torch.full((n // (h * w), hp, wp_), -1, dtype=torch.int32, device=device)
            grid[:, :h, :w] = idx.reshape(-1, h, w)
            table = grid.reshape(-1, hp // 2, 2, wp_ // 2, 2).permute(0, 1, 3, 2, 4).reshape(-1, 4)
            self._packets = {key: table.contiguous()}  # keep one: shapes rarely alternate
        return self._packets[key]

    def closest_faces(self, verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, *,
                      max_distance: float | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Nearest face to each point; see :func:`closest_faces`."""
        verts, faces = _validate_mesh(verts, faces)
        require_tensor("points", points, shape=(None, 3))
        require_same_device(verts=verts, points=points)
        require_finite("points", points)
        if max_distance is None:
            limit = _MAX_T
        else:
            try:
                limit = float(max_distance)
            except (TypeError, ValueError):
                raise TypeError(f"max_distance must be a number or None, got {max_distance!r}") from None
            if not limit > 0:  # also rejects NaN
                raise ValueError(f"max_distance must be > 0, got {max_distance!r}")
            limit = min(limit, _MAX_T)
        self._update(verts, faces)
        p = points.shape[0]
        device = points.device
        face_id = torch.full((p,), -1, dtype=torch.int32, device=device)
        distance = torch.full((p,), float("inf"), dtype=torch.float32, device=device)
        closest = torch.zeros((p, 3), dtype=torch.float32, device=device)
        if self._mesh is not None and p > 0:
            with _Launcher(device) as launcher:
                _bridge.launch_split(
                    _k.closest_faces_kernel, p,
                    [self._mesh.id, wp.from_torch(points.detach().to(torch.float32).contiguous(), dtype=wp.vec3),
                     limit],
                    [wp.from_torch(face_id, dtype=wp.int32), wp.from_torch(distance, dtype=wp.float32),
                     wp.from_torch(closest, dtype=wp.vec3)],
                    device=launcher.wdev, min_chunk=1024)
        return face_id, distance.to(points.dtype), closest.to(points.dtype)


def raycast_mesh(verts: torch.Tensor, faces: torch.Tensor, camera, *, rays=None) -> MeshRender:
    """Render a triangle mesh by casting one ray per pixel against a BVH.

    Stateless: builds a BVH for this call. Use :class:`MeshRaycaster` to keep it across calls.

    Args:
        verts: vertex positions [world units], shape [V, 3], float32 or float64, any device.
            Depth and normal are differentiable w.r.t. ``verts``.
        faces: vertex indices, shape [F, 3], int32 or int64, same device; discrete. ``F = 0`` gives
            an all-miss render (zero gradients) without building a BVH.
        camera: a :class:`wtopo.Camera` (outputs [H, W]), or a sequence of ``N`` cameras of one
            image size (outputs [N, H, W]); may be ``None`` when ``rays`` are given.
        rays: optional ``(origins, directions)``, each shape [..., 3] float, world frame, replacing
            the camera's rays; outputs then have shape [...] and ``depth`` is the ray parameter
            ``t`` (the z-depth only when the direction's camera-z component is 1, as for
            :meth:`wtopo.Camera.pixel_rays`). Directions need not be unit length. Discrete.

    Returns:
        A :class:`MeshRender`.

    Raises:
        TypeError: wrong argument types or dtypes, no camera and no rays.
        ValueError: wrong shapes, non-finite values, face indices out of range, mixed devices,
            cameras of different sizes.
    """
    return MeshRaycaster().raycast(verts, faces, camera, rays=rays)


def closest_faces(verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, *,
                  max_distance: float | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest triangle of a mesh to each query point (``wp.mesh_query_point_no_sign``). Discrete.

    Stateless: builds a BVH for this call. Use :meth:`MeshRaycaster.closest_faces` to keep it.

    Args:
        verts: vertex positions [world units], shape [V, 3], float32 or float64.
        faces: vertex indices, shape [F, 3], int32 or int64.
        points: query points [world units], shape [P, 3], float32 or float64, same device.
        max_distance: search radius [world units]; ``None`` searches without limit.

    Returns:
        ``(face_id, distance, closest)``: int32 [P] index of the nearest face (-1 when none lies
        within ``max_distance`` or the mesh has no faces), [P] Euclidean distance (inf where
        ``face_id`` is -1) and [P, 3] closest point on the mesh (0 where ``face_id`` is -1), both
        in the dtype of ``points`` (computed in float32). Not differentiable.
    """
    return MeshRaycaster().closest_faces(verts, faces, points, max_distance=max_distance)
