"""Seeded Gaussian noise inside compiled loops: xoshiro256** with a 256-layer ziggurat.

numpy's Generator costs ~10 ns a sample on the project's machines; :func:`fill_normal` inside
the engine's kernel ~3 ns, and keeps every optic's stream its own, so runs repeat bit for bit
whatever the block size. Algorithms: Blackman & Vigna,
"Scrambled linear pseudorandom number generators" (2021); Marsaglia & Tsang, "The ziggurat
method for generating random variables" (2000), with numpy's 256-layer constants.
"""

from __future__ import annotations

import zlib

import numba as nb
import numpy as np
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
    """Independent xoshiro256** states for `n` streams from one integer seed, shape (n, 4).

    `key` (an optic's name) selects its own family of streams, so an optic's noise does not
    depend on which other optics run beside it.

    Parameters
    ----------
    seed : int
        The run's seed.
    n : int
        Streams wanted.
    key : str
        The family of streams (an optic's name; empty for the seed's own).

    Returns
    -------
    ndarray of uint64, shape (n, 4)
    """
    spawn_key = (zlib.crc32(key.encode()),) if key else ()
    children = np.random.SeedSequence(seed, spawn_key=spawn_key).spawn(n)
    states = np.array([c.generate_state(4, dtype=np.uint64) for c in children], dtype=np.uint64)
    states[np.all(states == 0, axis=1), 0] = 1  # the all-zero state is a fixed point
    return states


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


@nb.njit(nogil=True, cache=True)
def fill_normal(state: NDArray[np.uint64], scale: float, out: NDArray[np.float64]) -> None:
    """Fill `out` with normal deviates of standard deviation `scale` (ziggurat).

    Parameters
    ----------
    state : ndarray of uint64, shape (4,)
        A xoshiro256** stream from :func:`seed_states`, advanced past the draws.
    scale : float
        Standard deviation.
    out : ndarray, 1-D
        Filled in place.

    Notes
    -----
    The state stays in registers for the whole array; one loop with breaks and a single
    exit per deviate, as numba compiles early returns inside the loop into slower code.
    """
    s0, s1, s2, s3 = state[0], state[1], state[2], state[3]
    for k in range(out.shape[0]):
        while True:
            r, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
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
                continue
            u1, s0, s1, s2, s3 = _next(s0, s1, s2, s3)
            if (FI[idx - 1] - FI[idx]) * _uniform(u1) + FI[idx] < np.exp(-0.5 * x * x):
                break
        out[k] = scale * x
    state[0], state[1], state[2], state[3] = s0, s1, s2, s3
