"""Engine benchmarks, every figure measured side by side in one run (machines are noisy).

``twind bench`` prints: the engine's speed on one optic and on the 40m, the median and the
best of repeated runs, quiet and again with another process keeping one core busy; with the
wires' violin modes against rigid wires, timed in turns; its speed
and largest output difference against python-control's ``forced_response`` on the same
discrete closed loop; and the marginal speed of ``twind simulate`` (200 s minus 20 s of
simulated time over the wall-time difference, so start-up and compilation cancel).

A shared machine's pace varies from day to day (one engine has run one optic at 660x one day
and 1030x another): the first line prints the pace of a chain of dependent multiply-adds,
measured in the same run, and the one-optic lines the engine's time a sample in its units.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import replace

import control
import numba as nb
import numpy as np

from twind.config import load_config
from twind.model.violin import violin_modes
from twind.simulation.discretize import discrete_closed_loop
from twind.simulation.engine import Engine
from twind.simulation.noise import NoiseSpec

VIOLIN_MODES = 4
"""Violin modes per segment and direction the engine suite times: past 2 kHz on the 40m SOS."""


@nb.njit(cache=True, fastmath={"contract"})
def _chain(n: int, a: float, b: float) -> float:  # pragma: no cover - numba
    x = 1.0
    for _ in range(n):
        x = x * a + b  # one fused multiply-add, waiting on the last
    return x


def multiply_add_ns(n: int = 20_000_000, repeats: int = 3) -> float:
    """Wall time of one multiply-add that waits on the one before (the best of `repeats`
    chains of `n`): the latency the engine's filter cascades are made of, as this machine
    runs it now. At 4 cycles a multiply-add (AMD since Zen, Intel since Skylake) the clock
    is ``4 / multiply_add_ns()`` GHz.

    Returns
    -------
    float
        Nanoseconds.
    """
    _chain(10, 0.5, 0.5)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        _chain(n, 0.999, 0.001)
        best = min(best, time.perf_counter() - t0)
    return best / n * 1e9


def engine_speed(optics: list, seconds: float, seed: int = 0, repeats: int = 5
                 ) -> tuple[float, float]:
    """Simulated seconds per wall second of an engine over `optics` (noise on, 1 s blocks).

    Parameters
    ----------
    optics : list of OpticConfig
        The optics the engine runs.
    seconds : float
        Simulated seconds per run.
    seed : int
        Noise seed.
    repeats : int
        Runs timed, after one that compiles and warms up.

    Returns
    -------
    median, best : float
        Of the runs' speeds (x real time).
    """
    rate = optics[0].sus.sample_rate_hz
    engine = Engine([o.loop() for o in optics], {o.name: o.noise for o in optics}, seed=seed,
                    rate_hz=rate)
    n = int(rate)
    buf = engine.new_block(n)
    engine.step(n, out=buf)
    speeds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(max(1, int(seconds))):
            engine.step(n, out=buf)
        speeds.append(max(1, int(seconds)) / (time.perf_counter() - t0))
    return float(np.median(speeds)), float(max(speeds))


def violin_cost(optic, seconds: float, modes: int = VIOLIN_MODES, rounds: int = 3  # noqa: ANN001
                ) -> dict[str, float]:
    """The engine on one optic with rigid wires and with `modes` violin modes per segment and
    direction, timed in turns (`rounds` of each) so that both see the same machine.

    Returns
    -------
    dict
        ``rigid`` and ``violin`` median speeds (x real time), their ``ratio``, and the
        violin modes' highest frequency ``f_max_hz``.
    """
    violin = replace(optic, sus=replace(optic.sus, wire=replace(optic.sus.wire, modes=modes)))
    speeds: dict[str, list[float]] = {"rigid": [], "violin": []}
    for _ in range(rounds):
        for label, o in (("rigid", optic), ("violin", violin)):
            speeds[label].append(engine_speed([o], seconds, repeats=1)[0])
    rigid, with_violins = (float(np.median(speeds[k])) for k in ("rigid", "violin"))
    return {"rigid": rigid, "violin": with_violins, "ratio": with_violins / rigid,
            "f_max_hz": max(f for _, f, _ in violin_modes(violin.mechanics()))}


@contextmanager
def one_core_loaded() -> Iterator[None]:
    """Another process spinning on one core for as long as the block runs."""
    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.2)  # let it start and take its core
        yield
    finally:
        spin.kill()
        spin.wait()


def against_forced_response(optic, seconds: float, seed: int = 1, repeats: int = 3  # noqa: ANN001
                            ) -> dict[str, float]:
    """Engine and python-control on the same closed loop and the same broadband EXC.

    Each side runs `repeats` times from a fresh start, allocating its outputs, and its median
    wall time counts.

    Parameters
    ----------
    optic : OpticConfig
        The optic (noise off).
    seconds : float
        Simulated seconds.
    seed : int
        Seed of the EXC.
    repeats : int
        Runs of each.

    Returns
    -------
    dict
        ``engine_s``, ``control_s``, their ``ratio``, ``max_rel_diff`` (largest difference
        over the output RMS) and ``samples``.
    """
    rate = optic.sus.sample_rate_hz
    n = int(seconds * rate)
    exc = np.random.default_rng(seed).standard_normal((1, 4, n))
    Engine([optic.loop()], NoiseSpec(enabled=False), rate_hz=rate).step(16)  # compile first
    sys_cl = discrete_closed_loop(optic.loop(), rate)
    t_engine, t_control = [], []
    for _ in range(repeats):
        engine = Engine([optic.loop()], NoiseSpec(enabled=False), rate_hz=rate)
        t0 = time.perf_counter()
        block = engine.step(n, exc=exc)
        t_engine.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        resp = control.forced_response(sys_cl, U=exc[0])
        t_control.append(time.perf_counter() - t0)
    ours = np.concatenate([block.in1[0], block.in2[0], block.out[0]])
    diff = np.abs(ours - resp.outputs).max(axis=1) / ours.std(axis=1)
    engine_s, control_s = float(np.median(t_engine)), float(np.median(t_control))
    return {"engine_s": engine_s, "control_s": control_s, "ratio": control_s / engine_s,
            "max_rel_diff": float(diff.max()), "samples": n}


def simulate_marginal(config: str | None, short: float = 20.0, long: float = 200.0,
                      repeats: int = 5) -> dict[str, float]:
    """Wall times of ``twind simulate`` for two durations and the marginal speed.

    Each duration runs `repeats` times, alternating, and the shortest wall time counts:
    process start-up varies by tenths of a second, as much as 180 s of simulation takes.

    Parameters
    ----------
    config : str or None
        Twin configuration file (None: the shipped 40m).
    short, long : float
        Simulated durations (s).
    repeats : int
        Runs of each.

    Returns
    -------
    dict
        ``wall_short_s``, ``wall_long_s`` and ``marginal_x_real_time``.

    Raises
    ------
    RuntimeError
        If ``twind simulate`` prints no speed.
    """
    walls = {short: np.inf, long: np.inf}
    for _ in range(repeats):
        for duration in (short, long):
            cmd = [sys.executable, "-m", "twind", "simulate", "--duration", str(duration)]
            if config:
                cmd += ["--config", config]
            t0 = time.perf_counter()
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            walls[duration] = min(walls[duration], time.perf_counter() - t0)
            if not re.search(r"x real time", out):
                msg = f"unexpected output of {' '.join(cmd)}: {out[-200:]}"
                raise RuntimeError(msg)
    return {"wall_short_s": walls[short], "wall_long_s": walls[long],
            "marginal_x_real_time": (long - short) / (walls[long] - walls[short])}


def run_benchmarks(config: str | None = None, seconds: float = 20.0, marginal: bool = True) -> None:
    """Print every benchmark figure (see module docstring).

    Parameters
    ----------
    config : str or None
        Twin configuration file (None: the shipped 40m).
    seconds : float
        Sets the runs' lengths: `seconds` / 5 of one optic, `seconds` / 20 (at least 1 s) of
        all, each repeated 5 times.
    marginal : bool
        Whether to time ``twind simulate`` too (a minute more).
    """
    twin = load_config(config)
    etmx = twin.optics.get("ETMX", next(iter(twin.optics.values())))
    every = list(twin.optics.values())
    rate = etmx.sus.sample_rate_hz
    fma = multiply_add_ns()
    print(f"this machine now: a dependent multiply-add takes {fma:.3f} ns ({4 / fma:.2f} GHz "
          "at 4 cycles each)")
    for label, load in (("quiet", nullcontext()), ("one core loaded", one_core_loaded())):
        with load:
            one = engine_speed([etmx], seconds / 5)
            many = engine_speed(every, max(1.0, seconds / 20))
        print(f"engine, 1 optic ({etmx.name}), noise on, {label}: median {one[0]:7.1f}, best "
              f"{one[1]:7.1f} x real time ({one[0] * rate:.3g} samples/s, "
              f"{1e9 / (one[0] * rate) / fma:.0f} multiply-add latencies a sample)")
        print(f"engine, {len(every)} optics ({twin.source}), {label}: median {many[0]:7.1f}, "
              f"best {many[1]:7.1f} x real time ({many[0] * rate * len(every):.3g} "
              f"optic-samples/s)")
    v = violin_cost(etmx, seconds / 5)
    print(f"engine, 1 optic, its wires' violin modes ({VIOLIN_MODES} per segment and direction, "
          f"up to {v['f_max_hz']:.0f} Hz) against rigid wires, in turns: {v['violin']:.1f} "
          f"against {v['rigid']:.1f} x real time, {v['ratio']:.2f} of the speed")
    fr = against_forced_response(etmx, min(seconds, 5.0))
    print(f"python-control forced_response, same closed loop, {fr['samples']} samples, "
          f"median of 3: engine {fr['engine_s']:.4f} s, control {fr['control_s']:.3f} s, "
          f"engine faster by {fr['ratio']:.1f} x; largest difference {fr['max_rel_diff']:.2e} "
          f"of the output RMS")
    if marginal:
        m = simulate_marginal(config)
        print(f"twind simulate: 20 s in {m['wall_short_s']:.2f} s, 200 s in {m['wall_long_s']:.2f} s "
              f"wall; marginal speed {m['marginal_x_real_time']:.0f} x real time")
