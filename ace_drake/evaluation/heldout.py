"""The held-out evaluations that choose the main job's controller.

``ace-drake rally`` plays "the best shipped controller" (DESIGN): of the controllers a checkout can
build, the one that returned the highest share of the held-out players' playable recorded shots,
measured the same way for all (``docs/results/heldout/``: one ``ace-drake evaluate --controller
NAME --data ../shared/data/ace_match_events_elite.csv --players "Elite D,Elite E" --json`` per
controller). The returner keeps the place unless another controller's rate is strictly higher.
Plain Python: ``analysis.results`` reads the same files for the README without loading Drake.
"""

from __future__ import annotations

import json
from pathlib import Path

from ace_drake.config import RESULTS_DIR, ConfigError
from ace_drake.contracts import DEFAULT_CONTROLLER

HELDOUT_DIR = RESULTS_DIR / "heldout"
# What must agree between two held-out evaluations for their rates to be compared.
HELDOUT_CONDITIONS = ("data_sha256", "players", "sensors", "seed", "repeats", "skills", "ball_params", "action_noise")
# The value of a condition in a file stored before the condition was recorded: one play per shot.
CONDITION_DEFAULTS = {"repeats": 1}


def heldout_evaluations(directory: Path | None = None) -> dict[str, dict]:
    """The stored held-out evaluations by controller name: every ``*.json`` in ``directory``
    (default ``HELDOUT_DIR``; none if it does not exist). Raises ConfigError if a file is not an
    ``evaluate --json`` output, if two were measured under different conditions
    (``HELDOUT_CONDITIONS``) or if two name the same controller."""

    directory = HELDOUT_DIR if directory is None else Path(directory)
    evaluations: dict[str, dict] = {}
    reference = None
    for path in sorted(directory.glob("*.json")) if directory.is_dir() else []:
        evaluation = json.loads(path.read_text())
        name = evaluation.get("controller")
        if not name or "return_rate" not in evaluation:
            raise ConfigError(f"{path}: not an 'ace-drake evaluate --json' output (no controller or return_rate)")
        if name in evaluations:
            raise ConfigError(f"{path}: a second held-out evaluation of {name}")
        conditions = {key: evaluation.get(key, CONDITION_DEFAULTS.get(key)) for key in HELDOUT_CONDITIONS}
        if reference is None:
            reference = (path, conditions)
        elif conditions != reference[1]:
            differ = [key for key in HELDOUT_CONDITIONS if conditions[key] != reference[1][key]]
            raise ConfigError(f"{path} was measured under other conditions than {reference[0].name} ({', '.join(differ)}): "
                              "measure every controller the same way")
        evaluations[name] = evaluation
    return evaluations


def choose_controller(evaluations: dict[str, dict], available) -> tuple[str, float | None]:
    """(the controller to play, its held-out rate) among ``evaluations`` (``heldout_evaluations``)
    of the controllers in ``available`` (names a checkout can build): the highest rate; the
    returner (``DEFAULT_CONTROLLER``) on a tie, and with rate None while it is not measured itself
    (nothing to beat)."""

    available = set(available)
    rates = {name: evaluation["return_rate"]["rate"] for name, evaluation in evaluations.items()
             if name in available and evaluation["return_rate"]["rate"] is not None}
    if DEFAULT_CONTROLLER not in rates:
        return DEFAULT_CONTROLLER, None
    best = max(sorted(rates), key=lambda name: (rates[name], name == DEFAULT_CONTROLLER))
    return best, rates[best]
