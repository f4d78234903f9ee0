"""PolicyController: when it calls the policy, what it holds, torch modules and bad outputs."""

import numpy as np
import pytest
import torch
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from ace_drake.control.params import ControlParams
from ace_drake.systems.policy_controller import PolicyController


def controller_diagram(policy, observation=(1.0, 2.0, 3.0)):
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("dut", PolicyController(policy, len(observation), ControlParams()))
    source = builder.AddSystem(ConstantVectorSource(np.asarray(observation)))
    builder.Connect(source.get_output_port(), dut.observation_port)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    return dut, simulator, dut.GetMyContextFromRoot(simulator.get_context())


def test_the_policy_runs_5_ms_before_each_32_ms_segment():
    seen = []

    def policy(observation):
        seen.append(observation.copy())
        return np.full(16, 0.25 * len(seen))

    dut, simulator, context = controller_diagram(policy)
    # Drake handles an event at t when it advances from t: look just after.
    simulator.AdvanceTo(0.0269)
    assert dut.counts(context) == (0, 0) and dut.action_valid_port.Eval(context)[0] == 0.0
    simulator.AdvanceTo(0.0271)
    assert dut.counts(context) == (1, 0)
    np.testing.assert_array_equal(dut.action_port.Eval(context), 0.25)
    assert dut.action_valid_port.Eval(context)[0] == 1.0
    simulator.AdvanceTo(0.0589)
    assert dut.counts(context)[0] == 1
    simulator.AdvanceTo(0.0591)
    assert dut.counts(context)[0] == 2
    np.testing.assert_array_equal(seen[0], [1.0, 2.0, 3.0])
    # Finite actions beyond the box are clipped into it (the fourth call returns 1.25).
    simulator.AdvanceTo(0.0271 + 3 * 0.032)
    np.testing.assert_array_equal(dut.action_port.Eval(context), 1.0)


def test_none_and_garbage_mean_no_segment():
    outputs = iter([np.ones(16), None, np.full(16, np.nan), np.ones(3)])
    dut, simulator, context = controller_diagram(lambda observation: next(outputs))
    valid = []
    for k in range(4):
        simulator.AdvanceTo(0.0271 + 0.032 * k)
        valid.append(dut.action_valid_port.Eval(context)[0])
    assert valid == [1.0, 0.0, 0.0, 0.0]
    assert dut.counts(context) == (4, 2)


def test_a_torch_module_is_a_policy():
    torch.manual_seed(0)
    module = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Tanh())
    dut, simulator, context = controller_diagram(module)
    simulator.AdvanceTo(0.0271)
    with torch.no_grad():
        expected = module(torch.tensor([[1.0, 2.0, 3.0]])).numpy()[0]
    np.testing.assert_allclose(dut.action_port.Eval(context), expected, rtol=1e-6)


def test_not_a_policy_raises():
    with pytest.raises(TypeError, match="callable"):
        PolicyController(42, 3)


def external_controller_diagram():
    """A controller without a policy, its action_request exported as the diagram's input."""
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("dut", PolicyController(None, 3, ControlParams()))
    source = builder.AddSystem(ConstantVectorSource(np.zeros(3)))
    builder.Connect(source.get_output_port(), dut.observation_port)
    builder.ExportInput(dut.action_request_port, "action_request")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    return dut, diagram, simulator, dut.GetMyContextFromRoot(simulator.get_context())


