"""Mirror augmentation across the table's XZ plane, y -> -y (paper, Methods *Algorithm*, data
augmentation (1): "mirror all states, actions and rewards with respect to the XZ plane").

With M = diag(1, -1, 1):

- points and velocities (polar vectors) map by M: y flips;
- angular velocities (axial vectors, spins, the racket's w_WR) map by -M = det(M) M: x and z flip;
- rotations R map to M R M (a proper rotation: the mirrored frame's x and z axes are the mirrored
  x and z, its y the negated mirror of y, keeping it right-handed); for a quaternion
  [w, x, y, z] this is [w, -x, y, -z], since M R_n(phi) M = R_{-Mn}(phi) and -Mn is the axial
  rule again;
- the skill [y_desired, w_p, w_s] maps to [-y_desired, w_p, w_s]: the landing y mirrors with
  y_desired, so the position term is unchanged, and the spin term reads the travel-frame spin
  omega_y, which is invariant (``rewards`` docstring; tested there): rewards are kept;
- joints (``JointMirror``): a joint maps as q -> s q + c (rates by s), derived from its axis at
  q = 0 and checked by forward kinematics (``JointMirror.fk_error``). A revolute joint about an
  axis in the plane (x, z) has its angle negated (M R_n(phi) M = R_n(-phi)); about y it is kept
  (M R_y M = R_y). A prismatic joint along y is negated (offset -2 y0 for a joint whose zero is
  at y0 off the plane), along x or z kept. This is exact only if the robot at q = 0 is itself
  symmetric (every joint's origin, the racket frame, on the plane): ``fk_error`` measures it.
- actions: the action of a joint is its terminal (q, v) relative to the joint's feasible set
  (``control.action_mapping``, eq. (12)), which is built from the joint's start state and its
  limits. For a mirrored joint (s = -1, c = 0) with symmetric limits [-L, L] (and the velocity
  and acceleration bounds, which are symmetric by construction), the mirrored start state gives
  the point-reflected set F' = -F: centre -y_bar, the same half-widths, and the ray from -y_bar
  along -f(delta) meets the boundary at the same beta. So map(-delta; F') = -map(delta; F) and
  negating the joint's two action components is exact. ``Mirror`` checks that every negated
  joint's position limits mirror onto themselves ([s l + c, s u + c] = [l, u]) and refuses the
  robot otherwise. The hit-state action (``control.hit_state``: y_q = (q_hit - q0) / half-range,
  y_v = v_hit / v_max per joint) mirrors by the same signs: for a negated joint with zero offset
  both components negate, and the half-range and v_max of symmetric limits are unchanged.

Layouts: ``observation.ObservationLayout`` (actor) and ``rally_env.PRIVILEGED_PARTS`` (critic).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ace_drake.contracts import HISTORY_COLUMNS, ObservationLayout, privileged_slice
from ace_drake.robot.model import RobotModel
from ace_drake.robot.params import JOINT_NAMES

POLAR = np.array([1.0, -1.0, 1.0])  # M: positions, velocities
AXIAL = np.array([-1.0, 1.0, -1.0])  # -M: angular velocities, spins
QUATERNION_WXYZ = np.array([1.0, -1.0, 1.0, -1.0])
MIRROR = np.diag(POLAR)
BALL_STATE = np.r_[POLAR, POLAR, AXIAL]  # [p, v, w]


@dataclasses.dataclass(frozen=True)
class JointMirror:
    """q' = signs * q + offsets, v' = signs * v, a' = signs * a, per joint (8,) in JOINT_NAMES order."""

    signs: np.ndarray
    offsets: np.ndarray

    def positions(self, q):
        return self.signs * np.asarray(q) + self.offsets

    def rates(self, v):
        return self.signs * np.asarray(v)

    @staticmethod
    def from_model(model) -> "JointMirror":
        """The rule of the module docstring applied to each joint of a ``robot.model.RobotModel``
        at q = 0. Raises ValueError for a joint whose axis is neither in nor normal to the plane."""
        plant, context = model.plant, model.plant.CreateDefaultContext()
        plant.SetPositions(context, np.zeros(len(JOINT_NAMES)))
        signs, offsets = np.ones(len(JOINT_NAMES)), np.zeros(len(JOINT_NAMES))
        for i, name in enumerate(JOINT_NAMES):
            joint = plant.GetJointByName(name, model.robot)
            X_WF = joint.frame_on_parent().CalcPoseInWorld(context)
            prismatic = joint.type_name() == "prismatic"
            axis_F = joint.translation_axis() if prismatic else joint.revolute_axis()
            axis_W = X_WF.rotation().matrix() @ axis_F
            if np.allclose(MIRROR @ axis_W, axis_W, atol=1e-9):
                in_plane = True
            elif np.allclose(MIRROR @ axis_W, -axis_W, atol=1e-9):
                in_plane = False
            else:
                raise ValueError(f"JointMirror: joint {name}'s axis {axis_W} is neither in nor normal to the XZ plane")
            # Revolute: angle negated about an in-plane axis. Prismatic: negated along y.
            signs[i] = -1.0 if in_plane != prismatic else 1.0
            if prismatic and signs[i] < 0.0:
                offsets[i] = -2.0 * X_WF.translation()[1]
        return JointMirror(signs, offsets)

    def fk_error(self, model, samples: int = 50, seed: int = 0) -> tuple[float, float]:
        """(position m, rotation rad): the largest difference, over ``samples`` random q within
        the limits, between the racket pose of the mirrored q and the mirror of the racket pose
        of q (M p, M R M). Both zero for an exact joint mirror."""
        rng = np.random.default_rng(seed)
        worst_position = worst_angle = 0.0
        for _ in range(samples):
            q = rng.uniform(model.lower, model.upper)
            X = model.racket_pose(q)
            X_mirrored = model.racket_pose(self.positions(q))
            worst_position = max(worst_position, float(np.linalg.norm(X_mirrored.translation() - MIRROR @ X.translation())))
            R_expected = MIRROR @ X.rotation().matrix() @ MIRROR
            # The angle between two rotations from their chordal distance (accurate near zero).
            chord = np.linalg.norm(R_expected - X_mirrored.rotation().matrix()) / (2.0 * np.sqrt(2.0))
            worst_angle = max(worst_angle, float(2.0 * np.arcsin(min(chord, 1.0))))
        return worst_position, worst_angle

    def limit_mismatch(self, lower, upper) -> np.ndarray:
        """Per joint, m or rad: how far the mirrored position interval [s l + c, s u + c] is from
        [l, u] (0 where the limits mirror onto themselves)."""
        ends = np.sort(np.stack([self.positions(lower), self.positions(upper)]), axis=0)
        return np.maximum(np.abs(ends[0] - lower), np.abs(ends[1] - upper))


