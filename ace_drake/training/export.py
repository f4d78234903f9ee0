"""A training run's artefacts (``training.loop``'s module docstring): ``export`` writes the policy
(``models/policies/<name>.pt``), its sidecar JSON (``artefacts.write_sidecar``) and the learning
curve PNG; ``train_and_export`` is ``ace-drake train``: a run, then its export, with the exported
actor evaluated on recorded human shots if asked.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ace_drake.artefacts import write_sidecar
from ace_drake.config import MODELS_DIR, ConfigError, to_dict
from ace_drake.evaluation.evaluate import evaluate_controller
from ace_drake.learning.sac import save_policy
from ace_drake.robot.model import load_scenario
from ace_drake.play.shots import held_out_players
from ace_drake.training.checkpoint import CHECKPOINT, PREVIOUS_CHECKPOINT, Progress
from ace_drake.training.loop import TrainConfig, Trainer, load_train_config


def export(trainer: Trainer, policies_dir, which: str = "best", evaluation: dict | None = None) -> dict:
    """Writes ``<name>.pt`` (``sac.save_policy``), ``<name>.json`` (its sidecar, by
    ``artefacts.write_sidecar``: command, date, seed, the run as it stands (``run_record``: steps,
    updates, wall time in s, the periodic evaluations, failures) and ``evaluation``, e.g. the
    human-shot figures of ``final_evaluation``, the config, the robot it was trained for) and
    ``<name>_curve.png`` (learning curve) into ``policies_dir``; ``which``: "best" (the best
    evaluated actor), "final" or "actor" (``chosen_actor``). Returns the sidecar."""

    s, c = trainer.state, trainer.config
    actor, chosen = chosen_actor(trainer, which)
    policies_dir = Path(policies_dir)
    policies_dir.mkdir(parents=True, exist_ok=True)
    policy_path = policies_dir / f"{c.name}.pt"
    save_policy(policy_path, trainer.learner, actor)
    sidecar = write_sidecar(
        policy_path,
        seed=c.seed,
        name=c.name,
        actor=ACTOR_LABELS["final" if which == "best" and s.best_actor is None else which]
        + (" (not its average)" if which == "actor" and trainer.learner.averaged_actor is not None else ""),
        actor_at=None if chosen is None else {"env_steps": chosen[0], "updates": chosen[1], "evaluation": chosen[2]},
        **trainer.run_record(),
        final_evaluation=evaluation,
        config=to_dict(c),
        robot=trainer.robot_record(),  # the robot it was trained for (robot.params.scenario_record)
    )
    spread = c.exploration.policy_std_scale * c.sac.std_scale  # of the actor network's
    rollouts = "actor's mean" if spread == 0.0 else (
        "stochastic actor" if spread == 1.0 else f"actor at {spread:g} of its spread")
    started_at = s.initialized_at
    if started_at is None and c.initialize_from:
        started_at = s.learn_start[0]  # a run initialised before Progress.initialized_at existed: the same step
    step_seconds = c.env.rally.control.segment_samples * load_scenario(MODELS_DIR / c.env.rally.scenario).dynamics.command_period
    evaluated = "averaged actor, deterministic" if trainer.learner.averaged_actor is not None else "deterministic actor"
    plot_learning_curve(s, policies_dir / f"{c.name}_curve.png", c.name, evaluation_description(c), started_at, rollouts, step_seconds,
                        evaluated)
    return sidecar


def final_evaluation(trainer: Trainer, which: str, data, progress: Callable[[str], None] = print) -> dict:
    """The export's evaluation of the ``which`` actor (``chosen_policy``) on the recorded human
    shots (shot_p2) of the match-data CSV ``data``: ``ace-drake evaluate --controller
    policy:<name> --data <data>`` as if it were shipped (``evaluation.evaluate.evaluate_controller``
    with its defaults: the cameras, seed 0, the segment-stepped diagram 32 episodes at a time), and
    for a run trained on some players' shots the same with ``--players`` the others, under
    ``held_out``: the figure that decides whether it ships (issue 30) and, once stored in
    docs/results/heldout/, the main job's controller."""
    policy = chosen_policy(trainer, which)
    name = f"policy:{trainer.config.name}"

    def human_evaluation(players: tuple[str, ...] = ()) -> dict:
        return evaluate_controller(name, data=data, players=players, progress=progress, make=lambda params: policy)

    evaluation = human_evaluation()
    held_out = held_out_players(trainer.config.env.shots, data)
    if held_out:  # trained on some players' shots: the others' are reported on their own
        evaluation["held_out"] = human_evaluation(held_out)
    return evaluation


