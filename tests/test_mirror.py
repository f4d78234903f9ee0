"""Mirror across the XZ plane: involution, the joint mirror by forward kinematics, actions through
the feasible sets, and the shipped robot's asymmetry."""

import shutil

import numpy as np
import pytest

from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import map_action
from ace_drake.control.feasible_set import feasible_sets, in_invariant_set
from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.learning.mirror import JointMirror, Mirror
from ace_drake.robot.model import RobotModel, load_scenario

LAYOUT = ObservationLayout(3, 2)
# gantry_x, gantry_y, shoulder_yaw, shoulder_pitch, elbow, wrist_1, wrist_2, wrist_3
EXPECTED_SIGNS = [1, -1, -1, 1, 1, -1, 1, -1]


@pytest.fixture(scope="module")
def shipped():
    return RobotModel()


@pytest.fixture(scope="module")
def symmetric(tmp_path_factory):
    """The shipped robot with its arm moved onto the column's plane (the SDF's 0.15 m side offset
    of the arm removed): the smallest change that makes it mirror-symmetric."""
    directory = tmp_path_factory.mktemp("models")
    shutil.copy(MODELS_DIR / "table.sdf", directory / "table.sdf")
    text = (MODELS_DIR / "ace_robot.sdf").read_text()
    assert text.count(" 0.15 1.11 ") == 5
    (directory / "ace_robot.sdf").write_text(text.replace(" 0.15 1.11 ", " 0 1.11 "))
    model = RobotModel(load_scenario(), directory)
    model.models_dir = directory
    return model


def symmetric_sdf(model) -> str:
    """The path of the symmetric variant's robot SDF (``symmetric`` fixture)."""
    return str(model.models_dir / "ace_robot.sdf")


def test_joint_mirror_from_the_axes(shipped):
    joints = JointMirror.from_model(shipped)
    np.testing.assert_array_equal(joints.signs, EXPECTED_SIGNS)
    np.testing.assert_array_equal(joints.offsets, 0.0)
    # The mirrored joints' position limits are symmetric about zero.
    np.testing.assert_array_equal(joints.limit_mismatch(shipped.lower, shipped.upper), 0.0)


def test_forward_kinematics_mirror_the_racket_pose_on_a_symmetric_robot(symmetric):
    joints = JointMirror.from_model(symmetric)
    np.testing.assert_array_equal(joints.signs, EXPECTED_SIGNS)
    position_error, angle_error = joints.fk_error(symmetric, samples=100)
    assert position_error < 1e-12 and angle_error < 1e-7
    Mirror.from_robot(symmetric, LAYOUT)  # passes its own checks


def test_the_shipped_robot_is_not_mirror_symmetric(shipped):
    """The arm sits 0.15 m to the +y side of the column: the mirrored joint state puts the racket
    0.3 m (twice the offset) from the mirrored racket pose, whatever q; orientations do mirror."""
    position_error, angle_error = JointMirror.from_model(shipped).fk_error(shipped, samples=20)
    assert position_error == pytest.approx(0.3, abs=1e-9)
    assert angle_error < 1e-7
    with pytest.raises(ValueError, match="not symmetric"):
        Mirror.from_robot(shipped, LAYOUT)


def make_mirror(model):
    return Mirror(JointMirror.from_model(model), LAYOUT)


def test_mirroring_twice_is_the_identity(shipped):
    mirror = make_mirror(shipped)
    rng = np.random.default_rng(0)
    obs, privileged, action = rng.normal(size=(5, LAYOUT.size)), rng.normal(size=(5, 28)), rng.uniform(-1, 1, (5, 16))
    np.testing.assert_array_equal(mirror.observation(mirror.observation(obs)), obs)
    np.testing.assert_array_equal(mirror.privileged(mirror.privileged(privileged)), privileged)
    np.testing.assert_array_equal(mirror.action(mirror.action(action)), action)
    transitions = {"obs": obs, "next_obs": obs, "privileged": privileged, "next_privileged": privileged,
                   "action": action, "reward": rng.normal(size=5), "done": np.zeros(5)}
    twice = mirror.transitions(mirror.transitions(transitions))
    for key, value in transitions.items():
        np.testing.assert_array_equal(twice[key], value)
    np.testing.assert_array_equal(mirror.transitions(transitions)["reward"], transitions["reward"])