class Mirror:
    """Maps observations, privileged observations, actions and transitions to their mirror images
    (module docstring). Rewards and done flags are kept. ``transitions`` can serve as an
    ``replay.EventReplay`` augmentation."""

    def __init__(self, joints: JointMirror, layout: ObservationLayout | None = None):
        self.joints = joints
        self.layout = layout or ObservationLayout()
        if np.any(joints.offsets != 0.0):
            raise ValueError(f"Mirror: joint offsets {joints.offsets} would shift each joint's feasible set; "
                             "negating the action is exact only for zero offsets (module docstring)")
        n = self.layout.size
        # The observation mirror is diagonal: one sign per component, except the joint offsets (zero).
        sign = np.ones(n)
        age = np.ones(HISTORY_COLUMNS - 3)  # history rows are [vector (3), age]
        sign[self.layout.slice("positions")] = np.tile(np.r_[POLAR, age], self.layout.position_history)
        sign[self.layout.slice("spins")] = np.tile(np.r_[AXIAL, age], self.layout.spin_history)
        sign[self.layout.slice("robot_state")] = np.tile(joints.signs, 3)
        sign[self.layout.slice("end_effector")] = np.r_[POLAR, QUATERNION_WXYZ, POLAR, AXIAL]
        sign[self.layout.slice("skill")] = [-1.0, 1.0, 1.0]
        sign[self.layout.slice("estimate")] = BALL_STATE
        sign[self.layout.slice("estimate_status")] = 1.0
        sign[self.layout.slice("hit_prediction")] = np.r_[1.0, 1.0, BALL_STATE]  # [valid, time, ball state]
        self.observation_sign = sign
        privileged = np.ones(28)
        privileged[privileged_slice("ball_state")] = BALL_STATE
        privileged[privileged_slice("joint_state")] = np.tile(joints.signs, 2)
        privileged[privileged_slice("skill")] = [-1.0, 1.0, 1.0]
        self.privileged_sign = privileged
        self.action_sign = np.tile(joints.signs, 2)  # rows: terminal positions, velocities

    @staticmethod
    def from_robot(model=None, layout: ObservationLayout | None = None, tolerance: float = 1e-9) -> "Mirror":
        """The mirror of a ``robot.model.RobotModel`` (default: the shipped robot), after checking
        the joint mirror by forward kinematics and the mirrored joints' limits. Raises ValueError
        naming the failure when the robot is not mirror-symmetric (then no per-joint mirror of
        its states and actions is exact)."""
        if model is None:
            model = RobotModel()
        joints = JointMirror.from_model(model)
        position_error, angle_error = joints.fk_error(model)
        if position_error > tolerance or angle_error > tolerance:
            raise ValueError(
                f"Mirror: the robot is not symmetric about the XZ plane: the mirrored joint state's racket pose is "
                f"{position_error:.3g} m, {angle_error:.3g} rad from the mirrored racket pose (signs {joints.signs})"
            )
        mismatch = joints.limit_mismatch(model.lower, model.upper)
        if np.any(mismatch > tolerance):
            bad = [JOINT_NAMES[i] for i in np.flatnonzero(mismatch > tolerance)]
            raise ValueError(f"Mirror: the position limits of {bad} do not mirror onto themselves")
        return Mirror(joints, layout)

    def observation(self, obs):
        """The mirrored actor observation(s) (..., layout.size)."""
        return np.asarray(obs) * self.observation_sign.astype(np.asarray(obs).dtype)

    def privileged(self, privileged):
        """The mirrored privileged observation(s) (..., 28)."""
        return np.asarray(privileged) * self.privileged_sign.astype(np.asarray(privileged).dtype)

    def action(self, action):
        """The mirrored action(s) (..., 16) (module docstring: exact for symmetric limits)."""
        return np.asarray(action) * self.action_sign.astype(np.asarray(action).dtype)

    def transitions(self, transitions: dict) -> dict:
        """A mirrored copy of a transitions dict (``replay.TRANSITION_KEYS``); rewards kept."""
        out = dict(transitions)
        for key in ("obs", "next_obs"):
            out[key] = self.observation(transitions[key])
        for key in ("privileged", "next_privileged"):
            out[key] = self.privileged(transitions[key])
        out["action"] = self.action(transitions["action"])
        return out
