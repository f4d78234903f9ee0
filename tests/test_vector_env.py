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
    episodes = dut.collect(4, "ou") + dut.collect(6, "policy")  # the running OU episodes end as OU ones
    assert len(episodes) >= 5 and {e.mode for e in episodes} == {"ou", "policy"}
    for episode in episodes:
        t = episode.transitions
        assert t["done"][-1] == 1.0 and not t["done"][:-1].any() and t["reward"][-1] != 0.0 and not t["reward"][:-1].any()
        np.testing.assert_array_equal(t["obs"][1:], t["next_obs"][:-1])
        assert episode.end in ("out_of_play", "hit", "passed", "collision", "time_limit")
        assert episode.summary.closest_approach is not None and episode.summary.closest_approach >= 0.0
    with pytest.raises(ValueError, match="mode"):
        dut.collect(1, "teleport")


def test_hold_actions_continue_the_plan_from_the_segment_the_next_step_decides(distribution):
    """The hold action of an environment starts where its observation says the next segment
    starts (the plan at the boundary the next step decides), and a step with it commands the plan
    on: the same joint commands as a step that asks for no segment."""
    from ace_drake.control.action_mapping import map_action
    from ace_drake.control.feasible_set import feasible_sets

    dut = RallyVectorEnv(3, PARAMS, distribution)
    obs, _ = dut.reset(seed=4)
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(5):
        holds = dut.hold_actions()
        for row, state in enumerate(dut._supervisor_states()):
            q0, v0, a0 = np.split(dut.layout.part(obs[row].astype(float), "robot_state"), 3)
            boundary = int(dut.timing.boundary_sample(dut._clock.ticks(dut._clock.GetMyContextFromRoot(dut.context)))[row])
            plan_q0, plan_v0, _ = state.plan.state(int(np.clip(boundary - state.plan_start, 0, state.plan.samples)))
            np.testing.assert_allclose(q0, plan_q0, atol=1e-6)  # float32 observation
            np.testing.assert_allclose(v0, plan_v0, atol=1e-5)
            first = int(np.clip(boundary - state.plan_start, 0, state.plan.samples))
            sets = feasible_sets(*state.plan.state(first), dut.stack.limits, dut.stack.control, dut.stack.period)
            q1, v1 = map_action(holds[row], sets)
            target_q, target_v, _ = state.plan.state(min(first + dut.stack.control.segment_samples, state.plan.samples))
            n = target_q.size
            inside = np.all(np.abs(holds[row]).reshape(2, n) < 1.0 - 1e-9, axis=0)  # a joint outside the box maps onto its boundary
            np.testing.assert_allclose(q1[inside], target_q[inside], atol=1e-9)
            np.testing.assert_allclose(v1[inside], target_v[inside], atol=1e-9)
            checked += inside.sum()
        obs, *_ = dut.step(rng.uniform(-0.5, 0.5, (3, 16)))
    assert checked > 0.5 * 5 * 3 * 8  # most joints are inside: a reset plan brakes within the mapped set
    with pytest.raises(IndexError):
        dut.hold_actions([3])


def test_a_vector_worker_demonstrates_and_labels_with_one_returner_per_environment(distribution):
    """Demonstrator episodes: the returner acts (its label, or its label with DART noise) and every
    step is labelled; DAgger episodes: the actor acts and the returner labels; an episode started
    in one mode finishes in it after the mode changes; the returner returns balls."""
    from ace_drake.training.rollout import ExplorationParams, VectorRolloutWorker

    dut = VectorRolloutWorker(3, PARAMS, distribution=distribution, seed=5, exploration=ExplorationParams(demo_noise_fraction=0.5))
    demonstrated = dut.collect(6, "demonstrator")
    running = int((~dut._restarting).sum())  # episodes under way at the change of mode
    later = dut.collect(6, "dagger")
    assert len({id(r.model) for r in dut.returners}) == 1 and len({id(r) for r in dut.returners}) == 3
    assert {e.mode for e in demonstrated} == {"demonstrator"}
    still = sum(mode == "demonstrator" and not restarting for mode, restarting in zip(dut._modes, dut._restarting))
    assert [e.mode for e in later].count("demonstrator") + still == running  # the running ones go on (or finished) as begun
    assert "dagger" in {e.mode for e in later}  # new episodes start in the new mode (which finishes last depends on their lengths)
    noisy = exact = 0
    for episode in demonstrated + later:
        t = episode.transitions
        assert t["demo_action"].shape == t["action"].shape and np.isfinite(t["demo_action"]).all()
        assert np.all(np.abs(t["demo_action"]) <= 1.0)
        if episode.mode == "demonstrator":
            same = np.all(t["action"] == t["demo_action"], axis=1)
            exact += same.sum()
            noisy += (~same).sum()
            assert np.abs(t["action"] - t["demo_action"]).max() < 0.5  # DART noise of std 0.05, clipped into the box
    assert exact > 0 and noisy > 0
    assert sum(e.returned for e in demonstrated) >= 2, [e.outcome for e in demonstrated]


