# SPDX-License-Identifier: Apache-2.0
"""Options, result record and error of :func:`wtopo.loaders.sfm.run_sfm`, and the constants the
structure-from-motion modules share (image suffixes, camera models, the summary file's name)."""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, field

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
"""File suffixes (any case) read as photographs: the formats COLMAP's image reader decodes."""


_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")  # what load_colmap reads


_MAX_NAMED = 20  # an error names at most this many dropped images (then "and N more")
SFM_SUMMARY = "sfm.json"
"""What :func:`run_sfm` did, written in its workspace beside ``sparse/`` (also how a later load tells its model)."""


class Matcher(str, enum.Enum):
    """Which image pairs are matched."""

    EXHAUSTIVE = "exhaustive"
    """Every pair: N (N - 1) / 2 pairs. Robust for any capture order; quadratic in N."""
    SEQUENTIAL = "sequential"
    """Each image with its ``sequential_overlap`` successors in name order and those 2, 4, 8, ...
    further on (COLMAP's quadratic overlap): video frames, linear in N."""


class SfMError(ValueError):
    """Structure from motion ran but did not give a usable model (too few images registered, no
    overlap between the images). ``partial_model`` is the folder the largest partial model was
    written to, or ``None``; ``dropped`` maps each unregistered image to the reason."""

    def __init__(self, message: str, *, partial_model: str | None = None, dropped: dict | None = None):
        super().__init__(message)
        self.partial_model = partial_model
        self.dropped = dict(dropped or {})


@dataclass(kw_only=True)
class SfMOptions:
    """Settings of :func:`run_sfm`."""

    matcher: str | None = None
    """``"exhaustive"``, ``"sequential"`` or ``None`` to choose by the image count
    (:func:`choose_matcher`)."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model shared by all images: ``SIMPLE_RADIAL`` (f, cx, cy, k; phones and most
    cameras) or ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2); ``SIMPLE_PINHOLE``, ``PINHOLE`` and
    ``RADIAL`` also work."""
    exhaustive_max_images: int = 300
    """Up to this many images every pair is matched (300 images: 44,850 pairs, about an hour on 2
    cores at 8k features); beyond it the sequential matcher is chosen."""
    sequential_overlap: int = 10
    """Successors each image is matched with by the sequential matcher."""
    max_image_size: int = 2000
    """Longest side, pixels, features are extracted at (larger photos are downsampled for SIFT only)."""
    max_num_features: int = 8192
    """SIFT features kept per image."""
    min_registered_fraction: float = 0.5
    """The run fails (:class:`SfMError`) when fewer than this fraction of the images get a pose."""
    min_registered: int = 3
    """... or fewer than this many."""
    num_threads: int = -1
    """CPU threads for extraction, matching and mapping (-1: all cores)."""
    seed: int = 0
    """Random seed of RANSAC and the mapper."""
    robust_refinement: float = 1.0
    """Scale (pixels) of the Cauchy loss of a last global bundle adjustment of the model; 0: none.
    COLMAP's own adjustments minimise squared errors, which a few wrong matches (repetitive texture:
    bricks, gravel) bias: on the 64-view synthetic capture of ``tests/test_sfm.py`` this pass took
    the camera-centre error from 0.32 % to 0.11 % of the camera extent and the focal length from
    0.6 % to 0.3 % off, at the same mean reprojection error."""

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field and its value."""
        if self.matcher is not None and self.matcher not in [m.value for m in Matcher]:
            raise ValueError(f"matcher must be 'exhaustive', 'sequential' or None, got {self.matcher!r}")
        if self.camera_model not in _CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {', '.join(_CAMERA_MODELS)}, got {self.camera_model!r}")
        for name, lo in (("exhaustive_max_images", 2), ("sequential_overlap", 1), ("max_image_size", 16),
                         ("max_num_features", 16), ("min_registered", 2)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        f = self.min_registered_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f <= 1:
            raise ValueError(f"min_registered_fraction must be a number in [0, 1], got {f!r}")
        r = self.robust_refinement
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r >= 0):
            raise ValueError(f"robust_refinement must be a finite number >= 0 (pixels), got {r!r}")
        if isinstance(self.num_threads, bool) or not isinstance(self.num_threads, int) or self.num_threads == 0 \
                or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or an integer >= 1, got {self.num_threads!r}")


@dataclass
class SfMResult:
    """What :func:`run_sfm` did (also written to ``workspace/sfm.json``)."""

    model_dir: str
    """The model folder, ``workspace/sparse/0``."""
    workspace: str
    """The folder holding ``database.db``, ``sparse/`` and ``sfm.json``."""
    image_dir: str
    """The folder of the photographs."""
    images: list
    """Every image name, sorted."""
    registered: list
    """Names of the images that got a pose."""
    dropped: dict
    """Unregistered image name -> why."""
    matcher: str
    matcher_reason: str
    camera: dict
    """The shared camera: ``{"model", "width", "height", "params", "focal_prior"}``."""
    points: int
    """3D points of the model (they seed the surfels)."""
    reprojection_error: float | None
    """Mean reprojection error of the model, pixels."""
    seconds: dict = field(default_factory=dict)
    """Wall time of each step (``features``, ``matching``, ``mapping``, ``total``)."""
    reused: bool = False
    """The model was already there; nothing ran."""

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return asdict(self)
