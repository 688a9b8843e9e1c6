# SPDX-License-Identifier: Apache-2.0
"""A stand-in for ``torch.cuda.make_graphed_callables`` for the graph paths' tests on any device."""

from __future__ import annotations

import torch


def _run_on(static_in, inputs, samples, fn):
    """``inputs`` copied into the fixed buffers ``static_in`` and ``fn`` run on leaves of them (requiring grad as
    ``samples`` do): ``(leaves, outputs)``."""
    for buf, x in zip(static_in, inputs):
        buf.copy_(x.detach())
    with torch.enable_grad():
        leaves = [buf.detach().requires_grad_(x.requires_grad) for buf, x in zip(static_in, samples)]
        return leaves, fn(*leaves)


def static_buffers(fn, samples, num_warmup_iters=0):
    """A stand-in for ``torch.cuda.make_graphed_callables`` with its buffer semantics and no capture: inputs are
    copied into fixed buffers, outputs copied into fixed buffers that the next call overwrites (and returned as
    aliases of them), input gradients copied into fixed buffers zeroed at the next call (as a replay's gradient
    buffers are, by the forward graph). A caller that reads an output or a gradient after the next call sees
    another call's values, as it would on a GPU."""
    static_in = [x.detach().clone() for x in samples]
    state: dict = {}

    class Replay(torch.autograd.Function):
        @staticmethod
        def forward(ctx, *inputs):
            for g in state.get("grads", ()):
                if g is not None:
                    g.zero_()
            leaves, outs = _run_on(static_in, inputs, samples, fn)
            state["single"] = isinstance(outs, torch.Tensor)
            outs = (outs,) if state["single"] else tuple(outs)
            if "outs" not in state:
                state["outs"] = [o.detach().clone() for o in outs]
            for buf, o in zip(state["outs"], outs):
                buf.copy_(o.detach())
            ctx.leaves, ctx.outs = leaves, outs
            return tuple(buf.detach() for buf in state["outs"])

        @staticmethod
        def backward(ctx, *grads):
            pairs = [(o, g) for o, g in zip(ctx.outs, grads) if o.requires_grad and g is not None]
            diff = [leaf for leaf in ctx.leaves if leaf.requires_grad]
            got = torch.autograd.grad([o for o, _ in pairs], diff, [g for _, g in pairs], allow_unused=True)
            it = iter(got)
            out = [next(it) if leaf.requires_grad else None for leaf in ctx.leaves]
            if "grads" not in state:
                state["grads"] = [None if g is None else torch.zeros_like(g) for g in out]
            for buf, g in zip(state["grads"], out):
                if buf is not None and g is not None:
                    buf.copy_(g)
            return tuple(None if buf is None else buf.detach() for buf in state["grads"])

    def replay(*args):
        out = Replay.apply(*args)
        return out[0] if state["single"] else out

    return replay


def latest_state(fn, samples, num_warmup_iters=0):
    """A stand-in for ``torch.cuda.make_graphed_callables`` whose backward, as a replayed backward graph of the
    rasterizer does, reads the state the latest forward left (its inputs and intermediate values), whichever
    forward the gradient belongs to, and adds into input-gradient buffers that only a forward zeroes; outputs in
    fixed buffers as :func:`static_buffers`. A second forward before an earlier one's backward gives that backward
    the later forward's gradients, and a second backward after one forward doubles them, as on a GPU."""
    static_in = [x.detach().clone() for x in samples]
    state: dict = {}

    class Replay(torch.autograd.Function):
        @staticmethod
        def forward(ctx, *inputs):
            leaves, outs = _run_on(static_in, inputs, samples, fn)
            outs = tuple(outs)
            state["leaves"], state["outs"] = leaves, outs
            for g in state.get("grad_bufs", ()):
                if g is not None:
                    g.zero_()
            if "out_bufs" not in state:
                state["out_bufs"] = [o.detach().clone() for o in outs]
            for buf, o in zip(state["out_bufs"], outs):
                buf.copy_(o.detach())
            return tuple(buf.detach() for buf in state["out_bufs"])

        @staticmethod
        @torch.autograd.function.once_differentiable
        def backward(ctx, *grads):
            leaves, outs = state["leaves"], state["outs"]
            pairs = [(o, g) for o, g in zip(outs, grads) if o.requires_grad and g is not None]
            diff = [leaf for leaf in leaves if leaf.requires_grad]
            got = iter(torch.autograd.grad([o for o, _ in pairs], diff, [g for _, g in pairs], retain_graph=True,
                                           allow_unused=True))
            out = [next(got) if leaf.requires_grad else None for leaf in leaves]
            if "grad_bufs" not in state:
                state["grad_bufs"] = [None if g is None else torch.zeros_like(g) for g in out]
            for buf, g in zip(state["grad_bufs"], out):
                if buf is not None and g is not None:
                    buf.add_(g)
            return tuple(None if buf is None else buf.detach() for buf in state["grad_bufs"])

    return lambda *args: Replay.apply(*args)


def fixed_outputs(fn, args, warmup=0):
    """A stand-in for ``wtopo._graphs.capture_forward`` with its semantics and no capture: ``replay()`` runs ``fn``
    on ``args`` (reading what they hold at that moment, as a graph reads its captured addresses) with autograd
    off and copies the results into fixed output buffers, which the next replay overwrites."""
    with torch.no_grad():
        outs = tuple(o.clone() for o in fn(*args))

    def replay():
        with torch.no_grad():
            for buf, o in zip(outs, fn(*args)):
                buf.copy_(o)

    return replay, outs
