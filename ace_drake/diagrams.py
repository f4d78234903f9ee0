"""Diagram builders: the only place where systems are wired together.

Each builder returns a built Diagram whose systems have stable names (``AddNamedSystem``), so that
graphs and ``GetSubsystemByName`` lookups stay the same across runs. ``make_simulator`` configures
the integrator the way the BallPlant's contact timing needs.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    MakeRenderEngineVtk,
    Meshcat,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    RenderEngineVtkParams,
    Role,
    SceneGraph,
)
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import AddRandomInputs, ConstantValueSource, MatrixGain, TrajectorySource, VectorLogSink
from pydrake.systems.rendering import MultibodyPositionToGeometryPose
from pydrake.trajectories import PiecewisePolynomial, Trajectory

from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.params import ControlParams, RallyParams
from ace_drake.control.stack import ControlStack, make_control_stack
from ace_drake.perception.camera_segment import CameraSegment
from ace_drake.perception.cameras import load_cameras
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.contact import ResidualModel
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.racket_residual import residual_model
from ace_drake.play.umpire import Court
from ace_drake.robot.model import add_robot_to_plant, check_joint_order, load_scenario, racket_reach_box
from ace_drake.robot.params import RobotScenario
from ace_drake.systems.action_mapper import ActionMapper
from ace_drake.systems.aps_camera_array import ApsCameraArray, make_rgbd_sensor
from ace_drake.systems.ball_estimator import BallEstimator
from ace_drake.systems.ball_geometry import BallGeometry
from ace_drake.systems.ball_plant import BallPlant
from ace_drake.systems.ball_visualizer import BallVisualizer, set_court_view
from ace_drake.systems.delayed_joint_plant import DelayedJointPlant
from ace_drake.systems.gaze_spin_sensor import GazeSpinSensor
from ace_drake.systems.observation_builder import DEFAULT_SKILL, ObservationBuilder
from ace_drake.systems.policy_controller import PolicyController
from ace_drake.systems.random_seed import SEED_HOLD_PERIOD
from ace_drake.systems.reset_mpc import ResetMpc
from ace_drake.systems.robot_kinematics import RobotKinematics
from ace_drake.systems.safety_supervisor import SafetySupervisor
from ace_drake.systems.spline_qp import SplineQp
from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.robot.kinematics import RacketKinematics
from ace_drake.systems.segment.action_mapper import SegmentActionMapper
from ace_drake.systems.segment.ball_estimator import SegmentBallEstimator
from ace_drake.systems.segment.camera_array import SegmentCameraArray
from ace_drake.systems.segment.ball_plant import SegmentBallPlant
from ace_drake.systems.segment.clock import EpisodeClock
from ace_drake.systems.segment.end_effector import SegmentEndEffector
from ace_drake.systems.segment.joint_plant import SegmentJointPlant
from ace_drake.systems.segment.observation_builder import SegmentObservationBuilder
from ace_drake.systems.segment.policy_controller import SegmentPolicyController
from ace_drake.systems.segment.position_sensor import SegmentPositionSensor
from ace_drake.systems.segment.racket_kinematics import SegmentRacketKinematics
from ace_drake.systems.segment.reset_mpc import SegmentResetMpc
from ace_drake.systems.segment.safety_supervisor import SegmentSafetySupervisor
from ace_drake.systems.segment.spin_sensor import SegmentSpinSensor
from ace_drake.systems.segment.spline_qp import SegmentSplineQp
from ace_drake.systems.segment.umpire import SegmentUmpire
from ace_drake.systems.statistical_position_sensor import StatisticalPositionSensor
from ace_drake.systems.triangulator import Triangulator

TRIANGULATION_HISTORY = 32  # positions the triangulator keeps on its port (the Triangulator's default)
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


def add_random_sources(builder: DiagramBuilder) -> None:
    """Connects a RandomSource to every random input port left unconnected in ``builder`` (Drake's
    ``AddRandomInputs``; ports like ``systems.random_seed``'s) and names it after its port's
    system (``<system>_seed_source``), for stable graphs. Every builder here calls it before
    ``Build``, so that ``SetRandomContext`` seeds every stochastic system, one stream each
    (``start_rally``)."""
    named = {system.get_name() for system in builder.GetSystems()}
    AddRandomInputs(SEED_HOLD_PERIOD, builder)
    for (system, _), (source, _) in builder.connection_map().items():
        if source.get_name() not in named:  # a source AddRandomInputs just added
            source.set_name(f"{system.get_name()}_seed_source")


def add_ball(
    builder: DiagramBuilder,
    params: BallPhysicsParams,
    perturb: bool = False,
    seed: int = 0,
    racket_residual: ResidualModel | None = None,
    scenario: RobotScenario | None = None,
) -> BallPlant:
    """Adds the BallPlant as ``ball``; the shared first step of every builder. With the
    ``scenario`` of the robot whose racket it will meet, the ball knows the box the racket stays
    in (``robot.model.racket_reach_box``), which spares the racket witness most pose reads. The
    racket contact's residual network is ``racket_residual`` or else the one ``params.racket``
    selects (``racket_residual.residual_model``)."""
    reach = None if scenario is None else racket_reach_box(scenario)
    residual = racket_residual if racket_residual is not None else residual_model(params.racket)
    return builder.AddNamedSystem("ball", BallPlant(params, perturb=perturb, seed=seed, racket_residual=residual, racket_reach=reach))


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
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("ball_diagram")
    return diagram


@dataclasses.dataclass(frozen=True)
class PerceptionSystems:
    """The perception systems in a builder (``add_perception``): the position path's last system
    (``triangulator`` or ``position_sensor``), the spin sensor and the estimator; ``cameras`` is
    the ApsCameraArray, or None on the statistical path."""

    positions: object
    spin_sensor: GazeSpinSensor
    estimator: BallEstimator
    cameras: ApsCameraArray | None


def add_perception(builder: DiagramBuilder, ball: BallPlant, params: PerceptionParams, physics: BallPhysicsParams, scene_graph: SceneGraph | None = None) -> PerceptionSystems:
    """Adds what the robot perceives the ball through (DESIGN.md's wiring): the true ball state
    and contact events of ``ball`` feed either the nine frame cameras (``aps_cameras``, analytic
    or rendered) and the ``triangulator``, or the statistical ``position_sensor``; and the
    ``spin_sensor`` (the gaze-control system's statistical model); both measurement streams feed
    the ``ball_estimator`` (EKF on ``physics``). The rendered mode draws the ball
    (``ball_geometry``) into ``scene_graph`` (one with the court is made if None), gives it a VTK
    renderer and adds one RgbdSensor per camera (``camera_<name>``)."""
    spin = builder.AddNamedSystem("spin_sensor", GazeSpinSensor(params.spin, seed=params.seed))
    builder.Connect(ball.ball_state_port, spin.ball_state_port)
    builder.Connect(ball.contact_events_port, spin.contact_events_port)
    cameras = None
    if params.positions == "cameras":
        calibration = load_cameras(MODELS_DIR / params.camera.calibration)
        cameras = builder.AddNamedSystem("aps_cameras", ApsCameraArray(calibration, params.camera, seed=params.seed))
        builder.Connect(ball.ball_state_port, cameras.ball_state_port)
        if params.camera.mode == "rendered":
            _add_camera_renders(builder, ball, cameras, calibration, params, scene_graph)
        positions = builder.AddNamedSystem("triangulator", Triangulator(calibration, params.camera))
        builder.Connect(cameras.detections_port, positions.detections_port)
    else:
        positions = builder.AddNamedSystem("position_sensor", StatisticalPositionSensor(params.position, seed=params.seed))
        builder.Connect(ball.ball_state_port, positions.ball_state_port)
    estimator = builder.AddNamedSystem("ball_estimator", BallEstimator(params.estimator, physics))
    builder.Connect(positions.position_measurements_port, estimator.position_measurements_port)
    builder.Connect(spin.spin_measurements_port, estimator.spin_measurements_port)
    builder.Connect(ball.contact_events_port, estimator.contact_events_port)
    return PerceptionSystems(positions, spin, estimator, cameras)


def _add_camera_renders(builder, ball, cameras, calibration, params: PerceptionParams, scene_graph) -> None:
    """The rendered mode's scene: the ball's geometry, a renderer and one RgbdSensor per camera."""


    if scene_graph is None:
        court, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
        court.set_name("court")
        Parser(court).AddModels(str(MODELS_DIR / "table.sdf"))
        court.Finalize()
    renderer = "camera_renderer"
    if not scene_graph.HasRenderer(renderer):
        scene_graph.AddRenderer(renderer, MakeRenderEngineVtk(RenderEngineVtkParams()))
    geometry = builder.AddNamedSystem("ball_geometry", BallGeometry(scene_graph))
    builder.Connect(ball.ball_state_port, geometry.ball_state_port)
    builder.Connect(geometry.geometry_pose_port, scene_graph.get_source_pose_port(geometry.source_id))
    for camera in calibration:
        sensor = builder.AddNamedSystem(f"camera_{camera.name}", make_rgbd_sensor(camera, params.camera.render_scale, renderer, scene_graph.world_frame_id()))
        builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
        builder.Connect(sensor.color_image_output_port(), cameras.image_ports[camera.name])


def build_perception_diagram(
    params: PerceptionParams | None = None,
    physics: BallPhysicsParams | None = None,
    perturb: bool = True,
    meshcat: Meshcat | None = None,
) -> Diagram:
    """The ball seen by the robot's sensors: BallPlant (``ball``, post-bounce perturbations with
    ``perturb``) into ``add_perception``, with loggers of the truth (``ball_logger``, every 1 ms)
    and of the estimate (``estimate_logger``, 9, every 1 ms) and an optional Meshcat view of the
    true ball (``ball_visualizer``)."""
    params = params or PerceptionParams()
    physics = physics or BallPhysicsParams()
    builder = DiagramBuilder()
    ball = add_ball(builder, physics, perturb=perturb, seed=params.seed)
    perception = add_perception(builder, ball, params, physics)
    if meshcat is not None:
        visualizer = builder.AddNamedSystem("ball_visualizer", BallVisualizer(meshcat, physics))
        builder.Connect(ball.ball_state_port, visualizer.ball_state_port)
    truth = builder.AddNamedSystem("ball_logger", VectorLogSink(9, 1e-3))
    builder.Connect(ball.ball_state_port, truth.get_input_port())
    estimate = builder.AddNamedSystem("estimate_logger", VectorLogSink(9, 1e-3))
    builder.Connect(perception.estimator.ball_state_estimate_port, estimate.get_input_port())
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("perception_diagram")
    return diagram


@dataclasses.dataclass(frozen=True)
class RobotSystems:
    """The robot's systems in a builder (``add_robot``): the kinematics-only plant (not itself a
    system of the diagram), the SceneGraph it is registered with, the joints and the kinematics."""

    plant: MultibodyPlant
    scene_graph: SceneGraph
    joint_plant: DelayedJointPlant
    kinematics: RobotKinematics


def add_robot(builder: DiagramBuilder, scenario: RobotScenario, meshcat: Meshcat | None = None) -> RobotSystems:
    """Adds the robot's sub-diagram: ``joint_plant`` (DelayedJointPlant, paper eq. (9)) driving
    ``robot_kinematics`` (racket pose and velocity, end-effector state) and, through
    ``robot_geometry_pose``, the robot's geometry in ``scene_graph`` (court included), drawn in
    Meshcat when ``meshcat`` is given. The joints' ``q_command`` input is left for the caller.

    The MultibodyPlant is kinematics only: it is not added to the diagram (it would integrate its
    own dynamics); the joint plant's positions pose its geometry instead.
    """
    scene_graph = builder.AddNamedSystem("scene_graph", SceneGraph())
    plant = MultibodyPlant(time_step=0.0)
    plant.RegisterAsSourceForSceneGraph(scene_graph)
    robot = add_robot_to_plant(plant, scenario)
    plant.Finalize()
    check_joint_order(plant, robot)
    joint_plant = builder.AddNamedSystem("joint_plant", DelayedJointPlant(scenario.dynamics))
    kinematics = builder.AddNamedSystem("robot_kinematics", RobotKinematics(plant))
    geometry_pose = builder.AddNamedSystem("robot_geometry_pose", MultibodyPositionToGeometryPose(plant))
    builder.Connect(joint_plant.joint_state_port, kinematics.joint_state_port)
    builder.Connect(joint_plant.q_port, geometry_pose.get_input_port())
    builder.Connect(geometry_pose.get_output_port(), scene_graph.get_source_pose_port(plant.get_source_id()))
    if meshcat is not None:
        set_court_view(meshcat)
        MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration, publish_period=0.01)
        )
    return RobotSystems(plant, scene_graph, joint_plant, kinematics)


@dataclasses.dataclass(frozen=True)
class RobotView:
    """A diagram that only draws the robot and the court in Meshcat (``build_robot_view_diagram``):
    pose the robot with ``plant.SetPositions`` in its context, then ``visualizer.ForcedPublish``."""

    diagram: Diagram
    plant: MultibodyPlant
    visualizer: MeshcatVisualizer


def build_robot_view_diagram(scenario: RobotScenario, meshcat: Meshcat) -> RobotView:
    """The robot of ``scenario`` with the court, in a MultibodyPlant and SceneGraph drawn by a
    MeshcatVisualizer (illustration geometry) into ``meshcat``: for replays that set the joint
    positions frame by frame (``analysis.match_replay``). No dynamics run in it."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
    robot = add_robot_to_plant(plant, scenario)
    plant.Finalize()
    check_joint_order(plant, robot)
    visualizer = MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration))
    diagram = builder.Build()
    diagram.set_name("robot_view_diagram")
    return RobotView(diagram, plant, visualizer)


