"""``ace-drake train CONFIG``: the training run (issue 7; paper, Methods *Algorithm* and
shared/paper/notes.md).

A run lives in one directory (``run_dir``) and goes through four phases, each resumable:

1. ``demonstrations`` (this project's addition; 0 episodes in the paper's setting): the rollout
   workers play ``demonstrations`` episodes with the model-based returner (``rollout``), or the
   episodes are read from ``demonstration_files``. They enter the replay tables like any episode
   and the demonstration buffer of the behaviour-cloning term (``sac``).
2. ``ou``: ``ou_episodes`` episodes of Ornstein-Uhlenbeck exploration before learning starts
   (paper; notes.md).
3. ``pretrain``: ``pretrain_updates`` learner updates on what was collected, with the cloning
   weight ``pretrain_bc_weight`` (none in the paper's setting); the actor is evaluated after them
   and, with ``pretrain_evaluate_every``, every that many updates on the way (each followed by a
   checkpoint).
4. ``learn``: asynchronous collection and learning until ``env_steps`` environment steps: every
   worker always has a task in flight (``episodes_per_task`` episodes with the latest actor); the
   learner updates as long as it is below ``updates_per_step`` updates per collected step and
   otherwise waits for episodes; fresh weights go to every task submitted after an update chunk.
   The cloning weight goes linearly from ``bc_weight_start`` (default ``sac.bc_weight``) to
   ``bc_weight_final`` over the phase (or over its first ``bc_fade_steps`` steps, and stays
   there), and the actor's learning rate from ``sac.actor_lr`` to ``actor_lr_final`` if that is
   given (a schedule lets the actor settle on a precise fit by the end of a run; the paper's is
   fixed). With ``learn_mode`` "dagger" the returner labels the states the actor visits (all of
   them, or the episodes of a ``dagger_fraction`` of the tasks); a ``guided_fraction`` of the
   other tasks plays the returner's action near the predicted hit (``rollout``'s "guided" mode).

A rollout task that raises (an environment's simulation failing) or whose worker dies costs its
episodes, not the run: the worker is replaced by a fresh one with another seed, the failure is
logged with the worker's traceback (``run_dir/worker_failures.log``) and counted (per stage);
more than ``max_worker_failures`` stop the run (its last checkpoint stays). A periodic
evaluation that fails (in the learner's process) is logged the same way
(``run_dir/evaluation_failures.log``), counted and skipped; more than ``max_worker_failures`` of
those stop the run too.

Every ``checkpoint_every`` steps the whole learner state (networks, optimisers, generator, replay
tables, demonstrations, counters, history) is written atomically to ``checkpoint.pt`` (a
temporary file, flushed to disk, renamed over the old one, which is kept as ``checkpoint.prev.pt``),
so a killed run loses only the work since then; ``train`` on the same directory resumes from it
(from the previous one, with a warning, if the latest cannot be read or is missing) (the workers
are reseeded from the run's seed, the number of resumptions and the number of failed tasks, so a
resumed run is reproducible but not identical to an uninterrupted one). Every
``evaluate_every`` steps the deterministic policy actor (``SacLearner.policy_actor``: the averaged one where
the learner keeps an average) is evaluated in the rally diagram
(``evaluation.evaluate.play``) on ``evaluation_episodes`` shots, each ``evaluation_repeats``
times with successive seeds; the best evaluated actor is
kept (and, with ``heldout_players``, also on all of those players' shots, as many times, for the
curve only).
Logs go to TensorBoard (``run_dir/tensorboard``) and progress lines to the ``progress`` callable.
``export.export`` writes a policy artefact (``models/policies/<name>.pt``), its sidecar JSON and
the learning curve PNG.

This module is the loop (``TrainConfig``, ``Trainer``); ``training.checkpoint`` saves, loads and
resumes a run (and holds ``Progress``, the counters a checkpoint records), ``training.export`` writes its artefacts.
"""

from __future__ import annotations

import dataclasses
import math
import time
import traceback
from collections import deque
from pathlib import Path

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

from ace_drake.config import MODELS_DIR, ConfigError, InputError, from_dict, load_yaml
from ace_drake.control.params import RallyParams, ReturnerParams
from ace_drake.evaluation.evaluate import play, summarize
from ace_drake.learning.mirror import Mirror
from ace_drake.learning.replay import DemonstrationBuffer, EventReplay, ReplayConfig
from ace_drake.learning.sac import STAGE_FIELDS, PlayOptions, SacConfig, SacLearner, learner_config_differences
from ace_drake.perception.params import PerceptionParams
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.play.shots import human_shots, make_distribution
from ace_drake.training.checkpoint import Checkpointing, Progress, latest_checkpoint, read_checkpoint, schedule_progress
from ace_drake.training.env import RallyEnvParams
from ace_drake.training.rollout import Episode, ExplorationParams, load_episodes
from ace_drake.training.stages import earlier_stage_checkpoint, earlier_stage_from, with_earlier_stages
from ace_drake.training.workers import WorkerFailed, WorkerPool


