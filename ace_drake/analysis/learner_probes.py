"""Probes of a trained paper-action actor and its critic, for the studies of docs/experiments/ (not
the product): where on the training distribution the actor loses to the model-based returner, and
whether its critic knows (docs/experiments/2026-12-07-where-the-actor-loses.md).

- ``SubstitutingWorker`` / ``substitution_rollouts``: counterfactual rollouts on the training
  environment (``training.vector_env``, the initial-state distribution the actor is trained on,
  its four end conditions). The actor plays deterministically (the tanh of its mean), and the
  returner's action replaces the actor's where ``substitute`` says: ``"none"`` nowhere,
  ``"stroke"`` at every step whose predicted hit (the observation's ``hit_prediction``) is valid
  and at most ``window`` s ahead, ``"first"`` at the first such step of each episode only (the
  one-step deviation a critic values), ``"returner"`` everywhere (the returner playing alone, no
  DART noise). The returner is the one that labels the actor's DAgger rows, called at every step
  as it is then, so that its memory is what it would be. Each environment's episodes are a
  function of the seed and its number (``RallyVectorEnv``), so two substitutions with one seed meet
  the same shots.
- ``critic_preference``: the critic's view of the same question, on a run's labelled rows: the
  twin critics' minimum at the returner's label against at the actor's deterministic action, and
  whether the critic's ascent direction at the actor's action points towards the label, in bands
  of time to the predicted hit.
- ``critic_against_outcome``: the critic's value of the actions played along episodes (those of
  ``SubstitutingWorker``, say) against what followed them, the discounted terminal reward.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import torch

from ace_drake.config import from_dict
from ace_drake.learning.replay import load_weights_only
from ace_drake.learning.sac import SacConfig, SacLearner, split_play_options
from ace_drake.training.loop import TrainConfig
from ace_drake.training.rollout import VectorRolloutWorker

# Each substitution (module docstring) and the rollout mode it plays in: the actor acts and the
# returner labels ("dagger"), the training's "guided" mode, or the returner alone ("demonstrator").
SUBSTITUTIONS = {"none": "dagger", "stroke": "guided", "first": "dagger", "returner": "demonstrator"}
# Bands of time to the predicted hit (s) for critic_preference; rows without a valid prediction
# form their own band.
HIT_BANDS = ((-np.inf, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.5), (0.5, np.inf))


class SubstitutingWorker(VectorRolloutWorker):
    """A ``VectorRolloutWorker`` whose deterministic actor has the returner's action substituted
    for its own by ``substitute`` (module docstring); ``window`` in s. Play it with
    ``collect(episodes)``: ``distribution`` as ``RallyVectorEnv``'s; the episodes' rows keep the
    returner's label (``demo_action``) beside the action played. "stroke" is the training's
    ``guided`` mode (``training.rollout``) with ``guided_window`` = ``window``."""

    def __init__(self, batch: int, config: TrainConfig, substitute: str, window: float = 0.1, seed: int = 0, distribution=None):
        if substitute not in SUBSTITUTIONS:
            raise ValueError(f"SubstitutingWorker: substitute must be one of {tuple(SUBSTITUTIONS)}, got {substitute!r}")
        if not window >= 0.0:
            raise ValueError(f"SubstitutingWorker: window must be >= 0 s, got {window}")
        exploration = dataclasses.replace(config.exploration, policy_std_scale=0.0, demo_noise_fraction=0.0, guided_window=window)
        super().__init__(batch, config.env, config.sac, seed=seed, exploration=exploration, returner=config.returner, play=config.play,
                         distribution=distribution)
        self.substitute = substitute
        self.window = float(window)
        self._substituted = np.zeros(batch, dtype=bool)  # "first": this episode's substitution is spent

    def collect(self, episodes: int, mode: str | None = None) -> list:
        """Plays until at least ``episodes`` episodes have ended (``VectorRolloutWorker.collect``)
        and returns them, in the substitution's mode (``SUBSTITUTIONS``)."""
        if mode is not None:
            raise ValueError("SubstitutingWorker.collect: the substitution sets the mode")
        return super().collect(episodes, SUBSTITUTIONS[self.substitute])

    def _actions(self) -> tuple[np.ndarray, np.ndarray]:
        self._substituted[self._fresh] = False  # rows starting an episode now
        actions, labels = super()._actions()
        if self.substitute == "first":
            first = self.learner.config.layout.hit_within(self._obs, self.window) & np.isfinite(labels).all(axis=-1) & ~self._substituted
            self._substituted |= first
            actions[first] = labels[first]
        return actions, labels


