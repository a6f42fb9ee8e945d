"""A shorter launch path for Taichi kernels called with numpy arrays and numbers (issues 16 and
18; same bytes).

On every call, Taichi 1.7's ``Kernel.__call__`` finds the call's specialisation from each
argument's features, sets each argument through several layers of Python checks, and asks the
program for the compiled kernel, which it looks up in its cache by a hash: PCG's ``update_p``
on 10 voxels takes 149-188 us a call, of which launching the compiled kernel ~30 us. A scan
step's solve on the bowl's band makes ~1,000 calls of a few tens of microseconds of work each
(docs/measurements.md, "Kernel launches without Taichi's per-call Python path").

:func:`install` wraps ``Kernel.__call__``. A call whose arguments are positional C-contiguous
numpy arrays (for ``ti.types.ndarray`` parameters of scalar or vector elements), numbers (for
scalar parameters) and bools or ints (for ``ti.template()`` parameters, which select a compiled
specialisation), outside autodiff and debug mode, on the CPU, is launched directly from what the
first call with the same argument features looked up (kept per kernel): the compiled kernel, and
which setter each argument takes. Everything else (other template values such as fields, Taichi
ndarrays, keywords, other array types or layouts, kernels that print, and every first call of a
signature) takes Taichi's own path, which compiles, checks and raises as before. A
re-initialised Taichi (a new program) is looked up again.

The kernel runs the same compiled code on the same arguments: the same bytes
(``tests/test_launch.py`` compares the two paths; ``python tools/output_hashes.py``, 5 of 5).
:func:`bftaichi.init` installs it (unless ``BFTAICHI_TAICHI_LAUNCH=taichi``, which keeps Taichi's
own path for every call, for debugging); a Taichi program embedding :mod:`kernels` may call
:func:`install` itself. A Taichi whose ``Kernel`` lacks the 1.7 members used here is left alone.
"""

from __future__ import annotations

import numpy as np

_ARRAY, _FLOAT, _INT, _UINT = range(4)  # setters
_TEMPLATE, _VECTOR, _SCALAR, _OTHER = range(4, 8)  # parameter kinds (_ARRAY too)
_SKIP = "taichi"  # a signature whose calls take Taichi's own path


def _slots(kernel) -> tuple:
    """Per parameter of ``kernel``, what its argument's features are made of: _TEMPLATE (a
    template: its value, when a bool or an int), _VECTOR (an ndarray of vector elements:
    dtype, rank and last extent), _ARRAY (an ndarray of scalars: dtype and rank), _OTHER (an
    ndarray of matrices: never planned) or _SCALAR (its type). Read once from the
    annotations, kept on the kernel."""
    slots = kernel.__dict__.get("_bftaichi_slots")
    if slots is None:
        from taichi.lang.kernel_impl import template
        from taichi.types import ndarray_type, primitive_types

        out = []
        for arg in kernel.arguments:
            ann = arg.annotation
            if isinstance(ann, template):
                out.append(_TEMPLATE)
            elif not isinstance(ann, ndarray_type.NdarrayType):
                out.append(_SCALAR)
            elif ann.dtype is None or id(ann.dtype) in primitive_types.type_ids:
                out.append(_ARRAY)
            elif getattr(ann.dtype, "ndim", 0) == 1:
                out.append(_VECTOR)
            else:  # matrix elements: Taichi's path
                out.append(_OTHER)
        slots = kernel.__dict__["_bftaichi_slots"] = tuple(out)
    return slots


def _features(args, slots) -> tuple | None:
    """What decides a call's specialisation and setters here, per argument (:func:`_slots`);
    None when the call must take Taichi's path: an array that is not C-contiguous (Taichi's
    path copies or refuses it), a template whose value is not a bool or an int."""
    out = []
    for v, slot in zip(args, slots):
        if slot == _TEMPLATE:
            if type(v) not in (bool, int):
                return None
            out.append((type(v), v))
        elif type(v) is np.ndarray:
            if not v.flags.c_contiguous:
                return None
            out.append((v.dtype, v.ndim, v.shape[-1] if slot == _VECTOR and v.ndim else 0))
        else:
            out.append(type(v))
    return tuple(out)


