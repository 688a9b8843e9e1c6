# SPDX-License-Identifier: Apache-2.0
"""The built wheel holds every package of the source tree and each imports from it; ``wtopo --version``."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _source_packages() -> set[str]:
    """Every package of the source tree: directories under wtopo/ with an ``__init__.py``, and wtopo.kernels."""
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "wtopo").rglob("__init__.py")
             if "__pycache__" not in p.parts}
    assert (ROOT / "kernels" / "__init__.py").is_file()
    return found | {"wtopo.kernels"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of this tree, built with the environment's setuptools (no download: ``--no-build-isolation``)."""
    pytest.importorskip("setuptools")
    # built from a copy: an in-tree build would leave build/ behind, whose stale modules a later build ships
    src = tmp_path_factory.mktemp("source")
    for name in ("wtopo", "kernels"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    out = tmp_path_factory.mktemp("wheel")
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                          "-q", "-w", str(out), str(src)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    wheels = list(out.glob("wtopo-*.whl"))
    assert len(wheels) == 1, f"expected one wheel in {out}, got {wheels}"
    return wheels[0]


def test_the_wheel_holds_every_package(wheel):
    """Put every package under wtopo/ and kernels/ (as wtopo.kernels) in the wheel, and no top-level kernels."""
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    in_wheel = {n[: -len("/__init__.py")].replace("/", ".") for n in names if n.endswith("/__init__.py")}
    missing = _source_packages() - in_wheel
    assert not missing, f"packages missing from {wheel.name}: {sorted(missing)}"
    assert not any(n.startswith("kernels/") for n in names), "kernels/ must install as wtopo.kernels only"
    modules = {n for n in names if n.endswith(".py")}
    for src in [*(ROOT / "wtopo").rglob("*.py"), *(ROOT / "kernels").glob("*.py")]:
        rel = src.relative_to(ROOT)
        name = "/".join(("wtopo", *rel.parts)) if rel.parts[0] == "kernels" else "/".join(rel.parts)
        assert name in modules, f"{name} is missing from {wheel.name}"


def test_every_package_imports_from_the_installed_wheel(wheel, tmp_path):
    """Import every package from the wheel's files alone, not from the source tree."""
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    packages = sorted(_source_packages())
    code = (
        "import importlib, json, sys\n"
        f"sys.path.insert(0, {str(site)!r})\n"
        f"out = {{}}\n"
        f"for name in {packages!r}:\n"
        "    out[name] = importlib.import_module(name).__file__\n"
        "print(json.dumps(out))\n"
    )
    # the source tree stays off sys.path: run from the extraction directory, without PYTHONPATH
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-4000:]
    files = json.loads(run.stdout.strip().splitlines()[-1])
    outside = {k: v for k, v in files.items() if not Path(v).resolve().is_relative_to(site.resolve())}
    assert not outside, f"imported from outside the wheel: {outside}"


def test_version_flag_prints_the_package_version(capsys):
    """Print ``wtopo X.Y.Z`` for ``wtopo --version`` and exit 0."""
    import wtopo
    from wtopo.cli import main

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"wtopo {wtopo.__version__}"
    assert wtopo.__version__ == "0.1.0"
