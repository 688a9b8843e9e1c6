# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``kaolin``: ``pgsr_dpsr``'s ``nvdiffrast_utils/flexicubes.py`` imports
``kaolin.ops.conversions.FlexiCubes`` at import time; only its ``mesh_backend="flexicubes"`` uses it, and
its ``train.py`` runs ``"diffdmc"`` (diso). Any use raises."""
