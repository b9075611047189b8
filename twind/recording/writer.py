"""Write engine blocks to an MCAP file: one topic per channel, one message per block."""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

from mcap_protobuf.writer import Writer

from twind.channels import block_channels
from twind.recording.schema import sample_block_class
from twind.timeutil import gps_to_unix_ns

TOPIC_ROOT = "twin"  # the same root as the Zenoh keys: a twin is never mistaken for CDS


class SessionWriter:
    """An MCAP session file; use as a context manager so the summary is written on exit.

    Parameters
    ----------
    path : str or Path
        File to create (an existing file is refused, never overwritten).
    ifo : str
        Interferometer prefix of the channel names.
    gps_start : float
        GPS time of sample 0 of the engine.
    """

    def __init__(self, path: str | Path, ifo: str, gps_start: float) -> None:
        self.path = Path(path)
        if self.path.exists():
            msg = f"{self.path} exists; twind does not overwrite recordings"
            raise FileExistsError(msg)
        self._fh = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._fh)
        self._cls = sample_block_class()
        self.ifo, self.gps_start, self.sequence = ifo, gps_start, 0

    def write_block(self, block) -> None:  # noqa: ANN001 - twind.simulation.engine.Block
        """Append every channel of `block` as one message each."""
        gps = self.gps_start + block.start_sample / block.rate_hz
        t_ns = gps_to_unix_ns(gps)
        for name, unit, samples in block_channels(self.ifo, block):
            msg = self._cls(channel=name, gps_start=gps, rate_hz=block.rate_hz,
                            sequence=self.sequence, unit=unit)
            msg.samples.extend(samples.tolist())
            self._writer.write_message(f"{TOPIC_ROOT}/{name}", msg, log_time=t_ns,
                                       publish_time=t_ns, sequence=self.sequence)
        self.sequence += 1

    def close(self) -> None:
        """Write the MCAP summary and close the file."""
        if not self._fh.closed:
            self._writer.finish()
            self._fh.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
