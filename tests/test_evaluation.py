"""The return-rate evaluation's figures on constructed episodes (evaluation/evaluate.py): the
skill figures (aim, landing spin by w_s, eq. (10) reward) and how episodes are counted."""

import numpy as np
import pytest

from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.evaluation.evaluate import clustered_return_rate, return_rate, run_episodes, skill_figures, summarize, wilson_interval
from ace_drake.evaluation.runner import Episode
from ace_drake.learning.params import RewardParams
from ace_drake.physics.propagate import ContactEvent, ContactKind

SHOT = np.array([1.2, 0.0, 0.3, -8.0, 0.0, 1.0, 0.0, -100.0, 0.0])


def _event(kind, state) -> ContactEvent:
    state = np.asarray(state, dtype=float)
    return ContactEvent(kind, 0.5, state, state)


def returned(y_land: float, topspin: float, skill) -> Episode:
    """A return landing at y_land (m) flying along +x with ``topspin`` rad/s about the travel
    frame's y axis (for a ball flying along +x, that is the world's +y), played with ``skill``."""
    landing = _event(ContactKind.TABLE, [0.7, y_land, 0.02, 6.0, 0.0, -2.0, 0.0, topspin, 0.0])
    hit = _event(ContactKind.RACKET, [-1.5, 0.0, 0.25, 6.0, 0.0, 2.0, 0.0, topspin, 0.0])
    result = EpisodeResult(Outcome.RETURNED, "", None, hit, landing)
    return Episode(SHOT, result, 1.0, (10, 0), np.asarray(skill, dtype=float))


def missed(skill=(0.0, 1.0, 0.0)) -> Episode:
    return Episode(SHOT, EpisodeResult(Outcome.MISSED, "not hit: the ball reached the floor"), 1.0, (10, 0), np.asarray(skill, dtype=float))


def test_perfect_aim_has_slope_one_and_no_error_and_an_ignored_aim_slope_zero():
    skills = [(y, 1.0, 0.0) for y in (-0.6, -0.2, 0.1, 0.5)]
    perfect = skill_figures([returned(s[0], 0.0, s) for s in skills])["aim"]
    assert perfect["count"] == 4 and perfect["error_m"]["median"] == pytest.approx(0.0, abs=1e-12)
    assert perfect["slope"] == pytest.approx(1.0) and perfect["correlation"] == pytest.approx(1.0)
    ignored = skill_figures([returned(0.3 + 0.01 * i, 0.0, s) for i, s in enumerate(skills)])["aim"]
    assert abs(ignored["slope"]) < 0.05 and ignored["error_m"]["median"] > 0.2
    # Returns whose skill does not weigh the position (w_p = 0) are not aimed; one y_desired has no slope.
    unweighted = skill_figures([returned(0.0, 0.0, (0.5, 0.0, 0.0)), returned(0.4, 0.0, (0.4, 1.0, 0.0))])["aim"]
    assert unweighted["count"] == 1 and unweighted["slope"] is None


def test_landing_spin_is_grouped_by_the_sign_of_w_s():
    episodes = [returned(0.0, 300.0, (0.0, 0.0, 1.0)), returned(0.0, 250.0, (0.0, 0.0, 0.5)),
                returned(0.0, 10.0, (0.0, 0.0, 1.0 / 3.0)), returned(0.0, -20.0, (0.0, 0.0, -1.0 / 3.0)),
                returned(0.0, -200.0, (0.0, 0.0, -1.0)), missed((0.0, 1.0, 1.0))]
    groups = {group["group"]: group["landing_topspin_rad_s"] for group in skill_figures(episodes)["landing_topspin_rad_s"]}
    assert groups["topspin"]["count"] == 2 and groups["topspin"]["median"] == pytest.approx(275.0)
    assert groups["neutral"]["count"] == 2 and groups["neutral"]["median"] == pytest.approx(-5.0)  # |w_s| <= 1/3
    assert groups["backspin"]["count"] == 1 and groups["backspin"]["median"] == pytest.approx(-200.0)


