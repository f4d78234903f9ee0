"""Joint model of paper eq. (9): exact sampling with fractional delays, conversions."""

import numpy as np
import pytest

from ace_drake.config import ConfigError, from_dict
from ace_drake.control.joint_model import ProcessModel, discretize, ramp_tracking_lag, simulate_joint, step_response
from ace_drake.robot.params import JointDynamicsParams, RobotDynamicsParams


@pytest.mark.parametrize("delay", [0.0, 0.001, 0.0023, 0.0049])
def test_sampled_step_matches_the_analytic_response(delay):
    joint = ProcessModel(1.0, 800.0, 0.7, delay).to_state_space()
    command = np.r_[np.zeros(5), np.ones(55)]
    times = np.arange(60) * 1e-3
    np.testing.assert_allclose(simulate_joint(joint, command, 1e-3), step_response(joint, times - 0.005), atol=1e-12)


def test_nothing_moves_before_the_delay_has_passed():
    joint = ProcessModel(1.0, 1000.0, 0.9, 0.0034).to_state_space()
    q = simulate_joint(joint, np.r_[0.0, np.ones(20)], 1e-3)  # the step is applied from t = 1 ms
    assert np.all(q[:5] == 0.0)  # 1 + 3.4 ms: samples 0..4 are before it acts
    assert q[5] > 0.0


def test_step_response_hand_worked():
    # Critically damped, w = 100 rad/s, no delay: q(t) = 1 - (1 + w t) e^{-w t}.
    joint = ProcessModel(1.0, 100.0, 1.0, 0.0).to_state_space()
    t = np.array([0.0, 0.01, 0.03])
    np.testing.assert_allclose(step_response(joint, t), 1 - (1 + 100 * t) * np.exp(-100 * t), atol=1e-12)


def test_process_model_round_trip_and_default_lag():
    process = ProcessModel(1.05, 700.0, 0.8, 0.0021)
    back = ProcessModel.from_state_space(process.to_state_space())
    for field in ("gain", "natural_frequency", "damping_ratio", "delay"):
        assert getattr(back, field) == pytest.approx(getattr(process, field), rel=1e-12)
    default = JointDynamicsParams()
    assert ramp_tracking_lag(default) == pytest.approx(0.002 + 2 * 0.9 / 1000)
    assert ramp_tracking_lag(default) < 0.005  # the paper's tracking delay bound


def test_discretize_splits_whole_and_fractional_periods():
    phi, gamma0, gamma1, k = discretize(ProcessModel(1.0, 500.0, 0.8, 0.0025).to_state_space(), 1e-3)
    assert k == 2
    # DC: a constant input u held for ever gives zeta = (I - Phi)^-1 (Gamma0 + Gamma1) u = [u, 0].
    np.testing.assert_allclose(np.linalg.solve(np.eye(2) - phi, gamma0 + gamma1), [1.0, 0.0], atol=1e-12)


def test_config_rejects_unphysical_joints():
    with pytest.raises(ConfigError, match="Hurwitz"):
        JointDynamicsParams(a=(0.0, 1.0, 1e6, -10.0))
    with pytest.raises(ConfigError, match="q_aux = velocity"):
        JointDynamicsParams(a=(1.0, 1.0, -1e6, -10.0))
    with pytest.raises(ConfigError, match="joints"):
        from_dict(RobotDynamicsParams, {"joints": [{}] * 3})
    with pytest.raises(ValueError, match="non-empty"):
        simulate_joint(JointDynamicsParams(), np.zeros((2, 2)), 1e-3)


def test_feedforward_command_makes_the_delayed_joint_follow_a_motion():
    # Desired q_d(t) = 0.3 sin(2 pi 3 t); command u(t_n) = inverse of eq. (9) at t_n + tau + T/2.
    from ace_drake.control.joint_model import feedforward_command

    joint = ProcessModel(1.0, 900.0, 0.8, 0.0023).to_state_space()
    period, omega = 1e-3, 2 * np.pi * 3
    t_n = np.arange(400) * period
    felt = t_n + joint.delay + 0.5 * period
    command = feedforward_command([joint], 0.3 * np.sin(omega * felt)[:, None], 0.3 * omega * np.cos(omega * felt)[:, None],
                                  -0.3 * omega**2 * np.sin(omega * felt)[:, None])[:, 0]
    q = simulate_joint(joint, command, period)
    error = q[100:] - 0.3 * np.sin(omega * t_n[100:])
    assert np.max(np.abs(error)) < 2e-4  # rad; against 0.3 rad of motion and 3.2 ms of lag uncompensated
    lagging = simulate_joint(joint, 0.3 * np.sin(omega * t_n), period)
    assert np.max(np.abs(lagging[100:] - 0.3 * np.sin(omega * t_n[100:]))) > 10 * np.max(np.abs(error))


def test_the_segment_propagation_equals_period_by_period_propagation_bit_for_bit():
    """``propagate_samples`` (the two holds' coefficients computed once) against ``propagate``
    over one period at a time: under-, over- and critically damped joints, whole and fractional
    delays, a batch of environments."""
    from ace_drake.control.joint_model import JointPropagator

    joints = [ProcessModel(1.0, w, zeta, delay).to_state_space() for w, zeta, delay in
              [(800.0, 0.7, 0.003), (300.0, 1.0, 0.0023), (150.0, 2.5, 0.0), (1000.0, 0.2, 0.0049), (500.0, 1.0, 0.001)]]
    propagator = JointPropagator(joints, 1e-3)
    rng = np.random.default_rng(3)
    zeta, u_old, u_new = rng.normal(size=(3, 5, 2)), rng.normal(size=(3, 32, 5)), rng.normal(size=(3, 32, 5))
    samples = propagator.propagate_samples(zeta, u_old, u_new)
    for row in range(3):
        state = zeta[row]
        np.testing.assert_array_equal(samples[row, 0], state)
        for period in range(32):
            state = propagator.propagate(state, u_old[row, period], u_new[row, period], 1e-3)
            np.testing.assert_array_equal(samples[row, period + 1], state)
