"""SegmentPolicyController: the rally policy of B environments, once per segment."""

from __future__ import annotations

import inspect
from typing import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.control.action_mapping import ACTION_SIZE, is_valid_action
from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.systems.policy_controller import ACTION_REQUEST_SIZE, as_policy


def _is_torch_module(policy) -> bool:
    try:
        import torch  # lazy, as in policy_controller.as_policy: plain callables never need torch
    except ImportError:
        return False
    return isinstance(policy, torch.nn.Module)


class SegmentPolicyController(LeafSystem):
    """Runs the policy of B environments at each tick (paper: every 32 ms, on the observation 5 ms
    before the segment it commands), for the environments past their first tick; the
    continuous-time ``PolicyController``'s rules otherwise (invalid outputs counted and refused,
    finite actions clipped into [-1, 1]).

    Policies: a ``torch.nn.Module`` (one batched forward pass for all deciding environments), one
    stateless callable (observation (n,) -> action (16,) or None, called per environment), or a
    sequence of B callables, one per environment (a stateful policy such as the model-based
    returner remembers one episode, so a batch needs one each). None: the actions come from the
    ``action_request`` input, as a vector environment steps them.

    Input ports:
        observation (abstract float (B, n)): the ObservationBuilder's.
        episode_ticks (abstract int64 (B,)): the EpisodeClock's; environments at tick 0 (their
            first observation instant has not come) get no action.
        action_request (abstract float (B, 17)), only without a policy: [action (16), valid].
    Output ports:
        action (abstract float (B, 17)): [action (16) in [-1, 1], valid] for this tick's segment
            decision: valid 1 for an action, 0 for none, -1 for an invalid policy output (no
            segment either; counted). Direct feedthrough: the policy is called here, once per
            tick (the tick's update reads the cached value).
    State:
        abstract int64 (B, 2): [calls, invalid outputs] per environment.
    Events:
        periodic unrestricted update every T (offset 0): counts this tick's calls.
    """

    def __init__(self, policy, batch: int, observation_size: int, timing: SegmentTiming):
        """Args: policy (class docstring); batch, B; observation_size, n; timing, the time line."""
        super().__init__()
        self.batch = int(batch)
        self.observation_size = int(observation_size)
        self._module = policy if _is_torch_module(policy) else None
        self._policies: list | None = None
        if policy is not None and self._module is None:
            if isinstance(policy, Sequence):
                if len(policy) != self.batch:
                    raise ValueError(f"SegmentPolicyController: {len(policy)} policies for a batch of {self.batch}")
                self._policies = [as_policy(p) for p in policy]
            else:
                if callable(getattr(policy, "reset", None)) and self.batch > 1:
                    raise ValueError(
                        "SegmentPolicyController: a policy with a reset() keeps one episode's memory; "
                        f"give one per environment (a sequence of {self.batch}) for a batch"
                    )
                self._policies = [as_policy(policy)] * self.batch
        self._sources = list(policy) if isinstance(policy, Sequence) else [policy] * self.batch
        self.external = policy is None
        self.observation_port = self.DeclareAbstractInputPort("observation", AbstractValue.Make(np.zeros((self.batch, self.observation_size))))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(self.batch, dtype=np.int64)))
        self.action_request_port = None
        if self.external:
            self.action_request_port = self.DeclareAbstractInputPort("action_request", AbstractValue.Make(np.zeros((self.batch, ACTION_REQUEST_SIZE))))
        self._counts_index = self.DeclareAbstractState(AbstractValue.Make(np.zeros((self.batch, 2), dtype=np.int64)))
        self.action_port = self.DeclareAbstractOutputPort(
            "action", lambda: AbstractValue.Make(np.zeros((self.batch, ACTION_REQUEST_SIZE))), self.CalcAction
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.CountCalls)

    # ------------------------------------------------------------------------------ episodes
    def ResetPolicies(self, rows, seeds=None) -> None:
        """Tells the stateful policies of environments ``rows`` that a new episode starts: calls
        their ``reset()``, or ``reset(seed=...)`` with the row's episode seed (``seeds`` (k,)) for a
        stochastic policy whose ``reset`` takes one."""
        rows = np.asarray(rows, dtype=int).reshape(-1)
        seen = set()
        for k, row in enumerate(rows):
            source = self._sources[row]
            reset = getattr(source, "reset", None)
            if not callable(reset) or id(source) in seen:
                continue
            seen.add(id(source))
            if seeds is not None and "seed" in inspect.signature(reset).parameters:
                reset(seed=int(np.asarray(seeds).reshape(-1)[k]))
            else:
                reset()

    def counts(self, context) -> np.ndarray:
        """[calls, invalid outputs] (B, 2) so far in this system's ``context``."""
        return context.get_abstract_state(self._counts_index).get_value()

    def StartEpisodes(self, context, rows) -> None:
        """Zeroes the counts of environments ``rows``."""
        counts = self.counts(context).copy()
        counts[np.asarray(rows, dtype=int)] = 0
        context.SetAbstractState(self._counts_index, counts)

    # ------------------------------------------------------------------------------ outputs
    def CalcAction(self, context, output):
        deciding = self.episode_ticks_port.Eval(context) >= 1
        actions = np.zeros((self.batch, ACTION_REQUEST_SIZE))
        raw = self._raw_actions(context, deciding)
        for row in np.flatnonzero(deciding):
            value = raw[row]
            if value is not None and is_valid_action(value):
                # np.clip into [-1, 1] (finite values), as two ufuncs without np.clip's overhead
                np.minimum(np.maximum(np.asarray(value, dtype=float), -1.0), 1.0, out=actions[row, :ACTION_SIZE])
                actions[row, ACTION_SIZE] = 1.0
            elif value is not None:
                actions[row, ACTION_SIZE] = -1.0  # invalid: counted, then no segment
        output.set_value(actions)

    def _raw_actions(self, context, deciding: np.ndarray) -> list:
        """Each deciding row's policy output (None where there is none)."""
        raw: list = [None] * self.batch
        rows = np.flatnonzero(deciding)
        if not rows.size:
            return raw
        if self.external:
            request = self.action_request_port.Eval(context)
            for row in rows:
                raw[row] = request[row, :ACTION_SIZE] if request[row, ACTION_SIZE] > 0.5 else None
            return raw
        observation = self.observation_port.Eval(context)
        if self._module is not None:
            import torch

            with torch.no_grad():
                output = self._module.eval()(torch.as_tensor(observation[rows], dtype=torch.float32))
            output = output[0] if isinstance(output, tuple) else output
            for row, action in zip(rows, np.asarray(output, dtype=float)):
                raw[row] = action
            return raw
        for row in rows:
            raw[row] = self._policies[row](observation[row])
        return raw

    # ------------------------------------------------------------------------------ update
    def CountCalls(self, context, state):
        deciding = self.episode_ticks_port.Eval(context) >= 1
        if not deciding.any():
            return
        valid = self.action_port.Eval(context)[:, ACTION_SIZE]
        counts = self.counts(context).copy()
        counts[deciding, 0] += 1
        counts[deciding & (valid < 0.0), 1] += 1
        state.get_mutable_abstract_state(self._counts_index).set_value(counts)
