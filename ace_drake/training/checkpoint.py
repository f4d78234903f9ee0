"""A training run's checkpoint (``training.loop``'s module docstring): every ``checkpoint_every``
steps the whole learner state (networks, optimisers, generator, replay tables, demonstrations,
counters, history) is written atomically to ``run_dir/checkpoint.pt``; a ``Trainer`` made on a
run directory that holds one resumes from it, and one whose config names ``initialize_from``
starts from another run's. ``Checkpointing`` holds these methods of ``loop.Trainer`` (its
``config``, ``learner``, ``replay``, ``demonstrations``, ``state``, ``_recent``, ``run_dir``,
``log``, ``_started`` and ``_elapsed``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import torch
import yaml

from ace_drake.config import ConfigError, from_dict, to_dict

CHECKPOINT = "checkpoint.pt"


class Checkpointing:
    """Saving, loading and resuming a ``loop.Trainer``'s run (module docstring)."""

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
        }
        path = self.run_dir / CHECKPOINT
        temporary = path.with_name(path.name + ".tmp")
        torch.save(payload, temporary)
        os.replace(temporary, path)

    def _load(self, path: Path) -> None:
        """Resumes the run from its own checkpoint ``path``; raises ConfigError if that was
        written with another config."""
        from ace_drake.training.loop import Progress, TrainConfig  # loop.py imports this module

        payload = torch.load(path, weights_only=False)
        # Read back through the config classes, so that a field added since the checkpoint was
        # written compares at its default (a new field's default keeps the old behaviour).
        saved = to_dict(from_dict(TrainConfig, payload["config"]))
        if saved != to_dict(self.config):
            differing = sorted(k for k, v in to_dict(self.config).items() if saved.get(k) != v)
            raise ConfigError(f"train: {path} was written with another config (differs in {differing}); use a new run directory")
        self.learner.load_state_dict(payload["learner"])
        self.replay.load_state_dict(payload["replay"])
        self.demonstrations.load_state_dict(payload["demonstrations"])
        self.state = Progress(**payload["progress"])
        self.state.resumptions += 1
        self._recent.extend(payload["recent"])
        self.log(f"train: resumed from {path}: phase {self.state.phase}, {self.state.env_steps} steps, {self.learner.updates} updates")

    def _initialize_from(self, path: Path) -> None:
        """Starts from another run's checkpoint (``initialize_from``): its learner (the SacConfig
        must be the same), replay tables, demonstrations and counters, in ``initialize_phase``:
        the learn phase, or the demonstrations phase, whose collections and cloning updates then
        run on to this config's totals. Its best actor is forgotten (its evaluations may be of
        other shots): this run evaluates its actor first (after its cloning updates, if any) and
        chooses among its own evaluations."""
        from ace_drake.training.loop import Progress  # loop.py imports this module

        payload = torch.load(path, weights_only=False)
        self.learner.load_state_dict(payload["learner"])
        self.replay.load_state_dict(payload["replay"])
        self.demonstrations.load_state_dict(payload["demonstrations"])
        s = self.state = Progress(**payload["progress"])  # its counters and history
        c = self.config
        s.phase, s.learn_start, s.resumptions = c.initialize_phase, (s.env_steps, self.learner.updates), 0
        s.initialized_at = s.env_steps
        s.best_rate, s.best_actor, s.best_evaluation = -1.0, None, -1
        s.next_checkpoint = s.env_steps + c.checkpoint_every
        s.next_evaluation = s.env_steps
        self.log(f"train: initialised from {path}: {s.env_steps} steps, {self.learner.updates} updates; {s.phase} phase")

    def _save_config(self) -> None:
        """Writes the run's config to ``run_dir/config.yaml`` (for reading; the checkpoint holds it too)."""
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(json.loads(json.dumps(to_dict(self.config))), sort_keys=False))