def build_swing_diagram(
    command: Trajectory,
    scenario: RobotScenario | None = None,
    params: BallPhysicsParams | None = None,
    meshcat: Meshcat | None = None,
    log_period: float = 0.0,
) -> Diagram:
    """The robot playing a scripted joint command at the ball: ``command_source`` (the
    trajectory q*(t), m and rad, sampled by the joints at 1 kHz) drives the robot of ``add_robot``,
    whose racket is the BallPlant's racket. Loggers: ``ball_logger`` (ball state) and
    ``joint_logger`` (joint state), every step when ``log_period`` is 0."""
    scenario = scenario or load_scenario()
    params = params or BallPhysicsParams()
    if command.rows() != 8 or command.cols() != 1:
        raise ValueError(f"build_swing_diagram: command must be an 8 x 1 trajectory, got {command.rows()} x {command.cols()}")
    builder = DiagramBuilder()
    ball = add_ball(builder, params, scenario=scenario)
    robot = add_robot(builder, scenario, meshcat)
    source = builder.AddNamedSystem("command_source", TrajectorySource(command))
    builder.Connect(source.get_output_port(), robot.joint_plant.q_command_port)
    builder.Connect(robot.kinematics.racket_pose_port, ball.racket_pose_port)
    builder.Connect(robot.kinematics.racket_velocity_port, ball.racket_velocity_port)
    if meshcat is not None:
        visualizer = builder.AddNamedSystem("ball_visualizer", BallVisualizer(meshcat, params, draw_scene=False))
        builder.Connect(ball.ball_state_port, visualizer.ball_state_port)
    ball_logger = builder.AddNamedSystem("ball_logger", VectorLogSink(9, log_period))
    builder.Connect(ball.ball_state_port, ball_logger.get_input_port())
    joint_logger = builder.AddNamedSystem("joint_logger", VectorLogSink(16, log_period))
    builder.Connect(robot.joint_plant.joint_state_port, joint_logger.get_input_port())
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("robot_swing_diagram")
    return diagram


