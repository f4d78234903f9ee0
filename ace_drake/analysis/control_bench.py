"""Benchmarks of the rally control stack: the latency of one control step (``bench control``) and
the safety of the supervisor and joints under random and adversarial actions (``bench safety``).

Both drive ``control.stack.ControlStack``, the same code the Drake systems call; the safety
benchmark runs the joints' eq. (9) model on the command stream it produces (exactly sampled, as
the DelayedJointPlant does), because 100,000 cases through a Simulator would take days.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import torch

from ace_drake.analysis.reach import swing_through
from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.feasible_set import InfeasibleStartError
from ace_drake.control.joint_model import discretize
from ace_drake.control.params import ControlParams
from ace_drake.control.spline_qp import SegmentQp
from ace_drake.control.stack import ControlStack, make_control_stack, plan_state, random_invariant_state
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.collision import TrajectoryCollisionChecker
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.robot.params import RobotScenario
from ace_drake.robot.trajectory import JointTrajectory

# The actor network's size for the latency budget: the observation of issue 7's actor (ball
# position and spin histories with timestamps, robot state, skill state: about 128 numbers) through
# three hidden layers of 256 to the 16 action means. Keep in step with the trained policy.
ACTOR_LAYERS = (128, 256, 256, 256, ACTION_SIZE)


def actor_network(seed: int = 0):
    """A torch MLP of ACTOR_LAYERS (ReLU, tanh output): the policy's cost per call."""

    torch.manual_seed(seed)
    layers = []
    for inputs, outputs in zip(ACTOR_LAYERS[:-1], ACTOR_LAYERS[1:]):
        layers += [torch.nn.Linear(inputs, outputs), torch.nn.ReLU()]
    layers[-1] = torch.nn.Tanh()
    return torch.nn.Sequential(*layers).eval()


def make_stack(scenario: RobotScenario | None = None, control: ControlParams | None = None, check_collisions: bool = True) -> ControlStack:
    """The control stack with the Drake collision checker, as the diagrams build it."""

    return make_control_stack(scenario or load_scenario(), control or ControlParams(), check_collisions)


