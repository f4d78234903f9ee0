"""The time line of the segment-stepped rally diagram (docs/architecture.md, *Segment stepping*).

Paper, Extended Data Fig. 1: the policy acts every T = 32 ms on an observation built 5 ms before
the segment it commands starts. The segment-stepped diagram advances once per T, at the policy's
instants: tick j of an episode covers the episode's time [j T - lead, (j + 1) T - lead), decides
(from tick 1 on) the segment that starts ``lead`` into it, and leaves every system in its state at
the tick's end. An episode's own clock starts with the opponent's hit at 0; in the diagram's
(global) time it started ``lead`` after the tick at which it began, so every environment of a
batch shares the tick grid while each keeps its own episode clock. Times are counted in whole
command samples (1 ms) and turned into seconds in one place (``seconds``), so that the same
sample gives the same float in every environment and in every batch.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SegmentTiming:
    """samples: command samples per segment (T / command period); lead: samples between an
    observation and the segment it commands; period: the command period, s."""

    samples: int = 32
    lead: int = 5
    period: float = 0.001

    def __post_init__(self) -> None:
        if self.samples < 1 or not 0 <= self.lead < self.samples:
            raise ValueError(f"SegmentTiming: need samples >= 1 and 0 <= lead < samples, got samples={self.samples}, lead={self.lead}")
        if not self.period > 0.0:
            raise ValueError(f"SegmentTiming: period must be > 0 s, got {self.period}")

    @classmethod
    def from_control(cls, segment_samples: int, observation_lead: float, period: float) -> SegmentTiming:
        """From ControlParams' segment_samples and observation_lead (s) and the command period (s);
        the lead must be a whole number of command periods."""
        lead = observation_lead / period
        if abs(lead - round(lead)) > 1e-9:
            raise ValueError(f"SegmentTiming: the observation lead ({observation_lead} s) must be a whole number of command periods ({period} s)")
        return cls(int(segment_samples), int(round(lead)), float(period))

    @property
    def duration(self) -> float:
        """T, s."""
        return self.samples * self.period

    def first_sample(self, ticks) -> np.ndarray:
        """The episode's command sample at the start of tick ``ticks`` (int array): j T - lead."""
        return np.asarray(ticks, dtype=np.int64) * self.samples - self.lead

    def boundary_sample(self, ticks) -> np.ndarray:
        """The episode's sample where the segment decided at tick ``ticks`` starts: j T."""
        return np.asarray(ticks, dtype=np.int64) * self.samples

    def seconds(self, samples) -> np.ndarray:
        """Episode time (s) of command sample indices."""
        return np.asarray(samples, dtype=np.int64) * self.period

    def tick_time(self, ticks) -> np.ndarray:
        """Episode time (s) at the start of tick ``ticks``: the observation instant."""
        return self.seconds(self.first_sample(ticks))
