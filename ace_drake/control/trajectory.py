"""The limits that commanded joint motion must respect (``CommandLimits``); the motion itself is
``robot.trajectory.JointTrajectory``, sampled at the robot interface's rate.

Shared by the spline QP (segments), the reset planner (resets and protective stops), the safety
supervisor (which streams them) and the collision checker. Joint vectors are in JOINT_NAMES order;
prismatic joints in m, revolute in rad.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from ace_drake.control.params import ControlParams
from ace_drake.robot.params import RobotLimits
from ace_drake.robot.trajectory import JointTrajectory


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
        shape = np.broadcast_shapes(v.shape, self.velocity.shape)
        flat = np.ascontiguousarray(np.broadcast_to(v, shape)).reshape(-1, self.velocity.shape[0])
        lower, upper = np.empty(flat.shape), np.empty(flat.shape)
        _acceleration_bounds(flat, self.velocity, self.acceleration, self.jerk, lower, upper)
        return lower.reshape(shape), upper.reshape(shape)

    def violations(self, trajectory: JointTrajectory, tolerance: float = 1e-9) -> dict[str, int]:
        """How many samples break each bound (position, velocity, acceleration), with a relative
        ``tolerance`` for round-off."""
        return {
            "position": int(np.sum(np.any((trajectory.q < self.lower - tolerance) | (trajectory.q > self.upper + tolerance), axis=-1))),
            "velocity": int(np.sum(np.any(np.abs(trajectory.v) > self.velocity * (1 + tolerance), axis=-1))),
            "acceleration": int(np.sum(np.any(np.abs(trajectory.a) > self.acceleration * (1 + tolerance), axis=-1))),
        }


@numba.njit(cache=True)
def acceleration_room(v, V, A, J):
    """The largest acceleration (per s^2) towards +v allowed at velocity v (per s) for a joint
    with limits V, A, J (``CommandLimits.acceleration_bounds``: min(A, sqrt(2 J max(V - v, 0))));
    NaN for a NaN v. The one definition, which the spline QP's kernel calls too."""
    if np.isnan(v):
        return np.nan
    return min(A, math.sqrt(2.0 * J * max(V - v, 0.0)))


@numba.njit(cache=True)
def _acceleration_bounds(v, V, A, J, lower, upper):
    """``CommandLimits.acceleration_bounds`` of velocities v (n, 8) into lower, upper (n, 8)."""
    for i in range(v.shape[0]):
        for j in range(v.shape[1]):
            lower[i, j] = -acceleration_room(-v[i, j], V[j], A[j], J[j])
            upper[i, j] = acceleration_room(v[i, j], V[j], A[j], J[j])