def test_the_mean_reward_is_eq_10_over_the_playable_episodes():
    params = RewardParams()
    hit_target = returned(0.2, 400.0, (0.2, 1.0, 1.0))  # return_base + position_reward + 400 * spin_gain
    expected = (params.return_base + params.position_reward + 400.0 * params.spin_gain + params.miss) / 2
    invalid = Episode(SHOT, EpisodeResult(Outcome.INVALID, "the shot missed the table"), 0.5, (0, 0), np.array([0.0, 1.0, 0.0]))
    figures = summarize([hit_target, missed(), invalid])
    assert figures["skill"]["mean_reward"] == pytest.approx(expected)
    assert figures["return_rate"]["played"] == 2 and figures["invalid_shots"] == 1


class _Runner:
    """Records the skills it is asked to play with."""

    def __init__(self):
        self.skills = []

    def run(self, shot, seed=0, serve=False, skill=None):
        self.skills.append(skill)
        return missed()


def test_run_episodes_plays_each_shot_with_its_skill_and_refuses_a_wrong_shape():
    runner = _Runner()
    skills = np.array([[0.1, 1.0, 0.0], [-0.2, 0.5, 1.0]])
    run_episodes(runner, np.stack([SHOT, SHOT]), np.zeros(2, dtype=bool), skills=skills)
    np.testing.assert_array_equal(np.array(runner.skills), skills)
    run_episodes(runner, SHOT[None], np.zeros(1, dtype=bool))
    assert runner.skills[-1] is None  # the diagram's default
    with pytest.raises(ValueError, match="one per shot"):
        run_episodes(runner, np.stack([SHOT, SHOT]), np.zeros(2, dtype=bool), skills=skills[:1])


def _heldout(directory, controller, rate, **conditions):
    import json

    evaluation = {"controller": controller, "return_rate": {"rate": rate, "returned": 0, "played": 0, "ci95": [0, 1]},
                  "data_sha256": "abc", "players": ["Elite D", "Elite E"], "sensors": "cameras", "seed": 0, "skills": "default",
                  "ball_params": None, "action_noise": 0.0, **conditions}
    directory.mkdir(exist_ok=True)
    (directory / f"{controller.replace(':', '_')}.json").write_text(json.dumps(evaluation))


def test_the_main_jobs_controller_is_the_best_measured_on_the_heldout_players(tmp_path):
    from ace_drake.config import ConfigError
    from ace_drake.evaluation.controllers import best_controller, controller_names

    assert best_controller(tmp_path / "none") == ("returner", None)  # nothing measured
    _heldout(tmp_path / "a", "policy:rally_paper_mc", 0.95)
    assert best_controller(tmp_path / "a") == ("returner", None)  # nothing to beat: the returner is not measured
    _heldout(tmp_path / "a", "returner", 0.91)
    _heldout(tmp_path / "a", "policy:rally_skill", 0.80)
    assert "policy:rally_paper_mc" in controller_names()
    assert best_controller(tmp_path / "a") == ("policy:rally_paper_mc", 0.95)
    _heldout(tmp_path / "b", "returner", 0.91)
    _heldout(tmp_path / "b", "policy:rally_paper_mc", 0.91)  # a tie keeps the returner
    _heldout(tmp_path / "b", "policy:not_shipped", 0.99)  # a policy this checkout does not have is not chosen
    assert best_controller(tmp_path / "b") == ("returner", 0.91)
    _heldout(tmp_path / "c", "returner", 0.91)
    _heldout(tmp_path / "c", "policy:rally_paper_mc", 0.95, sensors="statistical")
    with pytest.raises(ConfigError, match="other conditions.*sensors"):
        best_controller(tmp_path / "c")
    # An evaluation stored before `repeats` was recorded played each shot once.
    _heldout(tmp_path / "d", "returner", 0.91)
    _heldout(tmp_path / "d", "policy:rally_paper_mc", 0.95, repeats=1)
    assert best_controller(tmp_path / "d") == ("policy:rally_paper_mc", 0.95)
    _heldout(tmp_path / "d", "policy:rally_paper_mc", 0.95, repeats=5)
    with pytest.raises(ConfigError, match="other conditions.*repeats"):
        best_controller(tmp_path / "d")


