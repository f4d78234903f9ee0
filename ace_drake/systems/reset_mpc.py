"""ResetMpc: the reset trajectory from a segment's end to the stationary reset pose."""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.stack import ControlStack, Stage


class ResetMpc(LeafSystem):
    """The reset trajectory for a segment (paper, *Reset trajectories*).

    The paper computes it with a near-time-optimal MPC; this system uses Ruckig's time-optimal,
    jerk-limited, time-synchronised trajectory instead (``control.reset``): optimal rather than
    near-optimal for the same limits, a few microseconds per plan, and what the authors' robot side
    runs. The name keeps the paper's role.

    Input ports:
        segment (abstract Stage): the SplineQp's segment.
    Output ports:
        reset (abstract Stage): value a JointTrajectory at 1 kHz from the segment's terminal state
            to the reset pose at rest, when ok; otherwise why not.
    State: none (direct feedthrough).
    """

    def __init__(self, stack: ControlStack):
        """Args: stack, the shared control stack (reset pose, limits, the Ruckig planner)."""
        super().__init__()
        self.stack = stack
        self.segment_port = self.DeclareAbstractInputPort("segment", AbstractValue.Make(Stage(False)))
        self.reset_port = self.DeclareAbstractOutputPort("reset", lambda: AbstractValue.Make(Stage(False)), self.CalcReset)

    def CalcReset(self, context, output):
        segment = self.segment_port.Eval(context)
        output.set_value(self.stack.reset(segment.value) if segment.ok else Stage(False, reason=segment.reason))
