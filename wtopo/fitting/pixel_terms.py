# SPDX-License-Identifier: Apache-2.0
"""The per-pixel loss terms of one view (photometric, mask, normal consistency, distortion, multi-view NCC) as one
function of the rendered images, replayed on CUDA as CUDA graphs.

At a fit's image sizes these terms' kernels take tens of microseconds and their cost is the host's: about sixty
torch operations, four Warp ops and their autograd nodes, 3.0 ms an iteration forward and backward on the H200 at
384 x 384 px. ``torch.cuda.make_graphed_callables`` captures them once per set of terms and image size as a
forward and a backward graph (the Warp ops launch on torch's capture stream); a replay copies the inputs into the
graph's buffers and costs 0.25 ms (``lab/graph_losses.py``: the same losses, the same gradients bit for bit). The
multi-view term's windows (random pixels, drawn neighbours: :meth:`~wtopo.fitting.multiview.MultiViewNCC.draw`) are
drawn eagerly and enter the graph as inputs. The scale and mesh terms stay eager: they depend on the surfel count
or on the proxy mesh.

A capture that fails, or whose first replay differs from the eager terms, leaves that set of terms eager for the
rest of the fit (:attr:`PixelTerms.failures` says why). On the CPU the terms always run eagerly. Captures
(``_graphs.make_graphed``) run with the fit's values trusted and the collector off, and each set's inputs require
gradients exactly where its terms differentiate them (the capture differentiates every such input).
Limitation: a capture the device invalidates part-way can leave torch's CUDA random generator unusable in the
process (on the H200 the lab's capture of all four terms and the fit's of the photometric term succeeded).
"""

from __future__ import annotations

import dataclasses
import warnings

import torch
import torch.nn.functional as F

from .._graphs import make_graphed
from ..depth_normals import depth_normals
from ..multiview_ncc import ReferenceWindows
from .losses import distortion, mask_loss, normal_consistency, photometric
from .multiview import Windows, ncc_loss

__all__ = ["PixelTerms", "TermSet", "GRAPHS", "ALPHA_COVERED", "HALO_RING", "halo_ring"]

GRAPHS = True
"""False: the terms run eagerly on CUDA too (for comparison in benchmarks and tests)."""
ALPHA_COVERED = 0.5
"""A pixel is covered by the surfels when their rendered opacity reaches this."""
HALO_RING = 1
"""Width [pixels] of the ring just outside a view's mask that the photometric term does not compare: surfels lying
exactly on the true surface render a silhouette wider than the mask (0.7-1 px at the CPU plan's 0.35-px low-pass,
0.3-0.5 px at 0.15 px: each edge-on surfel's low-pass disk and its own tail past a curved limb), and comparing that
halo with the black background pulled the whole surface inward (design/decisions.md, "Kept: the photometric term
is blind to a 1-px ring outside the mask")."""
_CHECK_RTOL = 1e-5  # a first replay farther than this from the eager terms leaves the set eager
_GRAPHS_KEPT = 16  # captured sets kept (a fit uses a few: the term sets of its stages at its views' sizes)


@dataclasses.dataclass(frozen=True)
class TermSet:
    """Which per-pixel terms apply, with their weights (a graph is captured per set and image size).

    Attributes:
        dssim: weight of D-SSIM in the photometric term.
        mask: weight of the mask term (0: none).
        normal: weight of the normal-consistency term (0: none).
        distortion: weight of the distortion term (0: none).
        multiview: weight of the multi-view NCC term (0: none).
        sources: the multi-view term's drawn neighbours (one or two; 0 without the term).
        half: the multi-view term's half window side [pixels].
    """

    dssim: float
    mask: float = 0.0
    normal: float = 0.0
    distortion: float = 0.0
    multiview: float = 0.0
    sources: int = 0
    half: int = 0

    @property
    def names(self) -> tuple[str, ...]:
        """The terms' names in the order of :meth:`PixelTerms.__call__`'s result."""
        return ("photo", *(n for n in ("mask", "normal", "distortion", "multiview") if getattr(self, n) > 0))


