"""A training run's checkpoint (``training.loop``'s module docstring): every ``checkpoint_every``
steps the whole learner state (networks, optimisers, generator, replay tables, demonstrations,
counters, history) is written atomically to ``run_dir/checkpoint.pt`` (a temporary file, flushed and fsynced, renamed
over the old one, which is kept as ``checkpoint.prev.pt``); a ``Trainer`` made on a
run directory that holds one resumes from it, and one whose config names ``initialize_from``
starts from another run's. ``Checkpointing`` holds these methods of ``loop.Trainer`` (its
``config``, ``learner``, ``replay``, ``demonstrations``, ``state``, ``_recent``, ``run_dir``,
``log``, ``_started`` and ``_elapsed``). ``Progress``, the run's counters and history, is what
a checkpoint's ``progress`` holds. A checkpoint records the robot it was written for
(``robot.params.scenario_record``); resuming or starting from it on another robot is refused.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import re
import sys
import time
from pathlib import Path

import torch
import yaml

from ace_drake.artefacts import write_sidecar
from ace_drake.config import ConfigError, from_dict, to_dict
from ace_drake.learning.replay import load_weights_only
from ace_drake.learning.sac import split_play_options
from ace_drake.robot.model import scenario_file_record
from ace_drake.robot.params import scenario_mismatch

# The phases of a run, in order (``loop.Trainer.run``); a checkpoint records the current one.
PHASES = ("demonstrations", "ou", "pretrain", "learn", "done")
CHECKPOINT = "checkpoint.pt"
PREVIOUS_CHECKPOINT = "checkpoint.prev.pt"  # the one before, kept by every write (module docstring)
# The same without the replay tables and labelled rows (None): networks, optimisers, counters and
# history in ~7 MB (the paper-action run's), where the whole checkpoint is ~2.4 GB. A run that moves to a machine without its
# run directory carries this one; a new stage starts from it (``initialize_from``), its tables
# filling anew. Written beside every checkpoint.
PORTABLE_CHECKPOINT = "checkpoint.portable.pt"
CHECKPOINT_KEYS = ("config", "learner", "replay", "demonstrations", "progress", "recent")
# Config fields a resumed run may change: its length (to stop a stage early or extend a run) and
# how many rollout failures it survives (to let a run that reached the limit go on).
CHANGEABLE_ON_RESUME = ("env_steps", "max_worker_failures")


class CheckpointError(ConfigError):
    """A training checkpoint that cannot be read: truncated, empty, or not a checkpoint."""


def read_checkpoint(path) -> dict:
    """The payload of the training checkpoint at ``path``. Raises CheckpointError naming the file
    and what to do when it cannot be read (truncated, e.g. by a crash while it was written by an
    older version, empty, or not a training checkpoint), FileNotFoundError when it is absent."""

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    remedy = f"delete it to start the run afresh, or point at an earlier checkpoint (e.g. {path.with_name(PREVIOUS_CHECKPOINT)})"
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: the checkpoint is empty; {remedy}")
    try:
        payload = load_weights_only(path)  # weights only: loading a checkpoint runs no code from it
    except pickle.UnpicklingError as error:
        refused = re.search(r"Unsupported global: GLOBAL (\S+)", str(error))
        what = refused.group(1) if refused else "something other than tensors, plain containers and NumPy arrays"
        raise CheckpointError(f"{path}: not a readable checkpoint (it holds {what}, which a weights-only load does not build); "
                              f"{remedy}") from None
    except Exception as error:  # torch raises several kinds (RuntimeError, EOFError, UnpicklingError) for a damaged file
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or damaged: {reason}); {remedy}") from None
    missing = [key for key in CHECKPOINT_KEYS if not isinstance(payload, dict) or key not in payload]
    if missing:
        raise CheckpointError(f"{path}: not a training checkpoint (no {', '.join(missing)}); {remedy}")
    return payload


@dataclasses.dataclass
class Progress:
    """The run's counters and history (all in the checkpoint)."""

    phase: str = PHASES[0]
    env_steps: int = 0
    episodes: int = 0
    demonstration_episodes: int = 0
    ou_episodes: int = 0
    pretrain_updates: int = 0
    wall_time: float = 0.0  # s of training, summed over resumptions
    resumptions: int = 0
    next_checkpoint: int = 0
    next_evaluation: int = 0
    # (env_steps, updates, rollout return rate of the last 100 policy episodes) per log line
    rollout_curve: list = dataclasses.field(default_factory=list)
    # (env_steps, updates, evaluation figures) per evaluation
    evaluations: list = dataclasses.field(default_factory=list)
    learn_start: tuple = (0, 0)  # (env_steps, updates) when the learn phase began
    # (env_steps, schedule progress there) of the last change of the run's length: the learn
    # phase's schedules go on linearly from that progress to 1 at the new length (schedule_progress)
    schedule_anchor: tuple | None = None
    length_changes: list = dataclasses.field(default_factory=list)  # (env_steps, old length, new length) per change
    initialized_at: int | None = None  # env_steps of the checkpoint the run started from (initialize_from)
    # (env_steps, worker index, error's last line) per rollout task that raised (loop.Trainer._wait)
    worker_failures: list = dataclasses.field(default_factory=list)
    # (env_steps, error's last line) per periodic evaluation that raised (loop.Trainer._evaluate)
    evaluation_failures: list = dataclasses.field(default_factory=list)
    # the learn phase's rollout tasks given a mode under a dagger_fraction below 1 (loop.Trainer._learn_task_mode;
    # per stage: tasks in flight at a checkpoint are counted and, after a resume, not played)
    learn_tasks: int = 0
    guided_tasks: int = 0  # the learn phase's policy tasks given a mode under a guided_fraction (per stage, as learn_tasks)
    best_rate: float = -1.0
    best_actor: dict | None = None
    best_evaluation: int = -1  # index into evaluations of the best actor's evaluation
    # env_steps of each start or resumption from a portable checkpoint (Checkpointing._load,
    # _initialize_from): the tables and labelled rows were empty from there and filled anew
    tables_refilled_at: list = dataclasses.field(default_factory=list)


