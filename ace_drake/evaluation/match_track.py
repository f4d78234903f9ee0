"""What happened in one match, sampled on the match's own time line, for replays.

A ``MatchTrack`` holds the ball's centre and the robot's joint positions at increasing times, with
the points laid end to end (pauses between them) and a label for each point. The match runner
records it; ``analysis.match_replay.write_match_replay`` draws it. Plain NumPy.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ace_drake.robot.params import JOINT_NAMES


@dataclasses.dataclass(frozen=True)
class TrackPoint:
    """One point of the match: when it starts on the track's time line (s) and its label
    (e.g. "Point 3, game 1: 2-0, robot serves - robot won (double bounce)")."""

    start_time: float
    label: str

    def __post_init__(self) -> None:
        if not isinstance(self.start_time, (int, float, np.floating, np.integer)) or not math.isfinite(self.start_time):
            raise ValueError(f"TrackPoint.start_time: expected a finite time in s, got {self.start_time!r}")
        if not isinstance(self.label, str) or not self.label.strip():
            raise ValueError(f"TrackPoint.label: expected a non-empty string, got {self.label!r}")
        object.__setattr__(self, "start_time", float(self.start_time))


@dataclasses.dataclass(frozen=True, eq=False)
class MatchTrack:
    """A match sampled at N instants.

    times (N,): s, strictly increasing, times[0] >= 0 (points end to end, with pauses).
    ball (N, 3): the ball centre in world, m (DESIGN.md frame); a NaN row: no ball in play.
    q (N, 8): the robot's joint positions, JOINT_NAMES order, m and rad.
    points: one ``TrackPoint`` per point, start times increasing and within [times[0], times[-1]].

    The arrays are stored as read-only float64 copies.
    """

    times: np.ndarray
    ball: np.ndarray
    q: np.ndarray
    points: tuple[TrackPoint, ...] = ()

    def __post_init__(self) -> None:
        times = _frozen_array(self.times, "times")
        if times.ndim != 1 or times.size < 1:
            raise ValueError(f"MatchTrack.times: expected shape (N,) with N >= 1, got {times.shape}")
        if not np.all(np.isfinite(times)):
            raise ValueError("MatchTrack.times: all times must be finite")
        if times[0] < 0:
            raise ValueError(f"MatchTrack.times: must start at >= 0 s, got {times[0]}")
        if np.any(np.diff(times) <= 0):
            first = int(np.argmax(np.diff(times) <= 0))
            raise ValueError(f"MatchTrack.times: must be strictly increasing; times[{first + 1}] = {times[first + 1]} <= {times[first]}")
        n = times.size
        ball = _frozen_array(self.ball, "ball")
        if ball.shape != (n, 3):
            raise ValueError(f"MatchTrack.ball: expected shape ({n}, 3), got {ball.shape}")
        finite_rows = np.all(np.isfinite(ball), axis=1)
        nan_rows = np.all(np.isnan(ball), axis=1)
        if not np.all(finite_rows | nan_rows):
            row = int(np.argmax(~(finite_rows | nan_rows)))
            raise ValueError(f"MatchTrack.ball: row {row} is {ball[row]}; rows must be finite or all NaN (no ball)")
        q = _frozen_array(self.q, "q")
        if q.shape != (n, len(JOINT_NAMES)):
            raise ValueError(f"MatchTrack.q: expected shape ({n}, {len(JOINT_NAMES)}) ({', '.join(JOINT_NAMES)}), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError("MatchTrack.q: all joint positions must be finite")
        points = tuple(self.points)
        for index, point in enumerate(points):
            if not isinstance(point, TrackPoint):
                raise ValueError(f"MatchTrack.points[{index}]: expected a TrackPoint, got {type(point).__name__}")
            if not times[0] <= point.start_time <= times[-1]:
                raise ValueError(
                    f"MatchTrack.points[{index}].start_time: {point.start_time} s is outside the track [{times[0]}, {times[-1]}] s"
                )
            if index > 0 and point.start_time <= points[index - 1].start_time:
                raise ValueError(
                    f"MatchTrack.points[{index}].start_time: {point.start_time} s does not follow the previous point's {points[index - 1].start_time} s"
                )
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "ball", ball)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "points", points)

    @property
    def duration(self) -> float:
        """The track's last time, s."""
        return float(self.times[-1])

    def resampled(self, fps: float) -> MatchTrack:
        """The track at the instants k / fps (s) within [times[0], times[-1]] (at least times[0]),
        joint positions and ball interpolated linearly between the bracketing samples. The ball is
        NaN (hidden) wherever a bracketing sample is NaN, so a pause recorded as NaN rows stays
        hidden. Points are kept."""
        if not math.isfinite(fps) or fps <= 0:
            raise ValueError(f"MatchTrack.resampled: fps must be a positive number of frames per second, got {fps}")
        first, last = math.ceil(self.times[0] * fps - 1e-9), math.floor(self.times[-1] * fps + 1e-9)
        frame_times = np.arange(first, last + 1) / fps if last >= first else np.array([self.times[0]])
        frame_times = np.clip(frame_times, self.times[0], self.times[-1])
        before = np.clip(np.searchsorted(self.times, frame_times, side="right") - 1, 0, self.times.size - 1)
        after = np.minimum(before + 1, self.times.size - 1)
        span = self.times[after] - self.times[before]
        weight = np.divide(frame_times - self.times[before], span, out=np.zeros_like(span), where=span > 0)[:, None]
        q = (1 - weight) * self.q[before] + weight * self.q[after]
        with np.errstate(invalid="ignore"):
            mixed = (1 - weight) * self.ball[before] + weight * self.ball[after]
        ball = np.where(weight == 0, self.ball[before], mixed)
        return MatchTrack(frame_times, ball, q, self.points)


def _frozen_array(value, name: str) -> np.ndarray:
    """A read-only float64 copy of ``value``; ValueError naming the field if it is not numeric."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f"MatchTrack.{name}: expected an array of numbers ({error})") from None
    array.setflags(write=False)
    return array
