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
  omega_y, which is invariant (``rewards`` docstring; tested there): rewards are kept.

Joints (``JointMirror``). Each joint maps by an affine map q -> s q + c (rates and accelerations by
s), an involution (s = -1, or s = 1 with c = 0). The signs come from the joint axes at q = 0: a
revolute joint about an axis in the plane (x, z) has its angle negated (M R_n(phi) M = R_n(-phi)),
about y kept (M R_y M = R_y); a prismatic joint along y is negated, along x or z kept. The offset
c of the (first) prismatic joint along y is the one that mirrors the racket frame at q = 0 onto
itself: c = -2 y_R(0), the racket's y there (for a joint whose zero is y0 off the plane with the
arm on its axis, -2 y0). ``JointMirror.fk_error`` measures what is left by forward kinematics.

The shipped robot (models/ace_robot.sdf) is mirror-symmetric. Its arm stands 0.15 m to the +y of
the column, and the shoulder_yaw axis passes through the arm's shoulder_pitch pivot, so the arm
(shoulder, links, racket, cup) is its own mirror image across the vertical plane through that
axis: with c = -2 x 0.15 = -0.3 m (the racket at q = 0 is 0.15 m off the plane) the mirrored joint
state puts every arm link at the mirrored pose, exactly (``fk_error``: round-off). The rest is
symmetric about the world's XZ plane: the base on y = 0, the rails at y = +-1.55, the beam
centred, the table and net. gantry_y's limits [-1.3, 1.0] (command limits [-1.28, 0.98]) are
symmetric about c / 2 = -0.15, every other mirrored joint's about 0 (below). One part is not: the
column stands 0.15 m on the arm's -y side, in the mirrored world it would stand on its +y side.
Collisions of the arm with the column (an arm yawed towards -y and pitched down over it, far from
any rally plan) do not mirror.