def test_a_short_run_on_the_batched_diagram_lowers_the_critic_loss(distribution):
    """SAC on episodes collected batched (OU exploration on 8 environments, the event tables with
    hindsight relabelling): the critic's loss on one fixed batch of those transitions falls."""
    import torch

    from ace_drake.learning.replay import EventReplay, ReplayConfig
    from ace_drake.learning.sac import SacConfig, SacLearner
    from ace_drake.training.rollout import VectorRolloutWorker

    torch.set_num_threads(1)
    config = SacConfig(batch_size=64, actor_hidden=(64, 64), embedding_size=32, decoder_hidden=(32,), critic_hidden=(64, 64),
                       critic_lr=1e-3, seed=3)
    worker = VectorRolloutWorker(8, PARAMS, sac=config, distribution=distribution, seed=3)
    replay = EventReplay(ReplayConfig(seed=3), config.layout, PARAMS.reward)
    for episode in worker.collect(48, "ou"):
        replay.add_episode(episode.transitions, episode.summary)
    learner = SacLearner(config, PARAMS.rally)
    fixed = replay.sample(256)

    def critic_loss() -> float:
        with torch.no_grad():
            b = learner._tensors(fixed)
            y = learner.target(b)
            q1, q2 = learner.critic(learner.critic_features(b["privileged"], b["obs"]), b["action"])
            return float(torch.mean((q1 - y) ** 2) + torch.mean((q2 - y) ** 2))

    before = critic_loss()
    for _ in range(300):
        learner.update(replay.sample(config.batch_size))
    after = critic_loss()
    assert len(replay) > 200 and after < 0.5 * before, (len(replay), before, after)


def test_a_returns_flight_is_decided_as_the_reference_propagator_decides_it(distribution, monkeypatch):
    """After the hit the environment flies the ball on with the compiled one-ball propagator
    (``simulate_ball``): the returner's episodes end with the same outcomes, landings and rewards
    as with ``simulate``, the NumPy reference it equals bit for bit."""
    from ace_drake.physics import propagate
    from ace_drake.training import vector_env
    from ace_drake.training.rollout import VectorRolloutWorker

    def collect():
        return VectorRolloutWorker(2, PARAMS, distribution=distribution, seed=6).collect(4, "demonstrator")

    compiled = collect()
    monkeypatch.setattr(vector_env, "simulate_ball", lambda *args, **kwargs: propagate.simulate(*args, **kwargs, record=False))
    reference = collect()
    assert len(compiled) == len(reference) >= 4
    assert sum(e.summary.result.outcome.value == "returned" for e in compiled) >= 1  # some flights were flown on
    for mine, theirs in zip(compiled, reference):
        a, b = mine.summary.result, theirs.summary.result
        assert (a.outcome, a.reason) == (b.outcome, b.reason) and (a.landing is None) == (b.landing is None)
        if a.landing is not None:
            assert a.landing.kind == b.landing.kind and a.landing.time == b.landing.time
            np.testing.assert_array_equal(a.landing.state_pre, b.landing.state_pre)
        np.testing.assert_array_equal(mine.transitions["reward"], theirs.transitions["reward"])