def test_without_a_policy_the_action_is_read_from_the_request_at_each_event():
    dut, diagram, simulator, context = external_controller_diagram()
    assert dut.external and dut.action_request_port.size() == 17
    request = diagram.GetInputPort("action_request")
    root = simulator.get_mutable_context()
    request.FixValue(root, np.r_[np.full(16, 0.5), 1.0])
    simulator.AdvanceTo(0.027)  # stops before the event at 27 ms: a request fixed now is read there
    request.FixValue(root, np.r_[np.full(16, -0.25), 1.0])
    simulator.AdvanceTo(0.0271)
    np.testing.assert_array_equal(dut.action_port.Eval(context), -0.25)
    assert dut.action_valid_port.Eval(context)[0] == 1.0 and dut.counts(context) == (1, 0)
    # A request that is not valid means no new segment; the last action is kept but not valid.
    request.FixValue(root, np.r_[np.full(16, 0.75), 0.0])
    simulator.AdvanceTo(0.0591)
    assert dut.action_valid_port.Eval(context)[0] == 0.0 and dut.counts(context) == (2, 0)
    np.testing.assert_array_equal(dut.action_port.Eval(context), -0.25)
    # A valid request with non-finite values is counted as invalid; values beyond the box are clipped.
    request.FixValue(root, np.r_[np.full(16, np.nan), 1.0])
    simulator.AdvanceTo(0.0911)
    assert dut.action_valid_port.Eval(context)[0] == 0.0 and dut.counts(context) == (3, 1)
    request.FixValue(root, np.r_[np.full(16, 3.0), 1.0])
    simulator.AdvanceTo(0.1231)
    np.testing.assert_array_equal(dut.action_port.Eval(context), 1.0)


def test_with_a_policy_there_is_no_request_port():
    dut = PolicyController(lambda observation: None, 3)
    assert not dut.external and dut.action_request_port is None
    assert [dut.get_input_port(i).get_name() for i in range(dut.num_input_ports())] == ["observation", "random_seed"]


def test_noisy_actions_add_seeded_gaussian_noise_in_the_box():
    from ace_drake.config import ConfigError
    from ace_drake.evaluation.controllers import NoisyActions

    resets = []

    class Fixed:
        def reset(self):
            resets.append(1)

        def __call__(self, observation):
            return None if observation[0] > 0 else np.full(16, 0.5)

    dut = NoisyActions(Fixed(), 0.1, seed=3)
    actions = np.array([dut(np.zeros(4)) for _ in range(2000)])
    assert np.std(actions - 0.5) == pytest.approx(0.1, rel=0.05) and abs(np.mean(actions - 0.5)) < 0.01
    assert dut(np.ones(4)) is None  # no action stays no action
    np.testing.assert_array_equal(NoisyActions(Fixed(), 0.1, seed=3)(np.zeros(4)), actions[0])  # seeded
    assert np.all(np.abs(NoisyActions(Fixed(), 5.0)(np.zeros(4))) <= 1.0)  # clipped into the box
    dut.reset()
    assert resets == [1]
    with pytest.raises(ConfigError, match=">= 0"):
        NoisyActions(Fixed(), -0.1)


def test_a_stochastic_policy_is_reseeded_by_the_episode_seed_from_the_random_context():
    # ResetPolicy hands a policy whose reset takes a seed the episode's seed (the random_seed
    # input, drawn by SetRandomContext): its noise then depends on that seed, not on earlier episodes.
    from pydrake.common import RandomGenerator

    from ace_drake.diagrams import add_random_sources
    from ace_drake.evaluation.controllers import NoisyActions

    policy = NoisyActions(lambda observation: np.zeros(16), 0.1, seed=3)
    builder = DiagramBuilder()
    dut = builder.AddNamedSystem("dut", PolicyController(policy, 3, ControlParams()))
    source = builder.AddSystem(ConstantVectorSource(np.zeros(3)))
    builder.Connect(source.get_output_port(), dut.observation_port)
    add_random_sources(builder)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()

    def episode(seed, calls):
        diagram.SetRandomContext(context, RandomGenerator(seed))
        dut.ResetPolicy(dut.GetMyContextFromRoot(context))
        return np.array([policy(np.zeros(3)) for _ in range(calls)])

    first = episode(5, 4)
    np.testing.assert_array_equal(episode(5, 2), first[:2])  # whatever came before
    assert not np.allclose(episode(6, 4), first)
