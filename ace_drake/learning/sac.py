"""Soft Actor-Critic with an asymmetric critic and the paper's auxiliary loss (issue 7).

Paper, Methods *Algorithm*: SAC (Haarnoja et al. 2018) with twin critics and target critics; the
critic reads ground truth from the simulator (asymmetric actor-critic), the actor reads sensor
histories; the policy loss has an auxiliary term reconstructing the ground-truth ball state from
the actor's embedding. The authors' pseudocode (shared/paper/notes.md) adds: Adam with learning
rate 1e-4 for actor and critic, a *fixed* entropy weight (no automatic temperature tuning),
Polyak target updates, and auxiliary weight 1. One ``update`` on a batch of transitions
(s, a, r, s', d) with s = (actor observation o, privileged observation x) does, in this order:

    y        = r + gamma (1 - d) [min_j Q'_j(x', a') - alpha log pi(a' | o')],  a' ~ pi(. | o')
    L_critic = sum_j mean (Q_j(x, a) - y)^2
    L_actor  = mean [alpha log pi(a~ | o) - min_j Q_j(x, a~)] + aux_weight * mean (D(e(o)) - b)^2,
               a~ ~ pi(. | o), e the actor's embedding, D its decoder, b the true ball state
               (both divided by networks.BALL_STATE_SCALE)
    theta'   = tau theta + (1 - tau) theta'

Demonstrations (this project's addition, not the paper's; docs/training.md, *The trainer*): ``update`` may take a
second batch of demonstrated transitions (observations with the model-based returner's actions,
``rollout`` docstring) and then adds a behaviour-cloning term to the actor's loss (Nair et al.
2018, "Overcoming exploration in RL with demonstrations"):

    L_actor += bc_weight * sum_i w_i |tanh(mu(o_i)) - a_i|^2 / sum_i w_i     (mu: the Gaussian's mean)

so that the sparse terminal reward is not the only thing telling 16 action dimensions how to hit
a ball; with ``bc_weight`` 0 (the default) or no demonstration batch, the update is the paper's.
The row weights w_i are 1, or 1 + ``bc_hit_weight`` where the observation's predicted hit is at
most ``bc_hit_window`` s away: the segments that decide the stroke are ~15% of the rows and the
hardest to fit (the cloned actor placed the blade well but swung at a third of the returner's
speed). Measured once, weighting them up did not help: weight 5 returned fewer shots after 40,000
cloning updates than uniform rows (docs/experiments/2026-12-06-paper-action-cloning.md).
Leaving those rows out instead (weight 0, the stroke left to the reward; commit 4ac913a) collapsed
the actor (docs/experiments/2026-12-06-cloning-loss.md).

With ``bc_loss`` "absolute" the term is the same with the absolute error |.|_1 summed over the
components: its minimiser is the labels' conditional median rather than their mean. Near the hit
the returner's labels are close to bang-bang (docs/experiments/2026-12-06-paper-action-cloning.md);
their mean is a slow swing, their median a decisive one. Measured offline, on the same labelled
rows and updates, a fresh actor cloned with it returned 72.6-76.3% of the held-out players' shots
against 56.3-63.2% squared (two seeds; docs/experiments/2026-12-06-cloning-loss.md).

The averaged actor (``SacConfig.actor_average`` > 0; this project's, not the paper's): a Polyak
average of the actor's weights, a <- (1 - r) a + r actor after every update, which the learner's
``policy`` (what is evaluated and exported) reads, while the rollouts play the actor itself. An
average over ~1/r updates smooths the actor's swings between evaluations: the paper-action run's
held-out rate moved by up to 17 points in 10,000 updates (docs/training.md).

The policy's spread (``SacConfig.std_scale`` s < 1; this project's, not the paper's): the policy's
Gaussian is the actor network's with its standard deviation times s, wherever the policy is drawn
from: the Bellman target's a', the actor loss's a~ and the rollouts. Episodes played at a tenth of
the network's spread (``ExplorationParams.policy_std_scale``) while the losses drew at its full
spread asked the critic about actions it had no data for; without a strong cloning term the
actor followed the critic's errors there and collapsed (docs/experiments/2026-12-06-paper-action-five-stages.md).
With s the learner draws where the episodes play. Its log density leaves out the constant n log s
(``networks.Actor.sample``). Measured once at s = 0.1 with the fixed alpha, it collapsed the
paper-action actor within ~1,600 updates (docs/training.md): near the mean the draws no longer
saturate tanh, whose log-Jacobian had held the spread down, and the entropy bonus widened it.

Monte Carlo targets (this project's, not the paper's; ``replay`` docstring: each row stores G, its
discounted return to its episode's end as played). y values an action followed by the policy's own
continuation; G is what did follow it: the returner's strokes after a guided episode's action
(``training.rollout``), the narrow exploring draws after an ordinary one. Two ways to bring G in:

    mixed (SacConfig.mc_mix = beta > 0):  y <- (1 - beta) y + beta G     (the mixed Monte Carlo
          update of Bellemare et al. 2016, "Unifying count-based exploration and intrinsic
          motivation"; beta = 1: the behaviour's Monte Carlo value, no bootstrapping)
    bound (SacConfig.mc_bound):           y <- max(y, G)                 (MCAC, Wilcox et al.
          2022, "Monte Carlo augmented actor-critic for sparse reward deep RL from suboptimal
          demonstrations")

G is the plain return; y is a soft value, which adds the entropy bonus -alpha log pi at every
step to come (alpha = 0.01 per nat: -0.002 to 0.05 per step over the entropies logged in the
2026-12-07 runs, -0.2 to 5 nats), so the two differ by that bonus before the
episode's end. The bound is a lower bound only where outcomes are deterministic. Here they are
not (the same state and action return some balls and miss others), and the bound is optimistic.
Take rows of states the critic cannot tell apart, whose next states it cannot tell apart either:
a share p return (G = G_ret), the others miss (G <= gamma Q, R_miss < 0), and the reward is
terminal. The fixed point of Q = p max(gamma Q, G_ret) + (1 - p) gamma Q is then
Q = p G_ret / (1 - (1 - p) gamma): ~G_ret wherever p >> 1 - gamma (0.99 G_ret at p = 0.6 and
gamma = 0.99), though the expected return is p G_ret + (1 - p) G_miss. Rows without a stored
return (G = -inf, tables of older checkpoints) keep y, with either knob.

The cloning term's fields (``CLONING_FIELDS``), the Monte Carlo targets (``mc_mix``, ``mc_bound``) and the entropy
weight ``alpha`` only shape a loss, and ``actor_average``, ``std_scale`` and ``actor_lr`` do not change the networks: a
learner's state loads into a learner whose config differs in them alone (``STAGE_FIELDS``), so
that a later training stage may change them (a stage starts at its own ``actor_lr``:
``training.checkpoint``).

The action (``SacConfig.action``): "terminal" is the paper's, the 16 components of eq. (12) for
the next segment; "hit_state" (this project's; docs/training.md, *Hit-state actor*) is the
joints' state at the hit (``control.hit_state.HitStateAction``), turned into the eq. (12) action
by a fixed layer outside the learner (``control.hit_state.HitStateLayer``: in the rollout workers
and the policy controller). The critic then values hit states, the replay stores them, and the
cloning term is ``learning.hit_state.HitStateCloning``'s loss on the returner's planned hit
states instead of the squared action error.

d is 1 only at a terminal transition (the episode ended; the rally environment never truncates).
The critic's features are the privileged observation plus the actor observation's parts named in
``SacConfig.critic_observation_parts`` (``networks`` docstring).

Batches are dicts of arrays (NumPy or torch) with keys ``BATCH_KEYS``: obs (B, n_obs),
privileged (B, 28), action (B, 16), reward (B,), next_obs, next_privileged, done (B,); and
``mc_return`` (B,) for the Monte Carlo targets (``replay.EventReplay.sample`` gives it).
"""

