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