def test_the_stored_heldout_evaluations_are_comparable_and_name_the_controller_the_main_job_plays():
    from ace_drake.evaluation.controllers import best_controller
    from ace_drake.evaluation.heldout import HELDOUT_DIR, heldout_evaluations

    evaluations = heldout_evaluations()
    assert "returner" in evaluations and {tuple(e["players"]) for e in evaluations.values()} == {("Elite D", "Elite E")}
    name, rate = best_controller()
    assert rate == max(e["return_rate"]["rate"] for e in evaluations.values())
    assert (HELDOUT_DIR / "README.md").is_file()


def test_repeats_of_a_shot_are_not_independent_trials():
    """A repeated evaluation's interval is Wilson's over the effective number of episodes: one play
    per shot gives Wilson's over the shots; every shot's outcome repeated three times adds no
    information and gives the same; outcomes that differ between a shot's repeats narrow it; an
    evaluation where every episode agrees keeps Wilson's over its shots."""
    outcomes = np.random.default_rng(3).random(60) < 0.8
    wilson = return_rate(int(outcomes.sum()), 60)
    once = clustered_return_rate(outcomes, np.arange(60))
    assert once["rate"] == pytest.approx(wilson["rate"]) and once["ci95"] == pytest.approx(wilson["ci95"], abs=1e-12)
    thrice = clustered_return_rate(np.tile(outcomes, 3), np.tile(np.arange(60), 3))
    assert thrice["played"] == 180 and thrice["rate"] == pytest.approx(outcomes.mean())
    assert thrice["ci95"] == pytest.approx(wilson["ci95"], abs=1e-12)
    independent = np.random.default_rng(4).random(180) < 0.8  # each repeat its own draw
    narrower = clustered_return_rate(independent, np.tile(np.arange(60), 3))
    assert narrower["ci95"] == pytest.approx(return_rate(int(independent.sum()), 180)["ci95"], rel=0.05)
    assert narrower["ci95"][1] - narrower["ci95"][0] < 0.8 * (once["ci95"][1] - once["ci95"][0])
    all_returned = clustered_return_rate(np.ones(15, dtype=bool), np.repeat(np.arange(3), 5))
    assert all_returned["ci95"] == pytest.approx(return_rate(3, 3)["ci95"], abs=1e-12) and all_returned["ci95"][0] < 0.5
    assert clustered_return_rate(np.zeros(0, dtype=bool), np.zeros(0, dtype=int))["rate"] is None


def test_a_repeated_evaluation_pools_its_episodes_by_shot():
    """summarize(episodes, shot_count): episode i played shot i mod shot_count; the pooled figures
    count every episode, an unplayable one (here shot 1 in the second repeat) left out, and the
    intervals are those of the episodes grouped by their shots."""
    invalid = Episode(SHOT, EpisodeResult(Outcome.INVALID, "not a legal shot"), 1.0, (0, 0), np.array([0.0, 1.0, 0.0]))
    skill = (0.0, 1.0, 0.0)
    first = [returned(0.0, 100.0, skill), missed(), returned(0.1, 100.0, skill)]
    second = [returned(0.0, 100.0, skill), invalid, missed()]
    pooled = summarize(first + second, shot_count=3)
    assert pooled["episodes"] == 6 and pooled["invalid_shots"] == 1
    expected = clustered_return_rate(np.array([True, False, True, True, False]), np.array([0, 1, 2, 0, 2]))
    assert pooled["return_rate"] == expected and expected["ci95"] != return_rate(3, 5)["ci95"]
    assert expected["ci95"] != clustered_return_rate(np.array([True, False, True, True, False]), np.arange(5))["ci95"]
    (row,) = [row for row in pooled["by_incoming_speed"] if row["played"]]
    assert {key: row[key] for key in expected} == expected  # every shot is SHOT: one bin
    assert summarize(first)["return_rate"] == return_rate(2, 3)  # one play of each shot: Wilson's


@pytest.mark.parametrize("returned, played", [(0, 3), (2, 3), (157, 187), (187, 187), (1, 1000)])
def test_the_wilson_interval_is_scipys(returned, played):
    from scipy.stats import binomtest

    reference = binomtest(returned, played).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson_interval(returned / played, played) == pytest.approx((reference.low, reference.high), abs=1e-12)
