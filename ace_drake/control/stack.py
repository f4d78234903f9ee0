"""One control step of the rally controller (paper, Fig. 1c and Methods *Feasible action for
optimal control*, *Reset trajectories*), as plain Python shared by the Drake systems, the
benchmarks and the tutorial.

Every 32 ms the policy's action (16,) becomes a proposal:

    feasible sets at the segment's start state -> eq. (12) mapping -> spline QP (segment)
        -> reset to the stationary reset pose (Ruckig) -> collision check of segment + reset,

and the supervisor executes segment + reset only if every stage succeeded and the motion is
collision-free; otherwise it keeps the plan it has, whose reset was checked when it was accepted
(the paper's fallback to the previous reset). A plan is therefore always a collision-free motion
within the command limits that ends at rest.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable

import numpy as np

from ace_drake.control.action_mapping import inverse_map_action, map_action
from ace_drake.control.feasible_set import InfeasibleStartError, feasible_sets, feasible_sets_batch, in_invariant_set
from ace_drake.control.params import ControlParams
from ace_drake.control.reset import ResetPlanner
from ace_drake.control.spline_qp import SegmentQp
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import RobotScenario
from ace_drake.robot.trajectory import JointTrajectory


@dataclasses.dataclass(frozen=True)
class Stage:
    """The outcome of one stage of a control step: ``value`` when ``ok``, else ``reason``."""

    ok: bool
    value: object = None
    reason: str = ""


NO_ACTION = "no action"  # the reason of a Stage that had nothing to work on: no refusal


@dataclasses.dataclass(frozen=True)
class SegmentDecision:
    """The safety supervisor's decision at a segment boundary (``decide_segment``): ``plan``, the
    new segment then its reset, to execute from the boundary, or None to keep the current plan;
    ``reason``: why not ("" when accepted; NO_ACTION when nothing was proposed)."""

    plan: JointTrajectory | None
    reason: str = ""

    @property
    def accepted(self) -> bool:
        return self.plan is not None

    @property
    def refused(self) -> bool:
        """A proposal refused (counted as such); no action is not one."""
        return self.plan is None and self.reason != NO_ACTION


def decide_segment(stack: ControlStack, segment: Stage, reset: Stage) -> SegmentDecision:
    """What the safety supervisor does with a proposal's last two stages (module docstring): the
    segment then its reset, if both exist and the plan is collision-free (``ControlStack.check``);
    otherwise keep the current plan, for the first failed stage's reason. The one copy of that
    rule: the SafetySupervisor runs it on its input ports' stages, ``ControlStack.propose`` (so the
    benchmarks and controllers that ask it) on its own."""
    if not segment.ok or not reset.ok:
        return SegmentDecision(None, segment.reason if not segment.ok else reset.reason)
    plan = segment.value.then(reset.value)
    checked = stack.check(plan)
    if not checked.ok:
        return SegmentDecision(None, checked.reason)
    return SegmentDecision(plan)


@dataclasses.dataclass(frozen=True)
class Proposal:
    """What one action would make the robot do: ``plan`` = segment then reset when ``safe``.

    reason: why it is not safe ("" when it is); target: the mapped terminal (q_T, v_T) (8,) each,
    or None if the mapping failed; seconds: wall time of each stage, s (for benchmarks);
    decision: the supervisor's decision on it (``decide_segment``; ``safe`` is its ``accepted``).
    """

    safe: bool
    reason: str
    plan: JointTrajectory | None
    segment: JointTrajectory | None
    reset: JointTrajectory | None
    target: tuple[np.ndarray, np.ndarray] | None
    seconds: dict[str, float]
    decision: SegmentDecision | None = None


@dataclasses.dataclass(frozen=True)
class BatchProposal:
    """``ControlStack.propose_batch``'s proposals for B environments; entry b is what
    ``propose`` returns for row b (``proposal(b)``).

    safe (B,) booleans and reason (B strings: "" when safe); plan, segment, reset (B each,
    JointTrajectory or None); mapped (B,) booleans: whether the mapping succeeded, and then
    target_q, target_v (B, 8) the mapped terminal state (NaN where it did not); seconds: wall
    time of each stage for the whole batch, s (for benchmarks).
    """

    safe: np.ndarray
    reason: list[str]
    plan: list[JointTrajectory | None]
    segment: list[JointTrajectory | None]
    reset: list[JointTrajectory | None]
    mapped: np.ndarray
    target_q: np.ndarray
    target_v: np.ndarray
    seconds: dict[str, float]

    def __len__(self) -> int:
        return self.safe.shape[0]

    def proposal(self, row: int) -> Proposal:
        """Row ``row`` as a Proposal (its ``seconds`` are the batch's)."""
        target = (self.target_q[row], self.target_v[row]) if self.mapped[row] else None
        decision = SegmentDecision(self.plan[row], self.reason[row])
        return Proposal(bool(self.safe[row]), self.reason[row], self.plan[row], self.segment[row], self.reset[row], target, dict(self.seconds), decision)


class ControlStack:
    """The mapping, segment QP, reset planner and collision check, built once.

    ``collision_check`` is any callable taking a JointTrajectory and returning a
    ``robot.collision.CollisionReport`` (``TrajectoryCollisionChecker.check``); None checks nothing
    (for studies of the maths alone). Joint vectors are in JOINT_NAMES order.
    """

    def __init__(
        self,
        scenario: RobotScenario | None = None,
        control: ControlParams | None = None,
        collision_check: Callable[[JointTrajectory], object] | None = None,
    ):
        self.scenario = scenario or RobotScenario()
        self.control = control or ControlParams()
        self.period = self.scenario.dynamics.command_period
        self.limits = CommandLimits.from_config(self.scenario.limits, self.control)
        self.reset_pose = np.asarray(self.control.reset_pose or self.scenario.ready_pose, dtype=float)
        if np.any(self.reset_pose < self.limits.lower) or np.any(self.reset_pose > self.limits.upper):
            raise ValueError(f"ControlStack: the reset pose {self.reset_pose} is outside the command limits [{self.limits.lower}, {self.limits.upper}]")
        self.qp = SegmentQp(self.limits, self.control.segment_samples, self.period, self.control.knot_samples, self.control.qp_solver)
        self.resets = ResetPlanner(self.limits, self.period)
        self.collision_check = collision_check
        self._initial_plans: dict = {}  # initial_plan's results by their exact inputs (see there)
        self._twice_braking = 2.0 * (self.control.stop_fraction * self.limits.acceleration)  # 2 A_s (action_towards)

    @property
    def segment_duration(self) -> float:
        """T, s: one policy step."""
        return self.control.segment_samples * self.period

    # ------------------------------------------------------------------------------ the stages
    def map(self, q, v, a, action) -> Stage:
        """Feasible sets at (q, v, a) and the eq. (12) mapping of ``action`` (16,): value
        (q_T, v_T), (8,) each."""
        try:
            sets = feasible_sets(q, v, a, self.limits, self.control, self.period)
        except InfeasibleStartError as error:
            return Stage(False, reason=f"infeasible start: {error}")
        return Stage(True, map_action(action, sets))

    def segment(self, q, v, a, target: tuple[np.ndarray, np.ndarray]) -> Stage:
        """The spline QP from (q, v, a) to the target (q_T, v_T): value the segment."""
        solution = self.qp.solve(q, v, a, *target)
        if not solution.success:
            return Stage(False, reason=f"segment QP failed: {solution.status}")
        return Stage(True, solution.trajectory)

    def reset(self, segment: JointTrajectory) -> Stage:
        """The reset from the segment's end to the reset pose: value the reset trajectory."""
        try:
            return Stage(True, self.resets.plan_reset(*segment.state(-1), self.reset_pose))
        except RuntimeError as error:
            return Stage(False, reason=f"reset planning failed: {error}")

    def check(self, plan: JointTrajectory) -> Stage:
        """The collision check of a whole plan: value the checker's report (None unchecked)."""
        if self.collision_check is None:
            return Stage(True)
        report = self.collision_check(plan)
        if report.free:
            return Stage(True, report)
        if not report.pairs:  # nothing found closing: the budget ran out before a proof
            return Stage(False, report, f"collision check over its budget: proven clear for {report.time:.3f} s of {plan.duration:.3f} s")
        return Stage(False, report, f"collision predicted: {report}")

    def propose(self, q, v, a, action) -> Proposal:
        """The proposal for ``action`` (16,) in [-1, 1] from the segment's start state (q, v, a):
        the stages in order as the diagram's systems run them (ActionMapper, SplineQp, ResetMpc:
        a failed stage passes its reason on), stopping at the first that fails, and the
        supervisor's decision on them (``decide_segment``: the collision check)."""
        seconds: dict[str, float] = {}

        def timed(name: str, stage_function, *args):
            start = time.perf_counter()
            stage = stage_function(*args)
            seconds[name] = time.perf_counter() - start
            return stage

        mapped = timed("map", self.map, q, v, a, action)
        target = mapped.value if mapped.ok else None
        segment = timed("segment", self.segment, q, v, a, target) if mapped.ok else Stage(False, reason=mapped.reason)
        reset = timed("reset", self.reset, segment.value) if segment.ok else Stage(False, reason=segment.reason)
        if reset.ok:
            decision = timed("check", decide_segment, self, segment, reset)
        else:
            decision = decide_segment(self, segment, reset)
        return Proposal(decision.accepted, decision.reason, decision.plan, segment.value if segment.ok else None,
                        reset.value if reset.ok else None, target, seconds, decision)

    def map_batch(self, q, v, a, actions) -> list[Stage]:
        """``map`` for B starts (q, v, a) (B, 8) each and actions (B, 16): the Stages (B,), the
        feasible sets of every row at once (``feasible_sets_batch``)."""
        q, v, a = (np.asarray(x, dtype=float) for x in (q, v, a))
        actions = np.asarray(actions, dtype=float)
        stages = [Stage(False)] * q.shape[0]
        if not q.shape[0]:
            return stages
        sets, mapped, infeasible = feasible_sets_batch(q, v, a, self.limits, self.control, self.period)
        if mapped.all():  # the common case: every row (no copies of the sets)
            target_q, target_v = map_action(actions, sets)
            return [Stage(True, (target_q[row], target_v[row])) for row in range(q.shape[0])]
        for row in np.flatnonzero(~mapped):
            stages[row] = Stage(False, reason=f"infeasible start: {infeasible[row]}")
        rows = np.flatnonzero(mapped)
        if rows.size:
            target_q, target_v = map_action(actions[rows], sets[rows])
            for index, row in enumerate(rows):
                stages[row] = Stage(True, (target_q[index], target_v[index]))
        return stages

    def segment_batch(self, q, v, a, targets: list[Stage]) -> list[Stage]:
        """``segment`` for B starts (q, v, a) (B, 8) each and the mapping's Stages (B,): a failed
        target passes its reason on; the others' QPs at once (``SegmentQp.solve_batch``)."""
        stages = [Stage(False, reason=target.reason) if not target.ok else None for target in targets]
        rows = [row for row, stage in enumerate(stages) if stage is None]
        if rows:
            q, v, a = (np.asarray(x, dtype=float) for x in (q, v, a))
            if len(rows) < len(targets):
                q, v, a = q[rows], v[rows], a[rows]
            target_q = np.array([targets[row].value[0] for row in rows])
            target_v = np.array([targets[row].value[1] for row in rows])
            solved = self.qp.solve_batch(q, v, a, target_q, target_v)
            for index, row in enumerate(rows):
                if solved.success[index]:
                    stages[row] = Stage(True, JointTrajectory(self.period, solved.q[index], solved.v[index], solved.a[index]))
                else:
                    stages[row] = Stage(False, reason=f"segment QP failed: {solved.status[index]}")
        return stages

    def reset_batch(self, segments: list[Stage]) -> list[Stage]:
        """``reset`` for the QP's Stages (B,): a failed segment passes its reason on; the others'
        resets planned at once (``ResetPlanner.plan_reset_batch``)."""
        stages = [Stage(False, reason=segment.reason) if not segment.ok else None for segment in segments]
        rows = [row for row, stage in enumerate(stages) if stage is None]
        if rows:
            ends = [segments[row].value.state(-1) for row in rows]
            planned, errors = self.resets.plan_reset_batch(*(np.array([end[k] for end in ends]) for k in range(3)), self.reset_pose)
            for row, reset, error in zip(rows, planned, errors):
                stages[row] = Stage(True, reset) if reset is not None else Stage(False, reason=f"reset planning failed: {error}")
        return stages

    def propose_batch(self, q, v, a, actions) -> BatchProposal:
        """``propose`` for B environments at once: start states (q, v, a) (B, 8) each, actions
        (B, 16) in [-1, 1]. The stages run in the same order with the same reasons, each on the
        rows that reached it (``map_batch``, ``segment_batch``, ``reset_batch``), then the
        collision check of each row's plan in turn (``decide_segment``)."""
        q, v, a = (np.asarray(x, dtype=float) for x in (q, v, a))
        actions = np.asarray(actions, dtype=float)
        if q.ndim != 2 or q.shape[1:] != (8,) or v.shape != q.shape or a.shape != q.shape or actions.shape != (q.shape[0], 16):
            raise ValueError(f"propose_batch: q, v, a must be (B, 8) and actions (B, 16), got shapes {q.shape}, {v.shape}, {a.shape}, {actions.shape}")
        rows = q.shape[0]
        seconds: dict[str, float] = {}
        start = time.perf_counter()
        targets = self.map_batch(q, v, a, actions)
        seconds["map"] = time.perf_counter() - start
        if any(target.ok for target in targets):
            start = time.perf_counter()
            segments = self.segment_batch(q, v, a, targets)
            seconds["segment"] = time.perf_counter() - start
        else:
            segments = [Stage(False, reason=target.reason) for target in targets]
        if any(segment.ok for segment in segments):
            start = time.perf_counter()
            resets = self.reset_batch(segments)
            seconds["reset"] = time.perf_counter() - start
        else:
            resets = [Stage(False, reason=segment.reason) for segment in segments]
        plans: list[JointTrajectory | None] = [None] * rows
        reason = [reset.reason for reset in resets]
        if any(reset.ok for reset in resets):
            start = time.perf_counter()
            for row in range(rows):
                if resets[row].ok:
                    decision = decide_segment(self, segments[row], resets[row])
                    plans[row], reason[row] = decision.plan, decision.reason
            seconds["check"] = time.perf_counter() - start
        mapped = np.array([target.ok for target in targets], dtype=bool)
        target_q = np.array([target.value[0] if target.ok else np.full(8, np.nan) for target in targets]).reshape(rows, 8)
        target_v = np.array([target.value[1] if target.ok else np.full(8, np.nan) for target in targets]).reshape(rows, 8)
        safe = np.array([plan is not None for plan in plans], dtype=bool)
        return BatchProposal(safe, reason, plans, [s.value if s.ok else None for s in segments], [r.value if r.ok else None for r in resets],
                             mapped, target_q, target_v, seconds)

    def action_towards(self, q, v, a, q_goal) -> np.ndarray:
        """An action (16,) that moves the joints from the start (q, v, a) towards q_goal (8,)
        about as fast as the limits allow (for controllers that think in joint targets): each
        joint aims at the velocity of the braking curve to its goal, v* = sign(e) min(V,
        sqrt(2 A_s |e|)) with e = q_goal - q, i.e. at the terminal state (q + (v + v*) T / 2, v*),
        through the inverse mapping, clipped onto the action box (a target outside the feasible
        set gives the boundary point in its direction). The start must lie in the control-
        invariant set (InfeasibleStartError otherwise)."""
        q, v = np.asarray(q, dtype=float), np.asarray(v, dtype=float)
        sets = feasible_sets(q, v, a, self.limits, self.control, self.period)
        error = np.asarray(q_goal, dtype=float) - q
        v_target = np.sign(error) * np.minimum(self.limits.velocity, np.sqrt(self._twice_braking * np.abs(error)))
        q_target = q + 0.5 * (v + v_target) * self.segment_duration
        return np.minimum(np.maximum(inverse_map_action(q_target, v_target, sets), -1.0), 1.0)  # np.clip without its overhead

    def protective_stop(self, q, v, a) -> tuple[JointTrajectory, bool]:
        """The fastest stop within the command limits from (q, v, a), and whether it is
        collision-free (if not, the caller keeps its checked plan instead)."""
        stop = self.resets.plan_stop(q, v, a)
        return stop, self.check(stop).ok

    def initial_plan(self, q, v=None, a=None) -> tuple[JointTrajectory, bool]:
        """A plan to start from at (q, v, a) (v, a default zero): at rest, standing still; moving,
        the reset from there. Returns it and whether it is collision-free. The plan is shared
        with other calls from the same state: do not modify it."""
        q = np.asarray(q, dtype=float)
        v = np.zeros_like(q) if v is None else np.asarray(v, dtype=float)
        a = np.zeros_like(q) if a is None else np.asarray(a, dtype=float)
        # Episode starts plan from a drawn state twice (drawing it checks that the supervisor's
        # plan from there is free; the supervisor then makes it): the same inputs bit for bit give
        # the same plan and check, so the second is looked up. A few recent states suffice.
        key = (q.shape, q.tobytes(), v.tobytes(), a.tobytes(), np.asarray(self.reset_pose).tobytes(), self.collision_check)
        if key in self._initial_plans:
            return self._initial_plans[key]
        if not np.any(v) and not np.any(a):
            plan = JointTrajectory.stationary(q, self.period)
        else:
            plan = self.resets.plan_reset(q, v, a, self.reset_pose)
        if len(self._initial_plans) >= 256:
            self._initial_plans.clear()
        for samples in (plan.q, plan.v, plan.a):  # shared between callers: nobody may change it
            samples.flags.writeable = False
        self._initial_plans[key] = result = (plan, self.check(plan).ok)
        return result


def random_invariant_state(stack: ControlStack, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random joint state (q, v, a) (8,) each in the control-invariant set: positions uniform
    within the command limits, velocities uniform up to the limit or to a fifth of it,
    accelerations uniform within the bounds a segment can end with
    (``CommandLimits.acceleration_bounds``). Units: rad or m, per s, per s^2."""
    limits = stack.limits
    while True:
        q = rng.uniform(limits.lower, limits.upper)
        v = rng.uniform(-1.0, 1.0, q.size) * limits.velocity * rng.choice([0.2, 1.0])
        a = rng.uniform(*limits.acceleration_bounds(v))
        if np.all(in_invariant_set(q, v, limits, stack.control, stack.period)):
            return q, v, a


def plan_state(plan: JointTrajectory, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, v, a) of ``plan`` at sample ``index``; after its end it rests at its last sample."""
    if index < 0:
        raise ValueError(f"plan_state: sample index must be >= 0, got {index}")
    return plan.state(min(index, plan.samples))


def make_control_stack(scenario: RobotScenario, control: ControlParams, check_collisions: bool = True) -> ControlStack:
    """The shared control stack with Drake collision checking of every plan (margin, influence
    distance and query budget from ``control``), or none when ``check_collisions`` is False."""
    check = None
    if check_collisions:
        # Drake's collision checker is imported only when plans are checked: the rest of the
        # control stack is NumPy and SciPy.
        from ace_drake.robot.collision import TrajectoryCollisionChecker

        checker = TrajectoryCollisionChecker(scenario, margin=control.collision_margin, influence=control.collision_influence)
        check = functools.partial(checker.check, max_queries=control.collision_query_budget)
    return ControlStack(scenario, control, check)
