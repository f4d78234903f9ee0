"""Driving the joints to a hit state: the returner's last step, and the hit-state action of a
learned actor (docs/training.md, *Hit-state actor*; this project's, not the paper's).

A hit state is the joints' (q_hit, v_hit) (8 each) at the instant the racket meets the ball.
``HitDriver`` turns one into the next segment's eq. (12) action from the segment-start state
(q0, v0, a0): along the cubic Hermite from (q0, v0) to (q_hit, v_hit) over the D seconds to the
hit's segment boundary, evaluated one segment T ahead, through the inverse of the eq. (12)
mapping (``action_mapping.inverse_map_action``: a target outside the feasible set maps onto its
boundary), checked as the safety supervisor will check it (``ControlStack.propose``), with the
time-optimal approach to q_hit (``ControlStack.action_towards``) as the fallback. When the hit
falls in the segment being commanded it follows through at the current joint velocities.

``HitStateAction`` reads a 16-vector y in [-1, 1]^16 as a hit state relative to the segment start:

    q_hit = q0 + y_q (upper - lower) / 2,    v_hit = y_v v_max                    (per joint)

(so that y = 0 is "stay where you are, stopped", and the box covers every reachable q_hit from
any q0 inside the limits). ``HitStateLayer`` is the fixed layer between such an actor and the
control stack: the hit is the observation's ``hit_prediction`` (the memoryless returner's
preferred hit, ``control.hit_prediction``) at t_p seconds, whose boundary is k segments ahead,
k = round((t_p - lead - lag) / T), D = k T (the predictor samples hits on that grid); k <= 0
follows through; no predicted hit gives no action (the supervisor resets).

A layer built to meet the ball (``meet_ball``; ``sac.PlayOptions.meet_ball``) also moves q_hit so
the blade centre sits at the contact standoff behind the predicted hit's ball position along the
blade's own normal, the blade's orientation kept: Gauss-Newton steps on the racket Jacobian J
(6 x 8), weighted as the returner weights its joint velocities (W = diag(v_max^2)),

    dq = W J^T (J W J^T + lambda I)^-1 [0; p_ball - s n(q) - p(q)],    q <- clip(q + dq)

so the actor chooses how to hit (the normal, the velocity, the arm's redundant posture) and the
layer makes the blade meet the ball where the predictor says it will be. A cloned actor's blade
centre sits 3.3 cm (median; 9.4 cm at the 90th percentile, against a blade radius of about
7.5 cm) off the line through the predicted ball along its normal, the returner's within 2 mm
(docs/experiments/2026-12-01-hit-state-actor.md).

``PlannedHitState`` is the memoryless returner's planned hit state as such an action: the
demonstrator and the labels of a hit-state actor (``training.rollout``), and with the layer a
controller (``returner:hit_state`` in ``analysis.experiments``: the layer's ceiling, what an actor
that imitated the returner's hit states perfectly would do).

Why: an actor that outputs eq. (12)'s per-segment terminal states must re-derive the whole swing
every 32 ms and its errors from call to call make the swing jitter; one that outputs the hit
state names the same target all along, and this layer makes the motion (docs/training.md, *Hit-state actor*).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import inverse_map_action, is_valid_action
from ace_drake.control.feasible_set import InfeasibleStartError, feasible_sets
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.stack import ControlStack, make_control_stack
from ace_drake.physics.contact import blade_standoff
from ace_drake.robot.model import RobotModel, load_scenario

HIT_STATE_SIZE = 16  # [y_q (8), y_v (8)]


def hermite(q0: np.ndarray, v0: np.ndarray, q1: np.ndarray, v1: np.ndarray, duration: float, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity at time t (s) of the cubic Hermite from (q0, v0) at 0 to (q1, v1) at
    ``duration`` (s), per joint; at and after ``duration`` the straight continuation
    (q1 + v1 (t - duration), v1)."""
    if t >= duration:
        return q1 + v1 * (t - duration), np.array(v1, dtype=float)
    s = t / duration
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    q = h00 * q0 + h10 * duration * v0 + h01 * q1 + h11 * duration * v1
    v = (d00 * q0 + d01 * q1) / duration + d10 * v0 + d11 * v1
    return q, v


