"""SegmentSplineQp: the segment QP for B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.stack import ControlStack
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE, split_start_state


class SegmentSplineQp(LeafSystem):
    """The continuous-time ``SplineQp`` for B environments (paper, *Optimization problem
    formulation*; ``ControlStack.segment_batch``: the jerk-minimising spline of every row as one
    linear map of its boundary conditions, DAQP only where a bound binds).

    Input ports:
        segment_start_state (abstract float (B, 24)): [q, v, a] where each segment starts.
        target (abstract tuple of B Stage): the SegmentActionMapper's.
    Output ports:
        segment (abstract tuple of B Stage): a JointTrajectory of 33 samples at 1 kHz from the
            start to the target when ok, else why not.
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack, batch: int):
        """Args: stack, the shared control stack; batch, B."""
        super().__init__()
        self.stack = stack
        self.batch = int(batch)
        self.segment_start_state_port = self.DeclareAbstractInputPort(
            "segment_start_state", AbstractValue.Make(np.zeros((self.batch, SEGMENT_START_STATE_SIZE)))
        )
        self.target_port = self.DeclareAbstractInputPort("target", AbstractValue.Make(()))
        self.segment_port = self.DeclareAbstractOutputPort("segment", lambda: AbstractValue.Make(()), self.CalcSegment)

    def CalcSegment(self, context, output):
        q, v, a = split_start_state(self.segment_start_state_port.Eval(context))
        output.set_value(tuple(self.stack.segment_batch(q, v, a, self.target_port.Eval(context))))