@dataclasses.dataclass(frozen=True)
class ControlSystems:
    """The control stack's systems in a builder (``add_control_stack``)."""

    stack: ControlStack
    policy_controller: PolicyController
    action_mapper: ActionMapper
    spline_qp: SplineQp
    reset_mpc: ResetMpc
    supervisor: SafetySupervisor


def add_control_stack(builder: DiagramBuilder, robot: RobotSystems, stack: ControlStack, policy, observation_size: int) -> ControlSystems:
    """Adds the rally control stack (paper, Fig. 1c) in front of the robot's joints:
    ``policy_controller`` (every 32 ms) -> ``action_mapper`` (eq. (12)) -> ``spline_qp`` ->
    ``reset_mpc`` -> ``safety_supervisor`` -> the joints' q_command. The supervisor's
    segment_start_state feeds the mapper and the QP; its ``light_curtain`` input and the policy's
    ``observation`` input are left for the caller."""
    period = stack.period
    policy_controller = builder.AddNamedSystem("policy_controller", PolicyController(policy, observation_size, stack.control, period))
    mapper = builder.AddNamedSystem("action_mapper", ActionMapper(stack))
    qp = builder.AddNamedSystem("spline_qp", SplineQp(stack))
    reset = builder.AddNamedSystem("reset_mpc", ResetMpc(stack))
    supervisor = builder.AddNamedSystem("safety_supervisor", SafetySupervisor(stack))
    builder.Connect(policy_controller.action_port, mapper.action_port)
    builder.Connect(policy_controller.action_valid_port, mapper.action_valid_port)
    builder.Connect(supervisor.segment_start_state_port, mapper.segment_start_state_port)
    builder.Connect(supervisor.segment_start_state_port, qp.segment_start_state_port)
    builder.Connect(mapper.target_port, qp.target_port)
    builder.Connect(qp.segment_port, reset.segment_port)
    builder.Connect(qp.segment_port, supervisor.segment_port)
    builder.Connect(reset.reset_port, supervisor.reset_port)
    builder.Connect(supervisor.q_command_port, robot.joint_plant.q_command_port)
    return ControlSystems(stack, policy_controller, mapper, qp, reset, supervisor)