def random_action(rng: np.random.Generator, kind: str, step: int) -> np.ndarray:
    """An action of one of the ACTION_KINDS: uniform in the box, random corners, all +1, all -1,
    +1 and -1 alternating over steps, or alternating within the action."""
    if kind == "uniform":
        return rng.uniform(-1.0, 1.0, ACTION_SIZE)
    if kind == "corners":
        return rng.choice([-1.0, 1.0], ACTION_SIZE)
    if kind == "plus":
        return np.ones(ACTION_SIZE)
    if kind == "minus":
        return -np.ones(ACTION_SIZE)
    if kind == "alternating_steps":
        return np.full(ACTION_SIZE, 1.0 if step % 2 == 0 else -1.0)
    if kind == "alternating_components":
        return np.tile([1.0, -1.0], ACTION_SIZE // 2) * (1.0 if step % 2 == 0 else -1.0)
    raise ValueError(f"random_action: unknown kind {kind!r}; expected one of {ACTION_KINDS}")


ACTION_KINDS = ("uniform", "corners", "plus", "minus", "alternating_steps", "alternating_components")


def _percentiles(samples) -> dict[str, float]:
    samples = np.asarray(samples) * 1e3
    return {"median_ms": float(np.median(samples)), "p99_ms": float(np.percentile(samples, 99)), "max_ms": float(np.max(samples))}


# Where the robot hits in the published match data (../shared/paper/notes.md): x from -2.55 to
# -0.94 m, y from -0.87 to 0.92 m, 0.15 to 0.34 m above the table.
CONTACT_BOX = ((-2.55, -0.87, 0.15), (-0.94, 0.92, 0.34))
STROKE_STEPS = (8, 8, 9)  # policy steps of backswing, swing and recovery: the 0.8 s stroke cycle
STROKE_NOISE = 0.3  # uniform noise added to each action component of a rally stroke


def hitting_states(stack: ControlStack, rng: np.random.Generator, count: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``count`` strokes as (q_start, q_hit, q_follow) (8,) each: a racket meeting a ball at a
    contact point drawn uniformly from CONTACT_BOX (inverse kinematics, blade facing the
    opponent, clear of the court), the fastest +x swing through it (``reach.swing_through``), its
    run-up start and where it would carry on to in 0.15 s, both pulled back towards q_hit until
    the robot is 2 cm clear of the court and itself there; clipped to the command limits."""

    model = RobotModel(stack.scenario)
    limits = stack.limits

    def clear_towards(q_hit: np.ndarray, q_far: np.ndarray) -> np.ndarray:
        for fraction in (1.0, 0.75, 0.5, 0.25, 0.0):
            q = np.clip(q_hit + fraction * (q_far - q_hit), limits.lower, limits.upper)
            if not model.colliding_pairs(q, margin=0.02):
                return q
        return q

    strokes = []
    while len(strokes) < count:
        point = rng.uniform(*CONTACT_BOX)
        result = model.solve_racket_ik(point)
        if not result.success:
            continue
        swing = swing_through(model, result.q)
        q_hit = np.clip(swing.q_hit, limits.lower, limits.upper)
        strokes.append((clear_towards(q_hit, swing.q_start), q_hit, clear_towards(q_hit, swing.q_hit + 0.15 * swing.v_hit)))
    return strokes


class RallyStrokes:
    """The actions of rally-like strokes for ``bench_control``: stroke after stroke, the robot
    steers (``ControlStack.action_towards``) to the backswing, through the hitting configuration,
    and back to the reset pose (STROKE_STEPS), with STROKE_NOISE on every action: the motions of
    a rally, fast and close to the table."""

    def __init__(self, stack: ControlStack, rng: np.random.Generator, strokes: int = 40):
        self.stack, self.rng = stack, rng
        self.strokes = hitting_states(stack, rng, strokes)
        self.step = 0

    def action(self, q, v, a) -> np.ndarray:
        """The next action (16,) from the segment's start state (q, v, a)."""
        cycle = sum(STROKE_STEPS)
        q_start, _, q_follow = self.strokes[(self.step // cycle) % len(self.strokes)]
        phase = self.step % cycle
        goal = q_start if phase < STROKE_STEPS[0] else q_follow if phase < STROKE_STEPS[0] + STROKE_STEPS[1] else self.stack.reset_pose
        self.step += 1
        try:
            action = self.stack.action_towards(q, v, a, goal)
        except InfeasibleStartError:  # on a reset outside the invariant set: the stack refuses any action
            action = np.zeros(ACTION_SIZE)
        return np.clip(action + self.rng.uniform(-STROKE_NOISE, STROKE_NOISE, ACTION_SIZE), -1.0, 1.0)


STATE_SOURCES = ("rally", "random")


def bench_control(steps: int = 1000, seed: int = 0, qp_comparisons: int = 200, states: str = "rally", progress: Callable[[str], None] | None = None) -> dict:
    """Latency of full control steps (actor MLP, mapping, spline QP, reset, collision check) on
    one thread, and the spline QP alone through DAQP and through MathematicalProgram (Clarabel) on
    the same problems. Times in ms: median, p99, max.

    states: "rally", the states of rally strokes (``rally_actions``: swings through hitting
    configurations at the data's contact points, with noise); or "random", the states a uniformly
    random policy visits from the ready pose in episodes of 20 steps (a stress test: it flails the
    racket into the floor and the robot's own carriage, where collision checks take longest)."""

    if states not in STATE_SOURCES:
        raise ValueError(f"bench_control: states must be one of {STATE_SOURCES}, got {states!r}")
    say = progress or (lambda _: None)
    torch.set_num_threads(1)
    rng = np.random.default_rng(seed)
    stack = make_stack()
    actor = actor_network(seed)
    clarabel = SegmentQp(stack.limits, stack.control.segment_samples, stack.period, stack.control.knot_samples, solver="clarabel")
    totals, unchecked, stages, problems = [], [], {"policy": [], "map": [], "segment": [], "reset": [], "check": []}, []
    refusals: dict[str, int] = {}
    observation = torch.zeros(1, ACTOR_LAYERS[0])
    if states == "rally":
        say("bench control: inverse kinematics for 40 rally strokes")
        strokes = RallyStrokes(stack, rng)
    plan, _ = stack.initial_plan(stack.reset_pose)
    for step in range(steps + 1):  # the first step warms up
        q, v, a = plan_state(plan, 0)
        observation[0, :24] = torch.as_tensor(np.concatenate([q, v, a]), dtype=torch.float32)
        start = time.perf_counter()
        with torch.no_grad():
            action = actor(observation)[0].numpy().astype(float)
        policy_seconds = time.perf_counter() - start
        # The untrained actor's actions are near the centre: the state source decides the action.
        if states == "rally":
            action = strokes.action(q, v, a)
        else:
            action = np.clip(action + rng.uniform(-1.0, 1.0, ACTION_SIZE), -1.0, 1.0)
        start = time.perf_counter()
        proposal = stack.propose(q, v, a, action)
        proposal_seconds = time.perf_counter() - start
        if proposal.target is not None and len(problems) < qp_comparisons:
            problems.append((q, v, a, proposal.target))
        if proposal.safe:
            plan = proposal.plan.from_sample(stack.control.segment_samples)
        else:
            plan = plan.from_sample(min(stack.control.segment_samples, plan.samples))
        if states == "random" and (step + 1) % 20 == 0:
            plan, _ = stack.initial_plan(stack.reset_pose)
        if step == 0:
            continue
        totals.append(policy_seconds + proposal_seconds)
        unchecked.append(policy_seconds + proposal_seconds - proposal.seconds.get("check", 0.0))
        stages["policy"].append(policy_seconds)
        for name, seconds in proposal.seconds.items():
            stages[name].append(seconds)
        if not proposal.safe:
            cause = next((key for key in REFUSALS if proposal.reason.startswith(key)), "other")
            refusals[cause] = refusals.get(cause, 0) + 1
        if step % 200 == 0:
            say(f"bench control: {step}/{steps} steps")
    say(f"bench control: the spline QP alone on {len(problems)} problems, DAQP and Clarabel")
    daqp_seconds, clarabel_seconds, differences = [], [], []
    for q, v, a, target in problems:
        start = time.perf_counter()
        reference = stack.qp.solve(q, v, a, *target)
        daqp_seconds.append(time.perf_counter() - start)
        start = time.perf_counter()
        other = clarabel.solve(q, v, a, *target)
        clarabel_seconds.append(time.perf_counter() - start)
        if reference.success and other.success:
            differences.append(float(np.max(np.abs(reference.trajectory.q - other.trajectory.q))))
    daqp_figures, clarabel_figures = _percentiles(daqp_seconds), _percentiles(clarabel_seconds)
    return {
        "steps": steps,
        "states": states,
        "threads": 1,
        "actor_layers": list(ACTOR_LAYERS),
        "step": _percentiles(totals),
        "step_without_check": _percentiles(unchecked),
        "stages": {name: _percentiles(values) for name, values in stages.items() if values},
        "refused_steps": sum(refusals.values()),
        "refusals": refusals,
        "qp": {
            "problems": len(problems),
            "daqp": daqp_figures,
            "mathematical_program_clarabel": clarabel_figures,
            "median_ratio_clarabel_to_daqp": clarabel_figures["median_ms"] / daqp_figures["median_ms"],
            "max_position_difference": max(differences) if differences else None,
        },
        "budget_ms": {"paper_total": 5.0, "p99_target": 2.0},
    }


# ---------------------------------------------------------------------------------- safety


@dataclasses.dataclass
class SafetyCounts:
    """Violations found by ``bench_safety`` (sums over cases)."""

    cases: int = 0
    steps: int = 0
    accepted: int = 0
    refused: int = 0
    start_redraws: int = 0
    refused_infeasible_start: int = 0  # the start is on a reset, outside the invariant set
    refused_qp: int = 0
    refused_reset: int = 0
    refused_collision: int = 0
    refused_check_budget: int = 0  # not proven clear within ControlParams.collision_query_budget
    command_position: int = 0
    command_velocity: int = 0
    command_acceleration: int = 0
    joint_position: int = 0
    joint_velocity: int = 0
    joint_acceleration: int = 0
    collisions: int = 0
    non_stationary_ends: int = 0

    def add(self, other: "SafetyCounts") -> None:
        for field in dataclasses.fields(self):
            setattr(self, field.name, getattr(self, field.name) + getattr(other, field.name))


REFUSALS = {
    "infeasible start": "refused_infeasible_start",
    "segment QP failed": "refused_qp",
    "reset planning failed": "refused_reset",
    "collision predicted": "refused_collision",
    "collision check over its budget": "refused_check_budget",
}


def execute_case(stack: ControlStack, rng: np.random.Generator, hardware: CommandLimits, checker=None) -> SafetyCounts:
    """One case: a random invariant start whose initial plan (its reset) and recent past
    (``lead_in``) are collision-free, then
    1-8 actions of one random kind through the supervisor's decision (``ControlStack.propose``,
    whose decision is ``control.stack.decide_segment``, the SafetySupervisor's own: execute the
    new plan, else keep the current one), then the plan to its end; the joints (eq. (9)) follow the command stream. The
    command is checked against the command limits, the joints against the hardware limits and,
    with ``checker`` (margin 0), against collisions; the end must be at rest."""
    counts = SafetyCounts(cases=1)
    while True:
        q, v, a = random_invariant_state(stack, rng)
        plan, free = stack.initial_plan(q, v, a)
        # The joints lag the command by a few ms: they start on the way the command came, which
        # (extrapolated, ``follow``) must be clear too, or the start is not one the robot can be in.
        if free and stack.check(lead_in(q, v, a, stack.period)).ok:
            break
        counts.start_redraws += 1
    kind = ACTION_KINDS[rng.integers(len(ACTION_KINDS))]
    segment_samples = stack.control.segment_samples
    executed = []
    for step in range(int(rng.integers(1, 9))):
        counts.steps += 1
        start = plan_state(plan, 0)
        decision = stack.propose(*start, random_action(rng, kind, step)).decision
        if decision.accepted:
            counts.accepted += 1
            plan = decision.plan
        elif decision.refused:
            counts.refused += 1
            for prefix, name in REFUSALS.items():
                if decision.reason.startswith(prefix):
                    setattr(counts, name, getattr(counts, name) + 1)
        executed.append(plan.until(segment_samples))
        plan = plan.from_sample(min(segment_samples, plan.samples))
    executed.append(plan)
    command = executed[0]
    for piece in executed[1:]:
        command = command.then(piece)
    command_violations = stack.limits.violations(command, tolerance=1e-6)
    counts.command_position += command_violations["position"]
    counts.command_velocity += command_violations["velocity"]
    counts.command_acceleration += command_violations["acceleration"]
    if np.any(command.v[-1] != 0.0) or np.any(command.a[-1] != 0.0):
        counts.non_stationary_ends += 1
    joints = follow(command, stack.scenario)
    joint_violations = hardware.violations(joints, tolerance=1e-9)
    counts.joint_position += joint_violations["position"]
    counts.joint_velocity += joint_violations["velocity"]
    counts.joint_acceleration += joint_violations["acceleration"]
    if np.max(np.abs(joints.v[-1])) > 1e-3:
        counts.non_stationary_ends += 1
    if checker is not None and not checker.check(joints).free:
        counts.collisions += 1
    return counts


def lead_in(q, v, a, period: float, duration: float = 0.01) -> JointTrajectory:
    """The last ``duration`` s before the state (q, v, a) (8,) each, extrapolated with constant
    acceleration (as ``follow`` starts the joints): where the lagging joints are at the start."""
    times = period * np.arange(-int(round(duration / period)), 1)[:, None]
    return JointTrajectory(period, q + v * times + 0.5 * a * times**2, v + a * times, np.repeat(a[None], times.shape[0], axis=0))


def follow(command: JointTrajectory, scenario: RobotScenario, settle: float = 0.05) -> JointTrajectory:
    """The joints' eq. (9) response to a 1 kHz command stream, exactly sampled (as the
    DelayedJointPlant computes it), continued ``settle`` s after the stream ends. The joints start
    tracking the first command as they would have after following its quadratic extrapolation
    into the past for 50 ms (the servo's transient long settled). The returned acceleration is the mean
    over each period, (v[n+1] - v[n]) / T (the instantaneous one jumps at every command step of
    the zero-order hold)."""
    period = command.period
    joints = scenario.dynamics.joints
    extra = int(round(settle / period))
    phi, gamma0, gamma1, delays = _discretized(tuple(joints), period)
    # The lead-in: the command's past extrapolated with its initial velocity and acceleration
    # over 50 time constants of the servo, the joints at rest where it starts.
    q0, v0, a0 = command.state(0)
    lead = int(round(0.05 / period))
    past_times = -period * np.arange(lead, 0, -1)[:, None]
    past = q0 + v0 * past_times + 0.5 * a0 * past_times**2
    stream = np.concatenate([np.repeat(past[:1], int(delays.max()) + 1, axis=0), past, command.q, np.repeat(command.q[-1:], extra, axis=0)])
    offset = int(delays.max()) + 1  # row n + offset of ``stream`` is the command of step n
    zeta = np.stack([past[0], np.zeros(8)], axis=-1)  # (8, 2), at rest at the lead-in's start
    columns = np.arange(8)
    steps = stream.shape[0] - offset
    states = np.empty((steps, 8, 2))
    states[0] = zeta
    for n in range(steps - 1):
        newer = stream[n - delays + offset, columns]
        older = stream[n - delays - 1 + offset, columns]
        zeta = np.einsum("jab,jb->ja", phi, zeta) + gamma0 * newer[:, None] + gamma1 * older[:, None]
        states[n + 1] = zeta
    q, v = states[lead:, :, 0], states[lead:, :, 1]
    a = np.vstack([np.diff(v, axis=0) / period, np.zeros((1, 8))])
    return JointTrajectory(period, q, v, a)


@functools.lru_cache(maxsize=4)
def _discretized(joints, period: float):
    """Phi (8, 2, 2), Gamma0, Gamma1 (8, 2) and whole-period delays k (8,) of eq. (9) sampled."""
    discrete = [discretize(joint, period) for joint in joints]
    return (
        np.array([d[0] for d in discrete]),
        np.array([d[1] for d in discrete]),
        np.array([d[2] for d in discrete]),
        np.array([d[3] for d in discrete]),
    )


def _safety_worker(arguments) -> dict:
    cases, seed, check_collisions = arguments

    stack = make_stack()
    checker = TrajectoryCollisionChecker(stack.scenario, margin=0.0) if check_collisions else None
    hardware = CommandLimits.hardware(stack.scenario.limits)
    rng = np.random.default_rng(seed)
    counts = SafetyCounts()
    for _ in range(cases):
        counts.add(execute_case(stack, rng, hardware, checker))
    return dataclasses.asdict(counts)


def bench_safety(cases: int = 1000, seed: int = 0, workers: int = 1, chunk: int = 500, check_collisions: bool = True, progress: Callable[[str], None] | None = None) -> dict:
    """``cases`` random cases (``execute_case``) in chunks over ``workers`` processes; the
    chunks' seeds derive from ``seed``, so the figures are the same for any worker count."""
    say = progress or (lambda _: None)
    sizes = [min(chunk, cases - start) for start in range(0, cases, chunk)]
    seeds = np.random.SeedSequence(seed).generate_state(len(sizes))
    jobs = [(size, int(chunk_seed), check_collisions) for size, chunk_seed in zip(sizes, seeds)]
    total = SafetyCounts()
    start = time.perf_counter()
    if workers <= 1:
        results = map(_safety_worker, jobs)
    else:
        pool = ProcessPoolExecutor(max_workers=workers)
        results = pool.map(_safety_worker, jobs)
    for done, result in enumerate(results, start=1):
        total.add(SafetyCounts(**result))
        say(f"bench safety: {total.cases}/{cases} cases, {time.perf_counter() - start:.0f} s")
    if workers > 1:
        pool.shutdown()
    figures = dataclasses.asdict(total)
    figures["violations"] = sum(
        figures[name]
        for name in (
            "command_position", "command_velocity", "command_acceleration",
            "joint_position", "joint_velocity", "joint_acceleration", "collisions", "non_stationary_ends",
        )
    )
    figures["seed"] = seed
    figures["wall_seconds"] = time.perf_counter() - start
    return figures
