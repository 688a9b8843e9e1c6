# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``plotly``: Open3D's ``visualization`` imports it at import time for ``draw_plotly`` only,
which the peers benchmark never calls. Any use raises."""
