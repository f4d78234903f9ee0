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

import numpy as np

from ace_drake.contracts import HIT_PREDICTION_SIZE
from ace_drake.control.joint_model import ramp_tracking_lag
from ace_drake.control.params import ControlParams, ReturnerParams
from ace_drake.physics.flight import rk4_step
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.robot.params import RobotScenario

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
            leg = simulate(state, self.physics, lead_in, dt=lead_in, kinds=kinds, stop_on=stops) if lead_in > 1e-9 else None
            if leg is None or leg.stop_events[0] is None:
                if leg is not None:
                    state, now = leg.final_state[0], upcoming
                    contacts += [(now - lead_in + e.time, e.kind, e.state_pre) for e in leg.events[0]]
                    times.append(now)
                    states.append(state)
                leg = simulate(state, self.physics, duration - lead_in, dt=self._step, kinds=kinds, stop_on=stops)
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

