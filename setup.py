# SPDX-License-Identifier: Apache-2.0
"""Package discovery; pyproject.toml holds the rest of the build configuration.

Every package under ``wtopo/`` is found, so a new subpackage cannot be left out of a wheel, and ``kernels/`` is
installed as ``wtopo.kernels`` (pyproject's ``[tool.setuptools.package-dir]``). setuptools' declarative
discovery (``[tool.setuptools.packages.find]``) finds only packages in their own directories: it cannot add
``wtopo.kernels`` from ``kernels/``, hence these lines.
"""

from setuptools import find_packages, setup

setup(packages=[*find_packages(include=["wtopo", "wtopo.*"]), "wtopo.kernels"])
