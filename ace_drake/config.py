"""Typed configuration: frozen dataclasses, loaded from YAML with errors that name the field.

Every physical constant of the simulation lives here with its unit and source. Defaults are the
paper's values (paper, Methods *Simulation*) as completed by the authors' published code (see
``../shared/paper/notes.md``); a fitted parameter set is a YAML file in ``models/`` that overrides
some of them (``load_config(BallPhysicsParams, path)``).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

T = TypeVar("T")


class InputError(ValueError):
    """What the user gave is wrong: a config value, a data or artefact file, a command-line value;
    the message names it and what was expected. The command line reports these (and a missing
    file) as ``error: ...`` with exit status 2; any other exception is a bug and keeps its
    traceback."""


class ConfigError(InputError):
    """A configuration value is missing, misspelt or out of range; the message names the field."""


# ----------------------------------------------------------------------------------------------
# Ball physics
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class AeroParams:
    """Ball and air constants for the flight model (paper eq. (1)); SI units."""

    air_density: float = 1.204  # rho_air, kg/m^3 (dry air, room temperature)
    ball_radius: float = 0.02  # r, m
    ball_density: float = 81.2  # rho_ball, kg/m^3 (mass 2.721e-3 kg; authors' code)
    gravity: float = 9.81  # |g|, m/s^2, along -z
    drag_coefficient: float = 0.55  # c_d
    # Magnus coefficient c_M = min(magnus_slope * |v| / (r |w|) + magnus_offset, magnus_cap):
    # the paper's c_M = 0.1 |v| / (r |w|) - 0.001, capped at 1 as in the authors' code.
    magnus_slope: float = 0.1
    magnus_offset: float = -0.001
    magnus_cap: float = 1.0
    buoyancy: bool = True  # include the (1 - rho_air / rho_ball) factor on gravity (authors' code)

    def __post_init__(self) -> None:
        _require_positive(self, "air_density", "ball_radius", "ball_density", "gravity")
        _require_non_negative(self, "drag_coefficient", "magnus_cap")

    @property
    def ball_mass(self) -> float:
        """Ball mass m = rho_ball * 4/3 pi r^3, kg."""
        return self.ball_density * 4.0 / 3.0 * math.pi * self.ball_radius**3


@dataclasses.dataclass(frozen=True)
class TableParams:
    """Ball-table contact (paper eqs (2)-(6)) and the table's geometry; SI units."""

    friction: float = 0.25  # mu, dynamic friction ball-table
    # eps_table = restitution_base - restitution_slope * |v_z^-|  (0.98 + 0.02 v_z with v_z < 0)
    restitution_base: float = 0.98
    restitution_slope: float = 0.02  # s/m
    rolling_alpha: float = 0.4  # alpha when the contact rolls (v_s <= 0), eq. (4): 2/5
    length: float = 2.74  # along x, m
    width: float = 1.525  # along y, m
    surface_height: float = 0.76  # playing surface above the floor, m (the world origin is on it)

    def __post_init__(self) -> None:
        _require_positive(self, "length", "width", "surface_height")
        _require_non_negative(self, "friction", "restitution_slope", "rolling_alpha")
        if not 0.0 < self.restitution_base <= 1.0:
            raise ConfigError(f"table.restitution_base must be in (0, 1], got {self.restitution_base}")


@dataclasses.dataclass(frozen=True)
class RacketParams:
    """Ball-racket contact (paper eqs (7)-(8)) and blade geometry; SI units."""

    # k = k_p / m with k_p = 1.928e-3 kg (authors' code) and m = 2.721e-3 kg.
    tangential_k: float = 0.7086
    # eps_racket = gamma1 * exp(gamma2 |v_z^-|); the paper publishes no values. These give 0.88 at
    # 1 m/s and 0.75 at 15 m/s normal speed, matching the authors' later linear fit
    # e = 0.878 - 0.0197 |v_n| over that range (notes.md).
    restitution_gamma1: float = 0.8901
    restitution_gamma2: float = -0.011418  # s/m
    blade_radius: float = 0.075  # m
    blade_thickness: float = 0.014  # rubber plus blade, m

    def __post_init__(self) -> None:
        _require_positive(self, "restitution_gamma1", "blade_radius")
        _require_non_negative(self, "tangential_k", "blade_thickness")


