# SPDX-License-Identifier: Apache-2.0
"""The bridge's memory: torch tensors viewed as Warp arrays and Warp arrays allocated in torch's memory.

:func:`to_warp` views a tensor without a copy; :func:`empty` allocates an op's arrays through torch's caching
allocator; :func:`as_torch` hands such an array back to torch. :mod:`wtopo._bridge` re-exports all three, and the ops
use them from there.
"""

from __future__ import annotations

import threading

import torch
import warp as wp
from warp._src.types import array_t

_init_lock = threading.Lock()
_initialized = False


def _ensure_init() -> None:
    global _initialized
    if not _initialized:
        with _init_lock:
            if not _initialized:
                wp.init()  # a no-op after wtopo's import-time initialisation (wtopo/__init__.py configures Warp)
                _initialized = True


_VEC = {
    (torch.float32, 1): wp.float32,
    (torch.float64, 1): wp.float64,
    (torch.float32, 2): wp.vec2,
    (torch.float64, 2): wp.vec2d,
    (torch.float32, 3): wp.vec3,
    (torch.float64, 3): wp.vec3d,
    (torch.float32, 4): wp.vec4,
    (torch.float64, 4): wp.vec4d,
}


def float_dtype(t: torch.Tensor):
    """Warp scalar type for a float32/float64 tensor."""
    return _VEC[(t.dtype, 1)]


def vec_dtype(t: torch.Tensor, n: int | None = None):
    """Warp vector type ``vecN``/``vecNd`` for a tensor whose last dimension is ``n``."""
    n = t.shape[-1] if n is None else n
    return _VEC[(t.dtype, n)]


_SCALAR = {torch.float32: wp.float32, torch.float64: wp.float64, torch.float16: wp.float16, torch.int32: wp.int32,
           torch.int64: wp.int64, torch.int16: wp.int16, torch.int8: wp.int8, torch.uint8: wp.uint8,
           torch.bool: wp.bool}
_wp_devices: dict = {}


def _view_device(device: torch.device):
    d = _wp_devices.get(device)
    if d is None:
        d = _wp_devices[device] = wp.device_from_torch(device)
    return d


_templates: dict = {}
_TEMPLATES_MAX = 1024  # distinct (dtype, shape, device) views kept; cleared when full (a fit uses a few dozen)


def _view(ptr: int, dtype, shape: tuple, device: torch.device) -> wp.array:
    """``wp.array(ptr=ptr, dtype=dtype, shape=shape, device=...)``, contiguous, made by copying the attributes of a
    template built once per ``(dtype, shape, device)`` by that constructor and setting ``ptr``: the same array
    (``tests/test_bridge.py`` compares every attribute with the constructor's) in about a tenth of the host time.
    Its kernel descriptor (``ctype``, which Warp builds at the array's first launch and drops when a gradient is
    attached) is made here too, as a byte copy of the template's with the address set: a fifth of the time of
    Warp's (1.8 against 0.36 us on a 2-core CPU, about 110 views an iteration)."""
    key = (dtype, shape, device)
    kept = _templates.get(key)
    if kept is None:
        if len(_templates) >= _TEMPLATES_MAX:
            _templates.clear()
        tmpl = wp.array(ptr=0, dtype=dtype, shape=shape, device=_view_device(device))
        kept = _templates[key] = (tmpl, array_t(data=0, grad=0, ndim=tmpl.ndim, shape=tmpl.shape,
                                                strides=tmpl.strides, flags=0))
    tmpl, ctype = kept
    arr = wp.array.__new__(wp.array)
    arr.__dict__.update(tmpl.__dict__)
    arr.ptr = ptr
    arr.ctype = c = array_t.from_buffer_copy(ctype)
    c.data = ptr
    return arr


_plans: dict = {}  # (torch dtype, Warp dtype, shape) -> the direct path's (Warp dtype, view shape), or False


def _direct_plan(tdtype, dtype, shape: tuple):
    """What :func:`to_warp`'s direct path makes of a contiguous tensor: ``(Warp dtype, view shape)``, or ``None``
    where it does not apply (an unknown or empty tensor, a vector type that does not fit its last dimensions)."""
    scalar = _SCALAR.get(tdtype)
    if scalar is None or not all(shape):
        return None
    if dtype is None or dtype is scalar:
        return scalar, shape
    want = getattr(dtype, "_shape_", None)
    k = 0 if want is None else len(want)
    if k == 0 or getattr(dtype, "_wp_scalar_type_", None) is not scalar or shape[-k:] != tuple(want):
        return None
    return dtype, shape[:-k] or (1,)