def train_and_export(config_path, run_dir=None, export_dir=MODELS_DIR / "policies", which: str = "best",
                     evaluate_data=None, export_only: bool = False, progress: Callable[[str], None] = print,
                     overwrite: bool = False, earlier_stage=None, resume_from=None) -> dict:
    """``ace-drake train``: the run of the config YAML ``config_path`` in ``run_dir`` (default
    out/train/<name>; resumed from its checkpoint if it has one; with ``export_only`` not trained
    further), then ``export`` into ``export_dir`` with, given the match-data CSV
    ``evaluate_data``, its ``final_evaluation``. Returns ``policy`` (the exported file), the run's
    ``env_steps``, ``episodes``, ``updates``, ``wall_time_s`` (s) and ``actor_at``, and
    ``final_evaluation`` (None without ``evaluate_data``). Raises ConfigError for a bad config,
    with ``export_only`` for a run directory without a checkpoint, and, before anything is trained
    or written, when ``export_dir`` already holds a policy of the config's name (a shipped one,
    say) unless ``overwrite``. ``earlier_stage``: a checkpoint of the config's ``after:`` stage to
    start from instead of running it; ``resume_from``: a checkpoint of this run to resume from in
    an empty ``run_dir`` (both ``Trainer``'s)."""
    config = load_train_config(config_path)
    run_dir = Path(run_dir or MODELS_DIR.parent / "out" / "train" / config.name)
    progress(f"train: {config_path} -> {run_dir} (seed {config.seed}, {config.workers} {config.backend} worker(s), {config.env_steps} steps)")
    if export_only and resume_from is None and not any((run_dir / name).is_file() for name in (CHECKPOINT, PREVIOUS_CHECKPOINT)):
        raise ConfigError(f"train --export-only: no checkpoint in {run_dir}")
    existing = [path for path in (Path(export_dir) / f"{config.name}{suffix}" for suffix in (".pt", ".json", "_curve.png")) if path.exists()]
    if existing and not overwrite:
        raise ConfigError(f"train: {existing[0]} exists (a policy named {config.name!r}, e.g. a shipped one); give --overwrite to "
                          "replace it, or another --export-dir or config name")
    trainer = Trainer(config, run_dir, progress=progress, earlier_stage=earlier_stage, resume_from=resume_from)
    if export_only:
        progress(f"train: exporting the run as it stands ({trainer.state.env_steps} steps, phase {trainer.state.phase}), no training")
    else:
        trainer.run()
    evaluation = final_evaluation(trainer, which, evaluate_data, progress) if evaluate_data else None
    sidecar = export(trainer, export_dir, which, evaluation)
    return {"policy": str(Path(export_dir) / f"{config.name}.pt"),
            **{key: sidecar[key] for key in ("env_steps", "episodes", "updates", "wall_time_s", "actor_at")},
            "final_evaluation": evaluation}


# What each choice of ``chosen_actor`` exports, in the sidecar's words.
ACTOR_LABELS = {"best": "best evaluated", "final": "final", "actor": "final, the actor itself"}


def chosen_actor(trainer: Trainer, which: str) -> tuple[dict, tuple | None]:
    """The actor ``export`` writes: its state dict ("best": the best evaluated one, else the
    final; "final": the learner's policy actor, the averaged one if it keeps one; "actor": the
    actor itself as it stands, which the episodes play, even where an average is kept) and its
    evaluation entry (env_steps, updates, figures), None when that actor was not evaluated (the
    periodic evaluations of a run that averages are its average's)."""
    if which not in ACTOR_LABELS:
        raise ValueError(f"export: which must be one of {', '.join(map(repr, ACTOR_LABELS))}, got {which!r}")
    s = trainer.state
    if which == "actor":
        evaluated = trainer.learner.averaged_actor is None and s.evaluations and s.evaluations[-1][0] == s.env_steps
        return trainer.learner.actor.state_dict(), s.evaluations[-1] if evaluated else None
    if which == "best" and s.best_actor is not None:
        if s.best_evaluation >= 0:
            return s.best_actor, s.evaluations[s.best_evaluation]
        # A checkpoint from before best_evaluation was recorded: the highest evaluation.
        return s.best_actor, max(s.evaluations, key=lambda e: e[2]["rate"] if e[2]["rate"] is not None else -1.0)
    last = s.evaluations[-1] if s.evaluations and s.evaluations[-1][0] == s.env_steps else None
    return trainer.learner.policy_actor.state_dict(), last


def chosen_policy(trainer: Trainer, which: str):
    """The DeterministicPolicy of ``chosen_actor`` (what the exported file holds)."""
    return trainer.learner.policy(chosen_actor(trainer, which)[0])


def evaluation_description(config: TrainConfig) -> str:
    """What the periodic evaluation plays, in words (for the learning curve's legend)."""
    times = f", each {config.evaluation_repeats} times" if config.evaluation_repeats > 1 else ""
    if not config.evaluation_data:
        return f"{config.evaluation_episodes} synthetic shots{times}"
    of = f" of {', '.join(config.evaluation_players)}" if config.evaluation_players else ""
    return f"first {config.evaluation_episodes} human shots{of}{times}"


