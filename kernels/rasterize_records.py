# SPDX-License-Identifier: Apache-2.0
"""Argument records and float32 / float64 overloads of the rasterizer kernels (:mod:`.rasterize`,
:mod:`.rasterize_binning`).

Warp structs cannot be generic, so :func:`float_structs` builds one ``@wp.struct`` per float dtype
from a template class: :class:`CameraRecord` (everything the kernels read per view, ``CAMERA``) and
:class:`SurfelRecord` (what the pixel kernels test per surfel, ``SURFEL``).
:func:`declare_float_overloads` instantiates a generic kernel for both dtypes, looking up each
argument's role by its name.
"""

from typing import Any

import warp as wp

# Warp types of each argument role, per float dtype: kernels are generic (``typing.Any``) and
# instantiated for both dtypes by :func:`declare_float_overloads`; records by :func:`float_structs`.
_TYPES = {
    wp.float32: {"s": wp.float32, "v2": wp.vec2, "v3": wp.vec3, "v4": wp.vec4, "m33": wp.mat33, "int": int,
                 "s_array": wp.array(dtype=wp.float32)},
    wp.float64: {"s": wp.float64, "v2": wp.vec2d, "v3": wp.vec3d, "v4": wp.vec4d, "m33": wp.mat33d, "int": int,
                 "s_array": wp.array(dtype=wp.float64)},
}


def float_structs(template: type) -> dict:
    """One ``@wp.struct`` per float dtype from a template class annotated with roles of ``_TYPES``.

    Warp structs cannot be generic, so the float32 and float64 records are two types built from
    one field list; generic kernels take them as ``typing.Any`` arguments.

    Returns:
        ``{wp.float32: struct, wp.float64: struct}``, named ``<template>_float32`` and ``_float64``.
    """
    out = {}
    for scalar, table in _TYPES.items():
        name = f"{template.__name__}_{scalar.__name__}"
        fields = {k: table[role] for k, role in template.__annotations__.items()}
        ns = {"__annotations__": fields, "__module__": __name__, "__qualname__": name, "__doc__": template.__doc__}
        out[scalar] = wp.struct(type(name, (), ns))
    return out


class CameraRecord:
    """Per-view constants of the rasterizer kernels (op dtype; ``wtopo.rasterize._camera._camera_record``), read
    from a one-element array in device memory (``cams[0]``): the clip planes are computed on the device and written
    into it, and a CUDA graph of the rasterizer can take a view's record as an input.

    Attributes:
        near: the near plane (z-depth, world units; contributions in front of it are skipped).
        far: the far value of the distortion depth mapping (world units).
        R: world-to-camera rotation, camera = ``R world + t``.
        t: world-to-camera translation [world units].
        center: camera centre in world coordinates [world units].
        fx, fy, cx, cy, skew: pinhole intrinsics [pixels] (``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``).
        k1, k2, p1, p2, k3: OpenCV distortion coefficients (0 without distortion).
        filter_inv_sq: ``1 / filter_sigma^2`` of the screen-space low-pass [1/px^2].
        width, height: image size [pixels].
    """

    near: "s"
    far: "s"
    R: "m33"
    t: "v3"
    center: "v3"
    fx: "s"
    fy: "s"
    cx: "s"
    cy: "s"
    skew: "s"
    k1: "s"
    k2: "s"
    p1: "s"
    p2: "s"
    k3: "s"
    filter_inv_sq: "s"
    width: "int"
    height: "int"


class SurfelRecord:
    """What the pixel kernels test for every (pixel, surfel) pair, packed per surfel (:func:`pack_surfels_kernel`).

    One record (16 scalars: a 64-byte cache line in float32) instead of seven arrays: the pair
    loop is bound by these loads, most pairs being rejected.

    Attributes:
        U, V: tangent axes divided by the scales (``uax``, ``vax``).
        n: plane normal.
        auv: ``(a.U, a.V, a.n)`` with ``a = camera centre - surfel centre``.
        m2: projected centre [pixels].
        zc: centre z-depth [world units].
        cutoff: exponent above which alpha < 1/255 for sure (negative: culled).
    """

    U: "v3"
    V: "v3"
    n: "v3"
    auv: "v3"
    m2: "v2"
    zc: "s"
    cutoff: "s"


CAMERA = float_structs(CameraRecord)
SURFEL = float_structs(SurfelRecord)


# -- explicit float32 / float64 overloads ----------------------------------------------------
# Declared up front so each module compiles once with every overload, instead of being rebuilt
# each time a new (kernel, dtype) pair is first launched (measured: 4+ rebuilds per dtype).

_VEC_LEN = {
    "s": ["zc", "cutoff", "opacity", "opacities", "alpha", "depth", "median", "distortion", "t_final",
          "g_alpha", "g_depth", "g_median", "g_dist", "d_zc", "d_opacity", "g_zc", "g_opacity", "run_t", "run_rg"],
    "v2": ["scales", "m2", "means2d", "d_m2", "g_m2", "g_shift"],
    "v3": ["means", "uax", "vax", "nrm", "auv", "nrm_face", "color", "background", "sh", "rays", "rgb", "normal",
           "sums", "g_rgb", "g_normal", "d_uax", "d_vax", "d_nrm", "d_auv", "d_nrm_face", "d_color", "g_uax", "g_vax",
           "g_nrm", "g_auv", "g_nrm_face", "g_color"],
    "v4": ["quats", "agg", "geo4"],
    "cam": ["cam", "cams"],
    "rec": ["geo"],
}
_ROLE = {name: kind for kind, names in _VEC_LEN.items() for name in names}
for _scalar, _table in _TYPES.items():
    _table["cam"] = CAMERA[_scalar]
    _table["rec"] = SURFEL[_scalar]


def declare_float_overloads(kernel) -> None:
    """Instantiate a generic kernel for float32 and float64 (argument roles looked up by name).

    ``Any`` arguments (the records) take the role's type, ``wp.array[Any]`` arguments arrays of it.
    """
    for table in _TYPES.values():
        types = {}
        for arg in kernel.adj.args:
            if arg.label not in _ROLE:
                continue
            if arg.type is Any:
                types[arg.label] = table[_ROLE[arg.label]]
            elif getattr(arg.type, "dtype", None) is Any:
                types[arg.label] = wp.array(dtype=table[_ROLE[arg.label]], ndim=arg.type.ndim)
        wp.overload(kernel, types)
