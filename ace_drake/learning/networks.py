"""The networks of the asymmetric actor-critic (paper, Methods *Algorithm*; issue 7).

- ``Actor``: the actor observation's selected parts (the paper's s_t: ball position and spin
  histories with ages, robot state, end-effector state, skill) -> an embedding (MLP trunk) ->
  a Gaussian over R^16 squashed by tanh into the action box [-1, 1]^16 (paper, *Actions*). A
  decoder head reconstructs the critic's ground-truth ball state [p, v, w] from the embedding;
  its mean squared error is the paper's auxiliary loss ("reconstruct the ground truth ball state
  from its ball state embedding").
- ``TwinCritic``: two independent Q networks Q_1, Q_2 of (critic features, action); the critic
  features are the privileged observation (true ball state, true joint state, skill) and the
  actor observation's ``robot_state`` part (the committed plan's [q, v, a] where the next segment
  starts: what the next segment does depends on it, and the true joint state does not carry it;
  see ``rally_env``'s docstring). Target critics are copies updated by Polyak averaging (``sac``).

Inputs are divided by fixed per-component scales (``observation_scale``, ``privileged_scale``) so
that metres, m/s and hundreds of rad/s enter the first layer at comparable sizes; the paper gives
no normalisation, these are this project's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from ace_drake.contracts import HISTORY_COLUMNS, ObservationLayout

BALL_STATE_SIZE = 9  # [p (m), v (m/s), w (rad/s)]
# Typical magnitudes (the divisors) of a ball state's position, velocity and spin.
BALL_STATE_SCALE = np.array([1.0] * 3 + [10.0] * 3 + [100.0] * 3)


def observation_scale(layout: ObservationLayout) -> np.ndarray:
    """Divisors (layout.size,) for the actor observation: positions m and ages s by 1, spins by
    100 rad/s, joint velocities by 10 and accelerations by 100 (per s, per s^2), end-effector
    velocities by 10, the estimate and the predicted hit's ball state as ball states, everything
    else by 1."""
    scale = np.ones(layout.size)
    spins = scale[layout.slice("spins")].reshape(-1, HISTORY_COLUMNS)
    spins[:, :3] = 100.0
    scale[layout.slice("spins")] = spins.ravel()
    scale[layout.slice("robot_state")] = np.repeat([1.0, 10.0, 100.0], 8)
    scale[layout.slice("end_effector")] = np.r_[np.ones(7), np.full(6, 10.0)]
    scale[layout.slice("estimate")] = BALL_STATE_SCALE
    scale[layout.slice("hit_prediction")] = np.r_[1.0, 1.0, BALL_STATE_SCALE]
    return scale


def privileged_scale() -> np.ndarray:
    """Divisors (28,) for the privileged observation [ball (9), joints q, v (16), skill (3)]."""
    return np.r_[BALL_STATE_SCALE, np.ones(8), np.full(8, 10.0), np.ones(3)]


def mlp(input_size: int, hidden: Sequence[int], output_size: int) -> nn.Sequential:
    """Linear layers with ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    size = input_size
    for width in hidden:
        layers += [nn.Linear(size, width), nn.ReLU()]
        size = width
    layers.append(nn.Linear(size, output_size))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy with a ground-truth-ball decoder head (module docstring).

    ``forward(obs)`` takes the actor's scaled input features (B, input_size) and returns the
    Gaussian's mean and log standard deviation (B, action_size) in the pre-tanh space and the
    embedding (B, embedding_size).
    """

    def __init__(
        self,
        input_size: int,
        action_size: int,
        hidden: Sequence[int],
        embedding_size: int,
        decoder_hidden: Sequence[int],
        log_std_bounds: tuple[float, float],
    ):
        super().__init__()
        self.trunk = nn.Sequential(mlp(input_size, hidden, embedding_size), nn.ReLU())
        self.mean = nn.Linear(embedding_size, action_size)
        self.log_std = nn.Linear(embedding_size, action_size)
        self.decoder = mlp(embedding_size, decoder_hidden, BALL_STATE_SIZE)
        self.log_std_bounds = log_std_bounds

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        embedding = self.trunk(features)
        low, high = self.log_std_bounds
        # Squash log_std smoothly into its bounds (as CleanRL's SAC does).
        log_std = low + 0.5 * (high - low) * (torch.tanh(self.log_std(embedding)) + 1.0)
        return self.mean(embedding), log_std, embedding

    def decode(self, embedding: torch.Tensor) -> torch.Tensor:
        """The reconstructed ground-truth ball state, scaled by BALL_STATE_SCALE (B, 9)."""
        return self.decoder(embedding)

    def sample(self, features: torch.Tensor, generator: torch.Generator | None = None, std_scale: float = 1.0):
        """(action, log_prob, deterministic action, embedding): a = tanh(u), u ~ N(mean, std),
        log pi(a) = log N(u) - sum log(1 - tanh(u)^2) (the change of variables of the squashing,
        SAC paper appendix C), summed over the action's components.

        ``std_scale`` s (``SacConfig.std_scale``) draws u ~ N(mean, (s std)^2), and log_prob is
        that distribution's plus n log s (n components): the constant the narrower spread adds to
        every log density is left out, so that the entropy bonus keeps its size against the
        rewards (alpha n log(1/s) per step, 0.37 at n = 16, s = 0.1, alpha = 0.01, would
        outweigh them); the gradients are the scaled distribution's."""
        mean, log_std, embedding = self(features)
        std = log_std.exp()
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        u = mean + std_scale * std * noise  # at s = 1 exactly SAC's draw (log s = 0 below)
        log_scale = math.log(std_scale)
        log_prob = squashed_gaussian_log_prob(u, mean, log_std + log_scale) + mean.shape[-1] * log_scale
        return torch.tanh(u), log_prob, torch.tanh(mean), embedding


