"""SegmentRacketKinematics: the racket's motion over a tick, for B environments."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.joint_model import JointMotion
from ace_drake.robot.kinematics import RacketKinematics
from ace_drake.robot.params import JOINT_NAMES


@dataclasses.dataclass(frozen=True)
class RacketMotion:
    """The racket over one tick for B environments (``physics.segment.RacketMotion``'s protocol):
    its state at the 1 kHz samples, ``times`` (n + 1,) s after the tick's first sample, p_WR
    (B, n + 1, 3) m, R_WR (B, n + 1, 3, 3), w_WR (rad/s) and v_WR (m/s) (B, n + 1, 3), and at
    any time between them (``state_at``) from the joints' exact solution."""

    kinematics: RacketKinematics
    joints: JointMotion
    times: np.ndarray
    p_WR: np.ndarray
    R_WR: np.ndarray
    w_WR: np.ndarray
    v_WR: np.ndarray

    @classmethod
    def of(cls, kinematics: RacketKinematics, joints: JointMotion) -> RacketMotion:
        """The racket driven by the joints' motion."""
        states = joints.states
        n = len(JOINT_NAMES)
        p, R, w, v = kinematics.racket_state(states[..., :n], states[..., n:])
        times = np.arange(states.shape[1]) * joints.propagator.period
        return cls(kinematics, joints, times, p, R, w, v)

    def state_at(self, env: np.ndarray, tau: np.ndarray):
        """(p (k, 3), R (k, 3, 3), w (k, 3), v (k, 3)) of environments ``env`` (k,) at times
        ``tau`` (k,) s after the tick's first sample."""
        states = self.joints.state_at(env, tau)
        n = len(JOINT_NAMES)
        return self.kinematics.racket_state(states[:, :n], states[:, n:])


class SegmentRacketKinematics(LeafSystem):
    """Forward kinematics of the racket over a tick for B environments (``robot.kinematics``):
    the BallPlant's racket, vectorised over the samples and environments.

    Input ports:
        joint_motion (abstract JointMotion): the SegmentJointPlant's.
    Output ports:
        racket_motion (abstract RacketMotion): the racket over the tick (direct feedthrough).
    State: none.
    """

    def __init__(self, kinematics: RacketKinematics):
        """Args: kinematics, the robot's vectorised racket kinematics."""
        super().__init__()
        self.kinematics = kinematics
        self.joint_motion_port = self.DeclareAbstractInputPort("joint_motion", AbstractValue.Make(None))
        self.racket_motion_port = self.DeclareAbstractOutputPort("racket_motion", lambda: AbstractValue.Make(None), self.CalcRacketMotion)

    def CalcRacketMotion(self, context, output):
        output.set_value(RacketMotion.of(self.kinematics, self.joint_motion_port.Eval(context)))