def substitution_rollouts(config: TrainConfig, actor_state: dict, substitute: str, window: float = 0.1, episodes: int = 1280,
                          seed: int = 0, batch: int = 64, distribution=None) -> dict:
    """The first ``episodes`` episodes to end of a ``SubstitutingWorker`` (``batch`` environments,
    ``seed``; ``distribution``: the shots, default the config's) with the actor weights ``actor_state`` (a ``SacLearner.actor`` state dict): their
    count by outcome and end condition, and the return rate among those with a legal shot (not
    INVALID)."""
    worker = SubstitutingWorker(batch, config, substitute, window, seed, distribution)
    worker.set_actor(actor_state)
    played = []
    while len(played) < episodes:
        played.extend(worker.collect(1))
    played = played[:episodes]
    ends = collections.Counter(f"{e.outcome}/{e.end}" for e in played)
    legal = [e for e in played if e.outcome != "invalid"]
    returned = sum(e.outcome == "returned" for e in legal)
    return {"substitute": substitute, "window_s": window, "episodes": len(played), "legal": len(legal), "returned": returned,
            "return_rate": returned / max(len(legal), 1), "ends": dict(sorted(ends.items()))}


def load_learner(path) -> SacLearner:
    """The learner (actor, averaged actor, critics) of a training checkpoint at ``path``, whole or
    portable."""
    state = load_weights_only(path)["learner"]
    learner = SacLearner(from_dict(SacConfig, split_play_options(state["config"])[0]))
    learner.load_state_dict(state)
    return learner


def critic_preference(learner: SacLearner, rows: dict, actor: str = "actor") -> list[dict]:
    """Per band of time to the predicted hit (``HIT_BANDS``, and "none" for rows without a valid
    prediction): the band's share of ``rows`` (a dict of arrays ``obs``, ``privileged``,
    ``demo_action``: labelled rows, e.g. a whole checkpoint's demonstrations), the mean of
    Q(label) - Q(action) and the share of rows where it is > 0 (Q the twin critics' minimum,
    action the tanh of ``actor``'s mean: "actor" or "averaged"), the mean L1 distance |label -
    action|_1, the mean cosine between the critic's ascent direction in the actor's mean
    (d Q(tanh(mu)) / d mu) and label - action, and the mean norms of that ascent and of the
    cloning term's gradient in the mean at weight 1 (the learner's ``bc_loss``, every row alike:
    ``bc_hit_weight`` left out): what the actor loss weighs against each other, before ``bc_weight``."""
    network = learner.actor if actor == "actor" else learner.averaged_actor
    if network is None:
        raise ValueError(f"critic_preference: the learner has no {actor!r} actor")
    obs = torch.as_tensor(np.asarray(rows["obs"]), dtype=torch.float32)
    label = torch.as_tensor(np.asarray(rows["demo_action"]), dtype=torch.float32)
    critic_input = learner.critic_features(torch.as_tensor(np.asarray(rows["privileged"]), dtype=torch.float32), obs)

    def q(action):
        return torch.minimum(*learner.critic(critic_input, action))

    with torch.no_grad():
        mean = network(learner.actor_features(obs))[0]
    mean = mean.clone().requires_grad_(True)
    q_action = q(torch.tanh(mean))
    ascent = torch.autograd.grad(q_action.sum(), mean)[0]
    error = torch.tanh(mean) - label  # the cloning term's error at weight 1 (sac docstring), per row
    cloning = torch.autograd.grad((error.abs() if learner.config.bc_loss == "absolute" else error**2).sum(), mean)[0]
    with torch.no_grad():
        action = torch.tanh(mean)
        advantage = (q(label) - q_action).numpy()
        toward = label - action
        cosine = ((ascent * toward).sum(-1) / (ascent.norm(dim=-1) * toward.norm(dim=-1)).clamp_min(1e-12)).numpy()
        distance = toward.abs().sum(-1).numpy()
        ascent_norm, cloning_norm = ascent.norm(dim=-1).numpy(), cloning.norm(dim=-1).numpy()
    layout, observations = learner.config.layout, obs.numpy()
    bands = [("none", ~layout.hit_within(observations, np.inf))] + [
        (f"{lo:g}-{hi:g} s", layout.hit_within(observations, hi) & ~layout.hit_within(observations, lo)) for lo, hi in HIT_BANDS]
    table = []
    for name, members in bands:
        n = int(members.sum())
        table.append({"band": name, "share": n / len(members), "rows": n,
                      **({} if n == 0 else {"q_label_minus_action": float(advantage[members].mean()),
                                            "label_preferred": float((advantage[members] > 0).mean()),
                                            "l1_distance": float(distance[members].mean()),
                                            "ascent_cosine": float(cosine[members].mean()),
                                            "ascent_norm": float(ascent_norm[members].mean()),
                                            "cloning_norm": float(cloning_norm[members].mean())})})
    return table


