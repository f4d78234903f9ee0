"""Joint trajectories sampled at the robot interface's rate, and the limits commands must respect.

Shared by the spline QP (segments), the reset planner (resets and protective stops), the safety
supervisor (which streams them) and the collision checker. Joint vectors are in JOINT_NAMES order;
prismatic joints in m, revolute in rad.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ace_drake.config import JOINT_NAMES, ControlParams, RobotLimits


@dataclasses.dataclass(frozen=True)
class CommandLimits:
    """Per-joint bounds (8,) on commanded motion: position [lower, upper] (rad or m), symmetric
    velocity (per s) and acceleration (per s^2) bounds, and the jerk bound (per s^3) of resets."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray

    @staticmethod
    def from_config(limits: RobotLimits, control: ControlParams) -> "CommandLimits":
        """The hardware limits shrunk by the control margins (``ControlParams``)."""
        hardware = limits.as_arrays()
        acceleration = control.acceleration_fraction * hardware["acceleration"]
        return CommandLimits(
            lower=hardware["lower"] + control.position_margin,
            upper=hardware["upper"] - control.position_margin,
            velocity=control.velocity_fraction * hardware["velocity"],
            acceleration=acceleration,
            jerk=acceleration / control.jerk_time,
        )

    @staticmethod
    def hardware(limits: RobotLimits, jerk_time: float = ControlParams.jerk_time) -> "CommandLimits":
        """The robot's own limits, with no control margins (what the joints must respect)."""
        return CommandLimits.from_config(limits, ControlParams(position_margin=0.0, velocity_fraction=1.0, acceleration_fraction=1.0, jerk_time=jerk_time))

    def acceleration_bounds(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The accelerations (lower, upper) (..., 8) allowed at velocity v (..., 8): within the
        acceleration limit, and small enough that ramping them to zero at the jerk limit keeps
        |v| <= V (v + a^2 / (2 J) <= V for a > 0, mirrored), so that a reset or stop that starts
        there stays within the velocity limits."""
        v = np.asarray(v, dtype=float)
        upper = np.sqrt(2.0 * self.jerk * np.maximum(self.velocity - v, 0.0))
        lower = np.sqrt(2.0 * self.jerk * np.maximum(self.velocity + v, 0.0))
        return -np.minimum(self.acceleration, lower), np.minimum(self.acceleration, upper)

    def violations(self, trajectory: "JointTrajectory", tolerance: float = 1e-9) -> dict[str, int]:
        """How many samples break each bound (position, velocity, acceleration), with a relative
        ``tolerance`` for round-off."""
        return {
            "position": int(np.sum(np.any((trajectory.q < self.lower - tolerance) | (trajectory.q > self.upper + tolerance), axis=-1))),
            "velocity": int(np.sum(np.any(np.abs(trajectory.v) > self.velocity * (1 + tolerance), axis=-1))),
            "acceleration": int(np.sum(np.any(np.abs(trajectory.a) > self.acceleration * (1 + tolerance), axis=-1))),
        }


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
