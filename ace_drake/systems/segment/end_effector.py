"""SegmentEndEffector: the racket frame's state at given joint states, for B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.contracts import END_EFFECTOR_SIZE
from ace_drake.robot.kinematics import RacketKinematics
from ace_drake.robot.params import JOINT_NAMES


class SegmentEndEffector(LeafSystem):
    """What the policy observes of the end effector (the racket frame) at B joint states:
    [p_WR (m), quaternion wxyz, v_WR (m/s), w_WR (rad/s)], as the continuous-time
    ``RobotKinematics``' end_effector_state.

    Input ports:
        joint_state (abstract float (B, >= 16)): [q (8), v (8), ...] (e.g. the supervisor's
            segment_start_state [q, v, a]; what follows v is ignored).
    Output ports:
        end_effector_state (abstract float (B, 13)).
    State: none (direct feedthrough).
    """

    def __init__(self, kinematics: RacketKinematics, batch: int):
        """Args: kinematics, the robot's vectorised racket kinematics; batch, B."""
        super().__init__()
        self.kinematics = kinematics
        self.batch = int(batch)
        self.joint_state_port = self.DeclareAbstractInputPort("joint_state", AbstractValue.Make(np.zeros((self.batch, 3 * len(JOINT_NAMES)))))
        self.end_effector_state_port = self.DeclareAbstractOutputPort(
            "end_effector_state", lambda: AbstractValue.Make(np.zeros((self.batch, END_EFFECTOR_SIZE))), self.CalcEndEffectorState
        )

    def CalcEndEffectorState(self, context, output):
        state = self.joint_state_port.Eval(context)
        n = len(JOINT_NAMES)
        output.set_value(self.kinematics.end_effector_state(state[:, :n], state[:, n : 2 * n]))
