"""SegmentResetMpc: the reset trajectories of B environments."""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.stack import ControlStack


class SegmentResetMpc(LeafSystem):
    """The continuous-time ``ResetMpc`` for B environments (paper, *Reset trajectories*;
    ``ControlStack.reset_batch``: Ruckig's time-optimal jerk-limited reset to the reset pose).

    Input ports:
        segment (abstract tuple of B Stage): the SegmentSplineQp's.
    Output ports:
        reset (abstract tuple of B Stage): a JointTrajectory at 1 kHz from each segment's end to
            the reset pose at rest when ok, else why not.
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack, batch: int):
        """Args: stack, the shared control stack; batch, B."""
        super().__init__()
        self.stack = stack
        self.batch = int(batch)
        self.segment_port = self.DeclareAbstractInputPort("segment", AbstractValue.Make(()))
        self.reset_port = self.DeclareAbstractOutputPort("reset", lambda: AbstractValue.Make(()), self.CalcReset)

    def CalcReset(self, context, output):
        output.set_value(tuple(self.stack.reset_batch(self.segment_port.Eval(context))))
