"""A joint motion sampled at a fixed period: what the control stack plans, the collision checker
checks and the robot interface plays (q, v, a per sample; rad or m, per s, per s^2)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ace_drake.robot.params import JOINT_NAMES


@dataclasses.dataclass(frozen=True)
class JointTrajectory:
    """Joint motion sampled every ``period`` s from its start: row k of q, v, a (n + 1, 8) is the
    position (rad or m), velocity (per s) and acceleration (per s^2) at time k * period; row 0 is
    the state it starts from."""

    period: float
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray

    def __post_init__(self) -> None:
        shape = np.shape(self.q)
        if len(shape) != 2 or shape[1] != len(JOINT_NAMES) or shape[0] < 1 or np.shape(self.v) != shape or np.shape(self.a) != shape:
            raise ValueError(f"JointTrajectory: q, v, a must share a shape (n + 1, {len(JOINT_NAMES)}), got {shape}, {np.shape(self.v)}, {np.shape(self.a)}")

    @property
    def samples(self) -> int:
        """The number of samples after the start (n)."""
        return self.q.shape[0] - 1

    @property
    def duration(self) -> float:
        """n * period, s."""
        return self.samples * self.period

    def state(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, v, a) at sample ``index`` (negative counts from the end)."""
        return self.q[index], self.v[index], self.a[index]

    def then(self, other: "JointTrajectory") -> "JointTrajectory":
        """This trajectory followed by ``other``, which starts where this one ends (its row 0 is
        dropped as a duplicate of this one's last row)."""
        if other.period != self.period:
            raise ValueError(f"JointTrajectory.then: periods differ ({self.period} s and {other.period} s)")
        return JointTrajectory(
            self.period,
            np.concatenate([self.q, other.q[1:]]),
            np.concatenate([self.v, other.v[1:]]),
            np.concatenate([self.a, other.a[1:]]),
        )

    def from_sample(self, index: int) -> "JointTrajectory":
        """The rest of this trajectory from sample ``index`` on (that sample becomes row 0)."""
        return JointTrajectory(self.period, self.q[index:], self.v[index:], self.a[index:])

    def until(self, index: int) -> "JointTrajectory":
        """This trajectory up to sample ``index`` (at most its end), that sample included."""
        end = min(index, self.samples) + 1
        return JointTrajectory(self.period, self.q[:end], self.v[:end], self.a[:end])

    @staticmethod
    def stationary(q: np.ndarray, period: float) -> "JointTrajectory":
        """Standing still at q: a single sample."""
        q = np.asarray(q, dtype=float)[None, :]
        return JointTrajectory(period, q.copy(), np.zeros_like(q), np.zeros_like(q))
