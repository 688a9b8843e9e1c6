# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of TSDF fusion (:func:`wtopo.tsdf_fusion.fuse_tsdf`): per-voxel integration of
z-depth (and colour) maps over every view, and the block test that skips voxels no view's
truncation band reaches.

Grid: node ``(i, j, k)`` sits at ``lower + (i, j, k) * voxel``; the wrapper processes the grid in
z-slabs of nodes ``k0 .. k0 + nz - 1``, stored ``[nx, ny, nz]`` with ``k`` fastest. One thread owns
one node and loops over all views, so no thread writes another's output (the CPU launches are
split across threads) and nothing is allocated per view.

Per view, a node is projected through the camera's own lens (world -> camera, ``x / z``, OpenCV
radial-tangential distortion, skewed ``K``; pixel centres at ``+0.5``) and reads the depth ``d``
of the pixel it falls in, as Open3D's integrator reads the nearest pixel. With ``z`` the node's
camera depth and ``m = |p_cam| / z`` its ray length per unit depth, ``sdf = (d - z) * m``; a view
contributes when ``0 < d < far`` and ``sdf > -truncation``, with ``min(1, sdf / truncation)`` and
weight 1 (Open3D's ``ScalableTSDFVolume`` rule; it takes ``m`` at the pixel centre's ray instead
of the node's, a difference below a pixel's angle). The stored value is the mean of the
contributions; a node no view contributes to is *unobserved*. An unobserved node that some view's
ray crosses on its way to no surface (the node projects into the image, in front of the camera, onto a
pixel without depth: ``d <= 0`` or ``d >= far``) is *seen free*; one that is not, but lies deeper than
the truncation behind some view's depth, is *hidden*; the others lie outside every view.

The module is discrete (``enable_backward=False``).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

vec3ub = wp.types.vector(length=3, dtype=wp.uint8)
"""RGB colour, 8 bits per channel."""

# A mean TSDF closer to 0 than this is moved to +-MIN_ABS_TSDF (0 to +MIN_ABS_TSDF, the side marching
# cubes calls outside): no vertex then lies within 1 / (1 + MIN_ABS_TSDF) of an edge's far end, so float32
# vertex coordinates in index space (resolution 6e-5 at 1024 nodes) never round an edge whose far end is
# unobserved onto its observed end (wtopo.tsdf_fusion keeps a face only when both ends of each of its
# vertices' edges are observed). The surface moves by at most MIN_ABS_TSDF * truncation (0.004 voxel at the
# default 4-voxel truncation).
MIN_ABS_TSDF = wp.constant(1.0e-3)
UNOBSERVED_TSDF = wp.constant(1.0)  # unobserved nodes are outside: they never make an inside region of their own
DEPTH_NONE_MIN = wp.constant(3.0e38)  # min-depth of a texel holding no valid depth (greater than any depth)
DEPTH_NONE_MAX = wp.constant(-3.0e38)  # max-depth of a texel holding no valid depth
# Block test: at most this many texels per axis are read from the depth-range pyramid. The coarser the texels, the
# wider the window and its depth range (self-occlusion edges, grazing views) and the more blocks pass. Measured on
# the bunny, 48 views of 160 x 120, 192^3: 2 texels mark 75 % of the blocks, 4: 53 %, 8: 42 %, 16: 39 % (blocks
# holding a node with TSDF < 1: 22 %; the rest is the box's own depth and its one-node growth); 8 (at most 64 reads)
# costs 0.07 s against the fusion's 1.5 s there.
QUERY_TEXELS = wp.constant(8)
OBS_NONE = wp.constant(wp.uint8(0))  # ``observed``: no view contributed and none saw the node free
OBS_TSDF = wp.constant(wp.uint8(1))  # ``observed``: some view contributed a TSDF value
OBS_FREE = wp.constant(wp.uint8(2))  # ``observed``: no contribution, but a ray through the node found no surface
OBS_HIDDEN = wp.constant(wp.uint8(3))  # ``observed``: no contribution, not seen free, behind some view's surface
BEHIND = wp.constant(1.0e-12)  # camera depth at or below which a point is behind the camera (depth units)


