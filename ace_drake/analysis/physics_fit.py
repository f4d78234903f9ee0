"""Identify aerodynamic and table coefficients from recorded match events (SciPy least squares).

The residual of one (shot or bounce) -> bounce pair is the predicted landing point, flight time
and post-bounce velocity and spin minus the recorded ones (see physics_validation.py), each scaled
by a typical measurement error so that the terms are comparable; a Cauchy loss keeps badly
estimated recordings from dominating. Fit on some players, judge on the others.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import yaml
from scipy.optimize import least_squares

from ace_drake.analysis.physics_validation import predict_pairs, summarize
from ace_drake.artefacts import data_file, sidecar_path, write_sidecar
from ace_drake.config import MODELS_DIR, ConfigError, InputError, to_dict
from ace_drake.match_data import EventPairs, event_pairs, load_match_events
from ace_drake.physics.params import BallPhysicsParams, load_ball_params

# name -> (lower, upper): the coefficients the fit may change, and the box it keeps them in.
FIT_BOUNDS = {
    "aero.drag_coefficient": (0.2, 1.2),
    "aero.magnus_slope": (0.0, 0.5),
    "aero.magnus_offset": (-0.05, 0.05),
    "aero.magnus_scale": (0.2, 3.0),  # the refined Magnus model's only free coefficient
    "table.friction": (0.02, 0.8),
    "table.restitution_base": (0.6, 1.0),
    "table.restitution_slope": (0.0, 0.15),
}
DEFAULT_FIT_PARAMETERS = tuple(name for name in FIT_BOUNDS if name != "aero.magnus_scale")  # the printed model's


def default_fit_parameters(params: BallPhysicsParams) -> tuple[str, ...]:
    """The coefficients ``physics-fit`` fits by default from ``params``: its drag coefficient (a
    constant, or the scale of the spin-ratio table), its Magnus model's coefficients (slope and
    offset of the printed ratio law, or the refined model's scale) and the table's."""
    if params.aero.magnus_model == "refined":
        return tuple(name for name in FIT_BOUNDS if name not in ("aero.magnus_slope", "aero.magnus_offset"))
    return DEFAULT_FIT_PARAMETERS



@dataclasses.dataclass(frozen=True)
class ResidualScales:
    """What counts as one unit of error in each residual term.

    The recorded event times carry a detection latency of their own (the printed model is ~20 ms
    early at landing on every transition, whatever the spin, while its landing points are only
    ~15 cm off), so time is weighted weakly: 50 ms weighs as much as 3 cm of landing error.
    """

    landing: float = 0.03  # m
    time: float = 0.05  # s
    velocity: float = 0.3  # m/s, post-bounce
    spin: float = 30.0  # rad/s, post-bounce
    missing: float = 10.0  # scaled residual of a prediction that never reaches the table


@dataclasses.dataclass
class FitResult:
    """Fitted parameters, the values of the fitted coefficients, and the optimiser's record."""

    params: BallPhysicsParams
    values: dict
    initial_cost: float
    final_cost: float
    evaluations: int
    message: str


def get_value(params: BallPhysicsParams, name: str) -> float:
    """Reads a dotted coefficient such as ``aero.drag_coefficient``."""
    group, field = _split(name)
    return getattr(getattr(params, group), field)


def with_values(params: BallPhysicsParams, names: Sequence[str], values: Sequence[float]) -> BallPhysicsParams:
    """A copy of ``params`` with the dotted coefficients ``names`` set to ``values``."""
    updates: dict[str, dict] = {}
    for name, value in zip(names, values):
        group, field = _split(name)
        updates.setdefault(group, {})[field] = float(value)
    return dataclasses.replace(
        params, **{group: dataclasses.replace(getattr(params, group), **fields) for group, fields in updates.items()}
    )


def pair_residuals(pairs: EventPairs, params: BallPhysicsParams, scales: ResidualScales = ResidualScales()) -> np.ndarray:
    """Scaled residuals (N, 9): landing x, y; time; post-bounce velocity (3); post-bounce spin (3)."""
    predictions = predict_pairs(pairs, params)
    residuals = np.concatenate(
        [
            (predictions.predicted_contact[:, :2] - pairs.end_states[:, :2]) / scales.landing,
            predictions.time_error[:, None] / scales.time,
            (predictions.predicted_post[:, 3:6] - pairs.end_states[:, 3:6]) / scales.velocity,
            (predictions.predicted_post[:, 6:9] - pairs.end_states[:, 6:9]) / scales.spin,
        ],
        axis=1,
    )
    return np.where(np.isfinite(residuals), residuals, scales.missing)