def _draw_evaluations(axes, points: list, color: str, label: str) -> None:
    """Evaluations [(x, figures)] as return rates with their 95 % intervals."""
    if not points:
        return
    rates = np.array([e[1]["rate"] for e in points])
    low = rates - np.array([e[1]["ci95"][0] for e in points])
    high = np.array([e[1]["ci95"][1] for e in points]) - rates
    axes.errorbar([e[0] for e in points], rates, yerr=[low, high], fmt="o-", color=color, capsize=3, label=label)


def evaluation_series(state: Progress, description: str = "", started_at: int | None = None,
                      actor: str = "deterministic actor") -> list[tuple[list, str]]:
    """The learning curve's evaluation series, [(points, label)], points (env_steps, figures):
    one series, or for a run started from another's checkpoint at ``started_at`` steps the
    earlier run's evaluations (at or before it) and this run's (after it); ``actor``: what the
    evaluations played (the averaged actor where the learner keeps one, ``SacConfig.actor_average``)."""
    evaluated = [(e[0], e[2]) for e in state.evaluations if e[2]["rate"] is not None]
    label = f"evaluation: {description} ({actor})" if description else f"evaluation ({actor})"
    if started_at is None:
        return [(evaluated, label)]
    return [([e for e in evaluated if e[0] <= started_at], "evaluation of the run it started from (its own shots)"),
            ([e for e in evaluated if e[0] > started_at], label)]


def heldout_series(state: Progress) -> tuple[list, str, str]:
    """The evaluations on the held-out players (``TrainConfig.heldout_players``): (points
    [(env_steps, figures)], colour, label); no points when the run has none."""
    points = [(e[0], e[2]["heldout"]) for e in state.evaluations if e[2].get("heldout", {}).get("rate") is not None]
    players = ", ".join(points[0][1]["players"]) if points else ""
    # a later stage may play them more times than its earlier stages did: name every count
    repeats = sorted({figures.get("repeats", 1) for _, figures in points})
    times = f", each {' or '.join(map(str, repeats))} times" if repeats and repeats != [1] else ""
    return points, "C2", f"held-out players ({players}), all their shots{times}"


def cloning_curve(state: Progress) -> list[tuple[int, dict]] | None:
    """A run that only clones (``pretrain_evaluate_every``): its evaluations as (learner updates,
    figures), when there are several and all came at one environment step count; else None."""
    evaluated = [e for e in state.evaluations if e[2]["rate"] is not None]
    if len(evaluated) < 2 or len({e[0] for e in evaluated}) > 1:
        return None
    return [(updates, figures) for _, updates, figures in evaluated]


def plot_learning_curve(state: Progress, path, title: str, description: str = "", started_at: int | None = None,
                        rollouts: str = "stochastic actor", step_seconds: float = 0.032,
                        actor: str = "deterministic actor") -> None:
    """Return rate against environment steps: the rollout policy's (last 100 episodes; how it
    acted: ``rollouts``) and the periodic evaluations' (with their 95 % intervals) on
    ``description``'s shots. A run started from another's checkpoint at ``started_at`` steps
    (``initialize_from``) draws the earlier run's evaluations, which may be of other shots, as a
    separate series; evaluations on held-out players (``heldout_series``) as one more. The top axis
    counts hours of simulated play (``step_seconds`` per environment step: one control segment). A
    run that only clones (``cloning_curve``) is drawn against learner updates; ``actor`` names
    what the evaluations played (``evaluation_series``)."""
    figure = Figure(figsize=(6, 4.5), dpi=100, layout="constrained")  # no pyplot: no display, no global figure state
    axes = figure.subplots()
    cloning = cloning_curve(state) if started_at is None else None
    if cloning is not None:
        ((_, label),) = evaluation_series(state, description, actor=actor)
        _draw_evaluations(axes, cloning, "C0", label)
        axes.set_xlabel(f"cloning updates (on {state.evaluations[0][0]:,} environment steps collected)")
    else:
        if state.rollout_curve:
            steps, _, rates = zip(*state.rollout_curve)
            axes.plot(steps, rates, color="0.6", label=f"rollouts ({rollouts}, last 100)")
        series = evaluation_series(state, description, started_at, actor)
        for (points, name), color in zip(series, ("C1", "C0")[-len(series):]):  # this run's in C0
            _draw_evaluations(axes, points, color, name)
        heldout = heldout_series(state)
        if heldout[0]:
            _draw_evaluations(axes, *heldout)
        axes.set_xlabel("environment steps (32 ms)")
        hours = axes.secondary_xaxis("top", functions=(lambda steps: steps * step_seconds / 3600.0, lambda h: h * 3600.0 / step_seconds))
        hours.set_xlabel("hours of simulated play", fontsize=8)
    axes.set_ylabel("return rate")
    axes.set_ylim(0.0, 1.0)
    axes.set_title(title)
    axes.grid(alpha=0.3)
    if axes.get_legend_handles_labels()[0]:  # a run with nothing drawn yet has no legend
        # beneath the axes, where it hides no point however long a run's curve and labels are
        figure.legend(loc="outside lower center", fontsize=7)
    figure.savefig(path)
