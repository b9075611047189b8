"""The fixed-step engine: all configured optics and their damping loops at the model rate.

State is carried across blocks and the noise comes from per-optic streams of one seed, so
``step(a)`` then ``step(b)`` gives bit for bit what ``step(a + b)`` gives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.loop.damping import DampingLoop
from twind.loop.filtermodule import IDENTITY_SECTION
from twind.simulation.discretize import (
    bilinear,
    delay_samples,
    modal,
    stage_sections,
)
from twind.simulation.kernel import N_DOF, N_OSEM, advance, shaped_noise
from twind.simulation.noise import CHANNELS as NOISE_CHANNELS
from twind.simulation.noise import NoiseSpec
from twind.simulation.rng import seed_states

N_NOISE = len(NOISE_CHANNELS)
CHUNK = 2048  # samples per kernel call and per noise draw: small enough to stay in cache


@dataclass(frozen=True)
class Block:
    """One block of samples of every test point, for every optic.

    Arrays are indexed ``[optic, dof, sample]``; ``sen`` is ``[optic, osem, sample]`` in um
    (OSEMs UL, UR, LL, LR, SIDE).
    """

    optics: tuple[str, ...]
    start_sample: int
    rate_hz: float
    exc: NDArray[np.float64]
    in1: NDArray[np.float64]
    in2: NDArray[np.float64]
    out: NDArray[np.float64]
    sen: NDArray[np.float64]

    def channel(self, optic: str, dof: str, point: str) -> NDArray[np.float64]:
        """Samples of e.g. ``("ETMX", "POS", "IN1")``."""
        arr = getattr(self, point.lower())
        return arr[self.optics.index(optic), DOFS.index(dof)]


def _padded(shape: tuple[int, int, int]) -> NDArray[np.float64]:
    """Zeros of `shape` whose rows do not lie a multiple of 4 KiB apart (see kernel)."""
    n = shape[-1]
    pad = 8 if (n + 8) % 512 else 16
    return np.zeros(shape[:-1] + (n + pad,))[..., :n]


class Engine:
    """Integrates plants plus damping loops in fixed steps of one model cycle.

    Parameters
    ----------
    loops : sequence of DampingLoop
        One per optic.
    noise : NoiseSpec or mapping of optic name to NoiseSpec
        Sensor and suspension-point noise; ``NoiseSpec(enabled=False)`` for none.
    seed : int
        Seed of all noise streams.
    rate_hz : float
        Model rate.
    """

    def __init__(self, loops: Sequence[DampingLoop], noise: NoiseSpec | Mapping[str, NoiseSpec]
                 = NoiseSpec(), seed: int = 0, rate_hz: float = 16384.0) -> None:
        self.loops = list(loops)
        self.optics = tuple(lp.name for lp in self.loops)
        self.rate_hz = float(rate_hz)
        self.samples = 0
        specs = [noise[n] if isinstance(noise, Mapping) else noise for n in self.optics]
        self._build_plants()
        self._build_filters()
        self._build_noise(specs, seed)

    def _build_plants(self) -> None:
        n_opt = len(self.loops)
        modes = []
        feedthrough, self._to_modal = [], []
        for lp in self.loops:
            mode, Dd, vr = self._discrete_plant(lp)
            modes.append(mode)
            feedthrough.append(Dd)
            self._to_modal.append(vr)
        ns = max(len(m[0]) for m in modes)
        self._a_diag = np.zeros((n_opt, ns))
        self._a_off = np.zeros((n_opt, ns))
        self._partner = np.tile(np.arange(ns), (n_opt, 1))
        self._bdrive = np.zeros((n_opt, ns, N_DOF))
        self._bsp = np.zeros((n_opt, ns, 3))
        self._cs = np.zeros((n_opt, N_OSEM, ns))  # OSEM um per modal state
        # the kernel's OSEM signals are in um, so the input matrix loses its calibration
        self._inmat = np.array([lp.plant.input_matrix * 1e-6 for lp in self.loops])
        self._ds = 1e6 * np.array(feedthrough)  # OSEM um per coil count and per sp m, rad
        for o, (a_diag, a_off, partner, B, C) in enumerate(modes):
            k = len(a_diag)
            self._a_diag[o, :k], self._a_off[o, :k], self._partner[o, :k] = a_diag, a_off, partner
            self._bdrive[o, :k], self._bsp[o, :k] = B[:, :N_DOF], B[:, N_DOF:]
            self._cs[o, :, :k] = C * 1e6
        self._x = np.zeros((n_opt, ns))
        self._ndelay = np.array([delay_samples(lp.plant.delay_s, self.rate_hz) for lp in self.loops])
        self._dbuf = np.zeros((n_opt, self._ndelay.max(), N_DOF))
        self._dpos = np.zeros(n_opt, dtype=np.int64)

    def _discrete_plant(self, lp: DampingLoop) -> tuple[tuple, NDArray, NDArray]:
        A, Bc, Bs, C = lp.plant.osem_state_space()
        Ad, Bd, Cd, Dd = bilinear(A, np.hstack([Bc @ lp.plant.output_matrix, Bs]), C,
                                  1.0 / self.rate_hz)
        mode = modal(Ad, Bd, Cd)
        return mode[:5], Dd, mode[5]

    def update_plant(self, optic: str, loop: DampingLoop) -> None:
        """Replace an optic's plant while running; its motion carries over.

        The state is mapped through physical coordinates (positions and velocities), so
        the optic keeps moving as it was and only the dynamics from now on change.
        """
        o, _ = self._where(optic, DOFS[0])
        (a_diag, a_off, partner, B, C), Dd, vr = self._discrete_plant(loop)
        k = len(a_diag)
        if k != len(self._to_modal[o]):
            msg = f"{optic}: the new plant has {k} states, the running one {len(self._to_modal[o])}"
            raise ValueError(msg)
        physical = self._to_modal[o] @ self._x[o, :k]
        self._x[o, :k] = np.linalg.solve(vr, physical)
        self._a_diag[o, :k], self._a_off[o, :k], self._partner[o, :k] = a_diag, a_off, partner
        self._bdrive[o, :k], self._bsp[o, :k] = B[:, :N_DOF], B[:, N_DOF:]
        self._cs[o, :, :k] = C * 1e6
        self._ds[o] = 1e6 * Dd
        self._to_modal[o] = vr
        self.loops[o].plant = loop.plant

    def _build_filters(self) -> None:
        n_opt = len(self.loops)
        self._stage_sos = [[stage_sections(lp, d, self.rate_hz) for d in DOFS] for lp in self.loops]
        nmax = max(1, max(len(sos) for lay in self._stage_sos for sos, _ in lay))
        # kernel layout [optic, section, coefficient, dof]; short cascades padded with identity
        self._sos = np.tile(IDENTITY_SECTION[None, :, None], (n_opt, nmax, 1, N_DOF))
        for o, lp in enumerate(self.loops):
            for d, dof in enumerate(DOFS):
                sos, where = self._stage_sos[o][d]
                self._sos[o, : len(sos), :, d] = sos
                for fm, rows in where.items():
                    if fm not in lp.modules[dof].on:
                        self._sos[o, rows, :, d] = IDENTITY_SECTION
        self._nsec = np.full(n_opt, nmax, dtype=np.int64)
        self._zi = np.zeros((n_opt, nmax, 2, N_DOF))
        self._gain = np.array([[lp.modules[d].gain for d in DOFS] for lp in self.loops], dtype=float)
        self._gain_target = self._gain.copy()
        self._gain_step = np.zeros((n_opt, N_DOF))
        self._ramp_left = np.zeros((n_opt, N_DOF), dtype=np.int64)
        self._limit = np.array([[lp.modules[d].limit for d in DOFS] for lp in self.loops], dtype=float)
        self._tripped = np.zeros(n_opt, dtype=bool)

    def _build_noise(self, specs: Sequence[NoiseSpec], seed: int) -> None:
        shaped = [s.shaping(self.rate_hz) for s in specs]
        self._noise_sos = np.array([sos for sos, _ in shaped])
        self._noise_sigma = np.array([sigma for _, sigma in shaped])
        self._noise_zi = np.zeros((len(specs), N_NOISE, 2))
        self._rng = np.array([seed_states(seed, N_NOISE, key=name) for name in self.optics])
        # noise comes in whole chunks, whatever the block sizes, so results do not depend on
        # them; the next chunk is drawn on the second thread while the loops run
        self._noise = _padded((len(specs), N_NOISE, CHUNK))
        self._noise_next = _padded((len(specs), N_NOISE, CHUNK))
        for o in range(len(specs)):
            shaped_noise(CHUNK, self._noise_sigma[o], self._noise_sos[o], self._noise_zi[o],
                         self._rng[o], self._noise[o])
        self._noise_pos = 0
        self._next_ready = False

    def new_block(self, n: int) -> Block:
        """An empty block of `n` samples to pass to :meth:`step` as ``out`` again and again."""
        n_opt = len(self.loops)
        arrays = [_padded((n_opt, N_DOF, n)) for _ in range(4)]
        return Block(self.optics, self.samples, self.rate_hz, *arrays, _padded((n_opt, N_OSEM, n)))

    def step(self, n: int, exc: NDArray[np.float64] | None = None, out: Block | None = None) -> Block:
        """Advance all optics by `n` samples.

        Parameters
        ----------
        n : int
            Number of samples.
        exc : ndarray, shape (n_optics, 4, n), optional
            Excitation added at each EXC test point (zero when omitted).
        out : Block, optional
            A block of `n` samples from :meth:`new_block` to fill instead of a new one.

        Returns
        -------
        Block
            The block's test points; its ``start_sample`` counts from the engine's start.
        """
        n_opt = len(self.loops)
        if n < 0:
            msg = f"cannot step by {n} samples"
            raise ValueError(msg)
        block = out if out is not None else self.new_block(n)
        if block.in1.shape != (n_opt, N_DOF, n):
            msg = f"out holds {block.in1.shape[-1]} samples, step asked for {n}"
            raise ValueError(msg)
        if exc is None:
            block.exc[:] = 0.0
        elif np.shape(exc) != (n_opt, N_DOF, n):
            msg = f"exc must have shape {(n_opt, N_DOF, n)}, got {np.shape(exc)}"
            raise ValueError(msg)
        else:
            block.exc[:] = exc
        start = 0
        while start < n:
            c = min(n - start, CHUNK - self._noise_pos if self._noise_pos < CHUNK else CHUNK)
            self._chunk(block, start, c)
            start += c
        block = replace(block, start_sample=self.samples)
        self.samples += n
        return block

    def _chunk(self, block: Block, a: int, c: int) -> None:
        if self._noise_pos == CHUNK:
            self._noise, self._noise_next = self._noise_next, self._noise
            self._noise_pos, self._next_ready = 0, False
        advance(c, a, self._noise_pos, self._a_diag, self._a_off, self._partner, self._bdrive,
                self._bsp, self._cs, self._ds, self._inmat, self._sos, self._nsec, self._zi,
                self._gain, self._gain_target, self._gain_step, self._ramp_left, self._limit,
                self._dbuf, self._dpos, self._ndelay, self._x, self._noise, block.exc,
                block.in1, block.in2, block.out, block.sen, not self._next_ready, CHUNK,
                self._noise_sigma, self._noise_sos, self._noise_zi, self._rng, self._noise_next)
        self._noise_pos += c
        self._next_ready = True

    def _where(self, optic: str, dof: str) -> tuple[int, int]:
        if optic not in self.optics:
            msg = f"unknown optic {optic!r}; the engine runs {', '.join(self.optics)}"
            raise KeyError(msg)
        if dof not in DOFS:
            msg = f"unknown DOF {dof!r}; expected one of {', '.join(DOFS)}"
            raise KeyError(msg)
        return self.optics.index(optic), DOFS.index(dof)

    def set_gain(self, optic: str, dof: str, gain: float, ramp_s: float | None = None) -> None:
        """Ramp a filter module's gain linearly to `gain` over `ramp_s` (its own ramp if None)."""
        o, d = self._where(optic, dof)
        module = self.loops[o].modules[dof]
        ramp = module.ramp_s if ramp_s is None else ramp_s
        if not (np.isfinite(gain) and 0 <= ramp <= 3600):
            msg = f"gain must be finite and ramp within 0..3600 s, got gain {gain}, ramp {ramp} s"
            raise ValueError(msg)
        module.gain = gain
        if self._tripped[o]:
            return
        steps = int(round(ramp * self.rate_hz))
        self._gain_target[o, d] = gain
        if steps == 0:
            self._gain[o, d], self._ramp_left[o, d] = gain, 0
        else:
            self._gain_step[o, d] = (gain - self._gain[o, d]) / steps
            self._ramp_left[o, d] = steps

    def trip(self, optic: str) -> None:
        """Zero an optic's damping outputs and reset its motion and filter histories, as a
        CDS watchdog does; the outputs stay zero until :meth:`rearm` (a gain change before
        then only sets what rearm restores)."""
        o, _ = self._where(optic, DOFS[0])
        self._tripped[o] = True
        self._gain[o] = self._gain_target[o] = 0.0
        self._ramp_left[o] = 0
        self._x[o] = self._zi[o] = self._dbuf[o] = 0.0

    def rearm(self, optic: str) -> None:
        """Restore a tripped optic's module gains (at once, from rest)."""
        o, _ = self._where(optic, DOFS[0])
        self._tripped[o] = False
        self._gain[o] = self._gain_target[o] = [self.loops[o].modules[d].gain for d in DOFS]

    def tripped(self, optic: str) -> bool:
        """Whether `optic`'s watchdog holds its outputs at zero."""
        return bool(self._tripped[self._where(optic, DOFS[0])[0]])

    def switch(self, optic: str, dof: str, fm: int, on: bool) -> None:
        """Switch stage FM`fm` of a module on or off.

        A stage switched on starts from rest, as CDS's "zero history" input switching does;
        the file's switching types (ramped or crossing-triggered outputs, always-on inputs)
        are not modelled: the switch is immediate.
        """
        o, d = self._where(optic, dof)
        sos, where = self._stage_sos[o][d]
        if fm not in where:
            msg = f"{optic} {dof} FM{fm} holds no filter"
            raise KeyError(msg)
        module = self.loops[o].modules[dof]
        if (fm in module.on) == on:
            return  # as CDS: pressing a button into the state it is in does nothing
        rows = where[fm]
        self._sos[o, rows, :, d] = sos[rows] if on else IDENTITY_SECTION
        self._zi[o, rows, :, d] = 0.0
        module.on = (module.on | {fm}) if on else (module.on - {fm})
