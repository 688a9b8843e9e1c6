# SPDX-License-Identifier: Apache-2.0
"""The documented entry points resolve to what DESIGN.md promises."""

import wtopo


def test_fit_is_callable_after_the_package_is_imported():
    """Call ``wtopo.fit(...)`` even after ``wtopo.FitConfig`` imported the ``wtopo.fit`` package."""
    cfg = wtopo.FitConfig()  # imports the subpackage, which rebinds wtopo.fit to the module
    assert callable(wtopo.fit)
    from wtopo.fit import fit as fit_function

    assert wtopo.fit.fit is fit_function
    try:
        wtopo.fit("not a scene", cfg, progress=False)
    except TypeError as e:  # the function ran and validated its argument
        assert "scene" in str(e)
    else:
        raise AssertionError("fit accepted a string as a scene")
