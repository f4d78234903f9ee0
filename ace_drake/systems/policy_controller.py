"""PolicyController: every 32 ms, 5 ms before its segment, calls a policy on the observation or
reads the action an outside learner requested (a gymnasium environment)."""

from __future__ import annotations

import inspect
from collections.abc import Callable

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ace_drake.control.action_mapping import ACTION_SIZE, is_valid_action
from ace_drake.control.params import ControlParams
from ace_drake.systems.random_seed import declare_seed_port, episode_seed


def as_policy(policy) -> Callable[[np.ndarray], np.ndarray | None]:
    """A callable observation (n,) -> action (16,) or None from a Python callable or a
    ``torch.nn.Module`` (run without gradients on a float32 batch of one; its output is the
    action)."""
    # Lazy: torch costs about a second to import, and diagrams whose policy is a plain callable
    # (the returner, scripted controllers) never need it.
    try:
        import torch
    except ImportError:
        torch = None
    if torch is not None and isinstance(policy, torch.nn.Module):
        module = policy.eval()

        def call(observation: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                output = module(torch.as_tensor(observation, dtype=torch.float32)[None])
            return np.asarray(output[0] if not isinstance(output, tuple) else output[0][0], dtype=float)

        return call
    if not callable(policy):
        raise TypeError(f"PolicyController: the policy must be callable or a torch.nn.Module, got {type(policy).__name__}")
    return policy


ACTION_REQUEST_SIZE = ACTION_SIZE + 1  # [action (16), valid flag]


class PolicyController(LeafSystem):
    """Runs a policy every segment (paper: every 32 ms), on the observation 5 ms before the segment
    it commands starts (paper, Extended Data Fig. 1), and holds its action.

    Two modes. With a policy (a callable or a torch module) the controller calls it on the
    observation at each event. Without one (``policy=None``) the action comes from outside the
    diagram, the way a gymnasium environment steps it: the controller reads its ``action_request``
    input at each event instead (fix the value on the Context, e.g. ``FixValue`` on the diagram's
    exported input, before advancing through the event).

    Input ports:
        observation (n,): whatever the policy reads (here: anything the diagram wires in).
        action_request (17,), only without a policy: [action (16) in [-1, 1], valid]; valid
            > 0.5 asks for a segment with that action, <= 0.5 for none (e.g. after the hit).
        random_seed (1,), random uniform, only with a policy: the episode's seed of a stochastic
            policy, drawn by Drake's random context (``systems.random_seed``; ``ResetPolicy``).
    Output ports:
        action (16,): the latest action, in [-1, 1] (row-major (2, 8): terminal positions, then
            velocities; ``control.action_mapping``).
        action_valid (1,): 1 if the latest call produced an action, 0 if the policy returned None
            (it wants no new segment, e.g. after its hit) or something that is not 16 finite
            numbers (counted in ``invalid_actions`` of the state); likewise for a request that is
            not valid or not finite.
    State:
        discrete: [action (16), action_valid (1), calls (1), invalid_actions (1)]; ``calls``
            counts events (policy calls or requests read).
    Events:
        periodic discrete update every T = segment_samples * command_period (32 ms), offset
        T - observation_lead (27 ms): the policy's call (or the request's reading) for the
        segment starting at the next multiple of T.

    A finite action outside [-1, 1] is clipped into the box (the mapping's domain); a policy's
    tanh head never needs it.
    """

    def __init__(self, policy, observation_size: int, control: ControlParams | None = None, command_period: float = 0.001):
        """Args: policy, a callable observation -> action | None, a torch.nn.Module, or None to
        read each action from the ``action_request`` input; observation_size: n; control: the
        segment length and observation lead; command_period, s."""
        super().__init__()
        self.control = control or ControlParams()
        self._policy = None if policy is None else as_policy(policy)
        self._source = policy
        segment = self.control.segment_samples * command_period
        if not 0.0 <= self.control.observation_lead < segment:
            raise ValueError(f"PolicyController: the observation lead must be in [0, {segment}) s, got {self.control.observation_lead}")
        self.segment_duration = segment
        self.observation_port = self.DeclareVectorInputPort("observation", observation_size)
        self.action_request_port = None
        if self._policy is None:
            self.action_request_port = self.DeclareVectorInputPort("action_request", ACTION_REQUEST_SIZE)
        self.random_seed_port = None if self._policy is None else declare_seed_port(self)
        self._state_index = self.DeclareDiscreteState(ACTION_SIZE + 3)
        self.action_port = self.DeclareVectorOutputPort(
            "action", ACTION_SIZE, self.CalcAction, prerequisites_of_calc={self.xd_ticket()}
        )
        self.action_valid_port = self.DeclareVectorOutputPort(
            "action_valid", 1, self.CalcActionValid, prerequisites_of_calc={self.xd_ticket()}
        )
        self.DeclarePeriodicDiscreteUpdateEvent(segment, segment - self.control.observation_lead, self.UpdateAction)

    def ResetPolicy(self, context=None) -> None:
        """Tells a stateful policy that a new episode starts: calls its ``reset()`` if it has one
        (the model-based returner remembers the ball it is playing). A stochastic policy, one
        whose ``reset`` takes a ``seed``, gets the episode's seed from this system's random_seed
        input in ``context`` (this system's context, after the diagram's ``SetRandomContext``),
        so that its noise too follows the episode's seed (``diagrams.start_rally``)."""
        reset = getattr(self._source, "reset", None)
        if not callable(reset):
            return
        if context is not None and "seed" in inspect.signature(reset).parameters:
            reset(seed=episode_seed(self.random_seed_port, context, 0))
        else:
            reset()

    @property
    def external(self) -> bool:
        """True when actions come from the ``action_request`` input (no policy)."""
        return self._policy is None

    def UpdateAction(self, context, discrete_state):
        """Calls the policy on the observation now, or reads the requested action; stores the
        action (or marks none)."""
        state = context.get_discrete_state(self._state_index).get_value().copy()
        if self._policy is None:
            request = self.action_request_port.Eval(context)
            output = request[:ACTION_SIZE] if request[ACTION_SIZE] > 0.5 else None
        else:
            output = self._policy(self.observation_port.Eval(context))
        state[ACTION_SIZE + 1] += 1
        action = None
        if output is not None and not is_valid_action(output):
            state[ACTION_SIZE + 2] += 1
        elif output is not None:
            action = np.asarray(output, dtype=float)
        state[ACTION_SIZE] = 0.0 if action is None else 1.0
        if action is not None:
            state[:ACTION_SIZE] = np.clip(action, -1.0, 1.0)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(state)

    def CalcAction(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._state_index).get_value()[:ACTION_SIZE])

    def CalcActionValid(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._state_index).get_value()[ACTION_SIZE : ACTION_SIZE + 1])

    def counts(self, context) -> tuple[int, int]:
        """(policy calls or requests read, invalid outputs) so far in this context."""
        state = context.get_discrete_state(self._state_index).get_value()
        return int(state[ACTION_SIZE + 1]), int(state[ACTION_SIZE + 2])