def build_controlled_robot_diagram(
    policy,
    scenario: RobotScenario | None = None,
    control: ControlParams | None = None,
    meshcat: Meshcat | None = None,
    check_collisions: bool = True,
    log_period: float = 0.001,
) -> Diagram:
    """The robot under the rally control stack with no ball: ``add_robot`` + ``add_control_stack``,
    the policy observing the robot state where its next segment starts (the supervisor's
    segment_start_state, 24 values; the rally diagram adds the ball's sensor histories), the
    light curtain as the diagram's input port ``light_curtain``, and loggers of the commanded
    state (``command_logger``, [q, v, a]) and the joints (``joint_logger``, [q, v]) every
    ``log_period`` s. Initialise an episode with ``start_controlled_robot``."""
    scenario = scenario or load_scenario()
    control = control or ControlParams()
    builder = DiagramBuilder()
    robot = add_robot(builder, scenario, meshcat)
    stack = make_control_stack(scenario, control, check_collisions)
    systems = add_control_stack(builder, robot, stack, policy, observation_size=24)
    builder.Connect(systems.supervisor.segment_start_state_port, systems.policy_controller.observation_port)
    builder.ExportInput(systems.supervisor.light_curtain_port, "light_curtain")
    command_logger = builder.AddNamedSystem("command_logger", VectorLogSink(24, log_period))
    builder.Connect(systems.supervisor.commanded_state_port, command_logger.get_input_port())
    joint_logger = builder.AddNamedSystem("joint_logger", VectorLogSink(16, log_period))
    builder.Connect(robot.joint_plant.joint_state_port, joint_logger.get_input_port())
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("controlled_robot_diagram")
    return diagram


def start_controlled_robot(diagram: Diagram, context, q=None, light_curtain: float = 0.0) -> None:
    """Sets an episode's start in ``context``: the joints at rest at q (default: the reset pose)
    with the supervisor's plan to stand there, and the light curtain input fixed at its value."""
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    joint_plant = diagram.GetSubsystemByName("joint_plant")
    q = np.asarray(supervisor.stack.reset_pose if q is None else q, dtype=float)
    supervisor.Initialize(supervisor.GetMyMutableContextFromRoot(context), q)
    joint_plant.SetJointState(joint_plant.GetMyMutableContextFromRoot(context), q)
    diagram.GetInputPort("light_curtain").FixValue(context, [light_curtain])


@dataclasses.dataclass(frozen=True)
class RallySystems:
    """The rally's systems in a builder (``add_rally``)."""

    ball: BallPlant
    robot: RobotSystems
    perception: PerceptionSystems
    control: ControlSystems
    observation: ObservationBuilder


