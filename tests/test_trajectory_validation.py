"""Trajectory validation on synthetic flights whose spin and initial state are known."""

import dataclasses

import numpy as np
import pytest

from ace_drake.analysis.trajectory_validation import (
    COLUMNS,
    TrajectoryFileError,
    fit_initial_state,
    format_trajectory_figures,
    generate_trajectories,
    load_trajectories,
    measured_bounce_index,
    propagate_and_compare,
    validate_trajectories,
    write_trajectories_csv,
)
from ace_drake.physics.params import BallPhysicsParams

PHYSICS = BallPhysicsParams()
HEADER = ",".join(COLUMNS) + "\n"


@pytest.fixture(scope="module")
def noise_free():
    return generate_trajectories(3, seed=3, noise_std=0.0)


def test_noise_free_fit_recovers_the_initial_state_and_the_flight(noise_free):
    trajectories, true_states = noise_free
    assert [t.name.rsplit("_", 1)[1] for t in trajectories] == ["topspin", "backspin", "sidespin"]
    for dut, truth in zip(trajectories, true_states):
        state0, info = fit_initial_state(dut, PHYSICS)
        assert info["samples"] == 11 and info["contact_in_window"] is None  # 0 to 50 ms at 200 Hz
        np.testing.assert_allclose(state0[:3], truth[:3], atol=1e-4)
        np.testing.assert_allclose(state0[3:6], truth[3:6], atol=1e-3)
        np.testing.assert_array_equal(state0[6:], truth[6:])
        errors = propagate_and_compare(dut, state0, PHYSICS)
        assert errors.bounce_index == measured_bounce_index(dut, PHYSICS)
        assert errors.pre_bounce.sum() == errors.bounce_index and errors.post_bounce.sum() > 20
        assert errors.errors.max() < 1e-6  # through the bounce, at sample times off the 1 ms steps


def test_gross_outliers_in_the_fit_window_do_not_spoil_the_fit(noise_free):
    trajectories, true_states = noise_free
    dut = trajectories[0]
    positions = dut.positions + np.random.default_rng(0).normal(0.0, 0.001, dut.positions.shape)
    positions[[2, 5, 8], 2] += 0.3
    positions[4, 0] -= 0.3
    state0, _ = fit_initial_state(dataclasses.replace(dut, positions=positions), PHYSICS)
    np.testing.assert_allclose(state0[:3], true_states[0, :3], atol=0.003)
    np.testing.assert_allclose(state0[3:6], true_states[0, 3:6], atol=0.05)


def test_measured_spin_explains_the_flights_and_zero_spin_does_not(tmp_path):
    trajectories, _ = generate_trajectories(12, seed=1, noise_std=0.001)
    path = tmp_path / "trajectories.csv"
    write_trajectories_csv(path, trajectories)
    progress = []
    result = validate_trajectories(path, progress=progress.append)["trajectories"]
    assert len(progress) == 2 and result["count"] == result["fitted"] == 12 and result["skipped"] == {}
    assert result["model"] == "default"
    default, zero_spin = result["models"]["default"], result["models"]["zero_spin"]
    assert result["pre_bounce_error_m"] == default["pre_bounce_error_m"]
    assert default["pre_bounce_error_m"]["count"] == 12
    assert default["pre_bounce_error_m"]["median"] < 0.02
    assert default["pre_bounce_all_samples_error_m"]["median"] < 0.008
    assert default["post_bounce_error_m"]["median"] < 0.03
    assert zero_spin["pre_bounce_error_m"]["median"] > 5 * default["pre_bounce_error_m"]["median"]
    assert zero_spin["post_bounce_error_m"]["median"] > 5 * default["post_bounce_error_m"]["median"]
    table = format_trajectory_figures(result)
    assert "zero_spin" in table and "default" in table


