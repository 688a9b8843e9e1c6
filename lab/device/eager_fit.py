# SPDX-License-Identifier: Apache-2.0
"""benchmarks/peers/run_wtopo.py with every CUDA graph of the fit off (render, per-pixel terms, Adam): the eager
baseline of the same tree, for a before/after on one machine.

    python3 lab/device/eager_fit.py EXCH OUT [run_wtopo.py's arguments]
"""
import os
import runpy
import sys

import wtopo.fitting.adam as adam
import wtopo.fitting.pixel_terms as pixel_terms
import wtopo.fitting.raster_graph as raster_graph

adam.GRAPHS = pixel_terms.GRAPHS = raster_graph.GRAPHS = False
here = os.path.dirname(os.path.abspath(__file__))
sys.argv = [os.path.join(here, "..", "..", "benchmarks", "peers", "run_wtopo.py"), *sys.argv[1:]]
runpy.run_path(sys.argv[0], run_name="__main__")