def add_rally(builder: DiagramBuilder, params: RallyParams, policy, meshcat: Meshcat | None = None) -> RallySystems:
    """The one wiring of a rally episode (DESIGN.md's diagram), shared by the rally, training and
    analysis builders: the ``ball`` (BallPlant) whose racket is the robot's (``add_robot``); the
    robot's perception of it (``add_perception``: positions, spins, ``ball_estimator``); the
    ``observation_builder`` (paper, *States*) reading the sensors' histories, the estimate, and the
    robot where its next segment starts (the supervisor's segment_start_state, and its racket state
    from ``planned_kinematics``); the control stack (``add_control_stack``) calling ``policy`` on
    that observation every 32 ms, or, when ``policy`` is None, reading each action from the
    diagram's input ``action_request`` (17: action, valid flag; ``PolicyController``). The light
    curtain is the diagram's input ``light_curtain``; ``meshcat`` draws the robot, the court and
    the ball."""
    scenario = load_scenario(MODELS_DIR / params.scenario)
    ball = add_ball(builder, params.physics, perturb=params.perturb, seed=params.seed, scenario=scenario)
    robot = add_robot(builder, scenario, meshcat)
    builder.Connect(robot.kinematics.racket_pose_port, ball.racket_pose_port)
    builder.Connect(robot.kinematics.racket_velocity_port, ball.racket_velocity_port)
    perception = add_perception(builder, ball, params.perception, params.physics, scene_graph=robot.scene_graph)
    layout = ObservationLayout(params.position_history, params.spin_history)
    control = add_control_stack(builder, robot, make_control_stack(scenario, params.control), policy, layout.size)
    predictor = HitPredictor.for_robot(scenario, params.control, params.physics) if params.hit_prediction else None
    observation = builder.AddNamedSystem("observation_builder", ObservationBuilder(layout, predictor=predictor, hit_memory=params.hit_memory))
    joints = robot.joint_plant.q_port.size()
    # [q, v] of the planned [q, v, a] (a selection matrix: Drake's C++ MatrixGain).
    select = builder.AddNamedSystem("planned_joint_state", MatrixGain(np.eye(2 * joints, 3 * joints)))
    planned = builder.AddNamedSystem("planned_kinematics", RobotKinematics(robot.plant))
    builder.Connect(control.supervisor.segment_start_state_port, select.get_input_port())
    builder.Connect(select.get_output_port(), planned.joint_state_port)
    builder.Connect(perception.positions.position_measurements_port, observation.position_measurements_port)
    builder.Connect(perception.spin_sensor.spin_measurements_port, observation.spin_measurements_port)
    builder.Connect(control.supervisor.segment_start_state_port, observation.robot_state_port)
    builder.Connect(planned.end_effector_state_port, observation.end_effector_state_port)
    builder.Connect(perception.estimator.ball_state_estimate_port, observation.ball_state_estimate_port)
    builder.Connect(perception.estimator.estimate_status_port, observation.estimate_status_port)
    builder.Connect(observation.observation_port, control.policy_controller.observation_port)
    builder.ExportInput(control.supervisor.light_curtain_port, "light_curtain")
    if policy is None:
        builder.ExportInput(control.policy_controller.action_request_port, "action_request")
    if meshcat is not None:
        visualizer = builder.AddNamedSystem("ball_visualizer", BallVisualizer(meshcat, params.physics, draw_scene=False))
        builder.Connect(ball.ball_state_port, visualizer.ball_state_port)
    return RallySystems(ball, robot, perception, control, observation)


def build_rally_diagram(params: RallyParams | None = None, policy=None, meshcat: Meshcat | None = None, log_period: float = 0.002) -> Diagram:
    """The rally episode of ``add_rally`` with loggers of the true ball (``ball_logger``, 9) and
    the joints (``joint_logger``, [q, v] 16) every ``log_period`` s, for evaluation and replays.
    ``policy``: a callable observation -> action | None or a torch module (None: a policy that
    never acts, for graphs). Start each episode with ``start_rally``."""
    params = params or RallyParams()
    builder = DiagramBuilder()
    systems = add_rally(builder, params, policy if policy is not None else (lambda observation: None), meshcat)
    ball_logger = builder.AddNamedSystem("ball_logger", VectorLogSink(9, log_period))
    builder.Connect(systems.ball.ball_state_port, ball_logger.get_input_port())
    joint_logger = builder.AddNamedSystem("joint_logger", VectorLogSink(16, log_period))
    builder.Connect(systems.robot.joint_plant.joint_state_port, joint_logger.get_input_port())
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("rally_diagram")
    return diagram


def build_training_diagram(params: RallyParams | None = None) -> Diagram:
    """The rally episode of ``add_rally`` for RL training (``training.env``): no loggers, no
    Meshcat, and the action from the diagram's input ``action_request`` (17: action, valid flag)
    read at each policy event. ``params`` default: RallyParams with the training sensors
    (``PerceptionParams(positions="statistical")``); given params are used as they are. Start each
    episode with ``start_rally`` and fix ``action_request`` before advancing."""
    params = params or RallyParams(perception=PerceptionParams(positions="statistical"))
    builder = DiagramBuilder()
    add_rally(builder, params, None)
    add_random_sources(builder)
    diagram = builder.Build()
    diagram.set_name("training_diagram")
    return diagram


