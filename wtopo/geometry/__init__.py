# SPDX-License-Identifier: Apache-2.0
"""Geometry that several callers share: the scene, the metrics, the TSDF fusion and the fit.

It sits above the differentiable ops and below the fit, and never imports the fit
(``tests/test_layers.py`` holds the layer order). Modules:

* ``region``: the region of interest of a capture (visual hull of the masks, common volume of the frusta,
  box of the points), for :meth:`wtopo.Scene.region_of_interest`;
* ``mvs``: plane-sweep multi-view stereo (initial points, view neighbours, torch cameras);
* ``depth_warp``: resampling a lens camera's depth and colour onto an ideal pinhole camera;
* ``components``: connected components of a mesh's faces;
* ``winding``: consistent, outward face winding;
* ``mesh_policy``: what the returned mesh keeps (components by view support, crops).

Nothing is imported here: each caller imports the module it needs.
"""