An arm whose pitch pivot sits b off the yaw axis (this robot before 2026-12-06: the yaw axis on the
column, the pivot 0.15 m along the shoulder's +y) is not mirror-symmetric under any per-joint
map. The pivot turns with the yaw psi, and the mirrored joint state (q_y -> -q_y + c, psi -> -psi)
leaves the racket off its mirror by the constant-orientation translation

    e(psi) = (2 b sin psi, -2 b (1 - cos psi), 0),    |e| = 4 b |sin(psi / 2)|

(zero at psi = 0 only). The exact mirror moves the gantry with the yaw, (q_x, q_y, psi) ->
(q_x - 2b sin psi, -q_y - 2b cos psi, -psi): it couples three joints (their velocities too, by
2b psi_dot, beyond the gantry's limits for a fast yaw), so it does not commute with eq. (12)'s
per-joint mapping. ``from_robot`` refuses such a robot (``tests/test_mirror.py``).

Joint limits. A mirrored joint's position limits must map onto themselves, [s l + c, s u + c] =
[l, u], i.e. l + u = c for s = -1: limits symmetric about c / 2 (``JointMirror.limit_mismatch``).

Actions (eq. (12)). The action of a joint is its terminal (q, v) relative to the joint's feasible
set (``control.feasible_set``, ``control.action_mapping``), built from the start state (q0, v0, a0)
and the limits. Claim: for a joint with s = -1 whose limits satisfy l + u = c, negating its two
action components is exact, whatever c. Proof: let R(q, v, a) = (c - q, -v, -a), the point
reflection of the joint's state about (c / 2, 0, 0). The construction depends on positions only
through the distances to the limits, u - q1 and q1 - l (the reachable bounds are q1 plus terms in
the velocities; the invariant bounds are the limits less velocity pads; intersections take min and
max), and it computes its two sides by one formula, the lower side as the upper side of the
problem reflected by q -> -q, v -> -v (``_SIDES``). The mirrored start R(q0, v0, a0) has
u - q1' = (c - l) - (c - q1) = q1 - l and negated velocities: its upper side is the original's
lower side reflected, and vice versa. So F' = R(F): centre y_bar' = R(y_bar), the same half-widths
(scale), and the boundary point on the ray from y_bar' along f(-delta) = -f(delta) is the image
by R (whose linear part is -I) of the one on the ray from y_bar along f(delta): the same beta.
Hence map(-delta; F') = R(map(delta; F)): negation, with no offset term. (With c = 0 this is the
previous argument; the offset only moves the centre of the reflection.) When l + u != c the
mirrored start's set is R of the set built with the limits [c - u, c - l] instead: the action
mirror is still exact wherever neither limit shapes either set (far from both ends), and wrong
near them; ``Mirror.action_exact`` tells which.

Hit-state actions (``control.hit_state``: y_q = (q_hit - q0) / half-range, y_v = v_hit / v_max per
joint) are relative to the segment start q0, so the offset cancels: y_q' = ((s q_hit + c) -
(s q0 + c)) / h = s y_q, and the half-range (u - l) / 2 and v_max do not change under any
reflection: negation by the same signs is exact for every c and every limits (a mirrored q_hit may
fall outside asymmetric limits, where the layer clips it).

Observations. The actor's robot_state [q, v, a] and the critic's joint_state [q, v] map by the
joint map (q affinely, with c); the end-effector state, ball histories, estimate and predicted hit
by their vector kinds; on the shipped robot the end-effector state of the mirrored joint state is
the mirrored end-effector state.

Layouts: ``contracts.ObservationLayout`` (actor) and ``contracts.PRIVILEGED_PARTS`` (critic).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ace_drake.contracts import HISTORY_COLUMNS, PRIVILEGED_PARTS, ObservationLayout, privileged_slice
from ace_drake.control.feasible_set import feasible_sets_batch
from ace_drake.robot.model import RobotModel
from ace_drake.robot.params import JOINT_NAMES

POLAR = np.array([1.0, -1.0, 1.0])  # M: positions, velocities
AXIAL = np.array([-1.0, 1.0, -1.0])  # -M: angular velocities, spins
QUATERNION_WXYZ = np.array([1.0, -1.0, 1.0, -1.0])
MIRROR = np.diag(POLAR)
QUATERNION_HALF_TURN = 1e-12  # |w| below which a quaternion is a half turn (Mirror.observation)
BALL_STATE = np.r_[POLAR, POLAR, AXIAL]  # [p, v, w]
PRIVILEGED_SIZE = sum(PRIVILEGED_PARTS.values())


@dataclasses.dataclass(frozen=True)
class JointMirror:
    """q' = signs * q + offsets, v' = signs * v, a' = signs * a, per joint (8,) in JOINT_NAMES
    order (module docstring, *Joints*). An involution: an offset only where the sign is -1."""

    signs: np.ndarray
    offsets: np.ndarray

    def __post_init__(self) -> None:
        signs, offsets = np.asarray(self.signs, dtype=float), np.asarray(self.offsets, dtype=float)
        if signs.shape != (len(JOINT_NAMES),) or offsets.shape != signs.shape or not np.all(np.abs(signs) == 1.0):
            raise ValueError(f"JointMirror: expected {len(JOINT_NAMES)} signs of +-1 and as many offsets, got {signs}, {offsets}")
        if np.any((signs > 0.0) & (offsets != 0.0)):
            raise ValueError(f"JointMirror: an offset on a kept joint (sign +1) is a shift, not a mirror: signs {signs}, offsets {offsets}")

    def positions(self, q):
        return self.signs * np.asarray(q) + self.offsets

    def rates(self, v):
        return self.signs * np.asarray(v)

    @staticmethod
    def from_model(model) -> "JointMirror":
        """The rule of the module docstring applied to each joint of a ``robot.model.RobotModel``
        at q = 0: signs from the axes, and the first prismatic joint along y offset so that the
        racket frame at q = 0 mirrors onto itself. Raises ValueError for a joint whose axis is
        neither in nor normal to the plane."""
        plant, context = model.plant, model.plant.CreateDefaultContext()
        plant.SetPositions(context, np.zeros(len(JOINT_NAMES)))
        signs, offsets = np.ones(len(JOINT_NAMES)), np.zeros(len(JOINT_NAMES))
        lateral = []  # the prismatic joints along y
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
                lateral.append((i, float(axis_W[1])))
        if lateral:
            # y_R(c) = y_R(0) + axis_y c: the racket at q = 0 maps onto its mirror for c = -2 y_R(0) / axis_y.
            i, axis_y = lateral[0]
            y_racket = float(model.racket_frame.CalcPoseInWorld(context).translation()[1])
            offsets[i] = -2.0 * y_racket / axis_y + 0.0  # + 0.0: no negative zero
        return JointMirror(signs, offsets)

    def racket_error(self, model, q) -> tuple[float, float]:
        """(position m, rotation rad): how far the racket pose of the mirrored q is from the mirror
        of the racket pose of q (M p, M R M)."""
        X = model.racket_pose(np.asarray(q, dtype=float))
        X_mirrored = model.racket_pose(self.positions(q))
        position = float(np.linalg.norm(X_mirrored.translation() - MIRROR @ X.translation()))
        R_expected = MIRROR @ X.rotation().matrix() @ MIRROR
        # The angle between two rotations from their chordal distance (accurate near zero).
        chord = np.linalg.norm(R_expected - X_mirrored.rotation().matrix()) / (2.0 * np.sqrt(2.0))
        return position, float(2.0 * np.arcsin(min(chord, 1.0)))

    def fk_error(self, model, samples: int = 50, seed: int = 0) -> tuple[float, float]:
        """(position m, rotation rad): the largest ``racket_error`` over ``samples`` random q
        within the limits. Both zero for an exact joint mirror."""
        rng = np.random.default_rng(seed)
        errors = np.array([self.racket_error(model, rng.uniform(model.lower, model.upper)) for _ in range(samples)])
        return float(errors[:, 0].max()), float(errors[:, 1].max())

    def limit_mismatch(self, lower, upper) -> np.ndarray:
        """Per joint, m or rad: how far the mirrored position interval [s l + c, s u + c] is from
        [l, u] (0 where the limits mirror onto themselves)."""
        ends = np.sort(np.stack([self.positions(lower), self.positions(upper)]), axis=0)
        return np.maximum(np.abs(ends[0] - lower), np.abs(ends[1] - upper))

    def within_limits(self, q, lower, upper, tolerance: float = 0.0) -> np.ndarray:
        """Whether the mirror of each joint state q (..., 8) lies within [lower, upper], (...) booleans."""
        mirrored = self.positions(q)
        return np.all((mirrored >= np.asarray(lower) - tolerance) & (mirrored <= np.asarray(upper) + tolerance), axis=-1)

    def mirrored_limits(self, lower, upper) -> tuple[np.ndarray, np.ndarray]:
        """The limits [c - u, c - l] (sign -1) or [l, u] (sign 1) whose feasible sets the mirrored
        starts' sets are the mirrors of (module docstring, *Actions*)."""
        ends = np.sort(np.stack([self.positions(lower), self.positions(upper)]), axis=0)
        return ends[0], ends[1]


class Mirror:
    """Maps observations, privileged observations, actions and transitions to their mirror images
    (module docstring). Rewards and done flags are kept. ``transitions`` can serve as an
    ``replay.EventReplay`` augmentation.

    Observations map affinely (the joint positions by q -> s q + c), actions by signs: the eq. (12)
    terminal action exactly where the negated joints' limits are symmetric about c / 2, the
    hit-state action always (module docstring). ``failures`` lists what ``from_robot`` found not
    mirror-symmetric (empty: exact)."""

    def __init__(self, joints: JointMirror, layout: ObservationLayout | None = None, failures: tuple[str, ...] = ()):
        self.joints = joints
        self.layout = layout or ObservationLayout()
        self.failures = tuple(failures)
        n = self.layout.size
        # The observation mirror is diagonal plus a shift (the joint offsets on q).
        sign, shift = np.ones(n), np.zeros(n)
        age = np.ones(HISTORY_COLUMNS - 3)  # history rows are [vector (3), age]
        sign[self.layout.slice("positions")] = np.tile(np.r_[POLAR, age], self.layout.position_history)
        sign[self.layout.slice("spins")] = np.tile(np.r_[AXIAL, age], self.layout.spin_history)
        sign[self.layout.slice("robot_state")] = np.tile(joints.signs, 3)  # [q, v, a]
        shift[self.layout.slice("robot_state").start + np.arange(len(JOINT_NAMES))] = joints.offsets
        sign[self.layout.slice("end_effector")] = np.r_[POLAR, QUATERNION_WXYZ, POLAR, AXIAL]
        sign[self.layout.slice("skill")] = [-1.0, 1.0, 1.0]
        sign[self.layout.slice("estimate")] = BALL_STATE
        sign[self.layout.slice("estimate_status")] = 1.0
        sign[self.layout.slice("hit_prediction")] = np.r_[1.0, 1.0, BALL_STATE]  # [valid, time, ball state]
        self.observation_sign, self.observation_shift = sign, shift
        privileged, privileged_shift = np.ones(PRIVILEGED_SIZE), np.zeros(PRIVILEGED_SIZE)
        privileged[privileged_slice("ball_state")] = BALL_STATE
        privileged[privileged_slice("joint_state")] = np.tile(joints.signs, 2)  # [q, v]
        privileged_shift[privileged_slice("joint_state").start + np.arange(len(JOINT_NAMES))] = joints.offsets
        privileged[privileged_slice("skill")] = [-1.0, 1.0, 1.0]
        self.privileged_sign, self.privileged_shift = privileged, privileged_shift
        # Rows: terminal positions, velocities (eq. (12)); or y_q, y_v (hit-state): the same signs.
        self.action_sign = np.tile(joints.signs, 2)

    @property
    def exact(self) -> bool:
        """Whether ``from_robot`` found the robot mirror-symmetric (no failures)."""
        return not self.failures

    @staticmethod
    def from_robot(model=None, layout: ObservationLayout | None = None, tolerance: float = 1e-9, exact: bool = True) -> "Mirror":
        """The mirror of a ``robot.model.RobotModel`` (default: the shipped robot), after checking
        the joint mirror by forward kinematics and the mirrored joints' position limits.
        ``exact``: raise ValueError naming the failures when the robot is not mirror-symmetric
        (then no per-joint mirror of its states and actions is exact); False returns the
        approximate mirror with them in ``failures``."""
        if model is None:
            model = RobotModel()
        joints = JointMirror.from_model(model)
        failures = []
        position_error, angle_error = joints.fk_error(model)
        if position_error > tolerance or angle_error > tolerance:
            failures.append(
                f"the robot is not symmetric about the XZ plane: the mirrored joint state's racket pose is up to "
                f"{position_error:.3g} m, {angle_error:.3g} rad from the mirrored racket pose (signs {joints.signs}, offsets {joints.offsets})"
            )
        mismatch = joints.limit_mismatch(model.lower, model.upper)
        if np.any(mismatch > tolerance):
            bad = {JOINT_NAMES[i]: round(float(mismatch[i]), 6) for i in np.flatnonzero(mismatch > tolerance)}
            failures.append(f"the position limits of {bad} (m or rad off) do not mirror onto themselves")
        if failures and exact:
            raise ValueError("Mirror: " + "; ".join(failures))
        return Mirror(joints, layout, tuple(failures))

    def observation(self, obs):
        """The mirrored actor observation(s) (..., layout.size). The end-effector quaternion keeps
        the builders' canonical sign (``robot.kinematics``, as Drake's ToQuaternion: w >= 0, and
        for w = 0, a half turn, the largest of x, y, z positive): [w, -x, y, -z] keeps w, and where
        |w| <= QUATERNION_HALF_TURN (a half turn up to round-off, whose w's sign is the round-off's)
        the result is negated if that makes its largest vector component positive (the ready
        pose's blade is such a half turn)."""
        obs = np.asarray(obs)
        mirrored = obs * self.observation_sign.astype(obs.dtype) + self.observation_shift.astype(obs.dtype)
        start = self.layout.slice("end_effector").start + 3
        quaternion = mirrored[..., start:start + 4]
        vector = quaternion[..., 1:]
        largest = np.take_along_axis(vector, np.argmax(np.abs(vector), axis=-1)[..., None], axis=-1)[..., 0]
        flip = (np.abs(quaternion[..., 0]) <= QUATERNION_HALF_TURN) & (largest < 0.0)
        if np.any(flip):
            mirrored[..., start:start + 4] = np.where(flip[..., None], -quaternion, quaternion)
        return mirrored

    def privileged(self, privileged):
        """The mirrored privileged observation(s) (..., 28)."""
        privileged = np.asarray(privileged)
        return privileged * self.privileged_sign.astype(privileged.dtype) + self.privileged_shift.astype(privileged.dtype)

    def action(self, action):
        """The mirrored action(s) (..., 16): eq. (12) terminal or hit-state actions (module
        docstring: exact for the former where the limits are symmetric about c / 2)."""
        action = np.asarray(action)
        return action * self.action_sign.astype(action.dtype)

    def transitions(self, transitions: dict) -> dict:
        """A mirrored copy of a transitions dict (``replay.TRANSITION_KEYS``, or the demonstration
        rows ``replay.DemonstrationBuffer.KEYS``): observations, privileged observations, actions
        and the demonstrator's labels ``demo_action`` (eq. (12) actions or hit-state coordinates,
        both mirrored by the action's signs) where present; rewards and the rest kept. Raises
        KeyError for a dict without ``obs`` and ``privileged`` (nothing of it would be mirrored)."""
        missing = [key for key in ("obs", "privileged") if key not in transitions]
        if missing:
            raise KeyError(f"Mirror.transitions: no {missing} to mirror (keys {sorted(transitions)})")
        out = dict(transitions)
        for key in ("obs", "next_obs"):
            if key in transitions:
                out[key] = self.observation(transitions[key])
        for key in ("privileged", "next_privileged"):
            if key in transitions:
                out[key] = self.privileged(transitions[key])
        for key in ("action", "demo_action"):
            if key in transitions:
                out[key] = self.action(transitions[key])
        return out

    def action_exact(self, q0, v0, a0, limits, control, period: float) -> np.ndarray:
        """Whether negating the eq. (12) action is exact from start states (q0, v0, a0) (..., 8)
        with ``limits`` (``control.trajectory.CommandLimits``): (...) booleans, true where every
        joint's feasible set is the same under the limits and under their mirror
        (``JointMirror.mirrored_limits``), so that the mirrored start's sets are the mirrors of
        these (module docstring, *Actions*). Starts outside the invariant set count as inexact."""
        lower, upper = self.joints.mirrored_limits(limits.lower, limits.upper)
        mirrored = dataclasses.replace(limits, lower=lower, upper=upper)
        sets, feasible, _ = feasible_sets_batch(q0, v0, a0, limits, control, period)
        sets_m, feasible_m, _ = feasible_sets_batch(q0, v0, a0, mirrored, control, period)
        same = np.all(np.isclose(sets.vertices, sets_m.vertices, rtol=0.0, atol=1e-12), axis=(-1, -2, -3))
        return feasible & feasible_m & same