def start_rally(diagram: Diagram, context, shot, seed: int = 0, skill=None, q=None, light_curtain: float = 0.0) -> None:
    """Starts an episode in ``context`` at its current time: the context's state and parameters
    drawn by Drake's random context from ``seed`` (``SetRandomContext(context,
    RandomGenerator(seed))``: every stochastic system, ball perturbations and sensors alike, gets
    its own stream, ``add_random_sources``; everything else takes its default), the policy told
    that an episode starts (``PolicyController.ResetPolicy``), the ball in the state ``shot``
    ([p (m), v (m/s), w (rad/s)], just after the opponent's hit), the skill [y_desired, w_p, w_s]
    (default: the ObservationBuilder's), and the robot at rest at q (default: the reset pose; see
    ``start_controlled_robot``). Reuse one context per Simulator; its time is kept."""
    # First: SetRandomContext resets every state and parameter, so what follows must come after.
    diagram.SetRandomContext(context, RandomGenerator(int(seed)))
    # The one place an episode's start reaches the policy's own memory (the model-based
    # returner's plan): the policy is a plain callable that the runner, the CLI and the tests all
    # hand in, so its memory cannot live in the Context; every episode starts here instead.
    if diagram.HasSubsystemNamed("policy_controller"):
        controller = diagram.GetSubsystemByName("policy_controller")
        controller.ResetPolicy(controller.GetMyContextFromRoot(context))
    ball = diagram.GetSubsystemByName("ball")
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), np.asarray(shot, dtype=float))
    if skill is not None:
        observation = diagram.GetSubsystemByName("observation_builder")
        observation.SetSkill(observation.GetMyMutableContextFromRoot(context), skill)
    start_controlled_robot(diagram, context, q, light_curtain)


@dataclasses.dataclass(frozen=True)
class SegmentRallySystems:
    """The segment-stepped rally's systems in a builder (``add_segment_rally``)."""

    batch: int
    timing: SegmentTiming
    clock: EpisodeClock
    ball: SegmentBallPlant
    joint_plant: SegmentJointPlant
    kinematics: SegmentRacketKinematics
    position_sensor: SegmentPositionSensor
    spin_sensor: SegmentSpinSensor
    estimator: SegmentBallEstimator
    observation: SegmentObservationBuilder
    policy_controller: SegmentPolicyController
    supervisor: SegmentSafetySupervisor
    umpire: SegmentUmpire
    stack: ControlStack


def add_segment_rally(builder: DiagramBuilder, params: RallyParams, policy, batch: int = 1) -> SegmentRallySystems:
    """The rally episode of ``add_rally`` for B = ``batch`` environments, segment-stepped
    (``params.stepping`` "segment"; docs/architecture.md, *Segment stepping*): the same systems
    under the same names, each carrying B environments and advancing once per 32 ms tick, plus
    the ``episode_clock`` they share; the position path is the statistical sensor
    (``position_sensor``) or the analytic cameras with their triangulation in one system
    (``aps_cameras``). Inputs: ``light_curtain`` (abstract float (B,)) and, when
    ``policy`` is None, ``action_request`` (abstract float (B, 17)). Start episodes with
    ``start_segment_episodes``."""
    if params.perception.positions == "cameras" and params.perception.camera.mode != "analytic":
        raise ValueError(f"add_segment_rally: the segment-stepped cameras are analytic only, got mode {params.perception.camera.mode!r} (rendered: the continuous-time diagram)")
    if batch < 1:
        raise ValueError(f"add_segment_rally: batch must be >= 1, got {batch}")
    scenario = load_scenario(MODELS_DIR / params.scenario)
    stack = make_control_stack(scenario, params.control)
    timing = SegmentTiming.from_control(params.control.segment_samples, params.control.observation_lead, stack.period)
    kinematics = RacketKinematics.for_scenario(scenario)
    layout = ObservationLayout(params.position_history, params.spin_history)
    predictor = HitPredictor.for_robot(scenario, params.control, params.physics) if params.hit_prediction else None
    add = builder.AddNamedSystem
    clock = add("episode_clock", EpisodeClock(batch, timing))
    ball = add("ball", SegmentBallPlant(params.physics, batch, timing, perturb=params.perturb,
                                         racket_residual=residual_model(params.physics.racket)))
    joints = add("joint_plant", SegmentJointPlant(scenario.dynamics, batch, timing))
    racket = add("robot_kinematics", SegmentRacketKinematics(kinematics))
    if params.perception.positions == "cameras":
        cameras = CameraSegment(load_cameras(MODELS_DIR / params.perception.camera.calibration), params.perception.camera)
        positions = add("aps_cameras", SegmentCameraArray(cameras, TRIANGULATION_HISTORY, batch, timing))
    else:
        positions = add("position_sensor", SegmentPositionSensor(params.perception.position, batch, timing))
    spins = add("spin_sensor", SegmentSpinSensor(params.perception.spin, batch, timing))
    estimator = add("ball_estimator", SegmentBallEstimator(params.perception.estimator, params.physics, batch, timing))
    observation = add("observation_builder", SegmentObservationBuilder(layout, batch, timing, predictor, params.hit_memory))
    planned = add("planned_kinematics", SegmentEndEffector(kinematics, batch))
    controller = add("policy_controller", SegmentPolicyController(policy, batch, layout.size, timing))
    mapper = add("action_mapper", SegmentActionMapper(stack, batch))
    qp = add("spline_qp", SegmentSplineQp(stack, batch))
    reset = add("reset_mpc", SegmentResetMpc(stack, batch))
    supervisor = add("safety_supervisor", SegmentSafetySupervisor(stack, batch, timing))
    umpire = add("umpire", SegmentUmpire(batch, timing.duration, Court.from_physics(params.physics)))
    connect = builder.Connect
    connect(ball.ball_flight_port, umpire.ball_flight_port)
    for system in (ball, positions, spins, estimator, observation, controller, supervisor):
        connect(clock.episode_ticks_port, system.episode_ticks_port)
    connect(supervisor.command_stream_port, joints.command_stream_port)
    connect(joints.joint_motion_port, racket.joint_motion_port)
    connect(racket.racket_motion_port, ball.racket_motion_port)
    connect(ball.ball_flight_port, positions.ball_flight_port)
    connect(ball.ball_flight_port, spins.ball_flight_port)
    connect(ball.contact_events_port, estimator.contact_events_port)
    connect(positions.position_measurements_port, estimator.position_measurements_port)
    connect(spins.spin_measurements_port, estimator.spin_measurements_port)
    connect(positions.position_measurements_port, observation.position_measurements_port)
    connect(spins.spin_measurements_port, observation.spin_measurements_port)
    connect(supervisor.segment_start_state_port, observation.robot_state_port)
    connect(supervisor.segment_start_state_port, planned.joint_state_port)
    connect(planned.end_effector_state_port, observation.end_effector_state_port)
    connect(estimator.ball_state_estimate_port, observation.ball_state_estimate_port)
    connect(estimator.estimate_status_port, observation.estimate_status_port)
    connect(observation.observation_port, controller.observation_port)
    connect(controller.action_port, mapper.action_port)
    connect(supervisor.segment_start_state_port, mapper.segment_start_state_port)
    connect(supervisor.segment_start_state_port, qp.segment_start_state_port)
    connect(mapper.target_port, qp.target_port)
    connect(qp.segment_port, reset.segment_port)
    connect(qp.segment_port, supervisor.segment_port)
    connect(reset.reset_port, supervisor.reset_port)
    builder.ExportInput(supervisor.light_curtain_port, "light_curtain")
    if policy is None:
        builder.ExportInput(controller.action_request_port, "action_request")
    return SegmentRallySystems(batch, timing, clock, ball, joints, racket, positions, spins, estimator, observation, controller, supervisor, umpire, stack)


