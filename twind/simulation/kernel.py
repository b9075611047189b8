"""Compiled loops of the engine: noise for a block, then every optic's loop sample by sample.

:func:`shaped_noise` draws and shapes the block's noise (parallel over optics and channels,
each channel its own stream); :func:`run_loops` then closes the damping loops sample by sample
(parallel over optics). Everything that persists between blocks lives in the arrays passed
in, so a block boundary changes nothing in the result.

Per-sample arrays of :func:`run_loops` are sample-major, ``[optic, sample, channel]``: rows of
channel-major arrays lie a power of two apart and evict each other from the cache.

Speed notes: inside the sample loop nothing is sliced (a numba array view costs more than a
filter section's arithmetic); the four DOFs' filter cascades are written out side by side, so
their four dependency chains overlap; the plant is in modal form (two multiplies a state).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from twind.simulation.rng import FI, KI, WI, normal

N_DOF = 4  # POS, PIT, YAW, SIDE


@nb.njit(parallel=True, nogil=True, cache=True)
def shaped_noise(n, sigma, sos, zi, states, out):
    """White Gaussian noise through one section per channel.

    Parameters: `sigma` (optics, channels) white standard deviations; `sos` (optics,
    channels, 6) shaping sections; `zi` (optics, channels, 2) their states; `states`
    (optics, channels, 4) xoshiro streams; `out` (optics, channels, n) the result.
    """
    n_opt, n_ch = sigma.shape
    for oc in nb.prange(n_opt * n_ch):
        o, c = oc // n_ch, oc % n_ch
        s, z, st, y = sos[o, c], zi[o, c], states[o, c], out[o, c]
        b0, b1, b2, a1, a2 = s[0], s[1], s[2], s[4], s[5]
        z0, z1, g = z[0], z[1], sigma[o, c]
        if g == 0.0:
            y[:] = 0.0
            continue
        for k in range(n):
            w = g * normal(st, KI, WI, FI)
            v = b0 * w + z0
            z0 = b1 * w - a1 * v + z1
            z1 = b2 * w - a2 * v
            y[k] = v
        z[0], z[1] = z0, z1


@nb.njit(nogil=True, cache=True, fastmath={"contract"})
def _run_optic(n, a_diag, a_off, partner, bdrive, cin, sos, nsec, zi, gain, gain_target,
               gain_step, ramp_left, limit, dbuf, dpos, ndelay, x, in1_noise, sp, exc,
               in1, in2, out, xs):
    ns = x.shape[0]
    xn = np.empty(ns)
    drive = np.empty(N_DOF)
    y = np.empty(N_DOF)
    pos = dpos[0]
    for k in range(n):
        for i in range(ns):
            xs[k, i] = x[i]
        for d in range(N_DOF):
            acc = in1_noise[k, d]
            for i in range(ns):
                acc += cin[d, i] * x[i]
            in1[k, d] = acc
            y[d] = acc + exc[k, d]
            in2[k, d] = y[d]
        v0, v1, v2, v3 = y[0], y[1], y[2], y[3]
        for m in range(nsec):
            s, z = sos[m], zi[m]
            w0 = s[0, 0] * v0 + z[0, 0]
            w1 = s[0, 1] * v1 + z[0, 1]
            w2 = s[0, 2] * v2 + z[0, 2]
            w3 = s[0, 3] * v3 + z[0, 3]
            z[0, 0] = s[1, 0] * v0 - s[4, 0] * w0 + z[1, 0]
            z[0, 1] = s[1, 1] * v1 - s[4, 1] * w1 + z[1, 1]
            z[0, 2] = s[1, 2] * v2 - s[4, 2] * w2 + z[1, 2]
            z[0, 3] = s[1, 3] * v3 - s[4, 3] * w3 + z[1, 3]
            z[1, 0] = s[2, 0] * v0 - s[5, 0] * w0
            z[1, 1] = s[2, 1] * v1 - s[5, 1] * w1
            z[1, 2] = s[2, 2] * v2 - s[5, 2] * w2
            z[1, 3] = s[2, 3] * v3 - s[5, 3] * w3
            v0, v1, v2, v3 = w0, w1, w2, w3
        y[0], y[1], y[2], y[3] = v0, v1, v2, v3
        for d in range(N_DOF):
            if ramp_left[d] > 0:
                ramp_left[d] -= 1
                gain[d] = gain_target[d] if ramp_left[d] == 0 else gain[d] + gain_step[d]
            o = y[d] * gain[d]
            if limit[d] > 0.0:
                o = min(max(o, -limit[d]), limit[d])
            out[k, d] = o
            if ndelay == 0:
                drive[d] = o
            else:
                drive[d] = dbuf[pos, d]
                dbuf[pos, d] = o
        if ndelay > 0:
            pos = pos + 1 if pos + 1 < ndelay else 0
        for i in range(ns):
            acc = a_diag[i] * x[i] + a_off[i] * x[partner[i]] + sp[k, i]
            for d in range(N_DOF):
                acc += bdrive[i, d] * drive[d]
            xn[i] = acc
        for i in range(ns):
            x[i] = xn[i]
    dpos[0] = pos


@nb.njit(parallel=True, nogil=True, cache=True)
def run_loops(n, a_diag, a_off, partner, bdrive, cin, sos, nsec, zi, gain, gain_target,
              gain_step, ramp_left, limit, dbuf, dpos, ndelay, x, in1_noise, sp, exc,
              in1, in2, out, xs):
    """Close every optic's loop for `n` samples; see :class:`twind.simulation.engine.Engine`."""
    for o in nb.prange(x.shape[0]):
        _run_optic(n, a_diag[o], a_off[o], partner[o], bdrive[o], cin[o], sos[o], nsec[o],
                   zi[o], gain[o], gain_target[o], gain_step[o], ramp_left[o], limit[o],
                   dbuf[o], dpos[o:o + 1], ndelay[o], x[o], in1_noise[o], sp[o], exc[o],
                   in1[o], in2[o], out[o], xs[o])