def test_file_round_trip_and_short_trajectories_are_skipped(tmp_path, noise_free):
    trajectories, _ = noise_free
    short = dataclasses.replace(trajectories[0], name="short", times=trajectories[0].times[:4],
                                positions=trajectories[0].positions[:4], lines=trajectories[0].lines[:4])
    path = tmp_path / "trajectories.csv"
    write_trajectories_csv(path, [*trajectories, short])
    loaded = load_trajectories(path)
    assert [t.name for t in loaded] == [t.name for t in trajectories] + ["short"]
    np.testing.assert_array_equal(loaded[1].positions, trajectories[1].positions)
    np.testing.assert_array_equal(loaded[1].times, trajectories[1].times)
    assert loaded[0].lines[0] == 2
    result = validate_trajectories(path, models={"paper": PHYSICS}, progress=lambda _: None)["trajectories"]
    assert result["count"] == 4 and result["fitted"] == 3
    assert list(result["skipped"].values()) == [1] and "fewer than 5 samples" in next(iter(result["skipped"]))
    assert result["pre_bounce_error_m"]["median"] < 1e-6


def write(tmp_path, body, header=HEADER):
    path = tmp_path / "bad.csv"
    path.write_text(header + body)
    return path


ROW = "a,{t},1.5,0.0,0.3,0,-100,0\n"


def test_bad_files_are_errors_that_name_file_line_and_field(tmp_path):
    with pytest.raises(TrajectoryFileError, match="not found"):
        load_trajectories(tmp_path / "absent.csv")
    path = write(tmp_path, "P,/game_0/rally_0/event1,shot_p2,1.0\n", header="player_id,rally_id,type,timestamp\n")
    with pytest.raises(TrajectoryFileError, match=f"{path}: not a trajectory file"):
        load_trajectories(path)
    path = write(tmp_path, ROW.format(t=0.0) + "a,0.005,1.5,0.0,nan,0,-100,0\n")
    with pytest.raises(TrajectoryFileError, match=r"bad.csv, line 3, field z: expected a finite number"):
        load_trajectories(path)
    path = write(tmp_path, ROW.format(t=0.0) + "a,0.005,1.5,zero,0.3,0,-100,0\n")
    with pytest.raises(TrajectoryFileError, match="line 3, field y: expected a number"):
        load_trajectories(path)
    path = write(tmp_path, ROW.format(t=0.0) + "b,0.0,1.5,0.0,0.3,0,0,0\n" + "a,0.005,1.5,0.0,0.3,0,-90,0\n")
    with pytest.raises(TrajectoryFileError, match=r"line 4, field wy: the spin of trajectory 'a' changes"):
        load_trajectories(path)
    path = write(tmp_path, ROW.format(t=0.01) + ROW.format(t=0.01))
    with pytest.raises(TrajectoryFileError, match="line 3, field t: .* not after"):
        load_trajectories(path)
    path = write(tmp_path, ROW.format(t=0.0) + "a,0.005,1.5\n")
    with pytest.raises(TrajectoryFileError, match="line 3: 3 fields; expected 8"):
        load_trajectories(path)
    with pytest.raises(TrajectoryFileError, match="no samples"):
        load_trajectories(write(tmp_path, ""))


def test_the_command_reports_every_model_side_by_side_with_the_issues_keys(tmp_path, capsys):
    import json

    from ace_drake import cli

    trajectories, _ = generate_trajectories(6, seed=3, noise_std=0.001)
    path = tmp_path / "trajectories.csv"
    write_trajectories_csv(path, trajectories)
    assert cli.main(["physics-validate", "--trajectories", str(path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)["trajectories"]
    assert result["model"] == "paper" and result["count"] == 6
    assert set(result["models"]) >= {"paper", "paper, authors' aerodynamics", "zero spin"}
    assert result["pre_bounce_error_m"]["median"] < 0.02 and result["pre_bounce_error_m"]["p90"] is not None
    assert result["models"]["zero spin"]["pre_bounce_error_m"]["median"] > 5 * result["pre_bounce_error_m"]["median"]
    assert cli.main(["physics-validate", "--trajectories", str(path)]) == 0
    assert "zero spin" in capsys.readouterr().out
