"""Replay recorded events through the ball model and measure how well it predicts the next bounce.

For every (shot or bounce) -> bounce pair of a match-data file, the recorded post-event state is
propagated with the flight model (net included) to its first contact with the plane of the table's
surface. That contact is compared with the recorded bounce: landing point (x, y), time, and the
post-bounce velocity and spin that the table model (eqs (2)-(6)) gives there. The plane, not the
table's rectangle, is used so that a prediction that lands just off the table still has a landing
error instead of dropping out of the statistics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from ace_drake.config import ConfigError
from ace_drake.match_data import EventPairs, event_pairs, load_match_events
from ace_drake.physics.flight import SPIN, VELOCITY
from ace_drake.physics.params import BallPhysicsParams, load_ball_params
from ace_drake.physics.propagate import ContactKind, simulate

PREDICTION_MARGIN = 0.5  # s beyond the recorded flight time before a prediction counts as missing


@dataclasses.dataclass
class PairPredictions:
    """Per-pair predictions and errors (NaN where the ball never reached the table plane).

    landing_error (N,) m, horizontal distance; time_error (N,) s, predicted minus recorded;
    velocity_error (N,) m/s and spin_error (N,) rad/s, norms of post-bounce differences;
    predicted_contact (N, 9) and predicted_post (N, 9): the states just before and just after the
    predicted contact (after: the table model, eqs (2)-(6)).
    """

    landing_error: np.ndarray
    time_error: np.ndarray
    velocity_error: np.ndarray
    spin_error: np.ndarray
    predicted_contact: np.ndarray
    predicted_post: np.ndarray


def predict_pairs(pairs: EventPairs, params: BallPhysicsParams, dt: float = 1e-3) -> PairPredictions:
    """Propagates every pair's start state to the table plane; see the module docstring."""
    n = len(pairs)
    if n == 0:
        raise ValueError("predict_pairs: no event pairs to predict")
    horizon = float(np.max(pairs.durations)) + PREDICTION_MARGIN
    trajectory = simulate(
        pairs.start_states,
        params,
        horizon,
        dt=dt,
        kinds=(ContactKind.NET, ContactKind.TABLE_PLANE),
        stop_on=(ContactKind.TABLE_PLANE,),
        record=False,
    )
    contact_state = np.full((n, 9), np.nan)
    post_state = np.full((n, 9), np.nan)
    contact_time = np.full(n, np.nan)
    for i, event in enumerate(trajectory.stop_events):
        if event is not None and event.time <= pairs.durations[i] + PREDICTION_MARGIN:
            contact_state[i] = event.state_pre
            post_state[i] = event.state_post
            contact_time[i] = event.time
    recorded = pairs.end_states
    return PairPredictions(
        landing_error=np.linalg.norm(contact_state[:, :2] - recorded[:, :2], axis=1),
        time_error=contact_time - pairs.durations,
        velocity_error=np.linalg.norm(post_state[:, VELOCITY] - recorded[:, VELOCITY], axis=1),
        spin_error=np.linalg.norm(post_state[:, SPIN] - recorded[:, SPIN], axis=1),
        predicted_contact=contact_state,
        predicted_post=post_state,
    )


