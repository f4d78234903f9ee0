"""RallyEnv: gymnasium's checker, seeding, the four end conditions on constructed episodes, and
the initial-state sampling."""

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from ace_drake.config import ConfigError
from ace_drake.contracts import PRIVILEGED_PARTS, Outcome, privileged_slice
from ace_drake.learning.params import RewardParams
from ace_drake.learning.rewards import return_reward
from ace_drake.physics.flight import make_state
from ace_drake.play.shots import ShotDistribution
from ace_drake.training.env import RallyEnv, RallyEnvParams, SkillSampling

# Bounces on the robot's half 0.64 m behind the net and flies on past the robot's end, wide of
# the racket in the ready pose (blade centre at (-1.84, 0, 0.25), facing +x).
PASSING_SHOT = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))
# Bounces at x = -0.93 and crosses x = -1.79 at (y, z) = (0, 0.25): into the blade of a racket
# held still in the ready pose (found with physics.propagate.simulate and scipy's fsolve).
HIT_SHOT = make_state((1.6, 0.2, 0.25), (-6.0, -0.354, 2.164), (0.0, 0.0, 0.0))
SKILL = (0.3, 1.0, 0.5)
# A distinct collision reward, so that the tests can tell a collision's end from a miss.
REWARD = RewardParams(collision=-2.0)


@pytest.fixture(scope="module")
def env():
    """One environment for the module (one diagram, one Simulator), drawing returns near
    PASSING_SHOT, four at a time."""
    rng = np.random.default_rng(0)
    returns = PASSING_SHOT + rng.normal(0.0, 1.0, (20, 9)) * np.r_[[0.02] * 3, [0.1] * 3, [5.0] * 3]
    distribution = ShotDistribution(np.empty((0, 9)), returns, serve_fraction=0.0)
    return RallyEnv(RallyEnvParams(reward=REWARD, shot_batch=4), distribution=distribution)


def hold_still(env, observation):
    """The action that keeps the joints where the next segment starts (ControlStack.action_towards)."""
    q, v, a = np.split(env.layout.part(observation, "robot_state").astype(float), 3)
    return env.stack.action_towards(q, v, a, q)


def run(env, choose, limit=80):
    """Runs the episode from the last reset with actions choose(env, observation); returns the
    rewards, the last info and the number of steps."""
    observation = env._observation()
    rewards = []
    for steps in range(1, limit + 1):
        observation, reward, terminated, truncated, info = env.step(choose(env, observation))
        rewards.append(reward)
        assert not truncated
        if terminated:
            return rewards, info, steps
    raise AssertionError("the episode did not end")


def test_gymnasium_checker_passes(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    # The checker reports problems as warnings too. The observation is unbounded (sensor noise,
    # estimator transients), which it remarks on; anything else is a problem.
    problems = [str(w.message) for w in caught if "infinity" not in str(w.message)]
    assert not problems


def test_same_seed_same_episode_bit_for_bit(env):
    def rollout(seed):
        observation, info = env.reset(seed=seed)
        rng = np.random.default_rng(1)
        observations, privileged = [observation], [info["privileged"]]
        for _ in range(3):
            observation, _, terminated, _, info = env.step(rng.uniform(-0.2, 0.2, 16))
            observations.append(observation)
            privileged.append(info["privileged"])
            if terminated:
                break
        return np.array(observations), np.array(privileged), info["skill"]

    first, second, other = rollout(11), rollout(11), rollout(12)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[1][0], other[1][0])  # another shot, skill and start


def test_the_first_observation_is_27_ms_in_and_steps_are_32_ms(env):
    observation, info = env.reset(seed=0, options={"shot": PASSING_SHOT, "skill": SKILL, "start": "static"})
    assert info["time"] == pytest.approx(0.027) and info["end"] == "" and info["start"] == "static"
    np.testing.assert_array_equal(env.layout.part(observation, "skill"), np.float32(SKILL))
    assert info["privileged"].shape == (sum(PRIVILEGED_PARTS.values()),)
    np.testing.assert_array_equal(info["privileged"][privileged_slice("skill")], np.float32(SKILL))
    _, _, _, _, info = env.step(hold_still(env, observation))
    assert info["time"] == pytest.approx(0.059)