def squashed_gaussian_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log density (B,) of a = tanh(u) for u ~ N(mean, exp(log_std)^2) per component.
    log(1 - tanh(u)^2) is written as 2 (log 2 - u - softplus(-2u)), which is exact and stable."""
    normal = -0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2.0 * math.pi)
    log_jacobian = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
    return (normal - log_jacobian).sum(dim=-1)


class TwinCritic(nn.Module):
    """Q_1, Q_2 (s, a): two MLPs on [critic features, action]; ``forward`` returns both (B,)."""

    def __init__(self, input_size: int, action_size: int, hidden: Sequence[int]):
        super().__init__()
        self.q1 = mlp(input_size + action_size, hidden, 1)
        self.q2 = mlp(input_size + action_size, hidden, 1)

    def forward(self, features: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([features, action], dim=-1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class DeterministicPolicy(nn.Module):
    """The trained actor as the PolicyController runs it (``systems.policy_controller.as_policy``):
    full observation vectors (B, layout.size) -> tanh of the Gaussian's mean (B, 16), the actor's
    part selection and input scaling included, so that it can be saved and loaded alone.
    ``action``: what the output is (``sac.SacConfig.action``); for "hit_state", ``hit_state`` is
    its ``control.hit_state.HitStateAction`` and the policy plays through
    ``evaluation.controllers.hit_state_controller``, whose layer meets the ball if ``meet_ball``
    (``sac.PlayOptions.meet_ball``); ``hit_memory``: it reads an observation whose predicted hit is
    kept from step to step (``sac.PlayOptions.hit_memory``, ``evaluation.controllers.diagram_params_for``)."""

    def __init__(self, actor: Actor, index: torch.Tensor, scale: torch.Tensor, action: str = "terminal", hit_state=None,
                 meet_ball: bool = False, hit_memory: bool = False):
        super().__init__()
        self.actor = actor
        self.action, self.hit_state, self.meet_ball, self.hit_memory = action, hit_state, meet_ball, hit_memory
        self.register_buffer("index", index.clone())
        self.register_buffer("scale", scale.clone())

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        mean, _, _ = self.actor(observation[:, self.index] / self.scale)
        return torch.tanh(mean)