def test_observation_parts_mirror_by_their_vector_kind(shipped):
    mirror = make_mirror(shipped)
    obs = np.arange(1.0, LAYOUT.size + 1.0)
    mirrored = LAYOUT.part(mirror.observation(obs), "positions")
    np.testing.assert_array_equal(mirrored[0], [1.0, -2.0, 3.0, 4.0])  # [p, age]: y flips
    spins = LAYOUT.part(obs, "spins")
    np.testing.assert_array_equal(LAYOUT.part(mirror.observation(obs), "spins")[0], spins[0] * [-1, 1, -1, 1])
    end_effector = LAYOUT.part(mirror.observation(obs), "end_effector") / LAYOUT.part(obs, "end_effector")
    np.testing.assert_array_equal(end_effector, [1, -1, 1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1])
    skill = LAYOUT.part(mirror.observation(obs), "skill") / LAYOUT.part(obs, "skill")
    np.testing.assert_array_equal(skill, [-1, 1, 1])


def test_mirrored_quaternion_is_the_mirrored_racket_rotation(symmetric):
    from pydrake.common.eigen_geometry import Quaternion
    from pydrake.math import RotationMatrix

    mirror = make_mirror(symmetric)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(symmetric.lower, symmetric.upper)
        quaternion = symmetric.racket_pose(q).rotation().ToQuaternion().wxyz()
        mirrored_quaternion = quaternion * [1, -1, 1, -1]
        expected = symmetric.racket_pose(mirror.joints.positions(q)).rotation().matrix()
        got = RotationMatrix(Quaternion(mirrored_quaternion)).matrix()
        np.testing.assert_allclose(got, expected, atol=1e-9)


def test_negating_a_mirrored_joints_action_mirrors_its_terminal_state(shipped):
    """The feasible set of the mirrored start state is the point reflection of the original's,
    so map_action(mirrored action) = the mirrored terminal state (mirror docstring)."""
    joints = JointMirror.from_model(shipped)
    mirror = make_mirror(shipped)
    control = ControlParams()
    limits = CommandLimits.from_config(load_scenario().limits, control)
    period = 0.001
    rng = np.random.default_rng(2)
    checked = 0
    while checked < 5:
        q0 = rng.uniform(limits.lower, limits.upper)
        v0 = rng.uniform(-0.3, 0.3, 8) * limits.velocity
        a0 = np.zeros(8)
        if not np.all(in_invariant_set(q0, v0, limits, control, period)):
            continue
        sets = feasible_sets(q0, v0, a0, limits, control, period)
        sets_mirrored = feasible_sets(joints.positions(q0), joints.rates(v0), a0, limits, control, period)
        action = rng.uniform(-1, 1, (10, 16))
        q_T, v_T = map_action(action, sets)
        q_T_mirrored, v_T_mirrored = map_action(mirror.action(action), sets_mirrored)
        np.testing.assert_allclose(q_T_mirrored, joints.positions(q_T), atol=1e-9)
        np.testing.assert_allclose(v_T_mirrored, joints.rates(v_T), atol=1e-9)
        checked += 1