def hermite_peak_acceleration(q0, v0, q1, v1, duration: float) -> np.ndarray:
    """The largest |acceleration| (8,) of the cubic Hermite of ``hermite`` (linear in time: the
    larger of its two ends)."""
    if duration <= 0.0:
        return np.full(np.shape(q0), np.inf)
    delta = np.asarray(q1) - np.asarray(q0)
    start = (6.0 * delta - (4.0 * np.asarray(v0) + 2.0 * np.asarray(v1)) * duration) / duration**2
    end = (-6.0 * delta + (2.0 * np.asarray(v0) + 4.0 * np.asarray(v1)) * duration) / duration**2
    return np.maximum(np.abs(start), np.abs(end))


class HitDriver:
    """The eq. (12) action of the next segment towards a hit state (module docstring), on a
    control stack like the supervisor's. ``last_choice``: which action the last call sent (0 the
    planned one, 1 the fallback, -1 none)."""

    def __init__(self, stack: ControlStack):
        self.stack = stack
        self.segment = stack.segment_duration
        self.last_choice = -1

    def action_to(self, q0, v0, a0, q_target, v_target) -> np.ndarray | None:
        """The action (16,) whose eq. (12) image from the segment start (q0, v0, a0) is (q_target,
        v_target), or the boundary point on its ray when outside the feasible set; None when the
        start state has no feasible set."""
        try:
            sets = feasible_sets(q0, v0, a0, self.stack.limits, self.stack.control, self.stack.period)
        except InfeasibleStartError:
            return None
        return np.clip(inverse_map_action(q_target, v_target, sets), -1.0, 1.0)

    def first_safe(self, q0, v0, a0, actions: Sequence[Callable[[], np.ndarray | None]]) -> np.ndarray | None:
        """The first of ``actions`` (callables returning an action or None, in order of
        preference) whose segment and reset the control stack accepts (``ControlStack.propose``:
        the supervisor's own test, so an action sent is an action executed), or None when none is
        (the supervisor then keeps its plan, as it would on a refusal). Without a collision check
        in the stack, the first action."""
        self.last_choice = -1
        for choice, make in enumerate(actions):
            try:
                action = make()
            except InfeasibleStartError:
                action = None
            if action is None:
                continue
            if self.stack.collision_check is None or self.stack.propose(q0, v0, a0, action).safe:
                self.last_choice = choice
                return action
        return None

    def follow_through(self, q0, v0, a0) -> np.ndarray | None:
        """The action that carries the joints on at their velocities v0 for one segment (the hit
        falls inside it), if the stack accepts it."""
        return self.first_safe(q0, v0, a0, [lambda: self.action_to(q0, v0, a0, q0 + v0 * self.segment, v0)])

    def drive(self, q0, v0, a0, q_hit, v_hit, duration: float) -> np.ndarray | None:
        """The action one segment along the Hermite from (q0, v0) to (q_hit, v_hit) ``duration``
        s after the segment starts, else the time-optimal approach to q_hit, else None (module
        docstring)."""
        q_target, v_target = hermite(q0, v0, q_hit, v_hit, duration, self.segment)
        return self.first_safe(q0, v0, a0, [
            lambda: self.action_to(q0, v0, a0, q_target, v_target),
            lambda: self.stack.action_towards(q0, v0, a0, q_hit),
        ])


@dataclasses.dataclass(frozen=True)
class HitStateAction:
    """The hit-state parameterisation of the module docstring: ``half_range`` (upper - lower) / 2
    (8; rad or m) and ``velocity`` v_max (8; rad/s or m/s) of the command limits. Its maps work on
    NumPy arrays and on torch tensors alike (the learner's cloning loss runs them in torch)."""

    half_range: np.ndarray
    velocity: np.ndarray

    @classmethod
    def from_limits(cls, limits) -> HitStateAction:
        """From a ``trajectory.CommandLimits``."""
        return cls(0.5 * (np.asarray(limits.upper) - np.asarray(limits.lower)), np.asarray(limits.velocity, dtype=float))

    @classmethod
    def from_dict(cls, data: dict) -> HitStateAction:
        return cls(np.asarray(data["half_range"], dtype=float), np.asarray(data["velocity"], dtype=float))

    def hit_state(self, y, q0):
        """(q_hit, v_hit) (..., 8 each) of hit-state actions y (..., 16) from segment starts q0 (..., 8)."""
        half_range, velocity = _like(self.half_range, y), _like(self.velocity, y)
        return q0 + y[..., :8] * half_range, y[..., 8:] * velocity

    def coordinates(self, q_hit, v_hit, q0) -> np.ndarray:
        """The hit-state action y (..., 16) of (q_hit, v_hit) from q0, clipped into [-1, 1]."""
        y = np.concatenate([(np.asarray(q_hit) - q0) / self.half_range, np.asarray(v_hit) / self.velocity], axis=-1)
        return np.clip(y, -1.0, 1.0)

    def as_dict(self) -> dict:
        return {"half_range": self.half_range.tolist(), "velocity": self.velocity.tolist()}

    def matches(self, other: HitStateAction) -> bool:
        return bool(np.allclose(self.half_range, other.half_range) and np.allclose(self.velocity, other.velocity))


