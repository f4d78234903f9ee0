"""Rally episodes on the rally diagram (diagrams.add_rally, evaluation/runner.py)."""

import numpy as np
import pytest

from ace_drake.contracts import Outcome
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_rally_diagram
from ace_drake.evaluation.runner import RallyRunner
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.flight import make_state

# Bounces on the robot's half 0.64 m behind the net and flies on past the robot's end.
SHOT = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))


class Recorder:
    """A policy that never acts, keeps what it observed and counts the episodes it was told of."""

    def __init__(self):
        self.observations = []
        self.resets = 0

    def reset(self):
        self.resets += 1

    def __call__(self, observation):
        self.observations.append(np.array(observation))
        return None


@pytest.fixture(scope="module")
def runner_and_policy():
    params = RallyParams(perception=PerceptionParams(positions="statistical"))
    policy = Recorder()
    return RallyRunner(build_rally_diagram(params, policy), params), policy


def test_a_robot_that_never_moves_misses_and_the_policy_sees_the_ball(runner_and_policy):
    runner, policy = runner_and_policy
    episode = runner.run(SHOT, seed=3)
    assert episode.result.outcome is Outcome.MISSED and episode.result.bounce is not None
    assert episode.segments == (0, 0)
    layout = runner.diagram.GetSubsystemByName("observation_builder").layout
    # Called every 32 ms, 5 ms before each segment: at 27, 59, ... ms.
    assert len(policy.observations) == int((episode.duration + 0.005) / 0.032)
    late = policy.observations[15]
    assert layout.part(late, "estimate_status")[0] == 1.0
    # The estimate extrapolated to the observation time is near the latest (~10 ms old) position.
    np.testing.assert_allclose(layout.part(late, "estimate")[:3], layout.part(late, "positions")[0, :3], atol=0.2)
    joints = runner.diagram.GetSubsystemByName("joint_plant")
    q = joints.q_port.Eval(joints.GetMyContextFromRoot(runner.context))
    np.testing.assert_allclose(q, runner.diagram.GetSubsystemByName("safety_supervisor").stack.reset_pose, atol=1e-9)
    np.testing.assert_array_equal(episode.skill, [0.0, 1.0, 0.0])  # the ObservationBuilder's default
    np.testing.assert_array_equal(runner.run(SHOT, seed=3, skill=[0.4, 0.5, -1.0]).skill, [0.4, 0.5, -1.0])


def test_same_seed_same_episode_bit_for_bit(runner_and_policy):
    runner, policy = runner_and_policy
    logs = []
    for seed in (5, 5, 6):
        policy.observations.clear()
        runner.run(SHOT, seed=seed)
        logs.append(np.array(policy.observations))
    np.testing.assert_array_equal(logs[0], logs[1])
    assert not np.array_equal(logs[0], logs[2])  # the sensors' noise follows the seed


def test_bad_shots_are_refused(runner_and_policy):
    runner, _ = runner_and_policy
    with pytest.raises(ValueError, match="9 finite values"):
        runner.run(np.zeros(6))


def test_each_episode_starts_with_empty_logs_and_a_told_policy(runner_and_policy):
    runner, policy = runner_and_policy
    resets = policy.resets
    for seed in (1, 2):
        episode = runner.run(SHOT, seed=seed)
    assert policy.resets == resets + 2
    times = runner.diagram.GetSubsystemByName("ball_logger").FindLog(runner.context).sample_times()
    assert times[0] == 0.0 and np.all(np.diff(times) > 0) and times[-1] <= episode.duration + 1e-9
