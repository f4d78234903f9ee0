"""The control benchmarks' machinery: the joints following a command stream, random starts, and
a small safety run that must find no violation (docs/robot_and_control.md's 100,000-case run is the real one)."""

import numpy as np

from ace_drake.analysis.control_bench import ACTION_KINDS, bench_safety, follow, make_stack, random_action
from ace_drake.control.feasible_set import in_invariant_set
from ace_drake.control.joint_model import ramp_tracking_lag, simulate_joint
from ace_drake.control.stack import plan_state, random_invariant_state
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


def test_the_safety_benchmark_decides_as_the_supervisor_does(monkeypatch):
    """On the same start states and actions, the benchmark's decision (ControlStack.propose) and
    the SafetySupervisor's in the control stack's diagram (ActionMapper -> SplineQp -> ResetMpc ->
    SafetySupervisor) are the same, and the benchmark takes it from decide_segment."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from ace_drake.analysis import control_bench
    from ace_drake.control import stack as stack_module
    from ace_drake.systems.action_mapper import ActionMapper
    from ace_drake.systems.reset_mpc import ResetMpc
    from ace_drake.systems.safety_supervisor import SafetySupervisor
    from ace_drake.systems.spline_qp import SplineQp

    stack = make_stack()
    builder = DiagramBuilder()
    mapper, qp = builder.AddSystem(ActionMapper(stack)), builder.AddSystem(SplineQp(stack))
    reset, dut = builder.AddSystem(ResetMpc(stack)), builder.AddSystem(SafetySupervisor(stack))
    builder.Connect(dut.segment_start_state_port, mapper.segment_start_state_port)
    builder.Connect(dut.segment_start_state_port, qp.segment_start_state_port)
    builder.Connect(mapper.target_port, qp.target_port)
    builder.Connect(qp.segment_port, reset.segment_port)
    builder.Connect(qp.segment_port, dut.segment_port)
    builder.Connect(reset.reset_port, dut.reset_port)
    diagram = builder.Build()
    rng = np.random.default_rng(3)
    outcomes = set()
    for case in range(24):
        while True:
            q, v, a = random_invariant_state(stack, rng)
            if stack.initial_plan(q, v, a)[1]:
                break
        action = random_action(rng, ACTION_KINDS[case % len(ACTION_KINDS)], 1)
        context = diagram.CreateDefaultContext()
        context.SetTime(0.032)  # a segment boundary
        supervisor_context = dut.GetMyMutableContextFromRoot(context)
        dut.Initialize(supervisor_context, q, v, a)
        mapper.action_port.FixValue(mapper.GetMyMutableContextFromRoot(context), action)
        mapper.action_valid_port.FixValue(mapper.GetMyMutableContextFromRoot(context), [1.0])
        dut.light_curtain_port.FixValue(supervisor_context, [0.0])
        # The benchmark proposes from its plan's first sample, as the supervisor's systems do.
        start = np.split(dut.segment_start_state_port.Eval(supervisor_context), 3)
        np.testing.assert_array_equal(np.concatenate(start), np.concatenate(plan_state(stack.initial_plan(q, v, a)[0], 0)))
        Simulator(diagram, context).AdvanceTo(0.0325)  # the boundary's update, and no other
        after = dut.supervisor_state(supervisor_context)
        decision = stack.propose(*start, action).decision
        if decision.accepted:
            assert (after.accepted, after.rejected, after.plan_start) == (1, 0, 32)
            # The same plan up to the spline QP's rounding (two solves of one problem by the shared,
            # warm-started solver differ in the last bits).
            np.testing.assert_allclose(after.plan.q, decision.plan.q, rtol=0, atol=1e-12)
            np.testing.assert_allclose(after.plan.v, decision.plan.v, rtol=0, atol=1e-9)
        else:
            assert decision.refused and (after.accepted, after.rejected, after.last_reason) == (0, 1, decision.reason)
        outcomes.add(decision.reason.split(":")[0])
    assert "" in outcomes and len(outcomes) >= 2, outcomes  # accepted and refused cases both

    calls = []
    decide = stack_module.decide_segment
    monkeypatch.setattr(stack_module, "decide_segment", lambda *args: calls.append(1) or decide(*args))
    counts = control_bench.execute_case(stack, np.random.default_rng(0), CommandLimits.hardware(RobotScenario().limits))
    assert len(calls) == counts.steps == counts.accepted + counts.refused
