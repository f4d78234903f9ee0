"""Forward kinematics of the racket frame over batches of joint states, compiled.

``systems.RobotKinematics`` asks Drake's MultibodyPlant for one joint state per call; the
segment-stepped diagram needs the racket's pose and twist at every 1 kHz sample of B environments
at once (B x 33 samples per 32 ms segment). ``RacketKinematics`` reads the serial chain from the
world to the racket frame R (origin at the blade centre, z along the forehand normal;
``robot.model.RACKET_FRAME``) out of a finalized plant once, and then evaluates it with NumPy
arrays and numba loops: no Drake call per sample.

The chain. Walking from R's body to the world, every joint must be a weld or a single-dof
revolute or prismatic joint, eight of the latter, and they must be all of the plant's positions.
Each moving joint's transform from its parent body P to its child body C is
X_PC(q) = X_PF X_FM(q) X_MC, F and M the joint's frames on P and C, with X_FM a rotation by q
about the joint's axis or a translation q along it: its 3 x 4 matrix is B0 + sin q B1 +
(1 - cos q) B2 or B0 + q B1 (``robot.bounds.KinematicTree._terms_of``, the broad phase's forward
kinematics, whose terms are reused here). The welds between two moving joints (and the world's
weld to the base, and R's pose in its body) are constant and fold into the neighbouring joint's
terms, so X_WR is the product of eight such matrices, in the plant's geometry for any scenario.

Velocity. With a_j the unit axis of joint j in world and o_j a point on it (F's origin), the
twist of R's origin is w_WR = sum over revolute j of a_j qdot_j and
v_WR = sum over revolute j of (a_j x (p_WR - o_j)) qdot_j + sum over prismatic j of a_j qdot_j,
accumulated outwards as v_WR = w_WR x p_WR + u with u = sum (prismatic a_j qdot_j) - sum
(revolute (a_j x o_j) qdot_j), so that nothing per joint need be stored.

Accuracy against Drake (tests/test_kinematics.py): positions and rotation matrices agree to
~1e-15, the spatial velocity to ~1e-13 (m/s, rad/s), and ``end_effector_state`` uses Drake's
``RotationMatrix::ToQuaternion`` (the canonical sign, w >= 0).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import BodyIndex

from ace_drake.robot.bounds import KinematicTree, compose_pose, sin_cos
from ace_drake.robot.model import RACKET_FRAME, ROBOT_MODEL_NAME, add_robot_to_plant, check_joint_order, load_scenario
from ace_drake.robot.params import JOINT_NAMES, RobotScenario

CHAIN_JOINTS = len(JOINT_NAMES)  # the moving joints between the world and the racket frame
_BLOCK = 128  # samples per block of the compiled loops (their working arrays stay in L1 cache)


class RacketKinematics:
    """Forward kinematics of the racket frame R (blade centre, z along the forehand normal) in
    world W, over any leading batch dimensions (module doc).

    Joint arrays q (..., 8) (m, rad) and v (..., 8) (m/s, rad/s) are in the plant's position
    order, JOINT_NAMES for the robot's plant (``robot.model.check_joint_order``); ``joint_names``
    lists it. Non-finite joint values give non-finite results for their samples.
    """

    def __init__(
        self,
        terms: np.ndarray,
        revolute: np.ndarray,
        axes: np.ndarray,
        origins: np.ndarray,
        position_index: np.ndarray,
        velocity_index: np.ndarray,
        joint_names: tuple[str, ...],
    ):
        """Use ``from_plant`` or ``for_scenario``. terms (8, 3, 12): each moving joint's B0, B1,
        B2 (module doc) from the previous joint's child body (the world for the first) to its own
        child body (R for the last), welds folded in; revolute (8,) bool; axes, origins (8, 3):
        each joint's unit axis and a point on it in that previous frame (m); position_index,
        velocity_index (8,): where each joint's q and v sit in the joint vectors."""
        self._terms = np.ascontiguousarray(terms, dtype=float)
        self._revolute = np.ascontiguousarray(revolute, dtype=np.bool_)
        self._axes = np.ascontiguousarray(axes, dtype=float)
        self._origins = np.ascontiguousarray(origins, dtype=float)
        self._position_index = np.ascontiguousarray(position_index, dtype=np.int64)
        self._velocity_index = np.ascontiguousarray(velocity_index, dtype=np.int64)
        self.joint_names = tuple(joint_names)

    @classmethod
    def from_plant(cls, plant: MultibodyPlant) -> "RacketKinematics":
        """The kinematics of the racket frame (``RACKET_FRAME`` of model ``ROBOT_MODEL_NAME``) of
        a finalized plant whose positions are exactly the eight joints of the chain from the world
        to it. Raises ValueError naming what is not supported otherwise."""
        if not plant.is_finalized():
            raise ValueError("RacketKinematics: the plant must be finalized")
        if not plant.HasModelInstanceNamed(ROBOT_MODEL_NAME) or not plant.HasFrameNamed(RACKET_FRAME, plant.GetModelInstanceByName(ROBOT_MODEL_NAME)):
            raise ValueError(f"RacketKinematics: the plant has no frame {RACKET_FRAME!r} in a model instance {ROBOT_MODEL_NAME!r}")
        racket = plant.GetFrameByName(RACKET_FRAME, plant.GetModelInstanceByName(ROBOT_MODEL_NAME))
        inboard = {int(plant.get_joint(index).child_body().index()): plant.get_joint(index) for index in plant.GetJointIndices()}
        world = int(plant.world_body().index())
        chain, body = [], int(racket.body().index())
        while body != world:
            if body not in inboard:
                raise ValueError(f"RacketKinematics: body {plant.get_body(BodyIndex(body)).name()!r} of the racket's chain has no joint to its parent")
            joint = inboard[body]
            kind = joint.type_name()
            if kind != "weld" and not (kind in ("revolute", "prismatic") and joint.num_positions() == 1 and joint.num_velocities() == 1):
                raise ValueError(
                    f"RacketKinematics: joint {joint.name()!r} ({kind}, {joint.num_positions()} positions) between {joint.parent_body().name()!r} "
                    f"and {joint.child_body().name()!r} is not supported; expected a serial chain of {CHAIN_JOINTS} single-dof revolute or "
                    f"prismatic joints (welds between them allowed) from the world to the racket frame {RACKET_FRAME!r}"
                )
            chain.append(joint)
            body = int(joint.parent_body().index())
        chain.reverse()  # world outwards
        moving = [joint for joint in chain if joint.type_name() != "weld"]
        if len(moving) != CHAIN_JOINTS:
            raise ValueError(
                f"RacketKinematics: the chain from the world to the racket frame {RACKET_FRAME!r} has {len(moving)} moving joints "
                f"({', '.join(joint.name() for joint in moving) or 'none'}); expected {CHAIN_JOINTS}"
            )
        starts = sorted(joint.position_start() for joint in moving)
        if plant.num_positions() != CHAIN_JOINTS or plant.num_velocities() != CHAIN_JOINTS or starts != list(range(CHAIN_JOINTS)):
            raise ValueError(
                f"RacketKinematics: the plant has {plant.num_positions()} positions and {plant.num_velocities()} velocities; expected exactly "
                f"the {CHAIN_JOINTS} of the racket's chain"
            )
        terms, axes, origins = [], [], []
        X_prev = np.eye(4)  # the welds since the previous moving joint's child (or the world)
        for joint in chain:
            local = _as_4x4(KinematicTree._terms_of(joint))  # (3, 4, 4): X_PC = B0 + c1 B1 + c2 B2
            if joint.type_name() == "weld":
                X_prev = X_prev @ local[0]
                continue
            X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame().GetAsMatrix4()
            axis = np.asarray(joint.revolute_axis() if joint.type_name() == "revolute" else joint.translation_axis(), dtype=float)
            axes.append(X_prev[:3, :3] @ X_PF[:3, :3] @ (axis / np.linalg.norm(axis)))
            origins.append(X_prev[:3, :3] @ X_PF[:3, 3] + X_prev[:3, 3])
            terms.append(X_prev @ local)  # the bottom rows of B1 and B2 are zero: X_prev's translation stays in B0
            X_prev = np.eye(4)
        X_prev = X_prev @ racket.GetFixedPoseInBodyFrame().GetAsMatrix4()
        terms[-1] = terms[-1] @ X_prev
        return cls(
            terms=np.array([t[:, :3, :].reshape(3, 12) for t in terms]),
            revolute=np.array([joint.type_name() == "revolute" for joint in moving]),
            axes=np.array(axes),
            origins=np.array(origins),
            position_index=np.array([joint.position_start() for joint in moving]),
            velocity_index=np.array([joint.velocity_start() for joint in moving]),
            joint_names=tuple(joint.name() for joint in sorted(moving, key=lambda joint: joint.position_start())),
        )

    @classmethod
    def for_scenario(cls, scenario: RobotScenario | None = None) -> "RacketKinematics":
        """The racket kinematics of the robot in ``scenario`` (default ``robot.model.load_scenario()``),
        from the kinematics-only plant that ``diagrams.add_robot`` builds."""
        plant = MultibodyPlant(time_step=0.0)
        robot = add_robot_to_plant(plant, scenario or load_scenario())
        plant.Finalize()
        check_joint_order(plant, robot)
        return cls.from_plant(plant)

    def racket_pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """X_WR at joint positions q (..., 8): (p_WR (..., 3) m, R_WR (..., 3, 3))."""
        q = _joint_array(q, "q")
        p, R, _, _ = self._evaluate(q, None)
        return p, R

    def racket_state(self, q, v) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """X_WR and V_WR (of R's origin, expressed in world) at joint states q, v (..., 8):
        (p_WR (..., 3) m, R_WR (..., 3, 3), w_WR (..., 3) rad/s, v_WR (..., 3) m/s)."""
        q, v = _joint_array(q, "q"), _joint_array(v, "v")
        if q.shape != v.shape:
            raise ValueError(f"RacketKinematics: q and v must have the same shape (..., 8), got {q.shape} and {v.shape}")
        return self._evaluate(q, v)

    def end_effector_state(self, q, v) -> np.ndarray:
        """The policy's view of the end effector at joint states q, v (..., 8), (..., 13):
        [p_WR (3; m), quaternion of R_WR (4; w, x, y, z; w >= 0, as Drake's ToQuaternion),
        v_WR (3; m/s), w_WR (3; rad/s)], the layout of ``RobotKinematics``' end_effector_state."""
        p, R, w, v_WR = self.racket_state(q, v)
        out = np.empty(p.shape[:-1] + (13,))
        _end_effector_rows(p.reshape(-1, 3), R.reshape(-1, 3, 3), w.reshape(-1, 3), v_WR.reshape(-1, 3), out.reshape(-1, 13))
        return out

    def _evaluate(self, q: np.ndarray, v: np.ndarray | None):
        """(p_WR, R_WR, w_WR, v_WR) over q's leading dimensions; the twist None without v."""
        batch = q.shape[:-1]
        samples = math.prod(batch)
        p, R = np.empty(batch + (3,)), np.empty(batch + (3, 3))
        w, v_WR = (np.empty(batch + (3,)), np.empty(batch + (3,))) if v is not None else (p, p)  # p: unused placeholders
        _racket_chain_rows(
            q.reshape(samples, CHAIN_JOINTS), (q if v is None else v).reshape(samples, CHAIN_JOINTS), v is not None,
            self._terms, self._revolute, self._axes, self._origins, self._position_index, self._velocity_index,
            p.reshape(samples, 3), R.reshape(samples, 3, 3), w.reshape(samples, 3), v_WR.reshape(samples, 3),
        )
        if v is None:
            return p, R, None, None
        return p, R, w, v_WR


