"""Event tables (events, batch proportions, ring buffers) and hindsight relabelling."""

import math

import numpy as np
import pytest

from ace_drake.contracts import EpisodeResult, ObservationLayout, Outcome, privileged_slice
from ace_drake.learning.params import RewardParams
from ace_drake.learning.replay import (
    EVENTS,
    EpisodeSummary,
    EventReplay,
    ReplayConfig,
    RingBuffer,
    discounted_returns,
    episode_events,
    relabel_episode,
)
from ace_drake.physics.flight import make_state
from ace_drake.physics.propagate import ContactEvent, ContactKind

LAYOUT = ObservationLayout(2, 2)
PARAMS = RewardParams(return_base=1.0, position_reward=2.0, position_length=0.3, spin_gain=0.01)


def event(kind, time, pre, post=None):
    return ContactEvent(kind, time, np.asarray(pre, float), np.asarray(pre if post is None else post, float))


BOUNCE = event(ContactKind.TABLE, 0.45, make_state((-0.8, 0.0, 0.02), (-5.0, 0.0, -2.0), (0, 0, 0)))


def hit(speed):
    return event(ContactKind.RACKET, 0.6, make_state((-1.8, 0, 0.25), (-4, 0, 1)), make_state((-1.8, 0, 0.25), (speed, 0, 1.0)))


def landing(y=0.4, topspin=0.0):
    # Flying +x: spin about +y is topspin.
    return event(ContactKind.TABLE, 1.0, make_state((0.9, y, 0.02), (5.0, 0.0, -2.0), (0.0, topspin, 0.0)))


def episode(steps=3, skill=(-0.3, 0.2, -1.0), seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(steps + 1, LAYOUT.size)).astype(np.float32)
    privileged = rng.normal(size=(steps + 1, 28)).astype(np.float32)
    obs[:, LAYOUT.slice("skill")] = skill
    privileged[:, privileged_slice("skill")] = skill
    reward = np.zeros(steps, np.float32)
    reward[-1] = 0.7
    done = np.zeros(steps, np.float32)
    done[-1] = 1.0
    return {"obs": obs[:-1], "privileged": privileged[:-1], "action": rng.uniform(-1, 1, (steps, 16)),
            "reward": reward, "next_obs": obs[1:], "next_privileged": privileged[1:], "done": done}


def summary(outcome, hit_speed=None, land=None, closest=None):
    result = EpisodeResult(outcome, "", BOUNCE, None if hit_speed is None else hit(hit_speed), land)
    return EpisodeSummary(result, closest)


def test_episode_events():
    assert episode_events(summary(Outcome.MISSED, closest=0.5)) == ("all", "miss")
    assert episode_events(summary(Outcome.MISSED, closest=0.1)) == ("all", "miss", "near_miss")
    assert episode_events(summary(Outcome.MISSED)) == ("all", "miss")  # closest approach unknown
    assert episode_events(summary(Outcome.INVALID)) == ("all",)
    assert episode_events(summary(Outcome.NOT_RETURNED, 6.0)) == ("all", "hit")
    assert episode_events(summary(Outcome.RETURNED, 6.0, landing())) == ("all", "hit", "return")
    assert episode_events(summary(Outcome.RETURNED, 12.0, landing(topspin=300.0))) == (
        "all", "hit", "return", "high_speed_return", "high_topspin_return")
    assert episode_events(summary(Outcome.RETURNED, 6.0, landing(topspin=-200.0))) == ("all", "hit", "return", "high_backspin_return")