def _without_changeable(config: dict) -> dict:
    """A config dict without the fields a resumed run may change (``CHANGEABLE_ON_RESUME``), its
    own and its earlier stages' (``after``: a stage that has finished may be given another length too)."""
    out = {key: value for key, value in config.items() if key not in CHANGEABLE_ON_RESUME}
    if isinstance(out.get("after"), dict):
        out["after"] = _without_changeable(out["after"])
    return out


def config_differences(saved: dict, config) -> list[str]:
    """The top-level fields in which a checkpoint's config ``saved`` (a dict) differs from
    ``config`` (a TrainConfig), but for those a resumed run may change (``CHANGEABLE_ON_RESUME``).
    ``saved`` is read back through the config classes, so that a field added since it was written
    compares at its default (a new field's default keeps the old behaviour)."""
    saved = to_dict(from_dict(type(config), play_options_moved(saved)))
    current = to_dict(config)
    return sorted(k for k, v in _without_changeable(current).items() if _without_changeable(saved).get(k) != v)


def schedule_progress(state: Progress, length: int) -> float:
    """How far (0..1) the learn phase's schedules (cloning weight, actor learning rate) stand at
    ``state.env_steps`` in a run of ``length`` steps: linear from the learn phase's start to its
    end, or, after a change of the length, from the progress the run had then to 1 at the new end."""
    if state.schedule_anchor is None:
        start, at = state.learn_start[0], 0.0
    else:
        start, at = state.schedule_anchor
    return min(1.0, at + (1.0 - at) * (state.env_steps - start) / max(1, length - start))


def play_options_moved(config: dict) -> dict:
    """A TrainConfig mapping written before PlayOptions (a checkpoint's, a sidecar's: its
    ``sac.meet_ball`` and ``sac.hit_memory``) with those under ``play``."""
    sac, play = split_play_options(config.get("sac") or {})
    return {**config, "sac": sac, "play": {**play, **(config.get("play") or {})}}


