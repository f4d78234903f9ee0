"""SegmentActionMapper: eq. (12) for B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.stack import NO_ACTION, ControlStack, Stage
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE, split_start_state


class SegmentActionMapper(LeafSystem):
    """The continuous-time ``ActionMapper`` for B environments: maps each valid action onto the
    feasible set of terminal (q, v) 32 ms after its segment's start (paper eq. (12);
    ``ControlStack.map_batch``: every row's feasible sets at once).

    Input ports:
        action (abstract float (B, 17)): the SegmentPolicyController's [action, valid].
        segment_start_state (abstract float (B, 24)): [q, v, a] where each next segment starts.
    Output ports:
        target (abstract tuple of B Stage): (q_T, v_T) per environment when ok, else why not.
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack, batch: int):
        """Args: stack, the shared control stack; batch, B."""
        super().__init__()
        self.stack = stack
        self.batch = int(batch)
        self.action_port = self.DeclareAbstractInputPort("action", AbstractValue.Make(np.zeros((self.batch, ACTION_SIZE + 1))))
        self.segment_start_state_port = self.DeclareAbstractInputPort(
            "segment_start_state", AbstractValue.Make(np.zeros((self.batch, SEGMENT_START_STATE_SIZE)))
        )
        self.target_port = self.DeclareAbstractOutputPort("target", lambda: AbstractValue.Make(()), self.CalcTarget)

    def CalcTarget(self, context, output):
        actions = self.action_port.Eval(context)
        acting = actions[:, ACTION_SIZE] > 0.5
        if acting.all():  # the common case: every row, no copies
            start, actions = self.segment_start_state_port.Eval(context), actions[:, :ACTION_SIZE]
            joints = start.shape[1] // 3
            output.set_value(tuple(self.stack.map_batch(start[:, :joints], start[:, joints : 2 * joints], start[:, 2 * joints :], actions)))
            return
        acting = np.flatnonzero(acting)
        stages = [Stage(False, reason=NO_ACTION)] * self.batch
        if acting.size:
            start = self.segment_start_state_port.Eval(context)[acting]
            q, v, a = split_start_state(start)
            for row, stage in zip(acting, self.stack.map_batch(q, v, a, actions[acting, :ACTION_SIZE])):
                stages[row] = stage
        output.set_value(tuple(stages))
