"""RacketKinematics (robot.kinematics): the batched racket kinematics against RobotKinematics and
the plant, over random joint states within the limits; batch shapes; unsupported chains."""

import dataclasses

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import BallRpyJoint, FixedOffsetFrame, PrismaticJoint, RevoluteJoint, SpatialInertia, WeldJoint

from ace_drake.robot.kinematics import RacketKinematics
from ace_drake.robot.model import RACKET_FRAME, ROBOT_MODEL_NAME, add_robot_to_plant, load_scenario
from ace_drake.robot.params import JOINT_NAMES, Pose
from ace_drake.systems.robot_kinematics import RobotKinematics

SAMPLES = 256


def scenario_plant(scenario):
    """The kinematics-only plant that diagrams.add_robot builds."""
    plant = MultibodyPlant(0.0)
    add_robot_to_plant(plant, scenario)
    plant.Finalize()
    return plant


def random_states(scenario, count, seed):
    """q, v (count, 8) uniform within the scenario's position and velocity limits."""
    limits = scenario.limits.as_arrays()
    rng = np.random.default_rng(seed)
    q = rng.uniform(limits["lower"], limits["upper"], (count, 8))
    v = rng.uniform(-limits["velocity"], limits["velocity"], (count, 8))
    return q, v


def reference(plant, q, v):
    """RobotKinematics' outputs per sample: p (S, 3), R (S, 3, 3), w, v (S, 3), state (S, 13)."""
    system = RobotKinematics(plant)
    context = system.CreateDefaultContext()
    rows = []
    for q_k, v_k in zip(q, v):
        system.joint_state_port.FixValue(context, np.concatenate([q_k, v_k]))
        X_WR = system.racket_pose_port.Eval(context)
        V_WR = system.racket_velocity_port.Eval(context)
        state = system.end_effector_state_port.Eval(context)
        # Copies: the outputs are views of the system's cache, overwritten by the next sample.
        rows.append([np.array(a, copy=True) for a in (X_WR.translation(), X_WR.rotation().matrix(), V_WR.rotational(), V_WR.translational(), state)])
    return [np.array(column) for column in zip(*rows)]


@pytest.fixture(scope="module")
def scenario():
    return load_scenario()


@pytest.fixture(scope="module")
def dut(scenario):
    return RacketKinematics.for_scenario(scenario)


