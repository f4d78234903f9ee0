"""Mirror across the XZ plane: involution, the joint mirror by forward kinematics, actions through
the feasible sets (with and without a joint offset), the shipped robot's symmetry, and the
asymmetry of an arm whose pitch pivot is off the yaw axis."""

import dataclasses
import shutil

import numpy as np
import pytest

from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout, privileged_slice
from ace_drake.control.action_mapping import map_action
from ace_drake.control.feasible_set import feasible_sets, in_invariant_set
from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.learning.mirror import JointMirror, Mirror
from ace_drake.robot.model import RobotModel, load_scenario

LAYOUT = ObservationLayout(3, 2)
# gantry_x, gantry_y, shoulder_yaw, shoulder_pitch, elbow, wrist_1, wrist_2, wrist_3
EXPECTED_SIGNS = [1, -1, -1, 1, 1, -1, 1, -1]
# The arm (its yaw axis and pitch pivot) 0.15 m to the +y of the column (ace_robot.sdf): gantry_y's offset -0.3 m.
ARM_OFFSET = 0.15
EXPECTED_OFFSETS = [0, -2 * ARM_OFFSET, 0, 0, 0, 0, 0, 0]


@pytest.fixture(scope="module")
def shipped():
    return RobotModel()


@pytest.fixture(scope="module")
def offset_arm(tmp_path_factory):
    """The shipped robot with its shoulder_yaw axis moved back onto the column (the robot before
    2026-12-06): the arm's pitch pivot then sits 0.15 m off the yaw axis and turns with the yaw."""
    directory = tmp_path_factory.mktemp("models")
    shutil.copy(MODELS_DIR / "table.sdf", directory / "table.sdf")
    text = (MODELS_DIR / "ace_robot.sdf").read_text()
    assert text.count("<pose>0.08 0.15 0.96 0 0 0</pose>") == 1
    (directory / "ace_robot.sdf").write_text(text.replace("<pose>0.08 0.15 0.96 0 0 0</pose>", "<pose>0.08 0 0.96 0 0 0</pose>"))
    return RobotModel(load_scenario(), directory)


def test_joint_mirror_from_the_axes(shipped):
    """Signs from the axes; gantry_y offset so that the racket at q = 0 (0.15 m off the plane)
    mirrors onto itself. Every mirrored joint's limits map onto themselves: gantry_y's [-1.3, 1.0]
    are symmetric about c / 2 = -0.15, the others about 0 (c = 0)."""
    joints = JointMirror.from_model(shipped)
    np.testing.assert_array_equal(joints.signs, EXPECTED_SIGNS)
    np.testing.assert_allclose(joints.offsets, EXPECTED_OFFSETS, atol=1e-12)
    np.testing.assert_allclose(joints.limit_mismatch(shipped.lower, shipped.upper), 0.0, atol=1e-12)
    # The ready pose (gantry_y -0.15, the racket on the plane) is its own mirror.
    np.testing.assert_allclose(joints.positions(shipped.ready_pose), shipped.ready_pose, atol=1e-12)
    assert joints.racket_error(shipped, shipped.ready_pose)[0] < 1e-12
    # Every state within the limits has its mirror within them, up to the ends.
    q = np.random.default_rng(0).uniform(shipped.lower, shipped.upper, (200, 8))
    q[:2, 1] = shipped.lower[1], shipped.upper[1]
    assert np.all(joints.within_limits(q, shipped.lower, shipped.upper, tolerance=1e-12))


def test_a_joint_mirror_is_an_involution_by_construction():
    with pytest.raises(ValueError, match="shift"):
        JointMirror(np.ones(8), np.r_[0.1, np.zeros(7)])
    with pytest.raises(ValueError, match="signs"):
        JointMirror(np.r_[0.5, np.ones(7)], np.zeros(8))


def test_forward_kinematics_mirror_the_racket_pose_on_the_shipped_robot(shipped):
    joints = JointMirror.from_model(shipped)
    np.testing.assert_array_equal(joints.signs, EXPECTED_SIGNS)
    position_error, angle_error = joints.fk_error(shipped, samples=100)
    assert position_error < 1e-12 and angle_error < 1e-7
    assert Mirror.from_robot(shipped, LAYOUT).exact  # passes its own checks


