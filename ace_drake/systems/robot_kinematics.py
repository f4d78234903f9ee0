"""RobotKinematics: racket and end-effector pose and twist from the joints' state."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import LeafSystem

from ace_drake.robot.model import RACKET_FRAME, ROBOT_MODEL_NAME
from ace_drake.robot.params import JOINT_NAMES

END_EFFECTOR_STATE_SIZE = 13


class RobotKinematics(LeafSystem):
    """Forward kinematics of the robot's MultibodyPlant (kinematics only: nothing is simulated).

    Input ports:
        joint_state (16,): [q (8; m, rad), v (8; m/s, rad/s)] in JOINT_NAMES order.
    Output ports:
        racket_pose (abstract RigidTransform): X_WR, the racket frame R in world; R's origin is the
            blade centre and its z axis the forehand normal (models/ace_robot.sdf). The BallPlant's
            racket input.
        racket_spatial_velocity (abstract SpatialVelocity): V_WR, [w (rad/s), v (m/s)] of R's
            origin in world. The BallPlant's racket input.
        end_effector_state (13,): what the policy observes of the end effector (the racket frame):
            [p_WR (3; m), quaternion of R_WR (4; w, x, y, z), v_WR (3; m/s), w_WR (3; rad/s)].
    State: none. All outputs are direct feedthrough of joint_state.

    The plant must be finalized and have the robot's positions in JOINT_NAMES order
    (``robot.model.check_joint_order``). The system keeps a private plant context as scratch space
    for the kinematics; it holds nothing between evaluations (every output sets it from the input).
    """

    def __init__(self, plant: MultibodyPlant):
        """Args: plant, the finalized robot (and court) plant, e.g. from diagrams.add_robot."""
        super().__init__()
        if not plant.is_finalized():
            raise ValueError("RobotKinematics: the plant must be finalized")
        self.plant = plant
        self._plant_context = plant.CreateDefaultContext()
        robot = plant.GetModelInstanceByName(ROBOT_MODEL_NAME)
        self._racket_frame = plant.GetFrameByName(RACKET_FRAME, robot)
        joint_count = len(JOINT_NAMES)
        self.joint_state_port = self.DeclareVectorInputPort("joint_state", 2 * joint_count)
        self.racket_pose_port = self.DeclareAbstractOutputPort(
            "racket_pose", lambda: AbstractValue.Make(RigidTransform()), self.CalcRacketPose
        )
        self.racket_velocity_port = self.DeclareAbstractOutputPort(
            "racket_spatial_velocity", lambda: AbstractValue.Make(SpatialVelocity()), self.CalcRacketSpatialVelocity
        )
        self.end_effector_state_port = self.DeclareVectorOutputPort(
            "end_effector_state", END_EFFECTOR_STATE_SIZE, self.CalcEndEffectorState
        )

    def _set_joint_state(self, context) -> None:
        self.plant.SetPositionsAndVelocities(self._plant_context, self.joint_state_port.Eval(context))

    def CalcRacketPose(self, context, output) -> None:
        self._set_joint_state(context)
        output.set_value(self._racket_frame.CalcPoseInWorld(self._plant_context))

    def CalcRacketSpatialVelocity(self, context, output) -> None:
        self._set_joint_state(context)
        output.set_value(self._racket_frame.CalcSpatialVelocityInWorld(self._plant_context))

    def CalcEndEffectorState(self, context, output) -> None:
        self._set_joint_state(context)
        X_WR = self._racket_frame.CalcPoseInWorld(self._plant_context)
        V_WR = self._racket_frame.CalcSpatialVelocityInWorld(self._plant_context)
        quaternion = X_WR.rotation().ToQuaternion()
        output.SetFromVector(
            np.concatenate([X_WR.translation(), quaternion.wxyz(), V_WR.translational(), V_WR.rotational()])
        )