from __future__ import annotations

import copy
import dataclasses
import os
from pathlib import Path

import numpy as np
import torch

from ace_drake.config import InputError, from_dict
from ace_drake.contracts import PRIVILEGED_PARTS, ObservationLayout, privileged_slice
from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.hit_state import HitStateAction
from ace_drake.control.params import RallyParams
from ace_drake.learning.hit_state import HitStateCloning
from ace_drake.learning.networks import (
    BALL_STATE_SCALE,
    Actor,
    DeterministicPolicy,
    TwinCritic,
    observation_scale,
    privileged_scale,
)

ACTIONS = ("terminal", "hit_state")
# SacConfig's fields that only weigh the cloning term (module docstring).
CLONING_FIELDS = ("bc_weight", "bc_loss", "bc_hit_weight", "bc_hit_window")
# SacConfig's fields a later training stage may change: a learner's state loads across them (module docstring).
STAGE_FIELDS = CLONING_FIELDS + ("actor_average", "std_scale", "actor_lr", "alpha", "mc_mix", "mc_bound")
CLONING_LOSSES = ("squared", "absolute")  # SacConfig.bc_loss (module docstring)
BATCH_KEYS = ("obs", "privileged", "action", "reward", "next_obs", "next_privileged", "done")
PRIVILEGED_SIZE = sum(PRIVILEGED_PARTS.values())


