"""Seeded Gaussian noise inside compiled loops: xoshiro256** with a 1024-layer ziggurat.

numpy's Generator costs ~10 ns a sample on the project's machines; :func:`fill_normal` ~3 ns,
and :func:`fill_normal8`, the same numbers from eight channels as two vectors of four,
~1.5 ns.

A channel is two streams: each deviate's candidate comes from the first, one draw a deviate,
and the ziggurat's rejections (a candidate outside its layer's rectangle, 0.4 % of them) take
what else they need from the second. The deviates are exactly normal and independent, as the
ziggurat's are; the first stream's pace is fixed, so the channels advance as vectors that
never stop, and the rejected candidates are completed afterwards. Each optic's streams
are its own, so runs repeat bit for bit whatever the block size. Algorithms: Blackman &
Vigna, "Scrambled linear pseudorandom number generators" (2021); Marsaglia & Tsang, "The
ziggurat method for generating random variables" (2000), with 1024 layers rather than
numpy's 256, so that four times fewer candidates need the slow completion: its tail start
:data:`_R` and layer area :data:`_V` solve Marsaglia & Tsang's closing condition for 1024
layers (the same solution gives numpy's 3.6541528853610088 for 256).
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

from twind.simulation.cache import register

register()

_LAYER_BITS = 10
_LAYERS = 1 << _LAYER_BITS
_R = 4.038849846109504  # start of the tail
_V = 0.0012263246463530893  # area of each layer: R f(R) plus the tail's
_M52 = float(2**52)


def tables() -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Ziggurat tables ``(ki, wi, fi)`` for 52-bit mantissas (Marsaglia & Tsang's zigset)."""
    ki = np.zeros(_LAYERS, dtype=np.int64)
    wi = np.zeros(_LAYERS)
    fi = np.zeros(_LAYERS)
    dn = tn = _R
    q = _V / np.exp(-0.5 * dn * dn)
    ki[0] = np.int64((dn / q) * _M52)
    wi[0], wi[-1] = q / _M52, dn / _M52
    fi[0], fi[-1] = 1.0, np.exp(-0.5 * dn * dn)
    for i in range(_LAYERS - 2, 0, -1):
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
        idx = np.int64(r & np.uint64(_LAYERS - 1))
        rr = np.int64(r >> np.uint64(_LAYER_BITS))
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
_W = 4  # streams a vector: eight as two halves of four, which fit the registers
_I64 = ir.IntType(64)
_V64 = ir.VectorType(_I64, _W)
_VD = ir.VectorType(ir.DoubleType(), _W)


def _v(value: int) -> ir.Constant:
    return ir.Constant(_V64, [value] * _W)


