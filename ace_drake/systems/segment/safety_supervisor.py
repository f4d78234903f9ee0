"""SegmentSafetySupervisor: the robot interface of B environments, once per segment."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.control.stack import ControlStack, decide_segment, plan_state
from ace_drake.robot.params import JOINT_NAMES
from ace_drake.robot.trajectory import JointTrajectory
from ace_drake.systems.action_mapper import SEGMENT_START_STATE_SIZE
from ace_drake.systems.safety_supervisor import STATUS_SIZE, SupervisorState


def plan_samples(plan: JointTrajectory, plan_start: int, first: int, out: np.ndarray) -> None:
    """Fills out (k, 8) with the commanded positions of ``plan`` (started at episode sample
    ``plan_start``) at episode samples first .. first + k - 1: before its start its first row,
    after its end its last (``plan_state``'s rule), as slices of its samples."""
    count, last = out.shape[0], plan.samples
    start = first - plan_start  # the plan's row at out[0]
    lead = min(max(-start, 0), count)  # samples before the plan's start
    inside = min(max(last + 1 - start, 0), count)  # samples up to its end
    out[:lead] = plan.q[0]
    out[lead:inside] = plan.q[start + lead : start + inside]
    out[inside:] = plan.q[last]


class SegmentSafetySupervisor(LeafSystem):
    """The continuous-time ``SafetySupervisor`` for B environments, deciding once per tick: a
    protective stop while the light curtain is broken (the fastest stop within the command
    limits, if collision-free, else the committed plan; no new segments until it clears),
    otherwise, from tick 1 on (and once a planned start's hold is over), the new segment and its
    reset if both exist and are collision-free (``control.stack.decide_segment``), else the
    committed plan. Its plan's samples at 1 kHz are the joints' commands.

    Differences from the reference: the light curtain is read at the ticks (every 32 ms, not
    every 1 ms), so a stop may start up to 32 ms later; an episode's start plan begins at the
    first tick's start, ``lead`` before the episode's time 0 (a moving start moves from there).

    Input ports:
        segment (abstract tuple of B Stage): the SegmentSplineQp's.
        reset (abstract tuple of B Stage): the SegmentResetMpc's.
        light_curtain (abstract float (B,)): > 0.5 while someone is on that robot's side.
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        segment_start_state (abstract float (B, 24)): [q, v, a] of the committed plan where this
            tick's segment starts (episode sample j T): the mapper's, the QP's and the
            observation's robot state. State only (no feedthrough).
        command_stream (abstract float (B, T, 8)): the commanded joint positions at the tick's T
            samples (episode samples j T - lead ...), after this tick's decision (feedthrough).
        commanded_state (abstract float (B, 24)): [q, v, a] of the plan at the tick's start.
        status (abstract float (B, 4)): [accepted, refused, protective stop (0/1), at rest].
    State:
        abstract tuple of B SupervisorState (plan_start in episode samples).
    Events:
        periodic unrestricted update every T (offset 0): stores this tick's decision.
    """

    def __init__(self, stack: ControlStack, batch: int, timing: SegmentTiming):
        """Args: stack, the shared control stack (its collision check decides); batch, B; timing."""
        super().__init__()
        self.stack = stack
        self.batch = int(batch)
        self.timing = timing
        self.period = stack.period
        self.segment_samples = timing.samples
        default = SupervisorState(JointTrajectory.stationary(stack.reset_pose, self.period), int(timing.first_sample(0)))
        self._state_index = self.DeclareAbstractState(AbstractValue.Make((default,) * self.batch))
        self.segment_port = self.DeclareAbstractInputPort("segment", AbstractValue.Make(()))
        self.reset_port = self.DeclareAbstractInputPort("reset", AbstractValue.Make(()))
        self.light_curtain_port = self.DeclareAbstractInputPort("light_curtain", AbstractValue.Make(np.zeros(self.batch)))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self._decision_cache = self.DeclareCacheEntry(
            "this tick's decision", ValueProducer(allocate=lambda: AbstractValue.Make(()), calc=self._CalcDecision),
            {self.abstract_state_ticket(self._state_index), self.all_input_ports_ticket()},
        )
        state_only = {self.abstract_state_ticket(self._state_index), self.input_port_ticket(self.episode_ticks_port.get_index())}
        joints = len(JOINT_NAMES)
        self.segment_start_state_port = self.DeclareAbstractOutputPort(
            "segment_start_state", lambda: AbstractValue.Make(np.zeros((self.batch, SEGMENT_START_STATE_SIZE))),
            self.CalcSegmentStartState, prerequisites_of_calc=state_only,
        )
        self.commanded_state_port = self.DeclareAbstractOutputPort(
            "commanded_state", lambda: AbstractValue.Make(np.zeros((self.batch, SEGMENT_START_STATE_SIZE))),
            self.CalcCommandedState, prerequisites_of_calc=state_only,
        )
        self.command_stream_port = self.DeclareAbstractOutputPort(
            "command_stream", lambda: AbstractValue.Make(np.zeros((self.batch, timing.samples, joints))),
            self.CalcCommandStream, prerequisites_of_calc={self._decision_cache.ticket()},
        )
        self.status_port = self.DeclareAbstractOutputPort(
            "status", lambda: AbstractValue.Make(np.zeros((self.batch, STATUS_SIZE))), self.CalcStatus, prerequisites_of_calc=state_only
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Update)

    # ------------------------------------------------------------------------------ set-up
    def supervisor_states(self, context) -> tuple[SupervisorState, ...]:
        """The B SupervisorStates in this system's ``context``."""
        return context.get_abstract_state(self._state_index).get_value()

    def StartEpisodes(self, context, rows, q, v=None, a=None, planned=None) -> None:
        """Starts the episodes of environments ``rows`` (k,) from joint states q, v, a (k, 8)
        each (v, a default zero): at rest the plan is to stand still; moving, the reset from
        there, starting at the first tick's start. ``planned`` (k,) of
        ``control.serve_execution.PlannedStart`` or None: those rows commit to that plan instead
        (its start_sample at the episode's time 0; no new segment within its hold; q, v, a
        unused). Raises ValueError if a plan is not collision-free."""
        rows = np.asarray(rows, dtype=int)
        states = list(self.supervisor_states(context))
        start = int(self.timing.first_sample(0))
        for k, row in enumerate(rows):
            given = None if planned is None else planned[k]
            if given is not None:
                plan, free = given.plan, self.stack.check(given.plan).ok
                states[row] = SupervisorState(plan, -given.start_sample, hold_until=given.hold_samples)
            else:
                plan, free = self.stack.initial_plan(q[k], None if v is None else v[k], None if a is None else a[k])
                states[row] = SupervisorState(plan, start)
            if not free:
                raise ValueError(f"SegmentSafetySupervisor.StartEpisodes: the initial plan of environment {row} is not collision-free")
        context.SetAbstractState(self._state_index, tuple(states))

    def ContinueEpisodes(self, context, rows, shifts) -> None:
        """Restarts the episode clocks of environments ``rows`` (k,) without touching their robots:
        each committed plan goes on, re-timed to the new episode (``shifts`` (k,): the old episode's
        sample that becomes the new one's sample 0, a whole number of segments); counts and any
        protective stop carry over. For the next shot of a rally the robot is in the middle of."""
        states = list(self.supervisor_states(context))
        for row, shift in zip(np.asarray(rows, dtype=int), np.asarray(shifts, dtype=np.int64)):
            state = states[row]
            hold = None if state.hold_until is None else int(state.hold_until - shift)
            states[row] = dataclasses.replace(state, plan_start=int(state.plan_start - shift), hold_until=hold)
        context.SetAbstractState(self._state_index, tuple(states))

    # ------------------------------------------------------------------------------ decision
    def _CalcDecision(self, context, value):
        """(new state, previous state) per environment after this tick's decision."""
        current = self.supervisor_states(context)
        ticks = self.episode_ticks_port.Eval(context)
        curtain = self.light_curtain_port.Eval(context) > 0.5
        first_samples, boundaries = self.timing.first_sample(ticks).tolist(), self.timing.boundary_sample(ticks).tolist()
        decided = []
        segments = resets = None
        for row, state in enumerate(current):
            sample = first_samples[row]
            updated = state
            if curtain[row] and not state.stopped:
                stop, free = self.stack.protective_stop(*plan_state(state.plan, max(sample - state.plan_start, 0)))
                if free:
                    updated = dataclasses.replace(state, plan=stop, plan_start=sample, stopped=True, last_reason="protective stop")
                else:
                    updated = dataclasses.replace(state, stopped=True, last_reason="protective stop would collide: keeping the checked plan")
            elif not curtain[row] and state.stopped:
                updated = dataclasses.replace(state, stopped=False)
            elif not curtain[row] and ticks[row] >= 1 and (state.hold_until is None or boundaries[row] >= state.hold_until):
                if segments is None:
                    segments, resets = self.segment_port.Eval(context), self.reset_port.Eval(context)
                decision = decide_segment(self.stack, segments[row], resets[row])
                boundary = boundaries[row]
                if decision.accepted:
                    updated = dataclasses.replace(state, plan=decision.plan, plan_start=boundary, accepted=state.accepted + 1)
                elif decision.refused:
                    updated = dataclasses.replace(state, rejected=state.rejected + 1, last_reason=decision.reason)
            decided.append(updated)
        value.set_value(tuple(decided))

    def Update(self, context, state):
        state.get_mutable_abstract_state(self._state_index).set_value(self._decision_cache.Eval(context))

    # ------------------------------------------------------------------------------ outputs
    def CalcCommandStream(self, context, output):
        first_samples = self.timing.first_sample(self.episode_ticks_port.Eval(context)).tolist()
        previous = self.supervisor_states(context)
        stream = np.empty((self.batch, self.timing.samples, len(JOINT_NAMES)))
        for row, state in enumerate(self._decision_cache.Eval(context)):
            first = first_samples[row]
            plan_samples(state.plan, state.plan_start, first, stream[row])
            if first < state.plan_start:  # a plan decided at the boundary: the old plan until then
                old = previous[row]
                plan_samples(old.plan, old.plan_start, first, stream[row, : state.plan_start - first])
        output.set_value(stream)

    def CalcSegmentStartState(self, context, output):
        output.set_value(self._states_at(context, self.timing.boundary_sample(self.episode_ticks_port.Eval(context))))

    def CalcCommandedState(self, context, output):
        output.set_value(self._states_at(context, self.timing.first_sample(self.episode_ticks_port.Eval(context))))

    def CalcStatus(self, context, output):
        samples = self.timing.first_sample(self.episode_ticks_port.Eval(context))
        status = np.array([
            [s.accepted, s.rejected, float(s.stopped), float(samples[row] - s.plan_start >= s.plan.samples)]
            for row, s in enumerate(self.supervisor_states(context))
        ], dtype=float)
        output.set_value(status)

    def _states_at(self, context, samples: np.ndarray) -> np.ndarray:
        out = np.empty((self.batch, SEGMENT_START_STATE_SIZE))
        for row, (state, sample) in enumerate(zip(self.supervisor_states(context), samples.tolist())):
            out[row] = np.concatenate(plan_state(state.plan, max(sample - state.plan_start, 0)))
        return out