@dataclasses.dataclass(frozen=True)
class SacConfig:
    """Every hyper-parameter of the learner, with where its default comes from."""

    actor_lr: float = 1e-4  # notes.md: Adam, learning rate 1e-4 for the actor
    critic_lr: float = 1e-4  # notes.md: Adam, learning rate 1e-4 for the critic
    # The paper gives none. An episode lasts ~17 policy steps (0.55 s / 32 ms) and its reward is
    # terminal, so 0.99 discounts the first step's return by only ~16 %.
    gamma: float = 0.99
    # notes.md: a fixed entropy weight, value not public. Rewards are O(1) and terminal; with 16
    # action dimensions 0.01 keeps the entropy bonus (~0.01 x 16 nats per step) below them.
    alpha: float = 0.01
    tau: float = 0.005  # Polyak factor (notes.md: Polyak updates; value not public; SAC paper's)
    aux_weight: float = 1.0  # notes.md: decoder MSE with weight 1 added to the policy loss
    batch_size: int = 256  # not public; the SAC paper's
    # Network sizes: not public. Two 256-wide layers as in the SAC paper.
    actor_hidden: tuple[int, ...] = (256, 256)
    embedding_size: int = 256  # the actor's embedding (trunk output) that the decoder reads
    decoder_hidden: tuple[int, ...] = (256,)
    critic_hidden: tuple[int, ...] = (256, 256)
    log_std_bounds: tuple[float, float] = (-5.0, 2.0)  # pre-tanh log std range (CleanRL's SAC)
    # The paper's s_t (Methods *States*): histories, robot and end-effector state, skill; the
    # EKF estimate in the observation vector is for classical controllers only.
    actor_observation_parts: tuple[str, ...] = ("positions", "spins", "robot_state", "end_effector", "skill")
    # Added to the privileged observation for the critic (networks docstring).
    critic_observation_parts: tuple[str, ...] = ("robot_state",)
    # The behaviour-cloning term's weight (module docstring; this project's, 0: the paper's SAC).
    bc_weight: float = 0.0
    # The cloning term's error (module docstring): "squared" (the mean of the labels) or "absolute"
    # (their median). Terminal action only.
    bc_loss: str = "squared"
    # The cloning term's extra weight on rows whose predicted hit is at most bc_hit_window s away
    # (module docstring; 0: every row alike). Terminal action only.
    bc_hit_weight: float = 0.0
    bc_hit_window: float = 0.1
    # What the actor outputs (module docstring): "terminal" (eq. (12), the paper's) or "hit_state".
    action: str = "terminal"
    # The hit-state cloning loss (learning.hit_state): its consistency weight (30 measured best of
    # 0-100: docs/experiments/2026-12-01-hit-state-actor.md) and the task-space scales (blade position m, normal, blade velocity m/s).
    consistency_weight: float = 30.0
    hit_loss_scales: tuple[float, float, float] = (0.02, 0.05, 0.2)
    # The averaged actor's rate r per update (module docstring; 0: none, the policy is the actor).
    actor_average: float = 0.0
    # The policy's spread s (module docstring): its Gaussian's standard deviation is the actor
    # network's times s, in the Bellman target, the actor loss and the rollouts alike (1: SAC's).
    std_scale: float = 1.0
    # Monte Carlo targets (module docstring), G the row's return: the target (1 - mc_mix) y + mc_mix G
    # (0: the paper's y), then max(y, G) with mc_bound (MCAC).
    mc_mix: float = 0.0
    mc_bound: bool = False
    position_history: int = 10  # the ObservationLayout the learner reads (N_p, N_s)
    spin_history: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("actor_lr", "critic_lr", "tau", "batch_size", "embedding_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SacConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 < self.std_scale <= 1.0:
            raise ValueError(f"SacConfig.std_scale must be in (0, 1] (1: the actor network's spread), got {self.std_scale}")
        if not 0.0 <= self.mc_mix <= 1.0:
            raise ValueError(f"SacConfig.mc_mix must be in [0, 1] (0: no Monte Carlo return in the target), got {self.mc_mix}")
        if not 0.0 <= self.actor_average <= 1.0:
            raise ValueError(f"SacConfig.actor_average must be in [0, 1] (0: no averaged actor), got {self.actor_average}")
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"SacConfig.gamma must be in [0, 1), got {self.gamma}")
        if not self.tau <= 1.0:
            raise ValueError(f"SacConfig.tau must be in (0, 1], got {self.tau}")
        if not (self.alpha >= 0.0 and self.aux_weight >= 0.0 and self.bc_weight >= 0.0):
            raise ValueError(f"SacConfig.alpha, aux_weight and bc_weight must be >= 0, got {self.alpha}, {self.aux_weight}, {self.bc_weight}")
        if not (self.bc_hit_weight >= 0.0 and self.bc_hit_window > 0.0):
            raise ValueError(f"SacConfig: bc_hit_weight must be >= 0 and bc_hit_window > 0 s, got {self.bc_hit_weight}, {self.bc_hit_window}")
        if self.bc_loss not in CLONING_LOSSES:
            raise ValueError(f"SacConfig.bc_loss must be one of {CLONING_LOSSES}, got {self.bc_loss!r}")
        if self.bc_loss != "squared" and self.action != "terminal":
            raise ValueError("SacConfig.bc_loss is the terminal action's cloning error; the hit_state action has its own loss")
        if self.bc_hit_weight != 0.0 and self.action != "terminal":
            raise ValueError("SacConfig.bc_hit_weight weights the terminal action's cloning term; the hit_state action has its own loss")
        if self.action not in ACTIONS:
            raise ValueError(f"SacConfig.action must be one of {ACTIONS}, got {self.action!r}")
        if self.action == "hit_state" and not {"robot_state", "hit_prediction"} <= set(self.actor_observation_parts):
            raise ValueError("SacConfig: the hit_state action needs robot_state and hit_prediction among actor_observation_parts "
                             "(the hit state is relative to the segment start, and its hit is the predicted one)")
        if not (self.consistency_weight >= 0.0 and len(self.hit_loss_scales) == 3 and all(x > 0 for x in self.hit_loss_scales)):
            raise ValueError(f"SacConfig: consistency_weight must be >= 0 and hit_loss_scales three values > 0, "
                             f"got {self.consistency_weight}, {self.hit_loss_scales}")

    @property
    def layout(self) -> ObservationLayout:
        return ObservationLayout(self.position_history, self.spin_history)


