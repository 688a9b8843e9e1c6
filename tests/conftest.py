# SPDX-License-Identifier: Apache-2.0
"""Shared pytest fixtures: the device list (CPU always, CUDA when present)."""

import os

import pytest
import torch

CUDA_DEVICE = os.environ.get("WTOPO_TEST_CUDA", "cuda:0")
"""The CUDA device the tests use: on a machine with two GPUs, ``WTOPO_TEST_CUDA=cuda:1`` runs them on a
device that is not torch's current one (streams and events must follow the tensors' device)."""


def _devices():
    """CPU, and :data:`CUDA_DEVICE` when CUDA is there."""
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append(CUDA_DEVICE)
    return devs


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test taking ``device`` runs on CPU and, when available, on CUDA."""
    return request.param


@pytest.fixture(autouse=True)
def _fresh_replays():
    """Each test starts with no shape of :func:`rasterize_surfels` known to its CUDA-graph replays, so that a test
    that changes a kernel setting between calls never meets a replay captured by an earlier test."""
    from wtopo.rasterize import _replay

    _replay.reset()
    yield
