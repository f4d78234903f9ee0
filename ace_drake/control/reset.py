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
``sample_profiles`` evaluates them for all samples and joints in one compiled loop.

Position limits. Ruckig (community version) does not enforce position limits, so a reset or stop
stays within [lower, upper] only if it starts where a jerk-limited stop can: ``is_reset_safe``.
That set is the controller's control-invariant set (braking at stop_fraction of the acceleration
limit after reaction_time) taken after the start's acceleration has been ramped out at the jerk
limit (``stop_pad``): with a finite jerk J, a joint that ends a segment at velocity v with
acceleration a towards a limit keeps accelerating for a / J, and one at the velocity limit with
a > 0 overshoots it by a^2 / (2 J). The property tests in ``tests/test_reset.py`` check that
resets and stops from that set's boundary stay within all limits, and show by example that the
set without the ramp does not suffice. (``feasible_set.invariant_bounds`` pads for the worst
terminal acceleration A ramped out over max(knot period, jerk_time), and the spline QP bounds the
terminal acceleration by ``CommandLimits.acceleration_bounds``: every mapped state is a safe start,
tests/test_action_mapping.py.)

Ruckig 0.19 fails to find a profile for some nearly degenerate joints (within ~1e-8 of the target
with a small velocity and acceleration); ``plan_reset`` then stops first and resets from rest
(``plan_stop_then_reset``), which it solves reliably and which stays within the same set.

Joint vectors are (8,) in JOINT_NAMES order; prismatic joints in m, revolute in rad.
"""

from __future__ import annotations

import array
import atexit
import math
import weakref

import numba
import numpy as np
import ruckig

from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import JOINT_NAMES
from ace_drake.robot.trajectory import JointTrajectory

_DOFS = len(JOINT_NAMES)
_SAMPLING_BLOCK = 8  # rows that ResetPlanner.plan_reset_batch samples together
_SUCCESS = (ruckig.Result.Working, ruckig.Result.Finished)


# Ruckig's numbers per joint as sample_profiles reads them: t (0-6), j (7-13), p (14-21),
# v (22-29), a (30-37), then 0, the end position and inf (38-40).
_ZERO, _END, _INF = 38, 39, 40
_ROW = _INF + 1
_PROFILE_END = 21  # p[7]
# Each joint's ten constant-jerk pieces (two brake phases, seven profile phases, the hold after the
# profile) as five fields: the duration of the piece before (summed into the piece's start), and
# the position, velocity, acceleration and jerk the piece starts with. Without a brake, the brake
# pieces have zero duration, so (a sample belongs to the last piece that starts at or before it)
# they get no samples and their values never matter.
_PIECES = 10
_PIECE_MAP = np.array(
    [
        [_ZERO, _ZERO, _ZERO, *range(0, 7)],  # duration of the piece before
        [14, 14, *range(14, 22)],  # position at the piece's start
        [22, 22, *range(22, 30)],  # velocity
        [30, 30, *range(30, 38)],  # acceleration
        [_ZERO, _ZERO, *range(7, 14), _ZERO],  # jerk over the piece
    ]
)
# At rest after the profile: the hold piece starts at the end position with v = a = 0.
_PIECE_MAP_REST = _PIECE_MAP.copy()
_PIECE_MAP_REST[1:4, -1] = (_END, _ZERO, _ZERO)
_DURATION_MAP = np.array([_ZERO, _ZERO, _ZERO, *range(0, 7), _INF])  # cumulative sum: piece starts, inf


def sample_profiles(profiles, times: np.ndarray, at_rest: bool = False, final: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations (len(times), n) of Ruckig profiles at ``times``.

    ``profiles`` is one section of ``ruckig.Trajectory.profiles`` (a list of n ``ruckig.Profile``),
    ``times`` (k,) sorted times in s from the trajectory's start. Reproduces
    ``Trajectory.at_time``: within the brake pre-trajectory (``Profile.brake``: two constant-jerk
    phases of durations ``brake.t`` and jerks ``brake.j`` from ``brake.p``, ``.v``, ``.a``, in all
    ``brake.duration`` s), then the seven phases of the profile (durations ``Profile.t``, jerks
    ``.j``, starting from ``.p``, ``.v``, ``.a``), then constant acceleration from the profile's
    end state (``.p[7]``, ``.v[7]``, ``.a[7]``). With ``at_rest``, a joint whose profile has ended
    is at rest instead (v = a = 0 exactly), where its profile ends or at ``final`` (n,) if given.
    With ``final``, each joint's positions are also shifted by (final - p[7]) t / t_end (t_end:
    when its profile ends; only where |final - p[7]| > 1e-12) so that they reach ``final``
    continuously: Ruckig ends a profile within its precision (1e-8) of the target, e.g. 7e-9 rad
    short after a 1.2 s slow cruise, which would otherwise put the samples just before the end
    past a target on a position limit. The arrays returned are transposed views of (n, k) arrays.
    """
    if final is not None and not at_rest:
        raise ValueError("sample_profiles: final is only used with at_rest=True")
    n = len(profiles)
    numbers: list[float] = []
    brakes: list[tuple[int, object]] = []
    _profile_numbers(profiles, None if final is None else np.asarray(final, dtype=float).tolist(), numbers, brakes, 0)
    times = np.asarray(times, dtype=float)
    q, v, a = _sample_numbers(numbers, brakes, n, times, np.full(n, times.size), at_rest, final is not None)
    return q.reshape(n, -1).T, v.reshape(n, -1).T, a.reshape(n, -1).T


