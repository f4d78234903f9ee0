"""Camera placement by CMA-ES (paper, Methods *Ball triangulation*: "Camera placement is optimized
using a custom covariance matrix adaptation evolution strategy (CMA-ES) algorithm. The optimizer
determines the lens selection, mounting height and orientation for each camera, subject to
constraints such as the number of towers, desired coverage volume and a minimum projected 2D ball
radius (5 pixels).").

Each camera stands on a fixed tower outside the court; the optimiser chooses, per camera, a lens
from a catalogue, the mounting height on the tower and the heading and elevation of the optical
axis (no roll). A placement is scored over a grid of the play volume, the box where the ball flies
over and around the table:

- coverage: the fraction of grid points that at least ``min_views`` cameras see (in frame, in
  front, not behind the table; ``cameras.visibility``) with a projected ball radius of at least
  ``min_radius_px``;
- uncertainty: the mean over covered points of sqrt(trace(Sigma)), the RMS 3D error of
  triangulating them from those views with pixel noise sigma (``triangulation.position_covariance``).

CMA-ES (the maintained ``cma`` package) minimises

    cost = (1 - coverage) + partial_weight (1 - mean_n min(views_n, min_views) / min_views)
           + uncertainty_weight * uncertainty_mm,

where the middle term rewards views that do not yet make a point covered, so that the cost is not
flat for placements far from good ones. Genes are normalised to [0, 1] (CMA-ES bounds): per camera
[lens, mounting height, heading offset from the direction to the table centre, elevation]; the
lens gene is rounded down to an index into the catalogue.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import cma
import numpy as np

from ace_drake.artefacts import write_sidecar
from ace_drake.config import InputError
from ace_drake.perception.cameras import (
    BALL_RADIUS,
    PIXEL_PITCH,
    SENSOR_HEIGHT_PX,
    SENSOR_WIDTH_PX,
    Camera,
    Occluder,
    PlayingArea,
    projected_ball_radius,
    rotation_from_yaw_pitch,
    save_cameras,
    validate_camera_array,
    visibility,
)
from ace_drake.perception.triangulation import position_covariance
from ace_drake.physics.params import TableParams

GENES_PER_CAMERA = 4  # lens, mounting height, heading offset, elevation


@dataclasses.dataclass(frozen=True)
class Tower:
    """A fixed tower on the floor outside the court: its name (also the camera's) and position
    (x, y) in world, m."""

    name: str
    x: float
    y: float


@dataclasses.dataclass(frozen=True)
class Lens:
    """A C-mount lens: focal length, mm, and its OpenCV distortion (k1, k2, p1, p2, k3). The
    distortions are representative values for machine-vision lenses of each focal length (wider
    lenses bend more), not a vendor's calibration."""

    focal_length_mm: float
    distortion: tuple[float, ...]

    def focal_length_px(self, pixel_pitch: float = PIXEL_PITCH) -> float:
        """Focal length in pixels for square pixels of ``pixel_pitch`` m."""
        return self.focal_length_mm * 1e-3 / pixel_pitch


# Nine towers outside a 14 x 7 m court (cameras.PlayingArea), one camera each: three along each
# side line, two behind the human's end and one behind the robot (paper, Fig. 2a: towers around the
# court, outside the play area). +y is the robot's left.
DEFAULT_TOWERS = (
    Tower("left_robot", -3.5, 3.8),
    Tower("left_centre", 0.0, 3.8),
    Tower("left_human", 3.5, 3.8),
    Tower("right_robot", -3.5, -3.8),
    Tower("right_centre", 0.0, -3.8),
    Tower("right_human", 3.5, -3.8),
    Tower("human_end_left", 7.3, 2.0),
    Tower("human_end_right", 7.3, -2.0),
    Tower("robot_end", -7.3, 0.0),
)

DEFAULT_LENSES = (
    Lens(4.0, (-0.12, 0.06, 0.0, 0.0, 0.0)),
    Lens(6.0, (-0.08, 0.03, 0.0, 0.0, 0.0)),
    Lens(8.0, (-0.05, 0.02, 0.0, 0.0, 0.0)),
    Lens(12.0, (-0.03, 0.01, 0.0, 0.0, 0.0)),
    Lens(16.0, (-0.02, 0.005, 0.0, 0.0, 0.0)),
)


@dataclasses.dataclass(frozen=True)
class PlacementProblem:
    """What the placement optimiser may choose and how it scores a placement (module docstring).
    Lengths in m, angles in degrees, pixels in px."""

    towers: tuple[Tower, ...] = DEFAULT_TOWERS
    lenses: tuple[Lens, ...] = DEFAULT_LENSES
    min_mount_height: float = 0.5  # above the floor
    max_mount_height: float = 4.5  # under the hall's 5 m ceiling
    max_heading_offset_deg: float = 50.0  # from the direction of the tower to the table centre
    min_elevation_deg: float = -60.0
    max_elevation_deg: float = 10.0
    min_views: int = 3
    min_radius_px: float = 5.0  # paper: 5-pixel minimum projected ball radius
    pixel_noise_sigma: float = 1.5  # px, for the uncertainty term (CameraParams' default)
    partial_weight: float = 0.1
    uncertainty_weight: float = 0.02  # cost per mm of uncertainty
    playing_area: PlayingArea = dataclasses.field(default_factory=PlayingArea)
    ball_radius: float = BALL_RADIUS

    def __post_init__(self) -> None:
        if not self.towers or not self.lenses:
            raise ValueError("PlacementProblem: needs at least one tower and one lens")
        if not 0 < self.min_mount_height < self.max_mount_height <= self.playing_area.ceiling:
            raise ValueError(
                f"PlacementProblem: need 0 < min_mount_height < max_mount_height <= ceiling, got "
                f"{self.min_mount_height}, {self.max_mount_height}, {self.playing_area.ceiling}"
            )
        if not self.min_elevation_deg < self.max_elevation_deg:
            raise ValueError("PlacementProblem: min_elevation_deg must be < max_elevation_deg")
        if self.min_views < 2:
            raise ValueError(f"PlacementProblem: min_views must be >= 2, got {self.min_views}")

    @property
    def gene_count(self) -> int:
        """Length of a gene vector: GENES_PER_CAMERA per tower."""
        return GENES_PER_CAMERA * len(self.towers)


@dataclasses.dataclass(frozen=True)
class PlacementFigures:
    """A placement's scores on a grid of N points: coverage (fraction of points seen by at least
    min_views cameras at >= min_radius_px), the views per point (N,), the uncertainty (mean
    sqrt(trace(Sigma)) over covered points, m; inf if none) and the optimiser's cost."""

    coverage: float
    views: np.ndarray
    uncertainty: float
    cost: float


@dataclasses.dataclass(frozen=True)
class PlacementResult:
    """The outcome of ``optimize_placement``: the best cameras found and their genes (G,), their
    figures and those of the initial placement, the lens index per camera, the number of cost
    evaluations and the best cost after each iteration."""

    cameras: tuple[Camera, ...]
    genes: np.ndarray
    figures: PlacementFigures
    initial_figures: PlacementFigures
    lens_indices: tuple[int, ...]
    evaluations: int
    best_cost_history: tuple[float, ...]


# ----------------------------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------------------------


def play_volume_points(
    spacing: float = 0.25,
    x_range: tuple[float, float] = (-2.5, 2.5),
    y_range: tuple[float, float] = (-1.2, 1.2),
    z_range: tuple[float, float] = (0.05, 1.2),
) -> np.ndarray:
    """A regular grid (N, 3), m, over the play volume: where the ball flies over and around the
    table (x along the table, z above the playing surface). Each axis gets the fewest points
    whose spacing is at most ``spacing``, ends included."""
    axes = [np.linspace(low, high, max(2, math.ceil((high - low) / spacing - 1e-9) + 1)) for low, high in (x_range, y_range, z_range)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def views_per_point(
    cameras: Sequence[Camera],
    points: np.ndarray,
    min_radius_px: float = 5.0,
    occluders: Sequence[Occluder] | None = None,
    ball_radius: float = BALL_RADIUS,
) -> tuple[np.ndarray, np.ndarray]:
    """Which cameras see each point with a projected ball radius of at least ``min_radius_px``:
    (C, N) bool, and the count per point (N,)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    seen = visibility(cameras, points, occluders, ball_radius) & (projected_ball_radius(cameras, points, ball_radius) >= min_radius_px)
    return seen, seen.sum(axis=0)


def coverage(
    cameras: Sequence[Camera],
    points: np.ndarray,
    min_views: int = 3,
    min_radius_px: float = 5.0,
    occluders: Sequence[Occluder] | None = None,
) -> float:
    """The fraction of ``points`` (N, 3), m, seen by at least ``min_views`` cameras with a
    projected ball radius of at least ``min_radius_px`` (paper: 5 px). Occluders default to the
    table."""
    _, views = views_per_point(cameras, points, min_radius_px, occluders)
    return float(np.mean(views >= min_views))


def evaluate_placement(
    cameras: Sequence[Camera],
    points: np.ndarray,
    problem: PlacementProblem | None = None,
    occluders: Sequence[Occluder] | None = None,
) -> PlacementFigures:
    """Coverage, views per point, uncertainty and cost of a placement (module docstring)."""
    problem = problem or PlacementProblem()
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    seen, views = views_per_point(cameras, points, problem.min_radius_px, occluders, problem.ball_radius)
    covered = views >= problem.min_views
    coverage_fraction = float(np.mean(covered))
    partial = float(np.mean(np.minimum(views, problem.min_views) / problem.min_views))
    if covered.any():
        covariance = position_covariance(cameras, points[covered], seen[:, covered], problem.pixel_noise_sigma)
        uncertainty = float(np.mean(np.sqrt(np.trace(covariance, axis1=1, axis2=2))))
    else:
        uncertainty = math.inf
    uncertainty_cost = problem.uncertainty_weight * 1e3 * uncertainty if covered.any() else 0.0
    cost = (1.0 - coverage_fraction) + problem.partial_weight * (1.0 - partial) + uncertainty_cost
    return PlacementFigures(coverage_fraction, views, uncertainty, cost)


# ----------------------------------------------------------------------------------------------
# Genes
# ----------------------------------------------------------------------------------------------


def cameras_from_genes(genes: np.ndarray, problem: PlacementProblem | None = None) -> tuple[tuple[Camera, ...], tuple[int, ...]]:
    """The cameras a gene vector (4 per tower, each in [0, 1]) describes, and each one's lens
    index. Gene order per camera: lens (rounded down to a catalogue index), mounting height
    (min..max above the floor), heading offset (-max..+max from the direction to the table
    centre), elevation (min..max)."""
    problem = problem or PlacementProblem()
    genes = np.clip(np.asarray(genes, dtype=float).reshape(len(problem.towers), GENES_PER_CAMERA), 0.0, 1.0)
    cameras, lens_indices = [], []
    for tower, (lens_gene, height_gene, heading_gene, elevation_gene) in zip(problem.towers, genes):
        lens_index = min(int(lens_gene * len(problem.lenses)), len(problem.lenses) - 1)
        lens = problem.lenses[lens_index]
        height = problem.min_mount_height + height_gene * (problem.max_mount_height - problem.min_mount_height)
        heading = math.atan2(-tower.y, -tower.x) + math.radians((2.0 * heading_gene - 1.0) * problem.max_heading_offset_deg)
        elevation = math.radians(problem.min_elevation_deg + elevation_gene * (problem.max_elevation_deg - problem.min_elevation_deg))
        focal = lens.focal_length_px()
        K = np.array([[focal, 0.0, 0.5 * (SENSOR_WIDTH_PX - 1)], [0.0, focal, 0.5 * (SENSOR_HEIGHT_PX - 1)], [0.0, 0.0, 1.0]])
        p_WC = np.array([tower.x, tower.y, height - problem.playing_area.floor_depth])
        cameras.append(Camera(tower.name, K, np.array(lens.distortion), rotation_from_yaw_pitch(heading, elevation), p_WC))
        lens_indices.append(lens_index)
    return tuple(cameras), tuple(lens_indices)


def genes_aimed_at(target_W: np.ndarray, problem: PlacementProblem | None = None, lens_index: int | None = None, mount_height: float | None = None) -> np.ndarray:
    """Genes of cameras at ``mount_height`` (default mid-range, m above the floor) with lens
    ``lens_index`` (default the middle of the catalogue) whose optical axes point at target_W (3,),
    m (elevation clipped to the allowed range): CMA-ES's default starting point."""
    problem = problem or PlacementProblem()
    lens_index = len(problem.lenses) // 2 if lens_index is None else lens_index
    height = 0.5 * (problem.min_mount_height + problem.max_mount_height) if mount_height is None else mount_height
    target_W = np.asarray(target_W, dtype=float)
    genes = []
    for tower in problem.towers:
        z = height - problem.playing_area.floor_depth
        offset = target_W - np.array([tower.x, tower.y, z])
        heading_offset = math.degrees(math.atan2(offset[1], offset[0]) - math.atan2(-tower.y, -tower.x))
        heading_offset = (heading_offset + 180.0) % 360.0 - 180.0
        elevation = math.degrees(math.atan2(offset[2], math.hypot(offset[0], offset[1])))
        genes.append(
            [
                (lens_index + 0.5) / len(problem.lenses),
                (height - problem.min_mount_height) / (problem.max_mount_height - problem.min_mount_height),
                0.5 + 0.5 * heading_offset / problem.max_heading_offset_deg,
                (elevation - problem.min_elevation_deg) / (problem.max_elevation_deg - problem.min_elevation_deg),
            ]
        )
    return np.clip(np.array(genes).ravel(), 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Optimisation
# ----------------------------------------------------------------------------------------------


def optimize_placement(
    problem: PlacementProblem | None = None,
    points: np.ndarray | None = None,
    seed: int = 0,
    iterations: int = 100,
    population_size: int | None = None,
    initial_genes: np.ndarray | None = None,
    initial_step: float = 0.2,
    occluders: Sequence[Occluder] | None = None,
    progress: Callable[[int, float, PlacementFigures], None] | None = None,
) -> PlacementResult:
    """Runs CMA-ES (``cma``) on the placement cost (module docstring) for ``iterations``
    generations and returns the best placement evaluated.

    points: the play-volume grid (N, 3), m (default ``play_volume_points()``).
    seed (>= 0): fixes the run; CMA-ES's samples come from ``numpy.random.default_rng(seed)``.
    population_size: candidates per generation (default CMA-ES's 4 + 3 ln(genes)).
    initial_genes: the search's starting mean (default: every camera aimed at the table centre,
        0.3 m above it, middle lens, mid height); initial_step: the initial step size in gene units.
    progress: called after each generation with (iteration, best cost so far, best figures so far).
    """
    problem = problem or PlacementProblem()
    if seed < 0:
        raise InputError(f"optimize_placement: seed must be >= 0, got {seed}")
    points = play_volume_points() if points is None else np.asarray(points, dtype=float).reshape(-1, 3)
    x0 = genes_aimed_at([0.0, 0.0, 0.3], problem) if initial_genes is None else np.asarray(initial_genes, dtype=float)
    if x0.shape != (problem.gene_count,):
        raise ValueError(f"optimize_placement: initial_genes must have {problem.gene_count} values, got {x0.shape}")
    generator = np.random.default_rng(seed)
    options = {
        "bounds": [0.0, 1.0],
        "seed": seed + 1,  # cma seeds numpy's global generator too; it treats 0 as "from the clock"
        "randn": lambda *shape: generator.standard_normal(shape),
        "maxiter": iterations,
        "tolflatfitness": iterations + 1,  # coverage is piecewise constant: flat steps are expected
        "verbose": -9,
        "verb_log": 0,
        "verb_disp": 0,
    }
    if population_size is not None:
        options["popsize"] = population_size
    strategy = cma.CMAEvolutionStrategy(x0, initial_step, options)

    def evaluate(genes: np.ndarray) -> PlacementFigures:
        cameras, _ = cameras_from_genes(genes, problem)
        return evaluate_placement(cameras, points, problem, occluders)

    initial_figures = evaluate(x0)
    best_genes, best_figures = x0.copy(), initial_figures
    evaluations, history = 1, []
    for iteration in range(iterations):
        if strategy.stop():
            break
        candidates = strategy.ask()
        figures = [evaluate(np.asarray(candidate)) for candidate in candidates]
        evaluations += len(candidates)
        strategy.tell(candidates, [f.cost for f in figures])
        best = int(np.argmin([f.cost for f in figures]))
        if figures[best].cost < best_figures.cost:
            best_genes, best_figures = np.clip(np.asarray(candidates[best], dtype=float), 0.0, 1.0), figures[best]
        history.append(best_figures.cost)
        if progress is not None:
            progress(iteration, best_figures.cost, best_figures)
    cameras, lens_indices = cameras_from_genes(best_genes, problem)
    return PlacementResult(cameras, best_genes, best_figures, initial_figures, lens_indices, evaluations, tuple(history))


def optimize_and_write(
    calibration_path: str | Path,
    seed: int = 0,
    iterations: int = 200,
    spacing: float = 0.2,
    validation_spacing: float = 0.1,
    population_size: int | None = None,
    plot_path: str | Path | None = None,
    command: str | None = None,
    problem: PlacementProblem | None = None,
    progress: Callable[[int, float, PlacementFigures], None] | None = None,
) -> dict:
    """Optimises the placement (``optimize_placement`` over ``play_volume_points(spacing)``) and
    writes the calibration file, its sidecar (``artefacts.write_sidecar``, same name, ``.json``:
    command, or ``command`` if given, date, seed, settings, figures, also on the finer
    ``play_volume_points(validation_spacing)``, per-camera lens and mounting) and, when
    ``plot_path`` is given, the coverage plot. Returns the sidecar's content."""
    problem = problem or PlacementProblem()
    points = play_volume_points(spacing)
    result = optimize_placement(problem, points, seed=seed, iterations=iterations, population_size=population_size, progress=progress)
    validate_camera_array(result.cameras, problem.playing_area)
    calibration_path = Path(calibration_path)
    figures = result.figures
    header = (
        "Nine frame cameras (1440 x 1080, Sony IMX273, 3.45 um pixels) on towers outside the court,\n"
        "placed by CMA-ES (ace_drake/perception/placement.py); how: the .json sidecar beside this file.\n"
        f"Coverage of the play volume by >= {problem.min_views} views at >= {problem.min_radius_px:g} px ball radius: "
        f"{100 * figures.coverage:.1f} %.\n"
        "Units: px (K), m (p_WC); R_WC columns are the camera's x (right), y (down), z (optical axis) in world."
    )
    save_cameras(calibration_path, result.cameras, header)
    validation = evaluate_placement(result.cameras, play_volume_points(validation_spacing), problem)
    genes = result.genes.reshape(len(problem.towers), GENES_PER_CAMERA)
    mounting = []
    for camera, lens_index, gene in zip(result.cameras, result.lens_indices, genes):
        axis = camera.R_WC[:, 2]
        mounting.append(
            {
                "camera": camera.name,
                "lens_focal_length_mm": problem.lenses[lens_index].focal_length_mm,
                "mount_height_m": round(float(camera.p_WC[2] + problem.playing_area.floor_depth), 4),
                "heading_deg": round(math.degrees(math.atan2(axis[1], axis[0])), 3),
                "elevation_deg": round(math.degrees(math.asin(np.clip(axis[2], -1.0, 1.0))), 3),
                "genes": [round(float(g), 6) for g in gene],
            }
        )
    fields = {
        "produced_by": "ace_drake.perception.placement.optimize_and_write",
        "iterations": iterations,
        "population_size": population_size,
        "evaluations": result.evaluations,
        "cma_version": cma.__version__,
        "play_volume": {"x": [-2.5, 2.5], "y": [-1.2, 1.2], "z": [0.05, 1.2], "spacing_m": spacing, "points": int(len(points))},
        "problem": {
            "towers": [dataclasses.asdict(tower) for tower in problem.towers],
            "lenses_mm": [lens.focal_length_mm for lens in problem.lenses],
            "mount_height_m": [problem.min_mount_height, problem.max_mount_height],
            "max_heading_offset_deg": problem.max_heading_offset_deg,
            "elevation_deg": [problem.min_elevation_deg, problem.max_elevation_deg],
            "min_views": problem.min_views,
            "min_radius_px": problem.min_radius_px,
            "pixel_noise_sigma_px": problem.pixel_noise_sigma,
            "partial_weight": problem.partial_weight,
            "uncertainty_weight_per_mm": problem.uncertainty_weight,
        },
        "figures": {
            "coverage": round(figures.coverage, 5),
            "uncertainty_mm": round(1e3 * figures.uncertainty, 4),
            "cost": round(figures.cost, 6),
            "views_per_point_mean": round(float(np.mean(figures.views)), 4),
            "validation_spacing_m": validation_spacing,
            "validation_coverage": round(validation.coverage, 5),
            "validation_uncertainty_mm": round(1e3 * validation.uncertainty, 4),
            "initial_coverage": round(result.initial_figures.coverage, 5),
            "initial_cost": round(result.initial_figures.cost, 6),
        },
        "cameras": mounting,
    }
    if plot_path is not None:
        write_coverage_plot(result.cameras, points, plot_path, problem)
        fields["plot"] = Path(plot_path).name
    return write_sidecar(calibration_path, command=command, seed=seed, **fields)


# ----------------------------------------------------------------------------------------------
# Plot
# ----------------------------------------------------------------------------------------------


def write_coverage_plot(
    cameras: Sequence[Camera],
    points: np.ndarray,
    path: str | Path,
    problem: PlacementProblem | None = None,
    occluders: Sequence[Occluder] | None = None,
) -> None:
    """Writes a PNG (or any format matplotlib knows from the suffix) of a placement's coverage:
    a top view (x-y) of the fewest views (cameras seeing the ball at >= min_radius_px) over the
    heights of each grid column, with the cameras, their mounting heights and optical axes, and a
    side view (x-z) of the fewest views across y; points under ``min_views`` are hatched. Uses
    matplotlib's Agg canvas (no display)."""
    # Lazy: plotting only; the placement maths does not need matplotlib.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    problem = problem or PlacementProblem()
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    figures = evaluate_placement(cameras, points, problem, occluders)
    axes_values = [np.unique(points[:, k]) for k in range(3)]
    index = tuple(np.searchsorted(axes_values[k], points[:, k]) for k in range(3))
    views = np.zeros([len(v) for v in axes_values])
    views[index] = figures.views
    table = TableParams()
    half_length, half_width = 0.5 * table.length, 0.5 * table.width

    def extent(first: int, second: int) -> list[float]:
        edges = []
        for axis in (first, second):
            values = axes_values[axis]
            half_step = 0.5 * (values[1] - values[0]) if len(values) > 1 else 0.05
            edges += [values[0] - half_step, values[-1] + half_step]
        return edges

    figure = Figure(figsize=(11, 8.5))
    FigureCanvasAgg(figure)
    top, side = figure.subplots(2, 1, height_ratios=[1.6, 1])
    colour_options = {"vmin": 0, "vmax": len(cameras), "cmap": "viridis", "origin": "lower", "aspect": "equal"}
    for axes, view, (first, second) in ((top, views.min(axis=2), (0, 1)), (side, views.min(axis=1), (0, 2))):
        image = axes.imshow(view.T, extent=extent(first, second), **colour_options)
        x, y = np.meshgrid(axes_values[first], axes_values[second], indexing="ij")
        under = view < problem.min_views
        axes.plot(x[under], y[under], "rx", ms=4)
    top.plot([-half_length, half_length, half_length, -half_length, -half_length], [-half_width, -half_width, half_width, half_width, -half_width], "w-", lw=1.5)
    for camera in cameras:
        axis = camera.R_WC[:, 2]
        top.plot(camera.p_WC[0], camera.p_WC[1], "r^", ms=8)
        tip = camera.p_WC[:2] + 1.5 * axis[:2] / max(np.linalg.norm(axis[:2]), 1e-9)
        top.annotate("", xy=tip, xytext=camera.p_WC[:2], arrowprops={"arrowstyle": "->", "color": "r"})
        label = f"{camera.name}\nf = {camera.focal_length_px:.0f} px, h = {camera.p_WC[2] + problem.playing_area.floor_depth:.2f} m"
        top.text(camera.p_WC[0], camera.p_WC[1] + 0.3, label, fontsize=7, ha="center")
    top.set_xlim(-8.5, 8.5)
    top.set_ylim(-4.8, 4.8)
    top.set_xlabel("x, m (robot at -x)")
    top.set_ylabel("y, m")
    top.set_title(
        f"Fewest views over the heights. Coverage by >= {problem.min_views} cameras at >= {problem.min_radius_px:g} px: "
        f"{100 * figures.coverage:.1f} % (x: under); uncertainty {1e3 * figures.uncertainty:.2f} mm at {problem.pixel_noise_sigma:g} px",
        fontsize=9,
    )
    figure.colorbar(image, ax=top, label="cameras seeing the ball")
    side.plot([-half_length, half_length], [0.0, 0.0], "w-", lw=3)
    side.set_xlabel("x, m")
    side.set_ylabel("z above the table, m")
    side.set_title("fewest views across y", fontsize=9)
    figure.tight_layout()
    figure.savefig(str(path), dpi=90)
