"""The model-based returner: the classical rally controller (paper, related work: predict the ball,
choose a hitting point and racket state, solve for the motion) behind a policy's interface.

``ModelBasedReturner`` is a callable observation -> action (16,) in [-1, 1] | None, called by the
``PolicyController`` every T = 32 ms on the observation built 5 ms before the segment it commands
starts (``contracts``); its actions go through the same eq. (12) mapping, spline QP,
reset and safety supervisor as a learned policy's. Each call replans from the ball estimator's
latest estimate (the estimate improves as the ball flies):

1. **Predict** the incoming ball from the EKF estimate with the project's physics
   (``physics.propagate.simulate``: flight eq. (1), table eqs (2)-(6), net, floor), sampled at the
   instants the joints can hit it. The joints lag their command by the eq. (9) ramp-tracking lag
   plus half a command period of zero-order hold (``joint_lag``: 4.3 ms by default), so a state
   commanded at a segment boundary is reached that much later: the candidate hit times are
   lead + lag + k T after the observation, k = 1, 2, ... (lead: the observation's 5 ms), and a
   hit's (q_hit, v_hit) is the command's terminal state at its boundary.
2. **Pick a hit**: a candidate after the ball's bounce on the robot's half and before anything
   else touches it, with the ball centre ``hit_height_min``..``hit_height_max`` above the table
   and in front of ``hit_x_min``, nearest the top of the bounce (where the ball's height changes
   least with time, so timing errors cost least). The previous call's hit time is kept while it
   stays valid, so that the plan does not hop between segments as the estimate moves; a later
   candidate is taken when the robot cannot get there in time (the joint trajectory of step 5
   would exceed the acceleration limits).
3. **Solve the racket state** that sends the ball to the target on the opponent's half
   (``target_x``, the skill's y_desired), inverting the racket contact model (eqs (7)-(8)):
   ``solve_return`` finds, by Newton's method on the flight model, the outgoing velocity that
   lands the ball on the target after a chosen flight time, each iterate's spin coming from the
   racket state that makes it (``invert_racket_contact``: a racket moving along its normal, plus
   a brushing speed along the blade, ``brush_speed`` plus ``skill_brush`` times the skill's w_s:
   topspin for w_s > 0, backspin for w_s < 0, the paper's spin skill). Flight times are
   tried in order (``flight_times``) until the ball clears the net and the joints can make the
   racket state.
4. **Inverse kinematics** for the racket pose (``solve_hit_ik``: Drake's InverseKinematics with
   the blade free to roll about its normal and ``ik_clearance`` between all geometry, nearest a
   nominal configuration in a metric that makes the slow gantry expensive: the segment start, or
   without memory where braking uniformly to rest by the hit would stop the moving arm, so that
   the solution keeps to the branch the arm is moving towards, ``ReturnerParams.ik_nominal``),
   then on later calls the previous solution moved onto the updated pose by Gauss-Newton steps
   (``refine_hit_ik``: continuity, and 0.3 ms instead of 2-60 ms); the **joint velocities** for
   the racket velocity by least squares weighted by the joints' speed limits
   (``racket_joint_velocities``).
5. **Drive the joints** (``control.hit_state.HitDriver``, shared with the hit-state actor) from the segment-start state (q0, v0) towards (q_hit, v_hit) at the hit's
   boundary along the cubic Hermite between them, evaluated one segment ahead: that terminal
   (q_T, v_T) becomes the action through the inverse of the eq. (12) mapping, clipped to the box
   (a target outside the feasible set maps onto its boundary). When the hit falls in the segment
   being commanded, the action follows through at the current joint velocities.
6. **Check it as the supervisor will** (``ControlStack.propose`` on a stack like the
   supervisor's: mapping, segment, reset, collision check): the Hermite's segment or its reset
   can sweep the wrist or forearm into the table when the hit is over it, and a refused segment
   costs the swing a whole period. If it would be refused, the returner sends instead the
   time-optimal approach to q_hit (``ControlStack.action_towards``: each joint on its braking
   curve, so the wrist turns before the arm reaches over the table), and if that too would be
   refused, nothing.

The returner returns None (no new segment: the supervisor runs the last plan's reset to the
ready pose) while there is no track, when the ball is not coming (v_x >= 0: after the hit), and
when no hit is possible (the ball does not bounce on the robot's half, or nothing is reachable).

It remembers the ball it is playing between calls (a clock advanced by T per call, the last
prediction, the bounce time and the hit plan): the memory is dropped when the estimate stops
matching the last prediction (> 0.3 m), i.e. for a new ball; ``reset`` drops it explicitly.

With ``ReturnerParams.memory`` False it remembers nothing, so that its action is a function of
the observation alone (the labels a learner imitates must be: ``training.rollout``): each call
finds whether the ball has bounced by following its flight back in time (``bounce_behind``),
takes the preferred hit of step 2 afresh (the same grid of hit instants every call, so the choice
holds while the estimate does), follows through when that hit falls in the segment being
commanded, and solves the full IK afresh (from where braking would stop the arm: step 4).
``ReturnerParams.forget`` drops parts of the memory one at a time instead (its bounce, hit time,
follow-through, racket plan, hit configuration, fallback; ``returner:forget=...`` in
``analysis.experiments``), to measure
what each is worth (docs/experiments/2026-12-01-returner-memory.md).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Iterator

import numpy as np

from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.feasible_set import in_invariant_set
from ace_drake.control.hit_prediction import Flight, HitPredictor, Prediction
from ace_drake.control.hit_state import HitDriver, hermite_peak_acceleration
from ace_drake.control.params import ControlParams, RallyParams, ReturnerParams
from ace_drake.control.stack import ControlStack, make_control_stack
from ace_drake.physics.contact import blade_standoff
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.racket_inverse import solve_return
from ace_drake.robot.ik import racket_joint_velocities, refine_hit_ik, solve_hit_ik
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.robot.params import RobotScenario

SAME_BALL_DISTANCE = 0.3  # m: an estimate this far from the last prediction is a different ball


def _no_action() -> None:
    """A call's action where it sends none (the supervisor runs the last plan's reset)."""
    return None


# ---------------------------------------------------------------------------------------------
# Racket planning (shared with analysis/scripted_swing.py)
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RacketPlan:
    """The racket state at a hit: time (s, on the caller's clock), blade centre p_WR (3; m),
    forehand normal (3; unit), velocity of the blade centre v_WR (3; m/s), the ball state just
    before (9) and just after (9) the contact (eqs (7)-(8)), the predicted landing (2; m) and the
    return's flight time to it (s)."""

    time: float
    position: np.ndarray
    normal: np.ndarray
    velocity: np.ndarray
    ball_state: np.ndarray
    ball_out: np.ndarray
    predicted_landing: np.ndarray
    flight_time: float


def racket_plans(
    ball: np.ndarray,
    hit_time: float,
    params: BallPhysicsParams,
    target: np.ndarray,
    returner: ReturnerParams | None = None,
    previous: RacketPlan | None = None,
    brush_speed: float | None = None,
) -> Iterator[RacketPlan]:
    """Racket states that return ``ball`` (9,; just before the hit at ``hit_time`` s) to
    ``target`` (x, y) (m), one per flight time of ``returner.flight_times`` whose return clears the
    net by ``returner.net_clearance``, in that order (the caller takes the first its robot can
    make); a ``previous`` plan's flight time comes first, warm-started from its outgoing velocity
    (replanning the same hit with a better estimate). The racket brushes the ball at
    ``brush_speed`` (m/s along the blade's upward tangent, > 0 topspin; None:
    ``returner.brush_speed``). The blade centre sits ball radius + half the blade's thickness
    behind the ball along the normal."""
    returner = returner or ReturnerParams()
    ball = np.asarray(ball, dtype=float)
    standoff = blade_standoff(params.aero.ball_radius, params.racket)
    brush_speed = returner.brush_speed if brush_speed is None else brush_speed
    flight_times = list(returner.flight_times)
    if previous is not None:
        flight_times = [previous.flight_time] + [t for t in flight_times if t != previous.flight_time]
    for flight_time in flight_times:
        guess = previous.ball_out[3:6] if previous is not None and flight_time == previous.flight_time else None
        shot = solve_return(ball, target, flight_time, params, brush_speed, v_guess=guess)
        if shot is None or shot.net_clearance < returner.net_clearance:
            continue
        yield RacketPlan(
            time=hit_time,
            position=ball[:3] - standoff * shot.normal,
            normal=shot.normal,
            velocity=shot.racket_velocity,
            ball_state=ball.copy(),
            ball_out=np.concatenate([ball[:3], shot.v_out, shot.w_out]),
            predicted_landing=shot.landing,
            flight_time=flight_time,
        )


# ---------------------------------------------------------------------------------------------
# The controller
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class HitPlan:
    """A planned hit: the joints' hit time (s on the returner's clock), the racket plan, and the
    joint state there (q, v; 8 each)."""

    time: float
    racket: RacketPlan
    q: np.ndarray
    v: np.ndarray


class ModelBasedReturner:
    """The model-based returner (module docstring): ``returner(observation) -> action | None``.

    Attributes for analysis: ``call_seconds`` (wall time of every call, s), ``last_plan`` (the
    latest HitPlan or None; None after a call that followed through or had no hit) and
    ``driver.last_choice`` (which action of step 6 the last call sent: 0 the planned one, 1 the
    fallback, -1 none).
    """

    def __init__(
        self,
        scenario: RobotScenario | None = None,
        control: ControlParams | None = None,
        physics: BallPhysicsParams | None = None,
        params: ReturnerParams | None = None,
        layout: ObservationLayout | None = None,
        model: RobotModel | None = None,
        stack: ControlStack | None = None,
        self_check: bool = True,
    ):
        """Args: the robot scenario, control parameters, ball physics and observation layout the
        rally diagram is built with (``RallyParams``: its ``scenario`` loaded, ``control``,
        ``physics``, and ``ObservationLayout(position_history, spin_history)``), the returner's
        own parameters, and optionally a RobotModel to share. ``stack``: the control stack whose
        proposals it checks its actions with (``ControlStack.propose``); by default, with
        ``self_check``, one like the supervisor's (``control.stack.make_control_stack``: collision
        checking on), else the maths only (no check: every action is sent as planned)."""
        self.model = model or RobotModel(scenario)
        if stack is None and self_check:
            stack = make_control_stack(self.model.scenario, control or ControlParams())
        self.stack = stack or ControlStack(self.model.scenario, control, None)
        self.driver = HitDriver(self.stack)  # step 5 and the check of step 6
        self.physics = physics or BallPhysicsParams()
        self.params = params or ReturnerParams()
        self.layout = layout or ObservationLayout()
        self.segment = self.stack.segment_duration
        self.lead = self.stack.control.observation_lead
        # Steps 1-2 (the prediction and the ranking of hits): the observation's hit_prediction too.
        self.predictor = HitPredictor.for_robot(self.model.scenario, self.stack.control, self.physics, self.params)
        self.lag = self.predictor.lag
        self._flight: Flight | None = None
        self.call_seconds: list[float] = []
        self.last_plan: HitPlan | None = None
        self._ik_budget = self.params.ik_solves_per_call

    @classmethod
    def for_rally(cls, rally: RallyParams, params: ReturnerParams | None = None) -> ModelBasedReturner:
        """The returner for the rally diagram built with ``rally`` (``diagrams.build_rally_diagram``):
        its scenario, control parameters, ball physics and observation layout."""
        return cls(
            scenario=load_scenario(MODELS_DIR / rally.scenario), control=rally.control, physics=rally.physics, params=params,
            layout=ObservationLayout(rally.position_history, rally.spin_history),
        )

    def reset(self) -> None:
        """Forgets the ball being played (the next call starts afresh)."""
        self._flight = None
        self.last_plan = None

    def __call__(self, observation: np.ndarray) -> np.ndarray | None:
        start = time.perf_counter()
        try:
            return self._act(np.asarray(observation, dtype=float))()
        finally:
            self.call_seconds.append(time.perf_counter() - start)

    def plan(self, observation: np.ndarray, follow_observed_hit: bool = False) -> tuple[HitPlan | None, Callable[[], np.ndarray | None]]:
        """Steps 1-4 of a call: (the hit it plans for ``observation`` or None, a function giving
        the action the call would return). The plan is driven (step 5 and step 6's collision
        check) only if that function is called: for callers that play the plan their own way
        (``control.hit_state.PlannedHitState``). Advances the returner's state as a call does.
        ``follow_observed_hit``: the observation's ``hit_prediction`` hit, when it has one, is
        tried first (step 2), as a remembered hit is (for an observation that keeps its predicted
        hit: ``RallyParams.hit_memory``)."""
        start = time.perf_counter()
        try:
            observation = np.asarray(observation, dtype=float)
            keep = None
            if follow_observed_hit:
                hit = self.layout.part(observation, "hit_prediction")
                keep = float(hit[1]) if hit[0] > 0.5 else None
            drive = self._act(observation, keep=keep)
            return self.last_plan, drive
        finally:
            self.call_seconds.append(time.perf_counter() - start)

    # ------------------------------------------------------------------------------ one call
    def _act(self, observation: np.ndarray, keep: float | None = None) -> Callable[[], np.ndarray | None]:
        """Steps 1-4 of a call, and the function giving its action (or None): steps 5-6, which
        drive a planned hit and check it as the supervisor will, run only when it is called
        (``plan``). ``keep``: a hit time (s after the observation) to try first
        (``HitPredictor.candidates``) when no remembered hit is."""
        layout = self.layout
        self._ik_budget = self.params.ik_solves_per_call
        self.last_plan = None
        estimate = layout.part(observation, "estimate")
        valid = layout.part(observation, "estimate_status")[0] > 0.5
        robot = layout.part(observation, "robot_state")
        q0, v0, a0 = robot[:8], robot[8:16], robot[16:24]
        usable = valid and bool(np.all(np.isfinite(estimate)))
        flight = self._advance(estimate if usable else None)
        if valid and not usable:
            return self._keep_plan(flight, q0, v0, a0)
        if not valid or estimate[3] >= 0.0:
            # No track, or the ball is not coming (the robot has hit it): no new segment.
            self._flight = None if valid else flight
            return _no_action
        plan_follows = self._plan_follows
        if flight.hit is not None and flight.hit.time - flight.clock < self.lead + self.lag + 0.5 * self.segment:
            if plan_follows and flight.hit.time - flight.clock > self.lead + self.lag - 0.5 * self.segment:
                return functools.partial(self.driver.follow_through, q0, v0, a0)  # the hit happens in the segment this action commands
            flight.hit = None  # the hit time passed and the ball is still coming: replan
        prediction = self.predictor.predict(estimate)
        if prediction.times.size == 0:
            return _no_action  # the ball reaches the floor before the next segment starts
        flight.prediction_times = flight.clock + prediction.times
        flight.prediction_positions = prediction.states[:, :3]
        skill = layout.part(observation, "skill")
        target = np.array([self.params.target_x, np.clip(skill[0], -self.params.target_y_limit, self.params.target_y_limit)])
        if flight.hit is not None and "hit" not in self.params.forget:
            keep = flight.hit.time - flight.clock  # the planned hit is tried first while it is a candidate
        candidates = self.predictor.candidates(flight, prediction, include_current=not plan_follows, keep=keep)
        if not plan_follows and candidates and candidates[0] == 0:
            return functools.partial(self.driver.follow_through, q0, v0, a0)  # the preferred hit falls in the segment this action commands
        candidates = [index for index in candidates if index > 0]
        brush = self.params.brush_speed + self.params.skill_brush * skill[2]  # the skill's w_s: topspin > 0, backspin < 0
        hit = self._plan_hit(flight, candidates, prediction, q0, v0, target, brush)
        if hit is None and candidates and flight.hit is not None and "fallback" not in self.params.forget:
            hit = flight.hit  # nothing new works (e.g. no IK this time): keep going for the last plan
        flight.hit = hit
        self.last_plan = hit
        if hit is None:
            return _no_action
        boundary = hit.time - flight.clock - self.lag  # when the command must be at (q_hit, v_hit), s after the observation
        return functools.partial(self.driver.drive, q0, v0, a0, hit.q, hit.v, boundary - self.lead)  # steps 5-6

    @property
    def _plan_follows(self) -> bool:
        """Whether the plan's hit decides the follow-through (else the preferred hit does)."""
        return self.params.memory and "follow" not in self.params.forget

    def _keep_plan(self, flight: Flight, q0: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> Callable[[], np.ndarray | None]:
        """A call on an estimate that is not finite (a track whose numbers are NaN or infinite:
        nothing to predict from): the plan stands. The remembered hit is driven on towards as
        planned (followed through when it falls in the segment this action commands and the plan
        decides the follow-through, as in ``_act``); without one, or once its time has passed, no
        new segment (the supervisor keeps its plan, which
        ends at the reset pose)."""
        hit = flight.hit
        if hit is None:
            return _no_action
        to_hit = hit.time - flight.clock
        if to_hit < self.lead + self.lag + 0.5 * self.segment:
            if self._plan_follows and to_hit > self.lead + self.lag - 0.5 * self.segment:
                return functools.partial(self.driver.follow_through, q0, v0, a0)  # the hit happens in this segment
            flight.hit = None  # its time has passed
            return _no_action
        self.last_plan = hit
        return functools.partial(self.driver.drive, q0, v0, a0, hit.q, hit.v, to_hit - self.lag - self.lead)  # steps 5-6

    def _advance(self, estimate: np.ndarray | None) -> Flight:
        """The memory for this call: the clock advanced by one segment, or a fresh memory when the
        estimate is far from where the last prediction put the ball now (a new ball)."""
        if not self.params.memory:
            # Nothing carried over: the bounce, if behind, from the estimate alone.
            return Flight(bounce_time=self.predictor.bounce_behind(estimate) if estimate is not None else None)
        flight = self._flight
        if flight is not None:
            flight.clock += self.segment
            if estimate is not None and flight.prediction_times is not None:
                expected = np.array([np.interp(flight.clock, flight.prediction_times, flight.prediction_positions[:, i]) for i in range(3)])
                if np.linalg.norm(expected - estimate[:3]) > SAME_BALL_DISTANCE or flight.clock > flight.prediction_times[-1] + self.segment:
                    flight = None
        if flight is None:
            flight = Flight()
        if "bounce" in self.params.forget and estimate is not None:
            behind = self.predictor.bounce_behind(estimate)  # as the memoryless returner finds it
            flight.bounce_time = None if behind is None else flight.clock + behind
        self._flight = flight
        return flight

    # ------------------------------------------------------------------------------ prediction
    def _plan_hit(self, flight: Flight, candidates: list[int], prediction: Prediction, q0: np.ndarray, v0: np.ndarray, target: np.ndarray,
                  brush: float) -> HitPlan | None:
        """The most preferred candidate hit (``HitPredictor.candidates``) with a racket state the joints can
        make (sending the ball to ``target`` with the racket brushing at ``brush`` m/s) and reach in time (the cubic from the segment start within the acceleration limits);
        if none is in time, the previous plan's hit time if it is still possible (a late switch
        costs more than a late arrival), else the one that needs the least acceleration."""
        limits, forget = self.stack.limits, self.params.forget
        best, best_ratio = None, np.inf
        for index in candidates[: self.params.candidates_tried]:
            hit_time = flight.clock + prediction.times[index]
            duration = prediction.times[index] - self.lag - self.lead  # from the segment start to the hit's boundary, s
            same_hit = flight.hit is not None and abs(flight.hit.time - hit_time) < 1e-6
            previous = flight.hit if same_hit and "ik" not in forget else None
            previous_racket = flight.hit.racket if same_hit and "racket" not in forget else None
            nominal = self._ik_nominal(q0, v0, duration)
            for racket in racket_plans(prediction.states[index], hit_time, self.physics, target, self.params, previous_racket, brush):
                q_hit = self._hit_configuration(racket, nominal, previous)
                if q_hit is None:
                    break  # the position is out of reach: try another hit time
                previous = HitPlan(hit_time, racket, q_hit, np.zeros(8))  # seeds the next flight time's IK
                v_hit = racket_joint_velocities(self.model, q_hit, racket.velocity)
                if np.any(np.abs(v_hit) > limits.velocity) or not np.all(in_invariant_set(q_hit, v_hit, limits, self.stack.control, self.stack.period)):
                    continue  # too fast for the joints: a slower return
                ratio = float(np.max(hermite_peak_acceleration(q0, v0, q_hit, v_hit, duration) / limits.acceleration))
                if ratio <= 1.0:
                    return HitPlan(hit_time, racket, q_hit, v_hit)
                if same_hit and "fallback" not in forget:
                    ratio = 0.0  # the plan being executed stays the fallback
                if ratio < best_ratio:
                    best, best_ratio = HitPlan(hit_time, racket, q_hit, v_hit), ratio
                break
        return best

    def _ik_nominal(self, q0: np.ndarray, v0: np.ndarray, duration: float) -> np.ndarray:
        """Where a full IK solve for a hit ``duration`` s after the segment start starts
        (``ReturnerParams.ik_nominal``): the segment start q0, or with "braking" the arm's joints
        at q0 + v0 D / 2 (uniform braking from v0 to rest over D stops there; the gantry stays at
        q0), inside the joint limits. A moving arm's solution then stays on the branch it is moving
        towards instead of hopping between nearly equidistant ones from call to call (measured:
        docs/experiments/2026-12-01-returner-memory.md)."""
        if self.params.ik_rule == "segment_start":
            return q0
        step = np.where(self.model.revolute, 0.5 * v0 * max(duration, 0.0), 0.0)
        return np.clip(q0 + step, self.model.lower, self.model.upper)

    def _hit_configuration(self, racket: RacketPlan, nominal: np.ndarray, previous: HitPlan | None) -> np.ndarray | None:
        """q_hit for the racket plan: the previous plan's configuration moved onto it
        (``refine_hit_ik``) when there is one, else (or if that fails) the full IK
        (``solve_hit_ik``, nearest ``nominal``: ``_ik_nominal``) from the previous solution,
        ``nominal`` and the default seeds, within the call's budget of ``ik_solves_per_call``
        solves."""
        if previous is not None:
            q = refine_hit_ik(self.model, previous.q, racket.position, racket.normal)
            if q is not None:
                return q
        seeds = [nominal] if previous is None else [previous.q, nominal]
        for attempt in (seeds, [self.model.seed_for(racket.position, roll) for roll in (0.0, 1.5, -1.5)]):
            if self._ik_budget <= 0:
                return None  # this call has spent its budget (a failing IK can take 60 ms a seed)
            self._ik_budget -= 1
            ik = solve_hit_ik(self.model, racket.position, racket.normal, nominal, attempt, self.params.ik_clearance)
            if ik.success:
                return ik.q
        return None
