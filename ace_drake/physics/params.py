"""Ball-physics configs: the constants of the flight model (eq. 1) and the table, racket, net
and floor contacts (eqs 2-8), with their units and sources; loaded by ``ace_drake.config``.
"""

from __future__ import annotations

import dataclasses
import math

from ace_drake.config import ConfigError, load_config, require_non_negative, require_positive


DRAG_MODELS = ("constant", "spin_ratio")  # AeroParams.drag_model
MAGNUS_MODELS = ("ratio", "refined")  # AeroParams.magnus_model


@dataclasses.dataclass(frozen=True)
class AeroParams:
    """Ball and air constants for the flight model (paper eq. (1)); SI units."""

    air_density: float = 1.204  # rho_air, kg/m^3 (dry air, room temperature)
    ball_radius: float = 0.02  # r, m
    ball_density: float = 81.2  # rho_ball, kg/m^3 (mass 2.721e-3 kg; authors' code)
    gravity: float = 9.81  # |g|, m/s^2, along -z
    drag_coefficient: float = 0.55  # c_d
    # Which drag coefficient eq. (1) uses (physics.flight.drag_coefficient): "constant", the
    # printed paper's c_d = drag_coefficient, or "spin_ratio", the authors' code's c_d(|v|, |w| r / |v|)
    # table, multiplied by drag_coefficient / 0.55 (1 by default) so that fitting drag_coefficient
    # still scales it.
    drag_model: str = "constant"
    # Magnus coefficient c_M = min(magnus_slope * |v| / (r |w|) + magnus_offset, magnus_cap):
    # the paper's c_M = 0.1 |v| / (r |w|) - 0.001, capped at 1 as in the authors' code.
    magnus_slope: float = 0.1
    magnus_offset: float = -0.001
    magnus_cap: float = 1.0
    # Which Magnus coefficient eq. (1) uses (physics.flight.magnus_coefficient): "ratio", the one
    # above, or "refined", the authors' code's piecewise fit in |w| interpolated in |v|,
    # multiplied by magnus_scale (which acts on "refined" only).
    magnus_model: str = "ratio"
    magnus_scale: float = 1.0
    buoyancy: bool = True  # include the (1 - rho_air / rho_ball) factor on gravity (authors' code)

    def __post_init__(self) -> None:
        require_positive(self, "air_density", "ball_radius", "ball_density", "gravity")
        require_non_negative(self, "drag_coefficient", "magnus_cap", "magnus_scale")
        if self.drag_model not in DRAG_MODELS:
            raise ConfigError(f"drag_model must be one of {', '.join(DRAG_MODELS)}, got {self.drag_model!r}")
        if self.magnus_model not in MAGNUS_MODELS:
            raise ConfigError(f"magnus_model must be one of {', '.join(MAGNUS_MODELS)}, got {self.magnus_model!r}")

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
        require_positive(self, "length", "width", "surface_height")
        require_non_negative(self, "friction", "restitution_slope", "rolling_alpha")
        if not 0.0 < self.restitution_base <= 1.0:
            raise ConfigError(f"table.restitution_base must be in (0, 1], got {self.restitution_base}")


RESTITUTION_LAWS = ("exponential", "linear")  # RacketParams.restitution_law


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
    # Which restitution law eps(|v_n|) the contact uses: "exponential", the paper's printed
    # gamma1 exp(gamma2 |v_n|), or "linear", the authors' later a + b |v_n| (notes.md), with:
    restitution_law: str = "exponential"
    restitution_a: float = 0.878
    restitution_b: float = -0.0197  # s/m
    # The learned correction added to eqs (7)-(8) (physics.racket_residual): a network file written
    # by `ace-drake physics-fit-racket`, relative to models/ unless absolute; "" for none. Every
    # user of these params (both BallPlants, the returner's inverse) loads the same network
    # (``racket_residual.residual_model``).
    residual: str = ""
    blade_radius: float = 0.075  # m
    blade_thickness: float = 0.014  # rubber plus blade, m

    def __post_init__(self) -> None:
        require_positive(self, "restitution_gamma1", "blade_radius")
        require_non_negative(self, "tangential_k", "blade_thickness")
        if self.restitution_law not in RESTITUTION_LAWS:
            raise ConfigError(f"restitution_law must be one of {', '.join(RESTITUTION_LAWS)}, got {self.restitution_law!r}")


@dataclasses.dataclass(frozen=True)
class NetParams:
    """The net: a thin vertical rectangle in the plane x = 0; SI units."""

    height: float = 0.1525  # above the playing surface, m
    overhang: float = 0.1525  # beyond each side line, m
    restitution: float = 0.05  # normal restitution against net or cord (authors' code)
    tangential_retention: float = 1.0  # fraction of the tangential velocity kept at net contact

    def __post_init__(self) -> None:
        require_positive(self, "height")
        require_non_negative(self, "overhang", "restitution", "tangential_retention")


@dataclasses.dataclass(frozen=True)
class FloorParams:
    """The floor, 0.76 m below the playing surface; SI units."""

    restitution: float = 0.5  # normal restitution (authors' code)
    tangential_retention: float = 0.8  # fraction of tangential velocity kept; no source, chosen

    def __post_init__(self) -> None:
        require_non_negative(self, "restitution", "tangential_retention")


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
        require_non_negative(self, "velocity_std", "spin_std")


@dataclasses.dataclass(frozen=True)
class BallPhysicsParams:
    """Everything the ball model needs; the defaults are the paper's model."""

    aero: AeroParams = dataclasses.field(default_factory=AeroParams)
    table: TableParams = dataclasses.field(default_factory=TableParams)
    racket: RacketParams = dataclasses.field(default_factory=RacketParams)
    net: NetParams = dataclasses.field(default_factory=NetParams)
    floor: FloorParams = dataclasses.field(default_factory=FloorParams)
    perturbation: PerturbationParams = dataclasses.field(default_factory=PerturbationParams)


def load_ball_params(path=None) -> BallPhysicsParams:
    """The paper's ball model (``path`` None), or the parameter file ``path`` (a YAML like
    models/ball_physics_fitted.yaml; fields not given keep the paper's values)."""
    return BallPhysicsParams() if path is None else load_config(BallPhysicsParams, path)
