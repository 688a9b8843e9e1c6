# SPDX-License-Identifier: Apache-2.0
"""Shared pytest fixtures: the device list (CPU always, CUDA when present)."""

import os

import pytest
import torch


def _devices():
    """CPU, and the CUDA device ``WTOPO_TEST_CUDA`` names (default ``cuda:0``) when there is one: on a
    machine with two GPUs, ``WTOPO_TEST_CUDA=cuda:1`` runs the CUDA tests on a device that is not torch's
    current one (streams and events must follow the tensors' device, not the current one)."""
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append(os.environ.get("WTOPO_TEST_CUDA", "cuda:0"))
    return devs


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test taking ``device`` runs on CPU and, when available, on CUDA."""
    return request.param
