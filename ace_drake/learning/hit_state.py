"""The learner's side of the hit-state actor (``control.hit_state``; docs/training.md, *Hit-state
actor*): the racket's forward kinematics in torch and the cloning loss on hit states.

**Kinematics.** Drake computes the racket pose for one configuration at a time and does not give torch gradients;
the cloning loss needs the racket pose and velocity of a whole batch of hit states, and their
gradients. ``RacketKinematics`` reads the chain once from ``RobotModel``'s plant (world to the
racket's body: the base weld, the gantry's prismatic joints, the arm's revolute joints) and then
composes, for each joint, the fixed pose of its frame on the parent, its motion (a rotation
about the axis by q, or a translation along it by q) and the inverse of the fixed pose of its
frame on the child, then the racket frame's pose in its body. The racket's linear velocity is
the directional derivative J(q) v of its position (``torch.func.jvp``). Matched against
``RobotModel.racket_pose`` and ``racket_spatial_velocity`` by the tests.

**The cloning loss** (``HitStateCloning``) compares the actor's hit state y with the returner's
y_label (its planned hit's (q_hit, v_hit), ``control.hit_state.HitStateAction.coordinates``)
where it matters, per row, with D = k T the time from the segment start to the hit's boundary
(``control.hit_state.steps_to_hit``) and A the acceleration limits:

    task        = |p - p_l|^2 / s_p^2 + |n - n_l|^2 / s_n^2 + |u - u_l|^2 / s_u^2
                  (blade centre p, forehand normal n and blade velocity u = J(q) v of the two
                  hit states: what the contact model, eqs (7)-(8), reads)
    joint       = |y - y_label|^2      (the redundant directions the racket does not fix)
    consistency = |c(y) - c(y_label)|^2,  c = [12 (q - q0 - v0 D) / (A D^2), 4 (v - v0) / (A D)]
                  (the hit state as a deviation from coasting on at v0, in units of what the
                  acceleration limit allows in the time left; the label's clipped to [-2, 2])
    loss        = mean(task + joint + consistency_weight consistency)

The consistency term is what makes the target hold still between calls near the hit, where an
error in q_hit costs acceleration as 1 / D^2; measured in docs/experiments/2026-12-01-hit-state-actor.md.
"""

from __future__ import annotations

import numpy as np
import torch

from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.hit_state import HitStateAction, steps_to_hit
from ace_drake.control.params import RallyParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.model import RobotModel, load_scenario


