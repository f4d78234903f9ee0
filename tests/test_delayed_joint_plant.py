"""DelayedJointPlant: paper eq. (9) sampled at 1 kHz, exact at and between the samples."""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from ace_drake.control.joint_model import JointPropagator, ProcessModel, discretize, simulate_joint, step_response
from ace_drake.robot.params import JointDynamicsParams, RobotDynamicsParams
from ace_drake.systems.delayed_joint_plant import DelayedJointPlant

PERIOD = 1e-3
# (natural frequency rad/s, damping ratio, delay s): whole, fractional and zero delays; under-,
# critically (exactly, and 1e-6 either side) and over-damped joints.
MIXED_JOINTS = (
    (1000.0, 0.9, 0.0),
    (800.0, 0.7, 0.001),
    (600.0, 0.5, 0.0023),
    (1200.0, 1.0, 0.0049),
    (300.0, 1.5, 0.0005),
    (1000.0, 0.3, 0.002),
    (500.0, 0.999999, 0.0031),
    (900.0, 1.000001, 0.0037),
)
MIXED = RobotDynamicsParams(joints=tuple(ProcessModel(1.0, w, zeta, delay).to_state_space() for w, zeta, delay in MIXED_JOINTS))


def make_simulator(params: RobotDynamicsParams, source):
    """The smallest diagram: ``source`` -> q_command of the plant. Returns (simulator, dut, dut context)."""
    builder = DiagramBuilder()
    dut = builder.AddSystem(DelayedJointPlant(params))
    builder.Connect(builder.AddSystem(source).get_output_port(), dut.q_command_port)
    simulator = Simulator(builder.Build())
    return simulator, dut, dut.GetMyContextFromRoot(simulator.get_mutable_context())


def test_sample_times_match_the_exact_discretisation():
    command = np.random.default_rng(0).uniform(-0.5, 0.5, (40, 8))
    breaks = np.arange(len(command) + 1) * PERIOD
    held = PiecewisePolynomial.ZeroOrderHold(breaks, np.vstack([command, command[-1]]).T)
    simulator, dut, context = make_simulator(MIXED, TrajectorySource(held))
    dut.SetJointState(context, q=command[0])  # simulate_joint starts at rest at command[0]

    q = []
    for time in breaks[:-1]:
        simulator.AdvanceTo(time)
        q.append(dut.q_port.Eval(context))

    expected = np.column_stack([simulate_joint(joint, command[:, i], PERIOD) for i, joint in enumerate(MIXED.joints)])
    np.testing.assert_allclose(q, expected, rtol=0, atol=1e-9)
    assert np.ptp(expected) > 0.5  # the joints did move


def test_between_samples_a_step_matches_the_analytic_response():
    simulator, dut, context = make_simulator(MIXED, ConstantVectorSource(np.ones(8)))  # rest at 0, step at t = 0
    for time in (0.00337, 0.00791, 0.0123):
        simulator.AdvanceTo(time)
        expected = [step_response(joint, [time])[0] for joint in MIXED.joints]
        np.testing.assert_allclose(dut.q_port.Eval(context), expected, rtol=0, atol=1e-9)


def test_a_longer_delay_starts_the_joint_later():
    delayed = dataclasses.replace(JointDynamicsParams(), delay=0.0035)
    params = RobotDynamicsParams(joints=(JointDynamicsParams(),) * 2 + (delayed,) + (JointDynamicsParams(),) * 5)
    simulator, dut, context = make_simulator(params, ConstantVectorSource(np.ones(8)))
    simulator.AdvanceTo(0.0034)
    q = dut.q_port.Eval(context)
    assert q[2] == 0.0 and np.all(np.delete(q, 2) > 0.0)
    simulator.AdvanceTo(0.0036)
    assert dut.q_port.Eval(context)[2] > 0.0


def test_rest_stays_exactly_at_rest():
    q0 = np.linspace(-1.0, 1.0, 8)
    simulator, dut, context = make_simulator(MIXED, ConstantVectorSource(q0))
    dut.SetJointState(context, q0)
    simulator.AdvanceTo(0.0205)
    np.testing.assert_array_equal(dut.joint_state_port.Eval(context), np.r_[q0, np.zeros(8)])