def to_warp(t: torch.Tensor, dtype=None) -> wp.array:
    """View a tensor as a Warp array without copying (the tensor is made contiguous first).

    ``dtype`` is a Warp scalar or vector type; a vector type consumes the tensor's last dimension. No gradient
    buffer is attached (the bridge attaches torch-owned ones to the inputs that need them). The view keeps the
    tensor alive. A contiguous tensor of a known dtype takes a direct path (``wp.array`` at the tensor's address
    with the canonical strides: 4.8 us a call on a 2-core CPU, where ``wp.from_torch`` behind the stride fix-ups
    below took 25, ``benchmarks/gpu.md``); the result is the same view. A non-contiguous one (the expanded upstream
    gradient of a sum or a mean, a transpose) takes it through its contiguous copy, which the view keeps alive
    (8 against 15 us for a [64, 64, 3] expanded gradient as ``vec3``).
    """
    key = (t.dtype, dtype, t.shape)
    plan = _plans.get(key)
    if plan is None:
        _ensure_init()
        if len(_plans) >= _TEMPLATES_MAX:
            _plans.clear()
        plan = _plans[key] = _direct_plan(t.dtype, dtype, tuple(t.shape)) or False
    if plan and t.is_contiguous():
        arr = _view(t.data_ptr(), plan[0], plan[1], t.device)
        # keeps the storage alive, as wp.from_torch does; a tensor with a history through a detached alias (the view
        # must not hold its graph), any other as it is (a detach costs a torch operation, ~150 an iteration)
        arr._tensor = t if t.grad_fn is None else t.detach()  # noqa: SLF001
        return arr
    scalar = _SCALAR.get(t.dtype)
    if scalar is not None and t.numel() > 0 and not t.is_contiguous():
        # an upstream gradient of a sum or mean is an expanded scalar: its contiguous copy takes the direct path
        return to_warp(t.detach().contiguous(), dtype)
    t = t.detach().contiguous()
    if t.numel() == 0:  # an empty tensor counts as contiguous whatever its strides; Warp checks them
        t = torch.empty(t.shape, dtype=t.dtype, device=t.device)
    elif t.dim() > 1:
        # a size-1 dimension keeps any stride in a contiguous tensor ([1, 4] sliced from [1, 6]: stride 6); a
        # gradient buffer made for it has the canonical ones, which Warp requires to match
        t = t.view(-1).view(t.shape)
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


def struct_view(t: torch.Tensor, dtype) -> wp.array:
    """The bytes of ``t`` (a contiguous uint8 tensor) as a Warp array of the struct type ``dtype``, as many
    records as fit whole; the view keeps ``t`` alive."""
    if t.dtype != torch.uint8 or not t.is_contiguous():
        raise TypeError(f"struct_view needs a contiguous uint8 tensor, got {t.dtype}")
    n = t.numel() // wp.types.type_size_in_bytes(dtype)
    arr = _view(t.data_ptr(), dtype, (n,), t.device)
    arr._tensor = t  # noqa: SLF001
    return arr


def quad_view(records: wp.array, quad) -> wp.array:
    """The records of a :func:`empty_struct` array as ``[N, 4]`` of ``quad`` (``wp.vec4`` or ``wp.vec4d``): the same
    memory, four quads a record (the record's size must be four quads'); the view keeps it alive."""
    if wp.types.type_size_in_bytes(records.dtype) != 4 * wp.types.type_size_in_bytes(quad):
        raise TypeError(f"quad_view: a {records.dtype.__name__} record is not four {quad.__name__}")
    t = records._tensor  # noqa: SLF001
    arr = _view(t.data_ptr(), quad, (records.shape[0], 4), t.device)
    arr._tensor = t  # noqa: SLF001
    return arr


def empty_struct(n: int, dtype, device) -> wp.array:
    """``wp.empty(n, dtype=dtype)`` of a struct type in torch's memory (uninitialised; a CUDA graph's capture may
    allocate it, where Warp's own pool may not be used)."""
    if not isinstance(device, wp.Device):
        device = wp.get_device(device)
    size = wp.types.type_size_in_bytes(dtype)
    return struct_view(torch.empty(max(int(n), 0) * size, dtype=torch.uint8, device=_torch_device(device)), dtype)


_TORCH_OF = {v: k for k, v in _SCALAR.items()}
_torch_devices: dict = {}


def _torch_device(device: wp.Device) -> torch.device:
    """The torch device of a Warp device (Warp's devices are long-lived singletons, and not hashable: kept by id)."""
    tdev = _torch_devices.get(id(device))
    if tdev is None:
        tdev = _torch_devices[id(device)] = torch.device(wp.device_to_torch(device))
    return tdev


