"""Reset trajectories and protective stops: time-optimal, jerk-limited joint motions (Ruckig).

For every 32 ms segment the controller plans, a reset trajectory moves the robot from the
segment's terminal state (q, v, a) to a stationary reset configuration; it is executed when the
episode ends, and the previous one when a collision is predicted (paper, Methods *Reset
trajectories*). The paper plans resets with a near-time-optimal MPC; this module uses the Ruckig
library, which is time-optimal and jerk-limited and is what the authors' robot side runs
(``../shared/paper/notes.md``):

- ``plan_reset``: all eight joints time-synchronised to arrive together at the target at rest, as
  fast as the slowest joint allows within the velocity, acceleration and jerk limits;
- ``plan_stop``: the protective stop (a light curtain, a lost policy): every joint independently
  brings its velocity and acceleration to zero as fast as its acceleration and jerk limits allow
  (Ruckig's velocity interface), wherever that leaves it.

Both are sampled every ``period`` s into a ``JointTrajectory`` without calling
``Trajectory.at_time`` per sample: each joint's Ruckig profile is a chain of at most ten
constant-jerk pieces (two of the brake pre-trajectory that Ruckig prepends when the start state
will exceed a limit, the seven phases of the profile, then a hold at constant acceleration), and
``sample_profiles`` evaluates them for all samples and joints at once with NumPy.

Position limits. Ruckig (community version) does not enforce position limits. A reset or stop
stays within [lower, upper] when it starts in the controller's control-invariant set: the
property tests in ``tests/test_reset.py`` check it on the boundary of that set, and
``stop_margin`` gives the exact worst-case travel of a protective stop for a state. With a finite
jerk J a joint that ends a segment at velocity v with acceleration a towards a limit keeps
accelerating for |a| / J, so the set must account for a: see ``jerk_limited_stop``.

Joint vectors are (8,) in JOINT_NAMES order; prismatic joints in m, revolute in rad.
"""

from __future__ import annotations

import math

import numpy as np
import ruckig

from ace_drake.config import JOINT_NAMES
from ace_drake.control.trajectory import CommandLimits, JointTrajectory

_DOFS = len(JOINT_NAMES)
# Constant-jerk pieces per joint: 2 brake phases, 7 profile phases, 1 hold after the profile.
_PIECES = 10
_SUCCESS = (ruckig.Result.Working, ruckig.Result.Finished)