def test_relabelling_sets_the_achieved_landing_and_the_maximum_position_reward():
    transitions = episode(skill=(-0.3, 0.2, -1.0))
    land = landing(y=0.4, topspin=100.0).state_pre
    relabelled = relabel_episode(transitions, land, LAYOUT, PARAMS)
    for key in ("obs", "next_obs"):
        np.testing.assert_allclose(relabelled[key][:, LAYOUT.slice("skill")], np.tile([0.4, 1.0, -1.0], (3, 1)), rtol=1e-6)
    for key in ("privileged", "next_privileged"):
        np.testing.assert_allclose(relabelled[key][:, privileged_slice("skill")], np.tile([0.4, 1.0, -1.0], (3, 1)), rtol=1e-6)
    # Terminal reward: base + w_p * max position reward + w_s * spin_gain * omega_y, by hand.
    assert relabelled["reward"][-1] == pytest.approx(1.0 + 1.0 * 2.0 - 1.0 * 0.01 * 100.0)
    np.testing.assert_array_equal(relabelled["reward"][:-1], 0.0)
    # Everything else is untouched, and so is the original.
    for key in ("action", "done"):
        np.testing.assert_allclose(relabelled[key], transitions[key], rtol=1e-6)
    other = np.ones(LAYOUT.size, bool)
    other[LAYOUT.slice("skill")] = False
    np.testing.assert_array_equal(relabelled["obs"][:, other], transitions["obs"][:, other])
    assert transitions["obs"][0, LAYOUT.slice("skill")][0] == pytest.approx(-0.3)


def test_add_episode_stores_returns_twice_in_their_tables():
    replay = EventReplay(ReplayConfig(), LAYOUT, PARAMS)
    replay.add_episode(episode(), summary(Outcome.RETURNED, 6.0, landing()))
    replay.add_episode(episode(seed=1), summary(Outcome.MISSED, closest=0.1))
    sizes = {name: table.size for name, table in replay.tables.items()}
    assert sizes == {"all": 9, "miss": 3, "near_miss": 3, "hit": 6, "return": 6,
                     "high_speed_return": 0, "high_topspin_return": 0, "high_backspin_return": 0}
    # An augmentation is applied to the episode and its hindsight copy.
    flipped = EventReplay(ReplayConfig(), LAYOUT, PARAMS, augment=[lambda t: {**t, "action": -t["action"]}])
    flipped.add_episode(episode(), summary(Outcome.RETURNED, 6.0, landing()))
    assert flipped.tables["return"].size == 12


def test_discounted_returns_by_hand():
    np.testing.assert_allclose(discounted_returns([0.0, 0.0, 2.0], 0.5), [0.5, 1.0, 2.0])
    np.testing.assert_allclose(discounted_returns([1.0, -1.0, 4.0], 0.5), [1.0 - 0.5 + 1.0, -1.0 + 2.0, 4.0])


def test_each_stored_copy_carries_its_own_monte_carlo_returns():
    replay = EventReplay(ReplayConfig(), LAYOUT, PARAMS, gamma=0.9)
    replay.add_episode(episode(steps=4), summary(Outcome.RETURNED, 6.0, landing(y=0.1)))
    rows = replay.tables["all"].get(replay.tables["all"].oldest_first())
    original, relabelled = slice(0, 4), slice(4, 8)
    powers = 0.9 ** np.arange(3, -1, -1)
    np.testing.assert_allclose(rows["mc_return"][original], 0.7 * powers, rtol=1e-6)
    # The hindsight copy's terminal reward is recomputed, and its returns with it.
    relabelled_reward = rows["reward"][relabelled][-1]
    assert relabelled_reward != pytest.approx(0.7)
    np.testing.assert_allclose(rows["mc_return"][relabelled], relabelled_reward * powers, rtol=1e-6)
    assert "mc_return" in replay.sample(5)
    with pytest.raises(ValueError, match="gamma"):
        EventReplay(gamma=1.0)


def test_tables_written_before_the_monte_carlo_returns_load_with_no_bound():
    replay = EventReplay(ReplayConfig(), LAYOUT, PARAMS)
    replay.add_episode(episode(), summary(Outcome.MISSED))
    state = replay.state_dict()
    for table in state["tables"].values():  # as a checkpoint of before the column
        if table["data"] is not None:
            del table["data"]["mc_return"]
    for capacities in ({}, {"all": 2}):  # as it lay, and into a table of another capacity (a later stage's)
        restored = EventReplay(ReplayConfig(table_capacities=capacities), LAYOUT, PARAMS)
        restored.load_state_dict(state)
        assert np.all(restored.sample(6)["mc_return"] == -np.inf)
        kept = restored.tables["all"].size
        np.testing.assert_array_equal(restored.tables["all"].get(restored.tables["all"].oldest_first())["obs"],
                                      replay.tables["all"].get(np.arange(3))["obs"][-kept:])
        restored.add_episode(episode(seed=4), summary(Outcome.MISSED))  # new rows carry their returns beside the old
        table = restored.tables["all"]
        assert np.isfinite(table.get(table.oldest_first())["mc_return"][-3:]).all()
    with pytest.raises(KeyError, match="lacks the column"):  # any other missing column is an error
        RingBuffer(4).load_state_dict({"capacity": 4, "size": 1, "next": 1, "data": {"obs": np.zeros((1, 2))}})


