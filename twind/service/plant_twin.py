"""A state-space optic served as the 40m's optics are: every test point published under the
site's names (``K1:VIS-SRM_IM_DAMP_P_IN1``), excitations on its EXC points (a TEST point's,
a damping loop's), status and stop, paced to the wall clock.

What a running SOS also takes, a change of its physical parameters or of its filters, a
state-space optic does not: its plant is another lab's matrices, and its controllers are
changed in its configuration.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import zenoh

from twind.bus.keys import ROOT
from twind.config import TwinConfig
from twind.config.statespace import SENSOR_NOISE, StateSpaceOptic
from twind.errors import TwindError
from twind.excitation import Limits
from twind.service.twin import TwinService

UNIT = "ct"
"""A state-space optic's channels are in the model's own units, as counts of its front end."""


class PlantTwinService(TwinService):
    """:class:`~twind.service.twin.TwinService` of one state-space optic.

    Parameters
    ----------
    session : zenoh.Session
    twin : TwinConfig
    optics : list of StateSpaceOptic
        One optic.
    block_s, speed, seed, root, recorder_status
        As :class:`~twind.service.twin.TwinService`'s.
    """

    def __init__(self, session: zenoh.Session, twin: TwinConfig,
                 optics: list[StateSpaceOptic], block_s: float = 1 / 16, speed: float = 1.0,
                 seed: int = 0, root: str = ROOT,
                 recorder_status: Callable[[], dict] | None = None) -> None:
        if len(optics) != 1:
            msg = "a state-space twin serves one optic; choose it with --optics"
            raise TwindError(msg)
        super().__init__(session, twin, optics, block_s, speed, seed, root, recorder_status)

    def _start_engine(self, seed: int) -> None:
        """The optic's engine with its damping loops closed, and its channels: each EXC
        point, each readback, each loop's IN2 and OUT (the EXC points first)."""
        optic = self.optics[0]
        self.engine = optic.engine(seed=seed, noise=dict.fromkeys(optic.readbacks, SENSOR_NOISE))
        self.points = self.engine.points
        block = self.engine.step(0)  # compiles the kernel: the first block is not late
        self._suffixes = sorted(block.channels, key=lambda c: not c.endswith("_EXC"))
        self._names = [optic.channel(c) for c in self._suffixes]
        self._publish(block)

    def _publish(self, block) -> None:  # noqa: ANN001 - the engine's Block
        """The channels of `block` as the service publishes them."""
        self._channels = [(name, UNIT, block.channels[c])
                          for name, c in zip(self._names, self._suffixes, strict=True)]

    def _advance(self, exc: dict[tuple[int, int], np.ndarray] | None) -> None:
        """The next block, the excitations by EXC point."""
        drive = {self.points[p]: samples for (_, p), samples in (exc or {}).items()}
        self._publish(self.engine.step(self.n, drive))

    def _test_point(self, channel: str) -> tuple[int, int, Limits]:
        """``(0, index, limits)`` of EXC point `channel`: each has the ``_EXC`` limits."""
        optic = self.optics[0]
        names = [optic.channel(p) for p in self.points]
        if channel not in names:
            msg = f"unknown excitation channel {channel!r}; e.g. {names[0]}"
            raise TwindError(msg)
        return 0, names.index(channel), self.limits

    def _watchdogs(self) -> dict[str, str]:
        """A state-space optic has none."""
        return {self.optics[0].name: "none"}

    def params(self, request: dict) -> dict:
        """Refused: a state-space plant is changed in its configuration."""
        msg = (f"{self.optics[0].name} is a state-space model ({self.optics[0].source}): its "
               "plant and controllers are changed in its configuration, not live")
        raise TwindError(msg)

    filter = params