def _xoshiro4(builder: ir.IRBuilder, state: list) -> ir.Value:
    """xoshiro256** on four streams at once: `state` is four allocas of <4 x i64>, updated;
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
    for c in range(_W):
        lane = ir.Constant(ir.IntType(32), c)
        value = builder.load(builder.gep(table, [builder.extract_element(idx, lane)]))
        out = builder.insert_element(out, value, lane)
    return out


def _to_double(builder: ir.IRBuilder, m: ir.Value) -> ir.Value:
    """``float(m)`` of integers below 2**52, exactly: `m` as the mantissa of 2**52, less
    2**52 (AVX2 has no vector conversion from 64-bit integers; LLVM's is one scalar each)."""
    biased = builder.bitcast(builder.or_(m, _v(0x4330000000000000)), _VD)
    return builder.fsub(biased, ir.Constant(_VD, [_M52] * _W))


@intrinsic
def _fast4(typingctx, states, ki, wi, sigma, n, half, out, bits, outside, listed):  # noqa: ANN001, ANN201
    """The ziggurat's first candidates of `n` draws on streams ``4 half .. 4 half + 3`` of
    eight, as one vector.

    ``out[8 k + c]`` is stream c's k-th candidate times ``sigma[c]``. The draws with a
    candidate outside its layer's rectangle, which needs :func:`_complete`, are listed in
    order in ``outside`` from index `listed`, as ``256 k + lanes`` (bit c of `lanes` set for
    stream c), and entry i's four candidates' 64 random bits are ``bits[4 i:4 i + 4]``;
    returns the list's new length.
    """
    def codegen(context, builder, sig, args):  # noqa: ANN001, ANN202
        def data(i: int) -> ir.Value:
            return context.make_array(sig.args[i])(context, builder, args[i]).data

        def vector(ptr: ir.Value, i: ir.Value, vtype: ir.VectorType) -> ir.Value:
            return builder.bitcast(builder.gep(ptr, [i]), vtype.as_pointer())
        st, ki_p, wi_p, sigma_p, out_p, bits_p, outside_p = (
            data(0), data(1), data(2), data(3), data(6), data(7), data(8))
        first = builder.mul(args[5], ir.Constant(_I64, _W))
        scale = builder.load(vector(sigma_p, first, _VD), align=8)
        count = cgutils.alloca_once_value(builder, args[9])
        state = [cgutils.alloca_once_value(builder, builder.load(vector(
            st, builder.add(first, ir.Constant(_I64, _LANES8 * j)), _V64), align=8))
            for j in range(4)]
        with cgutils.for_range(builder, args[4]) as loop:
            k = loop.index
            at = builder.add(builder.mul(k, ir.Constant(_I64, _LANES8)), first)
            r = _xoshiro4(builder, state)
            m = builder.load(count)  # bits and entry written always, counted when outside
            builder.store(r, vector(bits_p, builder.mul(m, ir.Constant(_I64, _W)), _V64),
                          align=8)
            idx = builder.and_(r, _v(_LAYERS - 1))
            rr = builder.lshr(r, _v(_LAYER_BITS))
            rabs = builder.and_(builder.lshr(rr, _v(1)), _v(0x000FFFFFFFFFFFFF))
            negative = builder.icmp_unsigned("!=", builder.and_(rr, _v(1)), _v(0))
            x = builder.fmul(_to_double(builder, rabs), _lookup(builder, wi_p, idx, _VD))
            x = builder.select(negative, builder.fneg(x), x)
            builder.store(builder.fmul(scale, x), vector(out_p, at, _VD), align=8)
            outward = builder.icmp_signed(">=", rabs, _lookup(builder, ki_p, idx, _V64))
            lanes = builder.shl(builder.zext(builder.bitcast(outward, ir.IntType(_W)), _I64),
                                first)
            builder.store(builder.or_(builder.shl(k, ir.Constant(_I64, 8)), lanes),
                          builder.gep(outside_p, [m]))
            some = builder.icmp_unsigned("!=", lanes, ir.Constant(_I64, 0))
            builder.store(builder.add(m, builder.zext(some, _I64)), count)
        for j in range(4):
            builder.store(builder.load(state[j]),
                          vector(st, builder.add(first, ir.Constant(_I64, _LANES8 * j)), _V64),
                          align=8)
        return builder.load(count)
    return types.int64(states, ki, wi, sigma, n, half, out, bits, outside, listed), codegen


@nb.njit(nogil=True, cache=True)
def fill_normal8(states: NDArray[np.uint64], sigma: NDArray[np.float64],
                 out: NDArray[np.float64], bits: NDArray[np.uint64],
                 outside: NDArray[np.int64]) -> None:
    """Eight channels' normal deviates, ``out[8 k + c]`` channel c's k-th times ``sigma[c]``:
    the same numbers :func:`fill_normal` draws from each channel's streams, eight at a time.

    The eight candidate streams advance together, four a vector (:func:`_fast4`); then each
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
        Scratch of ``8 n`` uint64 and ``2 n`` int64.
    """
    n = out.shape[0] // _LANES8
    listed = _fast4(states[0], KI, WI, sigma, n, 0, out, bits, outside, 0)
    listed = _fast4(states[0], KI, WI, sigma, n, 1, out, bits, outside, listed)
    aux = states[1]
    for i in range(listed):
        k, lanes = outside[i] >> 8, outside[i] & 0xFF
        for c in range(_LANES8):
            if (lanes >> c) & 1:
                x, aux[0, c], aux[1, c], aux[2, c], aux[3, c] = _complete(
                    bits[_W * i + c % _W], aux[0, c], aux[1, c], aux[2, c], aux[3, c])
                out[_LANES8 * k + c] = sigma[c] * x
