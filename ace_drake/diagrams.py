"""Diagram builders: the only place where systems are wired together.

Each builder returns a built Diagram whose systems have stable names (``AddNamedSystem``), so that
graphs and ``GetSubsystemByName`` lookups stay the same across runs. ``make_simulator`` configures
the integrator the way the BallPlant's contact timing needs.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, VectorLogSink

from ace_drake.config import BallPhysicsParams
from ace_drake.physics.contact import ResidualModel
from ace_drake.systems.ball_plant import BallPlant
from ace_drake.systems.ball_visualizer import BallVisualizer

SIMULATION_ACCURACY = 1e-6  # integrator target accuracy; places witness events within ~1e-8 s
MAX_STEP = 1e-3  # s; keeps the racket from being tunnelled through at relative speeds up to 50 m/s


@dataclasses.dataclass(frozen=True)
class StaticRacket:
    """A racket held still, or moving at constant velocity, for ball-only diagrams.

    X_WR: pose of the racket frame (origin at the blade centre, z along the blade normal).
    V_WR: its spatial velocity [w (rad/s), v (m/s)] (used at contact; the pose does not move).
    """

    X_WR: RigidTransform
    V_WR: SpatialVelocity = dataclasses.field(default_factory=lambda: SpatialVelocity(np.zeros(6)))


def make_simulator(diagram: Diagram, context=None, accuracy: float = SIMULATION_ACCURACY, max_step: float = MAX_STEP) -> Simulator:
    """A Simulator for any diagram containing a BallPlant: error-controlled RK3 with the given
    target accuracy and maximum step (s), and the accuracy stored in the context so that witness
    isolation uses it."""
    context = context or diagram.CreateDefaultContext()
    context.SetAccuracy(accuracy)
    simulator = Simulator(diagram, context)
    integrator = simulator.get_mutable_integrator()
    integrator.set_target_accuracy(accuracy)
    integrator.set_maximum_step_size(max_step)
    return simulator


def add_ball(
    builder: DiagramBuilder,
    params: BallPhysicsParams,
    perturb: bool = False,
    seed: int = 0,
    racket_residual: ResidualModel | None = None,
) -> BallPlant:
    """Adds the BallPlant as ``ball``; the shared first step of every builder."""
    return builder.AddNamedSystem("ball", BallPlant(params, perturb=perturb, seed=seed, racket_residual=racket_residual))


def build_ball_diagram(
    params: BallPhysicsParams | None = None,
    racket: StaticRacket | None = None,
    meshcat: Meshcat | None = None,
    perturb: bool = False,
    seed: int = 0,
    log_period: float = 0.0,
) -> Diagram:
    """The ball on its own: BallPlant (``ball``), an optional static racket
    (``racket_pose_source``, ``racket_velocity_source``), an optional Meshcat visualizer
    (``ball_visualizer``) and a logger of the ball state (``ball_logger``; every step when
    ``log_period`` is 0, else every ``log_period`` seconds)."""
    params = params or BallPhysicsParams()
    builder = DiagramBuilder()
    ball = add_ball(builder, params, perturb=perturb, seed=seed)
    if racket is not None:
        pose = builder.AddNamedSystem("racket_pose_source", ConstantValueSource(AbstractValue.Make(racket.X_WR)))
        velocity = builder.AddNamedSystem(
            "racket_velocity_source", ConstantValueSource(AbstractValue.Make(racket.V_WR))
        )
        builder.Connect(pose.get_output_port(), ball.racket_pose_port)
        builder.Connect(velocity.get_output_port(), ball.racket_velocity_port)
    if meshcat is not None:
        visualizer = builder.AddNamedSystem("ball_visualizer", BallVisualizer(meshcat, params))
        builder.Connect(ball.ball_state_port, visualizer.ball_state_port)
    logger = builder.AddNamedSystem("ball_logger", VectorLogSink(9, log_period))
    builder.Connect(ball.ball_state_port, logger.get_input_port())
    diagram = builder.Build()
    diagram.set_name("ball_diagram")
    return diagram


def _documented_ball_diagram() -> Diagram:
    """The ball diagram as documented: with a (static) racket connected, no Meshcat."""
    return build_ball_diagram(racket=StaticRacket(RigidTransform()))


# name -> builder of the diagram whose graph ``ace-drake diagrams`` renders into diagrams/.
DOCUMENTED_DIAGRAMS = {
    "ball_diagram": _documented_ball_diagram,
}


def graphviz_dot(diagram: Diagram, max_depth: int = 1) -> str:
    """The diagram's Graphviz DOT text, normalised so that the same wiring always gives the same
    text: system ids renumbered from 0 in order of first appearance (Drake's ids are global
    counters that depend on what else the process built) and the edge lines sorted (Drake emits
    them in an order that can change between processes)."""
    import re

    dot = diagram.GetGraphvizString(max_depth=max_depth)
    numbering: dict[str, str] = {}

    def renumber(match: re.Match) -> str:
        number = numbering.setdefault(match.group(2), str(len(numbering)))
        return match.group(1) + number

    lines = re.sub(r"\b(digraph _|cluster|s)(\d+)", renumber, dot).split("\n")
    edge_rows = [i for i, line in enumerate(lines) if " -> " in line]
    for row, line in zip(edge_rows, sorted(lines[i] for i in edge_rows)):
        lines[row] = line
    return "\n".join(lines)
