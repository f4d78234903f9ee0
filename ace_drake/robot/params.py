"""Robot configs: joint names, the joints' delayed dynamics (eq. 9), hardware limits and the
scenario (model file, poses) that every robot builder loads; loaded by ``ace_drake.config``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np

from ace_drake.artefacts import dumps, sha256
from ace_drake.config import MODELS_DIR, ConfigError, require_positive

JOINT_NAMES = ("gantry_x", "gantry_y", "shoulder_yaw", "shoulder_pitch", "elbow", "wrist_1", "wrist_2", "wrist_3")


@dataclasses.dataclass(frozen=True)
class JointDynamicsParams:
    """One joint of paper eq. (9): d/dt [q, q_aux] = A [q, q_aux] + b q*(t - tau_d), output q.

    a: A in row-major order (4,); b: (2,); delay: tau_d, s. Here q_aux is the joint velocity, so
    A = [[0, 1], [a21, a22]] and b = [0, b2] (the form ``control.joint_model`` and the system
    identification produce); A must be Hurwitz. The paper publishes no values: the defaults are a
    stiff, slightly underdamped servo (natural frequency 1000 rad/s, damping ratio 0.9, unit gain)
    with a 2 ms input delay, i.e. a ramp-tracking lag tau_d + 2 zeta / omega = 3.8 ms, under the
    paper's 5 ms.
    """

    a: tuple[float, ...] = (0.0, 1.0, -1.0e6, -1800.0)
    b: tuple[float, ...] = (0.0, 1.0e6)
    delay: float = 0.002

    def __post_init__(self) -> None:
        if len(self.a) != 4 or len(self.b) != 2:
            raise ConfigError(f"a needs 4 values (row-major 2x2) and b 2, got {len(self.a)} and {len(self.b)}")
        if self.a[0] != 0.0 or self.a[1] != 1.0 or self.b[0] != 0.0:
            raise ConfigError(f"expected A = [[0, 1], [a21, a22]] and b = [0, b2] (q_aux = velocity), got a={self.a}, b={self.b}")
        if not (self.a[2] < 0.0 and self.a[3] < 0.0):
            raise ConfigError(f"A must be Hurwitz (a21 < 0 and a22 < 0), got a={self.a}")
        if not 0.0 <= self.delay < 0.1:
            raise ConfigError(f"delay must be in [0, 0.1) s, got {self.delay}")


@dataclasses.dataclass(frozen=True)
class RobotDynamicsParams:
    """The eight joints' dynamics (paper eq. (9)), in JOINT_NAMES order, and the command period."""

    joints: tuple[JointDynamicsParams, ...] = tuple(JointDynamicsParams() for _ in JOINT_NAMES)
    command_period: float = 0.001  # s, the 1 kHz robot interface

    def __post_init__(self) -> None:
        if len(self.joints) != len(JOINT_NAMES):
            raise ConfigError(f"joints: expected {len(JOINT_NAMES)} ({', '.join(JOINT_NAMES)}), got {len(self.joints)}")
        require_positive(self, "command_period")


@dataclasses.dataclass(frozen=True)
class JointLimits:
    """One joint's limits: position interval [lower, upper] (rad or m), and symmetric velocity
    (rad/s or m/s) and acceleration (rad/s^2 or m/s^2) bounds."""

    lower: float
    upper: float
    velocity: float
    acceleration: float

    def __post_init__(self) -> None:
        if not self.lower < self.upper:
            raise ConfigError(f"lower must be < upper, got [{self.lower}, {self.upper}]")
        if not (self.velocity > 0 and self.acceleration > 0):
            raise ConfigError(f"velocity and acceleration must be > 0, got {self.velocity} and {self.acceleration}")


