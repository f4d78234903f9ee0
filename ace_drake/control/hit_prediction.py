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

import numba
import numpy as np

from ace_drake.contracts import HIT_PREDICTION_SIZE
from ace_drake.control.joint_model import ramp_tracking_lag
from ace_drake.control.params import ControlParams, ReturnerParams
from ace_drake.physics.flight import flight_constants, rk4_one, rk4_step
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import (
    GAP_SCREEN_MARGIN,
    MAX_EVENTS_PER_STEP,
    ContactEvent,
    ContactKind,
    apply_impact,
    first_contact_time,
    guard_gaps,
    is_contact,
    simulate_ball,
)
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
        if hit is None:
            return np.zeros(HIT_PREDICTION_SIZE)
        return np.concatenate([[1.0, hit[0]], hit[1]])

    def bounce_behind(self, estimate: np.ndarray, horizon: float = 1.0, dt: float = 0.02) -> float | None:
        """When (s, < 0: before the observation) the ball of ``estimate`` (9,) bounced on the
        robot's half, or None if it has not: its flight (eq. (1), RK4 steps of ``dt`` s) followed
        back in time for up to ``horizon`` s meets the playing surface (ball centre one radius above
        it) inside the robot's half before it crosses back over the net. The memoryless mode's
        substitute for remembering a bounce it predicted (``ReturnerParams.memory``)."""
        table, radius = self.physics.table, self.physics.aero.ball_radius
        state = np.asarray(estimate, dtype=float)
        for step in range(1, int(round(horizon / dt)) + 1):
            before, state = state, rk4_step(state, -dt, self.physics.aero)
            if state[0] > 0.0:
                return None  # back over the net first: the ball is still to bounce
            if state[2] < radius:
                fraction = (before[2] - radius) / (before[2] - state[2])
                x, y = before[:2] + fraction * (state[:2] - before[:2])
                on_table = -0.5 * table.length <= x <= 0.0 and abs(y) <= 0.5 * table.width
                return -(step - 1 + fraction) * dt if on_table else None
        return None

    def predict(self, estimate: np.ndarray) -> Prediction:
        """The incoming ball from the estimate (at the observation time), sampled at lead + lag +
        j dt (dt = T / samples_per_segment), until it is out of reach (behind ``hit_x_min``, on
        the floor, bounced twice on the robot's half, or falling below ``hit_height_min`` after
        its bounce) or the horizon.

        The table is found as a crossing of its plane (``ContactKind.TABLE_PLANE``), kept as a
        bounce when it lies on the table: with steps this long (10 m/s x 32 ms = 0.32 m) the
        table's own guard misses a bounce within a step's travel of the table's end, where the
        step leaves the table's footprint."""
        params, table = self.params, self.physics.table
        kinds = (ContactKind.TABLE_PLANE, ContactKind.NET, ContactKind.FLOOR)
        stops = (ContactKind.TABLE_PLANE, ContactKind.FLOOR)
        first_sample = self.lead + self.lag
        times: list[float] = []
        states: list[np.ndarray] = []
        contacts: list[tuple[float, ContactKind, np.ndarray]] = []
        now, state = 0.0, np.asarray(estimate, dtype=float)
        while True:
            # One leg: to the next sample time, then on in steps of dt, up to a stopping contact.
            upcoming = first_sample + self._step * len(times)
            lead_in = upcoming - now
            duration = lead_in + 8 * self.segment
            leg = simulate_ball(state, self.physics, lead_in, dt=lead_in, kinds=kinds, stop_on=stops) if lead_in > 1e-9 else None
            if leg is None or leg.stop_events[0] is None:
                if leg is not None:
                    state, now = leg.final_state[0], upcoming
                    contacts += [(now - lead_in + e.time, e.kind, e.state_pre) for e in leg.events[0]]
                    times.append(now)
                    states.append(state)
                leg = simulate_ball(state, self.physics, duration - lead_in, dt=self._step, kinds=kinds, stop_on=stops)
                offset = now
                stopped = leg.stop_events[0]
                kept = leg.times[1:] if stopped is None else leg.times[1:][leg.times[1:] < stopped.time]
                times.extend(offset + kept)
                states.extend(leg.states[1 : 1 + kept.size, 0])
            else:
                offset, stopped = now, leg.stop_events[0]
            contacts += [(offset + e.time, e.kind, e.state_pre) for e in leg.events[0] if e is not stopped]
            if stopped is not None:
                now = offset + stopped.time
                on_table = abs(stopped.state_pre[0]) <= 0.5 * table.length and abs(stopped.state_pre[1]) <= 0.5 * table.width
                if stopped.kind == ContactKind.TABLE_PLANE and on_table:
                    contacts.append((now, ContactKind.TABLE, stopped.state_pre))
                    state = stopped.state_post  # the table's impact map, eqs (2)-(6)
                elif stopped.kind == ContactKind.TABLE_PLANE:
                    kinds, stops = (ContactKind.NET, ContactKind.FLOOR), (ContactKind.FLOOR,)  # past the table
                    state = stopped.state_pre
                else:
                    contacts.append((now, stopped.kind, stopped.state_pre))
                    break  # the floor
            else:
                now, state = times[-1], states[-1]
            robot_bounces = sum(kind == ContactKind.TABLE and pre[0] < 0.0 for _, kind, pre in contacts)
            falling_out = robot_bounces >= 1 and state[5] < 0.0 and state[2] < params.hit_height_min
            if robot_bounces >= 2 or state[0] < params.hit_x_min or falling_out or now - first_sample > params.prediction_horizon:
                break
        return Prediction(np.asarray(times), np.asarray(states).reshape(-1, 9), contacts)

    # ------------------------------------------------------------------ B environments at once
    def features_batch(self, estimates: np.ndarray, valid: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """``features`` of B environments at once: row b of the (B, HIT_PREDICTION_SIZE) result
        is ``features(estimates[b], valid[b], keep[b])`` bit for bit (tests/test_hit_prediction.py),
        keep[b] NaN for None. Args: estimates (B, 9) [p m, v m/s, w rad/s] (rows that are not
        valid may hold anything, NaN included); valid (B,) bool; keep (B,) s after the
        observation. The prediction (``predict_batch``) and the bounce behind
        (``bounce_behind_batch``) run vectorised over the rows; ``candidates`` runs per row (a
        single predicting row goes through ``features``)."""
        estimates = np.asarray(estimates, dtype=float)
        if estimates.ndim != 2 or estimates.shape[1] != 9:
            raise ValueError(f"HitPredictor.features_batch: estimates must be (B, 9), got {estimates.shape}")
        count = estimates.shape[0]
        valid, keep = np.asarray(valid, dtype=bool), np.asarray(keep, dtype=float)
        if valid.shape != (count,) or keep.shape != (count,):
            raise ValueError(f"HitPredictor.features_batch: valid and keep must be ({count},), got {valid.shape} and {keep.shape}")
        features = np.zeros((count, HIT_PREDICTION_SIZE))
        rows = np.flatnonzero(valid & ~(estimates[:, 3] >= 0.0))  # preferred_hit's test: NaN v_x is coming
        if rows.size == 0:
            return features
        if rows.size == 1:  # one ball: ``features`` itself is cheaper than the batched bookkeeping
            row = rows[0]
            features[row] = self.features(estimates[row], True, float(keep[row]) if np.isfinite(keep[row]) else None)
            return features
        bounces = self.bounce_behind_batch(estimates[rows])
        predictions = self.predict_batch(estimates[rows])
        for row, bounce, prediction in zip(rows, bounces, predictions):
            if prediction.times.size == 0:
                continue
            flight = Flight(bounce_time=None if np.isnan(bounce) else float(bounce))
            kept = float(keep[row]) if np.isfinite(keep[row]) else None
            order = self.candidates(flight, prediction, include_current=True, keep=kept)
            if order:
                features[row, 0], features[row, 1], features[row, 2:] = 1.0, prediction.times[order[0]], prediction.states[order[0]]
        return features

    def bounce_behind_batch(self, estimates: np.ndarray, horizon: float = 1.0, dt: float = 0.02) -> np.ndarray:
        """``bounce_behind`` of M balls (M, 9) at once: (M,) s, NaN for None; equal to it bit for
        bit (the same RK4 steps back in time, per row)."""
        table, radius = self.physics.table, self.physics.aero.ball_radius
        state = np.array(estimates, dtype=float).reshape(-1, 9)
        result = np.full(state.shape[0], np.nan)
        rows = np.arange(state.shape[0])
        for step in range(1, int(round(horizon / dt)) + 1):
            if rows.size == 0:
                break
            before = state[rows]
            after = rk4_step(before, -dt, self.physics.aero)
            state[rows] = after
            over = after[:, 0] > 0.0  # back over the net first: the ball is still to bounce
            down = ~over & (after[:, 2] < radius)
            if down.any():
                b, a = before[down], after[down]
                fraction = (b[:, 2] - radius) / (b[:, 2] - a[:, 2])
                x = b[:, 0] + fraction * (a[:, 0] - b[:, 0])
                y = b[:, 1] + fraction * (a[:, 1] - b[:, 1])
                on_table = (-0.5 * table.length <= x) & (x <= 0.0) & (np.abs(y) <= 0.5 * table.width)
                result[rows[down]] = np.where(on_table, -(step - 1 + fraction) * dt, np.nan)
            rows = rows[~(over | down)]
        return result

    def predict_batch(self, estimates: np.ndarray) -> list[Prediction]:
        """``predict`` of M balls (M, 9) at once: the M Predictions, each equal to ``predict`` of
        its row bit for bit. Each of ``predict``'s legs runs for all rows still predicting in one
        ``_simulate_rows`` call (rows have their own leg lengths and contact kinds and stop
        independently); the bookkeeping between legs is ``predict``'s, per row."""
        params, table = self.params, self.physics.table
        state = np.array(estimates, dtype=float).reshape(-1, 9)
        if not np.all(np.isfinite(state)):
            bad = np.flatnonzero(~np.all(np.isfinite(state), axis=1))
            raise ValueError(f"HitPredictor.predict_batch: estimates of rows {bad.tolist()} contain NaN or inf")
        count = state.shape[0]
        first_sample = self.lead + self.lag
        times: list[list[np.ndarray]] = [[] for _ in range(count)]
        states: list[list[np.ndarray]] = [[] for _ in range(count)]
        contacts: list[list[tuple[float, ContactKind, np.ndarray]]] = [[] for _ in range(count)]
        sample_count = np.zeros(count, dtype=np.int64)
        now = np.zeros(count)
        past_table = np.zeros(count, dtype=bool)  # predict's kinds (NET, FLOOR), stops (FLOOR,)
        robot_bounces = np.zeros(count, dtype=np.int64)
        running = np.arange(count)
        while running.size:
            upcoming = first_sample + self._step * sample_count[running]
            lead_in = upcoming - now[running]
            duration = lead_in + 8 * self.segment
            # Leg 1: to the next sample time, one step.
            first = lead_in > 1e-9
            stopped: list[ContactEvent | None] = [None] * running.size
            offset = now[running].copy()
            if first.any():
                idx = np.flatnonzero(first)
                rows = running[idx]
                leg = _simulate_rows(state[rows], lead_in[idx], lead_in[idx], past_table[rows], self.physics)
                for j, (i, row) in enumerate(zip(idx, rows)):
                    if leg.stop_events[j] is None:
                        state[row], now[row] = leg.final_state[j], upcoming[i]
                        contacts[row] += [(now[row] - lead_in[i] + e.time, e.kind, e.state_pre) for e in leg.events[j]]
                        times[row].append(np.array([now[row]]))
                        states[row].append(state[row][None].copy())
                        sample_count[row] += 1
                        offset[i] = now[row]
                    else:
                        stopped[i] = leg.stop_events[j]
                        contacts[row] += [(offset[i] + e.time, e.kind, e.state_pre) for e in leg.events[j] if e is not stopped[i]]
            # Leg 2: on in steps of dt, up to a stopping contact.
            idx = np.flatnonzero([event is None for event in stopped])
            if idx.size:
                rows = running[idx]
                leg = _simulate_rows(state[rows], duration[idx] - lead_in[idx], np.full(idx.size, self._step), past_table[rows], self.physics)
                for j, (i, row) in enumerate(zip(idx, rows)):
                    event = stopped[i] = leg.stop_events[j]
                    leg_times = leg.times[1 : leg.steps[j] + 1, j]
                    kept = leg_times if event is None else leg_times[leg_times < event.time]
                    times[row].append(offset[i] + kept)
                    states[row].append(leg.states[1 : 1 + kept.size, j].copy())
                    sample_count[row] += kept.size
                    contacts[row] += [(offset[i] + e.time, e.kind, e.state_pre) for e in leg.events[j] if e is not event]
            done = np.zeros(running.size, dtype=bool)
            for i, row in enumerate(running):
                event = stopped[i]
                if event is not None:
                    now[row] = offset[i] + event.time
                    pre = event.state_pre
                    on_table = abs(pre[0]) <= 0.5 * table.length and abs(pre[1]) <= 0.5 * table.width
                    if event.kind == ContactKind.TABLE_PLANE and on_table:
                        contacts[row].append((now[row], ContactKind.TABLE, pre))
                        robot_bounces[row] += pre[0] < 0.0
                        state[row] = event.state_post  # the table's impact map, eqs (2)-(6)
                    elif event.kind == ContactKind.TABLE_PLANE:
                        past_table[row] = True
                        state[row] = pre
                    else:
                        contacts[row].append((now[row], event.kind, pre))
                        done[i] = True  # the floor
                        continue
                else:
                    last = next(chunk for chunk in reversed(times[row]) if chunk.size)
                    last_state = next(chunk for chunk in reversed(states[row]) if chunk.shape[0])
                    now[row], state[row] = last[-1], last_state[-1]
                falling_out = robot_bounces[row] >= 1 and state[row, 5] < 0.0 and state[row, 2] < params.hit_height_min
                if robot_bounces[row] >= 2 or state[row, 0] < params.hit_x_min or falling_out or now[row] - first_sample > params.prediction_horizon:
                    done[i] = True
            running = running[~done]
        return [
            Prediction(
                np.concatenate(times[row]) if times[row] else np.zeros(0),
                np.concatenate(states[row]).reshape(-1, 9) if states[row] else np.zeros((0, 9)),
                contacts[row],
            )
            for row in range(count)
        ]

    # ------------------------------------------------------------------------------ the hit
    def candidates(self, flight: Flight, prediction: Prediction, include_current: bool = False, keep: float | None = None) -> list[int]:
        """Indices of the prediction's samples where the robot may hit (``control.returner``'s
        step 2), most preferred first. ``flight``: what is remembered of the ball (a fresh
        ``Flight`` with ``bounce_time`` from ``bounce_behind`` when nothing is); an imminent
        bounce is recorded in it. ``include_current``: also the hit in the segment being commanded
        (k = 0; the memoryless returner follows through there when it is preferred). The hit
        ``keep`` s after the observation (a remembered or kept hit) comes first while it is a
        candidate."""
        params = self.params
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
                return []
        elif first_is_bounce:
            bounce, after = table_contacts[0][0], table_contacts[1:]
            # Remembered only when it happens before the next call: a prediction that short is
            # reliable, and the next call's estimate will be past it.
            if bounce < self.segment + IMMINENT_MARGIN:
                flight.bounce_time = flight.clock + bounce
        else:
            return []  # no bounce on the robot's half ahead: an invalid shot, not to be touched
        end = after[0][0] if after else np.inf
        times, states = prediction.times, prediction.states
        # Hits at a segment boundary after the next (k >= 1), or from the one in the segment being
        # commanded (k = 0) with include_current.
        first = 0 if include_current else self._samples_per_segment
        index = np.arange(first, len(times), self._samples_per_segment)
        index = index[(times[index] > bounce) & (times[index] < end)]
        z, x = states[index, 2], states[index, 0]
        index = index[(z >= params.hit_height_min) & (z <= params.hit_height_max) & (x >= params.hit_x_min) & (states[index, 3] < 0.0)]
        if index.size == 0:
            return []
        after_bounce = np.flatnonzero((times > bounce) & (times < end))
        apex = times[after_bounce[np.argmax(states[after_bounce, 2])]]
        order = sorted(index, key=lambda i: abs(times[i] - apex))
        if keep is not None:
            kept = [i for i in order if abs(times[i] - keep) < KEEP_TOLERANCE]
            order = kept + [i for i in order if i not in kept]
        return order



@dataclasses.dataclass
class _RowTrajectories:
    """``_simulate_rows``' result for N balls: times (S+1, N) s and states (S+1, N, 9) at each
    ball's steps (column n valid up to row steps[n]); steps (N,); final_state (N, 9); events and
    stop_events per ball as in ``physics.propagate.Trajectory``."""

    times: np.ndarray
    states: np.ndarray
    steps: np.ndarray
    final_state: np.ndarray
    events: list[list[ContactEvent]]
    stop_events: list[ContactEvent | None]


def _simulate_rows(initial_state: np.ndarray, durations: np.ndarray, dts: np.ndarray, past_table: np.ndarray,
                   physics: BallPhysicsParams) -> _RowTrajectories:
    """``physics.propagate.simulate`` of N balls (N, 9), each with its own duration (N,) s, step
    (N,) s and ``predict``'s contact kinds: (TABLE_PLANE, NET, FLOOR) stopping on TABLE_PLANE and
    FLOOR, or with past_table (N,) (NET, FLOOR) stopping on FLOOR. Ball n's result equals
    ``simulate(initial_state[n], physics, durations[n], dt=dts[n], kinds, stop_on)``'s bit for
    bit (``simulate`` takes one duration and step for all its balls; ``predict``'s legs differ
    per ball).

    Each ball goes through ``simulate``'s operations in ``simulate``'s order: per step, trial RK4
    steps over what remains of it, and at a guard crossing the contact located
    (``first_contact_time``) and its impact map applied, up to MAX_EVENTS_PER_STEP times. Only
    the schedule differs: a ball whose trial step crosses a guard waits until every ball has
    either crossed one or finished, and then all waiting balls' contacts are located in one call
    (rows are independent there), so a leg costs a few calls per contact wave rather than per
    step. A kind a ball does not have is masked out of its crossings, which leaves the order of
    the others, hence the choice between simultaneous crossings, as ``simulate``'s; guards are
    compared by sign only, as in ``simulate`` (``guard_gaps``). Impact maps are applied to all
    table-plane or floor contacts of a wave at once (elementwise maps) and to net contacts one at
    a time."""
    kinds = _PREDICTION_KINDS
    x = np.array(initial_state, dtype=float).reshape(-1, 9)
    n_balls = x.shape[0]
    durations, dts = np.asarray(durations, dtype=float), np.asarray(dts, dtype=float)
    enabled = np.ones((n_balls, len(kinds)), dtype=bool)
    enabled[past_table, 0] = False
    stops_on_plane = ~np.asarray(past_table, dtype=bool)  # every ball stops on the floor; on the plane unless past the table
    active = np.ones(n_balls, dtype=bool)
    events: list[list[ContactEvent]] = [[] for _ in range(n_balls)]
    stop_events: list[ContactEvent | None] = [None] * n_balls
    steps = np.ceil(durations / dts - 1e-9).astype(np.int64) if n_balls else np.zeros(0, dtype=np.int64)
    n_steps = int(steps.max()) if n_balls else 0
    times = np.zeros((n_steps + 1, n_balls))
    states = np.empty((n_steps + 1, n_balls, 9))
    states[0] = x
    gaps = guard_gaps(x, kinds, physics)
    t, h = np.zeros(n_balls), np.zeros(n_balls)
    step = np.zeros(n_balls, dtype=np.int64)  # each ball's current step
    remaining, elapsed = np.zeros(n_balls), np.zeros(n_balls)
    rounds = np.zeros(n_balls, dtype=np.int64)  # trial steps taken in the current step
    finished = steps <= 0
    waiting = np.zeros(n_balls, dtype=bool)
    crossing = np.zeros((n_balls, len(kinds)), dtype=bool)

    def begin(rows):
        h[rows] = np.minimum(dts[rows], durations[rows] - t[rows])
        remaining[rows] = np.where(active[rows], h[rows], 0.0)
        elapsed[rows], rounds[rows] = 0.0, 0

    begin(np.flatnonzero(~finished))
    flight = flight_constants(physics.aero)
    table_height = physics.table.surface_height
    screened = np.full(n_balls, -1, dtype=np.int64)  # the step at which the free-flight kernel last stopped for a ball
    while not finished.all():
        fresh = np.flatnonzero(~finished & ~waiting & (rounds == 0) & (screened != step))
        if fresh.size:  # whole free steps (and a stopped ball's steps) in one compiled call
            before = step[fresh].copy()
            _free_steps(x, t, step, steps, dts, durations, active, enabled, fresh, times, states, *flight, table_height, GAP_SCREEN_MARGIN)
            screened[fresh] = step[fresh]
            moved = fresh[step[fresh] > before]
            if moved.size:
                finished[moved] = step[moved] >= steps[moved]
                begin(moved[~finished[moved]])
                gaps[moved] = guard_gaps(x[moved], kinds, physics)
            continue
        trying = ~finished & ~waiting & (remaining > 0.0) & (rounds < MAX_EVENTS_PER_STEP)
        ending = np.flatnonzero(~finished & ~waiting & ~trying)
        if ending.size:  # the step is over: record it, then the next one
            t[ending] = t[ending] + h[ending]
            times[step[ending] + 1, ending] = t[ending]
            states[step[ending] + 1, ending] = x[ending]
            step[ending] += 1
            finished[ending] = step[ending] >= steps[ending]
            begin(ending[~finished[ending]])
            continue
        if trying.any():
            rows = np.flatnonzero(trying)
            x1 = rk4_step(x[rows], remaining[rows], physics.aero)
            gaps1 = guard_gaps(x1, kinds, physics)
            crossed = (gaps[rows] > 0.0) & (gaps1 <= 0.0) & enabled[rows]
            free = ~crossed.any(axis=-1)
            x[rows[free]], gaps[rows[free]] = x1[free], gaps1[free]
            remaining[rows[free]] = 0.0
            rounds[rows[free]] += 1
            waiting[rows[~free]], crossing[rows[~free]] = True, crossed[~free]
            continue
        # Every ball still going has crossed a guard: locate all those contacts at once.
        rows = np.flatnonzero(waiting)
        x0, h0 = x[rows], remaining[rows]
        tau, kind_index = first_contact_time(x0, h0, crossing[rows], kinds, physics)
        x_pre = rk4_step(x0, tau, physics.aero)
        x_post = x_pre.copy()
        contact = np.array([is_contact(kinds[k], pre, physics) for k, pre in zip(kind_index, x_pre)], dtype=bool)
        for k, kind in enumerate(kinds):
            mapped = np.flatnonzero(contact & (kind_index == k))
            if kind == ContactKind.NET:
                for j in mapped:
                    x_post[j] = apply_impact(kind, x_pre[j], physics)
            elif mapped.size:
                x_post[mapped] = apply_impact(kind, x_pre[mapped], physics)
        for j, row in enumerate(rows):
            if contact[j]:
                kind = kinds[kind_index[j]]
                event = ContactEvent(kind, t[row] + elapsed[row] + tau[j], x_pre[j].copy(), x_post[j].copy())
                events[row].append(event)
                if kind == ContactKind.FLOOR or (kind == ContactKind.TABLE_PLANE and stops_on_plane[row]):
                    stop_events[row] = event
                    active[row] = False
                    x[row] = x_pre[j]
                    remaining[row] = 0.0
                    continue
            x[row] = x_post[j]
            remaining[row] -= tau[j]
            elapsed[row] += tau[j]
        rounds[rows] += 1
        waiting[rows] = False
        gaps[rows] = guard_gaps(x[rows], kinds, physics)
    return _RowTrajectories(times, states, steps, x, events, stop_events)


@numba.njit(cache=True)
def _free_steps(x, t, step, steps, dts, durations, active, enabled, rows, times, states,
                drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, table_height, margin):
    """``_simulate_rows``' whole steps of the balls ``rows`` while they are plainly free: from
    each ball's current step (none of it taken yet) on, the step h = min(dt, duration - t) by the
    compiled RK4 step (``physics.flight``'s, as ``rk4_step``), kept when every guard the ball has
    is above ``margin`` at its end (``contact_gap_lower_bound``'s bounds: table plane z - r, net
    |x| - r, floor z + surface height - r; then no guard crosses, as ``simulate`` would find), and
    recorded as ``simulate`` records it; a stopped ball's steps pass with no RK4 step, as in
    ``simulate``. A ball stays at the first step whose end is not plainly free, for the exact
    guards. In place on x (N, 9), t, step (N,), times (S+1, N), states (S+1, N, 9)."""
    k1, k2, k3, k4, trial, x1 = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for row in rows:
        while step[row] < steps[row]:
            h = min(dts[row], durations[row] - t[row])
            if active[row] and h > 0.0:
                rk4_one(x[row], h, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                        drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x1)
                if enabled[row, 0] and not x1[2] - radius > margin:
                    break
                if enabled[row, 1] and not abs(x1[0]) - radius > margin:
                    break
                if enabled[row, 2] and not x1[2] + table_height - radius > margin:
                    break
                x[row] = x1
            t[row] = t[row] + h
            step[row] += 1
            times[step[row], row] = t[row]
            states[step[row], row] = x[row]