def test_matches_robot_kinematics_within_the_limits(scenario, dut):
    q, v = random_states(scenario, SAMPLES, seed=0)
    p_ref, R_ref, w_ref, v_ref, state_ref = reference(scenario_plant(scenario), q, v)
    p_WR, R_WR, w_WR, v_WR = dut.racket_state(q, v)
    np.testing.assert_allclose(p_WR, p_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(R_WR, R_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w_WR, w_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(v_WR, v_ref, rtol=0, atol=1e-10)
    pose_p, pose_R = dut.racket_pose(q)
    np.testing.assert_array_equal(pose_p, p_WR)
    np.testing.assert_array_equal(pose_R, R_WR)
    # The same quaternion, sign included (Drake's canonical w >= 0).
    np.testing.assert_allclose(dut.end_effector_state(q, v), state_ref, rtol=0, atol=1e-10)
    assert dut.joint_names == JOINT_NAMES


def test_honours_the_scenario_geometry(scenario):
    # A base moved and turned: the fixed transforms come from the plant, not from constants.
    moved = dataclasses.replace(scenario, base_pose=Pose(xyz=(-2.2, 0.3, -0.7), rpy_deg=(4.0, -3.0, 25.0)))
    q, v = random_states(moved, 50, seed=1)
    p_ref, R_ref, w_ref, v_ref, state_ref = reference(scenario_plant(moved), q, v)
    state = RacketKinematics.for_scenario(moved).end_effector_state(q, v)
    np.testing.assert_allclose(state, state_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(state[:, :3], p_ref, rtol=0, atol=1e-12)


def chain_plant(kinds, seed=0, free_ball=False):
    """A plant with model instance ROBOT_MODEL_NAME: a serial chain from the world of joints of
    ``kinds`` ("revolute", "prismatic", "weld", "ball") between random joint frames (random
    offsets, rotations and axes), ending in a racket frame at a random offset; and with
    ``free_ball`` a free body besides."""
    rng = np.random.default_rng(seed)
    plant = MultibodyPlant(0.0)
    robot = plant.AddModelInstance(ROBOT_MODEL_NAME)
    if free_ball:
        plant.AddRigidBody("ball", plant.AddModelInstance("ball"), SpatialInertia.SolidSphereWithMass(0.0027, 0.02))

    def random_pose():
        return RigidTransform(RollPitchYaw(rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-0.3, 0.3, 3))

    parent = plant.world_body()
    for i, kind in enumerate(kinds):
        body = plant.AddRigidBody(f"link_{i}", robot, SpatialInertia.SolidSphereWithMass(1.0, 0.05))
        F = plant.AddFrame(FixedOffsetFrame(f"F_{i}", parent.body_frame(), random_pose()))
        M = plant.AddFrame(FixedOffsetFrame(f"M_{i}", body.body_frame(), random_pose()))
        axis = rng.normal(size=3)
        if kind == "revolute":
            plant.AddJoint(RevoluteJoint(f"joint_{i}", F, M, axis))
        elif kind == "prismatic":
            plant.AddJoint(PrismaticJoint(f"joint_{i}", F, M, axis))
        elif kind == "weld":
            plant.AddJoint(WeldJoint(f"joint_{i}", F, M, random_pose()))
        else:
            plant.AddJoint(BallRpyJoint(f"joint_{i}", F, M))
        parent = body
    plant.AddFrame(FixedOffsetFrame(RACKET_FRAME, parent.body_frame(), random_pose()))
    plant.Finalize()
    return plant


def test_any_serial_chain_with_fixed_offsets_matches_the_plant():
    kinds = ["weld", "prismatic", "revolute", "weld", "weld", "revolute", "prismatic", "revolute", "revolute", "weld", "revolute", "revolute", "weld"]
    plant = chain_plant(kinds, seed=3)
    dut = RacketKinematics.from_plant(plant)
    rng = np.random.default_rng(4)
    q, v = rng.uniform(-3.0, 3.0, (40, 8)), rng.uniform(-10.0, 10.0, (40, 8))
    p_WR, R_WR, w_WR, v_WR = dut.racket_state(q, v)
    context = plant.CreateDefaultContext()
    racket = plant.GetFrameByName(RACKET_FRAME)
    for k in range(len(q)):
        plant.SetPositionsAndVelocities(context, np.concatenate([q[k], v[k]]))
        X_WR, V_WR = racket.CalcPoseInWorld(context), racket.CalcSpatialVelocityInWorld(context)
        np.testing.assert_allclose(p_WR[k], X_WR.translation(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(R_WR[k], X_WR.rotation().matrix(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(w_WR[k], V_WR.rotational(), rtol=0, atol=1e-10)
        np.testing.assert_allclose(v_WR[k], V_WR.translational(), rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "kinds, message",
    [
        (["prismatic", "prismatic", "ball", "revolute", "revolute", "revolute", "revolute", "revolute"], "joint 'joint_2' \\(ball_rpy"),
        (["prismatic"] + ["revolute"] * 6, "has 7 moving joints"),
        (["prismatic"] * 2 + ["revolute"] * 7, "has 9 moving joints"),
    ],
)
def test_an_unsupported_chain_is_refused(kinds, message):
    with pytest.raises(ValueError, match=message):
        RacketKinematics.from_plant(chain_plant(kinds))


def test_positions_beyond_the_chain_are_refused():
    with pytest.raises(ValueError, match="the plant has 15 positions and 14 velocities; expected exactly the 8"):
        RacketKinematics.from_plant(chain_plant(["prismatic"] * 2 + ["revolute"] * 6, free_ball=True))


def test_a_plant_without_a_racket_chain_is_refused():
    with pytest.raises(ValueError, match="finalized"):
        RacketKinematics.from_plant(MultibodyPlant(0.0))
    empty = MultibodyPlant(0.0)
    empty.Finalize()
    with pytest.raises(ValueError, match=f"no frame '{RACKET_FRAME}'"):
        RacketKinematics.from_plant(empty)
    # A free racket: Drake joins it to the world by a floating joint, which is not a chain joint.
    free = MultibodyPlant(0.0)
    blade = free.AddRigidBody("blade", free.AddModelInstance(ROBOT_MODEL_NAME), SpatialInertia.SolidSphereWithMass(1.0, 0.05))
    free.AddFrame(FixedOffsetFrame(RACKET_FRAME, blade.body_frame(), RigidTransform()))
    free.Finalize()
    with pytest.raises(ValueError, match="joint 'blade' \\(quaternion_floating, 7 positions\\)"):
        RacketKinematics.from_plant(free)


def test_batch_shapes_give_the_per_sample_results(scenario, dut):
    q, v = random_states(scenario, 2 * 3, seed=5)
    flat = dut.racket_state(q, v)
    single = dut.racket_state(q[4], v[4])
    assert [a.shape for a in single] == [(3,), (3, 3), (3,), (3,)]
    for a, b in zip(single, flat):
        np.testing.assert_array_equal(a, b[4])
    batched = dut.racket_state(q.reshape(2, 3, 8), v.reshape(2, 3, 8))
    assert [a.shape for a in batched] == [(2, 3, 3), (2, 3, 3, 3), (2, 3, 3), (2, 3, 3)]
    for a, b in zip(batched, flat):
        np.testing.assert_array_equal(a.reshape(b.shape), b)
    assert dut.end_effector_state(q[4], v[4]).shape == (13,)
    assert dut.end_effector_state(q.reshape(2, 3, 8), v.reshape(2, 3, 8)).shape == (2, 3, 13)
    np.testing.assert_array_equal(dut.end_effector_state(q[4], v[4]), dut.end_effector_state(q, v)[4])
    assert dut.racket_pose(q.reshape(2, 3, 8))[1].shape == (2, 3, 3, 3)
    assert dut.racket_pose(np.zeros((0, 8)))[0].shape == (0, 3)


def test_a_wrong_shape_is_refused(dut):
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 8\).*got shape \(4, 7\)"):
        dut.racket_pose(np.zeros((4, 7)))
    with pytest.raises(ValueError, match=r"v must have shape \(\.\.\., 8\).*got shape \(\)"):
        dut.racket_state(np.zeros(8), 0.0)
    with pytest.raises(ValueError, match=r"same shape.*\(2, 8\) and \(3, 8\)"):
        dut.racket_state(np.zeros((2, 8)), np.zeros((3, 8)))


def reference_quaternion(R):
    """Drake's RotationMatrix::ToQuaternion in NumPy, one matrix at a time: the reference of the
    compiled ``_quaternion_one``."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace >= R[0, 0] and trace >= R[1, 1] and trace >= R[2, 2]:
        q = [1.0 + trace, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        q = [R[2, 1] - R[1, 2], 1.0 - (trace - 2.0 * R[0, 0]), R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]]
    elif R[1, 1] >= R[2, 2]:
        q = [R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], 1.0 - (trace - 2.0 * R[1, 1]), R[1, 2] + R[2, 1]]
    else:
        q = [R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1.0 - (trace - 2.0 * R[2, 2])]
    scale = (-1.0 if q[0] < 0.0 else 1.0) / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return np.array([x * scale for x in q])


def test_end_effector_state_is_the_racket_state_and_its_quaternion_bit_for_bit(scenario, dut):
    q, v = random_states(scenario, 400, seed=3)
    q, v = q.reshape(20, 20, -1), v.reshape(20, 20, -1)  # any leading dimensions
    state = dut.end_effector_state(q, v)
    p, R, w, v_WR = dut.racket_state(q, v)
    assert state.shape == (20, 20, 13)
    np.testing.assert_array_equal(state[..., :3], p)
    np.testing.assert_array_equal(state[..., 7:10], v_WR)
    np.testing.assert_array_equal(state[..., 10:], w)
    quaternions = np.array([reference_quaternion(M) for M in R.reshape(-1, 3, 3)])
    np.testing.assert_array_equal(state[..., 3:7].reshape(-1, 4), quaternions)
    # Each branch of the conversion: the trace, then each diagonal entry, the largest.
    branches = {int(np.argmax([np.trace(M), M[0, 0], M[1, 1], M[2, 2]])) for M in R.reshape(-1, 3, 3)}
    assert len(branches) >= 3
