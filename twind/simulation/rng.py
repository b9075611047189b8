"""Seeded Gaussian noise inside compiled loops: xoshiro256** with a 256-layer ziggurat.

numpy's Generator costs ~10 ns a sample on the project's machines; :func:`fill_normal` ~3 ns,
and :func:`fill_normal8`, the same numbers from eight channels as one vector, ~2 ns.

A channel is two streams: each deviate's candidate comes from the first, one draw a deviate,
and the ziggurat's rejections (a candidate outside its layer's rectangle, 1.5 % of them) take
what else they need from the second. The deviates are exactly normal and independent, as the
ziggurat's are; the first stream's pace is fixed, so eight channels advance as one vector
that never stops, and the rejected candidates are completed afterwards. Each optic's streams
are its own, so runs repeat bit for bit whatever the block size. Algorithms: Blackman &
Vigna, "Scrambled linear pseudorandom number generators" (2021); Marsaglia & Tsang, "The
ziggurat method for generating random variables" (2000), with numpy's 256-layer constants.
"""

from __future__ import annotations

import zlib

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import NDArray

_R = 3.6541528853610088  # start of the tail, 256 layers (numpy's ziggurat_nor_r)
_V = 0.00492867323399  # area of each layer
_M52 = float(2**52)


def tables() -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Ziggurat tables ``(ki, wi, fi)`` for 52-bit mantissas (Marsaglia & Tsang's zigset)."""
    ki = np.zeros(256, dtype=np.int64)
    wi = np.zeros(256)
    fi = np.zeros(256)
    dn = tn = _R
    q = _V / np.exp(-0.5 * dn * dn)
    ki[0] = np.int64((dn / q) * _M52)
    wi[0], wi[255] = q / _M52, dn / _M52
    fi[0], fi[255] = 1.0, np.exp(-0.5 * dn * dn)
    for i in range(254, 0, -1):
        dn = np.sqrt(-2.0 * np.log(_V / dn + np.exp(-0.5 * dn * dn)))
        ki[i + 1] = np.int64((dn / tn) * _M52)
        tn = dn
        fi[i] = np.exp(-0.5 * dn * dn)
        wi[i] = dn / _M52
    return ki, wi, fi


KI, WI, FI = tables()


def seed_states(seed: int, n: int, key: str = "") -> NDArray[np.uint64]:
    """Independent xoshiro256** states of `n` channels from one integer seed, two streams each
    (candidates, rejections: see the module's docstring).

    `key` (an optic's name) selects its own family of streams, so an optic's noise does not
    depend on which other optics run beside it.

    Parameters
    ----------
    seed : int
        The run's seed.
    n : int
        Channels wanted.
    key : str
        The family of streams (an optic's name; empty for the seed's own).

    Returns
    -------
    ndarray of uint64, shape (n, 2, 4)
    """
    spawn_key = (zlib.crc32(key.encode()),) if key else ()
    children = np.random.SeedSequence(seed, spawn_key=spawn_key).spawn(2 * n)
    states = np.array([c.generate_state(4, dtype=np.uint64) for c in children], dtype=np.uint64)
    states[np.all(states == 0, axis=1), 0] = 1  # the all-zero state is a fixed point
    return np.ascontiguousarray(states.reshape(2, n, 4).transpose(1, 0, 2))


@nb.njit(inline="always")
def _rotl(x: np.uint64, k: np.uint64) -> np.uint64:
    return (x << k) | (x >> (np.uint64(64) - k))


@nb.njit(inline="always")
def _next(s0: np.uint64, s1: np.uint64, s2: np.uint64, s3: np.uint64) -> tuple:
    """xoshiro256**: 64 random bits and the next state, all in registers."""
    result = _rotl(s1 * np.uint64(5), np.uint64(7)) * np.uint64(9)
    t = s1 << np.uint64(17)
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = _rotl(s3, np.uint64(45))
    return result, s0, s1, s2, s3


@nb.njit(inline="always")
def _uniform(bits: np.uint64) -> float:
    """Uniform in [0, 1) from the top 53 of 64 random bits."""
    return float(bits >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@nb.njit(inline="always")
def _complete(r: np.uint64, s0: np.uint64, s1: np.uint64, s2: np.uint64, s3: np.uint64
              ) -> tuple:
    """The ziggurat's deviate whose first candidate has the bits `r`, drawing what else it
    needs (the tail's or a wedge's uniforms, fresh candidates) from the stream ``s0..s3``.

    One loop with breaks and a single exit: numba compiles early returns inside the loop
    into code five times slower.
    """
    while True:
        idx = np.int64(r & np.uint64(0xFF))
        rr = np.int64(r >> np.uint64(8))
        rabs = (rr >> 1) & 0x000FFFFFFFFFFFFF
        x = rabs * WI[idx]
        if rr & 1:
            x = -x
        if rabs < KI[idx]:
            break
        if idx == 0:  # the tail beyond _R, Marsaglia's method
            u1, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
            u2, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
            xx = -np.log1p(-_uniform(u1)) / _R
            yy = -np.log1p(-_uniform(u2))
            if yy + yy > xx * xx:
                x = -(_R + xx) if rr & 1 else _R + xx
                break
        else:
            u1, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
            if (FI[idx - 1] - FI[idx]) * _uniform(u1) + FI[idx] < np.exp(-0.5 * x * x):
                break
        r, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
    return x, s0, s1, s2, s3


@nb.njit(nogil=True, cache=True)
def fill_normal(state: NDArray[np.uint64], scale: float, out: NDArray[np.float64]) -> None:
    """Fill `out` with normal deviates of standard deviation `scale` (ziggurat).

    Parameters
    ----------
    state : ndarray of uint64, shape (2, 4)
        The channel's two xoshiro256** streams from :func:`seed_states` (candidates, then
        rejections), advanced past the draws.
    scale : float
        Standard deviation.
    out : ndarray, 1-D
        Filled in place.
    """
    s0, s1, s2, s3 = state[0, 0], state[0, 1], state[0, 2], state[0, 3]
    t0, t1, t2, t3 = state[1, 0], state[1, 1], state[1, 2], state[1, 3]
    for k in range(out.shape[0]):
        r, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
        x, t0, t1, t2, t3 = _complete(r, t0, t1, t2, t3)
        out[k] = scale * x
    state[0, 0], state[0, 1], state[0, 2], state[0, 3] = s0, s1, s2, s3
    state[1, 0], state[1, 1], state[1, 2], state[1, 3] = t0, t1, t2, t3


_LANES8 = 8
_I64 = ir.IntType(64)
_V64 = ir.VectorType(_I64, _LANES8)
_VD = ir.VectorType(ir.DoubleType(), _LANES8)


def _v(value: int) -> ir.Constant:
    return ir.Constant(_V64, [value] * _LANES8)


def _xoshiro8(builder: ir.IRBuilder, state: list) -> ir.Value:
    """xoshiro256** on eight streams at once: `state` is four allocas of <8 x i64>, updated;
    returns the 64 random bits of each. (The products by 5 and 9 are shifts and adds.)"""
    def rotl(x: ir.Value, k: int) -> ir.Value:
        return builder.or_(builder.shl(x, _v(k)), builder.lshr(x, _v(64 - k)))
    s0, s1, s2, s3 = (builder.load(r) for r in state)
    times5 = builder.add(builder.shl(s1, _v(2)), s1)
    rotated = rotl(times5, 7)
    result = builder.add(builder.shl(rotated, _v(3)), rotated)
    t = builder.shl(s1, _v(17))
    s2 = builder.xor(s2, s0)
    s3 = builder.xor(s3, s1)
    s1 = builder.xor(s1, s2)
    s0 = builder.xor(s0, s3)
    s2 = builder.xor(s2, t)
    s3 = rotl(s3, 45)
    for r, v in zip(state, (s0, s1, s2, s3)):
        builder.store(v, r)
    return result


def _lookup(builder: ir.IRBuilder, table: ir.Value, idx: ir.Value, vtype: ir.VectorType
            ) -> ir.Value:
    """``table[idx]`` lane by lane."""
    out = ir.Constant(vtype, ir.Undefined)
    for c in range(_LANES8):
        lane = ir.Constant(ir.IntType(32), c)
        value = builder.load(builder.gep(table, [builder.extract_element(idx, lane)]))
        out = builder.insert_element(out, value, lane)
    return out


def _to_double(builder: ir.IRBuilder, m: ir.Value) -> ir.Value:
    """``float(m)`` of eight integers below 2**52, exactly: `m` as the mantissa of 2**52, less
    2**52 (AVX2 has no vector conversion from 64-bit integers; LLVM's is eight scalar ones)."""
    biased = builder.bitcast(builder.or_(m, _v(0x4330000000000000)), _VD)
    return builder.fsub(biased, ir.Constant(_VD, [_M52] * _LANES8))


@intrinsic
def _fast8(typingctx, states, ki, wi, sigma, n, out, bits, outside):  # noqa: ANN001, ANN201
    """The ziggurat's first candidates of `n` draws on eight streams, as one vector.

    ``out[8 k + c]`` is stream c's k-th candidate times ``sigma[c]``, ``bits[8 k + c]`` its
    64 random bits, and bit c of ``outside[k]`` set when it lies outside its layer's
    rectangle and needs :func:`_complete`.
    """
    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        def data(i: int, vtype: ir.Type | None = None) -> ir.Value:
            ptr = context.make_array(sig.args[i])(context, builder, args[i]).data
            return builder.bitcast(ptr, vtype.as_pointer()) if vtype else ptr
        st, ki_p, wi_p, out_p, bits_p, outside_p = (
            data(0, _V64), data(1), data(2), data(5, _VD), data(6, _V64), data(7))
        scale = builder.load(data(3, _VD), align=8)
        state = [cgutils.alloca_once_value(builder, builder.load(builder.gep(st, [ir.Constant(
            _I64, j)]), align=8)) for j in range(4)]
        with cgutils.for_range(builder, args[4]) as loop:
            k = loop.index
            r = _xoshiro8(builder, state)
            builder.store(r, builder.gep(bits_p, [k]), align=8)
            idx = builder.and_(r, _v(0xFF))
            rr = builder.lshr(r, _v(8))
            rabs = builder.and_(builder.lshr(rr, _v(1)), _v(0x000FFFFFFFFFFFFF))
            negative = builder.icmp_unsigned("!=", builder.and_(rr, _v(1)), _v(0))
            x = builder.fmul(_to_double(builder, rabs), _lookup(builder, wi_p, idx, _VD))
            x = builder.select(negative, builder.fneg(x), x)
            builder.store(builder.fmul(scale, x), builder.gep(out_p, [k]), align=8)
            outward = builder.icmp_signed(">=", rabs, _lookup(builder, ki_p, idx, _V64))
            builder.store(builder.bitcast(outward, ir.IntType(8)), builder.gep(outside_p, [k]))
        for j in range(4):
            builder.store(builder.load(state[j]), builder.gep(st, [ir.Constant(_I64, j)]),
                          align=8)
        return context.get_dummy_value()
    return types.none(states, ki, wi, sigma, n, out, bits, outside), codegen


@nb.njit(nogil=True, cache=True)
def fill_normal8(states: NDArray[np.uint64], sigma: NDArray[np.float64],
                 out: NDArray[np.float64], bits: NDArray[np.uint64],
                 outside: NDArray[np.uint8]) -> None:
    """Eight channels' normal deviates, ``out[8 k + c]`` channel c's k-th times ``sigma[c]``:
    the same numbers :func:`fill_normal` draws from each channel's streams, eight at a time.

    The eight candidate streams advance together as one vector (:func:`_fast8`); then each
    candidate outside its layer's rectangle is completed as :func:`fill_normal` completes it,
    from its channel's second stream.

    Parameters
    ----------
    states : ndarray of uint64, shape (2, 4, 8)
        The channels' streams, one column each (:func:`seed_states` transposed): candidates,
        then rejections; advanced.
    sigma : ndarray, shape (8,)
        Standard deviation of each channel's deviates.
    out : ndarray, shape (8 n,)
        Filled.
    bits, outside : ndarray
        Scratch of ``8 n`` uint64 and ``n`` uint8.
    """
    n = out.shape[0] // _LANES8
    _fast8(states[0], KI, WI, sigma, n, out, bits, outside)
    aux = states[1]
    for k in range(n):
        if outside[k] == 0:
            continue
        for c in range(_LANES8):
            if (outside[k] >> c) & 1:
                x, aux[0, c], aux[1, c], aux[2, c], aux[3, c] = _complete(
                    bits[_LANES8 * k + c], aux[0, c], aux[1, c], aux[2, c], aux[3, c])
                out[_LANES8 * k + c] = sigma[c] * x