@dataclasses.dataclass(frozen=True)
class NetParams:
    """The net: a thin vertical rectangle in the plane x = 0; SI units."""

    height: float = 0.1525  # above the playing surface, m
    overhang: float = 0.1525  # beyond each side line, m
    restitution: float = 0.05  # normal restitution against net or cord (authors' code)
    tangential_retention: float = 1.0  # fraction of the tangential velocity kept at net contact

    def __post_init__(self) -> None:
        _require_positive(self, "height")
        _require_non_negative(self, "overhang", "restitution", "tangential_retention")


@dataclasses.dataclass(frozen=True)
class FloorParams:
    """The floor, 0.76 m below the playing surface; SI units."""

    restitution: float = 0.5  # normal restitution (authors' code)
    tangential_retention: float = 0.8  # fraction of tangential velocity kept; no source, chosen

    def __post_init__(self) -> None:
        _require_non_negative(self, "restitution", "tangential_retention")


@dataclasses.dataclass(frozen=True)
class PerturbationParams:
    """Post-table-contact Gaussian perturbations (paper, *Physics perturbations*).

    Applied only when a random generator is given (training, seeded simulation); validation and
    prediction are deterministic. The paper gives no values: these are chosen to be small against
    the data's estimation noise and are config.
    """

    velocity_std: float = 0.05  # per Cartesian component, m/s
    spin_std: float = 5.0  # per Cartesian component, rad/s

    def __post_init__(self) -> None:
        _require_non_negative(self, "velocity_std", "spin_std")


@dataclasses.dataclass(frozen=True)
class BallPhysicsParams:
    """Everything the ball model needs; the defaults are the paper's model."""

    aero: AeroParams = dataclasses.field(default_factory=AeroParams)
    table: TableParams = dataclasses.field(default_factory=TableParams)
    racket: RacketParams = dataclasses.field(default_factory=RacketParams)
    net: NetParams = dataclasses.field(default_factory=NetParams)
    floor: FloorParams = dataclasses.field(default_factory=FloorParams)
    perturbation: PerturbationParams = dataclasses.field(default_factory=PerturbationParams)


