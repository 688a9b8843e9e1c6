# SPDX-License-Identifier: Apache-2.0
"""Shared pytest fixtures: the device list (CPU always, CUDA when present)."""

import pytest
import torch


def _devices():
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda:0")
    return devs


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test taking ``device`` runs on CPU and, when available, on CUDA."""
    return request.param
