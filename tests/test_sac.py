"""SacLearner: losses on hand-built batches, checkpoints, and a short run that learns."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from ace_drake.contracts import privileged_slice
from ace_drake.learning.networks import BALL_STATE_SCALE, squashed_gaussian_log_prob
from ace_drake.learning.sac import PRIVILEGED_SIZE, SacConfig, SacLearner, soft_target


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny networks run fastest on one thread (and the test machine has two cores)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


SMALL = dict(actor_hidden=(32,), embedding_size=32, decoder_hidden=(32,), critic_hidden=(32, 32), position_history=3, spin_history=3)


def make_batch(learner, size=16, seed=0):
    rng = np.random.default_rng(seed)
    n = learner.observation_size
    return {
        "obs": rng.normal(size=(size, n)),
        "privileged": rng.normal(size=(size, PRIVILEGED_SIZE)) * np.r_[BALL_STATE_SCALE, np.ones(19)],
        "action": rng.uniform(-1, 1, (size, 16)),
        "reward": rng.choice([-1.0, 0.0, 2.0], size),
        "next_obs": rng.normal(size=(size, n)),
        "next_privileged": rng.normal(size=(size, PRIVILEGED_SIZE)),
        "done": (rng.random(size) < 0.5).astype(float),
    }


def test_soft_target_by_hand():
    r, d = torch.tensor([1.0, -1.0, 0.5]), torch.tensor([0.0, 1.0, 0.0])
    q1, q2 = torch.tensor([2.0, 5.0, -1.0]), torch.tensor([3.0, 4.0, -2.0])
    log_prob = torch.tensor([-10.0, 3.0, 4.0])
    y = soft_target(r, d, q1, q2, log_prob, gamma=0.9, alpha=0.1)
    expected = [1.0 + 0.9 * (2.0 + 1.0), -1.0, 0.5 + 0.9 * (-2.0 - 0.4)]
    np.testing.assert_allclose(y.numpy(), expected, atol=1e-6)


def test_learner_target_uses_the_target_twins_min_and_the_entropy_term():
    learner = SacLearner(SacConfig(gamma=0.95, alpha=0.2, **SMALL))
    batch = make_batch(learner)
    state = learner.generator.get_state()
    y = learner.target(batch)
    # By hand: the same next actions (same generator state), the target twins, the formula.
    learner.generator.set_state(state)
    b = learner._tensors(batch)
    with torch.no_grad():
        a, log_prob, _, _ = learner.actor.sample(learner.actor_features(b["next_obs"]), learner.generator)
        features = learner.critic_features(b["next_privileged"], b["next_obs"])
        x = torch.cat([features, a], dim=-1)
        q1 = learner.target_critic.q1(x).squeeze(-1).numpy()
        q2 = learner.target_critic.q2(x).squeeze(-1).numpy()
    expected = batch["reward"] + 0.95 * (1 - batch["done"]) * (np.minimum(q1, q2) - 0.2 * log_prob.numpy())
    np.testing.assert_allclose(y.numpy(), expected, rtol=1e-5, atol=1e-6)
    # Terminal transitions: the target is the reward alone.
    terminal = batch["done"] == 1.0
    np.testing.assert_allclose(y.numpy()[terminal], batch["reward"][terminal], rtol=1e-6)


def test_critic_features_are_the_scaled_privileged_and_robot_state():
    learner = SacLearner(SacConfig(**SMALL))
    layout = learner.config.layout
    batch = learner._tensors(make_batch(learner))
    features = learner.critic_features(batch["privileged"], batch["obs"])
    assert features.shape[1] == PRIVILEGED_SIZE + 24
    np.testing.assert_allclose(features[:, 3:6].numpy(), batch["privileged"][:, 3:6].numpy() / 10.0, rtol=1e-6)
    np.testing.assert_allclose(features[:, PRIVILEGED_SIZE:].numpy()[:, :8], batch["obs"][:, layout.slice("robot_state")][:, :8].numpy(), rtol=1e-6)


def test_squashed_log_prob_matches_the_change_of_variables():
    mean, log_std = torch.tensor([[0.3, -1.0]]), torch.tensor([[-0.5, 0.2]])
    u = torch.tensor([[0.7, -2.5]])
    reference = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean, log_std.exp()), [torch.distributions.TanhTransform()]
    ).log_prob(torch.tanh(u)).sum(-1)
    np.testing.assert_allclose(squashed_gaussian_log_prob(u, mean, log_std).numpy(), reference.numpy(), rtol=1e-5)


def test_the_policys_spread_narrows_every_draw_and_keeps_the_entropy_terms_size():
    """SacConfig.std_scale s: the target's a', the actor loss's a~ and the rollouts draw from
    N(mean, (s std)^2); log_prob is that distribution's density plus n log s; the state loads
    across s (a later stage may change it)."""
    wide = SacLearner(SacConfig(seed=5, **SMALL))
    narrow = SacLearner(SacConfig(seed=5, std_scale=0.1, **SMALL))
    narrow.load_state_dict(wide.state_dict())
    features = wide.actor_features(wide._tensors(make_batch(wide))["obs"])
    draws = {}
    for name, scale in (("wide", 1.0), ("narrow", 0.1)):
        generator = torch.Generator().manual_seed(0)
        with torch.no_grad():
            draws[name] = wide.actor.sample(features, generator, scale)
    mean, log_std, _ = wide.actor(features)
    with torch.no_grad():
        u_wide, u_narrow = torch.atanh(draws["wide"][0].clamp(-1 + 1e-6, 1 - 1e-6)), torch.atanh(draws["narrow"][0])
        np.testing.assert_allclose((u_narrow - mean).numpy(), 0.1 * (u_wide - mean).numpy(), rtol=1e-3, atol=1e-4)
        reference = torch.distributions.TransformedDistribution(
            torch.distributions.Normal(mean, 0.1 * log_std.exp()), [torch.distributions.TanhTransform()]
        ).log_prob(draws["narrow"][0]).sum(-1) + 16 * math.log(0.1)
        np.testing.assert_allclose(draws["narrow"][1].numpy(), reference.numpy(), rtol=1e-4, atol=1e-3)
    # The Bellman target draws a' the same way.
    batch = make_batch(wide)
    narrow.generator.manual_seed(1)
    y = narrow.target(batch)
    b = narrow._tensors(batch)
    with torch.no_grad():
        a, log_prob, _, _ = narrow.actor.sample(narrow.actor_features(b["next_obs"]), torch.Generator().manual_seed(1), 0.1)
        q1, q2 = narrow.target_critic(narrow.critic_features(b["next_privileged"], b["next_obs"]), a)
    expected = soft_target(b["reward"], b["done"], q1, q2, log_prob, narrow.config.gamma, narrow.config.alpha)
    np.testing.assert_allclose(y.numpy(), expected.numpy(), rtol=1e-5, atol=1e-6)
    # The rollouts too: acting with the narrow policy is acting with the wide one at a tenth.
    obs = np.zeros((3, wide.observation_size))
    np.testing.assert_allclose(narrow.act(obs, generator=torch.Generator().manual_seed(2)),
                               wide.act(obs, generator=torch.Generator().manual_seed(2), std_scale=0.1), atol=1e-6)
    # And the actor loss: an update draws both its a' and its a~ at the narrow spread.
    scales = []
    sample = narrow.actor.sample
    narrow.actor.sample = lambda features, generator=None, std_scale=1.0: (scales.append(std_scale), sample(features, generator, std_scale))[1]
    narrow.update(batch)
    assert scales == [0.1, 0.1]
    with pytest.raises(ValueError, match="std_scale"):
        SacConfig(std_scale=0.0)


def test_auxiliary_loss_is_the_decoder_mse_against_the_privileged_ball_state():
    learner = SacLearner(SacConfig(**SMALL))
    b = learner._tensors(make_batch(learner))
    with torch.no_grad():
        _, _, embedding = learner.actor(learner.actor_features(b["obs"]))
        decoded = learner.actor.decode(embedding).numpy()
        loss = learner.auxiliary_loss(embedding, b["privileged"]).item()
    truth = b["privileged"][:, privileged_slice("ball_state")].numpy() / BALL_STATE_SCALE
    assert loss == pytest.approx(np.mean((decoded - truth) ** 2), rel=1e-5)


def test_actor_loss_entropy_term_sign_and_scale():
    """With a constant critic, L_actor = alpha mean log pi - Q + aux_weight aux: the entropy term
    is +alpha log pi (minimising it raises the entropy), linear in alpha."""
    losses = {}
    for alpha, aux_weight in ((0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (1.0, 2.0)):
        learner = SacLearner(SacConfig(alpha=alpha, aux_weight=aux_weight, **SMALL))
        with torch.no_grad():
            for net in (learner.critic.q1, learner.critic.q2):
                for p in net.parameters():
                    p.zero_()
                net[-1].bias.fill_(3.0)  # Q = 3 everywhere
        batch = make_batch(learner)
        batch["done"][:] = 1.0
        batch["reward"][:] = 3.0  # y = Q: the critic step before the actor's leaves Q = 3
        losses[(alpha, aux_weight)] = learner.update(batch)
    entropy = losses[(0.0, 0.0)]["entropy"]  # the same seed samples the same actions
    assert losses[(0.0, 0.0)]["policy_loss"] == pytest.approx(-3.0)
    for alpha in (0.5, 1.0):
        assert losses[(alpha, 0.0)]["policy_loss"] == pytest.approx(-alpha * entropy - 3.0, rel=1e-5)
    with_aux = losses[(1.0, 2.0)]
    assert with_aux["actor_loss"] == pytest.approx(with_aux["policy_loss"] + 2.0 * with_aux["aux_loss"], rel=1e-6)


def test_checkpoint_gives_identical_outputs_and_next_updates(tmp_path):
    config = SacConfig(seed=3, **SMALL)
    learner = SacLearner(config)
    batches = [make_batch(learner, seed=s) for s in range(4)]
    for batch in batches[:2]:
        learner.update(batch)
    path = tmp_path / "learner.pt"
    torch.save(learner.state_dict(), path)
    restored = SacLearner(config)
    restored.update(batches[3])  # diverge first: loading must restore everything
    restored.load_state_dict(torch.load(path, weights_only=False))
    obs = batches[0]["obs"][:4]
    np.testing.assert_array_equal(learner.act(obs, deterministic=True), restored.act(obs, deterministic=True))
    for batch in batches[2:]:
        assert learner.update(batch) == restored.update(batch)
    for a, b in zip(learner.actor.parameters(), restored.actor.parameters()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match=r"differs in \['gamma'\]"):
        SacLearner(SacConfig(gamma=0.5, bc_weight=3.0, seed=3, **SMALL)).load_state_dict(learner.state_dict())
    # The cloning term's fields and the entropy weight only weigh a loss: a later stage may change them.
    cloning = SacLearner(SacConfig(bc_weight=2.0, bc_loss="absolute", bc_hit_weight=1.0, bc_hit_window=0.2, alpha=0.0, seed=3, **SMALL))
    cloning.load_state_dict(learner.state_dict())
    np.testing.assert_array_equal(learner.act(obs, deterministic=True), cloning.act(obs, deterministic=True))


def test_the_standalone_policy_is_the_deterministic_actor(tmp_path):
    from ace_drake.systems.policy_controller import as_policy

    learner = SacLearner(SacConfig(**SMALL))
    learner.update(make_batch(learner))
    obs = make_batch(learner, seed=1)["obs"][:3]
    policy = learner.policy()
    torch.save(policy, tmp_path / "policy.pt")
    loaded = torch.load(tmp_path / "policy.pt", weights_only=False)
    expected = learner.act(obs, deterministic=True)
    np.testing.assert_allclose(as_policy(loaded)(obs[0].astype(np.float32)), expected[0], atol=1e-6)
    np.testing.assert_allclose(loaded(torch.as_tensor(obs, dtype=torch.float32)).numpy(), expected, atol=1e-6)


def test_the_averaged_actor_is_the_polyak_average_the_policy_reads_and_a_stage_may_add_it():
    rate = 0.25
    plain = SacLearner(SacConfig(seed=3, **SMALL))
    averaged = SacLearner(SacConfig(seed=3, actor_average=rate, **SMALL))
    assert plain.averaged_actor is None and plain.policy_actor is plain.actor
    before = {k: v.clone() for k, v in averaged.actor.state_dict().items()}
    batch = make_batch(averaged)
    assert plain.update(batch) == averaged.update(batch)  # the average does not change the learning
    for name, value in averaged.averaged_actor.state_dict().items():
        torch.testing.assert_close(value, (1 - rate) * before[name] + rate * averaged.actor.state_dict()[name])
        assert not torch.equal(value, averaged.actor.state_dict()[name])
    obs = torch.as_tensor(make_batch(averaged, seed=1)["obs"][:3], dtype=torch.float32)
    expected = torch.tanh(averaged.averaged_actor(averaged.actor_features(obs))[0])
    torch.testing.assert_close(averaged.policy()(obs), expected)  # evaluated and exported: the average
    torch.testing.assert_close(averaged.policy(averaged.actor.state_dict())(obs), plain.policy()(obs))  # given weights
    # Checkpointed with it; a later stage may add it to a learner without one (it starts at the actor).
    restored = SacLearner(SacConfig(seed=3, actor_average=rate, **SMALL))
    restored.load_state_dict(averaged.state_dict())
    torch.testing.assert_close(restored.policy()(obs), averaged.policy()(obs))
    added = SacLearner(SacConfig(seed=3, actor_average=0.01, **SMALL))
    added.load_state_dict(plain.state_dict())
    torch.testing.assert_close(added.policy()(obs), plain.policy()(obs))
    with pytest.raises(ValueError, match="actor_average"):
        SacConfig(actor_average=1.5)


def test_the_monte_carlo_bound_is_the_max_of_the_bellman_target_and_the_return():
    plain = SacLearner(SacConfig(gamma=0.95, **SMALL))
    bounded = SacLearner(SacConfig(gamma=0.95, mc_bound=True, **SMALL))
    batch = make_batch(plain)
    y = plain.target(batch).numpy()
    mc_return = y + np.where(np.arange(len(y)) % 2 == 0, 0.5, -0.5)  # every other row above y
    mc_return[1] = -np.inf  # a row with no return stored: no bound
    np.testing.assert_allclose(bounded.target({**batch, "mc_return": mc_return}).numpy(), np.maximum(y, mc_return), rtol=1e-6)
    assert bounded.update({**batch, "mc_return": mc_return})["mc_bound_share"] == pytest.approx(0.5)
    # G = y (the same networks and draws: fresh learners of one seed) raises nothing, terminal rows included.
    tied, y_fresh = SacLearner(SacConfig(gamma=0.95, mc_bound=True, **SMALL)), SacLearner(SacConfig(gamma=0.95, **SMALL)).target(batch)
    assert tied.update({**batch, "mc_return": y_fresh.numpy()})["mc_bound_share"] == 0.0
    with pytest.raises(KeyError, match="mc_return"):
        bounded.update(batch)
    assert "mc_bound_share" not in plain.update({**batch, "mc_return": mc_return})  # the plain learner ignores it


def test_the_mixed_monte_carlo_target_blends_the_bellman_target_and_the_return():
    plain = SacLearner(SacConfig(gamma=0.95, **SMALL))
    mixed = SacLearner(SacConfig(gamma=0.95, mc_mix=0.25, **SMALL))
    batch = make_batch(plain)
    y = plain.target(batch).numpy()
    mc_return = np.linspace(-1.0, 2.0, len(y))
    mc_return[3] = -np.inf  # no return stored: the Bellman target alone
    expected = 0.75 * y + 0.25 * mc_return
    expected[3] = y[3]
    np.testing.assert_allclose(mixed.target({**batch, "mc_return": mc_return}).numpy(), expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(KeyError, match="mc_return"):
        mixed.update(batch)
    with pytest.raises(ValueError, match="mc_mix"):
        SacConfig(mc_mix=1.5)


def test_the_monte_carlo_bound_lifts_the_critic_to_the_returns_and_a_stage_may_switch_it():
    plain = SacLearner(SacConfig(critic_lr=1e-3, **SMALL))
    batch = make_batch(plain, size=64)
    batch["mc_return"] = np.full(64, 3.0)  # better continuations than the policy's
    bounded = SacLearner(SacConfig(critic_lr=1e-3, mc_bound=True, **SMALL))
    bounded.load_state_dict(plain.state_dict())  # a stage field: the same networks
    for _ in range(150):
        plain_losses, bounded_losses = plain.update(batch), bounded.update(batch)
    assert bounded_losses["q_mean"] > 2.5 > plain_losses["q_mean"] + 1.0


def test_same_seed_same_learner():
    a, b = SacLearner(SacConfig(seed=5, **SMALL)), SacLearner(SacConfig(seed=5, **SMALL))
    batch = make_batch(a)
    assert a.update(batch) == b.update(batch)


def test_a_short_run_on_a_fixed_batch_decreases_the_critic_loss():
    learner = SacLearner(SacConfig(critic_lr=1e-3, actor_lr=1e-3, **SMALL))
    batch = make_batch(learner, size=64)
    first = np.mean([learner.update(batch)["critic_loss"] for _ in range(5)])
    for _ in range(100):
        losses = learner.update(batch)
    last = np.mean([learner.update(batch)["critic_loss"] for _ in range(5)])
    assert last < 0.2 * first
    assert math.isfinite(losses["actor_loss"])


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="gamma"):
        SacConfig(gamma=1.0)
    with pytest.raises(ValueError, match="tau"):
        SacConfig(tau=0.0)


# What each kept policy needs from its diagram, as its sidecar's recorded config gives it
# (sac.meet_ball, sac.hit_memory before PlayOptions existed).
KEPT_POLICY_PLAY = {"rally_hit_state_braking": (True, True), "rally_skill": (True, True)}


@pytest.mark.parametrize("name", sorted(KEPT_POLICY_PLAY))
def test_each_kept_policy_loads_with_the_play_options_it_was_trained_with(name):
    import json

    from ace_drake.config import MODELS_DIR
    from ace_drake.learning.sac import PlayOptions, load_policy

    path = MODELS_DIR / "policies" / f"{name}.pt"
    payload = torch.load(path, weights_only=False)
    assert "play" not in payload  # written before PlayOptions: its SacConfig holds them, read from there
    policy = load_policy(path)
    meet_ball, hit_memory = KEPT_POLICY_PLAY[name]
    assert (policy.meet_ball, policy.hit_memory) == (meet_ball, hit_memory)
    recorded = json.loads((MODELS_DIR / "policies" / f"{name}.json").read_text())["config"]["sac"]
    assert (recorded.get("meet_ball", False), recorded.get("hit_memory", False)) == (meet_ball, hit_memory)
    assert not {"meet_ball", "hit_memory"} & {f.name for f in dataclasses.fields(SacConfig)}  # not the learner's
    assert dataclasses.fields(PlayOptions)


def test_a_policy_artefact_stores_its_play_options_beside_the_learners_config(tmp_path):
    from ace_drake.learning.sac import PlayOptions, load_policy, save_policy

    config = SacConfig(batch_size=16, actor_hidden=(32, 32), embedding_size=32, decoder_hidden=(16,), critic_hidden=(32, 32))
    save_policy(tmp_path / "p.pt", SacLearner(config, play=PlayOptions(meet_ball=True)))
    payload = torch.load(tmp_path / "p.pt", weights_only=False)
    assert payload["play"] == {"meet_ball": True, "hit_memory": False} and "meet_ball" not in payload["sac_config"]
    policy = load_policy(tmp_path / "p.pt")
    assert policy.meet_ball and not policy.hit_memory


def test_the_absolute_cloning_loss_sums_the_absolute_errors():
    """bc_loss "absolute": the batch mean of sum_k |tanh(mu_k) - a_k| (the labels' median is its
    minimiser), with the rows' weights as the squared loss has them."""
    learner = SacLearner(SacConfig(**SMALL, bc_weight=1.0, bc_loss="absolute", seed=3))
    rng = np.random.default_rng(2)
    obs = rng.normal(size=(5, learner.observation_size))
    demos = {"obs": obs, "demo_action": rng.uniform(-1, 1, (5, 16))}
    with torch.no_grad():
        mean, _, _ = learner.actor(learner.actor_features(torch.as_tensor(obs, dtype=torch.float32)))
        error = np.abs(np.tanh(mean.numpy()) - demos["demo_action"]).sum(-1)
        assert learner.behaviour_cloning_loss(demos).item() == pytest.approx(error.mean(), rel=1e-5)
    # a label moved 1 further from the actor's output in one component: the loss grows by 1/5, the
    # squared loss would grow by (2 |error| + 1)/5
    moved = {**demos, "demo_action": demos["demo_action"].copy()}
    moved["demo_action"][0, 0] += np.sign(demos["demo_action"][0, 0] - np.tanh(mean[0, 0].item()))
    with torch.no_grad():
        assert learner.behaviour_cloning_loss(moved).item() == pytest.approx(error.mean() + 0.2, rel=1e-5)
    with pytest.raises(ValueError, match="bc_loss"):
        SacConfig(bc_loss="huber")
    with pytest.raises(ValueError, match="hit_state"):
        SacConfig(bc_loss="absolute", action="hit_state", actor_observation_parts=("robot_state", "hit_prediction"))


