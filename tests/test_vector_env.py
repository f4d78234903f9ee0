"""RallyVectorEnv: gymnasium's checks, autoreset, and a batch equal to single environments."""

import dataclasses

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_reset_return_type, check_reset_seed_determinism, data_equivalence
from gymnasium.wrappers.vector import RecordEpisodeStatistics

from ace_drake.play.shots import make_distribution
from ace_drake.training.env import RallyEnvParams
from ace_drake.training.vector_env import RallyVectorEnv

PARAMS = RallyEnvParams(shot_batch=8)
PARAMS = dataclasses.replace(PARAMS, rally=dataclasses.replace(PARAMS.rally, hit_prediction=False))


@pytest.fixture(scope="module")
def distribution():
    return make_distribution(PARAMS.shots, PARAMS.rally.physics)


def test_gymnasiums_checks_pass(distribution):
    dut = RallyVectorEnv(2, PARAMS, distribution)
    check_reset_return_type(dut)
    check_reset_seed_determinism(dut)
    # gymnasium's check_step_determinism, for a vector env (it expects scalar flags)
    runs = []
    for _ in range(2):
        dut.reset(seed=123)
        dut.action_space.seed(123)
        runs.append([dut.step(dut.action_space.sample())[:4] for _ in range(3)])
    assert data_equivalence(runs[0], runs[1], exact=True)
    observations, infos = dut.reset(seed=1)
    assert dut.observation_space.contains(observations)
    assert observations.shape == (2, dut.layout.size) and infos["privileged"].shape == (2, 28)
    assert dut.metadata["autoreset_mode"].name == "NEXT_STEP"


def test_an_ended_episode_restarts_in_the_next_step(distribution):
    """Random actions end episodes (collisions, misses); the step after a terminal step starts the
    environment's next episode with reward 0, and gymnasium's episode statistics count them."""
    dut = RecordEpisodeStatistics(RallyVectorEnv(2, PARAMS, distribution))
    rng = np.random.default_rng(0)
    dut.reset(seed=3)
    ended = episodes_before = None
    for _ in range(80):
        _, rewards, terminated, truncated, infos = dut.step(rng.uniform(-1.0, 1.0, (2, 16)))
        assert not truncated.any()
        if ended is not None:
            assert np.all(rewards[ended] == 0.0) and not terminated[ended].any()
            assert np.all(infos["episode_index"][ended] == episodes_before[ended] + 1)
            break
        if terminated.any():
            ended = np.flatnonzero(terminated)
            episodes_before = dut.env._episode_index.copy()
            assert np.all(np.isin(infos["end"][ended], ["out_of_play", "hit", "passed", "collision", "time_limit"]))
            assert np.all(rewards[ended] != 0.0)
            assert "episode" in infos  # gymnasium's statistics of the episodes that ended
    assert ended is not None
    assert np.all(dut.env._episode_index[ended] == episodes_before[ended] + 1)


def test_a_batch_gives_each_environment_its_single_run(distribution):
    """Environment i of a batch of 3 plays, bit for bit, what a batch of one with first_index i
    plays from the same seed and actions (its episodes are a function of (seed, i, k))."""
    rng = np.random.default_rng(5)
    actions = rng.uniform(-0.3, 0.3, (25, 3, 16))
    batch = RallyVectorEnv(3, PARAMS, distribution)
    observations = [batch.reset(seed=9)[0]]
    rewards = []
    for step in actions:
        obs, reward, *_ = batch.step(step)
        observations.append(obs)
        rewards.append(reward)
    for index in (0, 2):
        single = RallyVectorEnv(1, PARAMS, distribution, first_index=index)
        got = [single.reset(seed=9)[0]]
        got_rewards = []
        for step in actions:
            obs, reward, *_ = single.step(step[index : index + 1])
            got.append(obs)
            got_rewards.append(reward)
        assert data_equivalence(np.array(got)[:, 0], np.array(observations)[:, index], exact=True)
        assert data_equivalence(np.array(got_rewards)[:, 0], np.array(rewards)[:, index], exact=True)


def test_bad_actions_are_refused(distribution):
    dut = RallyVectorEnv(2, PARAMS, distribution)
    with pytest.raises(RuntimeError, match="reset"):
        dut.step(np.zeros((2, 16)))
    dut.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(2, 16\)"):
        dut.step(np.zeros(16))
    with pytest.raises(ValueError, match="num_envs"):
        RallyVectorEnv(0, PARAMS, distribution)


def test_a_vector_worker_returns_whole_episodes(distribution):
    """The batched rollout worker steps its environments until episodes end and returns each
    ended one whole: its last transition terminal with the only non-zero reward, its next
    observations the following observations, none of the autoreset steps recorded."""
    from ace_drake.training.rollout import VectorRolloutWorker

    dut = VectorRolloutWorker(3, PARAMS, distribution=distribution, seed=2)
    episodes = dut.collect(4, "ou") + dut.collect(1, "policy")
    assert len(episodes) >= 5 and {e.mode for e in episodes} == {"ou", "policy"}
    for episode in episodes:
        t = episode.transitions
        assert t["done"][-1] == 1.0 and not t["done"][:-1].any() and t["reward"][-1] != 0.0 and not t["reward"][:-1].any()
        np.testing.assert_array_equal(t["obs"][1:], t["next_obs"][:-1])
        assert episode.end in ("out_of_play", "hit", "passed", "collision", "time_limit")
        assert episode.summary.closest_approach is not None and episode.summary.closest_approach >= 0.0
    with pytest.raises(ValueError, match="mode"):
        dut.collect(1, "demonstrator")