# ----------------------------------------------------------------------------------------------
# Robot joint dynamics
# ----------------------------------------------------------------------------------------------

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
        _require_positive(self, "command_period")


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
    swing at 20 m/s (``ace-drake bench reach`` measures both; README, *Robot*). Prismatic joints
    in m, revolute in rad."""

    gantry_x: JointLimits = JointLimits(-0.90, 0.80, 5.0, 40.0)
    gantry_y: JointLimits = JointLimits(-1.30, 1.30, 5.0, 40.0)
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


@dataclasses.dataclass(frozen=True)
class ControlParams:
    """The rally control stack (paper, Methods *Feasible action for optimal control* and *Reset
    trajectories*; ``ace_drake/control``). Times in s; fractions are of the hardware limits of
    ``RobotLimits``. The paper gives the 32 ms segment, the 1 kHz sampling and the 5 ms budget;
    the margins are this project's, chosen so that the delayed joints (eq. (9)) that follow the
    commands stay inside the hardware limits (``ace-drake bench safety`` measures it).
    """

    segment_samples: int = 32  # T: one policy step is this many command periods (32 ms at 1 kHz)
    observation_lead: float = 0.005  # the observation is built this long before its segment starts
    # Command limits = hardware limits shrunk by these, so that the servo's lag, overshoot and
    # inter-sample ripple (eq. (9); ~9% velocity ripple at 1 kHz) stay inside the hardware limits.
    position_margin: float = 0.02  # rad or m inside each position limit
    velocity_fraction: float = 0.85
    acceleration_fraction: float = 0.85
    # The feasible set of the action mapping (eq. (12)) is an inner approximation of what the spline
    # QP can reach: reachability assumes this fraction of the command acceleration, and the
    # control-invariant part assumes braking at ``stop_fraction`` of it after ``reaction_time``.
    reach_fraction: float = 0.8
    stop_fraction: float = 0.6
    reaction_time: float = 0.006
    boundary_samples: int = 24  # velocities sampled along each side of a feasible set's polygon
    # Command periods per cubic piece of the segment spline: 1 (a knot at every 1 kHz sample); with
    # longer pieces the spline cannot follow the feasible set's bang-bang bounds (measured: the
    # QP became infeasible within 10 adversarial steps for 2, 4 and 8).
    knot_samples: int = 1
    qp_solver: str = "daqp"  # "daqp", or "clarabel" through Drake's MathematicalProgram
    # Reset and protective-stop trajectories (Ruckig, jerk-limited and time-optimal): the jerk limit
    # is the command acceleration reached from zero in ``jerk_time``.
    jerk_time: float = 0.002
    reset_pose: tuple[float, ...] | None = None  # stationary reset configuration; None: the ready pose
    # Collision checking of segment + reset (robot_collision): swept bounding boxes over the whole
    # plan, then conservative advancement on Drake's distances where they cannot decide; every
    # point of the robot stays at least ``collision_margin`` (m) from the court and itself.
    collision_margin: float = 0.005
    collision_influence: float = 0.3  # distances beyond this (m) are not reported
    # The check's deadline, in exact distance queries (~10-20 us each, ~40 us with the
    # advancement's bookkeeping): a plan not proven clear within it is refused like a collision
    # (fail safe), which bounds the control step's latency. 16 leaves 0.2% of rally plans over it,
    # all of them colliding anyway (ace-drake bench control).
    collision_query_budget: int = 16

    def __post_init__(self) -> None:
        _require_positive(self, "segment_samples", "boundary_samples", "knot_samples", "jerk_time", "collision_influence", "collision_query_budget")
        if self.segment_samples % self.knot_samples:
            raise ConfigError(f"segment_samples ({self.segment_samples}) must be a multiple of knot_samples ({self.knot_samples})")
        _require_non_negative(self, "observation_lead", "position_margin", "reaction_time", "collision_margin")
        for name in ("velocity_fraction", "acceleration_fraction", "reach_fraction", "stop_fraction"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if not self.stop_fraction < self.reach_fraction:
            raise ConfigError(f"stop_fraction ({self.stop_fraction}) must be < reach_fraction ({self.reach_fraction})")
        if self.qp_solver not in ("daqp", "clarabel"):
            raise ConfigError(f"qp_solver must be daqp or clarabel, got {self.qp_solver!r}")
        if self.reset_pose is not None and len(self.reset_pose) != len(JOINT_NAMES):
            raise ConfigError(f"reset_pose: expected {len(JOINT_NAMES)} values, got {len(self.reset_pose)}")


# ----------------------------------------------------------------------------------------------
# Perception: the frame cameras and triangulation
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CameraParams:
    """The nine frame cameras and the triangulator (paper, Methods *Ball triangulation*; systems
    ``ApsCameraArray`` and ``Triangulator``). The paper gives the 200 Hz trigger and the 10.2 ms
    latency; the noise, dropout and outlier threshold are this project's choices.

    mode: "analytic" projects the ball's centre; "rendered" detects the ball in Drake RgbdSensor
    images rendered at ``render_scale`` times the 1440 x 1080 resolution. Noise and dropout apply
    in both modes.
    """

    calibration: str = "cameras.yaml"  # relative to models/
    mode: str = "analytic"
    trigger_rate: float = 200.0  # Hz, the hardware trigger (paper)
    latency: float = 0.0102  # s from capture to the released triangulation (paper)
    # px per axis on each detected centre: 1.5 px makes the mean 3D error over the play volume with
    # the shipped placement 2.8 mm, near the paper's 3.0 mm (which includes calibration and blur).
    pixel_noise_sigma: float = 1.5
    dropout_probability: float = 0.02  # per camera and trigger
    render_scale: float = 0.25  # rendered mode: image size relative to 1440 x 1080
    outlier_threshold_px: float = 8.0  # largest reprojection residual of one view kept, px (> 5 sigma)
    min_views: int = 2  # fewer consistent views give no position

    def __post_init__(self) -> None:
        if self.mode not in ("analytic", "rendered"):
            raise ConfigError(f"mode must be analytic or rendered, got {self.mode!r}")
        _require_positive(self, "trigger_rate", "outlier_threshold_px")
        _require_non_negative(self, "latency", "pixel_noise_sigma")
        if not 0.0 <= self.dropout_probability <= 1.0:
            raise ConfigError(f"dropout_probability must be in [0, 1], got {self.dropout_probability}")
        if not 0.0 < self.render_scale <= 1.0:
            raise ConfigError(f"render_scale must be in (0, 1], got {self.render_scale}")
        if self.min_views < 2:
            raise ConfigError(f"min_views must be >= 2 (two views fix a point), got {self.min_views}")
        if not self.calibration:
            raise ConfigError("calibration must name a calibration file")


# ----------------------------------------------------------------------------------------------
# Perception: statistical sensor models and the ball state estimator
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PositionSensorParams:
    """The training path's ball-position sensor (paper, Methods *Sensor modelling*): a sample at
    each camera trigger, latency uniform on [latency_min, latency_max], zero-mean Gaussian noise,
    dropout with a fixed probability. The paper reports means only (200 Hz, 10.2 ms latency,
    3.0 mm error; notes.md): the spread of the latency and the dropout are this project's choices.
    Times in s, lengths in m."""

    trigger_period: float = 0.005  # the cameras' 200 Hz hardware trigger (paper)
    # Mean 10.2 ms (paper); the +-2 ms spread is chosen, under the trigger period, so that the
    # positions are released in capture order.
    latency_min: float = 0.0082
    latency_max: float = 0.0122
    # Per axis: the mean 3D error of an isotropic Gaussian is sigma * 2 sqrt(2 / pi) = 3.0 mm (paper).
    noise_std: float = 0.00188
    dropout_probability: float = 0.05  # chosen: no published value
    history_capacity: int = 32  # measurements kept on the output port

    def __post_init__(self) -> None:
        _require_positive(self, "trigger_period", "history_capacity")
        _require_non_negative(self, "latency_min", "noise_std")
        _require_latency_interval(self)
        _require_probability(self, "dropout_probability", allow_one=False)


@dataclasses.dataclass(frozen=True)
class SpinSensorParams:
    """The gaze-control system's spin measurement as a statistical model (paper, Methods *Sensor
    modelling*): uniform latency, dropout, extra dropout for a window after each racket contact
    (tracking loss), precision noise and an accuracy bias, each a zero-mean Gaussian on the spin
    magnitude (rad/s) and one on the axis direction (a rotation vector, rad per component); the bias
    is drawn once per contact event. Output every 1/rate_max to 1/rate_min s (uniform), i.e.
    400-700 Hz (paper). Only the 400-700 Hz rate and the 24.8 rad/s mean error are published: the
    other values are chosen. Noise and bias split that error equally; with radial and tangential
    components equal at the median incoming spin of 289 rad/s (notes.md), the mean error there is
    1.596 sqrt(2) 11.0 = 24.8 rad/s."""

    rate_min: float = 400.0  # Hz
    rate_max: float = 700.0  # Hz
    # The CNN works on a 15 ms time surface (paper): a measurement describes the middle of its
    # window, 7.5 ms before the window closes, plus 0.5-6.5 ms of processing (chosen).
    latency_min: float = 0.008
    latency_max: float = 0.014
    dropout_probability: float = 0.05  # chosen
    # Tracking loss after a racket contact: the mirrors re-acquire the ball and the time surface
    # refills with post-contact events (two 15 ms windows, chosen).
    racket_dropout_duration: float = 0.03
    racket_dropout_probability: float = 1.0
    magnitude_noise_std: float = 11.0  # rad/s, precision, per sample
    axis_noise_std: float = 0.038  # rad, precision, per sample (11.0 rad/s tangential at 289 rad/s)
    magnitude_bias_std: float = 11.0  # rad/s, accuracy, per contact event
    axis_bias_std: float = 0.038  # rad, accuracy, per contact event
    # The system samples the captures of the last poll period at once; it must not exceed
    # latency_min so that every measurement exists before it is released.
    poll_period: float = 0.005
    history_capacity: int = 64

    def __post_init__(self) -> None:
        _require_positive(self, "rate_min", "poll_period", "history_capacity")
        _require_non_negative(
            self, "latency_min", "racket_dropout_duration", "magnitude_noise_std", "axis_noise_std", "magnitude_bias_std", "axis_bias_std"
        )
        if not self.rate_min <= self.rate_max:
            raise ConfigError(f"rate_min ({self.rate_min} Hz) must be <= rate_max ({self.rate_max} Hz)")
        _require_latency_interval(self)
        _require_probability(self, "dropout_probability", allow_one=False)
        _require_probability(self, "racket_dropout_probability", allow_one=True)
        if self.poll_period > self.latency_min:
            raise ConfigError(f"poll_period ({self.poll_period} s) must be <= latency_min ({self.latency_min} s)")


@dataclasses.dataclass(frozen=True)
class EstimatorParams:
    """The ball state EKF over [p (m), v (m/s), w (rad/s)] (``perception/ball_ekf.py``). The
    authors' filter (notes.md) gives the initial position and velocity variances, the observation
    variances (1e-4 m^2, 1 (rad/s)^2) and the reset rules (0.2 s, 0.4 m); the rest is chosen."""

    # s, the estimator system's periodic update, which stores the filter: the rally controller's
    # observation instants (RallyParams: 32 ms segments, observed 5 ms before each starts), where
    # the controller's evaluation has just fused it. Fed the same measurements, any period and
    # offset give the same outputs (they fuse every measurement released by their time); these
    # only make it cheapest.
    update_period: float = 0.032
    update_offset: float = 0.027
    initial_position_count: int = 3  # positions fitted to start a track (10 ms at 200 Hz)
    # The start's fit is refused (a bounce inside: wait for one more position) when its residuals,
    # normalised by the measurements' covariances, exceed this chi-square quantile.
    initial_fit_confidence: float = 0.999
    initial_position_variance: float = 0.01  # m^2 (authors')
    initial_velocity_variance: float = 0.1  # (m/s)^2 (authors')
    # The authors start spin with 10 (rad/s)^2; this filter starts it at zero, unknown, until the
    # first spin measurement.
    initial_spin_variance: float = 1.0e5  # (rad/s)^2
    # None: each measurement's own covariance; the authors' values are 1e-4 m^2 and 1 (rad/s)^2.
    position_observation_variance: float | None = None
    spin_observation_variance: float | None = None
    # The spin sensor's per-contact bias, held as a consider parameter (Schmidt): std of the
    # magnitude (rad/s) and of the axis (rad per component), as SpinSensorParams' accuracy.
    spin_bias_magnitude_std: float = 11.0
    spin_bias_axis_std: float = 0.038
    # White acceleration noise in flight, m^2/s^3: 0.1 m/s of velocity per 0.1 s, the size of the
    # printed model's errors against the match data (about 1 m/s^2; notes.md, 15 cm over a flight).
    acceleration_noise_density: float = 0.1
    spin_noise_density: float = 10.0  # (rad/s)^2/s, spin random walk in flight
    bounce_velocity_std: float = 0.05  # m/s per component at a bounce (PerturbationParams)
    bounce_spin_std: float = 5.0  # rad/s per component at a bounce (PerturbationParams)
    max_measurement_gap: float = 0.2  # s: a longer gap between captures restarts the track (authors')
    max_position_jump: float = 0.4  # m from the prediction restarts the track (authors')
    # A position whose normalised innovation squared (3 dof) exceeds this restarts the track too:
    # the prediction missed something discrete (a net-cord contact on the wrong side of the cord).
    # chi-square(3) passes 100 with probability 2e-21.
    max_position_innovation: float = 100.0
    history_duration: float = 0.05  # s of capture time kept for re-filtering late measurements
    # Spins are processed this long after their capture time, so that one arriving after a position
    # captured up to this much later (spin latency 8-14 ms against 8.2-12.2 ms) needs no re-filtering.
    spin_fusion_lag: float = 0.006
    max_integration_step: float = 0.005  # s, RK4 step of the prediction
    finite_difference_step: float = 1e-6  # relative step of the Jacobian's finite differences

    def __post_init__(self) -> None:
        _require_positive(
            self, "update_period", "initial_position_variance", "initial_velocity_variance",
            "initial_spin_variance", "max_measurement_gap", "max_position_jump", "max_position_innovation", "history_duration",
            "max_integration_step", "finite_difference_step",
        )
        _require_non_negative(
            self, "update_offset", "spin_fusion_lag", "spin_bias_magnitude_std", "spin_bias_axis_std", "acceleration_noise_density", "spin_noise_density", "bounce_velocity_std", "bounce_spin_std"
        )
        if self.initial_position_count < 3:
            raise ConfigError(f"initial_position_count must be >= 3 (two to fit, one to check), got {self.initial_position_count}")
        if not 0.0 < self.initial_fit_confidence < 1.0:
            raise ConfigError(f"initial_fit_confidence must be in (0, 1), got {self.initial_fit_confidence}")
        for name in ("position_observation_variance", "spin_observation_variance"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"{name} must be > 0 or null, got {value}")


@dataclasses.dataclass(frozen=True)
class PerceptionParams:
    """What the robot perceives the ball through (DESIGN.md: sensor fidelity is a config choice in
    one wiring, ``diagrams.add_perception``).

    positions: "cameras", the nine frame cameras and the triangulator (``camera``: analytic or
    rendered), or "statistical", the training path's position model (``position``); spins always
    come from the gaze-control system's statistical model (``spin``) until the event-camera
    pipeline exists; ``estimator``: the EKF. ``seed``: the sensors' default seed parameter.
    """

    positions: str = "cameras"
    camera: CameraParams = dataclasses.field(default_factory=CameraParams)
    position: PositionSensorParams = dataclasses.field(default_factory=PositionSensorParams)
    spin: SpinSensorParams = dataclasses.field(default_factory=SpinSensorParams)
    estimator: EstimatorParams = dataclasses.field(default_factory=EstimatorParams)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.positions not in ("cameras", "statistical"):
            raise ConfigError(f"positions must be cameras or statistical, got {self.positions!r}")


RETURNER_MEMORY_PARTS = ("bounce", "hit", "follow", "racket", "ik", "fallback")  # ReturnerParams.forget
IK_NOMINALS = ("braking", "segment_start")  # ReturnerParams.ik_nominal


@dataclasses.dataclass(frozen=True)
class ReturnerParams:
    """The model-based returner (``control/returner.py``): where it sends the ball, which hits it
    considers and how it predicts. Lengths in m (world frame of DESIGN.md), times in s, speeds in
    m/s. The paper's robot has no such controller (it is the related work's approach), so every
    value is this project's choice."""

    target_x: float = 0.75  # landing point's x on the opponent's half (0.685: its centre)
    target_y_limit: float = 0.45  # the skill's y_desired is clipped to +-this
    # Flight times from the hit to the landing, tried in order until the racket state is reachable
    # within the joint speed limits and the ball clears the net by ``net_clearance``.
    flight_times: tuple[float, ...] = (0.55, 0.45, 0.65, 0.75, 0.38)
    net_clearance: float = 0.04  # between the ball's bottom and the net cord
    brush_speed: float = 0.0  # racket speed along the blade's upward tangent (> 0: topspin)
    # Added to brush_speed per unit of the skill's w_s (paper, *Rewards*: w_s weighs the landing's
    # topspin), so that the returner follows the spin skill: 2 m/s put the median landing topspin
    # at +198 / -32 / -157 rad/s for w_s = +1 / 0 / -1 on 21 recorded shots, returning 17 / 18 / 19
    # of them (4 m/s: 11 / 18 / 14; README, *Rally: the model-based returner*). 0: spin ignored.
    skill_brush: float = 2.0
    # The ball centre at the hit: height above the playing surface, and how far behind the table.
    hit_height_min: float = 0.12
    hit_height_max: float = 0.50
    hit_x_min: float = -2.6
    prediction_step: float = 0.032  # RK4 step of the incoming ball's prediction (one segment)
    prediction_horizon: float = 1.2  # how far ahead the incoming ball is predicted
    candidates_tried: int = 3  # hit times planned per call before giving up
    # Distance between all robot and court geometry at the hit configuration (the supervisor checks
    # the motion with a 5 mm margin, and the motion around the hit comes closer than the hit).
    ik_clearance: float = 0.03
    ik_solves_per_call: int = 4  # full IK solves (``solve_hit_ik``) a call may spend; refinements are free
    # Where a full IK solve starts (its nominal configuration and first seed): "braking", the arm's
    # revolute joints where braking uniformly to rest over the D s to the hit's boundary would stop
    # them, q0 + v0 D / 2, and the gantry at q0, so that a moving arm keeps to the solution it is
    # moving towards; "segment_start", q0 itself. None: "braking" without memory (369 of the 411
    # playable recorded shots against 353), "segment_start" with it (376 against 372), the better
    # rule for each (README, *Rally: the model-based returner*).
    ik_nominal: str | None = None
    # The joints' lag behind the command (eq. (9) ramp-tracking lag plus half a command period of
    # zero-order hold); None: computed from the scenario's joint dynamics.
    joint_lag: float | None = None
    # Whether the returner remembers the ball it is playing between calls (its hit time, the bounce,
    # its last IK solution: ``control/returner.py``). False: every call plans from its observation
    # alone, so that the action is a function of the observation (as a policy's is): the labels a
    # learner imitates (``learning.rollout``, DAgger) are then learnable.
    memory: bool = True
    # With memory on, remembered things to forget, for studying what the memory is worth (README,
    # *Rally: the model-based returner*); any of RETURNER_MEMORY_PARTS: "bounce" (found behind the
    # ball at every call instead), "hit" (the planned hit time is not tried first), "follow" (the
    # follow-through is decided from the preferred hit, not from the plan), "racket" (the plan's
    # flight time and return are not reused), "ik" (the plan's configuration is not refined: full IK
    # afresh), "fallback" (no falling back on the plan being executed).
    forget: tuple[str, ...] = ()

    @property
    def ik_rule(self) -> str:
        """The IK's starting rule in force (``ik_nominal``, None resolved by ``memory``)."""
        if self.ik_nominal is not None:
            return self.ik_nominal
        return "segment_start" if self.memory else "braking"

    def __post_init__(self) -> None:
        object.__setattr__(self, "forget", tuple(self.forget))
        unknown = [part for part in self.forget if part not in RETURNER_MEMORY_PARTS]
        if unknown:
            raise ConfigError(f"forget: unknown memory part(s) {unknown}; choose from {', '.join(RETURNER_MEMORY_PARTS)}")
        if self.ik_nominal is not None and self.ik_nominal not in IK_NOMINALS:
            raise ConfigError(f"ik_nominal must be one of {', '.join(IK_NOMINALS)}, got {self.ik_nominal!r}")
        _require_positive(self, "target_x", "net_clearance", "hit_height_max", "prediction_step", "prediction_horizon", "candidates_tried", "ik_solves_per_call")
        _require_non_negative(self, "target_y_limit", "hit_height_min", "ik_clearance")
        if not self.flight_times or any(not t > 0.0 for t in self.flight_times):
            raise ConfigError(f"flight_times must be a non-empty list of positive times (s), got {self.flight_times}")
        if not self.hit_height_min < self.hit_height_max:
            raise ConfigError(f"hit_height_min ({self.hit_height_min}) must be < hit_height_max ({self.hit_height_max})")
        if self.joint_lag is not None and not self.joint_lag >= 0.0:
            raise ConfigError(f"joint_lag must be >= 0 s or null, got {self.joint_lag}")


