"""Perception configs: the frame cameras, the statistical position and spin sensors and the
ball estimator (EKF), with their rates, latencies and noise.
"""

from __future__ import annotations

import dataclasses

from ace_drake.config import ConfigError, require_latency_interval, require_non_negative, require_positive, require_probability


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
        require_positive(self, "trigger_rate", "outlier_threshold_px")
        require_non_negative(self, "latency", "pixel_noise_sigma")
        if not 0.0 <= self.dropout_probability <= 1.0:
            raise ConfigError(f"dropout_probability must be in [0, 1], got {self.dropout_probability}")
        if not 0.0 < self.render_scale <= 1.0:
            raise ConfigError(f"render_scale must be in (0, 1], got {self.render_scale}")
        if self.min_views < 2:
            raise ConfigError(f"min_views must be >= 2 (two views fix a point), got {self.min_views}")
        if not self.calibration:
            raise ConfigError("calibration must name a calibration file")


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
        require_positive(self, "trigger_period", "history_capacity")
        require_non_negative(self, "latency_min", "noise_std")
        require_latency_interval(self)
        require_probability(self, "dropout_probability", allow_one=False)


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
        require_positive(self, "rate_min", "poll_period", "history_capacity")
        require_non_negative(
            self, "latency_min", "racket_dropout_duration", "magnitude_noise_std", "axis_noise_std", "magnitude_bias_std", "axis_bias_std"
        )
        if not self.rate_min <= self.rate_max:
            raise ConfigError(f"rate_min ({self.rate_min} Hz) must be <= rate_max ({self.rate_max} Hz)")
        require_latency_interval(self)
        require_probability(self, "dropout_probability", allow_one=False)
        require_probability(self, "racket_dropout_probability", allow_one=True)
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
    # A track predicted faster or spinning faster than any ball (the fastest smashes ~30 m/s, elite
    # spins ~1,000 rad/s) has diverged: it gives no estimate until its next position restarts it.
    max_speed: float = 60.0  # m/s
    max_spin: float = 3000.0  # rad/s
    history_duration: float = 0.05  # s of capture time kept for re-filtering late measurements
    # Spins are processed this long after their capture time, so that one arriving after a position
    # captured up to this much later (spin latency 8-14 ms against 8.2-12.2 ms) needs no re-filtering.
    spin_fusion_lag: float = 0.006
    max_integration_step: float = 0.005  # s, RK4 step of the prediction
    finite_difference_step: float = 1e-6  # relative step of the Jacobian's finite differences

    def __post_init__(self) -> None:
        require_positive(
            self, "update_period", "initial_position_variance", "initial_velocity_variance",
            "initial_spin_variance", "max_measurement_gap", "max_position_jump", "max_position_innovation", "max_speed", "max_spin",
            "history_duration",
            "max_integration_step", "finite_difference_step",
        )
        require_non_negative(
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