def test_holding_still_misses_a_ball_that_passes_the_racket(env):
    reset_pose = env.stack.reset_pose
    env.reset(seed=1, options={"shot": PASSING_SHOT, "skill": SKILL, "q": reset_pose})
    rewards, info, steps = run(env, hold_still)
    assert info["end"] == "passed" and info["outcome"] == Outcome.MISSED.value
    assert env.result.bounce is not None and env.result.hit is None
    assert rewards[-1] == REWARD.miss and all(r == 0.0 for r in rewards[:-1])
    # Ended soon after the ball went behind the blade, long before it reached the floor.
    ball = info["privileged"][privileged_slice("ball_state")]
    assert ball[0] < -1.9 and ball[2] > -0.5 and info["time"] < 1.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(16))


def test_driving_the_racket_into_the_table_ends_by_the_collision_condition(env):
    reset_pose = env.stack.reset_pose
    into_table = reset_pose.copy()
    into_table[0] = 0.75  # gantry_x forward: the forearm goes through the table's top
    into_table[3] += 0.6  # shoulder pitched down

    def drive(env, observation):
        q, v, a = np.split(env.layout.part(observation, "robot_state").astype(float), 3)
        return env.stack.action_towards(q, v, a, into_table)

    env.reset(seed=2, options={"shot": PASSING_SHOT, "skill": SKILL, "q": reset_pose})
    rewards, info, steps = run(env, drive)
    assert info["end"] == "collision" and info["outcome"] == Outcome.MISSED.value
    assert rewards[-1] == REWARD.collision
    accepted, refused = info["segments"]
    assert accepted >= 1 and refused == 1  # it moved, then its next plan was refused
    assert env._supervisor_state().last_reason.startswith("collision predicted")


def test_a_ball_into_the_still_racket_ends_with_the_hit_and_its_outcome(env):
    env.reset(seed=3, options={"shot": HIT_SHOT, "skill": SKILL, "q": env.stack.reset_pose})
    rewards, info, steps = run(env, hold_still)
    result = env.result
    assert info["end"] == "hit" and result.hit is not None and result.bounce is not None
    # Simulated on past the hit until the return was decided (it needs the landing).
    assert result.outcome in (Outcome.RETURNED, Outcome.NOT_RETURNED) and info["time"] > result.hit.time
    if result.outcome is Outcome.RETURNED:
        assert rewards[-1] == pytest.approx(return_reward(result.landing.state_pre, SKILL, REWARD))
    else:
        assert rewards[-1] == REWARD.hit


def test_a_dynamic_start_moves_along_its_reset_plan(env):
    _, info = env.reset(seed=4, options={"shot": PASSING_SHOT, "skill": SKILL, "start": "dynamic"})
    assert info["start"] == "dynamic"
    joint_velocity = info["privileged"][privileged_slice("joint_state")][8:]
    assert np.any(np.abs(joint_velocity) > 1e-3)


def test_static_starts_keep_the_arm_and_draw_the_gantry(env):
    poses = []
    for seed in range(3):
        env.reset(seed=seed, options={"shot": PASSING_SHOT, "start": "static"})
        poses.append(env._joints.q_port.Eval(env._joints.GetMyContextFromRoot(env.context)).copy())
    poses = np.array(poses)
    np.testing.assert_allclose(poses[:, 2:], np.tile(env.stack.reset_pose[2:], (3, 1)), atol=1e-9)
    assert np.ptp(poses[:, 0]) > 0.0 and np.ptp(poses[:, 1]) > 0.0


def test_skill_sampling_is_biased_to_sparse_and_boundary_weights():
    sampling = SkillSampling()
    skills = np.array([sampling.sample(np.random.default_rng(seed), 1.525) for seed in range(4000)])
    assert np.all(np.abs(skills[:, 0]) <= 0.7625)
    assert np.all((0.0 <= skills[:, 1]) & (skills[:, 1] <= 1.0)) and np.all(np.abs(skills[:, 2]) <= 1.0)
    np.testing.assert_allclose([np.mean(skills[:, 1] == 0.0), np.mean(skills[:, 1] == 1.0)], [0.25, 0.25], atol=0.03)
    np.testing.assert_allclose([np.mean(skills[:, 2] == v) for v in (0.0, -1.0, 1.0)], [0.3, 0.15, 0.15], atol=0.03)
    with pytest.raises(ConfigError, match="w_p_zero"):
        SkillSampling(w_p_zero=0.8, w_p_one=0.5)