def _as_4x4(terms: np.ndarray) -> np.ndarray:
    """(3, 4, 4) from KinematicTree's (3, 3, 4) terms: bottom row [0, 0, 0, 1] for B0, zero for
    B1 and B2 (so that X_PC = B0 + c1 B1 + c2 B2 holds as 4 x 4 matrices)."""
    out = np.zeros((3, 4, 4))
    out[:, :3, :] = terms
    out[0, 3, 3] = 1.0
    return out


def _joint_array(value, name: str) -> np.ndarray:
    """value as a float array (..., 8), or a ValueError naming it and its shape."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0 or array.shape[-1] != CHAIN_JOINTS:
        raise ValueError(f"RacketKinematics: {name} must have shape (..., {CHAIN_JOINTS}) ({', '.join(JOINT_NAMES)}), got shape {array.shape}")
    return array


@numba.njit(cache=True)
def _racket_chain_rows(q, v, with_velocity, terms, revolute, axes, origins, position_index, velocity_index, p_out, R_out, w_out, v_out):
    """``_racket_chain`` of samples q, v (S, 8), one per row: their columns copied contiguously
    first (as the chain's loops read them), in one compiled call."""
    _racket_chain(np.ascontiguousarray(q.T), np.ascontiguousarray(v.T), with_velocity, terms, revolute, axes, origins, position_index,
                  velocity_index, p_out, R_out, w_out, v_out)


@numba.njit(cache=True)
def _racket_chain(q, v, with_velocity, terms, revolute, axes, origins, position_index, velocity_index, p_out, R_out, w_out, v_out):
    """The racket chain (module doc) at samples q (8, S) (one per column), in place: p_out (S, 3),
    R_out (S, 3, 3) and, with_velocity, w_out, v_out (S, 3) from v (8, S). Works on blocks of
    samples with the samples innermost (poses as 12 rows of [R | p] entries, as
    ``robot.bounds``), which the compiler vectorises."""
    samples = q.shape[1]
    block = max(1, min(_BLOCK, samples))  # compose_pose works on whole blocks
    X = np.zeros((12, block))
    X_next = np.zeros((12, block))
    local = np.zeros((12, block))
    c1, c2 = np.zeros(block), np.zeros(block)
    w, u = np.zeros((3, block)), np.zeros((3, block))
    for start in range(0, samples, block):
        count = min(block, samples - start)
        X[:] = 0.0
        X[0, :] = 1.0
        X[5, :] = 1.0
        X[10, :] = 1.0
        w[:] = 0.0
        u[:] = 0.0
        for j in range(terms.shape[0]):
            angles = q[position_index[j]]
            if revolute[j]:
                for s in range(count):
                    sine, cosine = sin_cos(angles[start + s])
                    c1[s], c2[s] = sine, 1.0 - cosine
            else:
                for s in range(count):
                    c1[s], c2[s] = angles[start + s], 0.0
            if with_velocity:
                ax, ay, az = axes[j, 0], axes[j, 1], axes[j, 2]
                ox, oy, oz = origins[j, 0], origins[j, 1], origins[j, 2]
                rates = v[velocity_index[j]]
                if revolute[j]:
                    for s in range(count):
                        qdot = rates[start + s]
                        # The axis in world (R_W,prev a) and a point on it (X_W,prev o).
                        a0 = X[0, s] * ax + X[1, s] * ay + X[2, s] * az
                        a1 = X[4, s] * ax + X[5, s] * ay + X[6, s] * az
                        a2 = X[8, s] * ax + X[9, s] * ay + X[10, s] * az
                        o0 = X[0, s] * ox + X[1, s] * oy + X[2, s] * oz + X[3, s]
                        o1 = X[4, s] * ox + X[5, s] * oy + X[6, s] * oz + X[7, s]
                        o2 = X[8, s] * ox + X[9, s] * oy + X[10, s] * oz + X[11, s]
                        w[0, s] += qdot * a0
                        w[1, s] += qdot * a1
                        w[2, s] += qdot * a2
                        u[0, s] -= qdot * (a1 * o2 - a2 * o1)
                        u[1, s] -= qdot * (a2 * o0 - a0 * o2)
                        u[2, s] -= qdot * (a0 * o1 - a1 * o0)
                else:
                    for s in range(count):
                        qdot = rates[start + s]
                        u[0, s] += qdot * (X[0, s] * ax + X[1, s] * ay + X[2, s] * az)
                        u[1, s] += qdot * (X[4, s] * ax + X[5, s] * ay + X[6, s] * az)
                        u[2, s] += qdot * (X[8, s] * ax + X[9, s] * ay + X[10, s] * az)
            for e in range(12):
                B0, B1, B2 = terms[j, 0, e], terms[j, 1, e], terms[j, 2, e]
                for s in range(count):
                    local[e, s] = B0 + c1[s] * B1 + c2[s] * B2
            compose_pose(X, local, X_next)
            X, X_next = X_next, X
        for s in range(count):
            for r in range(3):
                p_out[start + s, r] = X[4 * r + 3, s]
                for c in range(3):
                    R_out[start + s, r, c] = X[4 * r + c, s]
        if with_velocity:
            for s in range(count):
                px, py, pz = X[3, s], X[7, s], X[11, s]
                w_out[start + s, 0], w_out[start + s, 1], w_out[start + s, 2] = w[0, s], w[1, s], w[2, s]
                v_out[start + s, 0] = w[1, s] * pz - w[2, s] * py + u[0, s]
                v_out[start + s, 1] = w[2, s] * px - w[0, s] * pz + u[1, s]
                v_out[start + s, 2] = w[0, s] * py - w[1, s] * px + u[2, s]


@numba.njit(cache=True)
def _quaternion_one(M):
    """The unit quaternion (w, x, y, z) of a rotation matrix M (3, 3) as Drake's
    RotationMatrix::ToQuaternion computes it: from the largest of the trace and the diagonal
    entries, then the canonical sign w >= 0."""
    trace = M[0, 0] + M[1, 1] + M[2, 2]
    if trace >= M[0, 0] and trace >= M[1, 1] and trace >= M[2, 2]:
        qw, qx, qy, qz = 1.0 + trace, M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]
    elif M[0, 0] >= M[1, 1] and M[0, 0] >= M[2, 2]:
        qw, qx, qy, qz = M[2, 1] - M[1, 2], 1.0 - (trace - 2.0 * M[0, 0]), M[0, 1] + M[1, 0], M[0, 2] + M[2, 0]
    elif M[1, 1] >= M[2, 2]:
        qw, qx, qy, qz = M[0, 2] - M[2, 0], M[0, 1] + M[1, 0], 1.0 - (trace - 2.0 * M[1, 1]), M[1, 2] + M[2, 1]
    else:
        qw, qx, qy, qz = M[1, 0] - M[0, 1], M[0, 2] + M[2, 0], M[1, 2] + M[2, 1], 1.0 - (trace - 2.0 * M[2, 2])
    scale = (-1.0 if qw < 0.0 else 1.0) / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw * scale, qx * scale, qy * scale, qz * scale


@numba.njit(cache=True)
def _end_effector_rows(p, R, w, v, out):
    """out (S, 13) = [p (3), the quaternion of R (4; ``_quaternion_one``), v (3), w (3)] of each of
    the S racket states p, w, v (S, 3), R (S, 3, 3)."""
    for s in range(p.shape[0]):
        out[s, 3], out[s, 4], out[s, 5], out[s, 6] = _quaternion_one(R[s])
        for i in range(3):
            out[s, i], out[s, 7 + i], out[s, 10 + i] = p[s, i], v[s, i], w[s, i]
