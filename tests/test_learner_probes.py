"""The study probes of analysis.learner_probes: the returner's action substituted exactly where
asked, and the critic's preference read off a critic whose values are known."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ace_drake.analysis import learner_probes
from ace_drake.analysis.learner_probes import SubstitutingWorker, critic_against_outcome, critic_preference, substitution_rollouts
from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.learning.replay import load_weights_only
from ace_drake.learning.sac import PRIVILEGED_SIZE, SacLearner
from ace_drake.play.shots import make_distribution
from ace_drake.training.loop import load_train_config
from ace_drake.training.rollout import Episode

CONFIG = load_train_config(MODELS_DIR / "train_rally_paper_mc.yaml")
CONFIG = dataclasses.replace(CONFIG, env=dataclasses.replace(CONFIG.env, shot_batch=8))


@pytest.fixture(scope="module")
def distribution():
    return make_distribution(CONFIG.env.shots, CONFIG.env.rally.physics)


@pytest.fixture(scope="module")
def actor():
    return load_weights_only(MODELS_DIR / "policies" / "rally_paper_mc.pt")["actor"]


def near_rows(worker, transitions, window):
    near = worker.learner.config.layout.hit_within(transitions["obs"], window)
    return near & np.isfinite(transitions["demo_action"]).all(axis=-1)


@pytest.mark.parametrize("substitute", ["stroke", "first"])
def test_the_returner_acts_exactly_where_the_substitution_says(distribution, actor, substitute):
    window = 0.3
    worker = SubstitutingWorker(2, CONFIG, substitute, window, seed=3, distribution=distribution)
    worker.set_actor(actor)
    episodes = worker.collect(3)
    substituted = 0
    for episode in episodes:
        t = episode.transitions
        own = worker.learner.act(t["obs"], deterministic=True)  # the actor's deterministic action
        played_label = np.all(t["action"] == t["demo_action"], axis=-1)
        near = near_rows(worker, t, window)
        if substitute == "stroke":
            np.testing.assert_array_equal(played_label[near], True)
        else:  # the first near row only
            first = np.zeros_like(near)
            first[np.argmax(near)] = near.any()
            np.testing.assert_array_equal(played_label[first], True)
            near = first
        np.testing.assert_allclose(t["action"][~near], own[~near], atol=1e-5)
        substituted += int(near.sum())
    layout = worker.learner.config.layout
    predicted_far = sum(int((layout.hit_within(e.transitions["obs"], 10.0) & ~layout.hit_within(e.transitions["obs"], window)).sum())
                        for e in episodes)
    assert substituted > 0 and predicted_far > 0  # the window, not the prediction, decides


def test_a_substitution_is_one_of_the_four(distribution):
    with pytest.raises(ValueError, match="substitute must be one of"):
        SubstitutingWorker(2, CONFIG, "half", distribution=distribution)
    with pytest.raises(ValueError, match="window"):
        SubstitutingWorker(2, CONFIG, "stroke", -0.1, distribution=distribution)
    with pytest.raises(ValueError, match="sets the mode"):
        SubstitutingWorker(2, CONFIG, "none", distribution=distribution).collect(1, "policy")


def test_substitution_rollouts_count_every_episode_once(distribution, actor):
    figures = substitution_rollouts(CONFIG, actor, "returner", episodes=3, seed=1, batch=2, distribution=distribution)
    assert figures["episodes"] == 3 == sum(figures["ends"].values())
    assert figures["legal"] == 3 - sum(n for key, n in figures["ends"].items() if key.startswith("invalid/"))
    assert figures["returned"] == sum(n for key, n in figures["ends"].items() if key.startswith("returned/"))


class KnownCritic(torch.nn.Module):
    """Twin critics that both value an action by -|a - best|^2, ``best`` one action per row."""

    def __init__(self, best):
        super().__init__()
        self.best = best

    def forward(self, features, action):
        q = -torch.sum((action - self.best) ** 2, dim=-1)
        return q, q + 1.0  # the minimum is the first


def test_the_critics_preference_by_time_to_the_hit():
    learner = SacLearner()
    layout = ObservationLayout()
    rng = np.random.default_rng(0)
    n = 60
    obs = rng.normal(size=(n, layout.size)).astype(np.float32) * 0.1
    times = np.repeat([0.05, 0.15, 0.25, 0.4, 0.8, 0.0], 10)
    prediction = layout.slice("hit_prediction")
    obs[:, prediction.start] = np.repeat([1, 1, 1, 1, 1, 0], 10)  # the last ten: no valid prediction
    obs[:, prediction.start + 1] = times
    best = torch.as_tensor(rng.uniform(-0.5, 0.5, (n, ACTION_SIZE)), dtype=torch.float32)
    learner.critic = KnownCritic(best)
    rows = {"obs": obs, "privileged": np.zeros((n, PRIVILEGED_SIZE), np.float32), "demo_action": best.numpy()}
    table = critic_preference(learner, rows)
    assert [row["band"] for row in table] == ["none", "-inf-0.1 s", "0.1-0.2 s", "0.2-0.3 s", "0.3-0.5 s", "0.5-inf s"]
    assert all(row["rows"] == 10 for row in table) and sum(row["share"] for row in table) == pytest.approx(1.0)
    for row in table:  # the label is the critic's best action: preferred everywhere, and uphill
        assert row["label_preferred"] == 1.0 and row["q_label_minus_action"] > 0.0 and row["ascent_cosine"] > 0.9
        # squared error: the cloning gradient is the critic's ascent (-|a - best|^2 is minus its error)
        assert row["cloning_norm"] == pytest.approx(row["ascent_norm"], rel=1e-5)
    rows["demo_action"] = np.clip(2.0 * np.asarray(learner.act(obs, deterministic=True)) - best.numpy(), -1.0, 1.0)
    for row in critic_preference(learner, rows):  # labels mirrored away from the best action: downhill
        assert row["label_preferred"] < 0.2 and row["ascent_cosine"] < -0.5
    with pytest.raises(ValueError, match="no 'averaged' actor"):
        critic_preference(learner, rows, actor="averaged")


def test_a_portable_checkpoint_has_no_rows_to_probe(tmp_path):
    path = tmp_path / "checkpoint.portable.pt"
    torch.save({"demonstrations": None}, path)
    with pytest.raises(ValueError, match="portable"):
        learner_probes.checkpoint_rows(path)


def test_the_critic_against_the_discounted_outcome():
    learner = SacLearner()
    learner.critic = KnownCritic(torch.zeros(ACTION_SIZE))  # Q = -|a|^2: 0 for zero actions
    layout = ObservationLayout()
    obs = np.zeros((3, layout.size), np.float32)
    prediction = layout.slice("hit_prediction")
    obs[:, prediction.start] = 1.0
    obs[:, prediction.start + 1] = [0.5, 0.2, 0.0]  # the last two steps within 0.3 s of the hit
    transitions = {"obs": obs, "privileged": np.zeros((3, PRIVILEGED_SIZE), np.float32), "action": np.zeros((3, ACTION_SIZE), np.float32),
                   "reward": np.array([0.0, 0.0, 2.0], np.float32)}
    episode = Episode(transitions, None, "guided", "returned", "hit", np.zeros(3), 0.0)
    figures = critic_against_outcome(learner, [episode], window=0.3)
    gamma = learner.config.gamma
    assert figures["near"]["steps"] == 2 and figures["elsewhere"]["steps"] == 1
    assert figures["near"]["q"] == 0.0 and figures["near"]["outcome"] == pytest.approx((2.0 * gamma + 2.0) / 2)
    assert figures["elsewhere"]["outcome"] == pytest.approx(2.0 * gamma**2)
