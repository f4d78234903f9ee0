"""``ace-drake physics-fit-racket`` and ``physics-validate --racket-contacts``: the racket contact
model (paper eqs (7)-(8)) identified on measured contacts and judged on contacts the fit did not
see (``physics.racket_contacts``).

The fit splits the contacts by game (whole games held out), identifies k and each restitution
law's coefficients on the training games (``fit_racket_model``), keeps the law with the lower
training cost, trains the residual network (``physics.racket_residual``, the paper's small MLP)
on that model's errors on the training games, and reports on the held-out games, for the paper's
defaults, each fitted law and the kept law with the residual: the post-contact velocity error
(m/s), the spin error (rad/s) and the landing error of the returned ball (m: the predicted and the
measured post-contact states flown through the ball model, eq. (1), from the contact to their
first table or floor contact).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import yaml

from ace_drake.analysis.physics_validation import error_figures
from ace_drake.artefacts import data_file, sidecar_path, write_sidecar
from ace_drake.config import MODELS_DIR, InputError, to_dict
from ace_drake.physics.params import BallPhysicsParams, load_ball_params
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.physics.racket_contacts import (
    LAW_PARAMETERS,
    RacketContacts,
    contact_errors,
    fit_racket_model,
    load_racket_contacts,
    predict_post_contact,
    split_by_game,
)
from ace_drake.physics.racket_residual import fit_racket_residual, load_residual, residual_model, residual_path, save_residual

DEFAULT_RACKET_PARAMS = MODELS_DIR / "racket_fitted.yaml"
DEFAULT_RESIDUAL = MODELS_DIR / "racket_residual.pt"
LANDING_HORIZON = 3.0  # s of flight within which a returned ball lands


def landing_points(contacts: RacketContacts, v_post: np.ndarray, w_post: np.ndarray, physics: BallPhysicsParams) -> np.ndarray:
    """Where each ball leaving the contact point with (v_post, w_post) first meets the table or
    the floor (N, 3), m; NaN where it does neither within LANDING_HORIZON."""
    states = np.concatenate([contacts.p, v_post, w_post], axis=1)
    flight = simulate(states, physics, LANDING_HORIZON, kinds=(ContactKind.TABLE, ContactKind.FLOOR),
                      stop_on=(ContactKind.TABLE, ContactKind.FLOOR), record=False)
    return np.array([event.state_pre[:3] if event is not None else np.full(3, np.nan) for event in flight.stop_events])


def racket_figures(contacts: RacketContacts, physics: BallPhysicsParams, residual: Callable | None = None) -> dict:
    """The model ``physics.racket`` (with ``residual``) on ``contacts``: velocity_error_m_s,
    spin_error_rad_s and landing_error_m, each {median, p90, rms, count}."""
    v_post, w_post = predict_post_contact(contacts, physics.racket, physics.aero.ball_radius, residual)
    velocity, spin = contact_errors(contacts, v_post, w_post)
    landing = np.linalg.norm(landing_points(contacts, v_post, w_post, physics) - landing_points(contacts, contacts.v_post, contacts.w_post, physics), axis=1)
    return {"velocity_error_m_s": error_figures(velocity), "spin_error_rad_s": error_figures(spin), "landing_error_m": error_figures(landing)}


def _residual_arrays(contacts: RacketContacts) -> dict:
    """fit_racket_residual's inputs for ``contacts``."""
    pre = np.concatenate([contacts.p, contacts.v_pre, contacts.w_pre], axis=1)
    post = np.concatenate([contacts.p, contacts.v_post, contacts.w_post], axis=1)
    return dict(pre_states=pre, racket_velocities=contacts.v_contact_point, R_WC=contacts.R_WC, post_states=post,
                contact_offsets=contacts.contact_offsets)


