"""The fixed-step engine: all configured optics and their damping loops at the model rate.

State is carried across blocks and the noise comes from per-optic streams of one seed, so
``step(a)`` then ``step(b)`` gives bit for bit what ``step(a + b)`` gives.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from twind import DOFS
from twind.loop.damping import DampingLoop
from twind.simulation.discretize import (
    bilinear,
    delay_samples,
    modal,
    stage_sections,
)
from twind.simulation.kernel import (
    CHUNK,
    N_DOF,
    N_NOISE,
    N_OSEM,
    N_SP,
    PLANT_ROWS,
    Arrays,
    advance_parallel,
    advance_serial,
)
from twind.simulation.noise import NoiseSpec
from twind.simulation.rng import seed_states
from twind.simulation.simd import LANES, SECTION_ROWS

_COEFFICIENTS = [0, 1, 2, 4, 5]  # b0, b1, b2, a1, a2 of a scipy section (a0 = 1)
_CACHE_LINE = 64  # bytes
_IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0])  # cascade4's rows of a section passing its input


@dataclass(frozen=True)
class Block:
    """One block of samples of every test point, for every optic.

    Arrays are indexed ``[optic, dof, sample]``; ``sen`` is ``[optic, osem, sample]`` in um
    (OSEMs UL, UR, LL, LR, SIDE); ``lsc`` is each DOF's excitation past the damping filters
    (ct, added to OUT on its way to the coils: the 40m's ``LSC_EXC`` of POS, ``ASCPIT_EXC``
    and ``ASCYAW_EXC``, :data:`twind.channels.DRIVE_POINTS`).
    """

    optics: tuple[str, ...]
    start_sample: int
    rate_hz: float
    exc: NDArray[np.float64]
    in1: NDArray[np.float64]
    in2: NDArray[np.float64]
    out: NDArray[np.float64]
    sen: NDArray[np.float64]
    lsc: NDArray[np.float64]

    def channel(self, optic: str, dof: str, point: str) -> NDArray[np.float64]:
        """Samples of e.g. ``("ETMX", "POS", "IN1")``.

        Parameters
        ----------
        optic : str
            One of the block's optics.
        dof : str
            POS, PIT, YAW or SIDE.
        point : str
            EXC, IN1, IN2 or OUT, or LSC: the excitation past the damping filters.

        Returns
        -------
        ndarray
            A view of the block's samples.
        """
        arr = getattr(self, point.lower())
        return arr[self.optics.index(optic), DOFS.index(dof)]


@contextmanager
def _threads(n: int) -> Iterator[None]:
    """numba's parallel loops on `n` threads, handing out one iteration (optic) at a time, so
    a thread held up by other work on its core takes fewer optics instead of holding the step."""
    threads, chunk = nb.get_num_threads(), nb.get_parallel_chunksize()
    nb.set_num_threads(n)
    nb.set_parallel_chunksize(1)
    try:
        yield
    finally:
        nb.set_parallel_chunksize(chunk)
        nb.set_num_threads(threads)


def _block_arrays(n_opt: int, n: int) -> list[NDArray[np.float64]]:
    """Zeroed EXC, IN1, IN2, OUT, OSEM and LSC arrays of `n` samples, views of one allocation.

    One allocation of a long block is large enough for numpy to ask the kernel for huge pages,
    which the engine's first pass then faults in a few times faster than five separate arrays.
    The rows do not lie a multiple of 4 KiB apart (see kernel).
    """
    pad = 8 if (n + 8) % 512 else 16
    shapes = [(n_opt, N_DOF)] * 4 + [(n_opt, N_OSEM), (n_opt, N_DOF)]
    rows = np.zeros((sum(a * b for a, b in shapes), n + pad))
    arrays, first = [], 0
    for shape in shapes:
        last = first + shape[0] * shape[1]
        arrays.append(rows[first:last].reshape(*shape, n + pad)[..., :n])
        first = last
    return arrays


def _zeros(shape: int | tuple[int, ...], dtype: type = np.float64) -> NDArray:
    """Zeros whose first element starts a cache line (64 bytes).

    Every row of the kernel's arrays is a whole number of 4-lane vectors (32 bytes), so each
    vector it loads then lies within one cache line; one that straddles two costs two loads,
    and the cascades' coefficients are most of the loop's loads (16 bytes off, as numpy may
    place them, the engine runs 10-20 % slower).
    """
    shape = (shape,) if isinstance(shape, int) else shape
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    raw = np.zeros(size + _CACHE_LINE, dtype=np.uint8)
    start = -raw.ctypes.data % _CACHE_LINE
    return raw[start:start + size].view(dtype).reshape(shape)


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
    threads : int, optional
        Threads to share the optics among (default: numba's, but one for a single optic),
        at most numba's thread count where the engine is made (``numba.set_num_threads``;
        by default ``NUMBA_NUM_THREADS``, the CPUs this process may run on); each optic runs
        on one thread for a whole step.
    osems : bool
        Whether the blocks carry the OSEM readings (``Block.sen``); without them (about a
        tenth of the engine's work) they stay zero.
    """

    def __init__(self, loops: Sequence[DampingLoop], noise: NoiseSpec | Mapping[str, NoiseSpec]
                 = NoiseSpec(), seed: int = 0, rate_hz: float = 16384.0,
                 threads: int | None = None, osems: bool = True) -> None:
        self.loops = list(loops)
        self.optics = tuple(lp.name for lp in self.loops)
        self.rate_hz = float(rate_hz)
        self.samples = 0
        pool = nb.get_num_threads()
        self.threads = min(len(self.loops), threads or pool, pool)
        specs = [noise[n] if isinstance(noise, Mapping) else noise for n in self.optics]
        n_opt = len(self.loops)
        self._order: list[NDArray[np.int64]] = [np.zeros(0, dtype=np.int64)] * n_opt
        self._to_modal: list[NDArray[np.float64]] = [np.zeros((0, 0))] * n_opt
        plants = [self._discrete_plant(lp) for lp in self.loops]
        self._stage_sos = [[stage_sections(lp, d, self.rate_hz) for d in DOFS] for lp in self.loops]
        ns = LANES * -(-max(len(p[0][0]) for p in plants) // LANES)
        self._a = self._allocate(n_opt, ns, specs, osems)
        for o, plant in enumerate(plants):
            self._set_plant(o, *plant)
        self._build_filters()
        self._build_noise(specs, seed)

    def _allocate(self, n_opt: int, ns: int, specs: Sequence[NoiseSpec], osems: bool) -> Arrays:
        ndelay = np.array([delay_samples(lp.plant.delay_s, self.rate_hz) for lp in self.loops])
        nmax = max(1, max(len(sos) for stages in self._stage_sos for sos, _ in stages))
        z = _zeros
        return Arrays(
            plant=z((n_opt, ns * PLANT_ROWS)), sp_to_x=z((n_opt, N_SP * ns)),
            x_to_in1=z((n_opt, ns * LANES)), u_to_in1=z((n_opt, N_DOF * LANES)),
            noise_to_in1=z((n_opt, N_NOISE * LANES)),
            sen_face=z((n_opt, (ns + N_DOF + N_NOISE) * LANES)), sen_side=z((n_opt, ns + N_DOF + N_NOISE)),
            sen_extra=z((n_opt, ns + N_DOF + N_NOISE)), sen_inverse=z((n_opt, 7 * LANES)),
            sen_by_inverse=z(n_opt, dtype=bool), read_osems=np.full(n_opt, osems),
            x=z((n_opt, ns)), filters=z((n_opt, nmax * SECTION_ROWS * LANES)),
            nsec=np.full(n_opt, nmax, dtype=np.int64),
            gain=z((n_opt, N_DOF)), gain_target=z((n_opt, N_DOF)), gain_step=z((n_opt, N_DOF)),
            ramp_left=z((n_opt, N_DOF), dtype=np.int64), limit=z((n_opt, N_DOF)),
            delay=z((n_opt, ndelay.max() * LANES)), delay_pos=z(n_opt, dtype=np.int64),
            ndelay=ndelay, noise_filters=z((n_opt, 2, SECTION_ROWS * LANES)),
            sigma=z((n_opt, N_NOISE)), quiet=z(n_opt, dtype=bool),
            rng=z((n_opt, 2, 4, N_NOISE), dtype=np.uint64),
            noise=z((n_opt, CHUNK * N_NOISE)), bits=z((n_opt, CHUNK * N_NOISE), dtype=np.uint64),
            outside=z((n_opt, 2 * CHUNK), dtype=np.int64),
            noise_pos=np.full(n_opt, CHUNK, dtype=np.int64), driven=z(n_opt, dtype=bool))

    def _discrete_plant(self, lp: DampingLoop) -> tuple[tuple, NDArray, NDArray]:
        A, Bc, Bs, C = lp.plant.osem_state_space()
        Ad, Bd, Cd, Dd = bilinear(A, np.hstack([Bc @ lp.plant.output_matrix, Bs]), C,
                                  1.0 / self.rate_hz)
        mode = modal(Ad, Bd, Cd)
        return mode[:5], Dd, mode[5]

    def _set_plant(self, o: int, mode: tuple, Dd: NDArray, vr: NDArray) -> None:
        """Write optic `o`'s modal plant into the kernel's rows, mode pairs on even states."""
        a_diag, a_off, partner, B, C = mode
        paired = [i for i in range(len(a_diag)) if partner[i] != i]
        order = np.array(paired + [i for i in range(len(a_diag)) if partner[i] == i])
        k, ns = len(order), self._a.x.shape[1]
        rows = np.zeros((ns, PLANT_ROWS))
        rows[:k, 0], rows[:k, 1], rows[:k, 2:] = a_diag[order], a_off[order], B[order, :N_DOF]
        self._a.plant[o] = rows.reshape(ns // LANES, LANES, PLANT_ROWS).transpose(0, 2, 1).ravel()
        sp = np.zeros((N_SP, ns))
        sp[:, :k] = B[order, N_DOF:].T
        self._a.sp_to_x[o] = sp.ravel()
        inmat = self.loops[o].plant.input_matrix
        c = np.zeros((N_OSEM, ns))
        c[:, :k] = C[:, order]
        self._a.x_to_in1[o] = (inmat @ c).T.ravel()
        self._a.u_to_in1[o] = (inmat @ Dd[:, :N_DOF]).T.ravel()
        self._a.noise_to_in1[o] = np.hstack([inmat, inmat @ Dd[:, N_DOF:]]).T.ravel()
        # the OSEM readings in um: 1e6 (C x + D u + n)
        sen = 1e6 * np.hstack([c, Dd[:, :N_DOF], np.eye(N_OSEM), Dd[:, N_DOF:]])
        self._a.sen_face[o], self._a.sen_side[o] = sen[:LANES].T.ravel(), sen[LANES]
        self._set_sen_inverse(o, inmat, sen)
        self._order[o], self._to_modal[o] = order, vr[:, order]

    def _set_sen_inverse(self, o: int, inmat: NDArray, sen: NDArray) -> None:
        """The OSEM readings from IN1 and one combination no DOF reads (see the kernel),
        when the input matrix has full rank and that is well conditioned."""
        _, singular, vt = np.linalg.svd(inmat)
        square = np.vstack([inmat * 1e-6, vt[-1] / np.abs(vt[-1]).max() * 1e-6 * singular[0]])
        usable = singular[-1] > 1e-8 * singular[0] and np.linalg.cond(square) < 1e8
        self._a.sen_by_inverse[o] = usable
        if not usable:
            return
        inverse = np.linalg.inv(square)  # um per [IN1; the fifth combination]
        self._a.sen_extra[o] = square[LANES] @ sen
        self._a.sen_inverse[o, :5 * LANES] = inverse[:LANES].T.ravel()
        self._a.sen_inverse[o, 5 * LANES:6 * LANES] = inverse[LANES, :LANES]
        self._a.sen_inverse[o, 6 * LANES] = inverse[LANES, LANES]

    def update_plant(self, optic: str, loop: DampingLoop) -> None:
        """Replace an optic's plant while running; its motion carries over.

        The state is mapped through physical coordinates (positions and velocities), so
        the optic keeps moving as it was and only the dynamics from now on change.

        Parameters
        ----------
        optic : str
            The optic whose plant changes.
        loop : DampingLoop
            The loop with the new plant (its filters are not read).

        Raises
        ------
        ValueError
            If the new plant has a different number of states.
        """
        o, _ = self._where(optic, DOFS[0])
        mode, Dd, vr = self._discrete_plant(loop)
        k = len(self._order[o])
        if len(mode[0]) != k:
            msg = f"{optic}: the new plant has {len(mode[0])} states, the running one {k}"
            raise ValueError(msg)
        physical = self._to_modal[o] @ self._a.x[o, :k]
        self.loops[o].plant = loop.plant
        self._set_plant(o, mode, Dd, vr)
        self._a.x[o, :k] = np.linalg.solve(self._to_modal[o], physical)

    def _build_filters(self) -> None:
        a = self._a
        # [optic, section, row, dof]: b0, b1, b2, a1, a2 and two states; identity-padded
        self._sections = a.filters.reshape(len(self.loops), -1, SECTION_ROWS, LANES)
        self._sections[:] = _IDENTITY[None, None, :, None]
        for o, lp in enumerate(self.loops):
            for d, dof in enumerate(DOFS):
                sos, where = self._stage_sos[o][d]
                self._sections[o, : len(sos), :5, d] = sos[:, _COEFFICIENTS]
                for fm, rows in where.items():
                    if fm not in lp.modules[dof].on:
                        self._sections[o, rows, :5, d] = _IDENTITY[:5]
        a.gain[:] = [[lp.modules[d].gain for d in DOFS] for lp in self.loops]
        a.gain_target[:] = a.gain
        a.limit[:] = [[lp.modules[d].limit for d in DOFS] for lp in self.loops]
        self._tripped = np.zeros(len(self.loops), dtype=bool)

    def _build_noise(self, specs: Sequence[NoiseSpec], seed: int) -> None:
        for o, spec in enumerate(specs):
            sos, sigma = spec.shaping(self.rate_hz)
            rows = self._a.noise_filters[o].reshape(2, SECTION_ROWS, LANES)
            rows[:, :5] = sos[:, _COEFFICIENTS].reshape(2, LANES, 5).transpose(0, 2, 1)
            self._a.sigma[o] = sigma
            self._a.quiet[o] = not np.any(sigma)
            self._a.rng[o] = seed_states(seed, N_NOISE, key=self.optics[o]).transpose(1, 2, 0)

    def new_block(self, n: int) -> Block:
        """An empty block of `n` samples to pass to :meth:`step` as ``out`` again and again.

        Parameters
        ----------
        n : int
            Samples per block.

        Returns
        -------
        Block
        """
        return Block(self.optics, self.samples, self.rate_hz, *_block_arrays(len(self.loops), n))

    def step(self, n: int, exc: NDArray[np.float64] | None = None, out: Block | None = None,
             lsc: NDArray[np.float64] | None = None) -> Block:
        """Advance all optics by `n` samples.

        Parameters
        ----------
        n : int
            Number of samples.
        exc : ndarray, shape (n_optics, 4, n), optional
            Excitation added at each EXC test point (zero when omitted).
        out : Block, optional
            A block of `n` samples from :meth:`new_block` to fill instead of a new one.
        lsc : ndarray, shape (n_optics, 4, n), optional
            Excitation added to each DOF's OUT on its way to the coils, past the damping
            filters (ct; zero when omitted): what the 40m's LSC and ASC paths inject.

        Returns
        -------
        Block
            The block's test points; its ``start_sample`` counts from the engine's start.

        Raises
        ------
        ValueError
            If `n` is negative or `exc`, `lsc` or `out` have the wrong shape.
        """
        n_opt = len(self.loops)
        if n < 0:
            msg = f"cannot step by {n} samples"
            raise ValueError(msg)
        block = out if out is not None else self.new_block(n)
        if block.in1.shape != (n_opt, N_DOF, n):
            msg = f"out holds {block.in1.shape[-1]} samples, step asked for {n}"
            raise ValueError(msg)
        for name, given, into in (("exc", exc, block.exc), ("lsc", lsc, block.lsc)):
            if given is None:
                into[:] = 0.0
            elif np.shape(given) != (n_opt, N_DOF, n):
                msg = f"{name} must have shape {(n_opt, N_DOF, n)}, got {np.shape(given)}"
                raise ValueError(msg)
            else:
                into[:] = given
        # a tripped optic's coils take nothing, as its watchdog cuts the whole drive
        self._a.driven[:] = (False if lsc is None
                             else np.any(block.lsc, axis=(1, 2)) & ~self._tripped)
        points = (block.exc, block.lsc, block.in1, block.in2, block.out, block.sen)
        if self.threads > 1:
            with _threads(self.threads):
                advance_parallel(self._a, n, *points)
        else:
            advance_serial(self._a, n, *points)
        block = Block(self.optics, self.samples, self.rate_hz, block.exc, block.in1, block.in2,
                      block.out, block.sen, block.lsc)
        self.samples += n
        return block

    def _where(self, optic: str, dof: str) -> tuple[int, int]:
        if optic not in self.optics:
            msg = f"unknown optic {optic!r}; the engine runs {', '.join(self.optics)}"
            raise KeyError(msg)
        if dof not in DOFS:
            msg = f"unknown DOF {dof!r}; expected one of {', '.join(DOFS)}"
            raise KeyError(msg)
        return self.optics.index(optic), DOFS.index(dof)

    def set_gain(self, optic: str, dof: str, gain: float, ramp_s: float | None = None) -> None:
        """Ramp a filter module's gain linearly to `gain` over `ramp_s` (its own ramp if None).

        Parameters
        ----------
        optic : str
            The optic.
        dof : str
            POS, PIT, YAW or SIDE.
        gain : float
            The new gain.
        ramp_s : float, optional
            Ramp time (s), 0 to 3600; the module's own when None.

        Raises
        ------
        KeyError
            If the optic or the DOF is unknown.
        ValueError
            If the gain is not finite or the ramp out of range.
        """
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
        self._a.gain_target[o, d] = gain
        if steps == 0:
            self._a.gain[o, d], self._a.ramp_left[o, d] = gain, 0
        else:
            self._a.gain_step[o, d] = (gain - self._a.gain[o, d]) / steps
            self._a.ramp_left[o, d] = steps

    def trip(self, optic: str) -> None:
        """Zero an optic's damping outputs and its drive past the damping filters, and reset
        its motion and filter histories, as a CDS watchdog does; the outputs stay zero until
        :meth:`rearm` (a gain change before then only sets what rearm restores)."""
        o, _ = self._where(optic, DOFS[0])
        self._tripped[o] = True
        self._a.gain[o] = self._a.gain_target[o] = 0.0
        self._a.ramp_left[o] = 0
        self._a.x[o] = self._sections[o, :, 5:] = self._a.delay[o] = 0.0

    def rearm(self, optic: str) -> None:
        """Restore a tripped optic's module gains (at once, from rest)."""
        o, _ = self._where(optic, DOFS[0])
        self._tripped[o] = False
        self._a.gain[o] = self._a.gain_target[o] = [self.loops[o].modules[d].gain for d in DOFS]

    def tripped(self, optic: str) -> bool:
        """Whether `optic`'s watchdog holds its outputs at zero."""
        return bool(self._tripped[self._where(optic, DOFS[0])[0]])

    def switch(self, optic: str, dof: str, fm: int, on: bool) -> None:
        """Switch stage FM`fm` of a module on or off.

        A stage switched on starts from rest, as CDS's "zero history" input switching does;
        the file's switching types (ramped or crossing-triggered outputs, always-on inputs)
        are not modelled: the switch is immediate.

        Parameters
        ----------
        optic : str
            The optic.
        dof : str
            POS, PIT, YAW or SIDE.
        fm : int
            The stage, 1 to 10.
        on : bool
            On or off.

        Raises
        ------
        KeyError
            If the optic or the DOF is unknown or FM`fm` holds no filter.
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
        self._sections[o, rows, :5, d] = sos[rows][:, _COEFFICIENTS] if on else _IDENTITY[:5]
        self._sections[o, rows, 5:, d] = 0.0
        module.on = (module.on | {fm}) if on else (module.on - {fm})