def sample_profiles(profiles, times: np.ndarray, final: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations (len(times), n) of Ruckig profiles at ``times``.

    ``profiles`` is one section of ``ruckig.Trajectory.profiles`` (a list of n ``ruckig.Profile``),
    ``times`` (k,) sorted times in s from the trajectory's start. Reproduces
    ``Trajectory.at_time``: within the brake pre-trajectory (``Profile.brake``: two constant-jerk
    phases of durations ``brake.t`` and jerks ``brake.j`` from ``brake.p``, ``.v``, ``.a``, in all
    ``brake.duration`` s), then the seven phases of the profile (durations ``Profile.t``, jerks
    ``.j``, starting from ``.p``, ``.v``, ``.a``), then constant acceleration from the profile's end
    state (``.p[7]``, ``.v[7]``, ``.a[7]``). With ``final`` (n,), a joint whose profile has ended is
    at rest at ``final`` instead (v = a = 0 exactly). The arrays are transposed views of (n, k)
    arrays (Fortran order).
    """
    n = len(profiles)
    # One flat list of each joint's 38 numbers: t (7), j (7), p (8), v (8), a (8).
    numbers: list[float] = []
    brake_joints = []
    for dof, profile in enumerate(profiles):
        numbers += profile.t
        numbers += profile.j
        numbers += profile.p
        numbers += profile.v
        numbers += profile.a
        brake = profile.brake
        if brake.duration > 0.0:
            brake_joints.append((dof, brake))
    table = np.array(numbers).reshape(n, 38)
    durations, jerks = table[:, 0:7], table[:, 7:14]
    positions, velocities, accelerations = table[:, 14:22], table[:, 22:30], table[:, 30:38]

    # Each joint's constant-jerk pieces (n, 10): brake phases 0-1, profile phases 2-8, hold 9.
    start = np.zeros((n, _PIECES))
    piece_p = np.empty((n, _PIECES))
    piece_v = np.empty((n, _PIECES))
    piece_a = np.empty((n, _PIECES))
    piece_j = np.zeros((n, _PIECES))
    ends = np.cumsum(durations, axis=1)  # Ruckig's t_sum
    # Without a brake both brake pieces start at 0 like phase 0 and get no samples (a sample
    # belongs to the last piece starting at or before it), so their values never matter.
    piece_p[:, 2:] = positions
    piece_v[:, 2:] = velocities
    piece_a[:, 2:] = accelerations
    piece_j[:, 2:9] = jerks
    piece_p[:, :2] = positions[:, :1]
    piece_v[:, :2] = velocities[:, :1]
    piece_a[:, :2] = accelerations[:, :1]
    for dof, brake in brake_joints:
        start[dof, 1] = brake.t[0]
        start[dof, 2:] = brake.duration
        piece_p[dof, :2] = brake.p
        piece_v[dof, :2] = brake.v
        piece_a[dof, :2] = brake.a
        piece_j[dof, :2] = brake.j
    start[:, 3:] += ends
    if final is not None:
        piece_p[:, 9] = final
        piece_v[:, 9] = 0.0
        piece_a[:, 9] = 0.0

    # Samples per piece: times is sorted, so piece k of a joint gets the samples from the first
    # at or after its start up to the first at or after the next piece's start.
    times = np.asarray(times, dtype=float)
    first = np.searchsorted(times, start, side="left")  # (n, 10)
    counts = np.empty_like(first)
    counts[:, :-1] = first[:, 1:] - first[:, :-1]
    counts[:, -1] = times.size - first[:, -1]
    counts = counts.ravel()
    dt = np.tile(times, n) - np.repeat(start.ravel(), counts)
    p0, v0, a0, j = (np.repeat(x.ravel(), counts) for x in (piece_p, piece_v, piece_a, piece_j))
    j_half = 0.5 * j
    a = a0 + dt * j
    v = v0 + dt * (a0 + dt * j_half)
    q = p0 + dt * (v0 + dt * (0.5 * a0 + dt * (j / 6.0)))
    return q.reshape(n, -1).T, v.reshape(n, -1).T, a.reshape(n, -1).T


def jerk_limited_stop(v: np.ndarray, a: np.ndarray, acceleration: np.ndarray, jerk: np.ndarray) -> np.ndarray:
    """An upper bound on the distance (same sign convention as v, towards +) that a time-optimal
    jerk-limited stop from velocity v and acceleration a travels in the + direction, (..., 8).

    The stop first ramps a to zero at jerk -J (for a > 0) over t1 = a / J, reaching
    v_e = v + a^2 / (2 J) after v t1 + a t1^2 / 3, then brakes from v_e with an acceleration ramp
    of the same jerk: at most v_e^2 / (2 A) + v_e A / (2 J) (the exact distance is
    v_e^2 / (2 A) + v_e A / (2 J) once A is reached, v_e sqrt(v_e / J) before, and
    x^1.5 <= (x^2 + x) / 2). For a <= 0 the stop is at most the a = 0 one. Units: per s, per s^2,
    per s^3 in; rad or m out. The controller's invariant set keeps q + this <= upper."""
    v, a = np.asarray(v, dtype=float), np.asarray(a, dtype=float)
    push = np.maximum(a, 0.0)
    t1 = push / jerk
    v_end = v + push * t1 / 2.0
    ramp = np.maximum(v * t1 + push * t1 * t1 / 3.0, 0.0)
    brake_up = np.maximum(v_end, 0.0)
    return ramp + brake_up**2 / (2.0 * acceleration) + brake_up * acceleration / (2.0 * jerk)


class ResetPlanner:
    """Plans resets and protective stops for one set of limits and a sample period, reusing one
    Ruckig instance, its inputs and its trajectory across calls (the supervisor plans one reset
    every 32 ms segment inside a 2 ms control step).

    limits: the command limits (velocity, acceleration, jerk are used; position limits are not
    enforced by Ruckig, see the module docstring); period: the sample period, s (0.001 at 1 kHz).
    After each plan, ``duration`` is Ruckig's (unrounded) duration of it, s.
    """

    def __init__(self, limits: CommandLimits, period: float) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f"ResetPlanner: period must be a finite number > 0 s, got {period}")
        for name in ("velocity", "acceleration", "jerk", "lower", "upper"):
            value = np.asarray(getattr(limits, name), dtype=float)
            if value.shape != (_DOFS,) or not np.all(np.isfinite(value)):
                raise ValueError(f"ResetPlanner: limits.{name} must be {_DOFS} finite values, got {value}")
        for name in ("velocity", "acceleration", "jerk"):
            if not np.all(np.asarray(getattr(limits, name)) > 0.0):
                raise ValueError(f"ResetPlanner: limits.{name} must be > 0, got {getattr(limits, name)}")
        if not np.all(np.asarray(limits.lower) <= np.asarray(limits.upper)):
            raise ValueError(f"ResetPlanner: limits.lower must be <= limits.upper, got {limits.lower} and {limits.upper}")
        self.limits = limits
        self.period = float(period)
        self.duration = 0.0
        self._lower = np.asarray(limits.lower, dtype=float)
        self._upper = np.asarray(limits.upper, dtype=float)
        self._otg = ruckig.Ruckig(_DOFS)
        self._trajectory = ruckig.Trajectory(_DOFS)
        self._reset_input = self._input(ruckig.ControlInterface.Position, ruckig.Synchronization.Time)
        self._stop_input = self._input(ruckig.ControlInterface.Velocity, ruckig.Synchronization.No)

    def _input(self, interface, synchronization) -> ruckig.InputParameter:
        inp = ruckig.InputParameter(_DOFS)
        inp.max_velocity = np.asarray(self.limits.velocity, dtype=float)
        inp.max_acceleration = np.asarray(self.limits.acceleration, dtype=float)
        inp.max_jerk = np.asarray(self.limits.jerk, dtype=float)
        inp.target_velocity = np.zeros(_DOFS)
        inp.target_acceleration = np.zeros(_DOFS)
        inp.control_interface = interface
        inp.synchronization = synchronization
        return inp

    def plan_reset(self, q, v, a, q_target) -> JointTrajectory:
        """The time-synchronised, time-optimal jerk-limited trajectory from (q, v, a) (8,) each
        (rad or m, per s, per s^2) to q_target (8,) at rest, within the velocity, acceleration and
        jerk limits; sampled every ``period`` s from t = 0 (row 0 is the start state exactly).
        Ruckig's duration is rounded up to a whole number of periods and the remainder filled with
        the target at rest, so the last row is exactly (q_target, 0, 0). q_target must lie within
        the position limits; a start outside the velocity or acceleration limits is brought back
        within them by Ruckig's brake pre-trajectory (jerk-limited, so not instantly)."""
        q, v, a = self._state("plan_reset", q, v, a)
        q_target = _joint_vector("plan_reset", "q_target", q_target)
        outside = (q_target < self._lower) | (q_target > self._upper)
        if np.any(outside):
            names = ", ".join(f"{JOINT_NAMES[i]}={q_target[i]} not in [{self._lower[i]}, {self._upper[i]}]" for i in np.flatnonzero(outside))
            raise ValueError(f"plan_reset: q_target outside the position limits: {names}")
        inp = self._reset_input
        inp.current_position = q
        inp.current_velocity = v
        inp.current_acceleration = a
        inp.target_position = q_target
        self._calculate("plan_reset", inp)
        return self._sample(q, v, a, q_target)

    def plan_stop(self, q, v, a) -> JointTrajectory:
        """The protective stop from (q, v, a) (8,) each (rad or m, per s, per s^2): every joint
        independently (no synchronisation) brings its velocity and acceleration to zero as fast as
        its acceleration and jerk limits allow (Ruckig's velocity interface), sampled every
        ``period`` s from t = 0 (row 0 is the start state exactly); each joint is held at rest
        where it stopped, and the last row is at rest (v = a = 0 exactly). Positions are not
        limited: see ``jerk_limited_stop`` for how far a joint travels."""
        q, v, a = self._state("plan_stop", q, v, a)
        inp = self._stop_input
        inp.current_position = q
        inp.current_velocity = v
        inp.current_acceleration = a
        self._calculate("plan_stop", inp)
        return self._sample(q, v, a, None)

    def _state(self, caller: str, q, v, a) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _joint_vector(caller, "q", q), _joint_vector(caller, "v", v), _joint_vector(caller, "a", a)

    def _calculate(self, caller: str, inp: ruckig.InputParameter) -> None:
        try:
            result = self._otg.calculate(inp, self._trajectory)
        except ruckig.RuckigError as error:
            raise RuntimeError(f"{caller}: Ruckig rejected the input ({error}) for q={inp.current_position}, v={inp.current_velocity}, a={inp.current_acceleration}") from None
        if result not in _SUCCESS:
            raise RuntimeError(f"{caller}: Ruckig failed with {result} for q={inp.current_position}, v={inp.current_velocity}, a={inp.current_acceleration}")
        self.duration = self._trajectory.duration

    def _sample(self, q, v, a, q_final) -> JointTrajectory:
        """The last calculated trajectory sampled every period; joints past their own end are at
        rest at q_final (the target; None: where their profile ends)."""
        period = self.period
        samples = math.ceil(self.duration / period - 1e-9)
        profiles = self._trajectory.profiles[0]
        if q_final is None:
            q_final = np.array([profile.p[7] for profile in profiles])
        if samples == 0 and not np.array_equal(q, q_final):
            samples = 1
        q_s, v_s, a_s = sample_profiles(profiles, np.arange(samples + 1) * period, q_final)
        q_s[0], v_s[0], a_s[0] = q, v, a
        if samples > 0:
            q_s[-1], v_s[-1], a_s[-1] = q_final, 0.0, 0.0
        return JointTrajectory(period, q_s, v_s, a_s)


def plan_reset(q, v, a, q_target, limits: CommandLimits, period: float) -> JointTrajectory:
    """``ResetPlanner(limits, period).plan_reset(q, v, a, q_target)``: the time-synchronised,
    time-optimal jerk-limited trajectory to q_target at rest (see there). Keep a ``ResetPlanner``
    to plan repeatedly."""
    return ResetPlanner(limits, period).plan_reset(q, v, a, q_target)


def plan_stop(q, v, a, limits: CommandLimits, period: float) -> JointTrajectory:
    """``ResetPlanner(limits, period).plan_stop(q, v, a)``: the fastest stop within the
    acceleration and jerk limits, each joint on its own (see there)."""
    return ResetPlanner(limits, period).plan_stop(q, v, a)


def _joint_vector(caller: str, name: str, value) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape != (_DOFS,):
        raise ValueError(f"{caller}: {name} must have shape ({_DOFS},) ({', '.join(JOINT_NAMES)}), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{caller}: {name} must be finite, got {array}")
    return array
