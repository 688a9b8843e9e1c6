# SPDX-License-Identifier: Apache-2.0
"""What kind of capture a scene is, and where its region of interest lies.

Decided from the cameras (optical-axis convergence, how parallel the axes are), the masks and
whatever the dataset gives (``Scene.bounds``: DTU ``scale_mat``, nerfstudio / instant-ngp ``aabb``),
in the internal frame of :meth:`wtopo.Scene.normalization`, where the region of interest fills
``[m, 1 - m]^3`` along its longest side (``m`` the normalisation margin).

Two kinds drive the fit:

* ``object``: masks tell the object from everything else. Nothing behind it is kept; the mesh is
  closed (watertight) and every separately observed part is kept.
* ``scene``: no masks, so the images show background (a room, a ground, hills, sky). Surfels
  outside the region of interest live on as background at their distance (:mod:`.background`),
  the proxy mesh and its losses cover the region of interest, and the returned mesh is the region
  of interest's surface, open where nothing was observed and never near a camera.

The capture layout (``360``: cameras around the region, axes converging; ``forward``: cameras on
one side looking the same way, as LLFF) is recorded with it: it sets how far the background is
initialised.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SceneKind", "Capture", "SceneLayout", "analyse_layout", "near_distance"]

# A forward-facing capture: the mean of the unit viewing directions has at least this length,
# i.e. the axes spread by less than about 35 degrees around their mean (LLFF rigs: < 20 degrees;
# an orbit or a hemisphere around an object: < 0.5).
_FORWARD_COHERENCE = 0.8
# A camera counts as "near" a mesh face (a hull around the cameras) inside this fraction of the
# scene extent; the meshing policy removes faces closer than this.
NEAR_FRACTION = 0.05


class SceneKind(str, enum.Enum):
    """How the fit treats what lies outside the region of interest."""

    OBJECT = "object"
    """Masked object: no background kept, closed mesh."""
    SCENE = "scene"
    """Unmasked capture: background kept at distance, open mesh of the region of interest."""


class Capture(str, enum.Enum):
    """Camera layout."""

    MASKED = "masked"
    """Masks given (the layout does not matter for the fit)."""
    ORBIT = "360"
    """Cameras around the region of interest, optical axes converging on it."""
    FORWARD = "forward"
    """Cameras on one side, optical axes nearly parallel."""


@dataclass(frozen=True)
class SceneLayout:
    """The region of interest and the capture layout in the internal frame.

    Attributes:
        kind: object or scene.
        capture: camera layout.
        roi_lower: lower corner [3] of the region of interest, internal units (float64).
        roi_upper: upper corner [3], internal units.
        roi_source: where the region of interest came from (bounds, masks, points, cameras).
        camera_centers: [N, 3] float64, internal units.
        scene_extent: the diagonal of the box around the region of interest and every camera
            centre, internal units (the unit of the near-camera criterion).
        near: distance from a camera centre inside which no surfel may sit and no mesh face may
            lie, internal units (``NEAR_FRACTION`` of ``scene_extent``, capped below the distance
            of the nearest camera to the region of interest).
        reason: one sentence for the plan.
    """

    kind: SceneKind
    capture: Capture
    roi_lower: np.ndarray
    roi_upper: np.ndarray
    roi_source: str
    camera_centers: np.ndarray
    scene_extent: float
    near: float
    reason: str

    @property
    def roi_center(self) -> np.ndarray:
        """Centre [3] of the region of interest."""
        return 0.5 * (self.roi_lower + self.roi_upper)

    @property
    def roi_radius(self) -> float:
        """Half the diagonal of the region of interest."""
        return 0.5 * float(np.linalg.norm(self.roi_upper - self.roi_lower))


def _roi_source(scene, capture: Capture | None = None) -> str:
    if scene.bounds is not None:
        return "the dataset's bounds"
    if scene.masks is not None:
        return "the visual hull of the masks"
    if scene.points is not None and len(scene.points) >= 8:
        return "the points seen by half of the cameras"
    if capture is Capture.FORWARD:
        return ("the volume seen by 90 % of the cameras (with parallel axes: around the depth stereo finds in the "
                "middle of the pictures, or a guess from the rig's spread when they hold no texture)")
    return "the volume seen by 90 % of the cameras"


def near_distance(centers: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[float, float]:
    """``(near, extent)`` of :class:`SceneLayout` for cameras at ``centers`` [N, 3] around the box
    ``[lower, upper]`` (any frame and units: both scale with them). ``extent`` is the diagonal of the box
    around the box's corners and the centres; ``near`` is ``NEAR_FRACTION`` of it, capped by half the
    cameras' median distance to the box's centre (a camera inside the region, as in a room scan, keeps
    a near distance small against the surfaces it films)."""
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    allp = np.concatenate([centers, lo[None], hi[None]])
    extent = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    dist = np.linalg.norm(centers - 0.5 * (lo + hi), axis=1)
    near = min(NEAR_FRACTION * extent, 0.5 * float(np.median(dist)))
    near = near if math.isfinite(near) and near > 0 else NEAR_FRACTION * extent
    return near, extent


def analyse_layout(scene, kind: SceneKind | str | None = None) -> SceneLayout:
    """Region of interest and kind of the normalised ``scene`` (internal frame).

    Args:
        scene: a :class:`wtopo.Scene` in the internal frame (``scene.normalized()``); its
            ``bounds`` (if any) are the region of interest, else the normalisation's estimate is.
        kind: force the kind (``None``: object with masks, scene without).

    Returns:
        :class:`SceneLayout`.
    """
    if scene.bounds is not None:
        lo, hi = (np.asarray(b, np.float64) for b in scene.bounds)
    elif "region_of_interest" in scene.info:  # what the normalisation estimated (Scene.normalized)
        lo, hi = (np.asarray(b, np.float64) for b in scene.info["region_of_interest"])
    else:
        lo, hi = scene.region_of_interest()
    centers = np.stack([c.center for c in scene.cameras]).astype(np.float64)
    forwards = np.stack([c.forward for c in scene.cameras]).astype(np.float64)
    coherence = float(np.linalg.norm(forwards.mean(axis=0)))
    if scene.masks is not None:
        capture = Capture.MASKED
        how = "masks given"
    elif coherence >= _FORWARD_COHERENCE:
        capture = Capture.FORWARD
        how = f"no masks; viewing directions agree (mean direction length {coherence:.2f} >= {_FORWARD_COHERENCE})"
    else:
        capture = Capture.ORBIT
        how = f"no masks; cameras around the region (mean direction length {coherence:.2f} < {_FORWARD_COHERENCE})"
    if kind is None:
        k = SceneKind.OBJECT if scene.masks is not None else SceneKind.SCENE
        why = ("object: " + how) if k is SceneKind.OBJECT else (
            f"scene ({capture.value}): {how}, so background is kept and the mesh is the region of interest's")
    else:
        k = SceneKind(kind)
        why = f"{k.value}: set in the configuration ({how})"
    near, extent = near_distance(centers, lo, hi)
    src = _roi_source(scene, capture)
    return SceneLayout(k, capture, lo, hi, src, centers, extent, near, f"{why}; region of interest from {src}")
