"""Compiled loops of the engine: every optic's damping loop, sample by sample, with its noise.

One optic is one task: :func:`run_optic` draws the optic's noise a chunk at a time and closes
its loop for a whole step, so optics share nothing and :func:`advance_parallel` hands them to
the cores one at a time, a core held up by other work taking fewer. Everything that persists
between steps lives in the :class:`Arrays`, so a step boundary changes nothing in the result.

Per sample the four DOFs run side by side in 4-lane vectors (:mod:`twind.simulation.simd`):

- IN1 of POS, PIT, YAW, SIDE: ``C x + D u + N n``, the plant's modal state ``x``, the coil
  drives ``u`` (OUT of ``ndelay`` cycles ago: the plant is bilinear, so its inputs of this
  cycle feed through) and the noise ``n``, all projected on the DOFs once at build time;
- IN2 = IN1 + EXC; the filter cascades, one lane each; OUT = gain x cascade, limited;
- the drive of the coils: OUT plus the excitation past the damping filters (the 40m's LSC and
  ASC paths), which goes through the output matrix as OUT does;
- the OSEM readings ``sen``, when wanted: from IN1 and one more combination of the
  readings, when the input matrix has full rank, or else from the same state, inputs and
  noise;
- the modal plant's next state, four states a vector (each state couples only to its pair).

Noise is drawn in chunks of :data:`CHUNK` samples, whatever the step sizes: white, the eight
channels' xoshiro streams as two vectors of four (:func:`~twind.simulation.rng.fill_normal8`),
then shaped, one section per channel; none for an optic whose noise is off. The loop takes
each cycle's noise from the chunk as it needs it.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from twind.simulation.cache import register
from twind.simulation.rng import fill_normal8
from twind.simulation.simd import (
    LANES,
    add4,
    cascade4,
    filter8,
    fma4,
    load4,
    mul4,
    splat4,
    store4,
    swap_pairs,
    vec4,
)

register()

N_DOF = 4  # POS, PIT, YAW, SIDE
N_OSEM = 5  # UL, UR, LL, LR, SIDE
N_NOISE = 8  # the five OSEMs, then the suspension point's x, y and yaw
N_SP = 3
CHUNK = 2048  # samples per noise draw: small enough to stay in cache
PLANT_ROWS = 2 + N_DOF  # per group of 4 modal states: a_diag, a_off, then B of each drive


class Arrays(NamedTuple):
    """Everything the kernel reads and keeps, stacked over optics (first axis).

    Flat rows of 4 lanes (``[optic, row * 4 + lane]``) hold the vectors the kernel loads.
    """

    plant: NDArray[np.float64]  # per 4 modal states: PLANT_ROWS rows (see PLANT_ROWS)
    sp_to_x: NDArray[np.float64]  # [optic, sp channel * ns + state]: B of the suspension point
    x_to_in1: NDArray[np.float64]  # per state: its C on the 4 DOFs
    u_to_in1: NDArray[np.float64]  # per drive: its feedthrough D on the 4 DOFs
    noise_to_in1: NDArray[np.float64]  # per noise channel: its part of the 4 DOFs' IN1
    sen_face: NDArray[np.float64]  # per state, drive and noise channel: UL, UR, LL, LR in um
    sen_side: NDArray[np.float64]  # [optic, ns + 4 + 8]: the same of SIDE
    sen_extra: NDArray[np.float64]  # [optic, ns + 4 + 8]: an OSEM combination no DOF reads
    sen_inverse: NDArray[np.float64]  # [optic, 7 * 4]: OSEMs from IN1 and that combination
    sen_by_inverse: NDArray[np.bool_]  # [optic]: whether the input matrix allows it
    read_osems: NDArray[np.bool_]  # [optic]: whether the OSEM readings are wanted at all
    x: NDArray[np.float64]  # [optic, ns] modal state
    filters: NDArray[np.float64]  # cascade4 layout, the four DOFs' cascades as lanes
    nsec: NDArray[np.int64]
    gain: NDArray[np.float64]  # [optic, 4], and its ramp: target, step, samples left
    gain_target: NDArray[np.float64]
    gain_step: NDArray[np.float64]
    ramp_left: NDArray[np.int64]
    limit: NDArray[np.float64]  # [optic, 4]; 0 for none
    delay: NDArray[np.float64]  # [optic, ndelay * 4]: OUT of the last ndelay cycles
    delay_pos: NDArray[np.int64]
    ndelay: NDArray[np.int64]
    noise_filters: NDArray[np.float64]  # [optic, 2, cascade4 layout]: two cascades of a section
    sigma: NDArray[np.float64]  # [optic, 8] white standard deviation of each noise channel
    quiet: NDArray[np.bool_]  # [optic]: no noise at all (every sigma 0), so none is drawn
    rng: NDArray[np.uint64]  # [optic, 2, 4, 8] xoshiro256** candidate and rejection streams
    noise: NDArray[np.float64]  # [optic, CHUNK * 8] the current chunk of shaped noise
    bits: NDArray[np.uint64]  # [optic, CHUNK * 8] scratch of fill_normal8
    outside: NDArray[np.int64]  # [optic, 2 CHUNK] scratch of fill_normal8
    noise_pos: NDArray[np.int64]  # samples of the current chunk used
    driven: NDArray[np.bool_]  # [optic]: whether this step's lsc holds anything


@nb.njit(nogil=True, cache=True)
def draw_noise(states, sigma, filters, out, bits, outside):
    """One optic's next chunk of noise, ``out[8 k + c]`` channel c's k-th sample: white
    Gaussian noise of each channel's level, the eight channels' streams as two vectors of
    four (:func:`fill_normal8`), then each channel's shaping section (channels 0-3 and 4-7 as the
    lanes of two cascades).

    Parameters
    ----------
    states : ndarray of uint64, shape (2, 4, 8)
        The channels' streams, as :func:`~twind.simulation.rng.fill_normal8` takes them.
    sigma : ndarray, shape (8,)
        The white standard deviation of each channel.
    filters : ndarray, shape (2, 28)
        The shaping sections in :func:`~twind.simulation.simd.cascade4`'s layout.
    out : ndarray, shape (8 CHUNK,)
        Filled with the chunk.
    bits, outside : ndarray
        Scratch for :func:`~twind.simulation.rng.fill_normal8`.
    """
    fill_normal8(states, sigma, out, bits, outside)
    filter8(filters, out, out.shape[0] // N_NOISE)


@nb.njit(inline="always", fastmath={"contract"})
def _in1(x_to_in1, u_to_in1, noise_to_in1, x, u, noise, q):
    """The four DOFs' IN1 of this cycle, from noise sample `q`: noise, then state (two
    sums), then the drives last, which come from the cycle before."""
    ya = splat4(0.0)
    for j in range(N_NOISE):
        ya = fma4(noise_to_in1, LANES * j, noise[N_NOISE * q + j], ya)
    yb = splat4(0.0)
    for g in range(x.shape[0] // LANES):
        i = LANES * LANES * g
        ya = fma4(x_to_in1, i, x[LANES * g], ya)
        yb = fma4(x_to_in1, i + LANES, x[LANES * g + 1], yb)
        ya = fma4(x_to_in1, i + 2 * LANES, x[LANES * g + 2], ya)
        yb = fma4(x_to_in1, i + 3 * LANES, x[LANES * g + 3], yb)
    ya = fma4(u_to_in1, 0, u[0], ya)
    yb = fma4(u_to_in1, LANES, u[1], yb)
    ya = fma4(u_to_in1, 2 * LANES, u[2], ya)
    yb = fma4(u_to_in1, 3 * LANES, u[3], yb)
    return add4(ya, yb)


@nb.njit(inline="always", fastmath={"contract"})
def _next_state(plant, sp_to_x, x, u, noise, q):
    """Advance the modal state `x` by one cycle, four states a vector; the suspension point's
    noise from noise sample `q`."""
    ns = x.shape[0]
    for g in range(ns // LANES):
        xn = splat4(0.0)
        for m in range(N_SP):
            xn = fma4(sp_to_x, m * ns + LANES * g, noise[N_NOISE * q + N_OSEM + m], xn)
        xg = load4(x, LANES * g)
        base = PLANT_ROWS * LANES * g
        xn = fma4(plant, base, xg, xn)
        xn = fma4(plant, base + LANES, swap_pairs(xg), xn)
        for d in range(N_DOF):
            xn = fma4(plant, base + LANES * (2 + d), u[d], xn)
        store4(x, LANES * g, xn)


@nb.njit(inline="always", fastmath={"contract"})
def _dot_inputs(row, x, u, noise, q):
    """The dot product of `row` with this cycle's inputs: the states, the drives and noise
    sample `q`'s channels (``ns + 4 + 8`` values), four a vector."""
    ns = x.shape[0]
    v = fma4(row, ns, u, splat4(0.0))
    for i in range(0, ns, LANES):
        v = fma4(row, i, load4(x, i), v)
    v = fma4(row, ns + N_DOF, load4(noise, N_NOISE * q), v)
    v = fma4(row, ns + N_DOF + LANES, load4(noise, N_NOISE * q + LANES), v)
    return (v[0] + v[1]) + (v[2] + v[3])


