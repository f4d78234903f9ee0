"""How well can an actor imitate the model-based returner? Offline fits on a training run's
demonstrations (docs/experiments/2026-12-01-imitation.md; ``ace-drake imitation CHECKPOINT``).

The learn phase's cloning term (``learning.sac``) asks the actor's mean to reproduce the
returner's actions from the actor's observation parts. This module measures, on the
demonstrations a run collected (its checkpoint's ``DemonstrationBuffer``), how well an MLP of the
actor's shape can do that with a given choice of parts and amount of data, on rows it was not fitted
on, and how smoothly the labels themselves depend on the ball estimate:

- ``fit_imitation``: an MLP (ReLU, tanh output, Adam) fitted to the first rows, scored on the last
  ``held_out`` fraction (rows are in collection order, so this splits by episode except for one at
  the boundary): the squared action error summed over the 16 components (the cloning loss's
  scale), over all held-out rows, those of the swing (a predicted hit less than ``SWING_TIME``
  ahead) and the others.
- ``imitation_report``: the actor's inputs without and with the ``hit_prediction`` part, and with
  it on a quarter and half of the fitting rows (how the error falls with data).
- ``label_sensitivity``: the returner relabels stored observations, then the same observations
  with the estimate moved by a small noise (1 mm, 1 cm/s, 0.5 rad/s per component): the size of the
  change shows whether the labels are a smooth function of what the actor sees.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ace_drake.config import InputError
from ace_drake.contracts import ObservationLayout
from ace_drake.learning.networks import mlp, observation_scale
from ace_drake.learning.replay import DemonstrationBuffer

SWING_TIME = 0.1  # s: rows whose predicted hit is nearer than this are the swing's
# The actor inputs of the shipped policy (models/train_rally.yaml): the paper's s_t and the estimate.
ESTIMATE_PARTS = ("positions", "spins", "robot_state", "end_effector", "skill", "estimate", "estimate_status")
# The estimate's perturbation of ``label_sensitivity``: p (m), v (m/s), w (rad/s) standard deviations.
ESTIMATE_NOISE = np.r_[np.full(3, 1e-3), np.full(3, 1e-2), np.full(3, 0.5)]


@dataclasses.dataclass(frozen=True)
class ImitationFit:
    """One fit's squared action errors (summed over the 16 components), means over rows."""

    parts: tuple[str, ...]
    fit_rows: int
    held_out: float
    held_out_swing: float
    held_out_other: float
    train: float
    label_variance: float  # the held-out labels' variance summed over the components


def in_swing(observations: np.ndarray, layout: ObservationLayout) -> np.ndarray:
    """Whether observations (..., n) have a predicted hit less than SWING_TIME ahead."""
    hit = np.asarray(observations)[..., layout.slice("hit_prediction")]
    return (hit[..., 0] > 0.5) & (hit[..., 1] < SWING_TIME)


def demonstration_arrays(checkpoint) -> tuple[np.ndarray, np.ndarray, ObservationLayout]:
    """(observations (N, n), the returner's actions (N, 16), the observation layout of the run's
    learner) of a training checkpoint's demonstration buffer, in collection order. Raises
    ValueError when it holds none."""
    from ace_drake.learning.replay import load_weights_only

    payload = load_weights_only(checkpoint)
    if "demonstrations" not in payload:
        raise InputError(f"imitation: {checkpoint} is not a training checkpoint (no demonstrations)")
    buffer = DemonstrationBuffer(capacity=int(payload["demonstrations"]["buffer"]["capacity"]))
    buffer.load_state_dict(payload["demonstrations"])
    if len(buffer) == 0:
        raise InputError(f"imitation: {checkpoint} holds no demonstrations")
    rows = buffer.buffer.get(buffer.buffer.oldest_first())
    sac = payload.get("config", {}).get("sac", {})
    layout = ObservationLayout(sac.get("position_history", 10), sac.get("spin_history", 10))
    if rows["obs"].shape[1] != layout.size:
        raise InputError(f"imitation: {checkpoint}'s observations have {rows['obs'].shape[1]} values, its layout {layout.size} "
                         "(written before an observation part was added?)")
    return rows["obs"].astype(np.float32), rows["demo_action"].astype(np.float32), layout