def learner_config_differences(saved: dict, mine: dict) -> list[str]:
    """The fields of ``mine`` (a SacConfig as a dict) in which ``saved`` differs, but for those a
    later stage may change (``STAGE_FIELDS``): a learner's state loads only where this is empty."""
    return sorted(k for k in mine if saved.get(k) != mine[k] and k not in STAGE_FIELDS)


def soft_target(reward, done, next_q1, next_q2, next_log_prob, gamma: float, alpha: float):
    """The soft Bellman target y = r + gamma (1 - d) (min(Q'_1, Q'_2) - alpha log pi(a'|s'))."""
    return reward + gamma * (1.0 - done) * (torch.minimum(next_q1, next_q2) - alpha * next_log_prob)


@dataclasses.dataclass(frozen=True)
class PlayOptions:
    """What a policy needs from the diagram it plays in: not a learner hyper-parameter (the
    learner's losses and updates are the same either way). Stored beside the SacConfig in a policy
    artefact (``save_policy``) and read where the actor plays: the rollout workers and the policy
    controller (``evaluation.controllers``). This project's, both."""

    # The hit-state layer moves the actor's q_hit so the blade meets the predicted ball
    # (control.hit_state, HitStateLayer.meet_ball).
    meet_ball: bool = False
    # The actor reads an observation whose predicted hit is kept from step to step (RallyParams.
    # hit_memory): the training env's diagram must be built with it (TrainConfig checks), and the
    # policy's diagram is (evaluation.controllers.diagram_params_for).
    hit_memory: bool = False


PLAY_OPTIONS = tuple(field.name for field in dataclasses.fields(PlayOptions))