def test_demonstrations_are_stored_with_their_augmentations():
    """Labelled rows only, each with its mirror (obs, privileged and the label mirrored)."""
    from ace_drake.learning.mirror import Mirror
    from ace_drake.learning.replay import DemonstrationBuffer

    rows = episode(steps=4)
    rows["demo_action"] = np.random.default_rng(2).uniform(-1, 1, (4, 16))
    rows["demo_action"][1] = np.nan  # no label
    mirror = Mirror.from_robot(layout=LAYOUT)
    buffer = DemonstrationBuffer(100, augment=[mirror.transitions])
    buffer.add(rows)
    assert len(buffer) == 6
    stored = buffer.buffer.get(np.arange(6))
    labelled = [0, 2, 3]
    np.testing.assert_allclose(stored["demo_action"][:3], rows["demo_action"][labelled], rtol=0, atol=1e-6)
    np.testing.assert_allclose(stored["demo_action"][3:], mirror.action(rows["demo_action"][labelled]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(stored["obs"][3:], mirror.observation(rows["obs"][labelled]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(stored["privileged"][3:], mirror.privileged(rows["privileged"][labelled]), rtol=0, atol=1e-6)


def test_batch_proportions_follow_the_weights_over_non_empty_tables():
    weights = {"all": 0.5, "miss": 0.2, "hit": 0.2, "high_speed_return": 0.1}
    replay = EventReplay(ReplayConfig(table_weights=weights, relabel=False, seed=4), LAYOUT, PARAMS)
    replay.add_episode(episode(), summary(Outcome.MISSED, closest=1.0))
    replay.add_episode(episode(seed=2), summary(Outcome.NOT_RETURNED, 6.0))
    # high_speed_return is empty: its share goes to the others, in proportion.
    expected = {"all": 0.5 / 0.9, "miss": 0.2 / 0.9, "hit": 0.2 / 0.9}
    draws = 20_000
    batch = replay.sample(draws)
    assert len(batch["reward"]) == draws
    for name, p in expected.items():
        count = np.sum(batch["table"] == EVENTS.index(name))
        assert abs(count - draws * p) < 4.0 * math.sqrt(draws * p * (1 - p)), name
    assert np.sum(batch["table"] == EVENTS.index("high_speed_return")) == 0
    # Rows from the miss table are the missed episode's transitions.
    miss_rows = batch["obs"][batch["table"] == EVENTS.index("miss")]
    assert np.all(np.isin(miss_rows[:, 0], episode()["obs"][:, 0]))


def test_ring_buffer_overwrites_the_oldest():
    buffer = RingBuffer(4)
    for start in (0, 3):
        t = episode(steps=3)
        t["reward"] = np.arange(start, start + 3, dtype=np.float32)
        buffer.add(t)
    assert buffer.size == 4
    assert sorted(buffer.get(np.arange(4))["reward"]) == [2.0, 3.0, 4.0, 5.0]
    big = episode(steps=6)
    big["reward"] = np.arange(6, dtype=np.float32)
    buffer.add(big)
    assert sorted(buffer.get(np.arange(4))["reward"]) == [2.0, 3.0, 4.0, 5.0]


def test_a_ring_buffer_loads_into_another_capacity_oldest_first():
    """A later training stage may give a table another capacity: the rows keep their order (the
    newest that fit), and the next row goes after them."""
    buffer = RingBuffer(4)
    for start in (0, 3):  # rows 0-5 into 4: 2, 3, 4, 5 remain, wrapped
        t = episode(steps=3)
        t["reward"] = np.arange(start, start + 3, dtype=np.float32)
        buffer.add(t)
    state = buffer.state_dict()
    for capacity, kept in ((8, [2.0, 3.0, 4.0, 5.0]), (2, [4.0, 5.0]), (4, [2.0, 3.0, 4.0, 5.0])):
        dut = RingBuffer(capacity)
        dut.load_state_dict(state)
        assert dut.size == len(kept) and dut.get(dut.oldest_first())["reward"].tolist() == kept
        t = episode(steps=1)
        t["reward"] = np.array([6.0], np.float32)
        dut.add(t)
        assert dut.get(dut.oldest_first())["reward"].tolist() == (kept + [6.0])[-capacity:]
    partial = RingBuffer(4)  # not full: rows 0-2
    t = episode(steps=3)
    t["reward"] = np.arange(3, dtype=np.float32)
    partial.add(t)
    for capacity, kept in ((8, [0.0, 1.0, 2.0]), (2, [1.0, 2.0])):
        dut = RingBuffer(capacity)
        dut.load_state_dict(partial.state_dict())
        assert dut.get(dut.oldest_first())["reward"].tolist() == kept
    same = RingBuffer(4)  # at the same capacity, the layout as it lay
    same.load_state_dict(state)
    assert (same._next, same.get(np.arange(4))["reward"].tolist()) == (buffer._next, buffer.get(np.arange(4))["reward"].tolist())
    empty = RingBuffer(8)
    empty.load_state_dict(RingBuffer(4).state_dict())
    assert empty.size == 0


def test_state_dict_restores_tables_and_sampling(tmp_path):
    import pickle

    config = ReplayConfig(table_capacities={"all": 5}, seed=1)
    replay = EventReplay(config, LAYOUT, PARAMS)
    for seed in range(3):
        replay.add_episode(episode(seed=seed), summary(Outcome.RETURNED, 12.0, landing()))
    replay.sample(7)
    (tmp_path / "replay.pkl").write_bytes(pickle.dumps(replay.state_dict()))
    restored = EventReplay(config, LAYOUT, PARAMS)
    restored.load_state_dict(pickle.loads((tmp_path / "replay.pkl").read_bytes()))
    for _ in range(2):
        a, b = replay.sample(9), restored.sample(9)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    replay.add_episode(episode(seed=9), summary(Outcome.MISSED))
    restored.add_episode(episode(seed=9), summary(Outcome.MISSED))
    np.testing.assert_array_equal(replay.sample(9)["obs"], restored.sample(9)["obs"])


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="table_weights"):
        ReplayConfig(table_weights={"bogus": 1.0})
    with pytest.raises(ValueError, match="empty"):
        EventReplay(ReplayConfig(), LAYOUT).sample(4)


def test_a_real_episode_through_the_replay_and_the_learner():
    """The environment/learner interface on the real diagram: an episode of RallyEnv acted by the
    learner's actor, stored (with its mirror and hindsight copies), sampled and learned from."""
    import torch

    from ace_drake.learning.mirror import Mirror
    from ace_drake.learning.sac import SacConfig, SacLearner
    from ace_drake.training.env import RallyEnv

    env = RallyEnv()
    learner = SacLearner(SacConfig(actor_hidden=(32,), embedding_size=32, decoder_hidden=(32,), critic_hidden=(32,)))
    mirror = Mirror.from_robot(layout=env.layout)
    replay = EventReplay(ReplayConfig(), env.layout, env.params.reward, augment=[mirror.transitions])
    shot = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))
    obs, info = env.reset(seed=0, options={"shot": shot, "skill": (0.3, 1.0, 0.5), "start": "static"})
    rows = []
    generator = torch.Generator().manual_seed(0)
    for _ in range(80):
        action = learner.act(obs, generator=generator)
        next_obs, reward, terminated, truncated, next_info = env.step(action)
        rows.append((obs, info["privileged"], action, reward, next_obs, next_info["privileged"], float(terminated)))
        obs, info = next_obs, next_info
        if terminated:
            break
    assert terminated
    transitions = {key: np.array(column, dtype=np.float32) for key, column in zip(
        ("obs", "privileged", "action", "reward", "next_obs", "next_privileged", "done"), zip(*rows))}
    events = replay.add_episode(transitions, EpisodeSummary(env.result))
    copies = 4 if env.result.outcome is Outcome.RETURNED else 2  # (+ hindsight) x (+ mirror)
    assert len(replay) == copies * len(rows)
    assert "all" in events
    losses = learner.update(replay.sample(32))
    assert all(np.isfinite(value) for value in losses.values())
