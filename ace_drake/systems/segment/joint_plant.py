"""SegmentJointPlant: the eight delayed joints of B environments (paper eq. (9)), once per segment."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.joint_model import JointMotion, JointPropagator
from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.robot.params import JOINT_NAMES, RobotDynamicsParams


@dataclasses.dataclass(frozen=True)
class JointPlantState:
    """zeta (B, 8, 2) = [q, q_dot] per joint at the tick's start, and the last ``history`` commands
    before it, (B, history, 8), oldest first. Immutable."""

    zeta: np.ndarray
    commands: np.ndarray

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


class SegmentJointPlant(LeafSystem):
    """The continuous-time ``DelayedJointPlant`` for B environments: each joint d/dt zeta = A zeta
    + b u(t - tau_d) (paper eq. (9)) driven by the 1 kHz command samples, solved exactly over the
    whole segment at each tick (``JointPropagator.propagate_samples``: the same compiled solution,
    so the samples equal the 1 kHz plant's bit for bit). Joint i is driven by u_i[n - k_i - 1] on
    [t_n, t_n + f_i) and by u_i[n - k_i] from there to t_{n+1} (tau_i = k_i T + f_i).

    Input ports:
        command_stream (abstract float (B, T, 8)): the supervisor's commands at the tick's samples.
    Output ports:
        joint_motion (abstract JointMotion): the exact motion over the tick (samples and the
            solution between them; feedthrough of command_stream).
        joint_state (abstract float (B, 16)): [q, v] at the tick's start (state only).
    State:
        abstract JointPlantState.
    Events:
        periodic unrestricted update every T (offset 0): stores the state at the tick's end.
    """

    def __init__(self, params: RobotDynamicsParams, batch: int, timing: SegmentTiming):
        """Args: params, the joints' eq. (9) parameters; batch, B; timing, the segment time line
        (its period must be the joints' command period)."""
        super().__init__()
        if abs(params.command_period - timing.period) > 1e-12:
            raise ValueError(f"SegmentJointPlant: the command period ({params.command_period} s) differs from the timing's ({timing.period} s)")
        self.params = params
        self.batch = int(batch)
        self.timing = timing
        self.propagator = JointPropagator(params.joints, params.command_period)
        joints = len(JOINT_NAMES)
        self.history = int(self.propagator.whole_periods.max()) + 2
        self._columns = np.arange(joints)
        # Rows of [history, stream] holding each period's delayed inputs: u[n - k_i] (newer) and
        # u[n - k_i - 1] (older), (T, 8); the same every tick.
        self._newer = np.arange(timing.samples)[:, None] - self.propagator.whole_periods[None, :] + self.history
        self._older = self._newer - 1
        default = JointPlantState(np.zeros((self.batch, joints, 2)), np.zeros((self.batch, self.history, joints)))
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(default))
        self.command_stream_port = self.DeclareAbstractInputPort("command_stream", AbstractValue.Make(np.zeros((self.batch, timing.samples, joints))))
        self._motion_cache = self.DeclareCacheEntry(
            "the motion over the tick",
            ValueProducer(allocate=lambda: AbstractValue.Make(None), calc=self._CalcMotion),
            {self.abstract_state_ticket(self._state_index), self.all_input_ports_ticket()},
        )
        self.joint_motion_port = self.DeclareAbstractOutputPort(
            "joint_motion", lambda: AbstractValue.Make(None), self.CalcJointMotion, prerequisites_of_calc={self._motion_cache.ticket()}
        )
        self.joint_state_port = self.DeclareAbstractOutputPort(
            "joint_state", lambda: AbstractValue.Make(np.zeros((self.batch, 2 * joints))), self.CalcJointState,
            prerequisites_of_calc={self.abstract_state_ticket(self._state_index)},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.Update)

    # ------------------------------------------------------------------------------ set-up
    def plant_state(self, context) -> JointPlantState:
        """The JointPlantState in this system's ``context``."""
        return context.get_abstract_state(self._state_index).get_value()

    def StartEpisodes(self, context, rows, q, v=None, planned=None) -> None:
        """Sets environments ``rows`` (k,) at joint positions q (k, 8), velocities v (default 0),
        with a command history of q (joints at rest with command q stay exactly there).
        ``planned`` (k,) of ``control.serve_execution.PlannedStart`` or None: those rows are set
        where that plan's executed commands have them at the first tick's start (q, v unused)."""
        rows = np.asarray(rows, dtype=int)
        q = np.asarray(q, dtype=float).reshape(rows.size, -1)
        v = np.zeros_like(q) if v is None else np.asarray(v, dtype=float).reshape(q.shape)
        if q.shape[1] != len(JOINT_NAMES) or not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
            raise ValueError(f"SegmentJointPlant.StartEpisodes: q and v must be finite ({rows.size}, {len(JOINT_NAMES)}), got {q.shape}")
        current = self.plant_state(context)
        zeta, commands = current.zeta.copy(), current.commands.copy()
        zeta[rows, :, 0], zeta[rows, :, 1] = q, v
        commands[rows] = q[:, None, :]
        for k, row in enumerate(rows):
            if planned is not None and planned[k] is not None:
                zeta[row], commands[row] = planned[k].joint_state(self.params, int(self.timing.first_sample(0)), self.history)
        context.SetAbstractState(self._state_index, JointPlantState(zeta, commands))

    # ------------------------------------------------------------------------------ motion
    def _CalcMotion(self, context, value):
        current = self.plant_state(context)
        stream = self.command_stream_port.Eval(context)
        commands = np.concatenate([current.commands, stream], axis=1)  # u[n0 - H] ... u[n0 + T - 1]
        u_new = commands[:, self._newer, self._columns]
        u_old = commands[:, self._older, self._columns]
        zeta = self.propagator.propagate_samples(current.zeta, u_old, u_new)
        value.set_value((JointMotion(self.propagator, zeta, u_old, u_new), commands[:, -self.history :]))

    def CalcJointMotion(self, context, output):
        output.set_value(self._motion_cache.Eval(context)[0])

    def CalcJointState(self, context, output):
        zeta = self.plant_state(context).zeta
        output.set_value(np.concatenate([zeta[..., 0], zeta[..., 1]], axis=-1))

    def Update(self, context, state):
        motion, history = self._motion_cache.Eval(context)
        state.get_mutable_abstract_state(self._state_index).set_value(JointPlantState(motion.zeta[:, -1].copy(), history.copy()))
