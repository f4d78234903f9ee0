"""The robot executes the serve: the release detection on hand-made cup motions, the offline
execution against the eq. (9) reference, and the toss (and strike) planned, executed and judged."""

import math

import numpy as np
import pytest

from ace_drake.control.hit_state import hermite_peak_acceleration
from ace_drake.control.joint_model import simulate_joint
from ace_drake.control.params import ControlParams
from ace_drake.control.serve import TossState, simulate_serve, strike_from_genes, toss_ball
from ace_drake.control.serve_execution import (
    GRAVITY,
    CupMotion,
    CupProfile,
    execute_commands,
    hit_velocity_bounds,
    plan_strike,
    plan_toss,
    release_time,
    strike_velocities,
)
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.control.stack import make_control_stack
from ace_drake.robot.model import RobotModel
from ace_drake.robot.trajectory import JointTrajectory

T = 0.001  # s, the command period
UP = np.array([0.0, 0.0, 1.0])
# The genes of the serve library's short_backspin_10 (analysis.serve_search, GA seed 10, from the
# default toss; a legal serve at the ball level that the robot makes).
SHORT_BACKSPIN = np.array([0.2028, 0.3769, 0.9153, 0.0863, 0.682, 0.3558, 0.8578, 0.8722, 0.5594])


@pytest.fixture(scope="module")
def model():
    return RobotModel()


@pytest.fixture(scope="module")
def stack(model):
    return make_control_stack(model.scenario, ControlParams())


@pytest.fixture(scope="module")
def toss(model, stack):
    """The default toss (0.1 m above the table, 0.18 m behind its end, 2 m/s up), planned once."""
    return plan_toss(model, stack)


@pytest.fixture(scope="module")
def strike(model, stack, toss):
    """The short backspin strike made after the default toss, planned once."""
    return plan_strike(model, stack, toss, strike_from_genes(SHORT_BACKSPIN, TossState(), BallPhysicsParams()))


def vertical_motion(times, height) -> CupMotion:
    """A cup at heights ``height`` (n,) m on a vertical line, its opening up."""
    position = np.zeros((times.size, 3))
    position[:, 2] = height
    return CupMotion(times, position, np.tile(np.eye(3), (times.size, 1, 1)))


# ---------------------------------------------------------------------------------- release detection
def test_release_time_finds_the_switch_of_a_hand_made_acceleration_profile():
    """12.5 m/s^2 up to t = 0.1 s, -1.5 g from the next sample, linear in between (a command
    spline's acceleration): the acceleration is -g at 0.1 + T (12.5 + g) / (12.5 + 1.5 g) s."""
    times = np.arange(201) * T
    a_z = np.where(times <= 0.1 + 1e-12, 12.5, -1.5 * GRAVITY)
    acceleration = np.column_stack([np.zeros_like(times), np.zeros_like(times), a_z])
    expected = 0.1 + T * (12.5 + GRAVITY) / (12.5 + 1.5 * GRAVITY)
    assert release_time(times, acceleration, np.tile(UP, (times.size, 1))) == pytest.approx(expected, abs=1e-12)
    # A cup that never decelerates faster than gravity keeps the ball.
    assert release_time(times, np.zeros_like(acceleration), np.tile(UP, (times.size, 1))) is None


def test_release_is_where_the_cups_opening_feels_less_than_gravity():
    """A cup tilted by 30 degrees releases when a . n < -g n_z: a horizontal deceleration of
    g n_z / |n_x| along the tilt's direction does it."""
    tilt = math.radians(30.0)
    n = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    times = np.arange(11) * T
    a_x = -np.linspace(0.0, 2.0, 11) * GRAVITY * n[2] / n[0]  # crosses the threshold at t = 5 T
    acceleration = np.column_stack([a_x, np.zeros(11), np.zeros(11)])
    assert release_time(times, acceleration, np.tile(n, (11, 1))) == pytest.approx(5 * T, abs=1e-12)


