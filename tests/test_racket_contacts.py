"""Measured racket contacts: loading and its refusals, the split by game, the racket model's fit
on synthetic contacts with planted parameters (physics/racket_contacts.py)."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ace_drake.config import InputError
from ace_drake.physics.contact import racket_impact
from ace_drake.physics.params import BallPhysicsParams, RacketParams
from ace_drake.physics.racket_contacts import (
    RacketContacts,
    RacketContactsError,
    contact_errors,
    fit_racket_model,
    game_keys,
    load_racket_contacts,
    predict_post_contact,
    split_by_game,
    write_racket_contacts,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "sony_racket_contacts.csv"
RADIUS = BallPhysicsParams().aero.ball_radius


def synthetic_contacts(racket: RacketParams, count: int = 240, games: int = 8, seed: int = 0, velocity_noise: float = 0.0,
                       spin_noise: float = 0.0) -> RacketContacts:
    """Contacts like the measured ones (incoming ~4 m/s, racket ~5 m/s into the ball, spins of a
    few hundred rad/s) whose post-contact states are ``racket``'s model plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    R_WR = Rotation.random(count, random_state=seed).as_matrix()
    normal = R_WR[:, :, 0]  # the racket frame's x axis is the blade normal on the ball's side
    v_pre = -4.0 * normal + rng.normal(0.0, 1.5, (count, 3))
    w_pre = rng.normal(0.0, 150.0, (count, 3))
    v_racket = 5.0 * normal + rng.normal(0.0, 1.0, (count, 3))
    w_racket = rng.normal(0.0, 3.0, (count, 3))
    offset = np.einsum("nij,nj->ni", R_WR, np.c_[np.zeros(count), rng.uniform(-0.04, 0.04, (count, 2))])
    p = rng.normal([-1.8, 0.0, 0.25], 0.2, (count, 3))
    shots = np.array([f"/game_{i * games // count}/rally_{i}/shot_1" for i in range(count)], dtype=object)
    contacts = RacketContacts(p=p, v_pre=v_pre, w_pre=w_pre, v_post=np.zeros((count, 3)), w_post=np.zeros((count, 3)), v_racket=v_racket,
                              w_racket=w_racket, offset=offset, R_WR=R_WR, shot_ids=shots,
                              games=game_keys(["20250101"] * count, [i * games // count for i in range(count)]),
                              serve=np.zeros(count, bool), spin_confidence=np.full((count, 2), np.nan), rows=np.arange(1, count + 1))
    v_post, w_post = predict_post_contact(contacts, racket, RADIUS)
    return dataclasses.replace(contacts, v_post=v_post + rng.normal(0.0, velocity_noise, (count, 3)),
                               w_post=w_post + rng.normal(0.0, spin_noise, (count, 3)))


def test_write_then_load_round_trip(tmp_path):
    contacts = synthetic_contacts(RacketParams(), count=20, games=3)
    loaded = load_racket_contacts(write_racket_contacts(tmp_path / "contacts.csv", contacts))
    for name in ("p", "v_pre", "w_pre", "v_post", "w_post", "v_racket", "w_racket", "offset", "R_WR"):
        np.testing.assert_allclose(getattr(loaded, name), getattr(contacts, name), atol=1e-12, err_msg=name)
    assert list(loaded.games) == list(contacts.games) and loaded.skipped == {}


def test_the_model_frame_matches_the_files_relations():
    """The racket frame's x axis is the blade normal on the ball's side: in C its z."""
    contacts = synthetic_contacts(RacketParams(), count=10)
    np.testing.assert_allclose(contacts.R_WC[:, :, 2], contacts.R_WR[:, :, 0])
    np.testing.assert_allclose(np.linalg.det(contacts.R_WC), 1.0)


def test_game_keys_restart_sessions_where_game_numbers_fall():
    keys = game_keys(["d1"] * 5 + ["d2"], [0, 0, 1, 0, 2, 0])
    assert list(keys) == ["d1/session_0/game_0", "d1/session_0/game_0", "d1/session_0/game_1", "d1/session_1/game_0",
                          "d1/session_1/game_2", "d2/session_0/game_0"]


def test_split_by_game_holds_out_whole_games():
    contacts = synthetic_contacts(RacketParams(), count=200, games=10)
    held, games = split_by_game(contacts, holdout_fraction=0.3, seed=4)
    assert len(games) == 3
    assert not set(contacts.games[held]) & set(contacts.games[~held])
    named, chosen = split_by_game(contacts, holdout_games=["session_0/game_2"])
    assert chosen == ["20250101/session_0/game_2"] and set(contacts.games[named]) == {"20250101/session_0/game_2"}
    with pytest.raises(InputError, match="no game"):
        split_by_game(contacts, holdout_games=["session_9/game_9"])
    with pytest.raises(InputError, match="holdout-fraction"):
        split_by_game(contacts, holdout_fraction=1.5)


@pytest.mark.parametrize("law, planted", [
    ("exponential", dict(tangential_k=0.62, restitution_gamma1=0.95, restitution_gamma2=-0.03)),
    ("linear", dict(tangential_k=0.75, restitution_a=0.91, restitution_b=-0.025)),
])
def test_fit_recovers_planted_parameters(law, planted):
    truth = dataclasses.replace(RacketParams(), restitution_law=law, **planted)
    exact = fit_racket_model(synthetic_contacts(truth), law)
    for name, value in planted.items():
        assert exact.parameters[name] == pytest.approx(value, abs=1e-6), name
    noisy = fit_racket_model(synthetic_contacts(truth, count=500, velocity_noise=0.1, spin_noise=10.0, seed=1), law)
    for name, value in planted.items():
        assert noisy.parameters[name] == pytest.approx(value, abs=0.02), name


def test_fitted_model_beats_the_default_on_held_out_games():
    truth = dataclasses.replace(RacketParams(), tangential_k=0.55, restitution_gamma1=0.97, restitution_gamma2=-0.03)
    contacts = synthetic_contacts(truth, count=400, games=10, velocity_noise=0.05, seed=2)
    held, _ = split_by_game(contacts, holdout_fraction=0.3, seed=0)
    fit = fit_racket_model(contacts.subset(~held), "exponential")
    test = contacts.subset(held)
    default = contact_errors(test, *predict_post_contact(test, RacketParams(), RADIUS))
    fitted = contact_errors(test, *predict_post_contact(test, fit.racket, RADIUS))
    assert np.median(fitted[0]) < 0.5 * np.median(default[0])
    assert np.median(fitted[1]) < 0.5 * np.median(default[1])


def _rewrite(path: Path, row: int, field: str, value: str) -> Path:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(field)] = value
    lines[row] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return path


def test_bad_files_are_named_with_row_and_field(tmp_path):
    with pytest.raises(RacketContactsError, match="no such file"):
        load_racket_contacts(tmp_path / "absent.csv")
    other = tmp_path / "other.csv"
    other.write_text("player_id,rally_id,type\nElite A,/game_1/rally_1/event1,shot_p2\n")
    with pytest.raises(RacketContactsError, match=r"other.csv: not a racket-contacts file.*missing column"):
        load_racket_contacts(other)
    contacts = synthetic_contacts(RacketParams(), count=6, games=2)
    skewed = _rewrite(write_racket_contacts(tmp_path / "quaternion.csv", contacts), 3, "Orientation_W", "3.0")
    with pytest.raises(RacketContactsError, match=r"quaternion.csv: row 3, fields Orientation_X/.*not a unit quaternion"):
        load_racket_contacts(skewed)
    shot = _rewrite(write_racket_contacts(tmp_path / "shot.csv", contacts), 2, "shot_ID", "rally 7")
    with pytest.raises(RacketContactsError, match="row 2, field shot_ID"):
        load_racket_contacts(shot)


def test_rows_with_missing_or_non_finite_values_are_skipped_and_counted(tmp_path):
    contacts = synthetic_contacts(RacketParams(), count=6, games=2)
    path = _rewrite(write_racket_contacts(tmp_path / "gaps.csv", contacts), 2, "Global_Ball_Vel_Pre_Y", "nan")
    path = _rewrite(path, 5, "Global_Ball_Vel_Pre_Y", "")
    path = _rewrite(path, 4, "Global_Racket_Spin_Z", "inf")
    loaded = load_racket_contacts(path)
    assert len(loaded) == 3 and list(loaded.rows) == [1, 3, 6]
    assert loaded.skipped == {"missing or non-finite Global_Ball_Vel_Pre_Y": 2, "missing or non-finite Global_Racket_Spin_Z": 1}


@pytest.mark.skipif(not DATA.is_file(), reason="needs ../shared/data/sony_racket_contacts.csv (not part of the repository)")
def test_the_measured_contacts_load_and_the_paper_model_misses_them_as_filed():
    contacts = load_racket_contacts(DATA)
    assert len(contacts) == 572 and contacts.skipped == {}
    assert np.all(np.einsum("nij,nj->ni", np.swapaxes(contacts.R_WC, 1, 2), contacts.v_pre - contacts.v_contact_point)[:, 2] < 0.0)
    # The file's racket-frame columns: Before_Vel = R^T (v_pre - v_r - w_r x d), Before_Dist = R^T d.
    with DATA.open(newline="") as handle:
        table = list(csv.DictReader(handle))
    before_velocity = np.array([[float(row[f"Before_Vel_{axis}"]) for axis in "XYZ"] for row in table])
    before_offset = np.array([[float(row[f"Before_Dist_{axis}"]) for axis in "XYZ"] for row in table])
    R_RW = np.swapaxes(contacts.R_WR, 1, 2)
    relative = contacts.v_pre - contacts.v_racket - np.cross(contacts.w_racket, contacts.offset)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R_RW, relative), before_velocity, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R_RW, contacts.offset), before_offset, atol=1e-9)
    velocity, spin = contact_errors(contacts, *predict_post_contact(contacts, RacketParams(), RADIUS))
    # The issue measured 0.51 m/s and 23 rad/s with the ball's centre for the contact point; on the
    # blade's surface point, as the BallPlant takes it, the paper's model misses by a little less.
    assert np.median(velocity) == pytest.approx(0.476, abs=0.005)
    assert np.median(spin) == pytest.approx(22.8, abs=0.3)
