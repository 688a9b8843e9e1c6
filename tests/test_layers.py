# SPDX-License-Identifier: Apache-2.0
"""The package's layers: imports flow one way (kernels -> base -> ops -> geometry -> data -> fit -> app),
no import cycle among wtopo modules, and no source file over 500 lines.

Every ``import`` statement is read with :mod:`ast`, at module level and inside functions, classes and
``if TYPE_CHECKING:`` blocks alike: a deferred import is still a dependency. An import names the module it
reaches (``from wtopo.fitting import loop`` reaches ``wtopo.fitting.loop``; ``from wtopo.fitting import fit``
reaches ``wtopo.fitting``). Importing a submodule also runs its parent packages' ``__init__``; that edge is
not counted (a package's ``__init__`` gathering its own modules is not a cycle). The root package's lazy
attributes (``wtopo.fit`` resolved by :func:`importlib.import_module` on first use) are not imports.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 500
# Files over the limit for now, each with why. The check fails once one of them is back under it, so the
# entry cannot outlive its reason.
OVER_LIMIT: dict[str, str] = {}

# Lowest first. A module belongs to the layer of the longest prefix listed here; a module may import its
# own layer and the layers below it, never one above.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # Warp code only: @wp.kernel / @wp.func / @wp.struct and lookup tables
    ("kernels", ("wtopo.kernels",)),
    # what every op shares: the torch bridge, validation, profiling sections, the camera; the root package
    # (``wtopo.__version__``, Warp's configuration)
    ("base", ("wtopo", "wtopo._views", "wtopo._bridge", "wtopo._validate", "wtopo._profile", "wtopo.camera")),
    # one module per differentiable or discrete op
    ("ops", ("wtopo.ops", "wtopo.rasterize", "wtopo.raycast", "wtopo.scatter", "wtopo.poisson",
             "wtopo.marching_cubes", "wtopo.oriented_points", "wtopo.photometric", "wtopo.multiview_ncc",
             "wtopo.plane_sweep", "wtopo.vertex_support", "wtopo.depth_normals")),
    # what several callers share; the TSDF fusion composes marching cubes, the lens warp and components
    ("geometry", ("wtopo.geometry", "wtopo.tsdf_fusion")),
    # scenes and their files, synthetic scenes, surfel / mesh / USD files, metrics
    ("data", ("wtopo.scene", "wtopo.loaders", "wtopo.scenes", "wtopo.io", "wtopo.metrics")),
    # the fit
    ("fit", ("wtopo.fitting",)),
    # what drives fits: chunked fits, reports, the command line
    ("app", ("wtopo.chunks", "wtopo.report", "wtopo.cli")),
]


def _sources() -> dict[str, tuple[Path, bool]]:
    """``{module name: (file, is a package __init__)}`` of wtopo/ and kernels/ (installed as wtopo.kernels)."""
    out = {}
    for base, prefix in (("wtopo", ()), ("kernels", ("wtopo",))):
        for path in sorted((ROOT / base).rglob("*.py")):
            parts = list(prefix) + list(path.relative_to(ROOT).with_suffix("").parts)
            package = parts[-1] == "__init__"
            if package:
                parts = parts[:-1]
            out[".".join(parts)] = (path, package)
    return out


MODULES = _sources()


def _imports(name: str, path: Path, package: bool) -> set[str]:
    """The wtopo modules ``name`` imports anywhere in its file."""
    here = name if package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = here.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.add(sub if sub in MODULES else base)
    out = set()
    for target in found:
        if not (target == "wtopo" or target.startswith("wtopo.")):
            continue
        while target not in MODULES and "." in target:  # an attribute path: its module
            target = target.rpartition(".")[0]
        if target in MODULES and target != name:
            out.add(target)
    return out


GRAPH = {name: _imports(name, path, package) for name, (path, package) in MODULES.items()}


def _layer(name: str) -> int:
    best, level = -1, None
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > best:
                best, level = len(p), i
    if level is None:
        raise AssertionError(f"{name} is in no layer of tests/test_layers.py: add it to LAYERS")
    return level


def test_every_module_has_a_layer():
    """Place every module under wtopo/ and kernels/ in exactly one layer."""
    for name in MODULES:
        _layer(name)


def test_imports_never_go_up_a_layer():
    """Import only modules of the same or a lower layer."""
    bad = [f"{m} ({LAYERS[_layer(m)][0]}) imports {t} ({LAYERS[_layer(t)][0]})"
           for m, targets in sorted(GRAPH.items()) for t in sorted(targets) if _layer(t) > _layer(m)]
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_nothing_outside_the_fit_imports_it():
    """Import ``wtopo.fitting`` only from the fit itself, the chunked fit and the CLI."""
    allowed = ("wtopo.fitting", "wtopo.chunks", "wtopo.cli")
    bad = [f"{m} imports {t}" for m, targets in sorted(GRAPH.items()) for t in sorted(targets)
           if (t == "wtopo.fitting" or t.startswith("wtopo.fitting."))
           and not any(m == a or m.startswith(a + ".") for a in allowed)]
    assert not bad, "\n".join(bad)


def test_chunks_use_the_public_surface_of_the_fit():
    """Import from ``wtopo.fitting`` in ``wtopo.chunks`` only names its ``__all__`` exports."""
    import wtopo.fitting

    public = set(wtopo.fitting.__all__)
    bad = []
    for name, (path, package) in MODULES.items():
        if not name.startswith("wtopo.chunks"):
            continue
        here = name if package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                parts = here.split(".")
                base = ".".join(parts[: len(parts) - (node.level - 1)] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base.startswith("wtopo.fitting"):
                names = [a.name for a in node.names]
                if base != "wtopo.fitting" or not set(names) <= public:
                    bad.append(f"{name}: from {base} import {', '.join(names)}")
    assert not bad, "\n".join(bad)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_cycles():
    """Keep the wtopo import graph acyclic, deferred imports included."""
    cycles = _cycles(GRAPH)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_check_finds_a_cycle():
    """Report a two-module cycle and a three-module one, and nothing in a chain."""
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": set()}) == [["a", "b"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


@pytest.mark.parametrize("folder", ["wtopo", "kernels"])
def test_no_source_file_over_500_lines(folder):
    """Keep every .py file under wtopo/ and kernels/ at 500 lines or fewer."""
    lines = {str(p.relative_to(ROOT)): len(p.read_text().splitlines()) for p in sorted((ROOT / folder).rglob("*.py"))}
    long = {f: n for f, n in lines.items() if n > MAX_LINES and f not in OVER_LIMIT}
    assert not long, f"files over {MAX_LINES} lines: {long}"
    stale = [f for f in OVER_LIMIT if f in lines and lines[f] <= MAX_LINES]
    assert not stale, f"{stale} are back within {MAX_LINES} lines: remove them from OVER_LIMIT"
