"""A scripted swing: an open-loop joint trajectory, planned in advance, that returns one ball.

This is the smallest demonstration that the robot model, its delayed joints and the BallPlant
work together; it is not a controller (the model-based returner and the policy drive the robot
through the control stack). The plan, from the true incoming ball state:

1. predict the ball with the project's physics and hit it at the top of its bounce on the
   robot's half;
2. solve for the racket state whose return lands on a target on the opponent's half, inverting
   the racket contact model (paper eqs (7)-(8)): ``control.returner.racket_plans``, the model-based
   returner's racket planning;
3. inverse kinematics for that racket pose, and the joint velocities that give the racket that
   velocity (``robot.ik.racket_joint_velocities``: velocity-limit-weighted least squares
   on the racket Jacobian);
4. a cubic Hermite joint trajectory from the ready pose at rest through (q_hit, v_hit) at the hit
   time, then braking to rest, within the position, velocity and acceleration limits;
5. the command that makes the delayed joints (paper eq. (9)) follow it: the exact eq. (9)
   inverse, issued tau_d early and sampled at the 1 kHz interface.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.trajectories import PiecewisePolynomial

from ace_drake.control.joint_model import feedforward_command
from ace_drake.control.returner import RacketPlan, racket_plans
from ace_drake.diagrams import build_swing_diagram, make_simulator
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind, simulate
from ace_drake.robot.ik import racket_joint_velocities
from ace_drake.robot.model import RobotModel
from ace_drake.robot.params import RobotScenario

# An incoming ball from the human's side: it bounces on the robot's half 0.64 m behind the net
# (0.45 s after the human's hit) and reaches the top of its bounce above the robot's end line
# (x = -1.37 m) 0.68 s after the hit.
INCOMING_BALL = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))
RETURN_TARGET = (0.8, 0.0)  # where the return should land on the opponent's half, m
SWING_START = 0.05  # s after the episode starts; the robot waits at its ready pose until then


@dataclasses.dataclass(frozen=True)
class ScriptedSwing:
    """A planned swing: the racket plan, the joint state at the hit (8 + 8), the desired joint
    trajectory q_d(t) and the 1 kHz command trajectory q*(t) (both 8 x 1 PiecewisePolynomials)."""

    racket: RacketPlan
    q_hit: np.ndarray
    v_hit: np.ndarray
    desired: PiecewisePolynomial
    command: PiecewisePolynomial


def plan_racket(ball_state: np.ndarray, params: BallPhysicsParams, target=RETURN_TARGET) -> RacketPlan:
    """Steps 1-2 of the module docstring. Raises ValueError if the ball does not bounce on the
    robot's half or no racket state returns it."""
    flight = simulate(ball_state, params, 2.0, stop_on=(ContactKind.FLOOR,))
    bounces = [e for e in flight.events[0] if e.kind == ContactKind.TABLE and e.state_pre[0] < 0.0]
    if not bounces:
        raise ValueError("plan_racket: the ball does not bounce on the robot's half")
    after = flight.times > bounces[0].time
    rising = after & (flight.states[:, 0, 5] > 0.0)
    apex_index = np.flatnonzero(after & ~rising)[0]  # first sample past the top of the bounce
    plan = next(racket_plans(flight.states[apex_index, 0], float(flight.times[apex_index]), params, np.asarray(target, dtype=float)), None)
    if plan is None:
        raise ValueError("plan_racket: no racket state returns the ball")
    return plan


def plan_scripted_swing(model: RobotModel, ball_state: np.ndarray, params: BallPhysicsParams, target=RETURN_TARGET) -> ScriptedSwing:
    """The whole plan of the module docstring for one incoming ball (9,), with the robot at rest
    at its ready pose at t = 0. Raises ValueError when a step has no solution within limits."""
    racket = plan_racket(ball_state, params, target)
    ik = model.solve_racket_pose_ik(racket.position, racket.normal)
    if not ik.success:
        raise ValueError(f"plan_scripted_swing: no configuration puts the racket at {racket.position.round(3)}")
    q_hit = ik.q
    v_hit = racket_joint_velocities(model, q_hit, racket.velocity)
    if np.any(np.abs(v_hit) > model.velocity_limit):
        raise ValueError(f"plan_scripted_swing: the hit needs joint speeds {np.abs(v_hit).round(1)} over the limits")

    # Braking after the hit: constant deceleration to rest over the time the slowest joint needs.
    brake_time = max(0.05, float(np.max(np.abs(v_hit) / model.acceleration_limit)))
    q_rest = np.clip(q_hit + 0.5 * v_hit * brake_time, model.lower, model.upper)
    ready = model.ready_pose
    zero = np.zeros(8)
    desired = None
    for approach in np.arange(0.15, racket.time - SWING_START + 1e-9, 0.01):
        start = racket.time - approach
        candidate = PiecewisePolynomial.CubicHermite(
            [0.0, start, racket.time, racket.time + brake_time],
            np.column_stack([ready, ready, q_hit, q_rest]),
            np.column_stack([zero, zero, v_hit, zero]),
        )
        if start >= SWING_START and _within_limits(model, candidate):
            desired = candidate
            break
    if desired is None:
        raise ValueError("plan_scripted_swing: no swing within the joint limits reaches the hit in time")
    return ScriptedSwing(racket, q_hit, v_hit, desired, _command_for(desired, model.scenario))


