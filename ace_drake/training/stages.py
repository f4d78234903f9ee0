"""A training run in stages (``TrainConfig.after``): a run that continues an earlier one.

``after`` is the earlier stage's whole config. ``Trainer`` with ``after`` and no checkpoint of its
own first runs that stage to its end in its own run directory, ``<run_dir>/after`` (resuming it
there if it was stopped, reusing it if it has finished), then starts from its checkpoint as from
``initialize_from`` (its learner, replay tables, demonstrations and counters, in
``initialize_phase``): one config and one command for a policy trained in stages
(``models/train_rally_paper.yaml``; docs/training.md, *Training the paper's policy*). The stages share the
learner's config but for the fields a stage may change (``sac.STAGE_FIELDS``: the cloning term's,
the averaged actor's, the spread's scale, the entropy weight and the actor's learning rate;
``TrainConfig`` checks), as its checkpoint is loaded.

In a config file (``loop.load_train_config``), ``after:`` is written as the earlier stage's
changes from the stage that follows it (``with_earlier_stages``), and may hold an ``after:`` of its
own.
"""

from __future__ import annotations

from pathlib import Path

from ace_drake.config import ConfigError, merge
from ace_drake.training.checkpoint import config_differences, latest_checkpoint, read_checkpoint

EARLIER_STAGE_DIR = "after"  # the earlier stage's run directory, inside the later stage's


def with_earlier_stages(data):
    """A training config's YAML mapping with its ``after:`` (the earlier stage's changes from this
    stage) made the earlier stage's whole mapping: this one without ``after``, those changes
    deep-merged over it (``config.merge``); recursively for the earlier stage's own ``after:``."""
    if not isinstance(data, dict) or data.get("after") is None:
        return data
    changes = data["after"]
    if not isinstance(changes, dict):
        raise ConfigError(f"after: expected a mapping (the earlier stage's changes from this one), got {changes!r}")
    stage = {key: value for key, value in data.items() if key != "after"}
    return {**data, "after": with_earlier_stages(merge(stage, changes))}


def earlier_stage_checkpoint(trainer) -> tuple[Path, dict]:
    """Runs ``trainer.config.after`` to its end in ``trainer.run_dir / EARLIER_STAGE_DIR`` with
    ``trainer``'s class and progress callable (resuming it there, or nothing if it has finished)
    and returns its checkpoint's path and payload (a finished stage's checkpoint is read once: a
    full one is ~2.3 GB)."""
    run_dir = trainer.run_dir / EARLIER_STAGE_DIR
    latest = latest_checkpoint(run_dir)  # the latest, or the one before it if that cannot be read
    same = latest is not None and not config_differences(latest[1]["config"], trainer.config.after)
    if same:  # (another config is refused below, as in any run directory)
        _refuse_past_its_length(*latest, trainer.config.after)
    if same and _finished(latest[1], trainer.config.after):
        trainer.log(f"train: the earlier stage (after:) has finished in {run_dir}: continuing from its checkpoint")
        return latest
    del latest  # not held while the earlier stage runs (a full payload is ~2.3 GB)
    # to run, resume, extend, or refuse (another config) as any run in its directory
    earlier = type(trainer)(trainer.config.after, run_dir, trainer.log)
    trainer.log(f"train: the earlier stage (after:) first, in {run_dir}")
    earlier.run()
    del earlier  # nor its tables
    latest = latest_checkpoint(run_dir)
    if latest is None:
        raise ConfigError(f"train: the earlier stage in {run_dir} has no checkpoint")
    return latest


def _refuse_past_its_length(path: Path, payload: dict, config) -> None:
    """Raises ConfigError if the checkpoint ``payload`` (at ``path``) of the earlier stage
    ``config`` has run past that stage's length without having been finished at it: a stage
    shortened since (e.g. to the step of its best evaluation) cannot be rewound, and starting from
    the later actor would be another run than the config says. That is a checkpoint past the
    length it was written with, or one that this run (since ``initialized_at``) shortened to below
    where it stood, and which then finished at once (``Progress.length_changes``)."""
    progress = payload["progress"]
    steps, length = progress["env_steps"], payload["config"]["env_steps"]
    since = progress.get("initialized_at") or 0
    shortened_below = any(at >= since and at > new for at, _, new in progress.get("length_changes", ()))
    if (steps > config.env_steps and length != config.env_steps) or shortened_below:
        raise ConfigError(f"train: {path} ran to {steps} steps (of {length}), past the earlier stage's length {config.env_steps}: "
                          "it cannot be rewound; start from a checkpoint of that stage at its length")


def _finished(payload: dict, config) -> bool:
    """Whether the checkpoint ``payload`` has finished its run at ``config``'s length (a stage
    extended since has not); its config is the caller's to compare."""
    progress = payload["progress"]
    return progress["phase"] == "done" and progress["env_steps"] >= config.env_steps


def earlier_stage_from(trainer, path: Path) -> tuple[Path, dict]:
    """``path``, a checkpoint of ``trainer.config.after`` written elsewhere (e.g. its portable
    checkpoint, carried to a machine without ``run_dir/after``: ``ace-drake train --earlier-stage``),
    to start from instead of running that stage. Raises ConfigError if it was written with
    another config than the earlier stage's (but for its length, ``CHANGEABLE_ON_RESUME``) or
    before that stage finished (at the config's length: a stage since extended has not). Returns
    its path and payload."""
    payload = read_checkpoint(path)
    differing = config_differences(payload["config"], trainer.config.after)
    if differing:
        raise ConfigError(f"train: {path} is not a checkpoint of the config's earlier stage (after:): it differs in {differing}")
    _refuse_past_its_length(path, payload, trainer.config.after)
    if not _finished(payload, trainer.config.after):
        progress = payload["progress"]
        raise ConfigError(f"train: {path} is a checkpoint of the earlier stage before its end (phase {progress['phase']}, "
                          f"{progress['env_steps']} of {trainer.config.after.env_steps} steps); finish that stage first")
    trainer.log(f"train: the earlier stage (after:) from {path}")
    return path, payload
