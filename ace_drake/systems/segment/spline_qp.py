"""SegmentSplineQp: the segment QP for B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.stack import ControlStack, Stage
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE


class SegmentSplineQp(LeafSystem):
    """The continuous-time ``SplineQp`` for B environments (paper, *Optimization problem
    formulation*; ``ControlStack.segment``).

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
        targets = self.target_port.Eval(context)
        stages = [Stage(False, reason=target.reason) if not target.ok else None for target in targets]
        if any(stage is None for stage in stages):
            start = self.segment_start_state_port.Eval(context)
            for row, target in enumerate(targets):
                if target.ok:
                    q, v, a = np.split(start[row], 3)
                    stages[row] = self.stack.segment(q, v, a, target.value)
        output.set_value(tuple(stages))
