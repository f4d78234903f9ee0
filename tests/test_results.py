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
        "name": "rally_sac",
        "command": "ace-drake train models/train_rally_sac.yaml",
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
    write_json(tmp_path / "models/policies/rally_sac.json", small_sidecar())
    rows = {row.what: row for row in results.result_rows(tmp_path)}
    row = rows["`policy:rally_sac`: the paper's action (eq. 12)"]
    assert row.figure == ("75.0% (3 of 4 playable; 95% CI 30.1-95.4%); "
                          "held-out players (Elite D): 50.0% (1 of 2 playable; 95% CI 9.4-90.5%)")
    assert row.measured_on == "10 recorded human shots of matches.csv, cameras, seed 3 (the run's), 2026-01-02"
    assert row.source == "`models/policies/rally_sac.json`"
    table = results.render_results(tmp_path)
    assert ("| `policy:rally_sac`: the paper's action (eq. 12) | 75.0% (3 of 4 playable; 95% CI 30.1-95.4%); held-out players "
            "(Elite D): 50.0% (1 of 2 playable; 95% CI 9.4-90.5%) | 10 recorded human shots of matches.csv, cameras, seed 3 "
            "(the run's), 2026-01-02 | `models/policies/rally_sac.json` |") in table.splitlines()
    # Files that are absent say so instead of showing a number.
    assert rows["`policy:rally_skill`: follows the skill's aim and spin"].figure == "not measured"
    assert rows["`returner`: the default controller"].figure == "not measured"


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
    sidecar_path = tmp_path / "models/policies/rally_sac.json"
    sidecar = json.loads(sidecar_path.read_text())
    sidecar["final_evaluation"]["return_rate"]["returned"] += 1
    sidecar_path.write_text(json.dumps(sidecar))
    assert results.stale_files(tmp_path) == ["README.md"]
    assert cli.main(["results", "--check"]) == 1
    assert "README.md is stale" in capsys.readouterr().err
    assert cli.main(["results"]) == 0
    assert "| `models/policies/rally_sac.json` |" in capsys.readouterr().out
    assert cli.main(["results", "--check"]) == 0


def test_collection_rows_name_the_best_batch_and_nothing_without_a_measurement():
    from ace_drake.analysis.results import collection_rows

    train = {"env_steps_per_s": {"1": 70.0, "2": 140.0}, "vector_env_steps_per_s": {"16": 900.0, "64": 1400.0, "256": 1300.0},
             "updates_per_s": {"1": 50.0, "2": 61.0}, "batch_size": 256, "seconds_per_collection": 60, "date": "2026-12-04"}
    rows = collection_rows(train, "docs/benchmarks/train.json")
    assert rows[0].figure == "1400 steps per second (B = 64 each); RallyEnv: 140"
    assert rows[1].figure.startswith("61 per second")
    assert collection_rows(None, "x") == [] and collection_rows({**train, "vector_env_steps_per_s": {}}, "x") == []