def error_figures(values) -> dict:
    """{median, p90, rms, count} of the finite errors in ``values`` (any unit; median, p90 and rms
    are None when there are none): the figures of the racket-contact and trajectory validations."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    if not values.size:
        return {"median": None, "p90": None, "rms": None, "count": 0}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)), "rms": float(np.sqrt(np.mean(values**2))),
            "count": int(values.size)}


def summarize(pairs: EventPairs, predictions: PairPredictions) -> dict:
    """Error figures overall and per transition type, as a JSON-ready dict.

    Landing error in m (median, p90, mean), absolute time error in s, post-bounce velocity error in
    m/s and spin error in rad/s (median, p90); ``missed`` counts pairs whose prediction never
    reached the table plane; ``non_finite`` counts, per error, the reached pairs left out of it
    because it is not finite (a recorded bounce without velocity or spin, NaN in the data), so
    that no figure is NaN.
    """

    def figures(mask: np.ndarray) -> dict:
        reached = mask & np.isfinite(predictions.landing_error)
        result = {"pairs": int(mask.sum()), "missed": int((mask & ~reached).sum()), "non_finite": {}}
        for name, values in [
            ("landing_error_m", predictions.landing_error),
            ("time_error_s", np.abs(predictions.time_error)),
            ("post_bounce_velocity_error_mps", predictions.velocity_error),
            ("post_bounce_spin_error_radps", predictions.spin_error),
        ]:
            selected = values[reached]
            finite = np.isfinite(selected)
            result["non_finite"][name] = int((~finite).sum())
            selected = selected[finite]
            if selected.size:
                result[name] = {
                    "median": float(np.median(selected)),
                    "p90": float(np.percentile(selected, 90)),
                    "mean": float(np.mean(selected)),
                }
        return result

    all_pairs = np.ones(len(pairs), dtype=bool)
    return {
        **figures(all_pairs),
        "by_transition": {t: figures(pairs.transitions == t) for t in sorted(set(pairs.transitions))},
    }


def format_summary(summary: dict, title: str = "") -> str:
    """A plain-text table of ``summarize``'s figures (medians and p90s), for humans."""
    lines = [title] if title else []
    header = f"{'transition':<26}{'pairs':>6}{'miss':>5}  {'landing cm':>13}  {'|dt| ms':>11}  {'dv m/s':>11}  {'dw rad/s':>13}"
    lines += [header, "-" * len(header)]

    def row(name: str, figures: dict) -> str:
        def cell(key: str, scale: float, width: int) -> str:
            if key not in figures:
                return f"{'-':>{width}}"
            text = f"{figures[key]['median'] * scale:.1f}/{figures[key]['p90'] * scale:.1f}"
            return f"{text:>{width}}"

        return (
            f"{name:<26}{figures['pairs']:>6}{figures['missed']:>5}  "
            f"{cell('landing_error_m', 100, 13)}  {cell('time_error_s', 1000, 11)}  "
            f"{cell('post_bounce_velocity_error_mps', 1, 11)}  {cell('post_bounce_spin_error_radps', 1, 13)}"
        )

    for name, figures in summary["by_transition"].items():
        lines.append(row(name, figures))
    lines.append(row("all", summary))
    lines.append("(median/p90 of each error)")
    skipped = {name: count for name, count in summary.get("non_finite", {}).items() if count}
    if skipped:
        lines.append("left out, not finite in the data: " + ", ".join(f"{count} pair(s) of {name}" for name, count in skipped.items()))
    return "\n".join(lines)


def validate_file(data, ball_params=None, players: Sequence[str] = (), progress: Callable[[str], None] = print) -> dict:
    """``ace-drake physics-validate``: the recorded (shot or bounce) -> bounce pairs of the
    match-data CSV ``data`` (of ``players`` only, if given) replayed through the ball model of the
    YAML ``ball_params`` (None: the paper's). Returns ``summarize``'s figures with ``command``,
    ``data`` and ``params``; raises ConfigError for a player the file does not hold."""
    params = load_ball_params(ball_params)
    pairs = event_pairs(load_match_events(data))
    if players:
        unknown = sorted(set(players) - set(pairs.players))
        if unknown:
            raise ConfigError(f"--player {unknown}: not in {data} (players: {sorted(set(pairs.players))})")
        pairs = pairs.subset(np.isin(pairs.players, list(players)))
    progress(f"replaying {len(pairs)} event pairs from {data} with {'the paper model' if ball_params is None else ball_params}")
    summary = summarize(pairs, predict_pairs(pairs, params))
    return {"command": "physics-validate", "data": str(data), "params": ball_params or "paper", **summary}
