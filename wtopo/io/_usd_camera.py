# SPDX-License-Identifier: Apache-2.0
"""USD cameras: :class:`wtopo.Camera` to and from ``UsdGeom.Camera`` (conventions: :mod:`wtopo.io.usd`)."""

from __future__ import annotations

import os

import numpy as np

from ._usd_common import _pxr

__all__ = ["camera_to_usd", "camera_from_usd", "read_cameras", "FILM_WIDTH"]

FILM_WIDTH = 36.0
"""Horizontal aperture written for every camera, in tenths of a scene unit (a 36 mm film at
``metersPerUnit = 0.01``); only ratios matter for the projection."""

_CAMERA_AXES = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes <-> USD camera axes (an involution)


def camera_to_usd(stage, path: str, camera, *, clipping_range=(0.01, 1000.0)):
    """Author ``camera`` (a :class:`wtopo.Camera`) as a ``UsdGeom.Camera`` at ``path`` (conventions above).

    Returns:
        The ``UsdGeom.Camera``.
    """
    Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
    K = camera.K
    fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    pitch_x = FILM_WIDTH / camera.width
    focal = fx * pitch_x
    pitch_y = focal / fy
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    cam.CreateFocalLengthAttr(float(focal))
    cam.CreateHorizontalApertureAttr(float(FILM_WIDTH))
    cam.CreateVerticalApertureAttr(float(camera.height * pitch_y))
    # Film-centre offsets: u grows with +x, v grows with -y (USD +y is up).
    cam.CreateHorizontalApertureOffsetAttr(float((camera.width / 2 - cx) * pitch_x))
    cam.CreateVerticalApertureOffsetAttr(float((cy - camera.height / 2) * pitch_y))
    near, far = (float(v) for v in clipping_range)
    if not 0 < near < far < float("inf"):
        raise ValueError(f"clipping_range must satisfy 0 < near < far < inf, got {clipping_range!r}")
    cam.CreateClippingRangeAttr(Gf.Vec2f(near, far))
    xf = cam.AddTransformOp(precision=UsdGeom.XformOp.PrecisionDouble)
    xf.Set(Gf.Matrix4d((camera.camera_to_world @ _CAMERA_AXES).T.tolist()))  # Gf is row-vector
    prim = cam.GetPrim()
    prim.CreateAttribute("wtopo:imageSize", Sdf.ValueTypeNames.Int2, custom=True).Set(
        Gf.Vec2i(camera.width, camera.height))
    if skew != 0:
        prim.CreateAttribute("wtopo:skew", Sdf.ValueTypeNames.Double, custom=True).Set(float(skew))
    if camera.distortion is not None:
        prim.CreateAttribute("wtopo:distortion", Sdf.ValueTypeNames.DoubleArray, custom=True).Set(
            Vt.DoubleArray([float(v) for v in camera.distortion]))
    if camera.name:
        prim.CreateAttribute("wtopo:name", Sdf.ValueTypeNames.String, custom=True).Set(camera.name)
    return cam


def camera_from_usd(usd_camera):
    """Rebuild a :class:`wtopo.Camera` from a ``UsdGeom.Camera`` written by :func:`camera_to_usd`.

    Cameras written by other tools (no ``wtopo:imageSize``) are read as 1000 pixels wide with
    square pixels and the height given by the aperture ratio.
    """
    from ..camera import Camera

    prim = usd_camera.GetPrim()
    size = prim.GetAttribute("wtopo:imageSize")
    ha = usd_camera.GetHorizontalApertureAttr().Get()
    va = usd_camera.GetVerticalApertureAttr().Get()
    focal = usd_camera.GetFocalLengthAttr().Get()
    if size and size.HasAuthoredValue():
        w, h = (int(v) for v in size.Get())
    else:
        w = 1000
        h = max(1, round(w * va / ha))
    pitch_x, pitch_y = ha / w, va / h
    fx, fy = focal / pitch_x, focal / pitch_y
    cx = w / 2 - usd_camera.GetHorizontalApertureOffsetAttr().Get() / pitch_x
    cy = h / 2 + usd_camera.GetVerticalApertureOffsetAttr().Get() / pitch_y
    skew_attr = prim.GetAttribute("wtopo:skew")
    skew = float(skew_attr.Get()) if skew_attr and skew_attr.HasAuthoredValue() else 0.0
    K = np.array([[fx, skew, cx], [0, fy, cy], [0, 0, 1.0]])
    from pxr import Usd

    c2w_usd = np.array(usd_camera.ComputeLocalToWorldTransform(Usd.TimeCode.Default()), dtype=np.float64).T
    c2w = c2w_usd @ _CAMERA_AXES
    w2c = np.eye(4)
    w2c[:3, :3] = c2w[:3, :3].T
    w2c[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
    dist = prim.GetAttribute("wtopo:distortion")
    distortion = np.array(dist.Get(), dtype=np.float64) if dist and dist.HasAuthoredValue() else None
    name_attr = prim.GetAttribute("wtopo:name")
    name = name_attr.Get() if name_attr and name_attr.HasAuthoredValue() else prim.GetName()
    return Camera(K, w2c, w, h, distortion, name)


def read_cameras(path_or_stage) -> list:
    """All ``UsdGeom.Camera`` prims of a stage (or file), in stage order, as :class:`wtopo.Camera`."""
    _, _, Usd, UsdGeom, _ = _pxr()
    stage = Usd.Stage.Open(os.fspath(path_or_stage)) if isinstance(path_or_stage, (str, os.PathLike)) else path_or_stage
    return [camera_from_usd(UsdGeom.Camera(p)) for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
