"""``ace-drake physics-fit-racket`` and ``physics-validate --racket-contacts`` end to end on
synthetic contacts with planted parameters, and the fitted model selected by its YAML in the
BallPlants (analysis/racket_fit.py)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from ace_drake import cli
from ace_drake.config import ConfigError
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import add_ball, build_segment_rally_diagram
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import RacketParams, load_ball_params
from ace_drake.physics.racket_contacts import write_racket_contacts
from ace_drake.physics.racket_residual import residual_model
from test_racket_contacts import synthetic_contacts

PLANTED = dict(tangential_k=0.6, restitution_law="linear", restitution_a=0.93, restitution_b=-0.024)


@pytest.fixture(scope="module")
def contacts_file(tmp_path_factory):
    contacts = synthetic_contacts(dataclasses.replace(RacketParams(), **PLANTED), count=300, games=10, velocity_noise=0.05,
                                  spin_noise=5.0, seed=3)
    return write_racket_contacts(tmp_path_factory.mktemp("contacts") / "contacts.csv", contacts)


@pytest.fixture(scope="module")
def fitted(contacts_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit")
    code = cli.main(["physics-fit-racket", "--data", str(contacts_file), "--holdout-fraction", "0.3", "--epochs", "60",
                     "--out", str(out / "racket.yaml"), "--residual-out", str(out / "residual.pt"), "--json"])
    assert code == 0
    return out


def test_the_fit_writes_the_model_the_network_and_their_sidecars(fitted):
    sidecar = json.loads((fitted / "racket.json").read_text())
    assert sidecar["law"] == "linear" and sidecar["artefact_sha256"]
    assert sidecar["fits"]["linear"]["parameters"]["tangential_k"] == pytest.approx(0.6, abs=0.02)
    assert sidecar["fits"]["linear"]["parameters"]["restitution_a"] == pytest.approx(0.93, abs=0.02)
    held_out = sidecar["figures"]["held_out"]
    assert held_out["fitted_linear"]["velocity_error_m_s"]["median"] < 0.5 * held_out["default"]["velocity_error_m_s"]["median"]
    assert set(held_out) == {"default", "fitted_exponential", "fitted_linear", "fitted_residual"}
    assert not set(sidecar["split"]["held_out_games"]) & set(sidecar["split"].get("training_games", []))
    assert json.loads((fitted / "residual.json").read_text())["racket_params"] == "racket.yaml"
    physics = load_ball_params(fitted / "racket.yaml")
    assert physics.racket.restitution_law == "linear" and physics.racket.residual == str((fitted / "residual.pt").resolve())
    assert residual_model(physics.racket) is not None


def test_validate_reports_the_issues_keys_for_any_contact_file(fitted, contacts_file, capsys):
    capsys.readouterr()
    assert cli.main(["physics-validate", "--racket-contacts", str(contacts_file), "--json"]) == 0
    default = json.loads(capsys.readouterr().out)
    assert cli.main(["physics-validate", "--racket-contacts", str(contacts_file), "--params", str(fitted / "racket.yaml"), "--json"]) == 0
    fitted_figures = json.loads(capsys.readouterr().out)
    for figures in (default, fitted_figures):
        for key in ("velocity_error_m_s", "spin_error_rad_s"):
            assert set(figures["racket"][key]) >= {"median", "p90"}
    assert fitted_figures["racket"]["velocity_error_m_s"]["median"] < 0.5 * default["racket"]["velocity_error_m_s"]["median"]
    assert fitted_figures["racket_model"] == "racket.yaml + residual" and default["residual"] is None


def test_the_yaml_selects_the_residual_in_both_ball_plants(fitted):
    physics = load_ball_params(fitted / "racket.yaml")
    plant = add_ball(DiagramBuilder(), physics)
    assert plant._residual is residual_model(physics.racket)
    plain = add_ball(DiagramBuilder(), load_ball_params(None))
    assert plain._residual is None
    params = RallyParams(physics=physics, perception=PerceptionParams(positions="statistical"), stepping="segment")
    segment = build_segment_rally_diagram(params, None, 2).GetSubsystemByName("ball")
    assert segment.residual is residual_model(physics.racket)


def test_a_missing_residual_file_is_a_config_error_naming_it(tmp_path):
    racket = dataclasses.replace(RacketParams(), residual=str(tmp_path / "absent.pt"))
    with pytest.raises(ConfigError, match="absent.pt"):
        residual_model(racket)


def test_bad_arguments_exit_2_with_a_message(contacts_file, capsys, tmp_path):
    assert cli.main(["physics-validate"]) == 2
    assert "give --data, --racket-contacts or --trajectories" in capsys.readouterr().err
    assert cli.main(["physics-fit-racket", "--data", str(contacts_file), "--holdout-fraction", "0.2", "--holdout-games", "game_1"]) == 2
    assert "not both" in capsys.readouterr().err
    assert cli.main(["physics-validate", "--racket-contacts", str(tmp_path / "absent.csv")]) == 2
    assert "absent.csv" in capsys.readouterr().err
    assert cli.main(["physics-fit-racket", "--data", str(contacts_file), "--holdout-games", "session_5/game_99"]) == 2
    assert "no game" in capsys.readouterr().err


def test_the_residual_lowers_a_planted_distortion_on_held_out_games(tmp_path):
    """Contacts whose normal restitution the linear law cannot follow (a bump at 4-6 m/s): the
    network, trained on the other games, takes part of it off the held-out ones."""
    from ace_drake.analysis.racket_fit import fit_racket_and_write

    contacts = synthetic_contacts(RacketParams(), count=600, games=12, seed=7)
    normal_speed = -np.einsum("nij,nj->ni", np.swapaxes(contacts.R_WC, 1, 2), contacts.v_pre - contacts.v_contact_point)[:, 2]
    bump = 0.8 * np.exp(-((normal_speed - 5.0) ** 2))  # m/s along the normal
    contacts = dataclasses.replace(contacts, v_post=contacts.v_post + bump[:, None] * contacts.R_WC[:, :, 2])
    path = write_racket_contacts(tmp_path / "bumped.csv", contacts)
    sidecar = fit_racket_and_write(path, 0.25, seed=1, out=tmp_path / "r.yaml", residual_out=tmp_path / "r.pt", epochs=300,
                                   progress=lambda _: None)
    held_out = sidecar["figures"]["held_out"]
    kept = held_out[f"fitted_{sidecar['law']}"]["velocity_error_m_s"]["rms"]
    assert held_out["fitted_residual"]["velocity_error_m_s"]["rms"] < 0.9 * kept
