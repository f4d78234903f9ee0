"""SafetySupervisor: executes a segment and its reset only if they are collision-free, streams
the 1 kHz command to the joints, and stops the robot when the light curtain is broken."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem

from ace_drake.control.stack import ControlStack, Stage, decide_segment, plan_state
from ace_drake.robot.params import JOINT_NAMES
from ace_drake.robot.trajectory import JointTrajectory
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE

STATUS_SIZE = 4


@dataclasses.dataclass(frozen=True)
class SupervisorState:
    """The supervisor's per-episode state (abstract state in the Context).

    plan: the committed command stream, row 0 at global sample ``plan_start`` (time
    plan_start * period); stopped: a protective stop is in force (no new segments); accepted,
    rejected: segments executed and refused (refusals with a reason: infeasible, QP, reset,
    collision); last_reason: why the last proposal was refused or the stop was taken;
    hold_until: no new segment starts before this sample (a planned start's held plan, e.g. a
    serve; the segment-stepped supervisor's, in episode samples).
    """

    plan: JointTrajectory
    plan_start: int
    stopped: bool = False
    accepted: int = 0
    rejected: int = 0
    last_reason: str = ""
    hold_until: int | None = None

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


class SafetySupervisor(LeafSystem):
    """The robot interface of the paper's Fig. 1c: at each segment boundary it executes the new
    segment and its reset if both exist and segment + reset is collision-free (Drake collision
    checking through ``ControlStack.check``); otherwise it keeps its plan, i.e. the reset of the
    last accepted segment, which was checked when it was accepted. It streams the plan to the
    joints at 1 kHz, and a broken light curtain triggers a protective stop: the fastest stop within
    the command limits (``ControlStack.protective_stop``) if it is collision-free, else the
    committed plan, with no new segments until the curtain clears.

    Input ports:
        segment (abstract Stage): from SplineQp.   reset (abstract Stage): from ResetMpc.
        light_curtain (1,): > 0.5 while someone is on the robot's side of the court.
    Output ports:
        q_command (8,): the commanded joint positions at the current 1 kHz sample, rad or m (the
            DelayedJointPlant's input).
        commanded_state (24,): [q, v, a] of the plan at the current sample.
        segment_start_state (24,): [q, v, a] of the plan at the next segment boundary (at a
            boundary, that boundary): where the next segment starts (ActionMapper, SplineQp),
            and the robot state the policy observes.
        status (4,): [accepted segments, refused segments, protective stop in force (0/1), at
            rest (1 when the plan has ended)].
    State:
        abstract SupervisorState (the plan and counters).
    Events:
        periodic unrestricted update every command period (1 ms, offset 0): the light curtain,
        and at multiples of the segment duration the segment decision. Most of these change
        nothing and say so (EventStatus.DidNothing), which spares the Simulator writing the state
        back; the q_command output comes from the plan and the time, not from the update.
    """

    def __init__(self, stack: ControlStack):
        """Args: stack, the shared control stack (its collision check decides)."""
        super().__init__()
        self.stack = stack
        self.period = stack.period
        self.segment_samples = stack.control.segment_samples
        joints = len(JOINT_NAMES)
        self.segment_port = self.DeclareAbstractInputPort("segment", AbstractValue.Make(Stage(False)))
        self.reset_port = self.DeclareAbstractInputPort("reset", AbstractValue.Make(Stage(False)))
        self.light_curtain_port = self.DeclareVectorInputPort("light_curtain", 1)
        default = SupervisorState(JointTrajectory.stationary(stack.reset_pose, self.period), 0)
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(default))
        only_state = {self.time_ticket(), self.abstract_state_ticket(self._state_index)}
        self.q_command_port = self.DeclareVectorOutputPort("q_command", joints, self.CalcQCommand, prerequisites_of_calc=only_state)
        self.commanded_state_port = self.DeclareVectorOutputPort(
            "commanded_state", SEGMENT_START_STATE_SIZE, self.CalcCommandedState, prerequisites_of_calc=only_state
        )
        self.segment_start_state_port = self.DeclareVectorOutputPort(
            "segment_start_state", SEGMENT_START_STATE_SIZE, self.CalcSegmentStartState, prerequisites_of_calc=only_state
        )
        self.status_port = self.DeclareVectorOutputPort("status", STATUS_SIZE, self.CalcStatus, prerequisites_of_calc=only_state)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self.Update)

    # ------------------------------------------------------------------------------ set-up
    def Initialize(self, context, q, v=None, a=None) -> None:
        """Starts an episode at the context's time from joint state (q, v, a) (8,) each (v, a
        default zero): at rest the plan is to stand still; moving, the reset from there. Raises
        ValueError if that plan is not collision-free (no safe way to start)."""
        plan, free = self.stack.initial_plan(q, v, a)
        if not free:
            raise ValueError(f"SafetySupervisor.Initialize: the initial plan from q={np.asarray(q)} is not collision-free")
        context.SetAbstractState(self._state_index, SupervisorState(plan, self._sample(context)))

    def supervisor_state(self, context) -> SupervisorState:
        """The SupervisorState in ``context``."""
        return context.get_abstract_state(self._state_index).get_value()

    # ------------------------------------------------------------------------------ update
    def Update(self, context, state):
        current = self.supervisor_state(context)
        sample = self._sample(context)
        updated = current
        curtain = self.light_curtain_port.Eval(context)[0] > 0.5
        if curtain and not current.stopped:
            stop, free = self.stack.protective_stop(*plan_state(current.plan, sample - current.plan_start))
            if free:
                updated = dataclasses.replace(current, plan=stop, plan_start=sample, stopped=True, last_reason="protective stop")
            else:
                updated = dataclasses.replace(current, stopped=True, last_reason="protective stop would collide: keeping the checked plan")
        elif not curtain and current.stopped:
            updated = dataclasses.replace(current, stopped=False)
        elif not curtain and sample % self.segment_samples == 0:
            updated = self._decide(context, current, sample)
        if updated is current:
            return EventStatus.DidNothing()  # the Simulator skips writing the state back
        state.get_mutable_abstract_state(self._state_index).set_value(updated)
        return EventStatus.Succeeded()

    def _decide(self, context, current: SupervisorState, sample: int) -> SupervisorState:
        """At a segment boundary: the new segment + reset if safe, else the plan as it is
        (``control.stack.decide_segment``, which the safety benchmark runs too)."""
        decision = decide_segment(self.stack, self.segment_port.Eval(context), self.reset_port.Eval(context))
        if decision.accepted:
            return dataclasses.replace(current, plan=decision.plan, plan_start=sample, accepted=current.accepted + 1)
        if decision.refused:
            return dataclasses.replace(current, rejected=current.rejected + 1, last_reason=decision.reason)
        return current

    # ------------------------------------------------------------------------------ outputs
    def CalcQCommand(self, context, output):
        output.SetFromVector(self._state_at(context, self._sample(context))[0])

    def CalcCommandedState(self, context, output):
        output.SetFromVector(np.concatenate(self._state_at(context, self._sample(context))))

    def CalcSegmentStartState(self, context, output):
        boundary = math.ceil(self._sample(context) / self.segment_samples) * self.segment_samples
        output.SetFromVector(np.concatenate(self._state_at(context, boundary)))

    def CalcStatus(self, context, output):
        current = self.supervisor_state(context)
        at_rest = self._sample(context) - current.plan_start >= current.plan.samples
        output.SetFromVector([current.accepted, current.rejected, float(current.stopped), float(at_rest)])

    # ------------------------------------------------------------------------------ helpers
    def _sample(self, context) -> int:
        """The index of the 1 kHz sample at or just before the context's time."""
        return int(math.floor(context.get_time() / self.period + 1e-6))

    def _state_at(self, context, sample: int):
        current = self.supervisor_state(context)
        return plan_state(current.plan, max(sample - current.plan_start, 0))