def build_segment_rally_diagram(params: RallyParams | None = None, policy=None, batch: int = 1) -> Diagram:
    """The segment-stepped rally of ``add_segment_rally`` for ``batch`` environments: the
    training, evaluation and benchmark diagram. ``params`` default: RallyParams with the
    statistical position sensor and ``stepping="segment"``; ``policy`` None reads the actions from
    the ``action_request`` input. Start episodes with ``start_segment_episodes``; simulate with
    a plain ``Simulator`` (``make_segment_simulator``)."""
    params = params or RallyParams(perception=PerceptionParams(positions="statistical"), stepping="segment")
    builder = DiagramBuilder()
    add_segment_rally(builder, params, policy, batch)
    diagram = builder.Build()
    diagram.set_name("segment_rally_diagram")
    return diagram


def make_segment_simulator(diagram: Diagram, context=None) -> Simulator:
    """A Simulator for a segment-stepped diagram: no continuous state, so no integrator settings;
    it jumps from tick to tick."""
    return Simulator(diagram, context or diagram.CreateDefaultContext())


SEED_STREAMS = {"ball": 1, "position_sensor": 2, "spin_sensor": 3, "aps_cameras": 4}  # per-system streams of an episode's seed


def system_seeds(seeds, stream: int) -> np.ndarray:
    """Each episode seed's (k,) stream ``stream`` for one stochastic system: distinct, reproducible
    int64 seeds (``numpy.random.SeedSequence([seed, stream])``)."""
    return np.array([np.random.SeedSequence([int(seed), stream]).generate_state(1, np.uint32)[0] for seed in np.asarray(seeds).reshape(-1)], dtype=np.int64)