@dataclasses.dataclass(frozen=True)
class RobotLimits:
    """Limits per joint (JOINT_NAMES). The paper publishes none: these are chosen so that the
    racket reaches the recorded robot contact points with the blade facing the opponent and can
    swing at 20 m/s (``ace-drake bench reach`` measures both; docs/robot_and_control.md,
    *The robot*). Prismatic joints in m, revolute in rad."""

    gantry_x: JointLimits = JointLimits(-0.90, 0.80, 5.0, 40.0)
    gantry_y: JointLimits = JointLimits(-1.30, 1.00, 5.0, 40.0)  # symmetric about -0.15: the arm's mirror
    shoulder_yaw: JointLimits = JointLimits(-2.6, 2.6, 10.0, 150.0)
    shoulder_pitch: JointLimits = JointLimits(-1.2, 1.4, 10.0, 150.0)
    elbow: JointLimits = JointLimits(-2.4, 2.4, 14.0, 250.0)
    wrist_1: JointLimits = JointLimits(-3.0, 3.0, 20.0, 500.0)
    wrist_2: JointLimits = JointLimits(-2.0, 2.0, 20.0, 500.0)
    wrist_3: JointLimits = JointLimits(-3.0, 3.0, 25.0, 600.0)

    def as_arrays(self) -> dict[str, np.ndarray]:
        """lower, upper, velocity, acceleration as (8,) arrays in JOINT_NAMES order."""
        rows = [getattr(self, name) for name in JOINT_NAMES]
        return {key: np.array([getattr(row, key) for row in rows]) for key in ("lower", "upper", "velocity", "acceleration")}


@dataclasses.dataclass(frozen=True)
class Pose:
    """A rigid pose: translation xyz (m) and roll-pitch-yaw (degrees, extrinsic X-Y-Z)."""

    xyz: tuple[float, ...] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, ...] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if len(self.xyz) != 3 or len(self.rpy_deg) != 3:
            raise ConfigError(f"xyz and rpy_deg need 3 values each, got {self.xyz} and {self.rpy_deg}")


@dataclasses.dataclass(frozen=True)
class RobotScenario:
    """The robot and its court: model files, where the robot stands, its limits and dynamics.

    Model paths are relative to the scenario file's directory (``models/``). The ready pose is
    the stationary configuration rallies start from (JOINT_NAMES order; m and rad); it must lie
    within the limits.
    """

    robot_model: str = "ace_robot.sdf"
    court_model: str = "table.sdf"
    # The gantry's model frame on the floor behind the robot's end of the table (DESIGN.md world).
    base_pose: Pose = Pose(xyz=(-2.45, 0.0, -0.76))
    limits: RobotLimits = dataclasses.field(default_factory=RobotLimits)
    ready_pose: tuple[float, ...] = (-0.45, -0.15, 0.0, 0.15, 0.35, 0.0, -0.5, 0.0)
    dynamics: RobotDynamicsParams = dataclasses.field(default_factory=RobotDynamicsParams)

    def __post_init__(self) -> None:
        if len(self.ready_pose) != len(JOINT_NAMES):
            raise ConfigError(f"ready_pose: expected {len(JOINT_NAMES)} values ({', '.join(JOINT_NAMES)}), got {len(self.ready_pose)}")
        limits = self.limits.as_arrays()
        outside = [
            f"{name}={value} not in [{low}, {high}]"
            for name, value, low, high in zip(JOINT_NAMES, self.ready_pose, limits["lower"], limits["upper"])
            if not low <= value <= high
        ]
        if outside:
            raise ConfigError(f"ready_pose outside the joint limits: {'; '.join(outside)}")


def scenario_record(scenario: RobotScenario) -> dict:
    """What of the robot a robot-specific artefact (a serve library's joint commands, a training
    run's checkpoint) depends on: its joint names, its model files' names and sha256 (``models/``)
    and a sha256 ``fingerprint`` over those and every field of the scenario (limits, dynamics,
    base pose, ready pose), with the fields themselves for naming a difference."""
    fields = json.loads(dumps(dataclasses.asdict(scenario), indent=None))
    files = {}
    for name in (scenario.robot_model, scenario.court_model):
        path = MODELS_DIR / name
        files[name] = sha256(path) if path.is_file() else None
    record = {"joint_names": list(JOINT_NAMES), "model_files": files, "fields": fields}
    record["fingerprint"] = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()
    return record


def scenario_mismatch(saved: dict, current: dict) -> str | None:
    """Why an artefact made for the robot ``saved`` (a ``scenario_record``) does not fit the robot
    ``current`` (None if it does)."""
    if saved.get("fingerprint") == current["fingerprint"]:
        return None
    if saved.get("joint_names") != current["joint_names"]:
        return f"its joints are {saved.get('joint_names')}, the robot's {current['joint_names']}"
    differ = [f"model file {name}" for name in current["model_files"] if saved.get("model_files", {}).get(name) != current["model_files"][name]]
    saved_fields = saved.get("fields", {})
    differ += [f"scenario field {name}" for name in current["fields"] if saved_fields.get(name) != current["fields"][name]]
    return "it differs in " + (", ".join(differ) if differ else "its fingerprint")