def _plan(kernel, args):
    """``(program, compiled kernel, Taichi kernel, setters)`` for launching ``kernel`` on
    arguments with the features of ``args`` (a call that has just run through Taichi's path),
    or _SKIP."""
    from taichi.lang import impl
    from taichi.lang.util import cook_dtype
    from taichi.types import primitive_types
    from taichi.types.utils import is_signed

    cfg = impl.current_cfg()
    if cfg.debug or cfg.arch.name not in ("x64", "arm64") or kernel.has_print:
        return _SKIP
    setters = []  # (position in args, argument index, setter, element dims)
    for pos, (arg, slot, v) in enumerate(zip(kernel.arguments, _slots(kernel), args)):
        ann, j = arg.annotation, len(setters)
        if slot == _TEMPLATE:
            continue  # compiled into the kernel (a bool or an int: :func:`_features`)
        if slot in (_ARRAY, _VECTOR):
            if type(v) is not np.ndarray or getattr(ann.layout, "name", "AOS") != "AOS":
                return _SKIP
            setters.append((pos, j, _ARRAY, int(slot == _VECTOR)))
        elif slot == _SCALAR and id(ann) in primitive_types.real_type_ids and isinstance(
                v, (float, int, np.floating, np.integer)):
            setters.append((pos, j, _FLOAT, 0))
        elif slot == _SCALAR and id(ann) in primitive_types.integer_type_ids and isinstance(
                v, (int, np.integer)):
            setters.append((pos, j, _INT if is_signed(cook_dtype(ann)) else _UINT, 0))
        else:
            return _SKIP
    t_kernel = kernel.compiled_kernels[kernel.ensure_compiled(*args)]  # compiled: a lookup
    prog = impl.get_runtime().prog
    compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
    return prog, compiled, t_kernel, tuple(setters)


def _launch(kernel, plan, args):
    """Launch ``kernel`` on ``args`` by ``plan``; its return value as Taichi's path gives it."""
    prog, compiled, t_kernel, setters = plan
    ctx = t_kernel.make_launch_context()
    for pos, j, kind, element_dim in setters:
        v = args[pos]
        if kind == _ARRAY:
            shape = v.shape[:-1] if element_dim else v.shape
            ctx.set_arg_external_array_with_shape((j,), v.ctypes.data, v.nbytes, shape, 0)
        elif kind == _FLOAT:
            ctx.set_arg_float((j,), float(v))
        elif kind == _INT:
            ctx.set_arg_int((j,), int(v))
        else:
            ctx.set_arg_uint((j,), int(v))
    prog.launch_kernel(compiled, ctx)
    ret_types = kernel.return_type
    if ret_types is None:
        return None
    from taichi.lang import runtime_ops

    runtime_ops.sync()
    ret = [kernel.construct_kernel_ret(ctx, t, (i,)) for i, t in enumerate(ret_types)]
    return ret[0] if len(ret) == 1 else ret


def install() -> bool:
    """Wrap Taichi 1.7's ``Kernel.__call__`` with the short path, once per process; False
    (nothing changed) where Taichi's ``Kernel`` lacks what it relies on."""
    from taichi.lang import impl, kernel_impl

    cls = getattr(kernel_impl, "Kernel", None)
    original = getattr(cls, "__call__", None)
    if original is None or not all(hasattr(cls, n) for n in (
            "ensure_compiled", "construct_kernel_ret")) or not hasattr(kernel_impl, "AutodiffMode"):
        return False
    if getattr(original, "_bftaichi_short", False):
        return True
    no_autodiff = kernel_impl.AutodiffMode.NONE

    def __call__(self, *args, **kwargs):
        runtime = impl.get_runtime()
        if (kwargs or self.autodiff_mode != no_autodiff or runtime.fwd_mode_manager
                or runtime.target_tape or len(args) != len(self.arguments)):
            return original(self, *args, **kwargs)
        sig = _features(args, _slots(self))
        if sig is None:
            return original(self, *args)
        plans = self.__dict__.setdefault("_bftaichi_plans", {})
        plan = plans.get(sig)
        if plan is None or (plan is not _SKIP and plan[0] is not runtime.prog):
            ret = original(self, *args)  # compiles if needed; checks and raises as Taichi does
            plans[sig] = _plan(self, args)
            return ret
        if plan is _SKIP:
            return original(self, *args)
        return _launch(self, plan, args)

    __call__._bftaichi_short = True
    __call__.__wrapped__ = original
    cls.__call__ = __call__
    return True