def checkpoint_rows(path, rows: int = 20000, seed: int = 0) -> dict:
    """``rows`` labelled rows drawn without replacement (``seed``) from the demonstrations of the
    whole training checkpoint at ``path`` (a portable one keeps none: ValueError)."""
    buffer = load_weights_only(path)["demonstrations"]
    if buffer is None:
        raise ValueError(f"checkpoint_rows: {path} is a portable checkpoint; its labelled rows were not kept")
    data, size = buffer["buffer"]["data"], buffer["buffer"]["size"]
    chosen = np.sort(np.random.default_rng(seed).choice(size, size=min(rows, size), replace=False))
    return {key: data[key][chosen].numpy() for key in ("obs", "privileged", "demo_action")}


def critic_against_outcome(learner: SacLearner, episodes, window: float = 0.3) -> dict:
    """The twin critics' minimum Q(s, a) at every step of ``episodes`` (``rollout.Episode``, the
    action being the one played) against the step's discounted outcome gamma^(T - 1 - t) r_T (the
    reward is terminal, eq. (10); T the episode's length, gamma the learner's), as means over the
    steps whose predicted hit is at most ``window`` s ahead ("near") and over the others
    ("elsewhere"), with their counts."""
    q_all, outcome_all, near_all = [], [], []
    for episode in episodes:
        t = episode.transitions
        steps = len(t["reward"])
        outcome_all.append(t["reward"][-1] * learner.config.gamma ** (steps - 1 - np.arange(steps)))
        with torch.no_grad():
            obs = torch.as_tensor(t["obs"], dtype=torch.float32)
            features = learner.critic_features(torch.as_tensor(t["privileged"], dtype=torch.float32), obs)
            q_all.append(torch.minimum(*learner.critic(features, torch.as_tensor(t["action"], dtype=torch.float32))).numpy())
        near_all.append(learner.config.layout.hit_within(t["obs"], window))
    q, outcome, near = (np.concatenate(parts) for parts in (q_all, outcome_all, near_all))
    return {name: {"steps": int(members.sum()), "q": float(q[members].mean()) if members.any() else None,
                   "outcome": float(outcome[members].mean()) if members.any() else None}
            for name, members in (("near", near), ("elsewhere", ~near))}