def empty(shape, dtype, device, requires_grad: bool = False, zero: bool = False) -> wp.array:
    """``wp.empty`` (``zero``: ``wp.zeros``) whose memory torch's caching allocator owns.

    ``shape`` an int or tuple; ``dtype`` a Warp scalar or vector type (a struct type or an empty shape falls
    back to Warp's own allocation); ``device`` a Warp device or its name. ``requires_grad`` attaches a zeroed
    gradient array of the same kind. On CUDA torch's allocator hands back a cached block in about a microsecond
    of host time where Warp's stream-ordered pool takes tens, and an op's output made here goes back to torch
    without a conversion (:func:`apply`). Allocated on torch's current stream, which the bridge's launches use.
    """
    if not isinstance(device, wp.Device):
        device = wp.get_device(device)
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    ts = _TORCH_OF.get(scalar)
    shape = tuple(int(x) for x in shape) if hasattr(shape, "__len__") else (int(shape),)
    if ts is None or not all(shape):
        make = wp.zeros if zero else wp.empty
        return make(shape, dtype=dtype, device=device, requires_grad=requires_grad)
    tdev = _torch_device(device)
    full = shape + tuple(getattr(dtype, "_shape_", ()))
    t = torch.zeros(full, dtype=ts, device=tdev) if zero else torch.empty(full, dtype=ts, device=tdev)
    arr = to_warp(t, dtype)
    arr._wtopo_tensor = t  # noqa: SLF001 - the tensor apply() returns for this output
    if requires_grad:
        arr.grad = to_warp(torch.zeros(full, dtype=ts, device=tdev), dtype)
    return arr


_GROUP_ALIGN = 256  # bytes: every array of a group starts this far apart (torch's CUDA blocks are 512-aligned)


def empty_group(shape, dtypes, device, requires_grad: bool = False) -> list[wp.array]:
    """One :func:`empty` array of ``shape`` per type of ``dtypes`` (float32 or float64 scalars and vectors of one
    scalar type), all carved from one torch allocation, each at a multiple of 256 bytes into it; with
    ``requires_grad`` their gradient arrays likewise from one zeroed allocation. Two allocations and one fill where
    :func:`empty` makes one of each per array: the rasterizer's eight per-surfel arrays and their gradients took
    sixteen. Other types (ints mixed in, structs) or an empty shape: one :func:`empty` each.
    """
    if not isinstance(device, wp.Device):
        device = wp.get_device(device)
    shape = tuple(int(x) for x in shape) if hasattr(shape, "__len__") else (int(shape),)
    scalar = getattr(dtypes[0], "_wp_scalar_type_", dtypes[0])
    ts = _TORCH_OF.get(scalar)
    if ts is None or not all(shape) or any(getattr(t, "_wp_scalar_type_", t) is not scalar for t in dtypes):
        return [empty(shape, t, device, requires_grad=requires_grad) for t in dtypes]
    tdev = _torch_device(device)
    size = 1
    for x in shape:
        size *= x
    align = _GROUP_ALIGN // ts.itemsize
    lens, offs, total = [], [], 0
    for t in dtypes:
        k = size * (getattr(t, "_length_", None) or 1)
        offs.append(total)
        lens.append(k)
        total += -(-k // align) * align
    base = torch.empty(total, dtype=ts, device=tdev)
    grads = torch.zeros(total, dtype=ts, device=tdev) if requires_grad else None
    out = []
    for t, o, k in zip(dtypes, offs, lens):
        full = shape + tuple(getattr(t, "_shape_", ()))
        v = base[o:o + k].view(full)
        arr = to_warp(v, t)
        arr._wtopo_tensor = v  # noqa: SLF001 - the tensor apply() returns for this output
        if grads is not None:
            arr.grad = to_warp(grads[o:o + k].view(full), t)
        out.append(arr)
    return out


def as_torch(a: wp.array) -> torch.Tensor:
    """The torch tensor of an op's output: a view of the one :func:`empty` allocated it in, else ``wp.to_torch``'s.

    Always a new tensor object: :func:`apply`'s context keeps the Warp array, which keeps its tensor, so handing
    torch that same tensor as the op's output (whose ``grad_fn`` keeps the context) would make a reference cycle
    through the autograd graph that is never freed.
    """
    t = getattr(a, "_wtopo_tensor", None)
    return wp.to_torch(a, requires_grad=False) if t is None else t.view(t.shape)


