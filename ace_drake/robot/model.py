"""The robot's MultibodyPlant: loading a scenario, its limits, racket kinematics, inverse kinematics.

One place builds the robot (``add_robot_to_plant``) for every use: the simulation diagrams (a
kinematics-only plant registered with the diagram's SceneGraph for Meshcat, driven by
``RobotKinematics``), and ``RobotModel``, a self-contained plant with its own SceneGraph for
analysis (reach, inverse kinematics, collision queries). The plant's position vector is in
``JOINT_NAMES`` order; velocities likewise.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable, ModelInstanceIndex
from pydrake.planning import RobotDiagramBuilder
from pydrake.solvers import Solve

from ace_drake.config import MODELS_DIR, ConfigError, load_config
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.robot.params import JOINT_NAMES, Pose, RobotScenario, scenario_record

DEFAULT_SCENARIO = MODELS_DIR / "scenario.yaml"
ROBOT_MODEL_NAME = "ace_robot"
RACKET_FRAME = "racket_blade"  # origin at the blade centre, z along the forehand normal
BALL_CUP_FRAME = "ball_cup"


def load_scenario(path: str | Path | None = None) -> RobotScenario:
    """The robot scenario from the ``robot`` section of a scenario YAML (default models/scenario.yaml)."""
    return load_config(RobotScenario, path or DEFAULT_SCENARIO, section="robot")


def scenario_file_record(name: str) -> dict:
    """The robot record (``params.scenario_record``) of the scenario file ``name`` in models/:
    what a checkpoint or a policy's sidecar records of the robot it was trained for."""
    return scenario_record(load_scenario(MODELS_DIR / name))


def pose_to_transform(pose: Pose) -> RigidTransform:
    """The RigidTransform of a config Pose (xyz in m, roll-pitch-yaw in degrees)."""
    return RigidTransform(RollPitchYaw(np.radians(pose.rpy_deg)), np.asarray(pose.xyz, dtype=float))


def add_robot_to_plant(plant: MultibodyPlant, scenario: RobotScenario, models_dir: str | Path = MODELS_DIR) -> ModelInstanceIndex:
    """Adds the court and the robot of ``scenario`` to an unfinalized ``plant``: parses both model
    files (paths relative to ``models_dir``), welds the robot's base at ``scenario.base_pose`` and
    sets every joint's position, velocity and acceleration limits from ``scenario.limits``.
    Returns the robot's model instance."""
    models_dir = Path(models_dir)
    paths = [models_dir / scenario.court_model, models_dir / scenario.robot_model]
    for path in paths:
        if not path.is_file():
            raise ConfigError(f"model file not found: {path}")
    parser = Parser(plant)
    parser.AddModels(str(paths[0]))
    (robot,) = parser.AddModels(str(paths[1]))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("base", robot), pose_to_transform(scenario.base_pose))
    for name in JOINT_NAMES:
        joint = plant.GetJointByName(name, robot)
        limits = getattr(scenario.limits, name)
        joint.set_position_limits([limits.lower], [limits.upper])
        joint.set_velocity_limits([-limits.velocity], [limits.velocity])
        joint.set_acceleration_limits([-limits.acceleration], [limits.acceleration])
    return robot


def check_joint_order(plant: MultibodyPlant, robot: ModelInstanceIndex) -> None:
    """Raises unless the finalized plant's positions and velocities are the joints in JOINT_NAMES
    order (every diagram relies on it)."""
    starts = [plant.GetJointByName(name, robot).position_start() for name in JOINT_NAMES]
    if starts != list(range(len(JOINT_NAMES))) or plant.num_positions() != len(JOINT_NAMES):
        raise ConfigError(f"robot model: expected the plant's positions to be {JOINT_NAMES} in order, got starts {starts}")