def _like(array: np.ndarray, reference):
    """``array`` as a tensor of ``reference``'s dtype when that is a torch tensor, else itself."""
    if type(reference).__module__.startswith("torch"):
        import torch  # lazy: only a torch caller (the cloning loss) reaches here; control is NumPy

        return torch.as_tensor(array, dtype=reference.dtype)
    return array


def steps_to_hit(hit_time, lead: float, lag: float, segment: float):
    """k = round((t_p - lead - lag) / T) (module docstring): the segments from the observation's
    segment start to the boundary where the joints must be at the hit state, for a hit
    ``hit_time`` s after the observation (lead, lag, segment T in s). An int, or an array of
    them; for a torch tensor of times (the cloning loss's), a tensor of rounded floats. Both
    round half to even."""
    ratio = (hit_time - lead - lag) / segment
    if type(hit_time).__module__.startswith("torch"):
        import torch  # lazy: only a torch caller (the cloning loss) reaches here; control is NumPy

        return torch.round(ratio)
    return np.rint(np.asarray(ratio)).astype(int)


class HitStateLayer:
    """The fixed layer from a hit-state action to the control stack's action (module docstring):
    ``layer(observation, y) -> action (16,) | None``."""

    MEET_ITERATIONS = 3  # Gauss-Newton steps of meet_ball (each one FK and one Jacobian)
    MEET_DAMPING = 1e-6  # lambda of meet_ball (m^2; keeps the step bounded near singular postures)

    def __init__(self, driver: HitDriver, layout: ObservationLayout, lead: float, lag: float, model=None, standoff: float = 0.0):
        """``driver`` on the supervisor's stack, the observation layout, the observation lead (s)
        and the joints' lag (s, ``hit_prediction.joint_lag``); with a RobotModel ``model``, the
        layer meets the ball (module docstring) with the blade centre ``standoff`` m behind it."""
        self.driver, self.layout, self.lead, self.lag = driver, layout, lead, lag
        self.segment = driver.segment
        self.parameterisation = HitStateAction.from_limits(driver.stack.limits)
        self.model, self.standoff = model, float(standoff)

    @property
    def meets_ball(self) -> bool:
        return self.model is not None

    def with_parameterisation(self, parameterisation: HitStateAction) -> HitStateLayer:
        """A copy of this layer that reads actions in ``parameterisation``'s coordinates (a
        policy's own, trained with other command limits); the stack's limits still bound every
        q_hit and command."""
        layer = copy.copy(self)
        layer.parameterisation = parameterisation
        return layer

    @classmethod
    def for_rally(cls, rally, meet_ball: bool = False) -> HitStateLayer:
        """The layer for the rally diagram of ``rally`` (a RallyParams): the supervisor's stack
        (``control.stack.make_control_stack``), its layout, and the lead and lag of the diagram's own
        hit predictor (``diagrams``: ``HitPredictor.for_robot`` with default ReturnerParams);
        ``meet_ball``: the layer meets the ball (module docstring). Raises ConfigError if
        ``rally`` does not compute the observation's hit prediction, which the layer plays."""

        if not rally.hit_prediction:
            raise ConfigError("the hit-state layer plays the observation's predicted hit: build its diagram with RallyParams.hit_prediction true")

        scenario = load_scenario(MODELS_DIR / rally.scenario)
        predictor = HitPredictor.for_robot(scenario, rally.control, rally.physics)
        model = RobotModel(scenario) if meet_ball else None
        return cls(HitDriver(make_control_stack(scenario, rally.control)), ObservationLayout(rally.position_history, rally.spin_history),
                   predictor.lead, predictor.lag, model, blade_standoff(rally.physics.aero.ball_radius, rally.physics.racket))

    def meet_ball(self, q_hit: np.ndarray, ball_position: np.ndarray) -> np.ndarray:
        """q_hit (8,) moved so that the blade centre sits ``standoff`` behind ``ball_position``
        (3,; m) along the blade's normal, its orientation kept (module docstring), inside the
        command limits."""
        limits = self.driver.stack.limits
        weights = self.model.velocity_limit**2
        q = np.array(q_hit, dtype=float)
        for _ in range(self.MEET_ITERATIONS):
            X_WR = self.model.racket_pose(q)
            error = ball_position - self.standoff * X_WR.rotation().matrix()[:, 2] - X_WR.translation()
            jacobian = self.model.racket_jacobian(q)
            weighted = jacobian * weights  # J W
            step = weighted.T @ np.linalg.solve(weighted @ jacobian.T + self.MEET_DAMPING * np.eye(6), np.r_[np.zeros(3), error])
            q = np.clip(q + step, limits.lower, limits.upper)
        return q

    def steps_to_hit(self, hit_time):
        """k (``steps_to_hit``) for this layer's lead, lag and segment."""
        return steps_to_hit(hit_time, self.lead, self.lag, self.segment)

    def __call__(self, observation: np.ndarray, y: np.ndarray | None) -> np.ndarray | None:
        """The action (16,) for the actor's hit-state action ``y``, or None (no new segment).
        An actor's output that is not 16 finite numbers is returned as it is, before the layer
        computes anything from it, so that whoever executes it (the PolicyController, a
        RallyEnv's request) counts it as an invalid action exactly as a plain policy's; None from
        the actor is None (it wants no new segment)."""
        if y is None:
            return None
        if not is_valid_action(y):
            return y
        observation = np.asarray(observation, dtype=float)
        hit = self.layout.part(observation, "hit_prediction")
        if hit[0] < 0.5:
            return None  # no predicted hit: no new segment (the supervisor resets)
        q0, v0, a0 = np.split(self.layout.part(observation, "robot_state"), 3)
        steps = int(self.steps_to_hit(hit[1]))
        if steps <= 0:
            return self.driver.follow_through(q0, v0, a0)
        q_hit, v_hit = self.parameterisation.hit_state(np.clip(np.asarray(y, dtype=float), -1.0, 1.0), q0)
        q_hit = np.clip(q_hit, self.driver.stack.limits.lower, self.driver.stack.limits.upper)
        if self.meets_ball:
            q_hit = self.meet_ball(q_hit, hit[2:5])
        return self.driver.drive(q0, v0, a0, q_hit, v_hit, steps * self.segment)


