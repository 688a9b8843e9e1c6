"""Held-out image metrics: inside the masks for masked captures, the whole image otherwise."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from wtopo.fitting.evaluate import Evaluator


def _case(masked: bool):
    torch.manual_seed(0)
    img = torch.rand(2, 16, 16, 3)
    mask = torch.zeros(2, 16, 16, dtype=torch.bool)
    mask[:, 4:12, 4:12] = True
    # the render is 0.01 off inside the mask and 0.5 off outside it
    err = torch.where(mask[..., None], torch.tensor(0.01), torch.tensor(0.5))
    renders = [(img[k] + err[k]).clamp(0, 1) for k in range(2)]
    calls = iter(range(2))
    test = SimpleNamespace(cameras=[object(), object()], images=img, masks=mask if masked else None)

    def render(_surfels, _cam):
        return SimpleNamespace(rgb=renders[next(calls)])

    ev = Evaluator(test, None, render=render, enabled=False, seed=0)
    return ev.image_metrics(None), img, renders, mask


def test_masked_captures_are_scored_inside_the_masks():
    rec, img, renders, mask = _case(masked=True)
    assert rec["psnr_on"] == "masks"
    se = [((r - i) ** 2)[m].mean().item() for r, i, m in zip(renders, img, mask)]
    expected = np.mean([10 * np.log10(1 / e) for e in se])
    assert rec["psnr"] == pytest.approx(expected, rel=1e-5)
    assert rec["psnr"] > 35  # clamping can only shrink the 0.01 error inside


def test_unmasked_captures_are_scored_on_the_whole_image():
    rec, img, renders, _ = _case(masked=False)
    assert rec["psnr_on"] == "image"
    expected = np.mean([10 * np.log10(1 / ((r - i) ** 2).mean().item()) for r, i in zip(renders, img)])
    assert rec["psnr"] == pytest.approx(expected, rel=1e-5)
    assert rec["psnr"] < 20
