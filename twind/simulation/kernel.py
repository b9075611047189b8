"""Compiled loops of the engine: noise for a block, then every optic's loop sample by sample.

:func:`advance` closes the damping loops sample by sample and, on the other thread, draws
and shapes the next chunk of noise (each channel its own stream) with :func:`shaped_noise`. Everything that persists between blocks lives in the arrays passed
in, so a block boundary changes nothing in the result.

Rows of the ``[optic, channel, sample]`` arrays the loops read and write are padded so that
they never lie a multiple of 4 KiB apart: such rows evict each other from the cache.

Speed notes: inside the sample loop nothing is sliced (a numba array view costs more than a
filter section's arithmetic); the four DOFs' filter cascades are written out side by side, so
their four dependency chains overlap; the plant is in modal form (two multiplies a state).
The plant is bilinear-discretised, so its inputs of this cycle (the coil drives, which are
OUT of ``ndelay >= 1`` cycles ago, and the suspension point) also feed through to the OSEMs.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from twind.simulation.rng import FI, KI, WI, normal

N_DOF = 4  # POS, PIT, YAW, SIDE
N_OSEM = 5  # UL, UR, LL, LR, SIDE


@nb.njit(nogil=True, cache=True)
def shaped_noise(n, sigma, sos, zi, states, out):
    """One optic's noise: white Gaussian noise through one section per channel.

    Parameters: `sigma` (channels,) white standard deviations; `sos` (channels, 6) shaping
    sections; `zi` (channels, 2) their states; `states` (channels, 4) xoshiro streams;
    `out` (channels, n) the result.
    """
    for c in range(sigma.shape[0]):
        b0, b1, b2, a1, a2 = sos[c, 0], sos[c, 1], sos[c, 2], sos[c, 4], sos[c, 5]
        z0, z1, g, st = zi[c, 0], zi[c, 1], sigma[c], states[c]
        if g == 0.0:
            out[c, :n] = 0.0
            continue
        for k in range(n):
            w = g * normal(st, KI, WI, FI)
            v = b0 * w + z0
            z0 = b1 * w - a1 * v + z1
            z1 = b2 * w - a2 * v
            out[c, k] = v
        zi[c, 0], zi[c, 1] = z0, z1


@nb.njit(nogil=True, cache=True, fastmath={"contract"})
def _run_optic(n, a, npos, a_diag, a_off, partner, bdrive, bsp, cs, ds, inmat, sos, nsec, zi, gain, gain_target, gain_step, ramp_left, limit, dbuf, dpos, ndelay, x,
               noise, exc, in1, in2, out, sen):
    ns = x.shape[0]
    xn = np.empty(ns)
    u = np.empty(N_DOF + 3)  # the plant's inputs this cycle: coil drives (delayed OUT), x/y/yaw sp
    y = np.empty(N_DOF)
    osem = np.empty(N_OSEM)
    pos = dpos[0]
    for k in range(n):
        t, q = a + k, npos + k
        for d in range(N_DOF):
            u[d] = dbuf[pos, d]
        for m in range(3):
            u[N_DOF + m] = noise[N_OSEM + m, q]
        for j in range(N_OSEM):
            acc = 1e6 * noise[j, q]
            for i in range(ns):
                acc += cs[j, i] * x[i]
            for m in range(N_DOF + 3):
                acc += ds[j, m] * u[m]
            osem[j] = acc
            sen[j, t] = acc
        for d in range(N_DOF):
            acc = 0.0
            for j in range(N_OSEM):
                acc += inmat[d, j] * osem[j]
            in1[d, t] = acc
            y[d] = acc + exc[d, t]
            in2[d, t] = y[d]
        v0, v1, v2, v3 = y[0], y[1], y[2], y[3]
        for m in range(nsec):
            w0 = sos[m, 0, 0] * v0 + zi[m, 0, 0]
            w1 = sos[m, 0, 1] * v1 + zi[m, 0, 1]
            w2 = sos[m, 0, 2] * v2 + zi[m, 0, 2]
            w3 = sos[m, 0, 3] * v3 + zi[m, 0, 3]
            zi[m, 0, 0] = sos[m, 1, 0] * v0 - sos[m, 4, 0] * w0 + zi[m, 1, 0]
            zi[m, 0, 1] = sos[m, 1, 1] * v1 - sos[m, 4, 1] * w1 + zi[m, 1, 1]
            zi[m, 0, 2] = sos[m, 1, 2] * v2 - sos[m, 4, 2] * w2 + zi[m, 1, 2]
            zi[m, 0, 3] = sos[m, 1, 3] * v3 - sos[m, 4, 3] * w3 + zi[m, 1, 3]
            zi[m, 1, 0] = sos[m, 2, 0] * v0 - sos[m, 5, 0] * w0
            zi[m, 1, 1] = sos[m, 2, 1] * v1 - sos[m, 5, 1] * w1
            zi[m, 1, 2] = sos[m, 2, 2] * v2 - sos[m, 5, 2] * w2
            zi[m, 1, 3] = sos[m, 2, 3] * v3 - sos[m, 5, 3] * w3
            v0, v1, v2, v3 = w0, w1, w2, w3
        y[0], y[1], y[2], y[3] = v0, v1, v2, v3
        for d in range(N_DOF):
            if ramp_left[d] > 0:
                ramp_left[d] -= 1
                gain[d] = gain_target[d] if ramp_left[d] == 0 else gain[d] + gain_step[d]
            o = y[d] * gain[d]
            if limit[d] > 0.0:
                o = min(max(o, -limit[d]), limit[d])
            out[d, t] = o
            dbuf[pos, d] = o
        pos = pos + 1 if pos + 1 < ndelay else 0
        for i in range(ns):
            acc = a_diag[i] * x[i] + a_off[i] * x[partner[i]]
            for m in range(3):
                acc += bsp[i, m] * u[N_DOF + m]
            for d in range(N_DOF):
                acc += bdrive[i, d] * u[d]
            xn[i] = acc
        for i in range(ns):
            x[i] = xn[i]
    dpos[0] = pos


@nb.njit(parallel=True, nogil=True, cache=True)
def advance(n, a, npos, a_diag, a_off, partner, bdrive, bsp, cs, ds, inmat, sos, nsec, zi, gain, gain_target, gain_step, ramp_left, limit, dbuf, dpos, ndelay, x,
            noise, exc, in1, in2, out, sen, draw, n_draw, sigma, noise_sos, noise_zi, rng,
            noise_next):
    """Close every optic's loop for `n` samples from sample `a` of the block arrays, with
    noise from sample `npos` of `noise`; meanwhile, when `draw`, fill `noise_next` with the
    next `n_draw` noise samples. Loops and draws interleave as tasks so that two threads
    share them; see :class:`twind.simulation.engine.Engine`."""
    for task in nb.prange(2 * x.shape[0]):
        o = task // 2
        if task % 2 == 0:
            _run_optic(n, a, npos, a_diag[o], a_off[o], partner[o], bdrive[o], bsp[o],
                       cs[o], ds[o], inmat[o], sos[o], nsec[o], zi[o], gain[o],
                       gain_target[o], gain_step[o], ramp_left[o], limit[o], dbuf[o],
                       dpos[o:o + 1], ndelay[o], x[o], noise[o], exc[o], in1[o], in2[o],
                       out[o], sen[o])
        elif draw:
            shaped_noise(n_draw, sigma[o], noise_sos[o], noise_zi[o], rng[o], noise_next[o])
