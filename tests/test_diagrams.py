"""Diagram builders: stable names, and the committed graphs in diagrams/ are current."""

from pathlib import Path

import pytest

from ace_drake.diagrams import DOCUMENTED_DIAGRAMS, graphviz_dot

DIAGRAMS_DIR = Path(__file__).resolve().parents[1] / "diagrams"


@pytest.mark.parametrize("name", sorted(DOCUMENTED_DIAGRAMS))
def test_committed_dot_is_current(name):
    committed = DIAGRAMS_DIR / f"{name}.dot"
    assert committed.is_file(), f"{committed} missing: run `ace-drake diagrams`"
    assert graphviz_dot(DOCUMENTED_DIAGRAMS[name]()) == committed.read_text(), (
        f"{committed} is out of date: run `ace-drake diagrams` and commit the result"
    )


def test_graph_text_does_not_depend_on_what_was_built_before():
    build = DOCUMENTED_DIAGRAMS["ball_diagram"]
    first = graphviz_dot(build())
    build()  # more systems in the process shift Drake's global ids
    assert graphviz_dot(build()) == first


def test_systems_have_stable_names():
    diagram = DOCUMENTED_DIAGRAMS["ball_diagram"]()
    names = {system.get_name() for system in diagram.GetSystems()}
    assert {"ball", "racket_pose_source", "racket_velocity_source", "ball_logger"} <= names


@pytest.mark.parametrize("positions", ["cameras", "statistical"])
def test_the_perception_diagram_tracks_a_ball_through_either_position_path(positions):
    import numpy as np

    from ace_drake.diagrams import build_perception_diagram, make_simulator
    from ace_drake.perception.params import PerceptionParams
    from ace_drake.physics.flight import make_state

    diagram = build_perception_diagram(PerceptionParams(positions=positions))
    names = {system.get_name() for system in diagram.GetSystems()}
    assert {"ball", "spin_sensor", "ball_estimator"} <= names
    assert ({"aps_cameras", "triangulator"} <= names) == (positions == "cameras")
    assert ("position_sensor" in names) == (positions == "statistical")
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball = diagram.GetSubsystemByName("ball")
    ball.GetMyMutableContextFromRoot(context).SetContinuousState(make_state((1.6, 0.2, 0.25), (-7.0, -0.3, 1.5), (0.0, -150.0, 0.0)))
    simulator.Initialize()
    simulator.AdvanceTo(0.3)  # through the bounce on the robot's half
    truth = diagram.GetSubsystemByName("ball_logger").FindLog(context).data()[:, -1]
    estimate = diagram.GetSubsystemByName("estimate_logger").FindLog(context).data()[:, -1]
    assert np.linalg.norm(estimate[:3] - truth[:3]) < 0.01
    assert np.linalg.norm(estimate[3:6] - truth[3:6]) < 0.3
    assert np.linalg.norm(estimate[6:] - truth[6:]) < 60.0


def test_the_rendered_cameras_are_wired_to_drake_images():
    from ace_drake.diagrams import build_perception_diagram
    from ace_drake.perception.params import CameraParams, PerceptionParams

    diagram = build_perception_diagram(PerceptionParams(camera=CameraParams(mode="rendered", render_scale=0.1)))
    cameras = diagram.GetSubsystemByName("aps_cameras")
    for name in cameras.camera_names:
        assert diagram.GetSubsystemByName(f"camera_{name}") is not None
        assert cameras.image_ports[name].get_name() == f"color_image_{name}"


def test_without_graphviz_the_index_keeps_only_the_svgs_still_current(tmp_path, monkeypatch):
    import argparse
    import shutil

    from ace_drake import cli

    monkeypatch.setattr(shutil, "which", lambda program: None)
    for name in ("ball_diagram", "rally_diagram"):
        (tmp_path / f"{name}.svg").write_text("<svg/>")
    (tmp_path / "ball_diagram.dot").write_text((DIAGRAMS_DIR / "ball_diagram.dot").read_text())  # current
    (tmp_path / "rally_diagram.dot").write_text("digraph { an_older_graph }")  # its graph changed since
    assert cli.cmd_diagrams(argparse.Namespace(out=str(tmp_path))) == 0
    index = (tmp_path / "README.md").read_text()
    assert "ball_diagram.svg" in index and "rally_diagram.svg" not in index and "training_diagram.svg" not in index
    assert all((tmp_path / f"{name}.dot").read_text() == (DIAGRAMS_DIR / f"{name}.dot").read_text() for name in DOCUMENTED_DIAGRAMS)
