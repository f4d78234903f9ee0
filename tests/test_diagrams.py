"""Diagram builders: stable names, the committed graphs in diagrams/ are current, and every
stochastic system is seeded by the diagram's random context."""

from pathlib import Path

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from ace_drake.diagrams import DOCUMENTED_DIAGRAMS, graphviz_dot
from ace_drake.systems.random_seed import declare_seed_port, episode_seed

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



class NoisyReading(LeafSystem):
    """A stochastic system seeded the way the project's sensors are (``systems.random_seed``): it
    declares the random ``random_seed`` input and nothing else about seeding. State: discrete, the
    last ``size`` Gaussian draws, redrawn every 10 ms from [seed, update number]."""

    def __init__(self, size: int = 3):
        super().__init__()
        self.size = size
        self.random_seed_port = declare_seed_port(self)
        self._draws = self.DeclareDiscreteState(size)
        self.DeclarePeriodicDiscreteUpdateEvent(0.01, 0.0, self.Draw)

    def Draw(self, context, discrete_state):
        rng = np.random.default_rng([episode_seed(self.random_seed_port, context, 0), round(context.get_time() / 0.01)])
        discrete_state.get_mutable_vector(self._draws).SetFromVector(rng.standard_normal(self.size))

    def draws(self, context) -> np.ndarray:
        return context.get_discrete_state(self._draws).get_value().copy()


def advance(simulator, system, steps: int = 5) -> np.ndarray:
    """The draws of ``system`` after each of ``steps`` 10 ms steps from the context's time."""
    context = simulator.get_mutable_context()
    simulator.Initialize()
    draws = []
    for _ in range(steps):
        simulator.AdvanceTo(context.get_time() + 0.01)
        draws.append(system.draws(system.GetMyContextFromRoot(context)))
    return np.array(draws)


def test_a_new_stochastic_system_is_seeded_by_start_rally_with_no_edit_elsewhere():
    # A system start_rally has never heard of, added to the rally wiring: the rally's seed gives it
    # the same noise bit for bit, another seed other noise, and its stream is not the sensors'.
    from ace_drake.control.params import RallyParams
    from ace_drake.diagrams import add_rally, add_random_sources, make_simulator, start_rally
    from ace_drake.perception.params import PerceptionParams
    from ace_drake.physics.flight import make_state

    builder = DiagramBuilder()
    add_rally(builder, RallyParams(perception=PerceptionParams(positions="statistical")), lambda observation: None)
    noisy = builder.AddNamedSystem("noisy_reading", NoisyReading())
    add_random_sources(builder)
    diagram = builder.Build()
    assert {"noisy_reading_seed_source", "ball_seed_source", "position_sensor_seed_source", "spin_sensor_seed_source"} <= {
        system.get_name() for system in diagram.GetSystems()
    }
    stochastic = [noisy, *(diagram.GetSubsystemByName(name) for name in ("ball", "position_sensor", "spin_sensor"))]
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    shot = make_state((1.6, 0.25, 0.25), (-6.0, -0.3, 2.2), (0.0, -80.0, 0.0))

    def episode(seed):
        context.SetTime(0.0)
        start_rally(diagram, context, shot, seed=seed)
        seeds = [episode_seed(system.random_seed_port, system.GetMyContextFromRoot(context), -1) for system in stochastic]
        start = context.Clone()
        return seeds, advance(simulator, noisy), start

    seeds, first, start = episode(7)
    assert len(set(seeds)) == 4  # four systems, four streams
    again_seeds, again, _ = episode(7)
    other_seeds, other, _ = episode(8)
    assert again_seeds == seeds and np.array_equal(again, first)
    assert all(a != b for a, b in zip(other_seeds, seeds)) and not np.allclose(other, first)
    # A copy of the episode's starting Context replays it bit for bit.
    context.SetTimeStateAndParametersFrom(start)
    np.testing.assert_array_equal(advance(simulator, noisy), first)


def test_two_copies_of_one_system_in_a_diagram_draw_different_streams():
    from ace_drake.diagrams import add_random_sources

    builder = DiagramBuilder()
    first, second = (builder.AddNamedSystem(name, NoisyReading()) for name in ("first", "second"))
    add_random_sources(builder)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()

    def run(seed):
        context.SetTime(0.0)
        diagram.SetRandomContext(context, RandomGenerator(seed))
        return advance(simulator, first), first.draws(first.GetMyContextFromRoot(context)), second.draws(second.GetMyContextFromRoot(context))

    stream, a, b = run(3)
    assert not np.allclose(a, b)
    again, a_again, b_again = run(3)
    np.testing.assert_array_equal(again, stream)
    np.testing.assert_array_equal(b_again, b)
    assert not np.allclose(run(4)[0], stream)


def test_an_unconnected_seed_port_falls_back_to_the_seed_parameter():
    from ace_drake.perception.params import SpinSensorParams
    from ace_drake.systems.gaze_spin_sensor import GazeSpinSensor

    dut = GazeSpinSensor(SpinSensorParams(), seed=5)
    context = dut.CreateDefaultContext()
    assert dut._seed(context) == 5
    dut.SetSeed(context, 9)
    assert dut._seed(context) == 9
