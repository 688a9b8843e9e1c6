# SPDX-License-Identifier: Apache-2.0
"""Load a helper module from ``tests/`` by its file path (the references, the test-sized configuration,
the stability cases), so a benchmark run as ``.venv/bin/python benchmarks/x.py`` needs no ``sys.path`` edit; and
another version of a package module (a benchmark's ``--against FILE``) under a name of its own."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "tests"


def load_file(path, name: str):
    """The module at ``path`` imported as ``name`` (once; registered in ``sys.modules`` first, where dataclasses look
    their module up). A name inside a package (``"wtopo.geometry._mvs_against"``) makes the file's relative imports
    resolve against that package."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def load(relpath: str):
    """The module at ``tests/<relpath>`` (e.g. ``"reference/rasterize.py"``), imported once."""
    return load_file(TESTS / relpath, "_tests_" + relpath.removesuffix(".py").replace("/", "_"))
