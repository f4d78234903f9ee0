"""EpisodeClock: how many segments each environment's episode has run."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.segment_timing import SegmentTiming


class EpisodeClock(LeafSystem):
    """The episode clock of B environments (``control.segment_timing``): tick j of an
    environment's episode covers its episode time [j T - lead, (j + 1) T - lead).

    Output ports:
        episode_ticks (abstract int64 (B,)): the tick each environment's episode is at (0 at its
            start).
    State:
        abstract int64 (B,): the same.
    Events:
        periodic unrestricted update every T (offset 0): every environment's count + 1.
    """

    def __init__(self, batch: int, timing: SegmentTiming):
        """Args: batch, B; timing, the segment time line."""
        super().__init__()
        self.batch = int(batch)
        self.timing = timing
        self._ticks_index = self.DeclareAbstractState(AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.episode_ticks_port = self.DeclareAbstractOutputPort(
            "episode_ticks",
            lambda: AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)),
            self.CalcEpisodeTicks,
            prerequisites_of_calc={self.abstract_state_ticket(self._ticks_index)},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Tick)

    def ticks(self, context) -> np.ndarray:
        """The episode ticks (B,) in this system's ``context`` (read only)."""
        return context.get_abstract_state(self._ticks_index).get_value()

    def StartEpisodes(self, context, rows) -> None:
        """Restarts the clock of the environments ``rows`` (int indices) at tick 0."""
        ticks = self.ticks(context).copy()
        ticks[np.asarray(rows, dtype=int)] = 0
        context.SetAbstractState(self._ticks_index, ticks)

    def CalcEpisodeTicks(self, context, output):
        output.set_value(self.ticks(context))

    def Tick(self, context, state):
        state.get_mutable_abstract_state(self._ticks_index).set_value(self.ticks(context) + 1)
