"""SplineQp: the jerk-minimising spline segment to the mapped terminal state."""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.stack import ControlStack, Stage
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE, split_start_state


class SplineQp(LeafSystem):
    """The segment QP (paper, *Optimization problem formulation*; ``control.spline_qp``).

    Input ports:
        segment_start_state (24,): [q, v, a] where the segment starts.
        target (abstract Stage): the ActionMapper's (q_T, v_T).
    Output ports:
        segment (abstract Stage): value a JointTrajectory of 33 samples at 1 kHz from the start to
            the target when ok; otherwise why not (no target, or the QP failed).
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack):
        """Args: stack, the shared control stack (its QP is built once)."""
        super().__init__()
        self.stack = stack
        self.segment_start_state_port = self.DeclareVectorInputPort("segment_start_state", SEGMENT_START_STATE_SIZE)
        self.target_port = self.DeclareAbstractInputPort("target", AbstractValue.Make(Stage(False)))
        self.segment_port = self.DeclareAbstractOutputPort("segment", lambda: AbstractValue.Make(Stage(False)), self.CalcSegment)

    def CalcSegment(self, context, output):
        target = self.target_port.Eval(context)
        if not target.ok:
            output.set_value(Stage(False, reason=target.reason))
            return
        q, v, a = split_start_state(self.segment_start_state_port.Eval(context))
        output.set_value(self.stack.segment(q, v, a, target.value))