def _profile_numbers(profiles, ends: list[float] | None, numbers: list[float], brakes: list, first_dof: int) -> None:
    """Appends the numbers of ``profiles`` (one trajectory's joints) to ``numbers`` in
    ``sample_profiles``'s layout (``_ROW`` per joint; ``ends``: the final positions, or None for
    where the profiles end) and (joint index + first_dof, brake) to ``brakes`` for each joint with
    a brake pre-trajectory."""
    for dof, profile in enumerate(profiles):
        numbers += profile.t
        numbers += profile.j
        positions = profile.p
        numbers += positions
        numbers += profile.v
        numbers += profile.a
        numbers += (0.0, positions[7] if ends is None else ends[dof], math.inf)
        brake = profile.brake
        if brake.duration > 0.0:
            brakes.append((first_dof + dof, brake))


def _sample_numbers(numbers: list[float], brakes: list, n: int, times: np.ndarray, lengths: np.ndarray, at_rest: bool, shift: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of n joints' profiles (``_profile_numbers``) at times[:lengths[i]] for joint i
    (times sorted, s): q, v, a flat, joint after joint (sum(lengths),). ``shift``: move each
    joint's positions onto its final position (``sample_profiles``). One compiled loop
    (``_sample_pieces``)."""
    flat = np.frombuffer(array.array("d", numbers))
    brake_dofs, brake_values = _NO_BRAKE_DOFS, _NO_BRAKES
    if brakes:
        brake_dofs = np.array([dof for dof, _ in brakes], dtype=np.int64)
        brake_values = np.array([(*brake.t, *brake.p, *brake.v, *brake.a, *brake.j) for _, brake in brakes], dtype=float)
    return _sample_pieces(flat, _PIECE_MAP_REST if at_rest else _PIECE_MAP, _DURATION_MAP, brake_dofs, brake_values, np.asarray(times, dtype=float),
                          np.asarray(lengths, dtype=np.int64), shift)


_NO_BRAKE_DOFS, _NO_BRAKES = np.empty(0, dtype=np.int64), np.empty((0, 10))  # _sample_numbers without brakes


@numba.njit(cache=True)
def _sample_pieces(flat, piece_map, duration_map, brake_dofs, brake_values, times, lengths, shift):
    """``_sample_numbers`` (returns its q, v, a): joint i's ten constant-jerk pieces
    (``_PIECE_MAP``) from its ``_ROW`` numbers in ``flat`` (for the joints ``brake_dofs``, the
    brake phases' t, p, v, a, j from ``brake_values`` instead): piece k starts at the sum of the
    durations before it and covers the samples from the first at or after its start to the first
    at or after the next's; at time dt into it, a = a0 + j dt, v = v0 + dt (a0 + j dt / 2),
    q = p0 + dt (v0 + dt (a0 / 2 + j dt / 6)). With ``shift``, a joint whose final position
    differs from its profile's end by more than 1e-12 has its positions moved by that difference
    times min(t / t_end, 1) before t_end."""
    pieces = piece_map.shape[1]
    q, v, a = np.empty(lengths.sum()), np.empty(lengths.sum()), np.empty(lengths.sum())
    brake_of = np.full(lengths.shape[0], -1)  # each joint's row of brake_values, -1 without a brake
    for index in range(brake_dofs.shape[0]):
        brake_of[brake_dofs[index]] = index
    starts = np.empty(pieces + 1)
    first = np.empty(pieces + 1, dtype=np.int64)
    offset = 0
    for i in range(lengths.shape[0]):
        base, length, brake = i * _ROW, lengths[i], brake_of[i]
        total = 0.0
        for k in range(pieces + 1):  # the pieces' starts: a cumulative sum of the durations
            duration = brake_values[brake, k - 1] if brake >= 0 and (k == 1 or k == 2) else flat[base + duration_map[k]]
            total = duration if k == 0 else total + duration
            starts[k] = total
            first[k] = min(np.searchsorted(times, total), length)
        for k in range(pieces):
            start = starts[k]
            if brake >= 0 and k < 2:
                p0, v0, a0, jerk = brake_values[brake, 2 + k], brake_values[brake, 4 + k], brake_values[brake, 6 + k], brake_values[brake, 8 + k]
            else:
                p0, v0, a0, jerk = flat[base + piece_map[1, k]], flat[base + piece_map[2, k]], flat[base + piece_map[3, k]], flat[base + piece_map[4, k]]
            for sample in range(first[k], first[k + 1]):
                dt = times[sample] - start
                jerk_dt = dt * jerk
                a[offset + sample] = a0 + jerk_dt
                v[offset + sample] = v0 + dt * (a0 + 0.5 * jerk_dt)
                q[offset + sample] = p0 + dt * (v0 + dt * (0.5 * a0 + jerk_dt * (1.0 / 6.0)))
        shortfall = flat[base + _END] - flat[base + _PROFILE_END]  # final - p[7]
        if shift and abs(shortfall) > 1e-12:  # round-off below that is left alone
            end = starts[pieces - 1]  # where the profile ends
            for sample in range(length):
                t = times[sample]
                progress = min(t / (end if end > 0.0 else 1.0), 1.0)
                q[offset + sample] += shortfall * (progress if t < end else 0.0)
        offset += length
    return q, v, a


def stop_pad(v, a, limits: CommandLimits, control: ControlParams) -> np.ndarray:
    """The room (..., 8), rad or m, that a joint moving at v (per s) with acceleration a (per s^2)
    must keep below its upper position limit for a protective stop or reset to stay within it.

    The controller's control-invariant set (``ControlParams``: stop_fraction, reaction_time)
    keeps q + v tau + v^2 / (2 A_s) <= upper for v > 0: a stop that starts braking at once. With a
    jerk limit J (``limits.jerk``) an acceleration a > 0 towards the limit is first ramped out
    over t1 = a / J, during which the joint travels v t1 + a t1^2 / 3 and speeds up to
    v_e = v + a^2 / (2 J); so the pad is that condition at the end of the ramp,

        pad = max(v, 0) t1 + a t1^2 / 3 + max(v_e, 0) tau + max(v_e, 0)^2 / (2 A_s),  a = max(a, 0),

    which is the original for a <= 0. It bounds the time-optimal jerk-limited stop: from
    (v_e, 0) that travels v_e^2 / (2 A) + v_e A / (2 J) once A is reached and v_e sqrt(v_e / J)
    before (<= the former), within v_e tau + v_e^2 / (2 A_s) since A_s <= A, as long as
    A / (2 J) = jerk_time / 2 <= tau (true of the defaults, 1 ms and 6 ms; otherwise A / (2 J)
    replaces tau). The lower limit needs stop_pad(-v, -a).
    """
    v, a = np.asarray(v, dtype=float), np.asarray(a, dtype=float)
    push = np.maximum(a, 0.0)
    ramp = push / limits.jerk  # t1
    moving = np.maximum(v + 0.5 * push * ramp, 0.0)  # max(v_e, 0)
    braking = control.stop_fraction * limits.acceleration
    reaction = np.maximum(control.reaction_time, 0.5 * limits.acceleration / limits.jerk)
    return np.maximum(v, 0.0) * ramp + push * ramp * ramp / 3.0 + moving * reaction + moving**2 / (2.0 * braking)


def is_reset_safe(q, v, a, limits: CommandLimits, control: ControlParams, tolerance: float = 1e-9) -> np.ndarray:
    """Whether each joint's state (q, v, a) (..., 8) lies in the set from which ``plan_stop`` and
    ``plan_reset`` (to any target within the limits) keep positions, velocities and accelerations
    within ``limits`` (tests/test_reset.py checks it on the set's boundary): |a| <= A; the
    velocity after ramping a out at the jerk limit, v + a |a| / (2 J), within [-V, V] (else the
    jerk-limited motion overshoots V by up to A^2 / (2 J)); and q + stop_pad(v, a) <= upper,
    q - stop_pad(-v, -a) >= lower (with |v| <= V, |a| <= A). A sufficient condition: like the
    controller's set it assumes braking at stop_fraction A after reaction_time, where the stop
    brakes at A at once. ``tolerance`` is absolute, in the units of each bound."""
    q, v, a = (np.asarray(x, dtype=float) for x in (q, v, a))
    ramped_velocity = v + a * np.abs(a) / (2.0 * limits.jerk)
    return (
        (np.abs(a) <= limits.acceleration + tolerance)
        & (np.abs(v) <= limits.velocity + tolerance)
        & (np.abs(ramped_velocity) <= limits.velocity + tolerance)
        & (q + stop_pad(v, a, limits, control) <= limits.upper + tolerance)
        & (q - stop_pad(-v, -a, limits, control) >= limits.lower - tolerance)
    )


class RuckigFailure(RuntimeError):
    """Ruckig rejected an input or found no trajectory; the message gives Ruckig's result or error."""


# Drake never frees Python systems in built diagrams (Drake 1.51), so planners held by them live
# until exit, where nanobind would report their Ruckig objects as leaked: release them first.
_LIVE_PLANNERS: "weakref.WeakSet[ResetPlanner]" = weakref.WeakSet()


@atexit.register
def _release_ruckig_objects() -> None:
    for planner in list(_LIVE_PLANNERS):
        planner._otg = planner._trajectory = planner._reset_input = planner._stop_input = None


class ResetPlanner:
    """Plans resets and protective stops for one set of limits and a sample period, reusing one
    Ruckig instance, its inputs and its trajectory across calls (the supervisor plans one reset
    every 32 ms segment inside a 2 ms control step).

    limits: the command limits (velocity, acceleration, jerk are used; position limits are not
    enforced by Ruckig, see the module docstring); period: the sample period, s (0.001 at 1 kHz).

    After each plan, ``duration`` is its unrounded duration, s, and ``fell_back`` whether a reset
    had to stop first (``plan_reset``). A plan longer than ``max_duration`` s (a start far outside
    the limits) raises RuntimeError rather than filling memory with samples.
    """

    max_duration = 60.0

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
        self.fell_back = False
        self._times = np.arange(1001) * self.period  # sample times, grown on demand
        self._lower = np.asarray(limits.lower, dtype=float)
        self._upper = np.asarray(limits.upper, dtype=float)
        self._otg = ruckig.Ruckig(_DOFS)
        self._trajectory = ruckig.Trajectory(_DOFS)
        self._reset_input = self._input(ruckig.ControlInterface.Position, ruckig.Synchronization.Time)
        self._stop_input = self._input(ruckig.ControlInterface.Velocity, ruckig.Synchronization.No)
        _LIVE_PLANNERS.add(self)

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
        within them by Ruckig's brake pre-trajectory (jerk-limited, so not instantly).

        Ruckig 0.19 fails on some nearly degenerate joints (a joint within ~1e-8 of its target with
        a small velocity and acceleration: about one in five such states). Then the reset is
        ``plan_stop_then_reset`` instead, which Ruckig solves reliably (``fell_back`` is True)."""
        state = self._validated("plan_reset", ("q", "v", "a", "q_target"), (q, v, a, q_target))
        self._check_target("plan_reset", state[3])
        inp = self._reset_input
        # (lists convert to Ruckig's vectors ten times faster than NumPy rows)
        inp.current_position, inp.current_velocity, inp.current_acceleration, inp.target_position = state.tolist()
        try:
            self._calculate("plan_reset", inp)
        except RuckigFailure:
            return self._stop_then_reset(state)
        self.fell_back = False
        return self._sample(state, state[3])

    def plan_reset_batch(self, q, v, a, q_target) -> tuple[list[JointTrajectory | None], list[str]]:
        """``plan_reset`` for B starts (q, v, a) (B, 8) each, to q_target (8,) or (B, 8): one
        Ruckig plan per row, all sampled at once. Returns the trajectories (B,) (each equal to
        ``plan_reset`` of its row; None where it failed) and the failures' messages (B,) ("" for
        a plan; else the RuntimeError ``plan_reset`` would raise, e.g. a plan over
        ``max_duration``). Bad input (shapes, non-finite values, a target outside the position
        limits) raises ValueError as ``plan_reset`` does, for the batch."""
        q, v, a = (np.asarray(x, dtype=float) for x in (q, v, a))
        if q.ndim != 2:
            raise ValueError(f"plan_reset_batch: q, v, a must be (B, {_DOFS}), got shape {q.shape}")
        states = None
        if q.shape[1:] == (_DOFS,) and v.shape == q.shape and a.shape == q.shape and np.shape(q_target) in ((_DOFS,), q.shape):
            states = np.empty((q.shape[0], 4, _DOFS))  # (B, 4, 8): q, v, a, target
            states[:, 0], states[:, 1], states[:, 2], states[:, 3] = q, v, a, np.asarray(q_target, dtype=float)
        if states is None or not np.isfinite(states).all():
            for row in range(q.shape[0]):  # the first bad vector raises, named
                self._validated("plan_reset", ("q", "v", "a", "q_target"), (q[row], v[row], a[row], q_target[row] if np.ndim(q_target) == 2 else q_target))
            raise ValueError(f"plan_reset_batch: q, v, a, q_target must be (B, {_DOFS}) finite values (q_target may be ({_DOFS},)), got shapes {q.shape}, {v.shape}, {a.shape}, {np.shape(q_target)}")
        inside = (self._lower <= states[:, 3]) & (states[:, 3] <= self._upper)
        if not inside.all():
            self._check_target("plan_reset", states[np.flatnonzero(~inside.all(axis=-1))[0], 3])
        rows = states.shape[0]
        plans: list[JointTrajectory | None] = [None] * rows
        errors = [""] * rows
        sampled, lengths, numbers, brakes = [], [], [], []
        inp = self._reset_input
        for row, (state, values) in enumerate(zip(states, states.tolist())):
            inp.current_position, inp.current_velocity, inp.current_acceleration, inp.target_position = values
            try:
                try:
                    self._calculate("plan_reset", inp)
                except RuckigFailure:
                    plans[row] = self._stop_then_reset(state)
                    continue
            except RuntimeError as error:
                errors[row] = str(error)
                continue
            self.fell_back = False
            samples = self._sample_count(state, state[3])
            _profile_numbers(self._trajectory.profiles[0], values[3], numbers, brakes, _DOFS * len(sampled))
            sampled.append(row)
            lengths.append(samples + 1)
        # Sampled in blocks of rows small enough for the samples to stay in cache.
        for block in range(0, len(sampled), _SAMPLING_BLOCK):
            block_rows, block_lengths = sampled[block : block + _SAMPLING_BLOCK], lengths[block : block + _SAMPLING_BLOCK]
            block_numbers = numbers[block * _DOFS * _ROW : (block + len(block_rows)) * _DOFS * _ROW]
            block_brakes = [(dof - block * _DOFS, brake) for dof, brake in brakes if block * _DOFS <= dof < (block + len(block_rows)) * _DOFS]
            longest = max(block_lengths)
            if longest > self._times.size:
                self._times = np.arange(2 * longest) * self.period
            per_joint = np.repeat(np.array(block_lengths), _DOFS)
            flat = _sample_numbers(block_numbers, block_brakes, per_joint.size, self._times[:longest], per_joint, True, True)
            start = 0
            for row, length in zip(block_rows, block_lengths):
                q_row, v_row, a_row = (x[start : start + _DOFS * length].reshape(_DOFS, length).T for x in flat)
                start += _DOFS * length
                plans[row] = self._finished(states[row], states[row, 3], q_row, v_row, a_row)
        return plans, errors

    def plan_stop(self, q, v, a) -> JointTrajectory:
        """The protective stop from (q, v, a) (8,) each (rad or m, per s, per s^2): every joint
        independently (no synchronisation) brings its velocity and acceleration to zero as fast as
        its acceleration and jerk limits allow (Ruckig's velocity interface), sampled every
        ``period`` s from t = 0 (row 0 is the start state exactly); each joint is held at rest
        where it stopped, and the last row is at rest (v = a = 0 exactly). Positions are not
        limited: from a state where ``is_reset_safe`` holds they stay within them."""
        state = self._validated("plan_stop", ("q", "v", "a"), (q, v, a))
        self.fell_back = False
        return self._stop(state)

    def plan_stop_then_reset(self, q, v, a, q_target) -> JointTrajectory:
        """``plan_stop`` from (q, v, a), then from where it stopped the time-synchronised reset
        from rest to q_target (8,) at rest (``plan_reset``): after a protective stop, or the
        fallback of ``plan_reset``. Slower than the direct reset when joints move towards their
        targets; ``duration`` is the stop's, rounded to whole periods, plus the reset's."""
        state = self._validated("plan_stop_then_reset", ("q", "v", "a", "q_target"), (q, v, a, q_target))
        self._check_target("plan_stop_then_reset", state[3])
        return self._stop_then_reset(state)

    def _stop(self, state: np.ndarray) -> JointTrajectory:
        inp = self._stop_input
        inp.current_position, inp.current_velocity, inp.current_acceleration = state[:3].tolist()
        self._calculate("plan_stop", inp)
        return self._sample(state, None)

    def _stop_then_reset(self, state: np.ndarray) -> JointTrajectory:
        stop = self._stop(state)
        at_rest = np.stack([stop.q[-1], np.zeros(_DOFS), np.zeros(_DOFS), state[3]])
        inp = self._reset_input
        inp.current_position, inp.current_velocity, inp.current_acceleration, inp.target_position = at_rest.tolist()
        self._calculate("plan_reset (from rest, after a stop)", inp)
        reset = self._sample(at_rest, state[3])
        self.duration += stop.duration
        self.fell_back = True
        return stop.then(reset)

    def _check_target(self, caller: str, q_target: np.ndarray) -> None:
        if not ((self._lower <= q_target) & (q_target <= self._upper)).all():
            outside = np.flatnonzero((q_target < self._lower) | (q_target > self._upper))
            names = ", ".join(f"{JOINT_NAMES[i]}={q_target[i]} not in [{self._lower[i]}, {self._upper[i]}]" for i in outside)
            raise ValueError(f"{caller}: q_target outside the position limits: {names}")

    @staticmethod
    def _validated(caller: str, names: tuple[str, ...], values: tuple) -> np.ndarray:
        """The joint vectors stacked (len(names), 8); ValueError naming the first bad one."""
        try:
            state = np.array(values, dtype=float)
        except (TypeError, ValueError):
            state = None
        if state is None or state.shape != (len(names), _DOFS) or not np.isfinite(state).all():
            for name, value in zip(names, values):
                _joint_vector(caller, name, value)
        return state

    def _calculate(self, caller: str, inp: ruckig.InputParameter) -> None:
        """Ruckig's trajectory for ``inp`` into self._trajectory and self.duration."""
        try:
            result = self._otg.calculate(inp, self._trajectory)
        except ruckig.RuckigError as error:
            raise RuckigFailure(f"{caller}: Ruckig rejected the input ({str(error).strip()})") from None
        if result not in _SUCCESS:
            raise RuckigFailure(f"{caller}: Ruckig failed with {result} for q={inp.current_position}, v={inp.current_velocity}, a={inp.current_acceleration}, target={inp.target_position}")
        self.duration = self._trajectory.duration
        if not self.duration <= self.max_duration:
            raise RuntimeError(f"{caller}: Ruckig's trajectory lasts {self.duration} s, more than max_duration = {self.max_duration} s, from q={inp.current_position}, v={inp.current_velocity}, a={inp.current_acceleration}")

    def _sample(self, state: np.ndarray, q_final: np.ndarray | None) -> JointTrajectory:
        """The last calculated trajectory from state[:3] = (q, v, a), sampled every period; joints
        past their own end are at rest at q_final (the target; None: where their profile ends)."""
        samples = self._sample_count(state, q_final)
        if samples >= self._times.size:
            self._times = np.arange(2 * samples + 2) * self.period
        q, v, a = sample_profiles(self._trajectory.profiles[0], self._times[: samples + 1], True, q_final)
        return self._finished(state, q_final, q, v, a)

    def _sample_count(self, state: np.ndarray, q_final: np.ndarray | None) -> int:
        """The samples after the start of the last calculated trajectory: its duration rounded up
        to whole periods, and at least one to move to a q_final that differs from the start."""
        samples = math.ceil(self.duration / self.period - 1e-9)
        if samples == 0 and q_final is not None and not np.array_equal(state[0], q_final):
            samples = 1
        return samples

    def _finished(self, state: np.ndarray, q_final: np.ndarray | None, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> JointTrajectory:
        """Samples (k + 1, 8) as a JointTrajectory that starts exactly at state[:3] and, after at
        least one sample, ends exactly at rest (at q_final unless that is None)."""
        period, samples = self.period, q.shape[0] - 1
        q[0], v[0], a[0] = state[0], state[1], state[2]
        if samples > 0:
            if q_final is not None:
                q[-1] = q_final
            v[-1] = 0.0
            a[-1] = 0.0
        return JointTrajectory(period, q, v, a)


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
    vector = np.asarray(value, dtype=float)
    if vector.shape != (_DOFS,):
        raise ValueError(f"{caller}: {name} must have shape ({_DOFS},) ({', '.join(JOINT_NAMES)}), got shape {vector.shape}")
    if not np.all(np.isfinite(vector)):
        raise ValueError(f"{caller}: {name} must be finite, got {vector}")
    return vector
