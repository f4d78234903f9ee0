"""The control benchmarks' machinery: the joints following a command stream, random starts, and
a small safety run that must find no violation (docs/robot_and_control.md's 100,000-case run is the real one)."""

import numpy as np

from ace_drake.analysis.control_bench import ACTION_KINDS, bench_safety, follow, make_stack, random_action
from ace_drake.control.feasible_set import in_invariant_set
from ace_drake.control.joint_model import ramp_tracking_lag, simulate_joint
from ace_drake.control.stack import random_invariant_state
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import RobotScenario
from ace_drake.robot.trajectory import JointTrajectory


def test_follow_matches_the_joint_model_and_lags_a_ramp_by_its_tracking_lag():
    scenario = RobotScenario()
    period, samples = 0.001, 200
    times = period * np.arange(samples + 1)[:, None]
    # A step from rest: the same samples as simulate_joint.
    step = np.where(times > 0.0, 0.1, 0.0) * np.ones(8)
    joints = follow(JointTrajectory(period, step, np.zeros_like(step), np.zeros_like(step)), scenario, settle=0.0)
    np.testing.assert_allclose(joints.q[:, 0], simulate_joint(scenario.dynamics.joints[0], step[:, 0], period), atol=1e-12)
    # A ramp at 2 rad/s already under way: tracked from the start with the ramp lag, plus the
    # half period by which a held command lags the ramp it samples.
    ramp = 2.0 * times * np.ones(8)
    joints = follow(JointTrajectory(period, ramp, np.full_like(ramp, 2.0), np.zeros_like(ramp)), scenario, settle=0.0)
    lag = ramp_tracking_lag(scenario.dynamics.joints[0])
    np.testing.assert_allclose(joints.q[:50], ramp[:50] - 2.0 * (lag + 0.5 * period), atol=1e-5)  # up to the ripple


def test_random_starts_are_invariant_and_actions_cover_the_kinds():
    stack = make_stack(check_collisions=False)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q, v, a = random_invariant_state(stack, rng)
        assert np.all(in_invariant_set(q, v, stack.limits, stack.control, stack.period))
        low, high = stack.limits.acceleration_bounds(v)
        assert np.all((low <= a) & (a <= high))
    for kind in ACTION_KINDS:
        action = random_action(rng, kind, 1)
        assert action.shape == (16,) and np.all(np.abs(action) <= 1.0)
    np.testing.assert_array_equal(random_action(rng, "alternating_steps", 1), -1.0)


def test_a_small_safety_run_is_clean_and_reproducible():
    first = bench_safety(cases=12, seed=5, chunk=6)
    assert first["violations"] == 0 and first["cases"] == 12
    second = bench_safety(cases=12, seed=5, chunk=6)
    assert {k: v for k, v in first.items() if k != "wall_seconds"} == {k: v for k, v in second.items() if k != "wall_seconds"}
    assert CommandLimits.hardware(RobotScenario().limits).velocity[0] == 5.0
