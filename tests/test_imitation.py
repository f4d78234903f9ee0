"""The offline imitation fits (analysis.imitation) on constructed demonstrations."""

import numpy as np
import pytest
import torch

from ace_drake.analysis.imitation import demonstration_arrays, fit_imitation, label_sensitivity
from ace_drake.contracts import ObservationLayout
from ace_drake.learning.replay import DemonstrationBuffer

LAYOUT = ObservationLayout()


def constructed(rows: int, seed: int = 0):
    """Observations whose labels depend on the hit_prediction part alone (a smooth function of
    the predicted hit time and ball position), noise everywhere else."""
    rng = np.random.default_rng(seed)
    observations = rng.normal(size=(rows, LAYOUT.size)).astype(np.float32)
    hit = np.column_stack([np.ones(rows), rng.uniform(0.0, 0.5, rows), rng.normal(size=(rows, 9))])
    observations[:, LAYOUT.slice("hit_prediction")] = hit
    weights = rng.normal(size=(4, 16))
    actions = np.tanh(np.column_stack([hit[:, 1] * 4.0, hit[:, 2:5]]) @ weights * 0.5).astype(np.float32)
    return observations, actions


def test_the_fit_finds_what_the_labels_depend_on_and_improves_with_data():
    observations, actions = constructed(4000)
    kwargs = dict(hidden=(64,), steps=600, seed=0)
    blind = fit_imitation(observations, actions, LAYOUT, ["skill", "estimate"], **kwargs)
    seeing = fit_imitation(observations, actions, LAYOUT, ["skill", "hit_prediction"], **kwargs)
    assert seeing.held_out < 0.3 * blind.held_out
    assert blind.held_out == pytest.approx(blind.label_variance, rel=0.3)  # no better than the mean
    fewer = fit_imitation(observations, actions, LAYOUT, ["skill", "hit_prediction"], fit_fraction=0.1, **kwargs)
    assert fewer.fit_rows == 360 and fewer.held_out > seeing.held_out
    # Held-out rows split into the swing (a hit < 0.1 s ahead) and the rest.
    assert np.isfinite(seeing.held_out_swing) and np.isfinite(seeing.held_out_other)
    # The same seed, the same fit.
    assert fit_imitation(observations, actions, LAYOUT, ["skill", "hit_prediction"], **kwargs) == seeing
    with pytest.raises(ValueError, match="too few"):
        fit_imitation(observations[:100], actions[:100], LAYOUT, ["skill"], **kwargs)
    with pytest.raises(ValueError, match="need observations"):
        fit_imitation(observations[:, :10], actions, LAYOUT, ["skill"], **kwargs)


def test_demonstrations_come_from_a_checkpoint_in_collection_order(tmp_path):
    buffer = DemonstrationBuffer(capacity=5)
    for start in (0, 3):  # the second episode wraps the ring: rows 0..2, then 3..5 (row 0 overwritten)
        rows = np.arange(start, start + 3, dtype=np.float32)
        buffer.add({"obs": np.repeat(rows[:, None], LAYOUT.size, 1), "privileged": np.zeros((3, 28)),
                    "demo_action": np.repeat(rows[:, None], 16, 1)})
    torch.save({"demonstrations": buffer.state_dict()}, tmp_path / "checkpoint.pt")
    observations, actions, layout = demonstration_arrays(tmp_path / "checkpoint.pt")
    np.testing.assert_array_equal(observations[:, 0], [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(actions[:, 0], [1, 2, 3, 4, 5])
    assert layout == LAYOUT  # no config saved: the default histories
    # A run whose learner read shorter histories has another layout than these observations.
    torch.save({"demonstrations": buffer.state_dict(), "config": {"sac": {"position_history": 3, "spin_history": 3}}}, tmp_path / "short.pt")
    with pytest.raises(ValueError, match="its layout"):
        demonstration_arrays(tmp_path / "short.pt")
    torch.save({"learner": {}}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a training checkpoint"):
        demonstration_arrays(tmp_path / "other.pt")


def test_label_sensitivity_measures_how_labels_move_with_the_estimate():
    observations, _ = constructed(50)
    estimate = LAYOUT.slice("estimate")

    def smooth(observation):  # labels proportional to the estimate's position: tiny changes
        return np.r_[observation[estimate][:3], np.zeros(13)]

    def jumpy(observation):  # a label that flips with the sign of the third decimal of x
        return np.full(16, 1.0 if (observation[estimate][0] * 1e3) % 2 < 1 else -1.0)

    calm = label_sensitivity(observations, smooth, LAYOUT, rows=40)
    assert calm["rows"] == 40 and calm["mean"] == pytest.approx(3e-6, rel=0.5) and calm["share_above_0.5"] == 0.0
    wild = label_sensitivity(observations, jumpy, LAYOUT, rows=40)
    assert wild["share_above_0.5"] > 0.2
    assert label_sensitivity(observations, lambda o: None if o[0] > 0 else smooth(o), LAYOUT, rows=40)["skipped"] > 0


def test_the_imitation_command_reports_its_fits(tmp_path, capsys):
    import json

    from ace_drake import cli

    observations, actions = constructed(1500)
    buffer = DemonstrationBuffer(capacity=2000)
    buffer.add({"obs": observations, "privileged": np.zeros((1500, 28)), "demo_action": actions})
    torch.save({"demonstrations": buffer.state_dict()}, tmp_path / "checkpoint.pt")
    assert cli.main(["imitation", str(tmp_path / "checkpoint.pt"), "--steps", "50", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["rows"] == 1500 and [fit["fit_rows"] for fit in report["fits"]] == [1350, 1350, 675, 337]
    assert "hit_prediction" not in report["fits"][0]["parts"] and "hit_prediction" in report["fits"][1]["parts"]
    assert cli.main(["imitation", str(tmp_path / "missing.pt")]) == 2


def test_the_imitation_command_reports_a_file_that_is_not_a_checkpoint_as_an_input_error(tmp_path, capsys):
    from ace_drake import cli

    torch.save({"learner": {}}, tmp_path / "other.pt")
    assert cli.main(["imitation", str(tmp_path / "other.pt")]) == 2
    assert f"error: imitation: {tmp_path / 'other.pt'} is not a training checkpoint" in capsys.readouterr().err
