"""Recordings of the twin made without the bus, for tests of the analysis."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import signal

from twind import DOFS
from twind.config import OpticConfig
from twind.recording.writer import SessionWriter
from twind.simulation.engine import Engine

GPS0 = 1.4e9


def record_excited_session(cfg: OpticConfig, path: Path, amps: dict[str, float],
                           seconds: int, seed: int = 4, band_hz: float = 10.0,
                           late: tuple[str, ...] = ()) -> Path:
    """An MCAP session of `cfg`'s optic excited in turn on each DOF of `amps` (RMS, white
    below `band_hz`) for `seconds`, with the injection events ``twind tf`` reads.

    Channels ending in one of `late` miss the first second, as when a recorder joins a
    running twin between one channel's block and the next's."""
    eng = Engine([cfg.loop()], cfg.noise, seed=seed)
    rate = int(cfg.sus.sample_rate_hz)
    band = signal.butter(4, band_hz, fs=rate, output="sos")
    rng = np.random.default_rng(seed + 3)
    with SessionWriter(path, "C1", GPS0) as w:
        for k, (dof, amp) in enumerate(amps.items()):
            start = GPS0 + k * seconds
            w.write_event({"event": "start", "id": f"e{k}",
                           "channel": f"C1:SUS-{cfg.name}_SUS{dof}_EXC", "gps": start,
                           "start_gps": start, "request": {"duration": seconds}})
            for _ in range(seconds):
                exc = np.zeros((1, 4, rate))
                exc[0, DOFS.index(dof)] = amp * signal.sosfilt(band, rng.standard_normal(rate)) \
                    * np.sqrt(rate / 2 / band_hz)
                block = eng.step(rate, exc=exc)
                if late and block.start_sample == 0:
                    _write_some(w, block, late)
                else:
                    w.write_block(block)
    return path


def _write_some(w: SessionWriter, block, late: tuple[str, ...]) -> None:  # noqa: ANN001
    from twind.bus.codec import SampleBlock
    from twind.channels import block_channels
    from twind.recording.writer import BlockHeader

    gps = w.gps_start + block.start_sample / block.rate_hz
    for name, unit, samples in block_channels(w.ifo, block):
        if not name.endswith(late):
            data = SampleBlock(name, gps, block.rate_hz, w.sequence, samples, unit).encode()
            w._file.write_block(data, BlockHeader(name, gps, block.rate_hz, w.sequence, unit, ()))
    w.sequence += 1
