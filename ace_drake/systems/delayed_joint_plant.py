"""DelayedJointPlant: the robot's eight joints as delayed second-order LTI systems (paper eq. (9))."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from ace_drake.control.joint_model import JointPropagator
from ace_drake.robot.params import JOINT_NAMES, RobotDynamicsParams


@dataclasses.dataclass(frozen=True)
class _CommandSample:
    """What the outputs need of the last command sample (``DelayedJointPlant._CalcSample``)."""

    time: float
    state: np.ndarray
    zeta: np.ndarray
    u_old: np.ndarray
    u_new: np.ndarray


class DelayedJointPlant(LeafSystem):
    """Eight decoupled joints, each d/dt zeta = A zeta + b u(t - tau_d), zeta = [q, q_dot] (paper eq. (9)).

    Input ports:
        q_command (8,): desired joint positions q*, rad or m, in JOINT_NAMES order.
    Output ports:
        joint_state (16,): [q (rad or m), v (rad/s or m/s)] at the context's time.
        q (8,): the joint positions alone.
    State:
        discrete, three groups: zeta at the last command sample as [q (8), v (8)]; the time of that
            sample t_last (1,), s; the sampled commands (history_length, 8) row-major, row j holding
            u[n - j], with history_length = max_i k_i + 2 (every joint's two inputs of the current
            period, tau_i = k_i T + f_i).
    Events:
        periodic discrete update every T = params.command_period (1 ms, offset 0): moves zeta
        exactly from t_last to now, samples q_command into the history and sets t_last = now.

    The command is sampled at the update times t_n = n T, and joint i is driven by u_i[n - k_i - 1]
    on [t_n, t_n + f_i) and by u_i[n - k_i] from t_n + f_i to t_{n+1}, as the 1 kHz interface holds
    it. All updates at one instant read the state from before that instant, so an upstream
    discrete system updating at the same instants is seen one sample later (one more period of
    delay); a time-dependent source is seen at t_n itself.

    Between samples the velocity ripples: each step of the held command kicks the stiff servo
    (1000 rad/s against 1 kHz sampling by default), so at the sample instants the joint velocity
    of a smooth swing sits several percent from its mean over the period (9% in the scripted
    swing of analysis/scripted_swing.py) while the position stays on the smooth motion.

    The outputs are the exact solution at the context's time (``JointPropagator``), computed from
    the discrete state: the joints move continuously between samples, so contact times against a
    racket driven by them are exact, and the outputs do not depend on q_command directly. The joint
    state is not continuous state of a LinearSystem because the stiff poles (1000 rad/s) made the
    error-controlled integrator take 141,000 steps per simulated second; here a simulation costs
    1000 updates per second plus whatever output evaluations its consumers need. What those read
    of the last sample is cached once per sample (``_CalcSample``), and at the sample instant
    itself (right after each update, where the BallPlant's racket witness starts every step) the
    output is the stored state, with no propagation.
    """

    def __init__(self, params: RobotDynamicsParams | None = None):
        """Args: params, the joints' eq. (9) parameters and the command period (defaults: config)."""
        super().__init__()
        self.params = params or RobotDynamicsParams()
        self.propagator = JointPropagator(self.params.joints, self.params.command_period)
        joint_count = len(JOINT_NAMES)
        joints = np.arange(joint_count)
        self._history_length = int(self.propagator.whole_periods.max()) + 2
        # Rows of each joint's two inputs in the history: u_i[n - k_i] and u_i[n - k_i - 1].
        self._newer_input = (self.propagator.whole_periods, joints)
        self._older_input = (self.propagator.whole_periods + 1, joints)
        # Sample times are n T in floating point: allow their differences to round off T.
        self._time_tolerance = 1e-6 * self.params.command_period

        self._joint_state_index = self.DeclareDiscreteState(2 * joint_count)
        self._sample_time_index = self.DeclareDiscreteState(1)
        self._command_history_index = self.DeclareDiscreteState(self._history_length * joint_count)
        self.q_command_port = self.DeclareVectorInputPort("q_command", joint_count)
        self._sample_cache = self.DeclareCacheEntry(
            "the last command sample",
            ValueProducer(allocate=lambda: AbstractValue.Make(None), calc=self._CalcSample),
            {self.xd_ticket()},
        )
        output_prerequisites = {self.time_ticket(), self._sample_cache.ticket()}
        self.joint_state_port = self.DeclareVectorOutputPort(
            "joint_state", 2 * joint_count, self.CalcJointState, prerequisites_of_calc=output_prerequisites
        )
        self.q_port = self.DeclareVectorOutputPort("q", joint_count, self.CalcQ, prerequisites_of_calc=output_prerequisites)
        self.DeclarePeriodicDiscreteUpdateEvent(self.params.command_period, 0.0, self.UpdateCommandSample)

    # ------------------------------------------------------------------------------ set-up
    def SetJointState(self, context, q, v=None, command=None) -> None:
        """Starts an episode at the context's time: joint positions q (8,), velocities v (8,),
        default zeros, and a command history filled with ``command`` (8,), default q, so that
        joints at rest with command q stay exactly at q. Units: rad or m, and per second."""
        q = self._checked("q", q)
        v = np.zeros_like(q) if v is None else self._checked("v", v)
        command = q if command is None else self._checked("command", command)
        context.get_mutable_discrete_state(self._joint_state_index).SetFromVector(np.concatenate([q, v]))
        context.get_mutable_discrete_state(self._sample_time_index).SetFromVector([context.get_time()])
        context.get_mutable_discrete_state(self._command_history_index).SetFromVector(np.tile(command, self._history_length))

    # ------------------------------------------------------------------------------ outputs
    def CalcJointState(self, context, output):
        output.SetFromVector(self._joint_state_now(context))

    def CalcQ(self, context, output):
        output.SetFromVector(self.joint_state_port.Eval(context)[: len(JOINT_NAMES)])

    # ------------------------------------------------------------------------------ update
    def UpdateCommandSample(self, context, discrete_state):
        """At t_n: zeta(t_n) from the last sample, then u[n] = q_command(t_n) into the history."""
        joint_count = len(JOINT_NAMES)
        # The output at t_n is zeta(t_n): reusing it keeps q and v continuous across the update.
        discrete_state.get_mutable_vector(self._joint_state_index).SetFromVector(self.joint_state_port.Eval(context))
        discrete_state.get_mutable_vector(self._sample_time_index).SetFromVector([context.get_time()])
        history = context.get_discrete_state(self._command_history_index).get_value()
        shifted = np.concatenate([self.q_command_port.Eval(context), history[:-joint_count]])
        discrete_state.get_mutable_vector(self._command_history_index).SetFromVector(shifted)

    # ------------------------------------------------------------------------------ helpers
    def _CalcSample(self, context, value):
        """The last sample, for every output until the next: its time t_last (s), zeta there as
        (8, 2) and flat [q, v] (16,), and each joint's inputs u_old, u_new (8,) of the period."""
        zeta = context.get_discrete_state(self._joint_state_index).get_value()
        history = context.get_discrete_state(self._command_history_index).get_value().reshape(self._history_length, -1)
        value.set_value(
            _CommandSample(
                context.get_discrete_state(self._sample_time_index).GetAtIndex(0),
                zeta.copy(),
                zeta.reshape(2, -1).T.copy(),
                history[self._older_input],
                history[self._newer_input],
            )
        )

    def _joint_state_now(self, context) -> np.ndarray:
        """[q, v] (16,) at the context's time, from the last command sample."""
        time = context.get_time()
        sample = self._sample_cache.Eval(context)
        elapsed = time - sample.time
        if elapsed == 0.0:  # at the sample itself (after each update): the state stored there
            return sample.state
        if not -self._time_tolerance <= elapsed <= self.params.command_period + self._time_tolerance:
            raise RuntimeError(
                f"DelayedJointPlant: the context time {time} s is {elapsed} s after the last command sample "
                f"at {sample.time} s; the joints are defined from it up to one command period "
                f"({self.params.command_period} s) later. Advance the context with a Simulator, or call "
                "SetJointState after setting the time."
            )
        return self.propagator.propagate(sample.zeta, sample.u_old, sample.u_new, elapsed).T.ravel()

    @staticmethod
    def _checked(name: str, value) -> np.ndarray:
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.shape != (len(JOINT_NAMES),) or not np.all(np.isfinite(array)):
            raise ValueError(
                f"DelayedJointPlant.SetJointState: {name} must be {len(JOINT_NAMES)} finite values "
                f"({', '.join(JOINT_NAMES)}), got {value!r}"
            )
        return array