def run_scripted_swing(
    swing: ScriptedSwing,
    ball_state: np.ndarray,
    scenario: RobotScenario,
    params: BallPhysicsParams,
    duration: float = 1.6,
    meshcat: Meshcat | None = None,
) -> tuple[tuple[ContactEvent, ...], dict]:
    """Simulates the swing diagram (diagrams.build_swing_diagram) with the ball starting at
    ``ball_state`` and the robot at rest at its ready pose; returns the ball's contact events and
    the logs {"time", "ball" (T, 9), "joint_time", "joints" (T, 16)}. With ``meshcat`` the run is
    recorded and published."""

    diagram = build_swing_diagram(swing.command, scenario, params, meshcat)
    context = diagram.CreateDefaultContext()
    ball = diagram.GetSubsystemByName("ball")
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), ball_state)
    joints = diagram.GetSubsystemByName("joint_plant")
    joints.SetJointState(joints.GetMyMutableContextFromRoot(context), np.asarray(scenario.ready_pose, dtype=float))
    simulator = make_simulator(diagram, context)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=100.0, set_visualizations_while_recording=False)
    simulator.AdvanceTo(duration)
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    events = ball.contact_events_port.Eval(ball.GetMyContextFromRoot(context))
    ball_log = diagram.GetSubsystemByName("ball_logger").FindLog(context)
    joint_log = diagram.GetSubsystemByName("joint_logger").FindLog(context)
    logs = {"time": ball_log.sample_times(), "ball": ball_log.data().T, "joint_time": joint_log.sample_times(), "joints": joint_log.data().T}
    return events, logs


def _within_limits(model: RobotModel, trajectory: PiecewisePolynomial, step: float = 1e-3) -> bool:
    """Whether the trajectory's positions, velocities and accelerations stay within the limits at
    ``step``-spaced samples (the Hermite segments' extremes lie at their ends or one interior
    point, which 1 ms sampling resolves to well under the margins that matter here)."""
    times = np.arange(trajectory.start_time(), trajectory.end_time() + step / 2, step)
    q = trajectory.vector_values(times).T
    v = trajectory.derivative(1).vector_values(times).T
    a = trajectory.derivative(2).vector_values(times).T
    return bool(
        np.all(q >= model.lower - 1e-9) and np.all(q <= model.upper + 1e-9)
        and np.all(np.abs(v) <= model.velocity_limit + 1e-9)
        and np.all(np.abs(a) <= model.acceleration_limit + 1e-9)
    )


def _command_for(desired: PiecewisePolynomial, scenario: RobotScenario) -> PiecewisePolynomial:
    """The 1 kHz command that makes the joints follow ``desired``: sample n (issued at t_n = n T and
    held for T) is the eq. (9) inverse at the middle of the interval in which the joint feels it,
    t_n + tau_d + T/2. Returned as a zero-order hold whose steps sit half a period before the
    sample instants, so the joints' sampling at t_n never falls on a step."""
    dynamics = scenario.dynamics
    period = dynamics.command_period
    sample_times = np.arange(0.0, desired.end_time() + 0.1, period)
    velocity, acceleration = desired.derivative(1), desired.derivative(2)
    commands = np.empty((len(sample_times), 8))
    for joint, params in enumerate(dynamics.joints):
        felt = np.clip(sample_times + params.delay + 0.5 * period, desired.start_time(), desired.end_time())
        commands[:, joint] = feedforward_command(
            [params], desired.vector_values(felt)[joint, :, None],
            velocity.vector_values(felt)[joint, :, None], acceleration.vector_values(felt)[joint, :, None],
        )[:, 0]
    breaks = np.r_[sample_times - 0.5 * period, sample_times[-1] + 0.5 * period]
    breaks[0] = 0.0
    return PiecewisePolynomial.ZeroOrderHold(breaks, np.vstack([commands, commands[-1]]).T)