def halo_ring(mask: torch.Tensor, width: int = HALO_RING) -> torch.Tensor:
    """The pixels outside ``mask`` within ``width`` pixels of it (Chebyshev distance: a square dilation), bool
    [..., H, W].

    Args:
        mask: object masks [..., H, W] (one view's, or the views' stacked), bool or float (inside where >= 0.5).
        width: the ring's width [pixels], at least 1.
    """
    if width < 1:
        raise ValueError(f"width must be at least 1 pixel, got {width}")
    inside = mask.to(torch.float32) >= 0.5
    flat = inside.reshape(-1, 1, *inside.shape[-2:]).to(torch.float32)
    grown = F.max_pool2d(flat, 2 * width + 1, stride=1, padding=width).reshape(inside.shape)
    return (grown > 0.5) & ~inside


def _inputs(ts: TermSet, render, image, mask, rays, windows: Windows | None,
            ring: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
    """The tensors the terms read: rgb, [alpha], [normal], [distortion], [median depth], image, [mask], [median
    depth, ray origins, ray directions], [the multi-view windows' tensors]. Each is differentiable exactly when a
    term differentiates it (a graph's backward takes the gradient of every input that requires one): the opacity
    only through the mask term (the others read its value), the depth only through the multi-view term (the depth
    normals are a fixed target). With a mask, the colour in its :func:`halo_ring` (``ring`` when given) is the
    photograph's (no gradient there)."""
    mv = ts.multiview > 0
    rgb = render.rgb
    if mask is not None:
        rgb = torch.where((halo_ring(mask) if ring is None else ring)[..., None], image.to(rgb.dtype), rgb)
    diff = [rgb]
    if ts.mask > 0:
        diff.append(render.alpha)
    elif ts.normal > 0 or mv:
        diff.append(render.alpha.detach())
    if ts.normal > 0 or mv:
        diff.append(render.normal)
    if ts.distortion > 0:
        diff.append(render.distortion)
    if mv:
        diff.append(render.median_depth)
    const = [image]
    if ts.mask > 0:
        const.append(mask.to(render.alpha.dtype))
    if ts.normal > 0:
        const += [*([] if mv else [render.median_depth.detach()]), *rays]
    if mv:
        const += [windows.py, windows.px, *windows.reference, *windows.images, windows.params]
    return (*diff, *const)


def _terms_fn(ts: TermSet):
    """The terms as a function of :func:`_inputs`' tensors, returning their weighted values stacked [k]."""
    mv = ts.multiview > 0

    def terms(*args):
        it = iter(args)
        rgb = next(it)
        alpha = next(it) if ts.mask > 0 or ts.normal > 0 or mv else None
        normal = next(it) if ts.normal > 0 or mv else None
        dist = next(it) if ts.distortion > 0 else None
        depth = next(it) if mv else None
        image = next(it)
        mask = next(it) if ts.mask > 0 else None
        out = [photometric(rgb, image, ts.dssim)]
        if ts.mask > 0:
            out.append(ts.mask * mask_loss(alpha, mask))
        if ts.normal > 0:
            median = depth.detach() if mv else next(it)
            o, d = next(it), next(it)
            dn, dmask = depth_normals(median, o, d, alpha.detach() >= ALPHA_COVERED)
            out.append(ts.normal * normal_consistency(normal, dn, alpha, dmask))
        if ts.distortion > 0:
            out.append(ts.distortion * distortion(dist))
        if mv:
            py, px = next(it), next(it)
            ref = ReferenceWindows(*(next(it) for _ in ReferenceWindows._fields))
            images = tuple(next(it) for _ in range(ts.sources))
            w = Windows(py, px, ref, images, next(it), ts.half)
            out.append(ts.multiview * ncc_loss(depth, normal, alpha, w))
        return torch.stack(out)

    return terms


class PixelTerms:
    """The per-pixel terms of a fit's views, graphed on CUDA (:data:`GRAPHS`).

    Args:
        make: what captures the terms (``torch.cuda.make_graphed_callables``'s signature); tests pass one that returns
            the function itself, so that everything but the capture runs on any device.

    Attributes:
        failures: ``{description of the set: why it runs eagerly}`` for the sets whose graph failed.
    """

    def __init__(self, *, make=None):
        self._make = make
        self._graphs: dict = {}
        self.failures: dict[str, str] = {}

    def __call__(self, ts: TermSet, render, image: torch.Tensor, mask: torch.Tensor | None,
                 rays: tuple[torch.Tensor, torch.Tensor] | None, windows: Windows | None = None,
                 ring: torch.Tensor | None = None) -> torch.Tensor:
        """The weighted terms of ``ts`` [len(ts.names)], differentiable w.r.t. the render's images.

        Args:
            ts: the terms and weights.
            render: the rasterizer's output of the view (``rgb``, ``alpha``, ``normal``, ``distortion``,
                ``median_depth``).
            image: the view's photograph [H, W, 3].
            mask: the view's object mask [H, W] (bool or float), needed when ``ts.mask > 0``; with it, the
                photometric term ignores the :func:`halo_ring` (:data:`HALO_RING` px) outside the mask.
            rays: the view's ``(origins, directions)`` [H, W, 3] (:meth:`wtopo.Camera.pixel_rays`), needed when
                ``ts.normal > 0``.
            windows: the multi-view term's windows (:meth:`~wtopo.fitting.multiview.MultiViewNCC.draw`), needed
                when ``ts.multiview > 0`` (``ts.sources`` images, ``ts.half`` their half side).
            ring: ``halo_ring(mask)`` when the caller keeps it (a fit computes each view's once), else ``None``.
        """
        if ts.multiview > 0 and (windows is None or len(windows.images) != ts.sources or windows.half != ts.half):
            raise ValueError(f"the multi-view term of {ts} needs windows of {ts.sources} images and half side "
                             f"{ts.half}, got {None if windows is None else (len(windows.images), windows.half)}")
        args = _inputs(ts, render, image, mask, rays, windows, ring)
        rgb = render.rgb
        if not (GRAPHS and (rgb.is_cuda or self._make is not None) and torch.is_grad_enabled()):
            return _terms_fn(ts)(*args)
        key = (ts, tuple(tuple(a.shape) for a in args), rgb.dtype, rgb.device, tuple(a.requires_grad for a in args))
        fn = self._graphs.get(key)
        if fn is None:
            if len(self._graphs) >= _GRAPHS_KEPT:  # views of many sizes: the oldest set's graphs go
                self._graphs.pop(next(iter(self._graphs)))
            fn = self._graphs[key] = self._capture(ts, key, args)
        return fn(*args)

    def _capture(self, ts: TermSet, key, args):
        """A graphed version of the terms for ``key``, checked against the eager terms on ``args``; the eager
        function when capturing fails or disagrees."""
        eager = _terms_fn(ts)
        try:
            graphed = make_graphed(eager, args, warmup=3, make=self._make)
            with torch.no_grad():
                want = eager(*args)
            got = graphed(*(a.detach() for a in args)).detach()
            if not torch.allclose(got, want, rtol=_CHECK_RTOL, atol=0.0, equal_nan=True):  # a non-finite step too
                raise RuntimeError(f"a replay gave {got.tolist()} where the eager terms give {want.tolist()}")
        except Exception as e:  # noqa: BLE001 - any failure of the capture leaves this set eager
            why = f"{type(e).__name__}: {e}"
            self.failures[f"{ts.names} at {tuple(key[1][0])}"] = why
            warnings.warn(f"wtopo: the loss terms {ts.names} run eagerly on this device: {why}", RuntimeWarning,
                          stacklevel=3)
            return eager
        return graphed