def test_the_cups_mean_motion_finds_a_ramped_release_exactly():
    """A cup from rest at 12.5 m/s^2, then a linear ramp over 10 ms to -1.5 g: the mean
    accelerations (second differences) are exact on the ramp, so t_lift is the ramp's -g crossing
    and the release velocity the motion's velocity there."""
    a_up, a_down, t_ramp, ramp = 12.5, -1.5 * GRAVITY, 0.100, 0.010

    def motion(t):  # (z, v_z) of the hand-made profile, integrated in closed form
        t1 = np.clip(t, 0.0, t_ramp)
        t2 = np.clip(t - t_ramp, 0.0, ramp)
        t3 = np.clip(t - t_ramp - ramp, 0.0, None)
        jerk = (a_down - a_up) / ramp
        v1 = a_up * t_ramp
        z1 = 0.5 * a_up * t_ramp**2
        v2 = v1 + a_up * ramp + 0.5 * jerk * ramp**2
        z2 = z1 + v1 * ramp + 0.5 * a_up * ramp**2 + jerk * ramp**3 / 6
        z = np.where(t <= t_ramp, 0.5 * a_up * t1**2, np.where(t <= t_ramp + ramp, z1 + v1 * t2 + 0.5 * a_up * t2**2 + jerk * t2**3 / 6,
                                                             z2 + v2 * t3 + 0.5 * a_down * t3**2))
        v = np.where(t <= t_ramp, a_up * t1, np.where(t <= t_ramp + ramp, v1 + a_up * t2 + 0.5 * jerk * t2**2, v2 + a_down * t3))
        return z, v

    times = np.arange(161) * T
    cup = vertical_motion(times, motion(times)[0])
    expected = t_ramp + ramp * (a_up + GRAVITY) / (a_up - a_down)
    t_lift = cup.release()
    assert t_lift == pytest.approx(expected, abs=1e-9)
    _, velocity, spin = cup.state_at(t_lift)
    # mean velocities, linear between midpoints: second order in T (jerk T^2 / 6 = 0.45 mm/s on the ramp)
    assert velocity[2] == pytest.approx(float(motion(np.array(t_lift))[1]), abs=1e-3)
    np.testing.assert_allclose(spin, 0.0, atol=1e-12)


def test_the_cups_mean_motion_finds_a_step_within_one_period():
    """A true step from 12.5 m/s^2 to -1.5 g at a sample is smeared over the two periods either
    side by the finite differences: t_lift falls within one period of it, and the release speed
    within 0.02 m/s of the peak (the ball and cup accelerations differ by only 0.5 g there)."""
    times = np.arange(201) * T
    t_s = 0.1
    z = np.where(times <= t_s, 0.5 * 12.5 * times**2, 0.5 * 12.5 * t_s**2 + 12.5 * t_s * (times - t_s) - 0.75 * GRAVITY * (times - t_s) ** 2)
    cup = vertical_motion(times, z)
    t_lift = cup.release()
    assert t_s <= t_lift <= t_s + T
    assert cup.state_at(t_lift)[1][2] == pytest.approx(12.5 * t_s, abs=0.02)


# ---------------------------------------------------------------------------------- offline execution
def test_execute_commands_is_the_joints_eq_9_response(model):
    """Each joint's executed samples equal ``simulate_joint``'s (the transfer-function reference):
    a commanded ramp and a step from rest."""
    samples = 60
    start = model.ready_pose
    q = np.tile(start, (samples + 1, 1))
    q[10:, 3] += 0.2  # a step in shoulder_pitch at sample 10
    q[:, 6] += 3.0 * np.arange(samples + 1) * T  # a ramp in wrist_2 from the start
    plan = JointTrajectory(T, q, np.zeros_like(q), np.zeros_like(q))
    motion = execute_commands(model.scenario.dynamics, plan, settle=0)
    executed = motion.zeta[0, :, :, 0]
    for joint in (3, 6):
        reference = simulate_joint(model.scenario.dynamics.joints[joint], q[:, joint], T)
        np.testing.assert_allclose(executed[:, joint], reference, atol=1e-9)
    np.testing.assert_allclose(executed[:, 0], start[0], atol=1e-12)  # a joint at rest with its command held stays there


def test_the_cup_profile_reaches_the_release_state_and_stops():
    profile = CupProfile(t_switch=0.16, s_switch=0.0, v_switch=2.0, brake=2.5 * GRAVITY)
    s, s_dot, _ = profile.at(np.array([0.0, 0.16, profile.t_stop, 1.0]))
    np.testing.assert_allclose(s, [-0.16, 0.0, profile.top, profile.top], atol=1e-12)
    np.testing.assert_allclose(s_dot, [0.0, 2.0, 0.0, 0.0], atol=1e-12)
    assert profile.top == pytest.approx(4.0 / (5.0 * GRAVITY))


# ---------------------------------------------------------------------------------- the toss
def test_the_executed_toss_releases_the_intended_ball(toss):
    intended = TossState()
    assert toss.t_lift is not None
    # t_lift is where the designed profile switches to braking, give or take the joints' lag
    assert toss.profile.t_switch - 0.002 < toss.t_lift < toss.profile.t_switch + 0.016
    assert np.linalg.norm(toss.position_error) < 0.005
    assert np.linalg.norm(toss.velocity_error) < 0.05
    assert toss.release.velocity[2] == pytest.approx(intended.velocity[2], abs=0.01)
    assert math.degrees(toss.tilt) < 10.0
    assert toss.rise >= 0.16
    assert toss.legal
    assert np.linalg.norm(toss.release.spin) < 2.0  # rad/s: the cup translates