def fit_imitation(
    observations: np.ndarray,
    actions: np.ndarray,
    layout: ObservationLayout,
    parts: Sequence[str],
    hidden: Sequence[int] = (512, 512),
    steps: int = 6000,
    seed: int = 0,
    held_out: float = 0.1,
    fit_fraction: float = 1.0,
    batch_size: int = 256,
    learning_rate: float = 3e-4,
) -> ImitationFit:
    """Fits tanh(MLP(scaled parts)) to the actions of the rows before the held-out tail (their
    first ``fit_fraction``) by ``steps`` Adam steps on minibatches, seeded; scores it (module
    docstring). Inputs are scaled as the actor's (``networks.observation_scale``)."""


    observations, actions = np.asarray(observations, np.float32), np.asarray(actions, np.float32)
    if observations.ndim != 2 or observations.shape[1] != layout.size or actions.shape != (len(observations), 16):
        raise ValueError(f"fit_imitation: need observations (N, {layout.size}) and actions (N, 16), got {observations.shape}, {actions.shape}")
    split = int(round((1.0 - held_out) * len(observations)))
    fit_rows = int(fit_fraction * split)
    if not 0.0 < held_out < 1.0 or fit_rows < batch_size or split == len(observations):
        raise InputError(f"fit_imitation: {len(observations)} rows are too few to fit {fit_rows} and hold out {held_out:.0%}")
    columns = layout.indices(parts)
    scale = observation_scale(layout).astype(np.float32)[columns]
    x, y = torch.as_tensor(observations[:, columns] / scale), torch.as_tensor(actions)
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = mlp(len(columns), hidden, actions.shape[1])
    optimiser = torch.optim.Adam(net.parameters(), learning_rate)
    for _ in range(steps):
        rows = torch.randint(fit_rows, (batch_size,), generator=generator)
        loss = ((torch.tanh(net(x[rows])) - y[rows]) ** 2).sum(-1).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        test = ((torch.tanh(net(x[split:])) - y[split:]) ** 2).sum(-1).numpy()
        train = float(((torch.tanh(net(x[:fit_rows])) - y[:fit_rows]) ** 2).sum(-1).mean())
    swing = in_swing(observations[split:], layout)
    return ImitationFit(
        parts=tuple(parts), fit_rows=fit_rows, held_out=float(test.mean()),
        held_out_swing=float(test[swing].mean()) if swing.any() else float("nan"),
        held_out_other=float(test[~swing].mean()) if (~swing).any() else float("nan"),
        train=train, label_variance=float(actions[split:].var(axis=0).sum()),
    )


def imitation_report(observations, actions, layout: ObservationLayout, steps: int = 6000, seed: int = 0,
                     progress: Callable[[str], None] = lambda message: None) -> list[ImitationFit]:
    """The fits of the module docstring: the shipped actor's inputs, the same with
    ``hit_prediction`` on all, a half and a quarter of the fitting rows."""
    with_hit = (*ESTIMATE_PARTS, "hit_prediction")
    fits = []
    for parts, fraction in ((ESTIMATE_PARTS, 1.0), (with_hit, 1.0), (with_hit, 0.5), (with_hit, 0.25)):
        fits.append(fit_imitation(observations, actions, layout, parts, steps=steps, seed=seed, fit_fraction=fraction))
        progress(f"imitation: {'+ hit_prediction' if 'hit_prediction' in parts else 'without hit_prediction'}, "
                 f"{fits[-1].fit_rows} rows: held-out {fits[-1].held_out:.3f}")
    return fits


def label_sensitivity(observations: np.ndarray, returner, layout: ObservationLayout, rows: int = 300, seed: int = 0) -> dict:
    """The returner's labels of ``rows`` random stored observations against its labels of the
    same with the estimate perturbed by ESTIMATE_NOISE (module docstring): the squared change
    summed over the components (mean, median, the share above 0.5), overall and in the swing.
    Observations where either call gives no action are skipped (counted)."""
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(observations), size=min(rows, len(observations)), replace=False)
    estimate = layout.slice("estimate")
    changes, swing, skipped = [], [], 0
    for row in chosen:
        observation = np.asarray(observations[row], dtype=float)
        moved = observation.copy()
        moved[estimate] += rng.normal(0.0, ESTIMATE_NOISE)
        first, second = returner(observation), returner(moved)
        if first is None or second is None:
            skipped += 1
            continue
        changes.append(float(np.sum((second - first) ** 2)))
        swing.append(bool(in_swing(observation, layout)))
    changes, swing = np.asarray(changes), np.asarray(swing, dtype=bool)
    if changes.size == 0:
        raise InputError("label_sensitivity: the returner gave no action on any chosen observation")
    return {
        "rows": int(changes.size), "skipped": skipped, "mean": float(changes.mean()), "median": float(np.median(changes)),
        "share_above_0.5": float(np.mean(changes > 0.5)),
        "swing_mean": float(changes[swing].mean()) if swing.any() else None,
        "other_mean": float(changes[~swing].mean()) if (~swing).any() else None,
    }
