# SPDX-License-Identifier: Apache-2.0
"""Finding the photographs of a structure-from-motion run: the image folder and its workspace,
which image pairs are matched (:func:`choose_matcher`), and the one image size they must share."""

from __future__ import annotations

import itertools
import os
import re

from ._sfm_options import IMAGE_EXTENSIONS, Matcher, SfMOptions

_IMAGE_FOLDERS = ("images", "image")  # a workspace's image folder: the model goes beside it, not into it


def _image_names(folder: str) -> list[str]:
    try:
        entries = sorted(os.listdir(folder))
    except OSError:
        return []
    return [e for e in entries if e.lower().endswith(IMAGE_EXTENSIONS) and os.path.isfile(os.path.join(folder, e))]


def find_photos(path: str) -> tuple[str, list[str]] | None:
    """``(image folder, sorted image names)`` when ``path`` is a folder of photographs (or holds
    one called ``images``, or ``image`` as in the IDR / NeuS layout), else ``None``. Only files with
    an :data:`IMAGE_EXTENSIONS` suffix count; other files (a ``masks/`` folder, notes) are ignored."""
    p = os.fspath(path)
    for d in (*(os.path.join(p, f) for f in _IMAGE_FOLDERS), p):
        names = _image_names(d)
        if names:
            return d, names
    return None


def _workspace(image_dir: str) -> str:
    named = os.path.basename(os.path.normpath(image_dir)) in _IMAGE_FOLDERS
    return os.path.dirname(os.path.normpath(image_dir)) if named else image_dir


def _frame_sequence(names: list[str]) -> bool:
    """Whether the names read as numbered frames of one sequence (``frame_0001.jpg``, ...)."""
    parts = [re.fullmatch(r"(.*?)(\d+)(\.[^.]+)", n) for n in names]
    if not all(parts) or len({(m.group(1), m.group(3)) for m in parts}) != 1:
        return False
    nums = sorted(int(m.group(2)) for m in parts)
    steps = {b - a for a, b in zip(nums, nums[1:])}
    return len(steps) == 1 and steps != {0}


def choose_matcher(names: list[str], options: SfMOptions) -> tuple[str, str]:
    """``(matcher, reason)``: the configured matcher, or exhaustive up to
    :attr:`SfMOptions.exhaustive_max_images` images and sequential beyond (video frames)."""
    n = len(names)
    pairs = n * (n - 1) // 2
    if options.matcher is not None:
        return options.matcher, f"set in the options ({n} images)"
    if n <= options.exhaustive_max_images:
        return Matcher.EXHAUSTIVE.value, (f"{n} images <= {options.exhaustive_max_images}: all {pairs} pairs are "
                                          "matched (robust to any capture order)")
    why = (f"{n} images > {options.exhaustive_max_images}: matching all {pairs} pairs would take hours; each image "
           f"is matched with its {options.sequential_overlap} successors in name order")
    if _frame_sequence(names):
        return Matcher.SEQUENTIAL.value, why + " (the names number the frames of one sequence: a video)"
    return Matcher.SEQUENTIAL.value, why + (" (the names do not number one sequence: if the photos are not in capture "
                                            "order, pass matcher='exhaustive')")


def _pairs(names: list[str], matcher: str, overlap: int) -> list[tuple[str, str]]:
    if matcher == Matcher.EXHAUSTIVE.value:
        return list(itertools.combinations(names, 2))
    n = len(names)
    steps = sorted(set(range(1, overlap + 1)) | {2 ** k for k in range(overlap)})  # COLMAP's quadratic overlap
    return [(names[i], names[i + s]) for i in range(n) for s in steps if i + s < n]


def _check_sizes(image_dir: str, names: list[str]) -> tuple[int, int]:
    """The one ``(width, height)`` of all images (headers only); ``ValueError`` listing the sizes if not one."""
    from PIL import Image

    sizes: dict[tuple[int, int], list[str]] = {}
    for n in names:
        p = os.path.join(image_dir, n)
        try:
            with Image.open(p) as im:
                sizes.setdefault(im.size, []).append(n)
        except (OSError, SyntaxError, ValueError) as e:
            raise ValueError(f"cannot read image {p}: {e}") from None
    if len(sizes) > 1:
        listed = "; ".join(f"{w}x{h}: {len(v)} image(s), e.g. {v[0]}" for (w, h), v in
                           sorted(sizes.items(), key=lambda kv: -len(kv[1])))
        raise ValueError(f"the photos in {image_dir} must share one size, since one camera is fitted to all of them; "
                         f"got {len(sizes)} sizes (WxH): {listed}. Resize or crop them to one size (rotated portrait "
                         "shots: rotate them to the landscape ones)")
    return next(iter(sizes))
