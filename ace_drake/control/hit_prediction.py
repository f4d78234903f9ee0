"""The incoming ball as a rally controller sees it: its predicted flight from the ball estimator's
estimate, sampled at the instants the joints can hit it, and the preferred hit among them.

The model-based returner (``control.returner``, steps 1-2 of its docstring) plans its hits on this
prediction, and the ``ObservationBuilder`` gives a learned actor the same preferred hit as an
observation part (``contracts``, ``hit_prediction``): the ball's state at the segment
boundary nearest the top of its bounce where the racket may meet it, and how far ahead that is.
Judged from each estimate alone, that hit jumps by a segment whenever the estimated top of the
bounce crosses the midpoint between two boundaries; the returner with memory keeps the hit it
planned, and the builder with ``hit_memory`` keeps the hit it predicted (``keep``), while either is
still a candidate.

``HitPredictor`` holds what the prediction needs: the ball physics, the returner's hit window
(``ReturnerParams``: heights, ``hit_x_min``, step, horizon), the segment length T, the observation
lead (the observation is built that long before its segment starts) and the joints' lag behind
their command (eq. (9)'s ramp-tracking lag plus half a command period of zero-order hold).
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from ace_drake.contracts import HIT_PREDICTION_SIZE
from ace_drake.control.joint_model import ramp_tracking_lag
from ace_drake.control.params import ControlParams, ReturnerParams
from ace_drake.physics.flight import flight_constants, rk4_one
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, contact_constants, simulate_ball_arrays
from ace_drake.robot.params import RobotScenario

_PREDICTION_KINDS = (ContactKind.TABLE_PLANE, ContactKind.NET, ContactKind.FLOOR)  # predict's guards, in its order
IMMINENT_MARGIN = 0.01  # s: a bounce predicted within one segment + this is remembered as happening
KEEP_TOLERANCE = 1e-6  # s: a candidate this close to a remembered hit time is that hit (sample times are exact multiples)


@dataclasses.dataclass(frozen=True)
class Prediction:
    """The incoming ball from an estimate: sample times (J,; s after the observation), states
    (J, 9) and contacts [(time, kind, state just before)] in order."""

    times: np.ndarray
    states: np.ndarray
    contacts: list[tuple[float, ContactKind, np.ndarray]]


@dataclasses.dataclass
class Flight:
    """What the returner remembers about the ball it is playing: its clock (s since its first call
    for this ball; calls are one segment apart), the last prediction on that clock, the time of
    the ball's bounce on the robot's half (or None), and the hit plan (or None)."""

    clock: float = 0.0
    prediction_times: np.ndarray | None = None
    prediction_positions: np.ndarray | None = None
    bounce_time: float | None = None
    hit: object = None  # the returner's plan (control.returner.HitPlan) or None


def joint_lag(scenario: RobotScenario) -> float:
    """How far (s) the joints lag a command: the slowest joint's eq. (9) ramp-tracking lag plus
    half a command period of zero-order hold."""
    dynamics = scenario.dynamics
    return max(ramp_tracking_lag(joint) for joint in dynamics.joints) + 0.5 * dynamics.command_period


class HitPredictor:
    """Predicts the incoming ball and ranks its possible hits (module docstring)."""

    def __init__(self, physics: BallPhysicsParams, params: ReturnerParams, segment: float, lead: float, lag: float):
        """Args: the ball physics; the returner parameters (hit window, prediction step and
        horizon); the segment length T (s); the observation lead (s); the joints' lag (s,
        ``joint_lag``)."""
        if not segment > 0.0 or not 0.0 <= lead < segment or not lag >= 0.0:
            raise ValueError(f"HitPredictor: need segment > 0, 0 <= lead < segment and lag >= 0 (s), got {segment}, {lead}, {lag}")
        self.physics = physics
        self.params = params
        self.segment = segment
        self.lead = lead
        self.lag = lag
        self._samples_per_segment = max(1, round(segment / params.prediction_step))
        self._step = segment / self._samples_per_segment
        self._flight = flight_constants(physics.aero)  # the compiled kernels' constants
        self._contact = contact_constants(physics)

    @classmethod
    def for_robot(cls, scenario: RobotScenario, control: ControlParams, physics: BallPhysicsParams, params: ReturnerParams | None = None) -> HitPredictor:
        """The predictor for a robot: T and the lead from ``control``, the lag from the scenario's
        joint dynamics (``params.joint_lag`` if set)."""
        params = params or ReturnerParams()
        segment = control.segment_samples * scenario.dynamics.command_period
        lag = joint_lag(scenario) if params.joint_lag is None else params.joint_lag
        return cls(physics, params, segment, control.observation_lead, lag)

    def preferred_hit(self, estimate: np.ndarray, keep: float | None = None) -> tuple[float, np.ndarray] | None:
        """The preferred hit of a ball estimated at ``estimate`` (9,) now, judged from the estimate
        alone (the memoryless returner's choice), or the hit ``keep`` s from now while that is
        still a candidate (an ObservationBuilder with ``hit_memory``): (seconds from now to the
        ball sample, the ball state there (9,)), or None when the ball is not coming or has no
        hit."""
        estimate = np.asarray(estimate, dtype=float)
        if estimate[3] >= 0.0:
            return None
        flight = Flight(bounce_time=self.bounce_behind(estimate))
        prediction = self.predict(estimate)
        if prediction.times.size == 0:
            return None
        order = self.candidates(flight, prediction, include_current=True, keep=keep)
        if not order:
            return None
        return float(prediction.times[order[0]]), prediction.states[order[0]].copy()

    def features(self, estimate: np.ndarray, valid: bool, keep: float | None = None) -> np.ndarray:
        """The ``hit_prediction`` observation part (HIT_PREDICTION_SIZE,): [1, time to the
        preferred hit (s; ``keep``: ``preferred_hit``), ball state there (p m, v m/s, w rad/s)],
        or zeros without a valid estimate or a hit."""
        hit = self.preferred_hit(estimate, keep) if valid else None
        features = np.zeros(HIT_PREDICTION_SIZE)
        if hit is not None:
            features[0], features[1], features[2:] = 1.0, hit[0], hit[1]
        return features

    def bounce_behind(self, estimate: np.ndarray, horizon: float = 1.0, dt: float = 0.02) -> float | None:
        """When (s, < 0: before the observation) the ball of ``estimate`` (9,) bounced on the
        robot's half, or None if it has not: its flight (eq. (1), RK4 steps of ``dt`` s) followed
        back in time for up to ``horizon`` s meets the playing surface (ball centre one radius above
        it) inside the robot's half before it crosses back over the net. The memoryless mode's
        substitute for remembering a bounce it predicted (``ReturnerParams.memory``). Compiled
        (``_bounce_behind``): one call instead of up to horizon / dt RK4 calls."""
        table = self.physics.table
        state = np.array(estimate, dtype=float).reshape(9)
        time = _bounce_behind(state, int(round(horizon / dt)), dt, table.length, table.width, *self._flight)
        return None if np.isnan(time) else time

    def predict(self, estimate: np.ndarray) -> Prediction:
        """The incoming ball from the estimate (at the observation time), sampled at lead + lag +
        j dt (dt = T / samples_per_segment), until it is out of reach (behind ``hit_x_min``, on
        the floor, bounced twice on the robot's half, or falling below ``hit_height_min`` after
        its bounce) or the horizon.

        The table is found as a crossing of its plane (``ContactKind.TABLE_PLANE``), kept as a
        bounce when it lies on the table: with steps this long (10 m/s x 32 ms = 0.32 m) the
        table's own guard misses a bounce within a step's travel of the table's end, where the
        step leaves the table's footprint.

        Compiled (``_predict``: its legs are ``propagate.simulate_ball``'s compiled loop), one call
        per prediction; raises ValueError if the estimate, or the ball at the start of a leg, is
        not finite (as ``simulate_ball``)."""
        params = self.params
        state = np.array(estimate, dtype=float).reshape(-1)
        if state.shape != (9,):
            raise ValueError(f"HitPredictor.predict: estimate must be 9 numbers [p, v, w], got {np.shape(estimate)}")
        times, states, contact_times, contact_kinds, contact_states, finite = _predict(
            state, self.lead + self.lag, self._step, self.segment, self.physics.table.length, self.physics.table.width,
            params.hit_x_min, params.hit_height_min, params.prediction_horizon, self._contact, *self._flight,
        )
        if not finite:
            raise ValueError("HitPredictor.predict: the estimate (or the predicted ball) contains NaN or inf")
        contacts = [(float(t), _CONTACT_KINDS[k], pre) for t, k, pre in zip(contact_times, contact_kinds, contact_states)]
        return Prediction(times, states, contacts)

    # ------------------------------------------------------------------ B environments at once
    def features_batch(self, estimates: np.ndarray, valid: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """``features`` of B environments at once: row b of the (B, HIT_PREDICTION_SIZE) result
        is ``features(estimates[b], valid[b], keep[b])`` (keep[b] NaN for None). Args: estimates
        (B, 9) [p m, v m/s, w rad/s] (rows that are not valid may hold anything, NaN included);
        valid (B,) bool; keep (B,) s after the observation. The rows go one by one: each row's
        prediction is one compiled call. Raises ValueError naming the row, its estimate and kept
        hit when a valid row's ball cannot be predicted (``predict``)."""
        estimates = np.asarray(estimates, dtype=float)
        if estimates.ndim != 2 or estimates.shape[1] != 9:
            raise ValueError(f"HitPredictor.features_batch: estimates must be (B, 9), got {estimates.shape}")
        count = estimates.shape[0]
        valid, keep = np.asarray(valid, dtype=bool), np.asarray(keep, dtype=float)
        if valid.shape != (count,) or keep.shape != (count,):
            raise ValueError(f"HitPredictor.features_batch: valid and keep must be ({count},), got {valid.shape} and {keep.shape}")
        features = np.zeros((count, HIT_PREDICTION_SIZE))
        for row in np.flatnonzero(valid & ~(estimates[:, 3] >= 0.0)):  # preferred_hit's test: NaN v_x is coming
            try:
                features[row] = self.features(estimates[row], True, float(keep[row]) if np.isfinite(keep[row]) else None)
            except ValueError as error:  # name the environment and its numbers
                estimate = np.array2string(estimates[row], precision=6, max_line_width=10**6)
                kept = f"{keep[row]} s" if np.isfinite(keep[row]) else "none"
                raise ValueError(f"{error} (environment {row}: estimate {estimate}, kept hit {kept})") from error
        return features

    # ------------------------------------------------------------------------------ the hit
    def bounce_window(self, flight: Flight, prediction: Prediction) -> tuple[float, float] | None:
        """The times (s after the observation) of the bounce on the robot's half and of the next
        contact after it (inf if none): where ``candidates`` may hit; None when there is no such
        bounce ahead (an invalid shot, or a remembered bounce already far behind). An imminent
        bounce is recorded in ``flight``."""
        table_contacts = [(t, kind, state) for t, kind, state in prediction.contacts if kind in (ContactKind.TABLE, ContactKind.FLOOR)]
        first_is_bounce = bool(table_contacts) and table_contacts[0][1] == ContactKind.TABLE and table_contacts[0][2][0] < 0.0
        if flight.bounce_time is not None:
            # The bounce was imminent at an earlier call: it is this prediction's first contact if
            # that lies within the margin of it (the same bounce, re-timed), else behind us.
            remembered = flight.bounce_time - flight.clock
            if first_is_bounce and abs(table_contacts[0][0] - remembered) < IMMINENT_MARGIN:
                bounce, after = table_contacts[0][0], table_contacts[1:]
            elif remembered <= IMMINENT_MARGIN:
                bounce, after = remembered, table_contacts
            else:
                return None
        elif first_is_bounce:
            bounce, after = table_contacts[0][0], table_contacts[1:]
            # Remembered only when it happens before the next call: a prediction that short is
            # reliable, and the next call's estimate will be past it.
            if bounce < self.segment + IMMINENT_MARGIN:
                flight.bounce_time = flight.clock + bounce
        else:
            return None  # no bounce on the robot's half ahead: an invalid shot, not to be touched
        return bounce, (after[0][0] if after else np.inf)

    def candidates(self, flight: Flight, prediction: Prediction, include_current: bool = False, keep: float | None = None) -> list[int]:
        """Indices of the prediction's samples where the robot may hit (``control.returner``'s
        step 2), most preferred first. ``flight``: what is remembered of the ball (a fresh
        ``Flight`` with ``bounce_time`` from ``bounce_behind`` when nothing is); an imminent
        bounce is recorded in it. ``include_current``: also the hit in the segment being commanded
        (k = 0; the memoryless returner follows through there when it is preferred). The hit
        ``keep`` s after the observation (a remembered or kept hit) comes first while it is a
        candidate."""
        params = self.params
        window = self.bounce_window(flight, prediction)
        if window is None:
            return []
        bounce, end = window
        # Hits at a segment boundary after the next (k >= 1), or from the one in the segment being
        # commanded (k = 0) with include_current.
        first = 0 if include_current else self._samples_per_segment
        order = _hit_order(prediction.times, prediction.states, bounce, end, first, self._samples_per_segment, params.hit_height_min,
                           params.hit_height_max, params.hit_x_min, np.nan if keep is None else keep)
        return list(order)




_CONTACT_KINDS = {int(kind): kind for kind in ContactKind}
_TABLE, _TABLE_PLANE = int(ContactKind.TABLE), int(ContactKind.TABLE_PLANE)  # as the compiled predictor compares them
_LEG_KINDS = np.array(_PREDICTION_KINDS, dtype=np.int64)
_LEG_STOPS = np.array([True, False, True])  # on TABLE_PLANE and FLOOR
_PAST_TABLE_KINDS = np.array([ContactKind.NET, ContactKind.FLOOR], dtype=np.int64)  # once the ball is past the table's end
_PAST_TABLE_STOPS = np.array([False, True])


@numba.njit(cache=True)
def _bounce_behind(state, steps, dt, table_length, table_width, drag_scale, density_ratio, slope, radius, offset, cap, weight,
                   drag_model, magnus_model, drag_table_scale, magnus_scale):
    """``HitPredictor.bounce_behind`` of one ball state (9,) (changed in place) over ``steps`` RK4
    steps of -dt s: the time (s) or NaN for None."""
    k1, k2, k3, k4, trial, before = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for step in range(1, steps + 1):
        before[:] = state
        rk4_one(before, -dt, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, state)
        if state[0] > 0.0:
            return np.nan  # back over the net first: the ball is still to bounce
        if state[2] < radius:
            fraction = (before[2] - radius) / (before[2] - state[2])
            x = before[0] + fraction * (state[0] - before[0])
            y = before[1] + fraction * (state[1] - before[1])
            on_table = -0.5 * table_length <= x <= 0.0 and abs(y) <= 0.5 * table_width
            return -(step - 1 + fraction) * dt if on_table else np.nan
    return np.nan


@numba.njit(cache=True)
def _grown(array, size):
    """``array`` (N, ...) if it has room for ``size`` rows, else a copy with twice the room."""
    if size <= array.shape[0]:
        return array
    bigger = np.empty((2 * size,) + array.shape[1:], dtype=array.dtype)
    bigger[: array.shape[0]] = array
    return bigger


@numba.njit(cache=True)
def _with_contact(times, kinds, states, count, time, kind, state):
    """The contact arrays (times, kinds, states) with (time, kind, state) in row ``count``."""
    times, kinds, states = _grown(times, count + 1), _grown(kinds, count + 1), _grown(states, count + 1)
    times[count], kinds[count], states[count] = time, kind, state
    return times, kinds, states


@numba.njit(cache=True)
def _predict(estimate, first_sample, step, segment, table_length, table_width, hit_x_min, hit_height_min, horizon, c, *flight):
    """``HitPredictor.predict`` of one ball estimate (9,): its legs, the bookkeeping between them
    and its stopping rule, in ``predict``'s order of operations; each leg is
    ``propagate.simulate_ball_arrays``. ``c``: the contact constants
    (``propagate.contact_constants``); ``flight``: ``flight_constants``. Returns (times (J,),
    states (J, 9), the contacts' times (K,), ContactKind values (K,) and states just before
    (K, 9), whether every leg started from a finite state)."""
    times, states = np.empty(64), np.empty((64, 9))
    contact_times, contact_kinds, contact_states = np.empty(8), np.empty(8, dtype=np.int64), np.empty((8, 9))
    samples, contacts = 0, 0
    kinds, stops = _LEG_KINDS, _LEG_STOPS
    now, state = 0.0, estimate.copy()
    robot_bounces = 0
    finite = True
    while True:
        # One leg: to the next sample time, then on in steps of dt, up to a stopping contact.
        upcoming = first_sample + step * samples
        lead_in = upcoming - now
        duration = lead_in + 8 * segment
        stopped, offset = -1, now
        event_kinds, event_times, event_pre, event_post = np.empty(0, dtype=np.int64), np.empty(0), np.empty((0, 9)), np.empty((0, 9))
        if lead_in > 1e-9:
            finite = np.all(np.isfinite(state))
            if not finite:
                break
            _, leg_states, event_kinds, event_times, event_pre, event_post, stopped = simulate_ball_arrays(
                state, lead_in, lead_in, kinds, stops, c, *flight)
            if stopped < 0:
                state, now = leg_states[-1].copy(), upcoming
                for e in range(event_kinds.size):
                    contact_times, contact_kinds, contact_states = _with_contact(
                        contact_times, contact_kinds, contact_states, contacts, now - lead_in + event_times[e], event_kinds[e], event_pre[e])
                    contacts += 1
                times, states = _grown(times, samples + 1), _grown(states, samples + 1)
                times[samples], states[samples] = now, state
                samples += 1
                offset = now
        if stopped < 0:
            finite = np.all(np.isfinite(state))
            if not finite:
                break
            leg_times, leg_states, event_kinds, event_times, event_pre, event_post, stopped = simulate_ball_arrays(
                state, duration - lead_in, step, kinds, stops, c, *flight)
            offset = now
            kept = leg_times.size - 1
            if stopped >= 0:  # the samples before the stop
                kept = 0
                for j in range(1, leg_times.size):
                    kept += leg_times[j] < event_times[stopped]
            times, states = _grown(times, samples + kept), _grown(states, samples + kept)
            j = 0
            for k in range(1, leg_times.size):
                if stopped < 0 or leg_times[k] < event_times[stopped]:
                    times[samples + j] = offset + leg_times[k]
                    j += 1
            states[samples : samples + kept] = leg_states[1 : 1 + kept]
            samples += kept
        for e in range(event_kinds.size):
            if e != stopped:
                contact_times, contact_kinds, contact_states = _with_contact(
                    contact_times, contact_kinds, contact_states, contacts, offset + event_times[e], event_kinds[e], event_pre[e])
                contacts += 1
        if stopped >= 0:
            now = offset + event_times[stopped]
            pre, kind = event_pre[stopped], event_kinds[stopped]
            on_table = abs(pre[0]) <= 0.5 * table_length and abs(pre[1]) <= 0.5 * table_width
            if kind == _TABLE_PLANE and on_table:
                contact_times, contact_kinds, contact_states = _with_contact(contact_times, contact_kinds, contact_states, contacts, now, _TABLE, pre)
                contacts += 1
                robot_bounces += pre[0] < 0.0
                state = event_post[stopped].copy()  # the table's impact map, eqs (2)-(6)
            elif kind == _TABLE_PLANE:
                kinds, stops = _PAST_TABLE_KINDS, _PAST_TABLE_STOPS  # past the table
                state = pre.copy()
            else:
                contact_times, contact_kinds, contact_states = _with_contact(contact_times, contact_kinds, contact_states, contacts, now, kind, pre)
                contacts += 1
                break  # the floor
        else:
            now, state = times[samples - 1], states[samples - 1].copy()
        falling_out = robot_bounces >= 1 and state[5] < 0.0 and state[2] < hit_height_min
        if robot_bounces >= 2 or state[0] < hit_x_min or falling_out or now - first_sample > horizon:
            break
    return times[:samples], states[:samples], contact_times[:contacts], contact_kinds[:contacts], contact_states[:contacts], finite


@numba.njit(cache=True)
def _hit_order(times, states, bounce, end, first, every, height_min, height_max, x_min, keep):
    """``HitPredictor.candidates``' ranking of a prediction's samples times (J,) s, states (J, 9):
    the indices first, first + every, ... strictly between ``bounce`` and ``end`` (s) where the
    ball is in the hit window (height_min <= z <= height_max m, x >= x_min m, v_x < 0), nearest in
    time to the top of the bounce (the highest sample strictly between bounce and end, the first
    of equals) first, equals in index order; then the one within KEEP_TOLERANCE of ``keep`` (s;
    NaN: none) moved to the front. Returns the indices (int64, possibly none)."""
    index = np.empty(times.size, dtype=np.int64)
    count = 0
    for i in range(first, times.size, every):
        if times[i] > bounce and times[i] < end:
            z, x = states[i, 2], states[i, 0]
            if z >= height_min and z <= height_max and x >= x_min and states[i, 3] < 0.0:
                index[count] = i
                count += 1
    if count == 0:
        return index[:0]
    top, highest = -1, 0.0  # np.argmax's rule: the first maximum, a NaN counting as one
    for i in range(times.size):
        if times[i] > bounce and times[i] < end:
            height = states[i, 2]
            if top < 0 or (not np.isnan(highest) and (height > highest or np.isnan(height))):
                top, highest = i, height
    index = index[:count]
    ranked = index[np.argsort(np.abs(times[index] - times[top]), kind="mergesort")]  # stable: equals keep their order
    order = np.empty(count, dtype=np.int64)
    moved = 0
    for i in ranked:
        if abs(times[i] - keep) < KEEP_TOLERANCE:
            order[moved] = i
            moved += 1
    for i in ranked:
        if not abs(times[i] - keep) < KEEP_TOLERANCE:
            order[moved] = i
            moved += 1
    return order