def test_the_environment_is_mirror_symmetric_with_a_symmetric_robot_and_quiet_sensors(symmetric, tmp_path):
    """RallyEnv reset with a shot, a robot state and a skill, and again with their mirrors and the
    same seed: the first observations (27 ms in: ball histories, spins, robot and end-effector
    state, skill, EKF estimate) and the privileged observations mirror onto each other.

    The shipped robot is not symmetric (test above), so this runs the symmetric variant (ready
    pose moved onto the plane too). Sensor noise is switched (nearly) off: the same seed draws the same
    noise for both episodes, which is not the mirrored noise; latencies and dropouts, drawn
    alike, are symmetric. (Nearly off: the EKF weighs measurements by the sensors' noise, which
    must not be zero: 10 um and 1e-3 rad/s leave differences far below the tolerances.)"""
    from ace_drake.control.params import RallyParams
    from ace_drake.perception.params import PerceptionParams, PositionSensorParams, SpinSensorParams
    from ace_drake.physics.flight import make_state
    from ace_drake.training.env import RallyEnv, RallyEnvParams

    text = (MODELS_DIR / "scenario.yaml").read_text()
    assert "robot_model: ace_robot.sdf" in text and "ready_pose: [-0.45, -0.15," in text
    text = text.replace("robot_model: ace_robot.sdf", f"robot_model: {symmetric_sdf(symmetric)}")
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(text.replace("ready_pose: [-0.45, -0.15,", "ready_pose: [-0.45, 0.0,"))
    perception = PerceptionParams(
        positions="statistical",
        position=PositionSensorParams(noise_std=1e-5),
        spin=SpinSensorParams(magnitude_noise_std=1e-3, axis_noise_std=1e-5, magnitude_bias_std=1e-3, axis_bias_std=1e-5),
    )
    env = RallyEnv(RallyEnvParams(rally=RallyParams(scenario=str(scenario), perception=perception, perturb=False)))
    mirror = Mirror.from_robot(symmetric, env.layout)
    shot = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (40.0, -80.0, 25.0))
    q = np.array([-0.45, 0.2, 0.15, 0.15, 0.35, 0.3, -0.5, 0.2])
    skill = np.array([0.3, 1.0, 0.5])
    obs, info = env.reset(seed=7, options={"shot": shot, "skill": skill, "q": q})
    obs_m, info_m = env.reset(seed=7, options={"shot": shot * mirror.privileged_sign[:9], "skill": skill * [-1, 1, 1],
                                               "q": mirror.joints.positions(q)})
    assert env.layout.part(obs, "estimate_status")[0] == 1.0  # the EKF has a track to compare
    # Tolerances: ~10 sigma of the remaining (unmirrored) noise, m and rad/s; float32 elsewhere.
    tolerances = {"positions": 2e-4, "spins": 0.03, "robot_state": 1e-5, "end_effector": 1e-5, "skill": 0.0,
                  "estimate_status": 1e-6}
    for part, atol in tolerances.items():
        np.testing.assert_allclose(env.layout.part(mirror.observation(obs), part), env.layout.part(obs_m, part),
                                   atol=atol, rtol=1e-5, err_msg=part)
    estimate, estimate_m = env.layout.part(mirror.observation(obs), "estimate"), env.layout.part(obs_m, "estimate")
    for part, atol in ((slice(0, 3), 2e-4), (slice(3, 6), 0.01), (slice(6, 9), 0.03)):  # EKF p, v, w
        np.testing.assert_allclose(estimate[part], estimate_m[part], atol=atol, rtol=1e-5, err_msg="estimate")
    # The hit predicted from the estimate: the same hit instant, the mirrored ball state there.
    hit, hit_m = env.layout.part(mirror.observation(obs), "hit_prediction"), env.layout.part(obs_m, "hit_prediction")
    assert hit[0] == hit_m[0] == 1.0 and hit[1] == pytest.approx(hit_m[1], abs=1e-9)
    for part, atol in ((slice(2, 5), 2e-3), (slice(5, 8), 0.02), (slice(8, 11), 0.05)):  # p, v, w
        np.testing.assert_allclose(hit[part], hit_m[part], atol=atol, rtol=1e-4, err_msg="hit_prediction")
    np.testing.assert_allclose(mirror.privileged(info["privileged"]), info_m["privileged"], rtol=1e-6, atol=1e-6)