@nb.njit(inline="always", fastmath={"contract"})
def _osem_cycle(face, side, x, u, noise, q):
    """The five OSEM readings (um) of this cycle: UL, UR, LL, LR as a vector, and SIDE.

    UL, UR, LL, LR are the lanes of a vector summed over the inputs (states, drives, noise
    channels: the rows of `face`), in four partial sums; SIDE is the dot product of `side`
    with the inputs.
    """
    ns = x.shape[0]
    zero = splat4(0.0)
    va, vb, vc, vd = zero, zero, zero, zero
    for i in range(0, ns, LANES):
        va = fma4(face, LANES * i, x[i], va)
        vb = fma4(face, LANES * (i + 1), x[i + 1], vb)
        vc = fma4(face, LANES * (i + 2), x[i + 2], vc)
        vd = fma4(face, LANES * (i + 3), x[i + 3], vd)
    va = fma4(face, LANES * ns, u[0], va)
    vb = fma4(face, LANES * (ns + 1), u[1], vb)
    vc = fma4(face, LANES * (ns + 2), u[2], vc)
    vd = fma4(face, LANES * (ns + 3), u[3], vd)
    for m in range(0, N_NOISE, LANES):
        r = ns + N_DOF + m
        va = fma4(face, LANES * r, noise[N_NOISE * q + m], va)
        vb = fma4(face, LANES * (r + 1), noise[N_NOISE * q + m + 1], vb)
        vc = fma4(face, LANES * (r + 2), noise[N_NOISE * q + m + 2], vc)
        vd = fma4(face, LANES * (r + 3), noise[N_NOISE * q + m + 3], vd)
    return add4(add4(va, vb), add4(vc, vd)), _dot_inputs(side, x, u, noise, q)