# Candidate values per coefficient: before each stage's local search, every combination of these
# (and the initial values) is evaluated on the fitting pairs, and the search starts from the best.
# The flight-model cost is flat and ragged near the paper's values (predictions switch between
# clearing and clipping the net), where a local search alone stops early.
START_GRID = {
    "aero.drag_coefficient": (0.3, 0.4, 0.5, 0.6),
    "aero.magnus_slope": (0.07, 0.09, 0.11, 0.13),
    "aero.magnus_offset": (-0.03, -0.01, 0.0),
    "aero.magnus_scale": (0.7, 1.0, 1.4),
}

# Which residual columns (of pair_residuals) identify which coefficients: the landing point and
# time depend only on the flight model (the start states are recorded), the post-bounce velocity
# and spin mostly on the table model. Fitting the two groups in turn keeps each least-squares
# problem small and well conditioned.
STAGES = (("flight", "aero.", slice(0, 3)), ("bounce", "table.", slice(3, 9)))


def fit_physics(
    pairs: EventPairs,
    initial: BallPhysicsParams | None = None,
    names: Sequence[str] = DEFAULT_FIT_PARAMETERS,
    max_evaluations: int = 200,
    progress: Callable[[str], None] | None = None,
    scales: ResidualScales = ResidualScales(),
    loss: str = "cauchy",
) -> FitResult:
    """Least-squares fit of the coefficients ``names`` (keys of FIT_BOUNDS) to ``pairs``.

    Two stages (see STAGES): the ``aero.*`` coefficients on landing point and time, then the
    ``table.*`` coefficients on post-bounce velocity and spin, each started from the best point of
    START_GRID and refined by SciPy's trust-region least squares with at most ``max_evaluations``
    model evaluations. The default Cauchy loss
    gives a recording that is far off (estimation glitches, a p90 landing error of ~60 cm) little
    pull, so the fit follows the bulk of the data, which the median error measures. Deterministic:
    the same data and start give the same result. ``progress`` receives a line per evaluation.
    """
    if len(pairs) == 0:
        raise InputError("fit_physics: no event pairs to fit")
    unknown = [n for n in names if n not in FIT_BOUNDS]
    if unknown:
        raise InputError(f"fit_physics: cannot fit {unknown}; choose from {sorted(FIT_BOUNDS)}")
    params = initial or BallPhysicsParams()
    evaluations = [0]
    messages = []
    costs = []
    for stage, prefix, columns in STAGES:
        stage_names = tuple(n for n in names if n.startswith(prefix))
        if not stage_names:
            continue
        lower = np.array([FIT_BOUNDS[n][0] for n in stage_names])
        upper = np.array([FIT_BOUNDS[n][1] for n in stage_names])
        x0 = np.clip([get_value(params, n) for n in stage_names], lower, upper)
        start = params

        def residuals(x: np.ndarray, start=start, stage_names=stage_names, columns=columns, stage=stage) -> np.ndarray:
            values = pair_residuals(pairs, with_values(start, stage_names, x), scales)[:, columns].ravel()
            evaluations[0] += 1
            if progress is not None:
                cost = float(np.sum(np.log1p(values**2)))
                progress(f"{stage} eval {evaluations[0]:3d}  Cauchy cost {cost:9.1f}  "
                         + "  ".join(f"{n}={v:.4g}" for n, v in zip(stage_names, x)))
            return values

        initial_cost = float(np.sum(np.log1p(residuals(x0) ** 2)))
        x0 = _best_grid_start(x0, initial_cost, stage_names, lambda x: float(np.sum(np.log1p(residuals(x) ** 2))))
        result = least_squares(
            residuals, x0, bounds=(lower, upper), loss=loss, x_scale="jac",
            diff_step=1e-2, max_nfev=max_evaluations,
        )
        params = with_values(start, stage_names, result.x)
        messages.append(f"{stage}: {result.message}")
        costs.append((initial_cost, float(result.cost)))
    return FitResult(
        params=params,
        values={n: float(get_value(params, n)) for n in names},
        initial_cost=sum(c[0] for c in costs),
        final_cost=sum(c[1] for c in costs),
        evaluations=evaluations[0],
        message="; ".join(messages),
    )


