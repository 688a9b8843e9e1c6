# SPDX-License-Identifier: Apache-2.0
"""The documented entry points resolve to what design/overview.md promises."""

import types

import wtopo


def test_fit_is_a_function_after_the_pipeline_is_imported():
    """Call ``wtopo.fit(...)`` as a plain function, also after ``wtopo.FitConfig`` imported the pipeline."""
    cfg = wtopo.FitConfig()  # imports wtopo.fitting
    from wtopo.fitting import fit as fit_function

    assert isinstance(wtopo.fit, types.FunctionType)
    assert wtopo.fit is fit_function
    try:
        wtopo.fit("not a scene", cfg, progress=False)
    except TypeError as e:  # the function ran and validated its argument
        assert "scene" in str(e)
    else:
        raise AssertionError("fit accepted a string as a scene")


def test_kernels_come_from_the_installed_package():
    """Import ``wtopo.kernels`` through the installed package mapping, not a ``sys.modules`` mount."""
    import wtopo.kernels
    from wtopo.kernels import rasterize  # noqa: F401

    assert wtopo.kernels.__name__ == "wtopo.kernels"