def _rotation_about(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) about a unit ``axis`` (3,) by ``angle`` (...,) (Rodrigues)."""
    k = torch.zeros(3, 3, dtype=axis.dtype)
    k[0, 1], k[0, 2], k[1, 0], k[1, 2], k[2, 0], k[2, 1] = -axis[2], axis[1], axis[2], -axis[0], -axis[1], axis[0]
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=axis.dtype) + s * k + (1.0 - c) * (k @ k)


class RacketKinematics:
    """X_WR(q) for batches of joint vectors q (..., 8) (JOINT_NAMES order): ``pose(q)`` gives the
    blade centre p (..., 3; m) and orientation R (..., 3, 3), whose third column is the forehand
    normal; ``pose_and_velocity(q, v)`` adds the blade centre's velocity (..., 3; m/s)."""

    def __init__(self, model: RobotModel, dtype=torch.float32):
        plant, context = model.plant, model.plant_context
        by_child = {plant.get_joint(index).child_body().index(): plant.get_joint(index) for index in plant.GetJointIndices()}
        chain, body = [], model.racket_frame.body()
        while body.index() != plant.world_body().index():
            joint = by_child[body.index()]
            chain.append(joint)
            body = joint.parent_body()
        self.dtype = dtype
        self._steps = []  # per joint from the world: (R_PF, p_PF, kind, axis, q index, R_MC, p_MC)
        for joint in reversed(chain):
            X_PF = joint.frame_on_parent().CalcPoseInBodyFrame(context)
            kind = joint.type_name()
            if kind == "weld":
                X_PF = X_PF.multiply(joint.X_FM())  # a weld's motion is its fixed X_FM
                axis, index = None, None
            elif kind in ("revolute", "prismatic"):
                axis = torch.as_tensor(np.asarray(joint.revolute_axis() if kind == "revolute" else joint.translation_axis(), dtype=float), dtype=dtype)
                index = joint.position_start()  # the plant's q is the robot's, in JOINT_NAMES order (RobotModel._set)
            else:
                raise ValueError(f"RacketKinematics: the chain has a {kind} joint ({joint.name()}); only welds, revolute and prismatic joints are handled")
            X_MC = joint.frame_on_child().CalcPoseInBodyFrame(context).inverse()
            self._steps.append((*self._tensors(X_PF), kind, axis, index, *self._tensors(X_MC)))
        self._R_BR, self._p_BR = self._tensors(model.racket_frame.CalcPoseInBodyFrame(context))

    def _tensors(self, transform) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.as_tensor(transform.rotation().matrix(), dtype=self.dtype),
                torch.as_tensor(np.array(transform.translation()), dtype=self.dtype))

    def pose(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(p_WR (..., 3), R_WR (..., 3, 3)) of joint vectors q (..., 8)."""
        R = torch.eye(3, dtype=q.dtype).expand(*q.shape[:-1], 3, 3)
        p = torch.zeros(*q.shape[:-1], 3, dtype=q.dtype)
        for R_PF, p_PF, kind, axis, index, R_MC, p_MC in self._steps:
            p, R = p + (R @ p_PF[:, None])[..., 0], R @ R_PF
            if kind == "revolute":
                R = R @ _rotation_about(axis, q[..., index])
            elif kind == "prismatic":
                p = p + (R @ axis[:, None])[..., 0] * q[..., index, None]
            p, R = p + (R @ p_MC[:, None])[..., 0], R @ R_MC
        return p + (R @ self._p_BR[:, None])[..., 0], R @ self._R_BR

    def pose_and_velocity(self, q: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(p_WR, R_WR, the blade centre's velocity J(q) v (..., 3; m/s)) of (q, v) (..., 8 each)."""
        (p, R), (velocity, _) = torch.func.jvp(self.pose, (q,), (v,))
        return p, R, velocity


class HitStateCloning:
    """The cloning loss of the module docstring for the rally diagram of ``rally`` (its scenario,
    command limits and timing) and observation ``layout``. ``scales`` (s_p m, s_n, s_u m/s)."""

    def __init__(self, rally: RallyParams, layout: ObservationLayout, scales: tuple[float, float, float], consistency_weight: float):
        scenario = load_scenario(MODELS_DIR / rally.scenario)
        limits = CommandLimits.from_config(scenario.limits, rally.control)
        predictor = HitPredictor.for_robot(scenario, rally.control, rally.physics)
        self.parameterisation = HitStateAction.from_limits(limits)
        self.kinematics = RacketKinematics(RobotModel(scenario))
        self.lead, self.lag, self.segment = predictor.lead, predictor.lag, predictor.segment
        self.acceleration = torch.as_tensor(limits.acceleration, dtype=torch.float32)
        self.scales = torch.as_tensor(scales, dtype=torch.float32)
        self.consistency_weight = float(consistency_weight)
        self._robot, self._hit = layout.slice("robot_state"), layout.slice("hit_prediction")

    def coasting(self, y: torch.Tensor, q0: torch.Tensor, v0: torch.Tensor, duration: torch.Tensor) -> torch.Tensor:
        """c(y) (B, 16) of the module docstring, for hit-time boundaries ``duration`` (B, 1) s ahead."""
        q, v = self.parameterisation.hit_state(y, q0)
        a = self.acceleration
        return torch.cat([12.0 * (q - q0 - v0 * duration) / (a * duration**2), 4.0 * (v - v0) / (a * duration)], dim=-1)

    def loss(self, obs: torch.Tensor, y: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
        """The mean loss over rows of full observations ``obs`` (B, layout.size), actor outputs
        ``y`` (B, 16) and labels (B, 16)."""
        robot = obs[:, self._robot]
        q0, v0 = robot[:, :8], robot[:, 8:16]
        hit_time = obs[:, self._hit][:, 1:2]
        steps = torch.clamp(steps_to_hit(hit_time, self.lead, self.lag, self.segment), min=1.0)
        duration = steps * self.segment
        q, v = self.parameterisation.hit_state(y, q0)
        p, R, u = self.kinematics.pose_and_velocity(q, v)
        with torch.no_grad():
            q_l, v_l = self.parameterisation.hit_state(label, q0)
            p_l, R_l, u_l = self.kinematics.pose_and_velocity(q_l, v_l)
            c_l = torch.clamp(self.coasting(label, q0, v0, duration), -2.0, 2.0)
        s_p, s_n, s_u = self.scales
        task = (((p - p_l) / s_p) ** 2).sum(-1) + (((R[..., :, 2] - R_l[..., :, 2]) / s_n) ** 2).sum(-1) + (((u - u_l) / s_u) ** 2).sum(-1)
        joint = ((y - label) ** 2).sum(-1)
        consistency = ((self.coasting(y, q0, v0, duration) - c_l) ** 2).sum(-1)
        return torch.mean(task + joint + self.consistency_weight * consistency)
