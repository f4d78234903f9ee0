"""Tests for analysis.results: the headline table is rendered from its files, and the README shows it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from ace_drake import cli
from ace_drake.analysis import results

REPO_ROOT = Path(__file__).resolve().parent.parent


def small_sidecar() -> dict:
    """A policy sidecar with only the keys the table reads (the shape ``ace-drake train`` writes)."""
    return {
        "name": "rally_paper_mc",
        "command": "ace-drake train models/train_rally_paper_mc.yaml",
        "date": "2026-01-02",
        "seed": 3,
        "final_evaluation": {
            "data": "../data/matches.csv",
            "sensors": "cameras",
            "episodes": 10,
            "return_rate": {"returned": 3, "played": 4, "rate": 0.75, "ci95": [0.30064, 0.95443]},
            "held_out": {"players": ["Elite D"], "return_rate": {"returned": 1, "played": 2, "rate": 0.5, "ci95": [0.0945, 0.9055]}},
        },
    }


def write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload))


def test_policy_row_from_a_constructed_sidecar(tmp_path):
    write_json(tmp_path / "models/policies/rally_paper_mc.json", small_sidecar())
    rows = {row.what: row for row in results.result_rows(tmp_path)}
    row = rows["`policy:rally_paper_mc`: the paper's action (eq. 12), SAC at scale"]
    assert row.figure == ("75.0% (3 of 4 playable; 95% CI 30.1-95.4%); "
                          "held-out players (Elite D): 50.0% (1 of 2 playable; 95% CI 9.4-90.5%)")
    assert row.measured_on == "10 recorded human shots of matches.csv, cameras, seed 3 (the run's), 2026-01-02"
    assert row.source == "`models/policies/rally_paper_mc.json`"
    table = results.render_results(tmp_path)
    assert ("| `policy:rally_paper_mc`: the paper's action (eq. 12), SAC at scale | 75.0% (3 of 4 playable; 95% CI 30.1-95.4%); held-out players "
            "(Elite D): 50.0% (1 of 2 playable; 95% CI 9.4-90.5%) | 10 recorded human shots of matches.csv, cameras, seed 3 "
            "(the run's), 2026-01-02 | `models/policies/rally_paper_mc.json` |") in table.splitlines()
    # Files that are absent say so instead of showing a number.
    assert rows["`policy:rally_skill`: follows the skill's aim and spin"].figure == "not measured"
    assert rows["`returner`: the default controller"].figure == "not measured"


def test_policy_row_of_an_export_measured_as_evaluate_measures_says_so(tmp_path):
    sidecar = small_sidecar()
    sidecar["final_evaluation"].update(seed=0, stepping="segment", batch=32)  # training.export.final_evaluation today
    write_json(tmp_path / "models/policies/rally_paper_mc.json", sidecar)
    row = {row.what: row for row in results.result_rows(tmp_path)}["`policy:rally_paper_mc`: the paper's action (eq. 12), SAC at scale"]
    assert row.measured_on == "10 recorded human shots of matches.csv, cameras, seed 0, the segment diagram, 32 at a time, 2026-01-02"


def test_a_stored_evaluation_fills_the_returner_row(tmp_path):
    evaluation = {"controller": "returner", "data": "../data/matches.csv", "sensors": "cameras", "seed": 0, "episodes": 10,
                  "date": "2026-01-03", "command": "ace-drake evaluate --json",
                  "return_rate": {"returned": 3, "played": 4, "rate": 0.75, "ci95": [0.30064, 0.95443]}}
    write_json(tmp_path / "docs/results/returner.json", evaluation)
    row = results.result_rows(tmp_path)[0]
    assert row == results.Row("`returner`: the default controller", "75.0% (3 of 4 playable; 95% CI 30.1-95.4%)",
                              "10 recorded human shots of matches.csv, cameras, seed 0, the continuous diagram, 2026-01-03", "`docs/results/returner.json`")


def test_replace_block_keeps_the_text_around_the_markers():
    text = f"intro\n{results.RESULTS_BEGIN}\nold\n{results.RESULTS_END}\nafter\n"
    assert results.replace_block(text, "new") == f"intro\n{results.RESULTS_BEGIN}\nnew\n{results.RESULTS_END}\nafter\n"
    with pytest.raises(ValueError, match="results:begin"):
        results.replace_block("no markers", "new")


def test_readme_and_benchmarks_page_show_what_their_sources_hold():
    """The staleness test: fails whenever a sidecar or stored JSON changes without `ace-drake results`."""
    assert results.stale_files(REPO_ROOT) == []
    readme = (REPO_ROOT / "README.md").read_text()
    assert f"{results.RESULTS_BEGIN}\n{results.render_results(REPO_ROOT)}\n{results.RESULTS_END}" in readme


def copy_sources(root: Path) -> None:
    """The generated documents and every file their tables read, copied under ``root``."""
    for name in ("README.md", "docs/benchmarks.md", "models/ball_physics_fitted.json", "models/racket_fitted.json", "docs/benchmarks/sim.json",
                 "docs/benchmarks/train.json",
                 *(f"models/policies/{policy}.json" for policy in results.SHIPPED_POLICIES)):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO_ROOT / name, root / name)
    if (REPO_ROOT / "docs/results").is_dir():
        shutil.copytree(REPO_ROOT / "docs/results", root / "docs/results")


def test_check_fails_on_a_stale_readme_and_passes_once_regenerated(tmp_path, monkeypatch, capsys):
    copy_sources(tmp_path)
    monkeypatch.setattr(cli, "REPO_ROOT", tmp_path)
    assert cli.main(["results", "--check"]) == 0
    sidecar_path = tmp_path / "models/policies/rally_paper_mc.json"
    sidecar = json.loads(sidecar_path.read_text())
    sidecar["final_evaluation"]["return_rate"]["returned"] += 1
    sidecar_path.write_text(json.dumps(sidecar))
    assert results.stale_files(tmp_path) == ["README.md"]
    assert cli.main(["results", "--check"]) == 1
    assert "README.md is stale" in capsys.readouterr().err
    assert cli.main(["results"]) == 0
    assert "| `models/policies/rally_paper_mc.json` |" in capsys.readouterr().out
    assert cli.main(["results", "--check"]) == 0


def test_collection_rows_name_the_best_batch_and_nothing_without_a_measurement():
    from ace_drake.analysis.results import collection_rows

    train = {"env_steps_per_s": {"1": 70.0, "2": 140.0}, "vector_env_steps_per_s": {"16": 900.0, "64": 1400.0, "256": 1300.0},
             "updates_per_s": {"1": 50.0, "2": 61.0}, "batch_size": 256, "seconds_per_collection": 60, "date": "2026-12-04"}
    rows = collection_rows(train, "docs/benchmarks/train.json")
    assert rows[0].figure == "1400 steps per second (B = 64 each); RallyEnv: 140"
    assert rows[1].figure.startswith("61 per second")
    assert collection_rows(None, "x") == [] and collection_rows({**train, "vector_env_steps_per_s": {}}, "x") == []


def test_stored_matches_make_one_row_each_beside_the_papers(tmp_path):
    """A stored ``ace-drake rally --json`` becomes a row of matches, games and points won, rally
    length and the returns in play; the paper's Fig. 3a follows."""
    (tmp_path / "docs/results/matches").mkdir(parents=True)
    stored = {"controller": "returner", "opponent": "Elite A", "best_of": 3, "golden_point": True, "sensors": "cameras", "seed": 0, "date": "2026-12-06",
              "opponent_recorded": {"returns_landed": 0.772},
              "match": {"matches": 5, "matches_won": 4, "games": [[11, 5]] * 9 + [[5, 11]] * 2, "games_won": 9, "points_won": 150, "points_played": 230,
                        "rally_length_mean": 4.31, "rally_length_std": 3.02, "robot_returns": 200, "robot_return_errors": 10,
                        "human_returns": 180, "human_return_errors": 45,
                        "service_faults": 2, "points_served": 115, "human_service_faults": 9, "human_points_served": 115}}
    (tmp_path / "docs/results/matches/elite_a.json").write_text(json.dumps(stored))
    rows = results.match_rows(tmp_path)
    assert [row.what for row in rows] == ["`returner` against Elite A's model", "the paper's matches"]
    assert rows[0].figure == ("won 4 of 5 matches, 9 of 11 games, 150 of 230 points; rally length 4.3 +- 3.0 strikes; "
                              "the robot's returns in play 95.0%, the human's 75.0% (recorded 77.2%); service faults: the robot's 2 of 115, the human's 9 of 115")
    assert rows[0].measured_on == "5 matches (best of 3, golden point), cameras, seed 0, 2026-12-06"
    assert "3 of 5 matches, 7 of 13 games" in rows[1].figure
    assert results.match_rows(tmp_path / "nowhere") == []


def test_a_repeated_evaluation_says_its_seeds_and_repeats():
    evaluation = {"controller": "returner", "episodes": 30, "sensors": "cameras", "seed": 2, "data": None, "stepping": "segment", "batch": 32,
                  "return_rate": {"rate": 0.9, "returned": 27, "played": 30, "ci95": [0.74, 0.97]}}
    assert ", seed 2, " in results.evaluation_row("returner", evaluation, "x.json").measured_on
    repeated = results.evaluation_row("returner", {**evaluation, "repeats": 3}, "x.json").measured_on
    assert ", seeds 2-4, each shot 3 times, " in repeated