def racket_reach_box(scenario: RobotScenario, models_dir: str | Path = MODELS_DIR) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box (lower, upper corners (3,), m, world) that contains the racket frame's
    origin in every configuration within the scenario's joint limits: a sound bound, not a tight
    one, for whoever must know where the racket cannot be (the BallPlant's racket witness).

    Walking from the racket frame towards the world, every joint is revolute or fixed until the
    first prismatic one (the gantry). A revolute or fixed joint keeps the origins of its frames F
    (on the parent P) and M (on the child C) together, so each moves the next body's origin by at
    most |p_PF| + |p_CM|; the innermost revolute joint's F is fixed on the carriage (the body the
    last prismatic joint moves), so the racket frame's origin lies within L = |p_BR| + the sum of
    the others' of that point, the pivot. The carriage only translates, so the pivot is affine in
    the prismatic joints' positions and spans the box of its positions at the corners of their
    limits; the result is that box padded by L on every side. Raises ValueError for a robot not
    built that way.
    """
    plant = MultibodyPlant(time_step=0.0)
    robot = add_robot_to_plant(plant, scenario, models_dir)
    plant.Finalize()
    racket = plant.GetFrameByName(RACKET_FRAME, robot)
    joint_of_child = {plant.get_joint(index).child_body().index(): plant.get_joint(index) for index in plant.GetJointIndices()}
    reach = float(np.linalg.norm(racket.GetFixedPoseInBodyFrame().translation()))
    body, pivot_frame = racket.body(), None
    while body.index() in joint_of_child and joint_of_child[body.index()].type_name() != "prismatic":
        joint = joint_of_child[body.index()]
        if joint.type_name() not in ("revolute", "weld"):
            raise ValueError(f"racket_reach_box: joint {joint.name()} is {joint.type_name()}; expected revolute, weld or prismatic")
        if pivot_frame is not None:
            reach += float(np.linalg.norm(pivot_frame.GetFixedPoseInBodyFrame().translation()))
        reach += float(np.linalg.norm(joint.frame_on_child().GetFixedPoseInBodyFrame().translation()))
        pivot_frame, body = joint.frame_on_parent(), joint.parent_body()
    if pivot_frame is None:
        raise ValueError("racket_reach_box: no revolute or fixed joint between the racket and the gantry")
    prismatic, inboard = [], body
    while inboard.index() in joint_of_child:
        joint = joint_of_child[inboard.index()]
        if joint.type_name() == "prismatic":
            prismatic.append(joint)
        elif joint.type_name() != "weld":
            raise ValueError(f"racket_reach_box: joint {joint.name()} ({joint.type_name()}) lies inboard of the gantry")
        inboard = joint.parent_body()
    context = plant.CreateDefaultContext()
    pivots = []
    for corner in np.ndindex(*(2,) * len(prismatic)):
        for joint, end in zip(prismatic, corner):
            joint.set_translation(context, (joint.position_lower_limits() if end == 0 else joint.position_upper_limits())[0])
        pivots.append(pivot_frame.CalcPoseInWorld(context).translation())
    pivots = np.array(pivots)
    return pivots.min(axis=0) - reach, pivots.max(axis=0) + reach


class RobotModel:
    """The robot and court in a MultibodyPlant with its own SceneGraph, for analysis.

    Kinematics only (nothing here is simulated): racket pose, spatial velocity and Jacobian,
    collision queries and inverse kinematics. Joint vectors q (8,) are in JOINT_NAMES order,
    m and rad; v (8,) in m/s and rad/s.
    """

    def __init__(self, scenario: RobotScenario | None = None, models_dir: str | Path = MODELS_DIR):
        self.scenario = scenario or load_scenario()
        builder = RobotDiagramBuilder(time_step=0.0)
        self.plant = builder.plant()
        self.robot = add_robot_to_plant(self.plant, self.scenario, models_dir)
        self.plant.Finalize()
        check_joint_order(self.plant, self.robot)
        self.diagram = builder.Build()
        self.scene_graph = self.diagram.scene_graph()
        self._diagram_context = self.diagram.CreateDefaultContext()
        self.plant_context = self.plant.GetMyMutableContextFromRoot(self._diagram_context)
        self.racket_frame = self.plant.GetFrameByName(RACKET_FRAME, self.robot)
        self.ball_cup_frame = self.plant.GetFrameByName(BALL_CUP_FRAME, self.robot)
        limits = self.scenario.limits.as_arrays()
        self.lower, self.upper = limits["lower"], limits["upper"]
        self.velocity_limit, self.acceleration_limit = limits["velocity"], limits["acceleration"]
        self.ready_pose = np.asarray(self.scenario.ready_pose, dtype=float)
        # True for the arm's revolute joints, False for the gantry's prismatic ones (JOINT_NAMES order).
        self.revolute = np.array([self.plant.GetJointByName(name, self.robot).type_name() == "revolute" for name in JOINT_NAMES])

    # ------------------------------------------------------------------------------ kinematics
    def _set(self, q: np.ndarray, v: np.ndarray | None = None) -> None:
        self.plant.SetPositions(self.plant_context, joint_vector(q, "q"))
        self.plant.SetVelocities(self.plant_context, np.zeros(8) if v is None else joint_vector(v, "v"))

    def racket_pose(self, q: np.ndarray) -> RigidTransform:
        """X_WR: the racket frame (blade centre, z along the forehand normal) in world."""
        self._set(q)
        return self.racket_frame.CalcPoseInWorld(self.plant_context)

    def racket_spatial_velocity(self, q: np.ndarray, v: np.ndarray) -> SpatialVelocity:
        """V_WR: the racket frame's spatial velocity in world, [w (rad/s), v (m/s)]."""
        self._set(q, v)
        return self.racket_frame.CalcSpatialVelocityInWorld(self.plant_context)

    def racket_jacobian(self, q: np.ndarray) -> np.ndarray:
        """J (6, 8) with V_WR = J v: rows [w; v] of the racket frame's origin, expressed in world."""
        self._set(q)
        world = self.plant.world_frame()
        return self.plant.CalcJacobianSpatialVelocity(
            self.plant_context, JacobianWrtVariable.kV, self.racket_frame, np.zeros(3), world, world
        )

    # ------------------------------------------------------------------------------ collisions
    def colliding_pairs(self, q: np.ndarray, margin: float = 0.0) -> list[tuple[str, str, float]]:
        """Pairs of collision geometries (robot-robot, robot-court) closer than ``margin`` (m) at
        configuration q, as (name, name, signed distance) with body-qualified names."""
        self._set(q)
        query = self.scene_graph.get_query_output_port().Eval(self.scene_graph.GetMyContextFromRoot(self._diagram_context))
        inspector = query.inspector()
        pairs = []
        for pair in query.ComputeSignedDistancePairwiseClosestPoints(max_distance=max(margin, 0.0) + 1e-9):
            if pair.distance < margin:
                names = [self.plant.GetBodyFromFrameId(inspector.GetFrameId(g)).name() + "/" + inspector.GetName(g) for g in (pair.id_A, pair.id_B)]
                pairs.append((names[0], names[1], float(pair.distance)))
        return pairs

    # ------------------------------------------------------------------------------ inverse kinematics
    def solve_racket_ik(
        self,
        p_WB: np.ndarray,
        q_seed: np.ndarray | None = None,
        max_normal_angle: float = np.radians(45.0),
        blade_region: float = 0.04,
        clearance: float | None = 0.01,
    ) -> IkResult:
        """A configuration within the joint limits that puts a ball at ``p_WB`` (m) against the
        forehand face, with the face normal within ``max_normal_angle`` (rad) of +x (facing the
        opponent) and no robot geometry closer than ``clearance`` (m) to itself or the court.

        The ball touches the face: its centre lies ball radius + half the blade thickness along
        the normal from a point of the face within ``blade_region`` (m) of the blade centre.
        Solved with Drake's InverseKinematics from ``q_seed``; by default from seeds placed behind
        the point with the handle down, then rolled to either side (low balls over the table
        need the handle sideways, or the wrist would be in the table).
        """
        p_WB = np.asarray(p_WB, dtype=float)
        if p_WB.shape != (3,) or not np.all(np.isfinite(p_WB)):
            raise ValueError(f"solve_racket_ik: p_WB must be 3 finite numbers (m), got {p_WB}")
        ball = BallPhysicsParams()
        standoff = ball.aero.ball_radius + 0.5 * ball.racket.blade_thickness  # m
        seeds = self._seeds(p_WB, q_seed)

        def constrain(ik: InverseKinematics) -> None:
            world = self.plant.world_frame()
            ik.AddPositionConstraint(
                frameB=world, p_BQ=p_WB, frameA=self.racket_frame,
                p_AQ_lower=[-blade_region, -blade_region, standoff - 1e-3],
                p_AQ_upper=[blade_region, blade_region, standoff + 1e-3],
            )
            ik.AddAngleBetweenVectorsConstraint(world, [1.0, 0.0, 0.0], self.racket_frame, [0.0, 0.0, 1.0], 0.0, max_normal_angle)

        return self._solve_ik(constrain, seeds, clearance)

    def solve_racket_pose_ik(
        self,
        p_WR: np.ndarray,
        normal_W: np.ndarray,
        q_seed: np.ndarray | None = None,
        position_tolerance: float = 1e-3,
        angle_tolerance: float = np.radians(0.5),
        clearance: float | None = 0.01,
    ) -> IkResult:
        """A configuration within the joint limits with the blade centre at ``p_WR`` (m, within
        ``position_tolerance``) and the forehand normal along ``normal_W`` (within
        ``angle_tolerance`` rad), the blade free to roll about its normal, clear of the court and
        itself by ``clearance`` (m; None skips the check)."""
        p_WR = np.asarray(p_WR, dtype=float)
        normal_W = np.asarray(normal_W, dtype=float)
        if p_WR.shape != (3,) or normal_W.shape != (3,) or not np.all(np.isfinite(np.r_[p_WR, normal_W])) or np.linalg.norm(normal_W) < 1e-9:
            raise ValueError(f"solve_racket_pose_ik: expected a position (3,) m and a non-zero normal (3,), got {p_WR}, {normal_W}")
        seeds = self._seeds(p_WR, q_seed)

        def constrain(ik: InverseKinematics) -> None:
            world = self.plant.world_frame()
            tolerance = np.full(3, position_tolerance)
            ik.AddPositionConstraint(self.racket_frame, np.zeros(3), world, p_WR - tolerance, p_WR + tolerance)
            ik.AddAngleBetweenVectorsConstraint(world, normal_W, self.racket_frame, [0.0, 0.0, 1.0], 0.0, angle_tolerance)

        return self._solve_ik(constrain, seeds, clearance)

    def _seeds(self, p_W: np.ndarray, q_seed: np.ndarray | None) -> list[np.ndarray]:
        """The given seed, or seeds behind p_W with the handle down, then rolled to either side."""
        if q_seed is not None:
            return [joint_vector(q_seed, "q_seed")]
        return [self.seed_for(p_W, handle_roll) for handle_roll in (0.0, 1.5, -1.5)]

    def _solve_ik(self, constrain: Callable[[InverseKinematics], None], seeds: list[np.ndarray], clearance: float | None) -> IkResult:
        """Drake's InverseKinematics with joint limits, the constraints ``constrain`` adds, an
        optional minimum distance between all collision geometries, and a cost on the distance
        from the seed (among the many solutions of a redundant arm, prefer the nearest), tried
        from each seed in turn."""
        start = time.perf_counter()
        for attempt, seed in enumerate(seeds, start=1):
            ik = InverseKinematics(self.plant, self.plant_context, with_joint_limits=True)
            constrain(ik)
            if clearance is not None:
                ik.AddMinimumDistanceLowerBoundConstraint(clearance, clearance + 0.05)
            ik.prog().AddQuadraticErrorCost(np.eye(8), seed, ik.q())
            result = Solve(ik.prog(), seed)
            if result.is_success():
                return IkResult(True, result.GetSolution(ik.q()), time.perf_counter() - start, attempt)
        return IkResult(False, result.GetSolution(ik.q()), time.perf_counter() - start, len(seeds))

    def seed_for(self, p_WB: np.ndarray, handle_roll: float = 0.0) -> np.ndarray:
        """An IK seed for a racket at p_WB: the ready pose with the gantry placed so that the
        shoulder stands 0.75 m behind the point and the column level with it in y (the arm 0.15 m
        to its +y), and wrist_1 (the roll about the forearm) at ``handle_roll`` rad."""
        seed = self.ready_pose.copy()
        seed[5] = handle_roll
        X_WBase = pose_to_transform(self.scenario.base_pose)
        shoulder_offset = 0.08  # shoulder axis ahead of the gantry's origin, m (ace_robot.sdf)
        seed[0] = p_WB[0] - 0.75 - X_WBase.translation()[0] - shoulder_offset
        seed[1] = p_WB[1] - X_WBase.translation()[1]
        return np.clip(seed, self.lower, self.upper)


@dataclasses.dataclass(frozen=True)
class IkResult:
    """The outcome of ``RobotModel.solve_racket_ik``: q (8,) is the solution (or the solver's last
    iterate when success is False); solve_time in s over all attempts."""

    success: bool
    q: np.ndarray
    solve_time: float
    attempts: int


def joint_vector(value, name: str) -> np.ndarray:
    """``value`` as a float array of one entry per joint (rad or m, in JOINT_NAMES' order);
    a ValueError naming ``name`` if it has another shape or a non-finite entry."""
    value = np.asarray(value, dtype=float)
    if value.shape != (len(JOINT_NAMES),) or not np.all(np.isfinite(value)):
        raise ValueError(f"{name}: expected {len(JOINT_NAMES)} finite joint values ({', '.join(JOINT_NAMES)}), got {value}")
    return value