def split_play_options(sac: dict) -> tuple[dict, dict]:
    """A SacConfig mapping as (the SacConfig's fields, the PlayOptions' fields): those written
    before PlayOptions (policy artefacts, checkpoints and sidecars) hold its fields among the
    learner's."""
    return {k: v for k, v in sac.items() if k not in PLAY_OPTIONS}, {k: v for k, v in sac.items() if k in PLAY_OPTIONS}


def _require_finite(loss: torch.Tensor, which: str) -> None:
    """Raises FloatingPointError before a non-finite ``loss`` reaches the networks: one such step
    turns every weight into NaN, and a run that went on would write them into its checkpoints.
    (Not atomic across the update: when the actor's loss is the non-finite one, the critic has
    already taken its step on its own finite loss.)"""
    if not torch.isfinite(loss):
        taken = ("the actor did not step; the critic had already stepped on its finite loss" if which == "actor"
                 else "no network stepped")
        raise FloatingPointError(f"SacLearner.update: the {which} loss is {loss.item()} (a non-finite or overflowing batch); {taken}")


class SacLearner:
    """The learner: actor, twin critics, target critics and their Adam optimisers (module
    docstring). Seeded by ``config.seed``: network initialisation and every sampled action come
    from its own torch generator, so the same seed and batches give the same updates, bit for
    bit, and a learner restored from ``state_dict`` continues exactly as the original would."""

    def __init__(self, config: SacConfig | None = None, rally=None, hit_state_action=None, play: PlayOptions | None = None):
        """``rally``: the RallyParams of the diagram the actor plays in (default RallyParams()),
        read only by the hit-state action's cloning loss and parameterisation;
        ``hit_state_action``: the hit-state parameterisation (``control.hit_state.HitStateAction``)
        if not the one of ``rally``'s command limits (a loaded artefact's own); ``play``: what
        its policy needs from the diagram it plays in (``PlayOptions``)."""
        self.config = config or SacConfig()
        self.play = play or PlayOptions()
        self.rally = rally
        self._hit_cloning = None
        self._hit_state_action = hit_state_action
        c = self.config
        layout = c.layout
        self.generator = torch.Generator().manual_seed(c.seed)
        obs_scale = observation_scale(layout)
        self._actor_index = torch.as_tensor(layout.indices(c.actor_observation_parts))
        self._critic_obs_index = torch.as_tensor(layout.indices(c.critic_observation_parts))
        self._actor_scale = torch.as_tensor(obs_scale, dtype=torch.float32)[self._actor_index]
        self._critic_scale = torch.cat([
            torch.as_tensor(privileged_scale(), dtype=torch.float32),
            torch.as_tensor(obs_scale, dtype=torch.float32)[self._critic_obs_index],
        ])
        self._ball_slice = privileged_slice("ball_state")
        self._ball_scale = torch.as_tensor(BALL_STATE_SCALE, dtype=torch.float32)
        self.observation_size = layout.size
        with torch.random.fork_rng(devices=[]):  # seed the initial weights, leave the global stream
            torch.manual_seed(c.seed)
            self.actor = Actor(len(self._actor_index), ACTION_SIZE, c.actor_hidden, c.embedding_size, c.decoder_hidden, c.log_std_bounds)
            self.critic = TwinCritic(len(self._critic_scale), ACTION_SIZE, c.critic_hidden)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        # the Polyak average of the actor (module docstring), or None
        self.averaged_actor = copy.deepcopy(self.actor).requires_grad_(False) if c.actor_average > 0 else None
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=c.actor_lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=c.critic_lr)
        self.updates = 0

    # ------------------------------------------------------------------------------ features
    def actor_features(self, obs: torch.Tensor) -> torch.Tensor:
        """The actor's scaled input (B, n) from full observation vectors (B, layout.size)."""
        return obs[:, self._actor_index] / self._actor_scale

    def critic_features(self, privileged: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """The critic's scaled input: [privileged, the observation's critic parts] (B, n)."""
        return torch.cat([privileged, obs[:, self._critic_obs_index]], dim=-1) / self._critic_scale

    # ------------------------------------------------------------------------------ acting
    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False, generator: torch.Generator | None = None,
            std_scale: float = 1.0) -> np.ndarray:
        """Actions (..., 16) in [-1, 1] for observations (..., layout.size); sampled with
        ``generator`` (default: the learner's own) unless ``deterministic`` (tanh of the mean).
        ``std_scale`` multiplies the policy's standard deviation (the actor network's times
        ``SacConfig.std_scale``; 1: the policy itself)."""
        obs_t = torch.as_tensor(np.atleast_2d(obs), dtype=torch.float32)
        if deterministic:
            out = self.actor.sample(self.actor_features(obs_t), generator or self.generator)[2].numpy()
        else:
            mean, log_std, _ = self.actor(self.actor_features(obs_t))
            noise = torch.randn(mean.shape, generator=generator or self.generator, dtype=mean.dtype)
            out = torch.tanh(mean + std_scale * self.config.std_scale * log_std.exp() * noise).numpy()
        return out.reshape(*np.shape(obs)[:-1], ACTION_SIZE)

    def policy(self, actor_state: dict | None = None) -> DeterministicPolicy:
        """A copy of the policy's actor (``policy_actor``, or the actor with the weights
        ``actor_state``) as a standalone deterministic policy module (networks), with its action
        kind and, for hit states, their parameterisation."""
        actor = copy.deepcopy(self.actor if actor_state is not None else self.policy_actor)
        if actor_state is not None:
            actor.load_state_dict(actor_state)
        return DeterministicPolicy(actor.eval().requires_grad_(False), self._actor_index, self._actor_scale,
                                   self.config.action, self.hit_state_action, self.play.meet_ball, self.play.hit_memory)

    @property
    def policy_actor(self) -> torch.nn.Module:
        """The actor that is evaluated and exported: the averaged one if the config keeps one
        (``actor_average``), else the actor itself."""
        return self.actor if self.averaged_actor is None else self.averaged_actor

    @property
    def hit_state_action(self):
        """The hit-state parameterisation (``control.hit_state.HitStateAction``) of a hit-state
        learner, None for the terminal action."""
        if self.config.action != "hit_state":
            return None
        if self._hit_state_action is None:
            self._hit_state_action = self.hit_cloning.parameterisation
        return self._hit_state_action

    def set_actor_lr(self, lr: float) -> None:
        """Sets the actor optimiser's learning rate (a schedule: ``trainer``); the optimiser's
        state keeps it, so a restored learner continues at it."""
        for group in self.actor_optimizer.param_groups:
            group["lr"] = float(lr)

    @property
    def hit_cloning(self):
        """The hit-state cloning loss (``learning.hit_state.HitStateCloning``), built on first use."""
        if self._hit_cloning is None:
            c = self.config
            self._hit_cloning = HitStateCloning(self.rally or RallyParams(), c.layout, c.hit_loss_scales, c.consistency_weight)
        return self._hit_cloning

    # ------------------------------------------------------------------------------ losses
    def _tensors(self, batch: dict) -> dict[str, torch.Tensor]:
        missing = [key for key in BATCH_KEYS if key not in batch]
        if missing:
            raise KeyError(f"SacLearner: the batch lacks {missing}; expected keys {BATCH_KEYS}")
        keys = BATCH_KEYS + (("mc_return",) if "mc_return" in batch else ())
        return {key: torch.as_tensor(np.asarray(batch[key]), dtype=torch.float32) for key in keys}

    @property
    def uses_returns(self) -> bool:
        """Whether the critic's target reads the rows' Monte Carlo returns (``mc_mix``, ``mc_bound``)."""
        return self.config.mc_mix > 0.0 or self.config.mc_bound

    @torch.no_grad()
    def target(self, batch: dict) -> torch.Tensor:
        """The critic's target (B,): the soft Bellman target y of the module docstring (samples a'
        from the actor), with the Monte Carlo return mixed in (``mc_mix``) and bounding it
        (``mc_bound``) where the config asks (module docstring)."""
        b = batch if isinstance(batch.get("reward"), torch.Tensor) else self._tensors(batch)
        y = self._mixed_target(b)
        return torch.maximum(y, b["mc_return"]) if self.config.mc_bound else y

    def _mixed_target(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        """The target before the Monte Carlo bound: y, or its mixture with G (``mc_mix``)."""
        if self.uses_returns and "mc_return" not in b:
            raise KeyError("SacLearner: SacConfig.mc_mix and mc_bound need the batch's mc_return (the replay's Monte Carlo returns)")
        c = self.config
        next_action, next_log_prob, _, _ = self.actor.sample(self.actor_features(b["next_obs"]), self.generator, c.std_scale)
        next_q1, next_q2 = self.target_critic(self.critic_features(b["next_privileged"], b["next_obs"]), next_action)
        y = soft_target(b["reward"], b["done"], next_q1, next_q2, next_log_prob, c.gamma, c.alpha)
        if c.mc_mix > 0.0:
            stored = torch.isfinite(b["mc_return"])
            y = torch.where(stored, (1.0 - c.mc_mix) * y + c.mc_mix * torch.where(stored, b["mc_return"], 0.0), y)
        return y

    def auxiliary_loss(self, embedding: torch.Tensor, privileged: torch.Tensor) -> torch.Tensor:
        """The paper's auxiliary loss: MSE of the decoded ball state against the true one (the
        privileged observation's ball part), both divided by BALL_STATE_SCALE."""
        truth = privileged[:, self._ball_slice] / self._ball_scale
        return torch.mean((self.actor.decode(embedding) - truth) ** 2)

    def behaviour_cloning_loss(self, demonstrations: dict) -> torch.Tensor:
        """The weighted mean of |tanh(mu(o)) - a_demo|^2 (or |.|_1, ``bc_loss``) over a
        demonstration batch (keys ``obs``, ``demo_action``; weights ``cloning_weights``); for the
        hit-state action, ``HitStateCloning.loss`` (``demo_action`` then holds hit states)."""
        obs = torch.as_tensor(np.asarray(demonstrations["obs"]), dtype=torch.float32)
        target = torch.as_tensor(np.asarray(demonstrations["demo_action"]), dtype=torch.float32)
        mean, _, _ = self.actor(self.actor_features(obs))
        if self.config.action == "hit_state":
            return self.hit_cloning.loss(obs, torch.tanh(mean), target)
        difference = torch.tanh(mean) - target
        error = torch.sum(difference.abs() if self.config.bc_loss == "absolute" else difference ** 2, dim=-1)
        if self.config.bc_hit_weight == 0.0:
            return torch.mean(error)
        weights = self.cloning_weights(obs)
        return torch.sum(weights * error) / torch.sum(weights)

    def cloning_weights(self, obs: torch.Tensor) -> torch.Tensor:
        """The cloning term's row weights (B,) for full observations (B, layout.size): 1, or
        1 + ``bc_hit_weight`` where the hit prediction is valid and at most ``bc_hit_window`` s
        ahead (module docstring)."""
        near = self.config.layout.hit_within(obs, self.config.bc_hit_window)
        return 1.0 + self.config.bc_hit_weight * near.to(obs.dtype)

    def update(self, batch: dict, demonstrations: dict | None = None, bc_weight: float | None = None) -> dict[str, float]:
        """One SAC update (critic, then actor, then targets) on ``batch``; returns the losses and
        diagnostics: critic_loss, actor_loss (policy + weighted auxiliary [+ weighted cloning]),
        policy_loss, aux_loss, entropy (mean -log pi), q_mean, target_mean, and bc_loss when a
        demonstration batch is given (``bc_weight`` overrides the config's, e.g. for annealing),
        and with the Monte Carlo bound mc_bound_share (the share of rows whose target it raised)."""
        c = self.config
        bc_weight = c.bc_weight if bc_weight is None else bc_weight
        b = self._tensors(batch)
        with torch.no_grad():
            y = self._mixed_target(b)
            bound_share = None
            if c.mc_bound:  # the rows whose target the bound raises (not the terminal ones, where G = y)
                bound_share = (b["mc_return"] > y).float().mean().item()
                y = torch.maximum(y, b["mc_return"])
        critic_input = self.critic_features(b["privileged"], b["obs"])
        q1, q2 = self.critic(critic_input, b["action"])
        critic_loss = torch.mean((q1 - y) ** 2) + torch.mean((q2 - y) ** 2)
        _require_finite(critic_loss, "critic")
        self.critic_optimizer.zero_grad()
        critic_loss.backward()
        self.critic_optimizer.step()

        action, log_prob, _, embedding = self.actor.sample(self.actor_features(b["obs"]), self.generator, c.std_scale)
        q1_pi, q2_pi = self.critic(critic_input, action)
        policy_loss = torch.mean(c.alpha * log_prob - torch.minimum(q1_pi, q2_pi))
        aux_loss = self.auxiliary_loss(embedding, b["privileged"])
        actor_loss = policy_loss + c.aux_weight * aux_loss
        bc_loss = None
        if demonstrations is not None and bc_weight > 0.0:
            bc_loss = self.behaviour_cloning_loss(demonstrations)
            actor_loss = actor_loss + bc_weight * bc_loss
        _require_finite(actor_loss, "actor")
        self.actor_optimizer.zero_grad()
        actor_loss.backward()  # also reaches the critic's grads, which its next zero_grad clears
        self.actor_optimizer.step()

        with torch.no_grad():
            for target, source in zip(self.target_critic.parameters(), self.critic.parameters()):
                target.mul_(1.0 - c.tau).add_(c.tau * source)
            if self.averaged_actor is not None:
                for average, source in zip(self.averaged_actor.parameters(), self.actor.parameters()):
                    average.mul_(1.0 - c.actor_average).add_(c.actor_average * source)
        self.updates += 1
        return {
            **({} if bc_loss is None else {"bc_loss": bc_loss.item()}),
            **({} if bound_share is None else {"mc_bound_share": bound_share}),
            "critic_loss": critic_loss.item(),
            "actor_loss": actor_loss.item(),
            "policy_loss": policy_loss.item(),
            "aux_loss": aux_loss.item(),
            "entropy": -log_prob.mean().item(),
            "q_mean": 0.5 * (q1.mean() + q2.mean()).item(),
            "target_mean": y.mean().item(),
        }

    # ------------------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue exactly: networks, optimisers, the sampling generator's
        state, the update count and the config (a dict, to check on load)."""
        return {
            "config": dataclasses.asdict(self.config),
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "target_critic": self.target_critic.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "updates": self.updates,
            **({} if self.averaged_actor is None else {"averaged_actor": self.averaged_actor.state_dict()}),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restores a ``state_dict``; raises ValueError if it was written with another config (a
        field added since it was written counts as its default)."""
        mine = dataclasses.asdict(self.config)
        config = split_play_options(state["config"])[0]  # play options written among the learner's: not the learner's
        written = {**{k: v for k, v in dataclasses.asdict(SacConfig()).items() if k not in config}, **config}
        saved = {k: tuple(v) if isinstance(v, list) else v for k, v in written.items()}
        differing = learner_config_differences(saved, mine)
        if differing:
            raise ValueError(f"SacLearner.load_state_dict: the checkpoint's config differs in {differing}")
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.load_state_dict(state["target_critic"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.generator.set_state(state["generator"])
        self.updates = int(state["updates"])
        if self.averaged_actor is not None:  # an earlier stage without one: the average starts at its actor
            self.averaged_actor.load_state_dict(state.get("averaged_actor", state["actor"]))


POLICY_FORMAT = 1


def save_policy(path, learner: SacLearner, actor_state: dict | None = None) -> None:
    """Writes a policy artefact: the SacConfig and the PlayOptions (as dicts) and the actor's
    weights (``actor_state``, default the learner's policy actor), atomically. A few hundred kB."""

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    payload = {"format": POLICY_FORMAT, "sac_config": dataclasses.asdict(learner.config), "play": dataclasses.asdict(learner.play),
               "actor": actor_state or learner.policy_actor.state_dict()}
    if learner.hit_state_action is not None:
        payload["hit_state"] = learner.hit_state_action.as_dict()
    torch.save(payload, temporary)
    os.replace(temporary, path)


def load_policy(path) -> DeterministicPolicy:
    """The DeterministicPolicy of a ``save_policy`` artefact (what ``policy:<name>`` runs). An
    artefact written before PlayOptions holds its fields in its SacConfig: read from there."""

    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)  # tensors and plain containers only
    except Exception as error:  # torch raises several kinds for a file that is not its own
        raise InputError(f"{path}: not a policy artefact ({type(error).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != POLICY_FORMAT:
        raise InputError(f"{path}: not a policy artefact (format {POLICY_FORMAT})")
    hit_state_action = None
    if "hit_state" in payload:  # the hit-state parameterisation it was trained with, not today's default

        hit_state_action = HitStateAction.from_dict(payload["hit_state"])
    sac, play = split_play_options(payload["sac_config"])
    learner = SacLearner(from_dict(SacConfig, sac), hit_state_action=hit_state_action, play=from_dict(PlayOptions, payload.get("play", play)))
    return learner.policy(payload["actor"])  # the weights written (the averaged actor's, if it had one)
