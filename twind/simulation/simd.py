"""Four-lane vector arithmetic for the engine's kernels, as numba intrinsics.

The damping loop does the same arithmetic on POS, PIT, YAW and SIDE at once, but numba's
optimiser does not pack such side-by-side scalar code into vector instructions (it cannot
prove that a filter's states and coefficients do not overlap). These intrinsics emit LLVM's
``<4 x double>`` operations directly, on values of the numba type :data:`VECTOR`, which is
that LLVM vector itself: a vector carried from one loop iteration to the next stays in one
register (a tuple of four floats would be taken apart into four scalars and put together
again on every iteration). ``v[d]`` reads lane `d`.

Arrays passed in are C-contiguous float64 arrays of any shape, indexed by their flat element
offset; no bounds are checked, so callers keep ``i + 4 <= a.size``.
"""

from __future__ import annotations

import operator

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.datamodel import models
from numba.extending import intrinsic, overload, register_model

LANES = 4
_V = ir.VectorType(ir.DoubleType(), LANES)
_I32 = ir.IntType(32)

SECTION_ROWS = 7
"""Rows of :func:`cascade4`'s layout per section: b0, b1, b2, a1, a2 and the two states."""


class Vector(types.Type):
    """Four float64 lanes in one LLVM ``<4 x double>`` (compiled code only)."""

    def __init__(self) -> None:
        super().__init__(name="Vector4")


VECTOR = Vector()


@register_model(Vector)
class _VectorModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type) -> None:  # noqa: ANN001
        super().__init__(dmm, fe_type, _V)


def _pointer(context, builder: ir.IRBuilder, arrty, arr: ir.Value, i: ir.Value) -> ir.Value:  # noqa: ANN001
    data = context.make_array(arrty)(context, builder, arr).data
    return builder.bitcast(builder.gep(data, [i]), _V.as_pointer())


def _fma(builder: ir.IRBuilder, a: ir.Value, b: ir.Value, c: ir.Value) -> ir.Value:
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V] * 3),
                                        "llvm.fma.v4f64")
    return builder.call(fn, [a, b, c])


def _splat(builder: ir.IRBuilder, s: ir.Value) -> ir.Value:
    vec = builder.insert_element(ir.Constant(_V, ir.Undefined), s, ir.Constant(_I32, 0))
    return builder.shuffle_vector(vec, vec, ir.Constant(ir.VectorType(_I32, LANES), [0] * LANES))


def _is_array(a: types.Type) -> bool:
    return isinstance(a, types.Array) and a.dtype == types.float64 and a.layout == "C"


@intrinsic
def vec4(typingctx, a, b, c, d):  # noqa: ANN001, ANN201
    """The vector ``(a, b, c, d)`` of four floats."""
    if not all(isinstance(x, types.Float) for x in (a, b, c, d)):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        vec = ir.Constant(_V, ir.Undefined)
        for lane, (ty, x) in enumerate(zip(sig.args, args)):
            x = context.cast(builder, x, ty, types.float64)
            vec = builder.insert_element(vec, x, ir.Constant(_I32, lane))
        return vec
    return VECTOR(a, b, c, d), codegen


@intrinsic
def splat4(typingctx, s):  # noqa: ANN001, ANN201
    """The vector of four copies of the float `s`."""
    if not isinstance(s, types.Float):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        return _splat(builder, context.cast(builder, args[0], sig.args[0], types.float64))
    return VECTOR(s), codegen