@nb.njit(inline="always", fastmath={"contract"})
def _osems_from_in1(extra, inverse, x, u, noise, q, y):
    """The five OSEM readings (um) of this cycle from the cycle's IN1 `y`, as
    :func:`_osem_cycle` returns them.

    IN1 holds four combinations of the five readings (the input matrix); `extra` gives a
    fifth, which no DOF reads, per state, drive and noise channel. `inverse` is the inverse
    of the input matrix with that row below it: its columns for UL-LR per IN1 DOF and per
    the fifth, then SIDE's row. A third of the work of :func:`_osem_cycle`.
    """
    e = _dot_inputs(extra, x, u, noise, q)
    zero = splat4(0.0)
    fa = fma4(inverse, 0, y[0], zero)
    fb = fma4(inverse, LANES, y[1], zero)
    fa = fma4(inverse, 2 * LANES, y[2], fa)
    fb = fma4(inverse, 3 * LANES, y[3], fb)
    fa = fma4(inverse, 4 * LANES, e, fa)
    vs = fma4(inverse, 5 * LANES, y, zero)
    return add4(fa, fb), ((vs[0] + vs[1]) + (vs[2] + vs[3])) + inverse[6 * LANES] * e


@nb.njit(nogil=True, cache=True)
def _ramp(gain, gain_target, gain_step, ramp_left):
    """One cycle of every ramping gain."""
    for d in range(N_DOF):
        if ramp_left[d] > 0:
            ramp_left[d] -= 1
            gain[d] = gain_target[d] if ramp_left[d] == 0 else gain[d] + gain_step[d]


@nb.njit(inline="always")
def _put(a, t, v):
    """``a[:4, t] = v``: a vector's lanes into column `t` of the first four rows of `a`."""
    a[0, t], a[1, t], a[2, t], a[3, t] = v[0], v[1], v[2], v[3]


@nb.njit(inline="always")
def _clip(v, lim):
    return min(max(v, -lim), lim) if lim > 0.0 else v