def test_an_arm_off_the_yaw_axis_is_not_mirror_symmetric(offset_arm):
    """With the pitch pivot 0.15 m off the yaw axis, gantry_y's offset -0.3 m puts the mirrored
    joint state's racket e(psi) = 0.3 (sin psi, cos psi - 1, 0) from the mirrored racket pose,
    |e| = 0.6 |sin(psi / 2)| (mirror docstring): exact at yaw 0 only; orientations mirror for every
    q. ``Mirror.from_robot`` refuses it."""
    joints = JointMirror.from_model(offset_arm)
    np.testing.assert_allclose(joints.offsets, EXPECTED_OFFSETS, atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(offset_arm.lower, offset_arm.upper)
        position_error, angle_error = joints.racket_error(offset_arm, q)
        assert position_error == pytest.approx(4 * ARM_OFFSET * abs(np.sin(q[2] / 2)), abs=1e-9)
        assert angle_error < 1e-7
        q[2] = 0.0
        assert joints.racket_error(offset_arm, q)[0] < 1e-12
    with pytest.raises(ValueError, match="not symmetric"):
        Mirror.from_robot(offset_arm, LAYOUT)
    assert not Mirror.from_robot(offset_arm, LAYOUT, exact=False).exact


def test_the_exact_mirror_of_an_arm_off_the_yaw_axis_moves_the_gantry_with_the_yaw(offset_arm):
    """No per-joint map mirrors that arm; the yaw-coupled one (q_x - 0.3 sin psi,
    -q_y - 0.3 cos psi, -psi, the rest by their signs) does, exactly (mirror docstring)."""
    joints = JointMirror.from_model(offset_arm)
    rng = np.random.default_rng(4)
    for _ in range(20):
        q = rng.uniform(offset_arm.lower, offset_arm.upper)
        coupled = joints.signs * q
        coupled[0] = q[0] - 2 * ARM_OFFSET * np.sin(q[2])
        coupled[1] = -q[1] - 2 * ARM_OFFSET * np.cos(q[2])
        X, X_mirrored = offset_arm.racket_pose(q), offset_arm.racket_pose(coupled)
        np.testing.assert_allclose(X_mirrored.translation(), np.diag([1, -1, 1]) @ X.translation(), atol=1e-12)
        np.testing.assert_allclose(X_mirrored.rotation().matrix(), np.diag([1, -1, 1]) @ X.rotation().matrix() @ np.diag([1, -1, 1]), atol=1e-12)


def make_mirror(model):
    return Mirror(JointMirror.from_model(model), LAYOUT)


def test_mirroring_twice_is_the_identity(shipped):
    """States, actions, actor and critic observations, rewards; with gantry_y's offset (the
    affine parts to round-off), in float64 and float32."""
    mirror = make_mirror(shipped)
    assert np.any(mirror.joints.offsets != 0.0)
    rng = np.random.default_rng(0)
    q, v = rng.uniform(shipped.lower, shipped.upper, (5, 8)), rng.normal(size=(5, 8))
    np.testing.assert_allclose(mirror.joints.positions(mirror.joints.positions(q)), q, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(mirror.joints.rates(mirror.joints.rates(v)), v)
    for dtype, atol in ((np.float64, 1e-15), (np.float32, 1e-7)):
        obs = rng.normal(size=(5, LAYOUT.size)).astype(dtype)
        privileged, action = rng.normal(size=(5, 28)).astype(dtype), rng.uniform(-1, 1, (5, 16)).astype(dtype)
        assert mirror.observation(obs).dtype == dtype and mirror.privileged(privileged).dtype == dtype
        np.testing.assert_allclose(mirror.observation(mirror.observation(obs)), obs, rtol=0, atol=atol)
        np.testing.assert_allclose(mirror.privileged(mirror.privileged(privileged)), privileged, rtol=0, atol=atol)
        np.testing.assert_array_equal(mirror.action(mirror.action(action)), action)
        transitions = {"obs": obs, "next_obs": obs, "privileged": privileged, "next_privileged": privileged,
                       "action": action, "reward": rng.normal(size=5), "done": np.zeros(5)}
        twice = mirror.transitions(mirror.transitions(transitions))
        for key, value in transitions.items():
            np.testing.assert_allclose(twice[key], value, rtol=0, atol=atol)
        np.testing.assert_array_equal(mirror.transitions(transitions)["reward"], transitions["reward"])
    with pytest.raises(KeyError, match="no \\['obs'\\]"):
        mirror.transitions({"privileged": privileged, "action": action})


def test_joint_positions_mirror_affinely_in_both_observations(shipped):
    mirror = make_mirror(shipped)
    obs, privileged = np.zeros(LAYOUT.size), np.zeros(28)
    q = np.arange(1.0, 9.0)
    obs[LAYOUT.slice("robot_state")] = np.r_[q, q, q]  # [q, v, a]
    privileged[privileged_slice("joint_state")] = np.r_[q, q]  # [q, v]
    robot_state = LAYOUT.part(mirror.observation(obs), "robot_state")
    np.testing.assert_allclose(robot_state, np.r_[mirror.joints.positions(q), mirror.joints.rates(q), mirror.joints.rates(q)])
    np.testing.assert_allclose(mirror.privileged(privileged)[privileged_slice("joint_state")],
                               np.r_[mirror.joints.positions(q), mirror.joints.rates(q)])
    assert robot_state[1] == pytest.approx(-2.0 - 0.3)


def test_the_mirrored_end_effector_quaternion_keeps_the_canonical_sign(shipped):
    """At the ready pose the blade is a half turn (w = 0): the canonical quaternion (largest
    component positive) of the mirrored pose is the negated [w, -x, y, -z]."""
    from ace_drake.robot.kinematics import RacketKinematics

    mirror, kinematics = make_mirror(shipped), RacketKinematics.for_scenario(load_scenario())
    rng = np.random.default_rng(5)
    for q in [shipped.ready_pose, *(rng.uniform(shipped.lower, shipped.upper) for _ in range(5))]:
        obs = np.zeros(LAYOUT.size)
        obs[LAYOUT.slice("end_effector")] = kinematics.end_effector_state(q, np.zeros(8))
        expected = kinematics.end_effector_state(mirror.joints.positions(q), np.zeros(8))
        np.testing.assert_allclose(LAYOUT.part(mirror.observation(obs), "end_effector"), expected, atol=1e-12)


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


def test_mirrored_quaternion_is_the_mirrored_racket_rotation(shipped):
    from pydrake.common.eigen_geometry import Quaternion
    from pydrake.math import RotationMatrix

    mirror = make_mirror(shipped)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(shipped.lower, shipped.upper)
        quaternion = shipped.racket_pose(q).rotation().ToQuaternion().wxyz()
        mirrored_quaternion = quaternion * [1, -1, 1, -1]
        expected = shipped.racket_pose(mirror.joints.positions(q)).rotation().matrix()
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


def action_mapping_case(joints, mirror, limits, seed: int, starts: int = 5):
    """map(mirror(action), mirror(start)) against mirror(map(action, start)) for random invariant
    starts and actions: the largest differences (position, velocity)."""
    control, period = ControlParams(), 0.001
    rng = np.random.default_rng(seed)
    worst = np.zeros(2)
    checked = 0
    while checked < starts:
        q0 = rng.uniform(limits.lower, limits.upper)
        v0 = rng.uniform(-0.3, 0.3, 8) * limits.velocity
        a0 = rng.uniform(-0.3, 0.3, 8) * limits.acceleration
        if not (np.all(in_invariant_set(q0, v0, limits, control, period)) and np.all(in_invariant_set(joints.positions(q0), -v0, limits, control, period))):
            continue
        sets = feasible_sets(q0, v0, a0, limits, control, period)
        sets_mirrored = feasible_sets(joints.positions(q0), joints.rates(v0), joints.rates(a0), limits, control, period)
        action = rng.uniform(-1, 1, (20, 16))
        q_T, v_T = map_action(action, sets)
        q_T_mirrored, v_T_mirrored = map_action(mirror.action(action), sets_mirrored)
        worst = np.maximum(worst, [np.max(np.abs(q_T_mirrored - joints.positions(q_T))), np.max(np.abs(v_T_mirrored - joints.rates(v_T)))])
        checked += 1
    return worst


def test_the_action_mirror_is_exact_with_the_shipped_limits(shipped):
    """gantry_y maps q -> -q - 0.3 and its command limits [-1.28, 0.98] are centred on -0.15:
    negating the action is exact through eq. (12) (mirror docstring, *Actions*), from starts
    anywhere in the limits; ``action_exact`` agrees."""
    joints, mirror = JointMirror.from_model(shipped), make_mirror(shipped)
    limits = CommandLimits.from_config(load_scenario().limits, ControlParams())
    np.testing.assert_allclose(joints.limit_mismatch(limits.lower, limits.upper), 0.0, atol=1e-12)
    assert np.all(action_mapping_case(joints, mirror, limits, seed=6) < 1e-9)
    rng = np.random.default_rng(7)
    q0 = rng.uniform(limits.lower, limits.upper, (50, 8))
    q0[0, 1], q0[1, 1] = limits.lower[1] + 0.01, limits.upper[1] - 0.01  # near both ends
    assert np.all(mirror.action_exact(q0, np.zeros((50, 8)), np.zeros((50, 8)), limits, ControlParams(), 0.001) | ~in_invariant_set(q0, np.zeros((50, 8)), limits, ControlParams(), 0.001).all(-1))


def test_with_limits_not_centred_on_half_the_offset_the_action_mirror_is_inexact_near_their_ends(shipped):
    """gantry_y's command limits [-1.28, 1.28] (centred on 0, not on -0.15): starts in the middle
    (rally states lie within [-0.48, 0.48] m) still mirror exactly; near the upper end, where
    the limit shapes the feasible set and not its mirror's, not."""
    joints, mirror = JointMirror.from_model(shipped), make_mirror(shipped)
    shipped_limits = CommandLimits.from_config(load_scenario().limits, ControlParams())
    limits = dataclasses.replace(shipped_limits, upper=np.r_[shipped_limits.upper[0], 1.28, shipped_limits.upper[2:]])
    assert joints.limit_mismatch(limits.lower, limits.upper)[1] == pytest.approx(0.3)
    control, period = ControlParams(), 0.001
    rng = np.random.default_rng(8)
    worst = np.zeros(2)
    for _ in range(5):
        q0 = rng.uniform(limits.lower, limits.upper)
        q0[1] = rng.uniform(-0.6, 0.6)
        v0, a0 = rng.uniform(-0.3, 0.3, 8) * limits.velocity, np.zeros(8)
        assert mirror.action_exact(q0, v0, a0, limits, control, period)
        sets = feasible_sets(q0, v0, a0, limits, control, period)
        sets_mirrored = feasible_sets(joints.positions(q0), joints.rates(v0), a0, limits, control, period)
        action = rng.uniform(-1, 1, (20, 16))
        q_T, v_T = map_action(action, sets)
        q_T_m, v_T_m = map_action(mirror.action(action), sets_mirrored)
        worst = np.maximum(worst, [np.max(np.abs(q_T_m - joints.positions(q_T))), np.max(np.abs(v_T_m - joints.rates(v_T)))])
    assert np.all(worst < 1e-9)
    q0 = shipped.ready_pose.copy()
    q0[1] = 0.97  # its mirror -1.27 is 0.01 m from the lower limit -1.28
    assert not mirror.action_exact(q0, np.zeros(8), np.zeros(8), limits, control, period)


def test_the_hit_state_action_mirrors_by_its_signs_whatever_the_offset(shipped):
    """y_q = (q_hit - q0) / half-range: the offset cancels (mirror docstring)."""
    from ace_drake.control.hit_state import HitStateAction

    mirror = make_mirror(shipped)
    parameterisation = HitStateAction.from_limits(CommandLimits.from_config(load_scenario().limits, ControlParams()))
    rng = np.random.default_rng(9)
    y, q0 = rng.uniform(-1, 1, (10, 16)), rng.uniform(shipped.lower, shipped.upper, (10, 8))
    q_hit, v_hit = parameterisation.hit_state(y, q0)
    q_hit_m, v_hit_m = parameterisation.hit_state(mirror.action(y), mirror.joints.positions(q0))
    np.testing.assert_allclose(q_hit_m, mirror.joints.positions(q_hit), atol=1e-12)
    np.testing.assert_allclose(v_hit_m, mirror.joints.rates(v_hit), atol=1e-12)


def test_the_environment_is_mirror_symmetric_with_quiet_sensors(shipped):
    """RallyEnv reset with a shot, a robot state and a skill, and again with their mirrors and the
    same seed: the first observations (27 ms in: ball histories, spins, robot and end-effector
    state, skill, EKF estimate) and the privileged observations mirror onto each other.

    Sensor noise is switched (nearly) off: the same seed draws the same noise for both episodes,
    which is not the mirrored noise; latencies and dropouts, drawn alike, are symmetric. (Nearly
    off: the EKF weighs measurements by the sensors' noise, which must not be zero: 10 um and
    1e-3 rad/s leave differences far below the tolerances.)"""
    from ace_drake.control.params import RallyParams
    from ace_drake.perception.params import PerceptionParams, PositionSensorParams, SpinSensorParams
    from ace_drake.physics.flight import make_state
    from ace_drake.training.env import RallyEnv, RallyEnvParams

    perception = PerceptionParams(
        positions="statistical",
        position=PositionSensorParams(noise_std=1e-5),
        spin=SpinSensorParams(magnitude_noise_std=1e-3, axis_noise_std=1e-5, magnitude_bias_std=1e-3, axis_bias_std=1e-5),
    )
    env = RallyEnv(RallyEnvParams(rally=RallyParams(perception=perception, perturb=False)))
    mirror = Mirror.from_robot(shipped, env.layout)
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


def test_a_rally_on_the_shipped_robot_mirrors_through_the_hit(shipped):
    """One episode and its mirror on the segment-stepped diagram (B = 2): the returner, and the
    mirrored returner (M_a . returner . M_o) from the mirrored shot and skill, the same seed, the
    ready pose (its own mirror), quiet sensors. The balls mirror each other to sensor noise before
    the hit, and the robot's return mirrors too: the same outcome, the balls apart by no more than
    what the returner's solvers leave."""
    from ace_drake.control.params import RallyParams
    from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
    from ace_drake.evaluation.controllers import diagram_params_for, make_controller
    from ace_drake.learning.mirror import BALL_STATE
    from ace_drake.perception.params import PerceptionParams, PositionSensorParams, SpinSensorParams
    from ace_drake.physics.flight import make_state

    perception = PerceptionParams(
        positions="statistical", position=PositionSensorParams(noise_std=1e-5),
        spin=SpinSensorParams(magnitude_noise_std=1e-3, axis_noise_std=1e-5, magnitude_bias_std=1e-3, axis_bias_std=1e-5),
    )
    params = RallyParams(perception=perception, stepping="segment", perturb=False)
    returners = [make_controller("returner", params) for _ in range(2)]
    params = diagram_params_for(returners[0], params)
    mirror = Mirror.from_robot(shipped, ObservationLayout(params.position_history, params.spin_history))

    class Mirrored:
        def __init__(self, inner):
            self.inner = inner

        def reset(self):
            self.inner.reset()

        def __call__(self, observation):
            action = self.inner(mirror.observation(observation))
            return None if action is None else mirror.action(action)

    diagram = build_segment_rally_diagram(params, [returners[0], Mirrored(returners[1])], 2)
    simulator = make_segment_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(2))
    shot = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (40.0, -80.0, 25.0))
    skill = np.array([0.3, 1.0, 0.5])
    q0 = shipped.ready_pose
    start_segment_episodes(diagram, context, [0, 1], np.stack([shot, shot * BALL_STATE]), [7, 7],
                           np.stack([skill, skill * [-1, 1, 1]]), q=np.stack([q0, mirror.joints.positions(q0)]))
    simulator.Initialize()
    ball = diagram.GetSubsystemByName("ball")
    period = diagram.GetSubsystemByName("episode_clock").timing.duration
    hit, worst = None, np.zeros(9)
    for tick in range(1, 45):
        simulator.AdvanceTo(tick * period)
        state = ball.plant_state(ball.GetMyContextFromRoot(context))
        kinds = [[event.kind.name for event in events] for events in state.events]
        assert ("RACKET" in kinds[0]) == ("RACKET" in kinds[1]), f"tick {tick}: {kinds}"
        hit = hit or (tick if "RACKET" in kinds[0] else None)
        difference = np.abs(state.balls[1] - state.balls[0] * BALL_STATE)
        if hit is None:
            assert np.all(difference < 1e-6), f"tick {tick}"
        worst = np.maximum(worst, difference)
    assert hit is not None and hit >= 10  # the incoming flight and bounce, then the return
    # After it, what the sensors' unmirrored noise leaves (the returners' actions differ by ~1e-3):
    # here 2 mm, 4 mm/s and 0.11 rad/s; a racket off its mirror by centimetres moves them by far more.
    np.testing.assert_array_less(worst, np.repeat([0.005, 0.02, 0.5], 3))