@dataclasses.dataclass(frozen=True)
class RewardParams:
    """A rally episode's terminal reward (paper eq. (10), *Rewards*; ``learning/rewards.py``):

        R_miss                    the robot did not hit the ball,
        R_hit                     it hit the ball but did not return it,
        R_return = return_base + w_p position_reward exp(-|y_land - y_desired| / position_length)
                               + w_s spin_gain omega_y,

    with the skill [y_desired, w_p, w_s] and omega_y the ball's spin about the y axis of its
    travel frame at landing (topspin > 0). The paper gives no numbers: these are this project's.
    """

    miss: float = -1.0  # R_miss, also for an episode timed out before any hit
    # An episode ended because the commanded motion would collide (paper's end condition (4)): the
    # robot did not hit the ball, so R_miss by default; lower it to punish such commands more.
    collision: float = -1.0
    hit: float = 0.0  # R_hit (not returned): between a miss and a return, so touching the ball pays
    return_base: float = 1.0  # every return gets this, whatever the skill
    # The position term's maximum, at y_land = y_desired (hindsight relabelling gives it): equal to
    # the base, so that an aimed return is worth twice an unaimed one.
    position_reward: float = 1.0
    position_length: float = 0.3  # m; a landing 0.3 m off y_desired gets 37 % (the half is 1.525 m wide)
    spin_gain: float = 1.0 / 400.0  # per rad/s: 400 rad/s of topspin (about the robot's p90 spin) gives 1
    invalid: float = 0.0  # the opponent's shot was a fault: there was no play to make

    def __post_init__(self) -> None:
        _require_positive(self, "position_length")
        _require_non_negative(self, "position_reward", "spin_gain")


