"""Seeded Gaussian noise inside compiled loops: xoshiro256** with a 256-layer ziggurat.

numpy's Generator costs ~20 ns a sample on the project's machines, more than the whole loop of
one optic; drawing inside the numba kernel is ~10x cheaper and keeps every optic's stream its
own, so runs repeat bit for bit whatever the block size. Algorithms: Blackman & Vigna,
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
def next_u64(s: NDArray[np.uint64]) -> np.uint64:
    """xoshiro256**: advance state `s` (length 4) and return 64 random bits."""
    result = _rotl(s[1] * np.uint64(5), np.uint64(7)) * np.uint64(9)
    t = s[1] << np.uint64(17)
    s[2] ^= s[0]
    s[3] ^= s[1]
    s[1] ^= s[2]
    s[0] ^= s[3]
    s[2] ^= t
    s[3] = _rotl(s[3], np.uint64(45))
    return result


@nb.njit(inline="always")
def next_double(s: NDArray[np.uint64]) -> float:
    """Uniform in [0, 1) with 53 random bits."""
    return float(next_u64(s) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@nb.njit(inline="always")
def normal(s: NDArray[np.uint64], ki: NDArray[np.int64], wi: NDArray[np.float64],
           fi: NDArray[np.float64]) -> float:
    """One standard normal deviate (ziggurat); tables from :func:`tables`.

    One loop with breaks and a single exit: numba compiles early returns inside the loop
    into code five times slower.
    """
    while True:
        r = next_u64(s)
        idx = np.int64(r & np.uint64(0xFF))
        rr = np.int64(r >> np.uint64(8))
        rabs = (rr >> 1) & 0x000FFFFFFFFFFFFF
        x = rabs * wi[idx]
        if rr & 1:
            x = -x
        if rabs < ki[idx]:
            break
        if idx == 0:  # the tail beyond _R, Marsaglia's method
            xx = -np.log1p(-next_double(s)) / _R
            yy = -np.log1p(-next_double(s))
            if yy + yy > xx * xx:
                x = -(_R + xx) if rr & 1 else _R + xx
                break
            continue
        if (fi[idx - 1] - fi[idx]) * next_double(s) + fi[idx] < np.exp(-0.5 * x * x):
            break
    return x


@nb.njit
def fill_normal(s: NDArray[np.uint64], out: NDArray[np.float64]) -> None:
    """Fill `out` with standard normal deviates from stream `s` (for tests and tools)."""
    flat = out.reshape(-1)
    for i in range(flat.size):
        flat[i] = normal(s, KI, WI, FI)
