# SPDX-License-Identifier: Apache-2.0
"""The argument-check helpers: value checks skipped only inside ``trusted_values`` (the fit's iterations)."""

import pytest
import torch

from wtopo._validate import require_finite, trusted_values, value_checks
from wtopo.ops import poisson_indicator


def test_trusted_values_skips_value_checks_only_inside():
    """Raise on NaN outside the block, skip inside it, and restore the checks after an exception."""
    bad = torch.tensor([1.0, float("nan")])
    with pytest.raises(ValueError, match="x must be finite"):
        require_finite("x", bad)
    with trusted_values():
        assert not value_checks()
        require_finite("x", bad)
    assert value_checks()
    with pytest.raises(RuntimeError), trusted_values():
        raise RuntimeError("inside")
    assert value_checks()


def test_trusted_values_keeps_shape_checks(device):
    """Skip the data-reading check of an op (negative weight) but keep its shape check inside the block."""
    pts = torch.rand(20, 3, dtype=torch.float64, device=device) * 0.5 + 0.25
    nrm = torch.nn.functional.normalize(torch.randn(20, 3, dtype=torch.float64, device=device), dim=1)
    w = torch.ones(20, dtype=torch.float64, device=device)
    w[3] = -1.0
    with pytest.raises(ValueError, match="weights must be >= 0"):
        poisson_indicator(pts, nrm, w, 8)
    with trusted_values():
        poisson_indicator(pts, nrm, w, 8)  # the caller vouches for its values: no device read
        with pytest.raises(ValueError, match="normals"):
            poisson_indicator(pts, nrm[:5], w, 8)