@wp.struct
class View:
    """One camera of the fusion (float32, world units of the grid).

    Attributes:
        rotation: world-to-camera rotation.
        translation: world-to-camera translation.
        fx: focal length along x [px].
        fy: focal length along y [px].
        cx: principal point x [px] (pixel centres at ``+0.5``).
        cy: principal point y [px].
        skew: ``K[0, 1]`` [px].
        k1: OpenCV radial coefficient.
        k2: OpenCV radial coefficient.
        k3: OpenCV radial coefficient.
        p1: OpenCV tangential coefficient.
        p2: OpenCV tangential coefficient.
        distorted: 1 when the distortion applies.
        radius2: squared undistorted normalised radius of the lens's field; beyond it a polynomial
            lens model folds back into the image, so nothing there is seen (only with ``distorted``).
        width: image width [px].
        height: image height [px].
        far: depths at or beyond this are no data (the per-view cut-off).
        offset: index of the view's first pixel in the flat depth and colour buffers (row-major).
    """

    rotation: wp.mat33
    translation: wp.vec3
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float
    k1: float
    k2: float
    k3: float
    p1: float
    p2: float
    distorted: int
    radius2: float
    width: int
    height: int
    far: float
    offset: int


@wp.struct
class Volume:
    """The grid and the slab being processed.

    Attributes:
        lower: world position of node ``(0, 0, 0)``.
        voxel: node spacing (world units).
        truncation: truncation distance (world units).
        k0: first node layer of the slab.
        nx: nodes along x.
        ny: nodes along y.
        nz: node layers in the slab.
        block: nodes per block side (the unit of the block test).
        nbx: blocks along x.
        nby: blocks along y.
        nbz: blocks along z (whole grid).
    """

    lower: wp.vec3
    voxel: float
    truncation: float
    k0: int
    nx: int
    ny: int
    nz: int
    block: int
    nbx: int
    nby: int
    nbz: int


@wp.func
def camera_point(view: View, p: wp.vec3):
    """``p`` (world) in the view's camera frame."""
    return view.rotation * p + view.translation


@wp.func
def image_point(view: View, pc: wp.vec3):
    """Continuous pixel coordinates of camera point ``pc`` (``z > 0``) and whether the lens sees it.

    Returns ``(ok, u, v)``; ``ok`` is false beyond the field's radius of a distorted lens.
    """
    x = pc[0] / pc[2]
    y = pc[1] / pc[2]
    ok = bool(True)
    if view.distorted != 0:
        r2 = x * x + y * y
        if r2 > view.radius2:
            ok = False
        radial = 1.0 + r2 * (view.k1 + r2 * (view.k2 + r2 * view.k3))
        xd = x * radial + 2.0 * view.p1 * x * y + view.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + view.p1 * (r2 + 2.0 * y * y) + 2.0 * view.p2 * x * y
        x = xd
        y = yd
    u = view.fx * x + view.skew * y + view.cx
    v = view.fy * y + view.cy
    return ok, u, v


@wp.func
def node_position(vol: Volume, i: int, j: int, k: int):
    """World position of grid node ``(i, j, k)`` (``k`` counted over the whole grid)."""
    return vol.lower + wp.vec3(float(i), float(j), float(k)) * vol.voxel


