# SPDX-License-Identifier: Apache-2.0
"""The documentation stays true to the code: docs/config.md is what scripts/config_reference.py writes
today, and every configuration path the README and docs/ name is a FitConfig field."""

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path

import pytest

from wtopo.fitting.config import FitConfig

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
HANDWRITTEN = [ROOT / "README.md"] + [p for p in DOCS if p.name != "config.md"]
SECTIONS = {f.name for f in dataclasses.fields(FitConfig) if dataclasses.is_dataclass(getattr(FitConfig(), f.name))}
FILE_SUFFIXES = (".ply", ".json", ".usdc", ".usda", ".usd", ".py", ".md", ".obj", ".npz", ".png", ".db", ".pt", ".txt")


def _generator():
    spec = importlib.util.spec_from_file_location("config_reference", ROOT / "scripts" / "config_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def resolves(path: str) -> bool:
    """Whether ``path`` (``"losses.mask"``) names a leaf field of ``FitConfig``."""
    node = FitConfig()
    for part in path.split("."):
        if not dataclasses.is_dataclass(node) or part not in {f.name for f in dataclasses.fields(node)}:
            return False
        node = getattr(node, part)
    return not dataclasses.is_dataclass(node)


def test_the_generator_reads_field_docstrings_from_the_source():
    gen = _generator()
    by_path = {e.path: e for e in gen.entries()}
    assert set(by_path) == {p for p in by_path if resolves(p)}
    assert "warmup.iterations" in by_path and "losses.mask" in by_path and "kind" in by_path
    assert by_path["runtime.device"].default == "auto"
    documented = [e for e in by_path.values() if e.doc]
    assert len(documented) >= 0.9 * len(by_path), [e.path for e in by_path.values() if not e.doc]


def test_config_reference_is_current(tmp_path):
    gen = _generator()
    fresh = gen.write(tmp_path / "config.md").read_text(encoding="utf-8")
    committed = (ROOT / "docs" / "config.md").read_text(encoding="utf-8")
    assert committed == fresh, "docs/config.md is stale: run .venv/bin/python scripts/config_reference.py"


def _set_paths(text: str) -> list[str]:
    """The paths of ``--set PATH=VALUE`` examples (lower case: ``PATH`` itself is the placeholder)."""
    return re.findall(r"--set[ =]+([a-z_][a-z0-9_.]*)=", text)


def _named_paths(text: str) -> list[str]:
    """Backticked ``section.field`` (optionally ``=value``) of a FitConfig section, not file names."""
    out = []
    for token in re.findall(r"`([A-Za-z_][\w.]*)(?:=[^`]*)?`", text):
        head = token.split(".")[0]
        if "." in token and head in SECTIONS and not token.endswith(FILE_SUFFIXES):
            out.append(token)
    return out


@pytest.mark.parametrize("doc", [ROOT / "README.md", *DOCS], ids=lambda p: p.name)
def test_every_set_example_is_a_field(doc):
    bad = [p for p in _set_paths(doc.read_text(encoding="utf-8")) if not resolves(p)]
    assert not bad, f"{doc.name}: --set paths that are not FitConfig fields: {bad}"


@pytest.mark.parametrize("doc", HANDWRITTEN, ids=lambda p: p.name)
def test_every_named_config_path_is_a_field(doc):
    bad = [p for p in _named_paths(doc.read_text(encoding="utf-8")) if not resolves(p)]
    assert not bad, f"{doc.name}: configuration paths that are not FitConfig fields: {bad}"


def test_the_checks_catch_a_wrong_path():
    assert _set_paths("x --set PATH=VALUE --set losses.mask=0.5 --set nope.field=1") == ["losses.mask", "nope.field"]
    assert _named_paths("`mesh.ply` `mesh.resolution` `final.method=proxy` `tests/x.py`") == [
        "mesh.resolution", "final.method"]
    assert resolves("losses.mask") and not resolves("losses") and not resolves("nope.field")