class PlannedHitState:
    """The memoryless returner's planned hit state as a hit-state action (module docstring).
    ``plan(observation)`` gives (the planned y or None, whether the plan's hit is the observation's
    predicted one, the returner's own action or None); calling it is the controller that plays the
    planned y through ``layer`` (the returner's own action where it plans no hit)."""

    def __init__(self, returner, layer: HitStateLayer, hit_memory: bool = False):
        """``returner``: a ``ModelBasedReturner`` without memory (its plan must be a function of
        the observation); ``layer``: the rally diagram's HitStateLayer; ``hit_memory``: the
        observation keeps its predicted hit (``RallyParams.hit_memory``), and the returner plans
        that hit first (``ModelBasedReturner.plan``'s ``follow_observed_hit``), so that the memory
        lives in the observation alone."""
        if returner.params.memory:
            raise ValueError("PlannedHitState: the returner must be memoryless (ReturnerParams.memory false)")
        self.returner, self.layer, self.hit_memory = returner, layer, hit_memory

    def reset(self) -> None:
        self.returner.reset()

    def plan(self, observation: np.ndarray) -> tuple[np.ndarray | None, bool, np.ndarray | None]:
        """(y (16,) of the returner's planned hit from the segment start, or None when it plans
        none or nothing is predicted; whether its hit time is the predicted hit's, within half a
        segment; the returner's action where there is no y, else None: a plan played through the
        layer is not also driven the returner's way, ``ModelBasedReturner.plan``). A plan for a
        later hit (the predicted one needs too much acceleration) still gives y: the layer aims
        it at the predicted hit."""
        observation = np.asarray(observation, dtype=float)
        plan, returner_action = self.returner.plan(observation, follow_observed_hit=self.hit_memory)
        hit = self.layer.layout.part(observation, "hit_prediction")
        if plan is None or hit[0] < 0.5:
            return None, False, returner_action()
        q0 = self.layer.layout.part(observation, "robot_state")[:8]
        return self.layer.parameterisation.coordinates(plan.q, plan.v, q0), abs(plan.time - hit[1]) <= 0.5 * self.segment, None

    @property
    def segment(self) -> float:
        return self.layer.segment

    def __call__(self, observation: np.ndarray) -> np.ndarray | None:
        planned, _, action = self.plan(observation)
        return action if planned is None else self.layer(observation, planned)