def start_segment_episodes(diagram: Diagram, context, rows, shots, seeds, skills=None, q=None, v=None, a=None, planned=None,
                           continuing: bool = False) -> None:
    """Starts episodes in environments ``rows`` (k,) of a segment-stepped diagram: balls in states
    ``shots`` (k, 9) [p (m), v (m/s), w (rad/s)] (just after the opponent's hit), each episode's
    stochastic systems seeded from ``seeds`` (k,) (one stream per system, ``system_seeds``), the
    skills (k, 3) (default: the builder's), the robots at q (k, 8) (default: the reset pose) with
    v, a (k, 8) (default rest; a moving start follows the reset from there), the episode clocks
    at tick 0 and the policies told (``SegmentPolicyController.ResetPolicies``). The next tick is
    each episode's first (``control.segment_timing``); the other environments go on.

    ``planned`` (k,) of ``control.serve_execution.PlannedStart`` or None: those robots start
    part-way along that plan (a serve), which the supervisor keeps through its hold.
    ``continuing``: the robots go on as they are (the next shot of a rally: their joints and
    committed plans untouched, the plans re-timed to the new episodes); q, v, a and planned must
    then be None."""
    rows = np.asarray(rows, dtype=int).reshape(-1)
    seeds = np.asarray(seeds).reshape(-1)
    if seeds.size != rows.size:
        raise ValueError(f"start_segment_episodes: {rows.size} rows but {seeds.size} seeds")
    if planned is not None and len(planned) != rows.size:
        raise ValueError(f"start_segment_episodes: {rows.size} rows but {len(planned)} planned starts")
    if continuing and not (q is None and v is None and a is None and planned is None):
        raise ValueError("start_segment_episodes: continuing robots take no q, v, a or planned start")

    def sub(name):
        system = diagram.GetSubsystemByName(name)
        return system, system.GetMyMutableContextFromRoot(context)

    supervisor, supervisor_context = sub("safety_supervisor")
    if q is None:
        q = np.tile(supervisor.stack.reset_pose, (rows.size, 1))
    q = np.asarray(q, dtype=float).reshape(rows.size, -1)
    estimator, estimator_context = sub("ball_estimator")
    estimator.StartEpisodes(estimator_context, rows)  # first: it stores the other rows' cached fusion
    clock, clock_context = sub("episode_clock")
    shifts = supervisor.timing.boundary_sample(clock.ticks(clock_context)[rows])  # the old episodes' samples at the new time 0
    clock.StartEpisodes(clock_context, rows)
    ball, ball_context = sub("ball")
    ball.StartEpisodes(ball_context, rows, shots, system_seeds(seeds, SEED_STREAMS["ball"]))
    for name in ("position_sensor", "aps_cameras", "spin_sensor"):
        if not diagram.HasSubsystemNamed(name):
            continue
        system, system_context = sub(name)
        system.StartEpisodes(system_context, rows, system_seeds(seeds, SEED_STREAMS[name]))
    observation, observation_context = sub("observation_builder")
    observation.SetSkills(observation_context, rows, np.tile(DEFAULT_SKILL, (rows.size, 1)) if skills is None else skills)
    if continuing:
        supervisor.ContinueEpisodes(supervisor_context, rows, shifts)
    else:
        supervisor.StartEpisodes(supervisor_context, rows, q, v, a, planned)
        joints, joints_context = sub("joint_plant")
        joints.StartEpisodes(joints_context, rows, q, v, planned)
    controller, controller_context = sub("policy_controller")
    controller.StartEpisodes(controller_context, rows)
    controller.ResetPolicies(rows, seeds)


def _documented_ball_diagram() -> Diagram:
    """The ball diagram as documented: with a (static) racket connected, no Meshcat."""
    return build_ball_diagram(racket=StaticRacket(RigidTransform()))


def _documented_swing_diagram() -> Diagram:
    """The swing diagram as documented: the robot holding its ready pose, no Meshcat."""
    ready = np.asarray(load_scenario().ready_pose, dtype=float)[:, None]
    return build_swing_diagram(PiecewisePolynomial(ready))


def _documented_controlled_robot_diagram() -> Diagram:
    """The controlled robot as documented: a policy that never acts, collision checking on."""
    return build_controlled_robot_diagram(lambda observation: None)


# name -> builder of the diagram whose graph ``ace-drake diagrams`` renders into diagrams/.
DOCUMENTED_DIAGRAMS = {
    "ball_diagram": _documented_ball_diagram,
    "perception_diagram": build_perception_diagram,
    "robot_swing_diagram": _documented_swing_diagram,
    "controlled_robot_diagram": _documented_controlled_robot_diagram,
    "rally_diagram": build_rally_diagram,
    "training_diagram": build_training_diagram,
    "segment_rally_diagram": build_segment_rally_diagram,
}


def graphviz_dot(diagram: Diagram, max_depth: int = 1) -> str:
    """The diagram's Graphviz DOT text, normalised so that the same wiring always gives the same
    text: system ids renumbered from 0 in order of first appearance (Drake's ids are global
    counters that depend on what else the process built; SceneGraph's source ports likewise) and
    the edge lines sorted (Drake emits them in an order that can change between processes)."""

    dot = diagram.GetGraphvizString(max_depth=max_depth)
    numbering: dict[str, str] = {}

    def renumber(match: re.Match) -> str:
        number = numbering.setdefault(match.group(2), str(len(numbering)))
        return match.group(1) + number

    dot = re.sub(r"\b(digraph _|clusters|cluster|s)(\d+)", renumber, dot)
    # SceneGraph names its per-source input ports after global source ids: renumber those too.
    sources: dict[str, str] = {}
    dot = re.sub(r"\bSource_(\d+)_", lambda m: f"Source_{sources.setdefault(m.group(1), str(len(sources)))}_", dot)
    lines = dot.split("\n")
    edge_rows = [i for i, line in enumerate(lines) if " -> " in line]
    for row, line in zip(edge_rows, sorted(lines[i] for i in edge_rows)):
        lines[row] = line
    return "\n".join(lines)