@nb.njit(nogil=True, cache=True, fastmath={"contract"})
def _close(s, o, n, a, p, exc, lsc, in1, in2, out, sen):
    """Close optic `o`'s loop for `n` cycles from block sample `a` and noise sample `p`;
    `lsc` is added to OUT on its way to the coils.

    The loop is bound by its loads and multiply-adds (the cascades' coefficients and states
    most of them), not by the chain of the cascades: see docs/benchmarks.md. The vectors
    carried from one cycle to the next (the drives ``u``) stay in registers.
    """
    x, delay, filters = s.x[o], s.delay[o], s.filters[o]
    x_to_in1, u_to_in1, plant = s.x_to_in1[o], s.u_to_in1[o], s.plant[o]
    noise_to_in1, sp_to_x = s.noise_to_in1[o], s.sp_to_x[o]
    sen_face, sen_side, noise = s.sen_face[o], s.sen_side[o], s.noise[o]
    sen_extra, sen_inverse, by_inverse = s.sen_extra[o], s.sen_inverse[o], s.sen_by_inverse[o]
    read_osems = s.read_osems[o]
    gain, gain_target, gain_step = s.gain[o], s.gain_target[o], s.gain_step[o]
    limit, ramp_left = s.limit[o], s.ramp_left[o]
    nsec, ndelay, pos = s.nsec[o], s.ndelay[o], s.delay_pos[o]
    if a < 0 or p < 0 or pos < 0:  # never: tells the compiler that no index wraps around
        return
    limited = np.any(limit > 0.0)
    ramping = np.any(ramp_left > 0)
    driven = s.driven[o]
    u = load4(delay, LANES * pos)
    for k in range(n):
        t = a + k
        y = _in1(x_to_in1, u_to_in1, noise_to_in1, x, u, noise, p + k)
        y2 = add4(y, vec4(exc[0, t], exc[1, t], exc[2, t], exc[3, t]))
        if read_osems:
            if by_inverse:
                face, side = _osems_from_in1(sen_extra, sen_inverse, x, u, noise, p + k, y)
            else:
                face, side = _osem_cycle(sen_face, sen_side, x, u, noise, p + k)
            sen[0, t], sen[1, t], sen[2, t], sen[3, t], sen[4, t] = (face[0], face[1], face[2],
                                                                     face[3], side)
        _next_state(plant, sp_to_x, x, u, noise, p + k)
        w = cascade4(filters, nsec, y2)
        _put(in1, t, y)
        _put(in2, t, y2)
        if ramping:
            _ramp(gain, gain_target, gain_step, ramp_left)
        v = mul4(w, load4(gain, 0))
        if limited:
            v = vec4(_clip(v[0], limit[0]), _clip(v[1], limit[1]), _clip(v[2], limit[2]),
                     _clip(v[3], limit[3]))
        _put(out, t, v)
        if driven:
            v = add4(v, vec4(lsc[0, t], lsc[1, t], lsc[2, t], lsc[3, t]))
        if ndelay == 1:
            u = v
        else:
            store4(delay, LANES * pos, v)
            pos = pos + 1 if pos + 1 < ndelay else 0
            u = load4(delay, LANES * pos)
    if ndelay == 1:
        store4(delay, 0, u)
    s.delay_pos[o] = pos


@nb.njit(nogil=True, cache=True)
def run_optic(s, o, n, exc, lsc, in1, in2, out, sen):
    """Advance optic `o` by `n` samples, drawing its noise as the chunks run out; the test
    points go to ``in1[:, :n]`` etc. (arrays ``[dof, sample]`` of this optic).

    Parameters
    ----------
    s : Arrays
        The engine's arrays.
    o : int
        The optic.
    n : int
        Cycles to run.
    exc : ndarray, shape (4, n)
        EXC of each DOF.
    lsc : ndarray, shape (4, n)
        Each DOF's excitation past the damping filters (ct), added to OUT.
    in1, in2, out : ndarray, shape (4, n)
        Filled with the test points.
    sen : ndarray, shape (5, n)
        Filled with the OSEM readings (um).
    """
    a = 0
    while a < n:
        if s.noise_pos[o] == CHUNK:
            if not s.quiet[o]:
                draw_noise(s.rng[o], s.sigma[o], s.noise_filters[o], s.noise[o], s.bits[o],
                           s.outside[o])
            s.noise_pos[o] = 0
        p = s.noise_pos[o]
        c = min(n - a, CHUNK - p)
        _close(s, o, c, a, p, exc, lsc, in1, in2, out, sen)
        s.noise_pos[o] += c
        a += c


@nb.njit(nogil=True, cache=True)
def advance_serial(s, n, exc, lsc, in1, in2, out, sen):
    """:func:`run_optic` on every optic, one after the other, on this thread.

    Parameters
    ----------
    s : Arrays
        The engine's arrays.
    n : int
        Cycles to run.
    exc, lsc, in1, in2, out, sen : ndarray
        Per optic as :func:`run_optic` takes them (first axis the optic).
    """
    for o in range(s.x.shape[0]):
        run_optic(s, o, n, exc[o], lsc[o], in1[o], in2[o], out[o], sen[o])


@nb.njit(parallel=True, nogil=True, cache=True)
def advance_parallel(s, n, exc, lsc, in1, in2, out, sen):
    """:func:`advance_serial`, the optics shared among numba's threads (same parameters)."""
    for o in nb.prange(s.x.shape[0]):
        run_optic(s, o, n, exc[o], lsc[o], in1[o], in2[o], out[o], sen[o])