@dataclasses.dataclass(frozen=True)
class RallyParams:
    """One rally episode's diagram (``diagrams.add_rally``): the ball (``physics``, with the
    paper's post-table perturbations when ``perturb``), the robot (``scenario``: a scenario YAML in
    models/), its perception (``perception``) and control stack (``control``), and the policy's
    observation histories (paper, *States*: the last N positions and spins; the paper does not
    give N, 10 is 50 ms of positions at 200 Hz). ``hit_prediction``: whether the observation's
    ``hit_prediction`` part is computed (``control.hit_prediction``, ~5 ms of CPU per observation,
    every 32 ms; False: zeros there, for controllers that do not read it). ``hit_memory``: that
    part keeps the hit it predicted 32 ms before while it is still a candidate (the model-based
    returner's memory of its hit time; ``ObservationBuilder``), instead of judging from the
    estimate alone (needs ``hit_prediction``). ``time_limit``: s after
    the opponent's hit at which an unresolved episode ends. ``seed``: the default of every seed
    parameter."""

    physics: BallPhysicsParams = dataclasses.field(default_factory=BallPhysicsParams)
    perturb: bool = True
    scenario: str = "scenario.yaml"
    control: ControlParams = dataclasses.field(default_factory=ControlParams)
    perception: PerceptionParams = dataclasses.field(default_factory=PerceptionParams)
    position_history: int = 10
    spin_history: int = 10
    hit_prediction: bool = True
    hit_memory: bool = False
    time_limit: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        _require_positive(self, "position_history", "spin_history", "time_limit")
        if self.hit_memory and not self.hit_prediction:
            raise ConfigError("hit_memory keeps the observation's predicted hit: it needs hit_prediction true")