def moving_context(dut: DelayedJointPlant):
    """A bare context with random q, v and a new command sampled at t = 0 over an old one."""
    rng = np.random.default_rng(1)
    context = dut.CreateDefaultContext()
    dut.SetJointState(context, q=rng.uniform(-1, 1, 8), v=rng.uniform(-50, 50, 8), command=rng.uniform(-1, 1, 8))
    dut.q_command_port.FixValue(context, rng.uniform(-1, 1, 8))
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    return context


def test_the_update_does_not_jump_the_joints():
    dut = DelayedJointPlant(MIXED)
    context = moving_context(dut)
    context.SetTime(PERIOD)
    before = dut.joint_state_port.Eval(context).copy()  # the end of the first period
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    after = dut.joint_state_port.Eval(context)  # the start of the second
    np.testing.assert_allclose(after, before, rtol=1e-13, atol=1e-13)
    context.SetTime(1.5 * PERIOD)  # the update moved the last sample on by one period
    assert np.all(np.isfinite(dut.joint_state_port.Eval(context)))


def test_at_a_sample_the_output_is_the_state_stored_there():
    dut = DelayedJointPlant(MIXED)
    context = moving_context(dut)
    context.SetTime(PERIOD)
    context.SetDiscreteState(dut.EvalUniquePeriodicDiscreteUpdate(context))
    stored = context.get_discrete_state(0).get_value()  # [q, v] at t = PERIOD
    np.testing.assert_array_equal(dut.joint_state_port.Eval(context), stored)
    np.testing.assert_array_equal(dut.q_port.Eval(context), stored[:8])


def test_v_is_the_time_derivative_of_q():
    dut = DelayedJointPlant(MIXED)
    context = moving_context(dut)
    step = 1e-8  # s; the times are away from every joint's input switch at its f_i
    for time in (0.00021, 0.00057, 0.00083):
        context.SetTime(time + step)
        q_after = dut.q_port.Eval(context).copy()
        context.SetTime(time - step)
        q_before = dut.q_port.Eval(context).copy()
        context.SetTime(time)
        v = dut.joint_state_port.Eval(context)[8:]
        np.testing.assert_allclose((q_after - q_before) / (2 * step), v, rtol=1e-6, atol=1e-5)
        assert np.min(np.abs(v)) > 1.0


def test_outputs_are_defined_only_within_one_period_of_the_last_sample():
    dut = DelayedJointPlant()
    context = dut.CreateDefaultContext()
    context.SetTime(2.5 * PERIOD)
    with pytest.raises(RuntimeError, match="command period"):
        dut.q_port.Eval(context)
    dut.SetJointState(context, np.zeros(8))  # a new episode starting now
    np.testing.assert_array_equal(dut.q_port.Eval(context), np.zeros(8))


@pytest.mark.parametrize(
    "arguments, name",
    [
        (dict(q=np.zeros(7)), "q"),
        (dict(q="home"), "q"),
        (dict(q=np.zeros(8), v=np.full(8, np.nan)), "v"),
        (dict(q=np.zeros(8), command=np.r_[np.zeros(7), np.inf]), "command"),
    ],
)
def test_set_joint_state_rejects_bad_arguments(arguments, name):
    dut = DelayedJointPlant()
    with pytest.raises(ValueError, match=f"{name} must be 8 finite values"):
        dut.SetJointState(dut.CreateDefaultContext(), **arguments)


def test_propagator_over_a_period_is_the_exact_discretisation():
    joints = [ProcessModel(gain, w, zeta, delay).to_state_space() for gain, (w, zeta, delay) in zip(np.linspace(0.9, 1.1, 8), MIXED_JOINTS)]
    propagator = JointPropagator(joints, PERIOD)
    rng = np.random.default_rng(2)
    zeta, u_old, u_new = rng.uniform(-1, 1, (8, 2)) * [1.0, 100.0], rng.uniform(-1, 1, 8), rng.uniform(-1, 1, 8)
    propagated = propagator.propagate(zeta, u_old, u_new, PERIOD)
    for i, joint in enumerate(joints):
        phi, gamma0, gamma1, k = discretize(joint, PERIOD)
        assert propagator.whole_periods[i] == k
        np.testing.assert_allclose(propagated[i], phi @ zeta[i] + gamma1 * u_old[i] + gamma0 * u_new[i], rtol=1e-12, atol=1e-12)
