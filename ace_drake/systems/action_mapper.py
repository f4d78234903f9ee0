"""ActionMapper: the policy's action onto a feasible terminal joint state (paper eq. (12))."""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.stack import NO_ACTION, ControlStack, Stage

SEGMENT_START_STATE_SIZE = 24  # [q, v, a] of the 8 joints where the next segment starts


def split_start_state(start):
    """The [q, v, a] parts (..., 8) of segment start states (..., 24) (rad or m, per s, per s^2),
    as views (read every tick: cheaper than numpy.split)."""
    joints = SEGMENT_START_STATE_SIZE // 3
    return start[..., :joints], start[..., joints : 2 * joints], start[..., 2 * joints :]


class ActionMapper(LeafSystem):
    """Maps the action onto the feasible set of terminal (q, v) 32 ms after the segment's start.

    Input ports:
        action (16,): in [-1, 1] (``control.action_mapping``).
        action_valid (1,): > 0.5 when ``action`` is to be executed.
        segment_start_state (24,): [q (8), v (8), a (8)] where the next segment starts (rad or m,
            per s, per s^2), from the SafetySupervisor.
    Output ports:
        target (abstract Stage): value (q_T (8,), v_T (8,)) when ok; otherwise the reason (no
            action, or a start outside the control-invariant set).
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack):
        """Args: stack, the shared control stack (limits, mapping parameters)."""
        super().__init__()
        self.stack = stack
        self.action_port = self.DeclareVectorInputPort("action", ACTION_SIZE)
        self.action_valid_port = self.DeclareVectorInputPort("action_valid", 1)
        self.segment_start_state_port = self.DeclareVectorInputPort("segment_start_state", SEGMENT_START_STATE_SIZE)
        self.target_port = self.DeclareAbstractOutputPort("target", lambda: AbstractValue.Make(Stage(False)), self.CalcTarget)

    def CalcTarget(self, context, output):
        if self.action_valid_port.Eval(context)[0] <= 0.5:
            output.set_value(Stage(False, reason=NO_ACTION))
            return
        q, v, a = split_start_state(self.segment_start_state_port.Eval(context))
        output.set_value(self.stack.map(q, v, a, self.action_port.Eval(context)))
