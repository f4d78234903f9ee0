"""Collecting episodes from the rally environment: the rollout worker's loop (issue 7).

A ``RolloutWorker`` owns one ``RallyEnv`` and plays whole episodes with one of five behaviours
(``MODES``), returning each as an ``Episode`` (transitions in ``replay.TRANSITION_KEYS`` layout
plus the ``EpisodeSummary`` the event tables read):

- ``"policy"``: the actor, sampled (SAC's exploration: the squashed Gaussian itself).
- ``"ou"``: Ornstein-Uhlenbeck noise in the action box (paper, Methods *Algorithm*: "before
  learning starts, actions are drawn from an Ornstein-Uhlenbeck process"; notes.md): temporally
  correlated exploration, so that consecutive 32 ms segments push the arm the same way.
- ``"demonstrator"``: the model-based returner (``control.returner``) acts, with Gaussian noise
  on a share of its actions (DART, Laskey et al. 2017: the states the returner visits after its
  own small errors, labelled with what it would do there). Every transition also records the
  returner's clean action (``demo_action``) for the learner's behaviour-cloning term
  (``sac`` docstring). This is this project's addition, not the paper's (docs/training.md, *The trainer*).
  When the returner has no action (no track yet, or after its hit), the label and the action are
  ``RallyEnv.hold_action``: continue the committed plan.
- ``"dagger"``: the actor acts as in ``"policy"`` and the returner labels every state it visits
  (DAgger, Ross et al. 2011: the cloning term then learns what to do in the states the actor's
  own errors lead to, which the returner's demonstrations never visit).
- ``"guided"``: as ``"dagger"``, but where the observation's predicted hit is valid and at most
  ``ExplorationParams.guided_window`` s ahead the returner's label is played instead of the
  actor's action (this project's, eq. (12) action only). The replay then holds, at the states the
  actor's own approach leads to, the returner's stroke and what it scored: the critic sees the
  actions the cloning term asks for played out, which neither the actor's narrow exploration nor
  DAgger's labels show it. Measured once, a tenth of the tasks guided changed neither the return
  rate nor, much, the critic, whose target values an action followed by the actor's own
  (docs/experiments/2026-12-07-where-the-actor-loses.md).

Every worker is seeded: worker ``index`` of a run with seed ``s`` draws its episodes from
``numpy.random.SeedSequence([s, index])``, so a run's episodes do not depend on how many workers
collect in parallel *per worker*, and the same seed gives the same episodes.

With the hit-state action (``sac.SacConfig.action``), every mode's action is a hit state y
(``control.hit_state``), stored as the transition's action, and the worker's ``HitStateLayer``
turns it into the environment's eq. (12) action (the supervisor's fallback, as for a returner
without action, when the layer has none). The returner's label is then its planned hit state,
where it plans one at the observation's predicted hit (NaN otherwise: no cloning row); the
demonstrator plays its planned hit state through the layer, with the DART noise added to the hit
state (and plays its own action where it plans no hit).

The near-miss measure (``EpisodeSummary.closest_approach``): the ball centre's distance to the
blade centre at every observation, and between consecutive observations the minimum of the
linearly interpolated relative position (the ball moves ~0.3 m in 32 ms; the racket far less).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.hit_state import HitStateLayer, PlannedHitState
from ace_drake.control.returner import ModelBasedReturner
from ace_drake.learning.replay import TRANSITION_KEYS, EpisodeSummary
from ace_drake.learning.sac import SacConfig, SacLearner
from ace_drake.training.env import RallyEnv, RallyEnvParams

MODES = ("policy", "ou", "demonstrator", "dagger", "guided")
ACTOR_MODES = ("policy", "dagger", "guided")  # the modes in which the actor acts (their workers need its weights)
LABELLED_MODES = ("demonstrator", "dagger", "guided")  # the modes whose episodes carry the returner's labels


@dataclasses.dataclass(frozen=True)
class ExplorationParams:
    """The noise of the non-policy modes.

    ou_theta (1/s), ou_sigma (action units / sqrt(s)): the OU process dx = -theta x dt + sigma dW
    sampled every 32 ms (the paper's values are not public; these give a stationary std of
    sigma / sqrt(2 theta) = 0.5 and a correlation time of 1 / theta = 0.2 s, about a third of an
    incoming ball's flight). demo_noise: std of the Gaussian added to the returner's actions;
    demo_noise_fraction: the share of its steps that get noise (DART). policy_std_scale: the
    ``policy`` mode samples the policy's Gaussian with its standard deviation times this (1: the
    policy's own sampling; below 1 explores less around the mean than the learner draws, e.g. for
    an actor cloned from demonstrations whose untrained spread would spoil every hit). To narrow
    the policy itself, for the learner too, use ``SacConfig.std_scale`` instead. guided_window (s):
    the ``guided`` mode plays the returner's action where the predicted hit is at most this far
    ahead (0.3 s: played there, the returner's actions recover 17.9 of stage 2's actor's 21.9
    points of deficit to the returner on the training distribution,
    docs/experiments/2026-12-07-where-the-actor-loses.md).
    """

    ou_theta: float = 5.0
    ou_sigma: float = 1.58
    demo_noise: float = 0.05
    demo_noise_fraction: float = 0.5
    policy_std_scale: float = 1.0
    guided_window: float = 0.3

    def __post_init__(self) -> None:
        for name in ("ou_theta", "ou_sigma", "demo_noise", "policy_std_scale", "guided_window"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"ExplorationParams.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.demo_noise_fraction <= 1.0:
            raise ValueError(f"ExplorationParams.demo_noise_fraction must be in [0, 1], got {self.demo_noise_fraction}")


class OrnsteinUhlenbeck:
    """Exact discretisation of dx = -theta x dt + sigma dW at step dt (s), per action component,
    started from its stationary distribution; clipped into [-1, 1] when used as an action."""

    def __init__(self, theta: float, sigma: float, dt: float, size: int = ACTION_SIZE):
        self.decay = np.exp(-theta * dt)
        self.stationary_std = sigma / np.sqrt(2.0 * theta) if theta > 0 else sigma * np.sqrt(dt)
        self.step_std = self.stationary_std * np.sqrt(1.0 - self.decay**2)
        self.size = size
        self.x = np.zeros(size)

    def reset(self, rng: np.random.Generator) -> None:
        self.x = rng.normal(0.0, self.stationary_std, self.size)

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        self.x = self.decay * self.x + rng.normal(0.0, self.step_std, self.size)
        return np.clip(self.x, -1.0, 1.0)


@dataclasses.dataclass
class Episode:
    """One ended episode: ``transitions`` (TRANSITION_KEYS, plus ``demo_action`` (n, 16) in the
    LABELLED_MODES), its ``summary`` for the event tables, the ``mode`` that played it, the
    outcome and end condition (``RallyEnv`` info), the skill and the wall time (s)."""

    transitions: dict[str, np.ndarray]
    summary: EpisodeSummary
    mode: str
    outcome: str
    end: str
    skill: np.ndarray
    seconds: float

    @property
    def steps(self) -> int:
        return len(self.transitions["reward"])

    @property
    def returned(self) -> bool:
        return self.outcome == "returned"


def save_episodes(path, episodes: list[Episode]) -> None:
    """Writes episodes to ``path`` (pickle), atomically (a temporary file renamed into place)."""

    path = Path(path)
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "wb") as stream:
        pickle.dump(episodes, stream, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(temporary, path)


def load_episodes(path) -> list[Episode]:
    """Reads the episodes ``save_episodes`` wrote."""

    with open(path, "rb") as stream:
        episodes = pickle.load(stream)
    if not isinstance(episodes, list) or not all(isinstance(e, Episode) for e in episodes):
        raise ValueError(f"{path}: not a file of rollout episodes")
    return episodes


def closest_approach(previous, relative: np.ndarray):
    """The near-miss measure (module docstring): (closest approach so far (m), ``relative`` now),
    from the previous pair (None at the episode's start) and the ball's position relative to the
    blade centre now (3,), m."""
    if previous is None:
        return float(np.linalg.norm(relative)), relative
    closest, before = previous
    step = relative - before
    s = np.clip(-before @ step / max(step @ step, 1e-12), 0.0, 1.0)
    return min(closest, float(np.linalg.norm(before + s * step))), relative


def fallback_action(returner: ModelBasedReturner, obs: np.ndarray, hold) -> np.ndarray:
    """The label of a returner without an action for ``obs``: continuing the committed plan
    (``hold()``, its eq. (12) action) or else heading for the reset pose, whichever the stack
    accepts first (the plan if neither)."""
    q0, v0, a0 = np.split(returner.layout.part(obs, "robot_state"), 3)
    label = returner.driver.first_safe(q0, v0, a0, [hold, lambda: returner.stack.action_towards(q0, v0, a0, returner.stack.reset_pose)])
    return hold() if label is None else label


def demonstrated_action(returner: ModelBasedReturner, obs: np.ndarray, label: np.ndarray, rng: np.random.Generator,
                        exploration: ExplorationParams) -> np.ndarray:
    """What the demonstrator plays for its ``label``: with probability ``demo_noise_fraction`` the
    label plus Gaussian noise (DART), if the stack accepts that segment (noise that would collide
    is not explored), else the label."""
    if rng.random() < exploration.demo_noise_fraction:
        noisy = np.clip(label + rng.normal(0.0, exploration.demo_noise, ACTION_SIZE), -1.0, 1.0)
        q0, v0, a0 = np.split(returner.layout.part(obs, "robot_state"), 3)
        if returner.stack.propose(q0, v0, a0, noisy).safe:
            return noisy
    return label


class RolloutWorker:
    """One environment playing whole episodes (module docstring). ``set_actor`` installs fresh
    actor weights (a ``SacLearner.actor`` state dict); ``collect(episodes, mode)`` plays them.

    Args: env_params (default RallyEnvParams()); sac (a ``sac.SacConfig``: the actor's shape and
    observation parts; default SacConfig()); seed, index: the run's seed and this worker's
    number; exploration: the noise parameters; distribution: a shared ``ShotDistribution``;
    returner: the demonstrating and labelling returner's ``ReturnerParams`` (default ones); play:
    what the actor needs from the diagram it plays in (a ``sac.PlayOptions``; default PlayOptions()).
    """

    def __init__(self, env_params: RallyEnvParams | None = None, sac=None, seed: int = 0, index: int = 0,
                 exploration: ExplorationParams | None = None, distribution=None, returner=None, play=None):

        self.env = RallyEnv(env_params, distribution)
        self.index = index
        self.exploration = exploration or ExplorationParams()
        sequence = np.random.SeedSequence([seed, index])
        env_seed, noise_seed, torch_seed = sequence.generate_state(3)
        self.env.reset(seed=int(env_seed))  # seeds the env's stream; the first episode resets again
        self.rng = np.random.default_rng(int(noise_seed))
        config = sac or SacConfig()
        self.learner = SacLearner(dataclasses.replace(config, seed=int(torch_seed) % 2**31), self.env.params.rally, play=play)
        self._layer = None
        self._planned = None
        self.generator = torch.Generator().manual_seed(int(torch_seed) % 2**63)
        self.noise = OrnsteinUhlenbeck(self.exploration.ou_theta, self.exploration.ou_sigma, self.env.period)
        self._returner = None
        self._returner_params = returner
        self.episodes = 0
        self.steps = 0

    def set_actor(self, state_dict: dict) -> None:
        """Installs actor weights (``SacLearner.actor.state_dict()``)."""
        self.learner.actor.load_state_dict(state_dict)

    @property
    def layer(self):
        """The hit-state layer (``control.hit_state.HitStateLayer``) of the env's rally diagram."""
        if self._layer is None:
            self._layer = HitStateLayer.for_rally(self.env.params.rally, meet_ball=self.learner.play.meet_ball)
        return self._layer

    @property
    def returner(self):
        if self._returner is None:
            self._returner = ModelBasedReturner.for_rally(self.env.params.rally, self._returner_params)
        return self._returner

    def collect(self, episodes: int, mode: str = "policy") -> list[Episode]:
        """Plays ``episodes`` whole episodes with ``mode`` (MODES) and returns them."""
        if mode not in MODES:
            raise ValueError(f"RolloutWorker.collect: mode must be one of {MODES}, got {mode!r}")
        if mode == "guided" and self.learner.config.action != "terminal":
            raise ValueError("RolloutWorker.collect: the guided mode plays the returner's eq. (12) action; the actor's is a hit state")
        return [self._play(mode) for _ in range(episodes)]

    # ------------------------------------------------------------------------------ one episode
    def _play(self, mode: str) -> Episode:
        env = self.env
        start = time.perf_counter()
        obs, info = env.reset()
        if mode == "ou":
            self.noise.reset(self.rng)
        if mode in LABELLED_MODES:
            self.returner.reset()
        rows = {key: [] for key in (*TRANSITION_KEYS, "demo_action")}
        closest = self._blade_distance(None)
        done = False
        while not done:
            if self.learner.config.action == "hit_state":
                action, stored, label = self._hit_state_action(mode, obs)
            else:
                action, label = self._action(mode, obs)
                stored = action
            next_obs, reward, done, _, next_info = env.step(action)
            closest = self._blade_distance(closest)
            for key, value in (("obs", obs), ("privileged", info["privileged"]), ("action", stored), ("reward", reward),
                               ("next_obs", next_obs), ("next_privileged", next_info["privileged"]), ("done", float(done)),
                               ("demo_action", label)):
                rows[key].append(value)
            obs, info = next_obs, next_info
        if mode not in LABELLED_MODES:
            del rows["demo_action"]
        transitions = {key: np.asarray(value, dtype=np.float32) for key, value in rows.items()}
        self.episodes += 1
        self.steps += len(transitions["reward"])
        return Episode(transitions, EpisodeSummary(env.result, closest[0]), mode, info["outcome"], info["end"],
                       info["skill"], time.perf_counter() - start)

    def _action(self, mode: str, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(the action to play, the demonstrator's label or None)."""
        if mode == "policy":
            return self.learner.act(obs, generator=self.generator, std_scale=self.exploration.policy_std_scale), None
        if mode == "ou":
            return self.noise.sample(self.rng), None
        if mode in ("dagger", "guided"):
            label = self._label(obs)
            if mode == "guided" and self.learner.config.layout.hit_within(obs, self.exploration.guided_window):
                return label, label
            return self.learner.act(obs, generator=self.generator, std_scale=self.exploration.policy_std_scale), label
        label = self._label(obs)
        return demonstrated_action(self.returner, obs, label, self.rng, self.exploration), label

    def _hit_state_action(self, mode: str, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(the env's action, the hit state stored as the action, the label or None) of the
        hit-state action (module docstring)."""
        label = None
        if mode in ("demonstrator", "dagger"):
            planned, label, returner_action = self._hit_label(obs)
        if mode == "ou":
            y = self.noise.sample(self.rng)
        elif mode in ("policy", "dagger"):
            y = self.learner.act(obs, generator=self.generator, std_scale=self.exploration.policy_std_scale)
        elif planned is None:  # no planned hit state: the returner's own action
            return self._fallback(obs) if returner_action is None else returner_action, np.zeros(ACTION_SIZE), label
        else:
            y = planned
            if self.rng.random() < self.exploration.demo_noise_fraction:
                y = np.clip(planned + self.rng.normal(0.0, self.exploration.demo_noise, ACTION_SIZE), -1.0, 1.0)
        action = self.layer(obs, y)
        return (self._fallback(obs) if action is None else action), np.asarray(y, dtype=float), label

    def _hit_label(self, obs: np.ndarray) -> tuple[np.ndarray | None, np.ndarray, np.ndarray | None]:
        """(the returner's planned hit state for ``obs``, or None; the label: the same where the
        plan's hit is the observation's predicted one, else NaN; the returner's action where there
        is no planned hit state, else None): ``control.hit_state.PlannedHitState.plan``. The
        fallback for a missing action is left to the one caller that plays it (a collision check
        per step saved in DAgger mode)."""
        if self._planned is None:
            self._planned = PlannedHitState(self.returner, self.layer, hit_memory=self.learner.play.hit_memory)
        planned, at_prediction, action = self._planned.plan(obs)
        label = planned if planned is not None and at_prediction else np.full(ACTION_SIZE, np.nan)
        return planned, label, action

    def _label(self, obs: np.ndarray) -> np.ndarray:
        """The returner's action for ``obs``; when it has none, continuing the plan or else heading
        for the reset pose, whichever the stack accepts first (the plan if neither)."""
        label = self.returner(obs)
        return self._fallback(obs) if label is None else label

    def _fallback(self, obs: np.ndarray) -> np.ndarray:
        """Without an action: ``fallback_action`` with the env's plan."""
        return fallback_action(self.returner, obs, self.env.hold_action)

    def _blade_distance(self, previous):
        """(closest approach so far (m), relative position now): module docstring."""
        return closest_approach(previous, self.env.ball_from_blade())


VECTOR_MODES = MODES


class VectorRolloutWorker:
    """B environments stepped together (``RallyVectorEnv`` on the segment-stepped diagram),
    returning whole episodes as ``RolloutWorker`` does: ``collect(episodes, mode)`` steps the
    batch until at least ``episodes`` episodes have ended and returns those that did (episodes
    still running go on in the next call). Every mode of ``RolloutWorker`` with the eq. (12)
    action: ``"policy"`` (the actor, sampled; one batched forward pass per step), ``"ou"`` (one
    Ornstein-Uhlenbeck process per environment), ``"demonstrator"``, ``"dagger"`` and ``"guided"`` (one
    model-based returner per environment, all sharing one robot model and control stack, each
    reset when its environment's episode starts). An episode is played to its end by the mode it
    started in: after a change of mode, the running episodes finish in theirs (so that an
    episode's labels are all its mode's). The hit-state action plays on ``RolloutWorker``.

    Worker ``index`` of a run with seed ``s`` steps environments index * B ... index * B + B - 1
    (``RallyVectorEnv.first_index``), so the episodes are a function of the seed and the
    environment's number, whatever the number of workers.

    Args: batch, B; the others as ``RolloutWorker``'s (env_params, sac, seed, index, exploration,
    distribution, returner, play).
    """

    def __init__(self, batch: int, env_params: RallyEnvParams | None = None, sac=None, seed: int = 0, index: int = 0,
                 exploration: ExplorationParams | None = None, distribution=None, returner=None, play=None):
        from ace_drake.training.vector_env import RallyVectorEnv  # only vector workers build the segment diagram

        config = sac or SacConfig()
        if config.action != "terminal":
            raise ValueError(f"VectorRolloutWorker: only the eq. (12) action ('terminal') plays batched, got {config.action!r}")
        self.env = RallyVectorEnv(batch, env_params, distribution, first_index=index * batch)
        self.batch = batch
        self.index = index
        self.exploration = exploration or ExplorationParams()
        sequence = np.random.SeedSequence([seed, index])
        env_seed, noise_seed, torch_seed = sequence.generate_state(3)
        self.rng = np.random.default_rng(int(noise_seed))
        self.learner = SacLearner(dataclasses.replace(config, seed=int(torch_seed) % 2**31), self.env.params.rally, play=play)
        self.generator = torch.Generator().manual_seed(int(torch_seed) % 2**63)
        self.noises = [OrnsteinUhlenbeck(self.exploration.ou_theta, self.exploration.ou_sigma, self.env.timing.duration) for _ in range(batch)]
        self._returner_params = returner
        self._returners: list[ModelBasedReturner] | None = None
        self._obs, self._info = self.env.reset(seed=int(env_seed) % 2**31)
        self._modes: list[str | None] = [None] * batch  # the mode each environment's running episode plays
        self._rows = [self._empty_rows() for _ in range(batch)]
        self._started = [time.perf_counter()] * batch
        self._closest = [closest_approach(None, relative) for relative in self.env.ball_from_blade()]
        self._fresh = np.ones(batch, dtype=bool)  # the environment's episode has not stepped yet
        self._restarting = np.zeros(batch, dtype=bool)  # its last step ended an episode: the next one restarts it
        self.episodes = 0
        self.steps = 0

    def set_actor(self, state_dict: dict) -> None:
        """Installs actor weights (``SacLearner.actor.state_dict()``)."""
        self.learner.actor.load_state_dict(state_dict)

    @property
    def returners(self) -> list[ModelBasedReturner]:
        """One model-based returner per environment (built at first use), sharing the robot model
        and the checking control stack of the first."""
        if self._returners is None:
            first = ModelBasedReturner.for_rally(self.env.params.rally, self._returner_params)
            self._returners = [first] + [ModelBasedReturner(physics=first.physics, params=first.params, layout=first.layout, model=first.model,
                                                            stack=first.stack) for _ in range(self.batch - 1)]
        return self._returners

    def collect(self, episodes: int, mode: str = "policy") -> list[Episode]:
        """Steps all B environments until at least ``episodes`` episodes have ended, starting new
        ones in ``mode`` (VECTOR_MODES); returns the ended ones."""
        if mode not in VECTOR_MODES:
            raise ValueError(f"VectorRolloutWorker.collect: mode must be one of {VECTOR_MODES}, got {mode!r}")
        ended: list[Episode] = []
        while len(ended) < episodes:
            for row in np.flatnonzero(self._fresh):
                self._modes[row] = mode
                self._rows[row] = self._empty_rows(mode)
                if mode == "ou":
                    self.noises[row].reset(self.rng)
                if mode in LABELLED_MODES:
                    self.returners[row].reset()
            actions, labels = self._actions()
            obs, rewards, terminated, _, info = self.env.step(actions)
            self._fresh[:] = False
            relative = self.env.ball_from_blade()  # every environment's at once (the kinematics of all B)
            for row in range(self.batch):
                if self._restarting[row]:
                    # NEXT_STEP autoreset: this step started the row's next episode; its action was ignored
                    self._started[row] = time.perf_counter()
                    self._closest[row] = closest_approach(None, relative[row])
                    self._fresh[row] = True
                    continue
                self._closest[row] = closest_approach(self._closest[row], relative[row])
                for key, value in (("obs", self._obs[row]), ("privileged", self._info["privileged"][row]), ("action", actions[row]),
                                   ("reward", rewards[row]), ("next_obs", obs[row]), ("next_privileged", info["privileged"][row]),
                                   ("done", float(terminated[row]))):
                    self._rows[row][key].append(value)
                if "demo_action" in self._rows[row]:
                    self._rows[row]["demo_action"].append(labels[row])
                if terminated[row]:
                    transitions = {key: np.asarray(value, dtype=np.float32) for key, value in self._rows[row].items()}
                    ended.append(Episode(transitions, EpisodeSummary(info["result"][row], self._closest[row][0]), self._modes[row],
                                         str(info["outcome"][row]), str(info["end"][row]), info["skill"][row].copy(),
                                         time.perf_counter() - self._started[row]))
                    self.episodes += 1
                    self.steps += len(transitions["reward"])
            self._restarting = terminated.copy()
            self._obs, self._info = obs, info
        if self._returners is not None:
            for returner in self._returners:
                returner.call_seconds.clear()  # kept per call for analysis; a long run must not keep them all
        return ended

    def _actions(self) -> tuple[np.ndarray, np.ndarray]:
        """(this step's actions (B, 16), the returner's labels (B, 16), NaN where there is none):
        each running environment's by the mode its episode plays (``RolloutWorker._action``'s
        rules); a restarting environment's action is ignored (zeros). (``analysis.learner_probes``
        overrides it, reading ``_fresh`` and ``_obs``: keep them, or change it with them.)"""
        actions = np.zeros((self.batch, ACTION_SIZE))
        labels = np.full((self.batch, ACTION_SIZE), np.nan)
        running = ~self._restarting
        modes = np.array([m if r else "" for m, r in zip(self._modes, running)])
        sampled = np.flatnonzero(np.isin(modes, ACTOR_MODES))
        if sampled.size:
            actions[sampled] = self.learner.act(self._obs[sampled], generator=self.generator, std_scale=self.exploration.policy_std_scale)
        for row in np.flatnonzero(modes == "ou"):
            actions[row] = self.noises[row].sample(self.rng)
        for row in np.flatnonzero(np.isin(modes, LABELLED_MODES)):
            labels[row] = self._label(row)
            if modes[row] == "demonstrator":
                actions[row] = self._demonstrate(row, labels[row])
        guided = modes == "guided"
        if guided.any():  # the returner's action near the hit (module docstring)
            guided &= self.learner.config.layout.hit_within(self._obs, self.exploration.guided_window)
            actions[guided] = labels[guided]
        return actions, labels

    def _label(self, row: int) -> np.ndarray:
        """Environment ``row``'s returner's action for its observation; when it has none, continuing
        the plan or else heading for the reset pose, whichever the stack accepts first (the plan if
        neither): ``RolloutWorker._label``."""
        returner, obs = self.returners[row], np.asarray(self._obs[row], dtype=float)
        label = returner(obs)
        return fallback_action(returner, obs, lambda: self.env.hold_actions([row])[0]) if label is None else label

    def _demonstrate(self, row: int, label: np.ndarray) -> np.ndarray:
        """The demonstrator's action: the label, with DART noise on a share of the steps where the
        noisy segment would be accepted (``RolloutWorker._action``)."""
        return demonstrated_action(self.returners[row], np.asarray(self._obs[row], dtype=float), label, self.rng, self.exploration)

    @staticmethod
    def _empty_rows(mode: str = "policy") -> dict:
        keys = (*TRANSITION_KEYS, "demo_action") if mode in LABELLED_MODES else TRANSITION_KEYS
        return {key: [] for key in keys}
