"""System identification recovers planted joint models (paper, Methods *Robot dynamics*)."""

import json

import numpy as np
import pytest

from ace_drake.cli import main
from ace_drake.config import load_config
from ace_drake.control.joint_model import ProcessModel
from ace_drake.control.sysid import JointLogError, identify_joint, load_joint_log, synthetic_joint_log, write_joint_log
from ace_drake.robot.params import RobotDynamicsParams

PLANTED = {
    "gantry_x": ProcessModel(1.0, 420.0, 0.85, 0.0032),
    "wrist_2": ProcessModel(0.98, 1500.0, 0.6, 0.0013),
}


def test_identify_recovers_planted_parameters_from_a_noisy_log():
    log = synthetic_joint_log({n: p.to_state_space() for n, p in PLANTED.items()}, duration=3.0, noise=2e-4, seed=1)
    for name, truth in PLANTED.items():
        result = identify_joint(log.times, log.commands[name], log.positions[name])
        assert result.process.gain == pytest.approx(truth.gain, rel=0.02)
        assert result.process.natural_frequency == pytest.approx(truth.natural_frequency, rel=0.03)
        assert result.process.damping_ratio == pytest.approx(truth.damping_ratio, rel=0.03)
        assert result.process.delay == pytest.approx(truth.delay, rel=0.03)
        assert result.rms_error == pytest.approx(2e-4, rel=0.2)  # down to the measurement noise


def test_sysid_command_writes_a_loadable_config(tmp_path, capsys):
    log_path = tmp_path / "log.csv"
    write_joint_log(log_path, synthetic_joint_log({"gantry_x": PLANTED["gantry_x"].to_state_space()}, duration=2.0, seed=2))
    out = tmp_path / "joints.yaml"
    assert main(["sysid", "--log", str(log_path), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["defaulted"] == ["gantry_y", "shoulder_yaw", "shoulder_pitch", "elbow", "wrist_1", "wrist_2", "wrist_3"]
    params = load_config(RobotDynamicsParams, out)
    identified = ProcessModel.from_state_space(params.joints[0])
    assert identified.delay == pytest.approx(0.0032, rel=0.03)
    assert params.joints[1] == RobotDynamicsParams().joints[1]
    assert json.loads(out.with_suffix(".json").read_text())["log"]["samples"] == 2000


def test_bad_logs_are_rejected_clearly(tmp_path):
    with pytest.raises(JointLogError, match="not found"):
        load_joint_log(tmp_path / "absent.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("time,x_command\n0,1\n")
    with pytest.raises(JointLogError, match="column pairs"):
        load_joint_log(bad)
    t = np.arange(200) * 1e-3
    t[100:] += 5e-4
    with pytest.raises(JointLogError, match="not uniform"):
        identify_joint(t, np.r_[np.zeros(100), np.ones(100)], np.zeros(200))
    with pytest.raises(JointLogError, match="not excited"):
        identify_joint(np.arange(200) * 1e-3, np.zeros(200), np.zeros(200))