def _require_latency_interval(config: Any) -> None:
    if not config.latency_min <= config.latency_max:
        raise ConfigError(f"latency_min ({config.latency_min} s) must be <= latency_max ({config.latency_max} s)")


def _require_probability(config: Any, name: str, allow_one: bool) -> None:
    value = getattr(config, name)
    if not (0.0 <= value < 1.0 or (allow_one and value == 1.0)):
        raise ConfigError(f"{name} must be in [0, {'1]' if allow_one else '1)'}, got {value}")


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------


def from_dict(cls: type[T], data: Any, path: str = "") -> T:
    """Builds dataclass ``cls`` from a nested dict, checking names and types.

    Missing fields keep their defaults; unknown fields, wrong types and values rejected by a
    dataclass's own checks raise ConfigError naming the dotted field (``aero.drag_coefficient``).
    """
    where = path or cls.__name__
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; expected some of {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{path}.{name}" if path else name)
    try:
        return cls(**kwargs)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None


def load_config(cls: type[T], path: str | Path, section: str | None = None) -> T:
    """Loads dataclass ``cls`` from a YAML file (optionally from one top-level ``section``)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    if section is not None:
        if not isinstance(data, dict) or section not in data:
            raise ConfigError(f"{path}: no top-level section '{section}'")
        data = data[section]
    try:
        return from_dict(cls, data)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def to_dict(config: Any) -> dict:
    """The plain-dict (YAML-ready) form of a config dataclass."""
    return dataclasses.asdict(config)


def _coerce(hint: Any, value: Any, name: str) -> Any:
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, name)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, name)
            except ConfigError as error:
                errors.append(str(error))
        raise ConfigError("; ".join(errors))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{name}: expected a finite number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        (item,) = typing.get_args(hint)[:1]
        return tuple(_coerce(item, v, f"{name}[{i}]") for i, v in enumerate(value))
    return value


def _require_positive(config: Any, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not value > 0:
            raise ConfigError(f"{name} must be > 0, got {value}")


def _require_non_negative(config: Any, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not value >= 0:
            raise ConfigError(f"{name} must be >= 0, got {value}")


# ----------------------------------------------------------------------------------------------
# Incoming shots
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ShotParams:
    """The opponent's incoming-shot distribution (``play/shots.py``; paper, Methods *Initial state
    training distribution*): Gaussian KDEs of post-hit ball states fitted to ``source``,
    "synthetic" (the built-in synthetic set, drawn with ``seed``) or the path of a match-data CSV
    (the human's shots), of the ``players`` named there only (``player_id`` values; empty: all);
    serves are drawn with probability ``serve_fraction`` (paper: 3:7 serves to returns);
    ``bandwidth``: the KDE bandwidth factor (dimensionless), null for Scott's rule."""

    source: str = "synthetic"
    serve_fraction: float = 0.3
    bandwidth: float | None = None
    seed: int = 0
    players: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.source.strip():
            raise ConfigError("source must be 'synthetic' or the path of a match-data CSV, got an empty string")
        _require_probability(self, "serve_fraction", allow_one=True)
        if self.bandwidth is not None and not (math.isfinite(self.bandwidth) and self.bandwidth > 0):
            raise ConfigError(f"bandwidth must be > 0 or null (Scott's rule), got {self.bandwidth}")
        if self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")
        if self.players and self.source == "synthetic":
            raise ConfigError("players selects shots of a match-data CSV; the synthetic source has none")