@intrinsic
def _lane(typingctx, v, d):  # noqa: ANN001, ANN201
    if not (v == VECTOR and isinstance(d, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        return builder.extract_element(args[0], args[1])
    return types.float64(v, d), codegen


@overload(operator.getitem)
def _getitem(v, d):  # noqa: ANN001, ANN202
    if v == VECTOR and isinstance(d, types.Integer):
        return lambda v, d: _lane(v, d)
    return None


@intrinsic
def load4(typingctx, a, i):  # noqa: ANN001, ANN201
    """``(a[i], a[i+1], a[i+2], a[i+3])`` of the flat array `a`."""
    if not (_is_array(a) and isinstance(i, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        ptr = _pointer(context, builder, sig.args[0], args[0], args[1])
        return builder.load(ptr, align=8)
    return VECTOR(a, i), codegen


@intrinsic
def store4(typingctx, a, i, v):  # noqa: ANN001, ANN201
    """``a[i:i+4] = v`` of the flat array `a`."""
    if not (_is_array(a) and isinstance(i, types.Integer) and v == VECTOR):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        ptr = _pointer(context, builder, sig.args[0], args[0], args[1])
        builder.store(args[2], ptr, align=8)
        return context.get_dummy_value()
    return types.none(a, i, v), codegen


@intrinsic
def fma4(typingctx, a, i, s, acc):  # noqa: ANN001, ANN201
    """``acc + a[i:i+4] * s``: `s` a scalar or a vector, one rounding per lane."""
    if not (_is_array(a) and isinstance(i, types.Integer) and acc == VECTOR
            and (s == VECTOR or isinstance(s, types.Float))):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        arr, idx, scale, total = args
        ptr = _pointer(context, builder, sig.args[0], arr, idx)
        factor = scale if sig.args[2] == VECTOR else _splat(builder, scale)
        return _fma(builder, builder.load(ptr, align=8), factor, total)
    return VECTOR(a, i, s, acc), codegen


def _lanewise(instruction: str, doc: str):  # noqa: ANN202
    """An intrinsic applying the LLVM `instruction` to two vectors, lane by lane."""
    def op(typingctx, v, w):  # noqa: ANN001, ANN202
        if not (v == VECTOR and w == VECTOR):
            return None

        def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
            return getattr(builder, instruction)(args[0], args[1])
        return VECTOR(v, w), codegen
    op.__doc__ = doc
    return intrinsic(op)


add4 = _lanewise("fadd", "``v + w`` lane by lane.")
mul4 = _lanewise("fmul", "``v * w`` lane by lane.")


@intrinsic
def swap_pairs(typingctx, v):  # noqa: ANN001, ANN202
    """``(v[1], v[0], v[3], v[2])``: each state's mode partner in the modal plant."""
    if v != VECTOR:
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        mask = ir.Constant(ir.VectorType(_I32, LANES), [1, 0, 3, 2])
        return builder.shuffle_vector(args[0], args[0], mask)
    return VECTOR(v), codegen


@intrinsic
def cascade4(typingctx, f, nsec, v):  # noqa: ANN001, ANN201
    """Four cascades of second-order sections, one per lane, advanced by one sample.

    Parameters
    ----------
    f : ndarray
        ``nsec`` sections of :data:`SECTION_ROWS` rows of 4 lanes each: ``b0, b1, b2, a1,
        a2`` (``a0 = 1``) and the transposed-direct-form-II states ``z0, z1``, updated here.
    nsec : int
        Sections in each cascade.
    v : vector
        This sample's input of each cascade.

    Returns
    -------
    vector
        The output of each cascade.
    """
    if not (_is_array(f) and isinstance(nsec, types.Integer) and v == VECTOR):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        arr, n, first = args
        vptr = cgutils.alloca_once_value(builder, first)
        step = ir.Constant(n.type, SECTION_ROWS * LANES)
        with cgutils.for_range(builder, n) as loop:
            base = builder.mul(loop.index, step)

            def row(r: int) -> ir.Value:
                i = builder.add(base, ir.Constant(n.type, r * LANES))
                return _pointer(context, builder, sig.args[0], arr, i)
            b0, b1, b2, a1, a2, z0, z1 = (builder.load(row(r), align=8) for r in range(7))
            x = builder.load(vptr)
            w = _fma(builder, b0, x, z0)
            builder.store(_fma(builder, b1, x, _fma(builder, builder.fneg(a1), w, z1)), row(5),
                          align=8)
            builder.store(_fma(builder, b2, x, builder.fneg(builder.fmul(a2, w))), row(6),
                          align=8)
            builder.store(w, vptr)
        return builder.load(vptr)
    return VECTOR(f, nsec, v), codegen


@intrinsic
def filter8(typingctx, f, x, n):  # noqa: ANN001, ANN201
    """One second-order section on each of eight channels over `n` samples, in place.

    Sample k of the channels is ``x[8 k:8 k + 8]``; ``f[0]`` holds the sections of channels
    0-3 and ``f[1]`` those of 4-7, each in :func:`cascade4`'s layout (one section). The states
    stay in registers and are stored back at the end. The states are :func:`cascade4`'s,
    advanced as ``z0' = (b1 - a1 b0) x + z1 - a1 z0`` and ``z1' = (b2 - a2 b0) x - a2 z0``:
    the output waits for no state update, so successive samples overlap (one multiply-add
    from a state to the next, against three through the output).
    """
    if not (_is_array(f) and f.ndim == 2 and _is_array(x) and isinstance(n, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        farr, xarr, count = args
        one = SECTION_ROWS * LANES

        def row(g: int, r: int) -> ir.Value:
            i = ir.Constant(count.type, g * one + r * LANES)
            return _pointer(context, builder, sig.args[0], farr, i)
        groups = []
        for g in range(2):
            b0, b1, b2, a1, a2 = (builder.load(row(g, r), align=8) for r in range(5))
            c1 = _fma(builder, builder.fneg(a1), b0, b1)
            c2 = _fma(builder, builder.fneg(a2), b0, b2)
            states = [cgutils.alloca_once_value(builder, builder.load(row(g, r), align=8))
                      for r in (5, 6)]
            groups.append(((b0, c1, c2, builder.fneg(a1), builder.fneg(a2)), states))
        with cgutils.for_range(builder, count) as loop:
            base = builder.mul(loop.index, ir.Constant(count.type, 2 * LANES))
            for g, ((b0, c1, c2, na1, na2), (z0, z1)) in enumerate(groups):
                i = builder.add(base, ir.Constant(count.type, g * LANES))
                ptr = _pointer(context, builder, sig.args[1], xarr, i)
                v = builder.load(ptr, align=8)
                s0, s1 = builder.load(z0), builder.load(z1)
                builder.store(_fma(builder, b0, v, s0), ptr, align=8)
                builder.store(_fma(builder, na1, s0, _fma(builder, c1, v, s1)), z0)
                builder.store(_fma(builder, na2, s0, builder.fmul(c2, v)), z1)
        for g, (_, (z0, z1)) in enumerate(groups):
            builder.store(builder.load(z0), row(g, 5), align=8)
            builder.store(builder.load(z1), row(g, 6), align=8)
        return context.get_dummy_value()
    return types.none(f, x, n), codegen
