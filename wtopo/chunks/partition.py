# SPDX-License-Identifier: Apache-2.0
"""Spatial partition of a scene's region of interest into overlapping chunks, and the chunk plan.

The region of interest (``Scene.region_of_interest()``, world frame) is cut into a grid of boxes
along its longest axes. Each grid cell is a chunk's *core*; the cores tile the region of interest
and are disjoint (half-open along the cut axes; the outermost cells reach to infinity, so every
point of space belongs to exactly one core). A chunk's *box* is its core grown by the overlap
margin across every cut it shares with a neighbour (the region of interest's outer faces stay):
it is fitted as a normal :func:`wtopo.fit` with ``Scene.bounds`` set to it and the cameras that
see enough of it, and the merge keeps what lies in its core.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["ChunkConfig", "Chunk", "ChunkPlan", "plan_chunks", "chunk_grid", "assign_cameras", "view_shares",
           "core_owner"]

# Per-view bytes on the fit's device, per pixel: colour, depth, normal (7 floats), the mask and the
# cached pixel rays (6 floats) and the rasterizer's per-pixel outputs (about as many again): a rough
# upper bound from the tensors the fit keeps per training view, not a measurement.
_BYTES_PER_PIXEL = 104
# Dense grids of the proxy and final meshing (Poisson FFT fields, TSDF volume, scatter targets):
# float32 arrays of the grid's size the fit holds at once, a rough count from the modules
# (poisson.py's complex FFT buffers count twice).
_GRID_ARRAYS = 12
_BYTES_PER_SURFEL = 4 * 64  # means, quats, scales, opacity, SH (degree 3) and their Adam moments
_RAY_GRID = 32  # rays per image row for the camera assignment (32 x 24 on a 4:3 image)
_RAY_SAMPLES = 32  # samples along each ray's segment through the region of interest


@dataclass(kw_only=True)
class ChunkConfig:
    """How a scene is cut into chunks and how they are merged.

    ``chunks`` and ``grid`` override the plan's decision; with neither, the plan picks the count
    from the cameras, the region's extent and the memory available (:func:`plan_chunks`).
    """

    chunks: int | None = None
    """Number of chunks (>= 1); the grid is chosen along the longest axes. ``None``: the plan decides."""
    grid: tuple[int, int, int] | None = None
    """Cells per world axis (x, y, z), overriding ``chunks``."""
    overlap: float = 0.15
    """Overlap margin on each side of a cut, as a fraction of the core's side along that axis."""
    min_share: float = 0.1
    """A camera is given to a chunk when at least this fraction of its image is expected to show
    the chunk's box (:func:`view_shares`: rays clipped to the region of interest, the surface
    anywhere along them)."""
    min_views: int = 3
    """A chunk seen by fewer cameras is skipped (recorded in the plan): too few views to fit."""
    max_views: int = 400
    """The plan adds chunks until no chunk needs more views than this (fit time grows with views)."""
    memory_bytes: int | None = None
    """Device memory one chunk may use; ``None``: 80 % of the free CUDA memory
    (``torch.cuda.mem_get_info``), or ``cpu_memory_bytes`` on CPU."""
    cpu_memory_bytes: int = 8 << 30
    """Memory assumed for a chunk on CPU when ``memory_bytes`` is ``None``."""
    iteration_share: bool = True
    """Each chunk runs the share of the iteration budget (warm-up and co-evolution) that its training
    views are of the scene's, so every view is visited as often as in a fit of the whole scene;
    ``False``: every chunk runs the full budget."""
    space_share: bool = True
    """Each chunk's point budgets (initial points, surfel cap, re-initialisation faces, background
    points when set) are the share of the configured or planned ones that its box is of the region
    of interest's volume, so its surfels are as dense as in a fit of the whole scene; ``False``:
    every chunk gets the full budgets (a finer, slower fit)."""
    min_budget_share: float = 0.25
    """The smallest share of an iteration or point budget a chunk gets."""
    merge: str = "refuse"
    """How the chunks become one mesh (:mod:`.merge`): ``"refuse"``, the fit's final meshing (TSDF
    fusion of rendered depth, the meshing policy) of the merged surfels once over the whole region of
    interest, seamless by construction; ``"weld"``, each chunk's own mesh cut to its core and the
    boundary vertices near the cuts welded (seams stay open where the chunks disagree)."""
    chunk_meshes: bool | None = None
    """Whether each chunk's fit builds its own final mesh (``chunks/<i>/mesh.ply``); ``None``: only when
    the merge uses them (``merge="weld"``), so a re-fusing merge does not pay for meshes it throws away."""
    weld_fraction: float = 0.75
    """Merge ``"weld"``: boundary vertices of different chunks closer than this fraction of the median
    boundary edge length are welded into one."""

    def builds_chunk_meshes(self) -> bool:
        """Whether the chunks' fits build their own final mesh (``chunk_meshes``, resolved)."""
        return self.merge == "weld" if self.chunk_meshes is None else bool(self.chunk_meshes)

    def validate(self) -> None:
        """Raise ``ValueError`` / ``TypeError`` naming the first bad field."""
        if self.chunks is not None and (isinstance(self.chunks, bool) or not isinstance(self.chunks, int)
                                        or self.chunks < 1):
            raise ValueError(f"ChunkConfig.chunks must be an integer >= 1 or None, got {self.chunks!r}")
        if self.grid is not None:
            g = tuple(self.grid)
            if len(g) != 3 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in g):
                raise ValueError(f"ChunkConfig.grid must be 3 integers >= 1 (x, y, z), got {self.grid!r}")
            self.grid = g
        if not (isinstance(self.overlap, (int, float)) and 0 <= self.overlap < 0.5):
            raise ValueError(f"ChunkConfig.overlap must be a number in [0, 0.5), got {self.overlap!r}")
        if not (isinstance(self.min_share, (int, float)) and 0 <= self.min_share <= 1):
            raise ValueError(f"ChunkConfig.min_share must be a fraction in [0, 1], got {self.min_share!r}")
        for name in ("min_views", "max_views", "cpu_memory_bytes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"ChunkConfig.{name} must be an integer >= 1, got {v!r}")
        if self.memory_bytes is not None and (isinstance(self.memory_bytes, bool) or
                                              not isinstance(self.memory_bytes, int) or self.memory_bytes < 1):
            raise ValueError(f"ChunkConfig.memory_bytes must be an integer >= 1 or None, got {self.memory_bytes!r}")
        if not (isinstance(self.min_budget_share, (int, float)) and 0 < self.min_budget_share <= 1):
            raise ValueError(f"ChunkConfig.min_budget_share must be in (0, 1], got {self.min_budget_share!r}")
        if self.merge not in ("refuse", "weld"):
            raise ValueError(f"ChunkConfig.merge must be 'refuse' or 'weld', got {self.merge!r}")
        if self.chunk_meshes is not None and not isinstance(self.chunk_meshes, bool):
            raise TypeError(f"ChunkConfig.chunk_meshes must be a bool or None, got {self.chunk_meshes!r}")
        if not (isinstance(self.weld_fraction, (int, float)) and 0 <= self.weld_fraction <= 2):
            raise ValueError(f"ChunkConfig.weld_fraction must be a number in [0, 2], got {self.weld_fraction!r}")


@dataclass
class Chunk:
    """One chunk: its core, its fitted box and its cameras (world frame, float64).

    Attributes:
        index: position in the plan (row-major over the grid, x slowest).
        cell: grid cell (i, j, k).
        core_lower: lower corner [3] of the core (``-inf`` on the outer side of an outer cell).
        core_upper: upper corner [3] (``+inf`` likewise).
        lower: lower corner [3] of the fitted box (core plus overlap, inside the region of interest).
        upper: upper corner [3] of the fitted box.
        cameras: indices of the scene's cameras given to the chunk.
        skipped: why the chunk is not fitted, or ``""``.
    """

    index: int
    cell: tuple
    core_lower: np.ndarray
    core_upper: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    cameras: list = field(default_factory=list)
    skipped: str = ""

    def volume_share(self, roi_lower, roi_upper) -> float:
        """The fitted box's volume over the region of interest's."""
        return float(np.prod((self.upper - self.lower) / (np.asarray(roi_upper) - np.asarray(roi_lower))))

    def to_dict(self) -> dict:
        """JSON-ready form (infinite core sides as ``null``)."""
        d = asdict(self)
        for k in ("core_lower", "core_upper", "lower", "upper"):
            d[k] = [None if not math.isfinite(v) else float(v) for v in np.asarray(d[k], np.float64)]
        d["cell"] = list(self.cell)
        return d


@dataclass
class ChunkPlan:
    """The partition and why it was chosen.

    Attributes:
        roi_lower: region of interest lower corner [3], world units.
        roi_upper: upper corner [3].
        grid: cells per axis (x, y, z).
        chunks: the :class:`Chunk` s.
        reason: one sentence for the plan record.
        overridden: the count came from the configuration.
    """

    roi_lower: np.ndarray
    roi_upper: np.ndarray
    grid: tuple
    chunks: list
    reason: str
    overridden: bool

    def cuts(self) -> list[tuple[int, float]]:
        """The interior cut planes ``(axis, coordinate)`` (the seams of the merge)."""
        out = []
        for a in range(3):
            for k in range(1, self.grid[a]):
                out.append((a, float(self.roi_lower[a] + k * (self.roi_upper[a] - self.roi_lower[a]) / self.grid[a])))
        return out

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {"roi_lower": self.roi_lower.tolist(), "roi_upper": self.roi_upper.tolist(), "grid": list(self.grid),
                "reason": self.reason, "overridden": self.overridden, "chunks": [c.to_dict() for c in self.chunks]}


def chunk_grid(extent, n: int) -> tuple[int, int, int]:
    """Cells per axis for at least ``n`` chunks: repeatedly cut the axis whose cells are longest.

    Args:
        extent: the region's side lengths [3].
        n: the number of chunks wanted (>= 1).

    Returns:
        ``(gx, gy, gz)`` with ``gx * gy * gz >= n`` (equal only when the cuts can make it so).
    """
    ext = np.asarray(extent, np.float64)
    if ext.shape != (3,) or not np.all(ext > 0):
        raise ValueError(f"extent must be 3 positive lengths, got {extent!r}")
    g = [1, 1, 1]
    while g[0] * g[1] * g[2] < n:
        a = int(np.argmax(ext / np.asarray(g)))
        g[a] += 1
    return tuple(g)


def _grid_chunks(lo: np.ndarray, hi: np.ndarray, grid, overlap: float) -> list[Chunk]:
    step = (hi - lo) / np.asarray(grid, np.float64)
    out = []
    for cell in np.ndindex(*grid):
        c = np.asarray(cell)
        core_lo, core_hi = lo + c * step, lo + (c + 1) * step
        first, last = c == 0, c == np.asarray(grid) - 1
        box_lo = np.where(first, lo, core_lo - overlap * step)
        box_hi = np.where(last, hi, core_hi + overlap * step)
        out.append(Chunk(len(out), tuple(int(v) for v in cell), np.where(first, -np.inf, core_lo),
                         np.where(last, np.inf, core_hi), box_lo, box_hi))
    return out


def grid_owner(points, lower, upper, grid):
    """Index (int64, shape ``points.shape[:-1]``) of the cell of the ``grid`` (3 counts) over the box
    ``[lower, upper]`` that holds each point [..., 3]; points outside belong to the nearest border cell
    (the outer cells reach to infinity). NumPy in, NumPy out; a torch tensor stays on its device (then
    ``lower`` / ``upper`` are [3] tensors or sequences on the host: a per-view call copies nothing)."""
    g = [int(n) for n in grid]
    if isinstance(points, np.ndarray) or not hasattr(points, "device"):
        p = np.asarray(points, np.float64)
        lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        cell = [np.clip(np.floor((p[..., k] - lo[k]) / ((hi[k] - lo[k]) / g[k])), 0, g[k] - 1).astype(np.int64)
                for k in range(3)]
    else:
        cell = [((points[..., k] - lower[k]) / ((upper[k] - lower[k]) / g[k])).floor().long().clamp(0, g[k] - 1)
                for k in range(3)]
    return (cell[0] * g[1] + cell[1]) * g[2] + cell[2]


def core_owner(points, plan: ChunkPlan) -> np.ndarray:
    """Index [P] (int64) of the chunk whose core holds each point [P, 3] (world units)."""
    return grid_owner(np.asarray(points, np.float64).reshape(-1, 3), plan.roi_lower, plan.roi_upper, plan.grid)


def _pixel_rays(camera, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Origin [3] and unit world directions [M, 3] of the rays through an ``n``-wide grid of pixel
    centres (``n * height / width`` rows), through the camera's lens."""
    cols = max(1, n)
    rows = max(1, round(n * camera.height / camera.width))
    u = (np.arange(cols) + 0.5) * camera.width / cols
    v = (np.arange(rows) + 0.5) * camera.height / rows
    uu, vv = (a.reshape(-1) for a in np.meshgrid(u, v))
    K = camera.K
    y = (vv - K[1, 2]) / K[1, 1]
    x = (uu - K[0, 2] - K[0, 1] * y) / K[0, 0]
    xy = camera.undistort(np.stack([x, y], axis=1))
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ camera.R  # rows: R^T [x, y, 1]
    return camera.center, d / np.linalg.norm(d, axis=1, keepdims=True)


def view_shares(camera, boxes, roi_lower, roi_upper) -> np.ndarray:
    """Expected fraction [B] of ``camera``'s image that shows each box ``(lower [3], upper [3])``.

    Each ray of a grid of pixels is clipped to the region of interest and the surface it sees is
    taken to lie anywhere along that segment with equal chance (the surface is unknown when the
    chunks are planned): a box's share is the mean over all rays of the fraction of the ray's
    segment inside the box (rays missing the region count 0). A far chunk that a camera sees along
    a grazing line of sight thus gets a small share, a chunk filling the view a large one.
    Occlusion is not modelled.
    """
    o, d = _pixel_rays(camera, _RAY_GRID)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t_a, t_b = (roi_lower - o) * inv, (roi_upper - o) * inv
    t0 = np.nanmax(np.minimum(t_a, t_b), axis=1).clip(min=0.0)
    t1 = np.nanmin(np.maximum(t_a, t_b), axis=1)
    hit = t1 > t0
    if not hit.any():
        return np.zeros(len(boxes))
    frac = (np.arange(_RAY_SAMPLES) + 0.5) / _RAY_SAMPLES
    t = t0[hit, None] + frac[None] * (t1 - t0)[hit, None]
    pts = o + t[..., None] * d[hit, None, :]  # [rays, samples, 3]
    out = np.zeros(len(boxes))
    for k, (lo, hi) in enumerate(boxes):
        out[k] = np.all((pts >= lo) & (pts <= hi), axis=2).mean(axis=1).sum() / len(d)
    return out


def assign_cameras(cameras, chunks: list[Chunk], min_share: float, roi_lower, roi_upper, train=None) -> None:
    """Give each chunk (in place, ``chunk.cameras``) the cameras whose image is expected to show its
    fitted box on at least ``min_share`` of the pixels (:func:`view_shares`); a chunk with no
    training camera gets none. A single chunk gets every camera."""
    if len(chunks) == 1:  # one chunk is the whole fit: every camera, as wtopo.fit would use
        chunks[0].cameras = list(range(len(cameras)))
        return
    boxes = [(ch.lower, ch.upper) for ch in chunks]
    shares = np.stack([view_shares(cam, boxes, roi_lower, roi_upper) for cam in cameras])  # [N, B]
    allowed = set(range(len(cameras))) if train is None else {int(i) for i in train}
    for k, ch in enumerate(chunks):
        ch.cameras = [int(i) for i in np.nonzero(shares[:, k] >= min_share)[0]]
        if not allowed & set(ch.cameras):
            ch.cameras = []


def _memory_available(cfg: ChunkConfig, device) -> tuple[int, str]:
    import torch

    if cfg.memory_bytes is not None:
        return cfg.memory_bytes, "ChunkConfig.memory_bytes"
    dev = torch.device(device) if device not in (None, "auto") else (
        torch.device("cuda:0") if torch.cuda.is_available() else torch.device("cpu"))
    if dev.type == "cuda":
        free, _ = torch.cuda.mem_get_info(dev)
        return int(0.8 * free), f"80 % of the free memory of {dev}"
    return cfg.cpu_memory_bytes, "ChunkConfig.cpu_memory_bytes on CPU"


def _memory_chunks(n_train: int, pixels: int, fcfg, device, mem: int) -> tuple[int, float, float]:
    """Fewest chunks whose estimated fit footprint fits ``mem``: the per-view tensors divide among
    the chunks, the dense grids and the surfel cap do not. Returns ``(count, views GiB, fixed GiB)``."""
    from ..fitting import plan_defaults

    base = plan_defaults("cuda" if str(device).startswith("cuda") or (device == "auto" and _cuda()) else "cpu",
                         fcfg.preset)
    proxy = fcfg.mesh.resolution or base.proxy_grid
    final = fcfg.final.resolution or base.final_grid
    surfels = fcfg.runtime.max_surfels or base.max_surfels
    views = n_train * pixels * _BYTES_PER_PIXEL
    fixed = _GRID_ARRAYS * 4 * proxy ** 3 + 2 * 4 * final ** 3 + surfels * _BYTES_PER_SURFEL
    if fixed >= mem:
        raise ValueError(f"one chunk's grids and surfels need about {fixed / 2**30:.2f} GiB, more than the "
                         f"{mem / 2**30:.2f} GiB available; lower mesh.resolution / final.resolution / "
                         "runtime.max_surfels or raise ChunkConfig.memory_bytes")
    return max(1, math.ceil(views / (mem - fixed))), views / 2**30, fixed / 2**30


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def plan_chunks(scene, config: ChunkConfig | None = None, *, fit_config=None, world_size: int = 1) -> ChunkPlan:
    """Partition ``scene``'s region of interest into chunks and give each its cameras.

    Without ``config.chunks`` / ``config.grid`` the count is the largest of: the world size (one
    chunk per process at least), enough chunks that none needs more than ``config.max_views`` views
    (the views are split by where they look), and enough that the estimated footprint of one
    chunk's fit (per-view tensors, the dense meshing grids, the surfel cap) fits the memory
    available. The estimate is a rough upper bound, not a measurement; give ``chunks`` to override.

    Args:
        scene: a :class:`wtopo.Scene` (world frame).
        config: :class:`ChunkConfig`; ``None`` for the defaults.
        fit_config: the :class:`wtopo.FitConfig` each chunk runs (device, grid sizes, surfel cap).
        world_size: processes that fit chunks.

    Returns:
        :class:`ChunkPlan`.

    Raises:
        TypeError: ``config`` is not a ChunkConfig.
        ValueError: a bad field of ``config``, ``world_size`` < 1, or no chunk has enough views.
    """
    from ..fitting import FitConfig

    cfg = ChunkConfig() if config is None else config
    if not isinstance(cfg, ChunkConfig):
        raise TypeError(f"config must be a wtopo.chunks.ChunkConfig or None, got {type(cfg).__name__}")
    cfg.validate()
    if isinstance(world_size, bool) or not isinstance(world_size, int) or world_size < 1:
        raise ValueError(f"world_size must be an integer >= 1, got {world_size!r}")
    fcfg = FitConfig() if fit_config is None else fit_config
    lo, hi = scene.region_of_interest()
    ext = hi - lo
    train = scene.train_indices
    n_train = len(scene) if train is None else len(train)
    overridden = cfg.grid is not None or cfg.chunks is not None
    if cfg.grid is not None:
        grid = cfg.grid
        reason = f"grid {grid} set in ChunkConfig.grid"
    elif cfg.chunks is not None:
        grid = chunk_grid(ext, cfg.chunks)
        reason = f"{cfg.chunks} chunks set in ChunkConfig.chunks, cut along the longest axes"
    else:
        mem, mem_src = _memory_available(cfg, fcfg.runtime.device)
        n_mem, views_gib, fixed_gib = _memory_chunks(n_train, scene.width * scene.height, fcfg,
                                                     str(fcfg.runtime.device), mem)
        n_view = max(1, math.ceil(n_train / cfg.max_views))
        n = max(world_size, n_mem, n_view)
        grid = chunk_grid(ext, n)
        why = [f"{world_size} for one per process", f"{n_view} for {n_train} views at most {cfg.max_views} a chunk",
               f"{n_mem} to fit the memory (views about {views_gib:.1f} GiB in all, grids and surfels "
               f"{fixed_gib:.1f} GiB a chunk, {mem / 2**30:.1f} GiB from {mem_src})"]
        reason = f"{n} chunks: the largest of {'; '.join(why)}; cut along the longest axes"
    chunks = _grid_chunks(lo, hi, grid, float(cfg.overlap))
    assign_cameras(scene.cameras, chunks, float(cfg.min_share), lo, hi, train)
    allowed = set(range(len(scene))) if train is None else {int(i) for i in train}
    for ch in chunks:
        n_views = sum(1 for i in ch.cameras if i in allowed)
        if n_views < cfg.min_views:
            ch.skipped = f"{n_views} training views see it (< ChunkConfig.min_views = {cfg.min_views})"
    if all(ch.skipped for ch in chunks):
        raise ValueError(f"no chunk of grid {grid} is seen by ChunkConfig.min_views = {cfg.min_views} training views "
                         f"(ChunkConfig.min_share = {cfg.min_share}); lower them or use fewer chunks")
    return ChunkPlan(lo, hi, tuple(int(v) for v in grid), chunks, reason, overridden)