@wp.kernel
def integrate_kernel(
    offset: int,
    vol: Volume,
    views: wp.array[View],
    depth: wp.array[wp.float32],
    color: wp.array[vec3ub],
    use_color: int,
    block_active: wp.array3d[wp.uint8],
    use_blocks: int,
    tsdf: wp.array3d[wp.float32],
    observed: wp.array3d[wp.uint8],
    node_color: wp.array3d[vec3ub],
):
    """Fuse every view into the slab's node ``offset + tid`` (flat ``(i * ny + j) * nz + k``).

    Writes the mean TSDF (``UNOBSERVED_TSDF`` where unobserved), ``observed`` (``OBS_TSDF``, ``OBS_FREE``,
    ``OBS_HIDDEN`` or ``OBS_NONE``) and, with
    ``use_color``, the mean colour of the contributing pixels. With ``use_blocks``, nodes of
    blocks whose ``block_active`` is 0 are written as unobserved without projecting.
    """
    n = offset + wp.tid()
    k = n % vol.nz
    j = (n // vol.nz) % vol.ny
    i = n // (vol.nz * vol.ny)
    kg = vol.k0 + k
    if use_blocks != 0 and block_active[i // vol.block, j // vol.block, kg // vol.block] == wp.uint8(0):
        tsdf[i, j, k] = UNOBSERVED_TSDF
        observed[i, j, k] = OBS_NONE
        if use_color != 0:
            node_color[i, j, k] = vec3ub(wp.uint8(0), wp.uint8(0), wp.uint8(0))
        return
    p = node_position(vol, i, j, kg)
    total = float(0.0)
    weight = float(0.0)
    free = int(0)
    hidden = int(0)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    for vi in range(views.shape[0]):
        view = views[vi]
        pc = camera_point(view, p)
        z = pc[2]
        if z > BEHIND:
            ok, u, v = image_point(view, pc)
            # pixel (row, col) covers [col, col + 1) x [row, row + 1) in continuous coordinates
            if ok and u >= 0.0 and v >= 0.0 and u < float(view.width) and v < float(view.height):
                pix = view.offset + int(v) * view.width + int(u)
                d = depth[pix]
                if d > 0.0 and d < view.far:
                    sdf = (d - z) * wp.length(pc) / z
                    if sdf > -vol.truncation:
                        total += wp.min(1.0, sdf / vol.truncation)
                        weight += 1.0
                        if use_color != 0:
                            c = color[pix]
                            rgb += wp.vec3(float(c[0]), float(c[1]), float(c[2]))
                    else:
                        hidden = 1
                else:
                    free = 1
    if weight > 0.0:
        t = total / weight
        if wp.abs(t) < MIN_ABS_TSDF:
            t = wp.where(t < 0.0, -MIN_ABS_TSDF, MIN_ABS_TSDF)
        tsdf[i, j, k] = t
        observed[i, j, k] = OBS_TSDF
        if use_color != 0:
            m = rgb / weight + wp.vec3(0.5, 0.5, 0.5)  # + 0.5: round to the nearest 8-bit value
            node_color[i, j, k] = vec3ub(wp.uint8(int(m[0])), wp.uint8(int(m[1])), wp.uint8(int(m[2])))
    else:
        tsdf[i, j, k] = UNOBSERVED_TSDF
        observed[i, j, k] = wp.where(free != 0, OBS_FREE, wp.where(hidden != 0, OBS_HIDDEN, OBS_NONE))
        if use_color != 0:
            node_color[i, j, k] = vec3ub(wp.uint8(0), wp.uint8(0), wp.uint8(0))


@wp.kernel
def depth_range_base_kernel(
    views: wp.array[View],
    depth: wp.array[wp.float32],
    height: int,
    width: int,
    dmin: wp.array[wp.float32],
    dmax: wp.array[wp.float32],
):
    """Level 0 of the per-view depth range pyramid: each pixel's depth where valid (``0 < d < far``).

    Levels are stored flat, ``[views, height, width]`` each (views padded to the largest image);
    invalid or padding texels get ``DEPTH_NONE_MIN`` / ``DEPTH_NONE_MAX``.
    """
    vi, r, c = wp.tid()
    view = views[vi]
    lo = DEPTH_NONE_MIN
    hi = DEPTH_NONE_MAX
    if r < view.height and c < view.width:
        d = depth[view.offset + r * view.width + c]
        if d > 0.0 and d < view.far:
            lo = d
            hi = d
    out = (vi * height + r) * width + c
    dmin[out] = lo
    dmax[out] = hi


@wp.kernel
def depth_range_reduce_kernel(
    src: int,
    src_height: int,
    src_width: int,
    dst: int,
    height: int,
    width: int,
    dmin: wp.array[wp.float32],
    dmax: wp.array[wp.float32],
):
    """Next pyramid level: texel ``(r, c)`` of level ``dst`` is the range of the 2 x 2 texels
    ``(2r .. 2r+1, 2c .. 2c+1)`` of level ``src`` (those inside it). Both levels live in
    ``dmin`` / ``dmax`` from their flat offsets ``src`` / ``dst``."""
    vi, r, c = wp.tid()
    lo = DEPTH_NONE_MIN
    hi = DEPTH_NONE_MAX
    for dr in range(2):
        for dc in range(2):
            rr = 2 * r + dr
            cc = 2 * c + dc
            if rr < src_height and cc < src_width:
                s = src + (vi * src_height + rr) * src_width + cc
                lo = wp.min(lo, dmin[s])
                hi = wp.max(hi, dmax[s])
    out = dst + (vi * height + r) * width + c
    dmin[out] = lo
    dmax[out] = hi


@wp.func
def range_meets(level: wp.vec4i, vi: int, c0: int, c1: int, r0: int, r1: int, dmin: wp.array[wp.float32],
                dmax: wp.array[wp.float32], lo: float, hi: float):
    """Whether a depth in ``(lo, hi)`` may lie in texels ``[r0, r1] x [c0, c1]`` of pyramid ``level``
    (``(offset, height, width, -)``): their depth range overlaps the interval."""
    meets = bool(False)
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            t = level[0] + (vi * level[1] + r) * level[2] + c
            if dmax[t] > lo and dmin[t] < hi:
                meets = True
    return meets


@wp.kernel
def mark_blocks_kernel(
    offset: int,
    vol: Volume,
    views: wp.array[View],
    levels: wp.array[wp.vec4i],
    dmin: wp.array[wp.float32],
    dmax: wp.array[wp.float32],
    margin_px: float,
    block_active: wp.array3d[wp.uint8],
):
    """Mark block ``offset + tid`` (flat ``(bi * nby + bj) * nbz + bk``) active when some view may put
    one of its nodes, or a node one step outside it, within the truncation band (``|d - z| <
    truncation``, a necessary condition of ``|sdf| < truncation`` since ``|p| / z >= 1``).

    A node whose mean TSDF is below 1 is within the band of a view, and every corner of a cell holding
    such a node lies in a block grown by one node that holds it: fusing only active blocks changes no
    cell that can hold a face. The test per view: the box's camera depth range (exact, from its 8
    corners) against the depth range (pyramid ``levels``, ``(offset, height, width, -)`` per level,
    at most ``QUERY_TEXELS`` texels per axis) over its projected pixel box, grown by ``margin_px`` (+ a
    quarter of its size for a distorted lens, whose image of a box bulges past its corners' box). A
    box partly behind the camera or beyond a distorted lens's field is tested against the whole image.
    """
    n = offset + wp.tid()
    bk = n % vol.nbz
    bj = (n // vol.nbz) % vol.nby
    bi = n // (vol.nbz * vol.nby)
    lo_node = node_position(vol, bi * vol.block - 1, bj * vol.block - 1, bk * vol.block - 1)
    size = float(vol.block + 1) * vol.voxel
    nlev = levels.shape[0]
    active = bool(False)
    vi = int(0)
    while vi < views.shape[0] and not active:
        view = views[vi]
        zmin = float(3.0e38)
        zmax = float(-3.0e38)
        umin = float(3.0e38)
        umax = float(-3.0e38)
        vmin = float(3.0e38)
        vmax = float(-3.0e38)
        whole = bool(False)
        behind = int(0)
        for corner in range(8):
            q = lo_node + wp.vec3(float(corner & 1), float((corner >> 1) & 1), float((corner >> 2) & 1)) * size
            pc = camera_point(view, q)
            zmin = wp.min(zmin, pc[2])
            zmax = wp.max(zmax, pc[2])
            if pc[2] > BEHIND:
                ok, u, v = image_point(view, pc)
                if not ok:
                    whole = True
                umin = wp.min(umin, u)
                umax = wp.max(umax, u)
                vmin = wp.min(vmin, v)
                vmax = wp.max(vmax, v)
            else:
                behind += 1
                whole = True
        if behind < 8:  # a box wholly behind the camera is not seen
            top = levels[nlev - 1]
            c0 = int(0)
            c1 = top[2] - 1
            r0 = int(0)
            r1 = top[1] - 1
            lev = top
            seen = bool(True)
            if not whole:
                grow = margin_px
                if view.distorted != 0:
                    grow += 0.25 * wp.max(umax - umin, vmax - vmin)
                umin = wp.max(umin - grow, 0.0)
                vmin = wp.max(vmin - grow, 0.0)
                umax = wp.min(umax + grow, float(view.width) - 1.0)
                vmax = wp.min(vmax + grow, float(view.height) - 1.0)
                if umin > umax or vmin > vmax:
                    seen = False  # the box projects outside the image
                else:
                    # the finest level at which the pixel box spans at most QUERY_TEXELS texels per axis
                    li = int(0)
                    while li < nlev - 1 and ((int(umax) >> li) - (int(umin) >> li) >= QUERY_TEXELS
                                             or (int(vmax) >> li) - (int(vmin) >> li) >= QUERY_TEXELS):
                        li += 1
                    lev = levels[li]
                    c0 = int(umin) >> li
                    c1 = int(umax) >> li
                    r0 = int(vmin) >> li
                    r1 = int(vmax) >> li
            if seen:
                zlo = wp.max(zmin, 0.0)
                active = range_meets(lev, vi, c0, c1, r0, r1, dmin, dmax, zlo - vol.truncation,
                                     zmax + vol.truncation)
        vi += 1
    block_active[bi, bj, bk] = wp.where(active, wp.uint8(1), wp.uint8(0))