def fit_racket_and_write(data, holdout_fraction: float | None = None, holdout_games: Sequence[str] = (), seed: int = 0,
                         params_file=None, out=DEFAULT_RACKET_PARAMS, residual_out=DEFAULT_RESIDUAL, epochs: int = 500,
                         progress: Callable[[str], None] = print) -> dict:
    """The fit of the module docstring on the contacts of ``data``, written to ``out`` (a ball
    parameter YAML with the fitted ``racket`` section; its sidecar beside it) and ``residual_out``
    (the network, with its sidecar). ``params_file``: the starting ball model (default the
    paper's). Returns the racket sidecar's content."""
    contacts = load_racket_contacts(data)
    physics = load_ball_params(params_file)
    held, games = split_by_game(contacts, holdout_fraction, holdout_games, seed)
    train, test = contacts.subset(~held), contacts.subset(held)
    progress(f"physics-fit-racket: {len(train)} contacts of {len(set(train.games))} games to fit, "
             f"{len(test)} of {len(games)} held out ({', '.join(games)})")
    fits = {}
    for law in LAW_PARAMETERS:
        fits[law] = fit_racket_model(train, law, physics)
        progress(f"  {law} law: {fits[law].parameters}, cost {fits[law].cost:.4g}")
    kept = min(fits.values(), key=lambda fit: fit.cost)
    fitted = dataclasses.replace(physics, racket=kept.racket)
    progress(f"  training the residual network on the {kept.law} model's errors ({epochs} epochs at most)")
    # Early stopping on whole games of the training part: on a random split of contacts it keeps
    # training on noise that correlated contacts share (held-out spin RMS 5% worse, not better).
    network, report = fit_racket_residual(**_residual_arrays(train), params=fitted, seed=seed, epochs=epochs, groups=train.games)
    residual = network.as_numpy()
    figures = {"held_out": {}, "training": {}}
    for name, model, correction in (("default", physics, None), *((f"fitted_{law}", dataclasses.replace(physics, racket=fit.racket), None)
                                                                  for law, fit in fits.items()), ("fitted_residual", fitted, residual)):
        for part, subset in (("held_out", test), ("training", train)):
            figures[part][name] = racket_figures(subset, model, correction)
    out, residual_out = Path(out), Path(residual_out)
    for path in (out, residual_out):
        if path.suffix == ".json":
            raise InputError(f"physics-fit-racket: {path} ends in .json, the name of its sidecar")
    command = (f"ace-drake physics-fit-racket --data {data}" + (f" --holdout-games {','.join(holdout_games)}" if holdout_games else
                                                                 f" --holdout-fraction {0.2 if holdout_fraction is None else holdout_fraction}")
               + f" --seed {seed} --epochs {epochs}" + (f" --params {params_file}" if params_file else ""))
    out.parent.mkdir(parents=True, exist_ok=True)
    header = ("# The racket contact model (paper eqs (7)-(8)) identified on measured contacts by `ace-drake physics-fit-racket`,\n"
              "# with the residual network trained on the same contacts (set `residual: ''` for the fitted law alone).\n"
              f"# Fields not listed keep the paper's values; the fit, its split and held-out figures are in {sidecar_path(out).name}.\n")
    section = {key: value for key, value in to_dict(kept.racket).items() if key in ("tangential_k", "restitution_law", *kept.parameters)}
    # The residual by name when it sits in models/ (the file moves with the repository), else by path.
    section["residual"] = residual_out.name if residual_out.resolve().parent == MODELS_DIR.resolve() else str(residual_out.resolve())
    out.write_text(header + yaml.safe_dump({"racket": section}, sort_keys=True))
    split = {"held_out_games": games, "training_games": sorted(set(train.games.tolist())), "training_contacts": len(train),
             "held_out_contacts": len(test), "skipped_rows": contacts.skipped}
    save_residual(network, residual_out, {"command": command, "seed": seed, "data": data_file(data), "racket_params": out.name,
                                          "split": split, "report": report.as_dict()})
    return write_sidecar(out, command=command, seed=seed, data=data_file(data), figures=figures, split=split, law=kept.law,
                         fits={law: {"parameters": fit.parameters, "cost": fit.cost, "success": fit.success} for law, fit in fits.items()},
                         residual=residual_out.name, starting_params=str(params_file) if params_file else "paper defaults")


def validate_racket(data, params_file=None, residual_file=None) -> dict:
    """``physics-validate --racket-contacts``: the racket model of ``params_file`` (default the
    paper's) with the residual network of ``residual_file`` (default: the one the params name,
    ``racket.residual``, if any) on every usable contact of ``data``. Keys: contacts,
    skipped_rows {reason: count}, racket_model (a label), residual (its file or None), racket
    (``racket_figures``)."""
    contacts = load_racket_contacts(data)
    physics = load_ball_params(params_file)
    if residual_file is not None:
        residual, residual_name = load_residual(residual_file).as_numpy(), str(residual_file)
    else:
        residual, path = residual_model(physics.racket), residual_path(physics.racket)
        residual_name = None if path is None else str(path)
    label = (Path(params_file).name if params_file else "paper") + (" + residual" if residual is not None else "")
    return {"contacts": len(contacts), "skipped_rows": contacts.skipped, "racket_model": label, "residual": residual_name,
            "racket": racket_figures(contacts, physics, residual)}


def format_racket_figures(figures: dict, title: str) -> str:
    """A text table of ``racket_figures`` results {model: figures}."""
    lines = [title, f"{'model':<26} {'velocity error m/s':>28} {'spin error rad/s':>28} {'landing error m':>28}",
             f"{'':<26} {'median / p90 / rms':>28} {'median / p90 / rms':>28} {'median / p90 / rms':>28}"]
    for name, row in figures.items():
        cells = [f"{row[key]['median']:.3f} / {row[key]['p90']:.3f} / {row[key]['rms']:.3f}" if row[key]["median"] is not None else "-"
                 for key in ("velocity_error_m_s", "spin_error_rad_s", "landing_error_m")]
        lines.append(f"{name:<26} {cells[0]:>28} {cells[1]:>28} {cells[2]:>28}")
    return "\n".join(lines)