def test_the_ball_leaves_the_cup_after_the_release(toss):
    """Beyond t_lift the free ball rises above the seat, and the seat never overtakes it."""
    gaps = []
    for dt in np.arange(0.002, 0.06, 0.002):
        seat = toss.cup.state_at(toss.t_lift + dt)[0]
        ball = toss_ball(toss.release, toss.physics, dt)[:3]
        gaps.append(ball[2] - seat[2])
    assert min(gaps) > 0.0
    assert gaps[-1] > 0.02


def test_every_toss_segment_passes_the_control_stack(toss, stack):
    commands = toss.commands
    assert commands.accepted.all()
    assert stack.limits.violations(commands.plan) == {"position": 0, "velocity": 0, "acceleration": 0}
    assert stack.check(commands.plan).ok  # the whole command sequence, the final reset included
    np.testing.assert_allclose(toss.q_start, commands.plan.q[0])
    assert stack.check(JointTrajectory.stationary(toss.q_start, T)).ok  # the robot can wait there


def test_the_robot_state_at_release_is_the_executed_motions(toss, model):
    """(q, v) at t_lift lie between the executed samples, and carry the cup at the ball's release
    velocity (through the kinematics: the mean velocities agree to second order)."""
    samples = toss.motion.zeta[0, :, :, 0]
    k = int(toss.t_lift / T)
    low, high = np.minimum(samples[k], samples[k + 1]), np.maximum(samples[k], samples[k + 1])
    assert np.all((low - 1e-12 <= toss.q_lift) & (toss.q_lift <= high + 1e-12))
    model.plant.SetPositions(model.plant_context, toss.q_lift)
    model.plant.SetVelocities(model.plant_context, toss.v_lift)
    V_WC = model.ball_cup_frame.CalcSpatialVelocityInWorld(model.plant_context)
    np.testing.assert_allclose(V_WC.translational(), toss.release.velocity, atol=0.01)


# ---------------------------------------------------------------------------------- the strike
def test_hit_velocity_bounds_are_where_the_hermites_acceleration_meets_the_limit():
    rng = np.random.default_rng(0)
    q0, v0, q1 = rng.normal(size=8), rng.normal(size=8), rng.normal(size=8) * 0.3
    A, V, D = np.full(8, 80.0), np.full(8, 100.0), 0.25
    lower, upper = hit_velocity_bounds(q0, v0, q1, D, V, A)
    for v1 in (lower, upper):
        np.testing.assert_allclose(hermite_peak_acceleration(q0, v0, q1, v1, D)[lower <= upper], A[lower <= upper], rtol=1e-9)
    assert np.all(hermite_peak_acceleration(q0, v0, q1, 0.5 * (lower + upper), D)[lower <= upper] <= A[lower <= upper])


def test_strike_velocities_move_the_contact_point_at_the_racket_velocity(model):
    q = model.ready_pose
    offset = np.array([0.0, 0.03, 0.02])
    v_WR = np.array([3.0, 0.5, 1.0])
    v = strike_velocities(model, q, v_WR, offset, -model.velocity_limit, model.velocity_limit)
    V_WR = model.racket_spatial_velocity(q, v)
    np.testing.assert_allclose(V_WR.translational() + np.cross(V_WR.rotational(), offset), v_WR, atol=1e-3)


def test_the_executed_strike_meets_the_intended_racket_state(strike):
    assert np.linalg.norm(strike.position_error) < 0.005
    assert math.degrees(strike.normal_error) < 1.0
    assert np.linalg.norm(strike.mean_velocity_error) < 0.3  # m/s
    assert not strike.roll_free
    assert strike.ball_clearance > 0.0  # the racket does not touch the ball before the hit


def test_every_strike_segment_passes_the_control_stack_after_the_toss(strike, stack, toss):
    commands = strike.commands
    assert commands.accepted.all()
    assert stack.limits.violations(commands.plan) == {"position": 0, "velocity": 0, "acceleration": 0}
    assert stack.check(commands.plan).ok
    boundary = strike.first_segment * stack.control.segment_samples
    assert boundary * T >= toss.t_lift
    np.testing.assert_array_equal(commands.plan.q[: boundary + 1], toss.commands.plan.q[: boundary + 1])  # the toss is kept up to the strike


def test_the_executed_serve_is_legal_at_the_ball_level(strike, toss):
    """The executed release and racket state, through the ball-level serve: still the legal short
    backspin serve, its second bounce near the intended one."""
    physics = BallPhysicsParams()
    intended = simulate_serve(strike.strike, TossState(), physics)
    executed = simulate_serve(strike.executed_strike, toss.release, physics)
    assert intended.legal and executed.legal
    assert np.linalg.norm(executed.bounce_position - intended.bounce_position) < 0.15
