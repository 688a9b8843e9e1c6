# SPDX-License-Identifier: Apache-2.0
"""Write a scene as an exchange folder for the peers benchmark (``exchange.py`` says what is in it).

    python benchmarks/peers/export.py SCENE OUT [--views N --resolution PX] [--test-every 8]

SCENE is a built-in scene name (``wtopo scenes``), a scene of the benchmark's own (``scenes.py``: the hard
suite's objects at 64 or 10 views of 512 px, the unbounded ``chair_env`` and ``mug_torus_env``) or a dataset
path (``wtopo.load_scene``).
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import scenes as peer_scenes  # noqa: E402
from exchange import export  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--views", type=int, default=None, help="views of a built-in scene")
    ap.add_argument("--resolution", type=int, default=None, help="image size of a built-in scene [px]")
    ap.add_argument("--name", default=None)
    ap.add_argument("--test-every", type=int, default=8)
    a = ap.parse_args(argv)
    import wtopo
    from wtopo import scenes

    if a.scene in scenes.names():
        kw = {k: v for k, v in (("n_views", a.views), ("resolution", a.resolution)) if v is not None}
        scene = scenes.load(a.scene, **kw)
    elif a.scene in peer_scenes.names():
        kw = {k: v for k, v in (("n_views", a.views), ("resolution", a.resolution)) if v is not None}
        scene = peer_scenes.load(a.scene, **kw)
    else:
        scene = wtopo.load_scene(a.scene)
    if a.name:
        scene.name = a.name
    elif not scene.name:
        scene.name = os.path.basename(os.path.normpath(a.scene))
    meta = export(scene, a.out, test_every=a.test_every)
    print(f"{a.out}: {len(meta['train'])} training + {len(meta['test'])} held-out views of "
          f"{meta['width']}x{meta['height']}, points: {meta['points']}, masks: {meta['masked']}, gt: {meta['gt']}"
          + (f", roi: {meta['roi']}" if "roi" in meta else ""))


if __name__ == "__main__":
    main()