EVALUATION_BATCH = 32  # episodes at a time of a batched run's evaluations (segment-stepped diagram)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """A training run (module docstring). Steps are environment steps (32 ms policy steps) of
    every mode, demonstrations included."""

    name: str = "rally"  # the exported policy's name: models/policies/<name>.pt
    seed: int = 0
    env_steps: int = 200_000
    workers: int = 2
    backend: str = "ray"  # "ray" or "local" (one in-process worker, for debugging)
    address: str = ""  # a Ray cluster's address; "" starts a local cluster
    episodes_per_task: int = 4  # per worker task; with batch, per environment of the worker's batch
    # Environments per rollout worker: 0 plays one RallyEnv (the continuous-time reference
    # diagram) per worker; B >= 1 a RallyVectorEnv of B environments on the segment-stepped
    # diagram (issue 29; every mode, with the eq. (12) action), and the evaluations run on the
    # segment-stepped diagram too, EVALUATION_BATCH episodes at a time.
    batch: int = 0
    demonstrations: int = 0  # returner episodes before learning (this project's; the paper: 0)
    demonstration_files: tuple[str, ...] = ()  # rollout.save_episodes files to use instead
    # Labelled transitions the cloning term keeps (demonstrations and DAgger labels; the oldest
    # go first). A row of the default layout is ~0.8 kB.
    demonstration_capacity: int = 200_000
    ou_episodes: int = 100  # OU exploration before learning starts (paper; count not public)
    pretrain_updates: int = 0
    # Cloning updates between evaluations of the actor during pretraining (0: one, after it), so
    # that a run that only clones draws a learning curve (return rate against cloning updates).
    pretrain_evaluate_every: int = 0
    pretrain_bc_weight: float = 10.0
    bc_weight_final: float = 0.0
    # The cloning weight at the learn phase's start (None: sac.bc_weight), e.g. for a stage that
    # takes up an earlier stage's run where its fade stood.
    bc_weight_start: float | None = None
    # Steps of the learn phase over which the cloning weight fades to bc_weight_final (0: the whole
    # phase, so that a longer run clones for longer; a fixed fade lets SAC take over early).
    bc_fade_steps: int = 0
    actor_lr_final: float | None = None  # the actor's learning rate at the learn phase's end (None: fixed)
    # The learn phase's collection: "policy" (SAC's) or "dagger" (the actor plays, the returner
    # labels its states for the cloning term; this project's, rollout docstring).
    learn_mode: str = "policy"
    # With learn_mode "dagger": the share of the learn phase's rollout tasks whose new episodes the
    # returner labels; the others' play as in "policy" (1: all). Labelling is what makes DAgger
    # collection ~8 x slower; a share keeps the cloning rows coming from the actor's current states.
    dagger_fraction: float = 1.0
    # The share of the learn phase's remaining "policy" tasks played in the "guided" mode (the
    # returner's action where the predicted hit is within exploration.guided_window; rollout
    # docstring); their episodes are labelled (their rows join the cloning term's) and stored, but
    # not counted in the rollout return rate, which stays the actor's own; they cost what DAgger's
    # do (the returner runs at every step). 0: none.
    guided_fraction: float = 0.0
    updates_per_step: float = 0.25  # the learner's update-to-data ratio (not public)
    # Steps the learner waits, collecting, after its tables start empty in the learn phase (a run
    # started or resumed from a portable checkpoint, Progress.tables_refilled_at) before it updates
    # again, as SAC waits before its first update; the update budget counts from there, so that no
    # burst follows. 0: it updates from the first batch (and, with DAgger, the first labelled rows).
    refill_steps: int = 0
    update_chunk: int = 50  # updates between looks at the workers and weight publications
    checkpoint_every: int = 10_000
    evaluate_every: int = 25_000
    evaluation_episodes: int = 100
    # Seeds each periodic evaluation plays every shot with (the run's seed and the next ones): the
    # sensors' and the ball's noise spread one actor's rate over seeds by ~4 points, as much as the
    # actors it chooses between differ; the figures pool the repeats (``evaluate.summarize``).
    evaluation_repeats: int = 1
    evaluation_data: str = ""  # a match-data CSV (its shot_p2 shots); "" the synthetic distribution
    evaluation_players: tuple[str, ...] = ()  # with evaluation_data: these players' shots only; () all
    evaluation_sensors: str = "statistical"  # the rally diagram's position sensor for evaluations
    # With evaluation_data: players whose shots every periodic evaluation also plays, all of them,
    # for the learning curve on players the run never saw; reported, never used to choose the
    # exported actor (that is evaluation_players'). () none.
    heldout_players: tuple[str, ...] = ()
    # Another run's checkpoint to start from, in the learn phase (its learner, replay tables and
    # demonstrations; e.g. a run stopped after its pretraining); "" starts afresh.
    initialize_from: str = ""
    # The phase a run initialised from a checkpoint takes up: "learn", or "demonstrations" to go on
    # collecting demonstrations, OU episodes and cloning updates up to this config's totals
    # (demonstrations, ou_episodes, pretrain_updates), counted from the checkpoint's own.
    initialize_phase: str = "learn"
    # The earlier stage this run continues (training.stages): run first, then started from as from
    # initialize_from. None: no earlier stage.
    after: TrainConfig | None = None
    mirror: bool = False  # mirror augmentation of the replay and the demonstrations (learning/mirror.py)
    torch_threads: int = 1
    # Rollout tasks that may raise before the run stops (module docstring), each losing its
    # episodes; the same number of periodic evaluations may fail, each skipped.
    max_worker_failures: int = 10
    log_every: float = 30.0  # s between progress lines
    sac: SacConfig = dataclasses.field(default_factory=SacConfig)
    play: PlayOptions = dataclasses.field(default_factory=PlayOptions)  # what the actor needs from its diagram
    replay: ReplayConfig = dataclasses.field(default_factory=ReplayConfig)
    env: RallyEnvParams = dataclasses.field(default_factory=RallyEnvParams)
    exploration: ExplorationParams = dataclasses.field(default_factory=ExplorationParams)
    # The model-based returner that demonstrates and labels (``training.rollout``); ``memory: false``
    # makes its labels a function of the observation alone (``control.returner`` docstring).
    returner: ReturnerParams = dataclasses.field(default_factory=ReturnerParams)

    def __post_init__(self) -> None:
        for name in ("env_steps", "workers", "episodes_per_task", "update_chunk", "checkpoint_every",
                     "evaluate_every", "evaluation_episodes", "evaluation_repeats", "torch_threads", "demonstration_capacity"):
            if getattr(self, name) < 1:
                raise ConfigError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("demonstrations", "ou_episodes", "pretrain_updates", "pretrain_evaluate_every", "batch", "bc_fade_steps",
                     "max_worker_failures", "refill_steps"):
            if getattr(self, name) < 0:
                raise ConfigError(f"TrainConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("pretrain_bc_weight", "bc_weight_final", "updates_per_step"):
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"TrainConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.bc_weight_start is not None and not self.bc_weight_start >= 0.0:
            raise ConfigError(f"TrainConfig.bc_weight_start must be >= 0 (or left out), got {self.bc_weight_start}")
        if self.actor_lr_final is not None and not self.actor_lr_final > 0.0:
            raise ConfigError(f"TrainConfig.actor_lr_final must be > 0 (or left out), got {self.actor_lr_final}")
        if self.learn_mode not in ("policy", "dagger"):
            raise ConfigError(f"TrainConfig.learn_mode must be 'policy' or 'dagger', got {self.learn_mode!r}")
        if not 0.0 < self.dagger_fraction <= 1.0:
            raise ConfigError(f"TrainConfig.dagger_fraction must be in (0, 1], got {self.dagger_fraction}")
        if self.dagger_fraction != 1.0 and self.learn_mode != "dagger":
            raise ConfigError("TrainConfig.dagger_fraction is the share of labelled tasks with learn_mode 'dagger'")
        if not 0.0 <= self.guided_fraction < 1.0:
            raise ConfigError(f"TrainConfig.guided_fraction must be in [0, 1), got {self.guided_fraction}")
        if self.guided_fraction > 0.0 and self.sac.action != "terminal":
            raise ConfigError("TrainConfig.guided_fraction: the guided mode plays the returner's eq. (12) action; "
                              f"the actor's action is {self.sac.action!r}")
        if self.guided_fraction > 0.0 and self.learn_mode == "dagger" and self.dagger_fraction == 1.0:
            raise ConfigError("TrainConfig.guided_fraction guides a share of the policy tasks; with dagger_fraction 1 there are none")
        if self.backend not in ("ray", "local"):
            raise ConfigError(f"TrainConfig.backend must be 'ray' or 'local', got {self.backend!r}")
        if self.backend == "local" and self.workers != 1:
            raise ConfigError("TrainConfig: the local backend runs one worker (workers: 1)")
        if self.batch and self.sac.action != "terminal":
            raise ConfigError(f"TrainConfig.batch: batched workers play the eq. (12) action ('terminal') only, got sac.action {self.sac.action!r}")
        if self.evaluation_sensors not in ("cameras", "statistical"):
            raise ConfigError(f"TrainConfig.evaluation_sensors must be 'cameras' or 'statistical', got {self.evaluation_sensors!r}")
        if self.evaluation_players and not self.evaluation_data:
            raise ConfigError("TrainConfig.evaluation_players selects shots of evaluation_data; give a match-data CSV")
        if self.evaluation_data and not Path(self.evaluation_data).is_file():
            raise ConfigError(f"TrainConfig.evaluation_data: no such file {self.evaluation_data}")
        if self.heldout_players:
            if not self.evaluation_data:
                raise ConfigError("TrainConfig.heldout_players selects shots of evaluation_data; give a match-data CSV")
            seen = set(self.heldout_players) & (set(self.evaluation_players) | set(self.env.shots.players))
            if seen or (self.env.shots.source != "synthetic" and not self.env.shots.players):
                raise ConfigError("TrainConfig.heldout_players must be players the run neither trains nor chooses its actor on "
                                  f"(env.shots.players {list(self.env.shots.players) or 'all'}, evaluation_players "
                                  f"{list(self.evaluation_players)}); got {list(self.heldout_players)}")
        if self.play.hit_memory != self.env.rally.hit_memory:
            raise ConfigError(f"TrainConfig: play.hit_memory ({self.play.hit_memory}) and env.rally.hit_memory ({self.env.rally.hit_memory}) "
                              "must agree: the actor reads the observation the env's diagram builds")
        if self.initialize_phase not in ("demonstrations", "learn"):
            raise ConfigError(f"TrainConfig.initialize_phase must be 'demonstrations' or 'learn', got {self.initialize_phase!r}")
        if self.after is not None and (self.initialize_from or
                                       learner_config_differences(dataclasses.asdict(self.after.sac), dataclasses.asdict(self.sac))):
            raise ConfigError("TrainConfig.after: give it or initialize_from, not both, and the same sac as this stage's but for "
                              f"the fields a stage may change {list(STAGE_FIELDS)} (its learner is loaded)")
        if self.initialize_from and not Path(self.initialize_from).is_file():
            raise ConfigError(f"TrainConfig.initialize_from: no such file {self.initialize_from}")
        for path in self.demonstration_files:
            if not Path(path).is_file():
                raise ConfigError(f"TrainConfig.demonstration_files: no such file {path}")

    @property
    def task_episodes(self) -> int:
        """Episodes per worker task: ``episodes_per_task``, times B with batched workers."""
        return self.episodes_per_task * max(self.batch, 1)


def refill_pause(refilled_at, refill_steps: int, start: int, now: int) -> int:
    """Steps of the learn phase (from ``start`` to ``now``) during which the learner waited for
    its tables to refill (``TrainConfig.refill_steps`` after each step in ``refilled_at``): the
    length of the union of those intervals within [start, now]."""
    paused, reached = 0, start
    for at in sorted(refilled_at):
        begin, end = max(at, reached), min(at + refill_steps, now)
        if end > begin:
            paused += end - begin
        reached = max(reached, end)
    return paused


def load_train_config(path) -> TrainConfig:
    """A TrainConfig from a YAML file (missing fields keep their defaults; ``base:`` composes it
    over another file, ``config.load_yaml``; ``after:`` is an earlier stage, ``training.stages``).
    Raises ConfigError naming the field for unknown names, wrong types and rejected values."""

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"train: config file not found: {path}")
    data = load_yaml(path)
    try:
        return from_dict(TrainConfig, with_earlier_stages(data))
    except (ConfigError, ValueError) as error:
        raise ConfigError(f"{path}: {error}") from None


def _spread(n: int, fraction: float) -> bool:
    """Whether task ``n`` (from 0) is among a ``fraction`` of tasks spread evenly, the first
    included: ceil((n + 1) f) > ceil(n f)."""
    return math.ceil((n + 1) * fraction) > math.ceil(n * fraction)


class Trainer(Checkpointing):
    """One training run in ``run_dir`` (module docstring); ``run()`` trains to the end (resuming
    from the checkpoint if there is one) and returns the final Progress. Saving, loading and
    resuming are ``checkpoint.Checkpointing``'s."""

    def __init__(self, config: TrainConfig, run_dir, progress=print, earlier_stage=None, resume_from=None):
        """``earlier_stage``: for a config with ``after``, a checkpoint of that earlier stage to
        start from instead of running it in ``run_dir/after`` (e.g. its portable checkpoint, carried
        to a machine without that directory; ``stages.earlier_stage_from``). ``resume_from``: a
        checkpoint of this very run written elsewhere (e.g. its portable checkpoint, carried to a
        machine without ``run_dir``) to resume from, for a ``run_dir`` that holds none; a portable
        one resumes with its tables filling anew (``Checkpointing._load``). Either writes the run's
        own checkpoint at once, so that it resumes from ``run_dir`` without them."""
        if earlier_stage is not None and config.after is None:
            raise ConfigError(f"train: an earlier stage's checkpoint ({earlier_stage}) was given, but the config has no after: stage")
        if earlier_stage is not None and resume_from is not None:
            raise ConfigError("train: give an earlier stage's checkpoint or one of this run to resume from, not both")
        self.config = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.log = progress
        torch.set_num_threads(config.torch_threads)
        self.learner = SacLearner(config.sac, config.env.rally, play=config.play)
        # Mirror augmentation (paper): every stored episode and demonstration also mirrored.
        augment = ()
        if config.mirror:
            robot = RobotModel(load_scenario(MODELS_DIR / config.env.rally.scenario))
            try:
                augment = (Mirror.from_robot(robot, config.sac.layout).transitions,)
            except ValueError as error:
                raise ConfigError(f"mirror: true needs a mirror-symmetric robot ({config.env.rally.scenario}): {error}") from None
        self.replay = EventReplay(dataclasses.replace(config.replay, seed=config.seed), config.sac.layout, config.env.reward, augment,
                                  config.sac.gamma)
        self.demonstrations = DemonstrationBuffer(config.demonstration_capacity, seed=config.seed + 1, augment=augment)
        self.state = Progress(next_checkpoint=config.checkpoint_every, next_evaluation=config.evaluate_every)
        self._recent = deque(maxlen=100)  # outcomes of the latest policy episodes
        self._losses: dict[str, list[float]] = {}
        self._writer = None
        self._pool = None
        self._started = time.perf_counter()
        self._last_log = self._started
        latest = latest_checkpoint(self.run_dir)
        if latest is not None and resume_from is not None:
            raise ConfigError(f"train: {self.run_dir} holds the run's checkpoint ({latest[0]}): resume from it without "
                              f"a checkpoint to resume from ({resume_from}), or give another run directory")
        if latest is not None:
            self._load(*latest)
        elif resume_from is not None:
            self._load(Path(resume_from), read_checkpoint(resume_from))
            self.checkpoint()  # from now on the run resumes from its own directory
        elif config.initialize_from:
            self._initialize_from(Path(config.initialize_from))
        elif config.after is not None:
            self._initialize_from(*(earlier_stage_from(self, Path(earlier_stage)) if earlier_stage else earlier_stage_checkpoint(self)))
            if earlier_stage:
                self.checkpoint()  # from now on the run resumes from its own directory, without --earlier-stage
        self._save_config()
        # this run's own time starts now (an earlier stage run above counted its time in its checkpoint)
        self._started = self._last_log = time.perf_counter()

    # ------------------------------------------------------------------------------ the run
    def run(self):
        c = self.config

        self._writer = SummaryWriter(str(self.run_dir / "tensorboard"))
        try:
            if self.state.phase == "demonstrations":
                self._demonstration_phase()
            if self.state.phase == "ou":
                self._collect_phase("ou", c.ou_episodes, "ou_episodes")
                self._advance("pretrain")
            if self.state.phase == "pretrain":
                self._pretrain_phase()
            if self.state.phase == "learn":
                self._learn_phase()
        finally:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None
            self._writer.close()
        return self.state

    def _advance(self, phase: str) -> None:
        self.state.phase = phase
        if phase == "learn":
            self.state.learn_start = (self.state.env_steps, self.learner.updates)
        self.checkpoint()
        self.log(f"train: phase {phase} at {self.state.env_steps} steps")

    def _workers(self):
        if self._pool is None:
            c = self.config
            self._pool = WorkerPool(c.workers, self._worker_args(), c.backend, c.address or None)
            self._pool.publish(self.learner.actor.state_dict())
        return self._pool

    def _worker_args(self) -> dict:
        """The rollout workers' arguments; the seed moves on with each resumption and each
        replaced worker, so that neither replays episodes already played."""
        c = self.config
        seed = c.seed + 7919 * self.state.resumptions + 104729 * len(self.state.worker_failures)
        args = {"env_params": c.env, "sac": c.sac, "play": c.play, "seed": seed, "exploration": c.exploration,
                "returner": c.returner}
        if c.batch:
            args["batch"] = c.batch
        return args

    def _wait(self, pool, timeout: float | None = None):
        """``pool.wait``, surviving a failed task (module docstring): the failure is logged and
        counted, the worker replaced, and (its index, no episodes) returned so that the caller
        gives it its next task. Raises the WorkerFailed beyond ``max_worker_failures``."""
        try:
            return pool.wait(timeout=timeout)
        except WorkerFailed as failure:
            s = self.state
            s.worker_failures.append((s.env_steps, failure.index, failure.error))
            self._record_failure(s.worker_failures, "worker_failures.log", f"worker {failure.index}", failure.traceback,
                                 f"rollout worker {failure.index} failed", "its task's episodes are lost and it is replaced")
            pool.replace(failure.index, self._worker_args())
            return failure.index, []

    def _record_failure(self, failures: list, log_name: str, where: str, trace: str, what: str, consequence: str) -> None:
        """Writes a failure (just appended to ``failures``, a list of ``Progress``) with its
        traceback to ``run_dir / log_name`` and logs it; re-raises the exception being handled when
        the list is longer than ``max_worker_failures``."""
        s, c = self.state, self.config
        with open(self.run_dir / log_name, "a", encoding="utf-8") as log:
            log.write(f"--- at {s.env_steps} steps, {where}:\n{trace}\n")
        if len(failures) > c.max_worker_failures:
            raise
        self.log(f"train: {what} at {s.env_steps} steps ({failures[-1][-1]}); {consequence} (failure {len(failures)} "
                 f"of at most {c.max_worker_failures}; traceback in {self.run_dir / log_name})")

    def _demonstration_phase(self) -> None:
        c = self.config
        if c.demonstration_files and self.state.demonstration_episodes == 0:
            for path in c.demonstration_files:
                episodes = load_episodes(path)
                for episode in episodes:
                    self._ingest(episode)
                self.state.demonstration_episodes += len(episodes)
                self.log(f"train: {len(episodes)} demonstration episodes from {path}")
        elif c.demonstrations:
            self._collect_phase("demonstrator", c.demonstrations, "demonstration_episodes")
        self._advance("ou")

    def _collect_phase(self, mode: str, total: int, counter: str) -> None:
        """Collects until ``total`` episodes of ``mode`` have been ingested (counted in
        ``self.state.<counter>``), checkpointing on the way."""
        if getattr(self.state, counter) >= total:
            return
        pool = self._workers()
        for index in range(pool.count):
            pool.submit(index, self.config.task_episodes, mode)
        while getattr(self.state, counter) < total:
            index, episodes = self._wait(pool)
            for episode in episodes:
                if getattr(self.state, counter) < total:
                    self._ingest(episode)
                    setattr(self.state, counter, getattr(self.state, counter) + 1)
            if getattr(self.state, counter) + pool.in_flight * self.config.task_episodes < total:
                pool.submit(index, self.config.task_episodes, mode)
            self._periodic(evaluate=False)
        while pool.in_flight:  # finished tasks beyond the total are dropped
            self._wait(pool)

    def _pretrain_phase(self) -> None:
        c = self.config
        if c.pretrain_updates and len(self.replay) == 0:
            raise ConfigError("train: pretrain_updates needs collected episodes (demonstrations or ou_episodes)")
        while self.state.pretrain_updates < c.pretrain_updates:
            chunk = min(c.update_chunk, c.pretrain_updates - self.state.pretrain_updates)
            self._update(chunk, c.pretrain_bc_weight)
            self.state.pretrain_updates += chunk
            if self.state.pretrain_updates % (20 * c.update_chunk) < chunk:
                self._log_line(force=True)
            every = c.pretrain_evaluate_every
            if every and self.state.pretrain_updates % every < chunk and self.state.pretrain_updates < c.pretrain_updates:
                self._evaluate()  # the one after cloning follows the loop
                self.checkpoint()
        self._advance("learn")
        if c.pretrain_updates:
            self._evaluate()

    def _learn_phase(self) -> None:
        c = self.config
        pool = self._workers()
        pool.publish(self.learner.actor.state_dict())
        for index in range(pool.count):
            pool.submit(index, c.task_episodes, self._learn_task_mode())
        learn_start, updates_start = self.state.learn_start
        while self.state.env_steps < c.env_steps:
            result = self._wait(pool, timeout=0.0 if self.config.backend == "ray" else None)
            self._take(pool, result)
            learned = self.state.env_steps - learn_start
            # With labels to come (DAgger, guided episodes) but none yet (a stage started from a portable
            # checkpoint), SAC without its cloning term would move the actor off what it was cloned to: wait for them.
            labels_due = (c.learn_mode == "dagger" or c.guided_fraction > 0) and len(self.demonstrations) == 0 and self.bc_weight() > 0
            paused = refill_pause(self.state.tables_refilled_at, c.refill_steps, learn_start, self.state.env_steps)
            refilling = any(at <= self.state.env_steps < at + c.refill_steps for at in self.state.tables_refilled_at)
            if (len(self.replay) >= c.sac.batch_size and not labels_due and not refilling
                    and self.learner.updates - updates_start < c.updates_per_step * (learned - paused)):
                progress = schedule_progress(self.state, c.env_steps)
                if c.actor_lr_final is not None:
                    self.learner.set_actor_lr(c.sac.actor_lr + progress * (c.actor_lr_final - c.sac.actor_lr))
                self._update(c.update_chunk, self.bc_weight())
                pool.publish(self.learner.actor.state_dict())
            elif result is None:  # nothing to learn from yet: wait for the workers
                self._take(pool, self._wait(pool))
            self._periodic(evaluate=True)
        self.state.phase = "done"
        if not self.state.evaluations or self.state.evaluations[-1][0] != self.state.env_steps:
            self._evaluate()
        self.checkpoint()
        self.log(f"train: done: {self.state.env_steps} steps, {self.learner.updates} updates, {self.state.wall_time + self._elapsed():.0f} s")

    # ------------------------------------------------------------------------------ pieces
    def bc_weight(self) -> float:
        """The cloning term's weight at the run's current step in the learn phase (module
        docstring): linear from ``bc_weight_start`` (default ``sac.bc_weight``) to
        ``bc_weight_final`` over the phase, or over its first ``bc_fade_steps`` steps."""
        c, s = self.config, self.state
        start = c.sac.bc_weight if c.bc_weight_start is None else c.bc_weight_start
        if c.bc_fade_steps:
            progress = min(1.0, max(0.0, (s.env_steps - s.learn_start[0]) / c.bc_fade_steps))
        else:
            progress = schedule_progress(s, c.env_steps)
        return start + progress * (c.bc_weight_final - start)

    def _take(self, pool, result) -> None:
        """Ingests a finished task's episodes (``WorkerPool.wait``'s result, or None) and gives
        its worker the next task."""
        if result is None:
            return
        index, episodes = result
        for episode in episodes:
            self._ingest(episode)
        pool.submit(index, self.config.task_episodes, self._learn_task_mode())

    def _learn_task_mode(self) -> str:
        """The mode of the learn phase's next rollout task: ``learn_mode``, but with a
        ``dagger_fraction`` below 1, "dagger" for that share of the tasks, evenly spread and
        first (task n is labelled when ceil((n + 1) f) > ceil(n f): the stage's first task is), and
        "policy" for the rest; of those "policy" tasks, a ``guided_fraction`` share is "guided",
        spread over them the same way."""
        c = self.config
        mode = c.learn_mode
        if c.dagger_fraction < 1.0:
            mode = "dagger" if _spread(self.state.learn_tasks, c.dagger_fraction) else "policy"
            self.state.learn_tasks += 1
        if mode == "policy" and c.guided_fraction > 0.0:
            mode = "guided" if _spread(self.state.guided_tasks, c.guided_fraction) else "policy"
            self.state.guided_tasks += 1
        return mode

    def _ingest(self, episode: Episode) -> None:
        summary = episode.summary
        self.replay.add_episode(episode.transitions, summary)
        if "demo_action" in episode.transitions:
            self.demonstrations.add(episode.transitions)
        self.state.env_steps += episode.steps
        self.state.episodes += 1
        if episode.mode in ("policy", "dagger"):
            self._recent.append(episode.returned)

    def _update(self, count: int, bc_weight: float) -> None:
        c = self.config
        for _ in range(count):
            batch = self.replay.sample(c.sac.batch_size)
            demos = self.demonstrations.sample(c.sac.batch_size) if len(self.demonstrations) and bc_weight > 0 else None
            losses = self.learner.update(batch, demos, bc_weight)
            for key, value in losses.items():
                self._losses.setdefault(key, []).append(value)

    def _periodic(self, evaluate: bool) -> None:
        s, c = self.state, self.config
        self._log_line()
        if evaluate and s.env_steps >= s.next_evaluation:
            self._evaluate()
        if s.env_steps >= s.next_checkpoint:
            s.next_checkpoint += c.checkpoint_every * (1 + (s.env_steps - s.next_checkpoint) // c.checkpoint_every)
            self.checkpoint()

    def _log_line(self, force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self._last_log < self.config.log_every:
            return
        self._last_log = now
        s = self.state
        rate = float(np.mean(self._recent)) if self._recent else None
        losses = {key: float(np.mean(values)) for key, values in self._losses.items() if values}
        self._losses = {}
        step = s.env_steps
        for key, value in losses.items():
            self._writer.add_scalar(f"loss/{key}", value, step)
        if rate is not None:
            self._writer.add_scalar("rollout/return_rate_last_100", rate, step)
            s.rollout_curve.append((step, self.learner.updates, rate))
        self._writer.add_scalar("rollout/episodes", s.episodes, step)
        self._writer.flush()
        text = ", ".join(f"{key} {value:.4g}" for key, value in losses.items() if key in ("critic_loss", "q_mean", "bc_loss", "aux_loss"))
        self.log(f"train [{s.phase}]: {step} steps, {s.episodes} episodes, {self.learner.updates} updates, "
                 f"returned {'-' if rate is None else f'{rate:.0%}'} of the last {len(self._recent)} policy episodes, "
                 f"{s.wall_time + self._elapsed():.0f} s; {text}")

    def _evaluate(self) -> None:
        """Evaluates the deterministic policy actor in the rally diagram (module docstring), surviving a
        failed evaluation: it is logged with its traceback (``run_dir/evaluation_failures.log``)
        and counted, and the run goes on to the next one (a held-out part that fails takes the
        whole evaluation with it). More than ``max_worker_failures`` such failures in a stage
        raise the last one. Bad input (``InputError``: the config, the match data) is raised at
        once: it would fail every evaluation."""

        try:
            self._evaluate_once()
        except InputError:
            raise
        except Exception as error:  # an episode's simulation or estimate failing, as a rollout's may
            s = self.state
            s.evaluation_failures.append((s.env_steps, traceback.format_exception_only(error)[-1].strip()))
            self._record_failure(s.evaluation_failures, "evaluation_failures.log", "evaluation", traceback.format_exc(),
                                 "the evaluation failed", "skipped")

    def _evaluate_once(self) -> None:
        c, s = self.config, self.state
        if s.env_steps >= s.next_evaluation:  # the next periodic one is due evaluate_every from here
            s.next_evaluation += c.evaluate_every * (1 + (s.env_steps - s.next_evaluation) // c.evaluate_every)
        shots, serve = evaluation_shots(c)
        params = RallyParams(perception=PerceptionParams(positions=c.evaluation_sensors), stepping="segment" if c.batch else "continuous")
        start = time.perf_counter()
        figures = self._play_repeats(params, shots, serve)
        rate = figures["return_rate"]
        summary = {"rate": rate["rate"], "ci95": rate["ci95"], "played": rate["played"], "returned": rate["returned"],
                   "not_returned_by_reason": figures["not_returned_by_reason"]}
        if c.evaluation_repeats > 1:
            summary["repeats"] = c.evaluation_repeats
        if c.heldout_players:
            shots, serve = human_shots(c.evaluation_data, c.heldout_players)
            held = self._play_repeats(params, shots, serve)["return_rate"]
            summary["heldout"] = {"players": list(c.heldout_players), "rate": held["rate"], "ci95": held["ci95"],
                                  "played": held["played"], "returned": held["returned"]}
            if c.evaluation_repeats > 1:
                summary["heldout"]["repeats"] = c.evaluation_repeats
            if held["rate"] is not None:
                self._writer.add_scalar("evaluation/heldout_return_rate", held["rate"], s.env_steps)
            self.log(f"train: evaluation at {s.env_steps} steps on the held-out players ({', '.join(c.heldout_players)}): "
                     f"returned {held['returned']} of {held['played']} ({(held['rate'] or 0):.1%})")
        s.evaluations.append((s.env_steps, self.learner.updates, summary))
        if rate["rate"] is not None:
            self._writer.add_scalar("evaluation/return_rate", rate["rate"], s.env_steps)
            if rate["rate"] > s.best_rate:
                s.best_rate = rate["rate"]
                s.best_actor = {k: v.clone() for k, v in self.learner.policy_actor.state_dict().items()}  # what was evaluated
                s.best_evaluation = len(s.evaluations) - 1
        self.log(f"train: evaluation at {s.env_steps} steps: returned {rate['returned']} of {rate['played']} "
                 f"({(rate['rate'] or 0):.1%}), {time.perf_counter() - start:.0f} s")

    def _play_repeats(self, params: RallyParams, shots: np.ndarray, serve: np.ndarray) -> dict:
        """The deterministic policy actor's figures (``evaluate.summarize``) on ``shots``, each played
        ``evaluation_repeats`` times with the seeds from the run's seed on (pooled, with the
        repeats' clustered interval when there are several)."""
        c = self.config
        episodes = [episode for seed in range(c.seed, c.seed + c.evaluation_repeats)
                    for episode in play(self.learner.policy(), params, shots, serve, seed=seed, batch=EVALUATION_BATCH if c.batch else 1)]
        return summarize(episodes, len(shots) if c.evaluation_repeats > 1 else None)

    def _elapsed(self) -> float:
        return time.perf_counter() - self._started


def evaluation_shots(config: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """The periodic evaluation's shots: the first ``evaluation_episodes`` shot_p2 shots of
    ``evaluation_data``, else as many from the synthetic distribution (seeded by the run's seed)."""

    if config.evaluation_data:
        shots, serve = human_shots(config.evaluation_data, config.evaluation_players)
        return shots[: config.evaluation_episodes], serve[: config.evaluation_episodes]
    sample = make_distribution(dataclasses.replace(config.env.shots, seed=config.seed), config.env.rally.physics).draw(
        np.random.default_rng(config.seed + 2), config.evaluation_episodes)
    return sample.states, sample.serve