def latest_checkpoint(run_dir) -> tuple[Path, dict] | None:
    """(path, payload) of the checkpoint in ``run_dir`` to resume from: the latest, or the previous
    one with a warning on stderr when the latest is missing or cannot be read; None when the run
    has none. Raises CheckpointError when neither can be read."""
    run_dir = Path(run_dir)
    latest, previous = run_dir / CHECKPOINT, run_dir / PREVIOUS_CHECKPOINT
    if not latest.is_file():
        if not previous.is_file():
            return None
        print(f"warning: train: {latest} is missing; resuming from the previous checkpoint {previous}", file=sys.stderr)
        return previous, read_checkpoint(previous)
    try:
        return latest, read_checkpoint(latest)
    except CheckpointError as error:
        if not previous.is_file():
            raise
        try:
            payload = read_checkpoint(previous)
        except CheckpointError as previous_error:
            raise CheckpointError(f"{error}; the previous checkpoint cannot be read either: {previous_error}") from None
        print(f"warning: train: {error}; resuming from the previous checkpoint {previous}", file=sys.stderr)
        return previous, payload


class Checkpointing:
    """Saving, loading and resuming a ``loop.Trainer``'s run (module docstring)."""

    # ------------------------------------------------------------------------------ checkpoints
    def checkpoint(self) -> None:
        """Writes the whole learner state atomically (module docstring)."""

        self.state.wall_time += self._elapsed()
        self._started = time.perf_counter()
        payload = {
            "config": to_dict(self.config),
            "learner": self.learner.state_dict(),
            "replay": self.replay.state_dict(),
            "demonstrations": self.demonstrations.state_dict(),
            "progress": dataclasses.asdict(self.state),
            "recent": list(self._recent),
            "robot": self.robot_record(),
        }
        path = self.run_dir / CHECKPOINT
        _write(payload, path.with_name(path.name + ".tmp"))
        if path.is_file():  # a crash from here on leaves the previous checkpoint (and the new one)
            os.replace(path, self.run_dir / PREVIOUS_CHECKPOINT)
        os.replace(path.with_name(path.name + ".tmp"), path)
        portable = self.run_dir / PORTABLE_CHECKPOINT
        _write({**payload, "replay": None, "demonstrations": None}, portable.with_name(portable.name + ".tmp"))
        os.replace(portable.with_name(portable.name + ".tmp"), portable)
        # its sidecar, so that the two files carried elsewhere say what they are
        write_sidecar(portable, seed=self.config.seed, phase=self.state.phase, **self.run_record(),
                      config=payload["config"], robot=payload["robot"])
        _sync_directory(self.run_dir)

    def run_record(self) -> dict:
        """The run as it stands, for a sidecar (the portable checkpoint's, the exported policy's):
        env_steps, episodes, updates, wall_time_s (s of training), the periodic evaluations, the
        rollout tasks and evaluations that failed, and the steps at which its tables filled anew."""
        s = self.state
        return dict(
            env_steps=s.env_steps,
            episodes=s.episodes,
            updates=self.learner.updates,
            wall_time_s=round(s.wall_time, 1),
            evaluations=[{"env_steps": e[0], "updates": e[1], **e[2]} for e in s.evaluations],
            # the stage's rollout tasks that failed (their workers replaced, with other seeds: loop.Trainer._wait)
            worker_failures=[{"env_steps": f[0], "worker": f[1], "error": f[2]} for f in s.worker_failures],
            evaluation_failures=[{"env_steps": f[0], "error": f[1]} for f in s.evaluation_failures],  # skipped evaluations
            tables_refilled_at=s.tables_refilled_at,  # starts or resumptions from a portable checkpoint: the tables filled anew there
        )

    def _load(self, path: Path, payload: dict) -> None:
        """Resumes the run from its checkpoint ``payload`` (at ``path``): the run directory's, or
        one carried from another machine (``resume_from``). A ``PORTABLE_CHECKPOINT`` resumes with
        empty tables that fill anew; it is refused before the learn phase (the cloning updates
        would miss the demonstrations collected). A run that goes on learning with empty tables (a
        portable checkpoint's, or a whole one's written since from one: a finished run resumed
        from its portable checkpoint, then extended) is refused where its cloning term would have
        no rows (``_refuse_portable``), and recorded in ``Progress.tables_refilled_at``."""
        # Read back through the config classes, so that a field added since the checkpoint was
        # written compares at its default (a new field's default keeps the old behaviour).
        differing = config_differences(payload["config"], self.config)
        if differing:
            raise ConfigError(f"train: {path} was written with another config (differs in {differing}); use a new run directory")
        self._check_robot(path, payload)
        portable = payload["replay"] is None
        phase = payload["progress"]["phase"]
        if portable and phase not in ("learn", "done"):
            raise ConfigError(f"train: {path} is a portable checkpoint in the {phase} phase: the cloning updates would miss the "
                              "demonstrations it collected (its tables were not kept); resume from the whole checkpoint "
                              f"({CHECKPOINT}) or start the run afresh")
        saved_steps = payload["config"]["env_steps"]
        resized = saved_steps != self.config.env_steps
        self.learner.load_state_dict(payload["learner"])
        if not portable:
            self.replay.load_state_dict(payload["replay"])
            self.demonstrations.load_state_dict(payload["demonstrations"])
        self.state = Progress(**payload["progress"])
        self.state.resumptions += 1
        if resized:
            self._resize(saved_steps, self.config.env_steps)
        # (a finished run resumed only to be exported learns nothing more: no refusal, no refill)
        empty = self.state.phase == "learn" and self._tables_empty()
        if empty:
            self._refuse_portable(path)
            if self.state.tables_refilled_at[-1:] != [self.state.env_steps]:
                self.state.tables_refilled_at.append(self.state.env_steps)
        self._recent.extend(payload["recent"])
        tables = self._tables_note(portable, empty)
        self.log(f"train: resumed from {path}: phase {self.state.phase}, {self.state.env_steps} steps, {self.learner.updates} updates{tables}")

    def _tables_empty(self) -> bool:
        """Whether the replay tables and the labelled rows hold nothing (read from a portable
        checkpoint, or from a whole one written before any rows came back)."""
        return len(self.replay) == 0 and len(self.demonstrations) == 0

    def _tables_note(self, portable: bool, empty: bool) -> str:
        """The log's words for the tables a checkpoint brought: none (``portable``), or empty ones
        (``empty``), and then the learner's wait while they refill (``refill_steps``)."""
        note = "; its tables were not kept (a portable checkpoint): they fill anew" if portable else (
            "; its tables are empty: they fill anew" if empty else "")
        steps = self.config.refill_steps
        return note + (f", the learner waiting {steps} steps before it updates" if empty and steps else "")

    def _refuse_portable(self, path: Path) -> None:
        """Raises ConfigError if the run's learn phase, started or resumed from the checkpoint at
        ``path`` with empty tables (a portable one, or one written from it), would have a cloning
        term and no labels to come (none come with learn_mode "policy" unless a ``guided_fraction``
        of its tasks is guided: guided episodes are labelled)."""
        c = self.config
        cloning = max(c.sac.bc_weight if c.bc_weight_start is None else c.bc_weight_start, c.bc_weight_final) > 0
        if c.learn_mode == "policy" and c.guided_fraction == 0.0 and cloning:
            raise ConfigError(f"train: {path} carries no tables (a portable checkpoint, or one written from it: no labelled rows), and in the learn phase with learn_mode "
                              "'policy' the cloning term would have none: start with initialize_phase: demonstrations (and "
                              "demonstrations to collect), learn_mode: dagger or a guided_fraction")

    def robot_record(self) -> dict:
        """The run's robot (``robot.params.scenario_record`` of its rally scenario)."""
        return scenario_file_record(self.config.env.rally.scenario)

    def _check_robot(self, path: Path, payload: dict) -> None:
        """Raises ConfigError if the checkpoint at ``path`` was written for another robot than the
        run's (its states, actions and plans are that robot's); checkpoints written before the
        record existed pass."""
        saved = payload.get("robot")
        mismatch = None if saved is None else scenario_mismatch(saved, self.robot_record())
        if mismatch:
            raise ConfigError(f"train: {path} was written for another robot ({mismatch}); use a new run directory "
                              "or the robot it was trained on")

    def _resize(self, old: int, new: int) -> None:
        """The run's length changed from ``old`` to ``new`` steps (``CHANGEABLE_ON_RESUME``): a run
        shortened below its steps finishes; a finished one extended learns on; in the learn phase the
        schedules go on from the progress they had (``schedule_progress``), without a jump."""
        s = self.state
        self.log(f"train: the run's length changed from {old} to {new} steps at {s.env_steps} steps")
        s.length_changes.append((s.env_steps, old, new))
        if s.phase in ("learn", "done"):
            s.schedule_anchor = (s.env_steps, schedule_progress(s, old))
        if s.phase == "done" and s.env_steps < new:
            s.phase = "learn"  # a finished run extended: learn on to the new length

    def _initialize_from(self, path: Path, payload: dict | None = None) -> None:
        """Starts from another run's checkpoint at ``path`` (``initialize_from``; ``payload``: its
        contents when already read): its learner (the SacConfig must be the same but for the
        fields a stage may change, ``sac.STAGE_FIELDS``), replay tables and demonstrations (none
        from a ``PORTABLE_CHECKPOINT``), and counters, in ``initialize_phase``: the learn phase,
        or the demonstrations phase, whose collections and cloning updates then run on to this
        config's totals, the actor's learning rate set to this stage's ``sac.actor_lr`` (the
        optimiser's state carries the earlier stage's). Its best actor is forgotten (its evaluations may be of
        other shots): this run evaluates its actor first (after its cloning updates, if any) and
        chooses among its own evaluations."""
        payload = read_checkpoint(path) if payload is None else payload
        self._check_robot(path, payload)
        c = self.config
        portable = payload["replay"] is None
        if not portable:
            self.replay.load_state_dict(payload["replay"])
            self.demonstrations.load_state_dict(payload["demonstrations"])
        # a portable checkpoint's tables, or a whole one's written from it before rows came (a
        # finished run resumed elsewhere to be exported); demonstrations first would fill them
        empty = c.initialize_phase == "learn" and self._tables_empty()
        if empty:
            self._refuse_portable(path)
        self.learner.load_state_dict(payload["learner"])
        self.learner.set_actor_lr(c.sac.actor_lr)  # then the schedule (actor_lr_final), if any
        s = self.state = Progress(**payload["progress"])  # its counters and history
        s.phase, s.learn_start, s.resumptions = c.initialize_phase, (s.env_steps, self.learner.updates), 0
        s.initialized_at = s.env_steps
        s.best_rate, s.best_actor, s.best_evaluation = -1.0, None, -1
        # counted per run (max_worker_failures); the earlier run's stay in its logs
        s.worker_failures, s.evaluation_failures = [], []
        s.tables_refilled_at = [s.env_steps] if empty else []  # its learn phase starts with empty tables (refill_steps)
        s.learn_tasks = s.guided_tasks = 0  # the stage's labelling and guiding patterns start with a labelled, a guided task
        s.next_checkpoint = s.env_steps + c.checkpoint_every
        s.next_evaluation = s.env_steps
        tables = self._tables_note(portable, empty)
        self.log(f"train: initialised from {path}: {s.env_steps} steps, {self.learner.updates} updates; {s.phase} phase{tables}")

    def _save_config(self) -> None:
        """Writes the run's config to ``run_dir/config.yaml`` (for reading; the checkpoint holds it too)."""
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(json.loads(json.dumps(to_dict(self.config))), sort_keys=False))


def _write(payload: dict, path: Path) -> None:
    """``torch.save`` of ``payload`` to ``path``, flushed and fsynced (the caller renames it)."""
    with open(path, "wb") as file:
        torch.save(payload, file)
        file.flush()
        os.fsync(file.fileno())


def _sync_directory(directory: Path) -> None:
    """Flushes ``directory``'s entries (the renames of a checkpoint write) to disk, where the
    platform allows it."""
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)