def _best_grid_start(x0, cost0, names, cost):
    """The START_GRID combination (or x0) with the lowest cost, for the coefficients ``names``."""

    grids = [START_GRID.get(name, (value,)) for name, value in zip(names, x0)]
    best, best_cost = np.asarray(x0, dtype=float), cost0
    for candidate in itertools.product(*grids):
        candidate = np.array(candidate, dtype=float)
        if np.array_equal(candidate, best):
            continue
        candidate_cost = cost(candidate)
        if candidate_cost < best_cost:
            best, best_cost = candidate, candidate_cost
    return best


def _split(name: str) -> tuple[str, str]:
    group, _, field = name.partition(".")
    if not field or group not in {f.name for f in dataclasses.fields(BallPhysicsParams)}:
        raise InputError(f"not a coefficient name: {name!r} (expected like 'aero.drag_coefficient')")
    return group, field


def fit_and_write(data, holdout_players: Sequence[str], parameters: Sequence[str] | None = None, ball_params=None,
                  out=MODELS_DIR / "ball_physics_fitted.yaml", max_evaluations: int = 200,
                  progress: Callable[[str], None] = print) -> dict:
    """``ace-drake physics-fit``: fits ``parameters`` (default ``default_fit_parameters``), from
    the ball model of the YAML ``ball_params`` (None: the paper's), on the pairs of the match-data
    CSV ``data`` of every player but ``holdout_players``; writes ``out`` (the fitted and changed
    fields, rounded) and its sidecar (``artefacts.write_sidecar``) with the figures of the initial
    and fitted models on the fit players and the held-out ones, of the file as written. Returns
    the sidecar; raises ConfigError for a player the file does not hold or when all are held out."""
    pairs = event_pairs(load_match_events(data))
    players = sorted(set(pairs.players))
    unknown = sorted(set(holdout_players) - set(players))
    if unknown:
        raise ConfigError(f"--holdout-player {unknown}: not in {data} (players: {players})")
    held_out = np.isin(pairs.players, list(holdout_players))
    if held_out.all():
        raise ConfigError("--holdout-player: every player is held out; nothing is left to fit on")
    initial = load_ball_params(ball_params)
    names = tuple(parameters or default_fit_parameters(initial))
    fit_players = sorted(set(pairs.players[~held_out]))
    progress(f"fitting {names} on {int((~held_out).sum())} pairs ({', '.join(fit_players)}); "
             f"holding out {int(held_out.sum())} pairs ({', '.join(holdout_players)})")
    result = fit_physics(pairs.subset(~held_out), initial, names, max_evaluations=max_evaluations, progress=progress)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # Every field that was fitted or differs from the paper's defaults (a --params start), rounded.
    final, defaults = to_dict(result.params), to_dict(BallPhysicsParams())
    nested: dict[str, dict] = {}
    for group, fields in final.items():
        for field, value in fields.items():
            if f"{group}.{field}" in result.values or value != defaults[group][field]:
                nested.setdefault(group, {})[field] = round(value, 6) if isinstance(value, float) else value
    header = (
        "# Ball-model coefficients fitted to recorded match data by `ace-drake physics-fit`.\n"
        "# Fields not listed keep the paper's defaults (ace_drake/config.py); how this file was\n"
        f"# produced, and its held-out figures, are in {sidecar_path(out).name}.\n"
    )
    out.write_text(header + yaml.safe_dump(nested, sort_keys=True))
    fitted = load_ball_params(out)  # the figures are those of the file as written (rounded)
    figures = {}
    for label, mask in [("fit_players", ~held_out), ("held_out_players", held_out)]:
        subset = pairs.subset(mask)
        figures[label] = {
            "initial": summarize(subset, predict_pairs(subset, initial)),
            "fitted": summarize(subset, predict_pairs(subset, fitted)),
        }
    sidecar = write_sidecar(
        out,
        data=data_file(data, pairs=len(pairs)),
        fit_players=fit_players,
        held_out_players=sorted(holdout_players),
        initial_params=str(ball_params) if ball_params else "paper",
        fitted=result.values,
        optimizer={"evaluations": result.evaluations, "message": result.message,
                   "initial_cost": result.initial_cost, "final_cost": result.final_cost},
        figures=figures,
    )
    progress(f"wrote {out} and {sidecar_path(out)}")
    return sidecar