def test_the_cloning_term_weights_the_rows_near_the_predicted_hit():
    learner = SacLearner(SacConfig(**SMALL, bc_weight=1.0, bc_hit_weight=4.0, bc_hit_window=0.1, seed=3))
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(4, learner.observation_size))
    prediction = learner.config.layout.slice("hit_prediction")
    # [valid, time to the hit]: near and valid, far, near but invalid, exactly at the window
    obs[:, prediction.start : prediction.start + 2] = [[1.0, 0.05], [1.0, 0.3], [0.0, 0.05], [1.0, 0.1]]
    demos = {"obs": obs, "demo_action": rng.uniform(-1, 1, (4, 16))}
    with torch.no_grad():
        mean, _, _ = learner.actor(learner.actor_features(torch.as_tensor(obs, dtype=torch.float32)))
        error = ((torch.tanh(mean) - torch.as_tensor(demos["demo_action"], dtype=torch.float32)) ** 2).sum(-1).numpy()
        loss = learner.behaviour_cloning_loss(demos).item()
    weights = np.array([5.0, 1.0, 1.0, 5.0])
    assert loss == pytest.approx(np.sum(weights * error) / weights.sum(), rel=1e-5)
    plain = SacLearner(SacConfig(**SMALL, bc_weight=1.0, seed=3))
    with torch.no_grad():
        assert plain.behaviour_cloning_loss(demos).item() == pytest.approx(error.mean(), rel=1e-5)
    # a wider window takes in the row 0.3 s from the hit; a batch of near rows alone is their mean
    wide = SacLearner(SacConfig(**SMALL, bc_weight=1.0, bc_hit_weight=4.0, bc_hit_window=0.3, seed=3))
    wide.actor.load_state_dict(learner.actor.state_dict())
    with torch.no_grad():
        wide_weights = np.array([5.0, 5.0, 1.0, 5.0])
        assert wide.behaviour_cloning_loss(demos).item() == pytest.approx(np.sum(wide_weights * error) / wide_weights.sum(), rel=1e-5)
        near = {key: value[[0, 3]] for key, value in demos.items()}
        assert learner.behaviour_cloning_loss(near).item() == pytest.approx(error[[0, 3]].mean(), rel=1e-5)
    with pytest.raises(ValueError, match="bc_hit_weight"):  # leaving the stroke's rows out was a study (module docstring)
        SacConfig(bc_hit_weight=-1.0)
    with pytest.raises(ValueError, match="hit_state"):
        SacConfig(bc_hit_weight=1.0, action="hit_state", actor_observation_parts=("robot_state", "hit_prediction"))


def test_an_update_on_an_overflowing_batch_raises_before_the_weights_turn_nan():
    """One observation of 1e24 (a diverged estimate once reached a run's tables) overflows the
    actor's loss: the update raises before its step, instead of turning every weight into NaN."""
    learner = SacLearner(SacConfig(**SMALL))
    before = {name: value.clone() for name, value in learner.state_dict()["actor"].items()}
    critic = {name: value.clone() for name, value in learner.state_dict()["critic"].items()}
    batch = make_batch(learner)
    batch["obs"][3, 5] = 1e24
    with pytest.raises(FloatingPointError, match="actor loss is (inf|nan).*actor did not step; the critic had already stepped"):
        learner.update(batch)
    assert all(torch.equal(value, learner.state_dict()["actor"][name]) for name, value in before.items())
    # (the critic, which does not read that part of the observation, took its step on a finite loss)
    assert all(torch.isfinite(value).all() for value in learner.state_dict()["critic"].values())
    assert any(not torch.equal(value, learner.state_dict()["critic"][name]) for name, value in critic.items())
    assert learner.updates == 0 and np.isfinite(list(learner.update(make_batch(learner)).values())).all()
