"""Validate the flight model against measured ball trajectories whose spin is known.

A trajectory file is a CSV with exactly the columns ``trajectory,t,x,y,z,wx,wy,wz``: one row per
measured ball centre (x, y, z in m, in this project's world frame: origin at the centre of the
playing surface, x towards the human, z up) at time t (s), with the trajectory's spin (wx, wy, wz,
rad/s, constant over the flight) repeated on each of its rows. Rows of one trajectory keep their
file order and need not be contiguous.

For every trajectory and ball model, the initial position and velocity at the first sample are
fitted to the samples of the first ``fit_window`` seconds (free flight with the trajectory's spin,
a robust least-squares fit), then propagated through table, net and floor contacts
(``physics.propagate.simulate``) to the last sample; the position error |p_model(t) - p(t)| at
every sample measures the model. Samples are split at the *measured* first bounce
(``measured_bounce_index``), so that every model is judged on the same samples.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ace_drake.analysis.physics_validation import error_figures
from ace_drake.config import MODELS_DIR, InputError
from ace_drake.physics.flight import POSITION, SPIN, make_state, rk4_step, rk4_trajectory
from ace_drake.physics.params import BallPhysicsParams, load_ball_params
from ace_drake.physics.propagate import DEFAULT_KINDS, ContactKind, simulate

COLUMNS = ("trajectory", "t", "x", "y", "z", "wx", "wy", "wz")
NUMERIC_COLUMNS = COLUMNS[1:]
SPIN_COLUMNS = ("wx", "wy", "wz")
FIT_WINDOW = 0.05  # s of samples from the first one that the initial state is fitted to
MIN_FIT_SAMPLES = 5  # fewer samples in the fit window: the trajectory is skipped
FIT_LOSS_SCALE = 0.003  # m, soft-l1 scale: residuals well above it count linearly (outliers)
BOUNCE_HEIGHT_MARGIN = 0.03  # m above the ball radius within which a sample over the table is "at the table"
STEP = 1e-3  # s, the longest RK4 step of the fit and the propagation


class TrajectoryFileError(InputError):
    """The trajectory file is missing or malformed; the message names the file, line and field."""


@dataclasses.dataclass(frozen=True)
class MeasuredTrajectory:
    """One measured flight: ``name`` (the file's trajectory id); times (T,) s, strictly increasing;
    positions (T, 3) m, the ball centre in the world frame; spin (3,) rad/s, constant; lines (T,)
    the samples' file lines (1 is the header; 0 for generated samples)."""

    name: str
    times: np.ndarray
    positions: np.ndarray
    spin: np.ndarray
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.times)

    def with_spin(self, spin) -> "MeasuredTrajectory":
        """The same samples with spin (3,) rad/s instead of the measured one."""
        return dataclasses.replace(self, spin=np.asarray(spin, dtype=float))


@dataclasses.dataclass(frozen=True)
class FlightModel:
    """A ball model to validate: its parameters, and whether the trajectories' measured spins are
    used (``use_spin`` False: every spin is set to zero and the fit absorbs what it can)."""

    params: BallPhysicsParams
    use_spin: bool = True


@dataclasses.dataclass(frozen=True)
class SampleErrors:
    """The model's position errors on one trajectory.

    errors (T,) m, |p_model(t) - p(t)| at every sample; bounce_index, the measured bounce sample
    (``measured_bounce_index``; None when the data hold no bounce); pre_bounce (T,) and
    post_bounce (T,) bool, the samples before and after it (the bounce sample is in neither).
    """

    errors: np.ndarray
    bounce_index: int | None
    pre_bounce: np.ndarray
    post_bounce: np.ndarray

    @property
    def last_pre_bounce_error(self) -> float:
        """The error at the last sample before the measured bounce, m (NaN if there is none)."""
        before = self.errors[self.pre_bounce]
        return float(before[-1]) if before.size else math.nan


def load_trajectories(path) -> list[MeasuredTrajectory]:
    """The trajectories of a CSV in this module's format (module docstring), in order of first
    appearance, each with its samples in file order.

    Every malformed row is an error, not skipped: a TrajectoryFileError names the file, the line
    (1 is the header) and the field, for a header other than exactly COLUMNS (a file of another
    kind), a missing or extra field, an empty trajectory id, a value that is not a finite number, a
    spin that differs from the trajectory's first row, or a time not after the trajectory's
    previous sample; a missing file or one without rows is an error too. Trajectories too short to
    fit are kept here: ``validate_trajectories`` skips them and counts them.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"trajectory file not found: {path}")
    samples: dict[str, list[tuple[int, list[float]]]] = {}
    with path.open(newline="", encoding="utf-8-sig") as handle:  # -sig: a spreadsheet's byte-order mark
        reader = csv.reader(handle)
        header = [name.strip() for name in next(reader, [])]
        if header != list(COLUMNS):
            raise TrajectoryFileError(f"{path}: not a trajectory file: header {','.join(header) or '(empty)'}; "
                                      f"expected exactly {','.join(COLUMNS)}")
        for row in reader:
            line = reader.line_num
            if not row:
                continue
            if len(row) != len(COLUMNS):
                raise TrajectoryFileError(f"{path}, line {line}: {len(row)} fields; expected {len(COLUMNS)} ({','.join(COLUMNS)})")
            name = row[0].strip()
            if not name:
                raise TrajectoryFileError(f"{path}, line {line}, field trajectory: empty trajectory id")
            values = [_parse_number(path, line, field, text) for field, text in zip(NUMERIC_COLUMNS, row[1:])]
            rows = samples.setdefault(name, [])
            if rows:
                first_line, first = rows[0]
                for k, field in enumerate(SPIN_COLUMNS, start=4):
                    if values[k] != first[k]:
                        raise TrajectoryFileError(f"{path}, line {line}, field {field}: the spin of trajectory {name!r} changes "
                                                  f"from {first[k]} (line {first_line}) to {values[k]} rad/s; it must be constant")
                previous_line, previous = rows[-1]
                if not values[0] > previous[0]:
                    raise TrajectoryFileError(f"{path}, line {line}, field t: {values[0]} s is not after trajectory {name!r}'s "
                                              f"previous sample ({previous[0]} s, line {previous_line}); times must increase")
            rows.append((line, values))
    if not samples:
        raise TrajectoryFileError(f"{path}: no samples")
    trajectories = []
    for name, rows in samples.items():
        table = np.array([values for _, values in rows])
        trajectories.append(MeasuredTrajectory(name=name, times=table[:, 0], positions=table[:, 1:4], spin=table[0, 4:7],
                                               lines=np.array([line for line, _ in rows])))
    return trajectories


def _parse_number(path: Path, line: int, field: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TrajectoryFileError(f"{path}, line {line}, field {field}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise TrajectoryFileError(f"{path}, line {line}, field {field}: expected a finite number, got {text!r}")
    return value


def write_trajectories_csv(path, trajectories: Sequence[MeasuredTrajectory]) -> None:
    """Writes trajectories to ``path`` in the format ``load_trajectories`` reads (values exact)."""
    with Path(path).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for trajectory in trajectories:
            spin = [repr(float(w)) for w in trajectory.spin]
            for t, p in zip(trajectory.times, trajectory.positions):
                writer.writerow([trajectory.name, repr(float(t)), *(repr(float(c)) for c in p), *spin])


def generate_trajectories(
    n: int,
    seed: int = 0,
    noise_std: float = 0.001,
    rate: float = 200.0,
    physics: BallPhysicsParams | None = None,
    post_bounce_duration: float = 0.15,
) -> tuple[list[MeasuredTrajectory], np.ndarray]:
    """``n`` synthetic shots from the human side that bounce on the robot's half of the table,
    sampled every 1/``rate`` s with Gaussian position noise of ``noise_std`` m per axis, and their
    true initial states (n, 9) at each first sample.

    Spins cycle through topspin, backspin and sidespin of 60 to 150 rad/s (a ball flying towards -x
    has topspin for w_y < 0). Each flight is simulated with ``physics`` (default: the paper's
    model; steps of 1/(5 rate) s, table, net and floor contacts) and ends ``post_bounce_duration``
    s after its first bounce, or before its next contact. Trajectory i starts at t = i s.
    """
    physics = physics or BallPhysicsParams()
    rng = np.random.default_rng(seed)
    substeps = 5
    kinds = ("topspin", "backspin", "sidespin")
    trajectories: list[MeasuredTrajectory] = []
    initial_states = []
    for _ in range(50):
        if len(trajectories) == n:
            break
        batch = 4 * (n - len(trajectories))
        spin_rate = rng.uniform(60.0, 150.0, batch)
        kind_index = (len(trajectories) + np.arange(batch)) % 3
        spin = np.zeros((batch, 3))
        spin[kind_index == 0, 1] = -spin_rate[kind_index == 0]
        spin[kind_index == 1, 1] = spin_rate[kind_index == 1]
        spin[kind_index == 2, 2] = spin_rate[kind_index == 2] * rng.choice([-1.0, 1.0], batch)[kind_index == 2]
        starts = make_state(
            np.c_[rng.uniform(1.3, 1.7, batch), rng.uniform(-0.4, 0.4, batch), rng.uniform(0.15, 0.35, batch)],
            np.c_[rng.uniform(-7.0, -4.0, batch), rng.uniform(-0.5, 0.5, batch), rng.uniform(0.5, 2.0, batch)],
            spin,
        )
        flights = simulate(starts, physics, 1.0, dt=1.0 / (rate * substeps))
        sample_times, sample_states = flights.times[::substeps], flights.states[::substeps]
        for i in range(batch):
            events = flights.events[i]
            bounces_on_robot_half = bool(events) and events[0].kind == ContactKind.TABLE and events[0].state_pre[0] < 0.0
            if kind_index[i] != len(trajectories) % 3 or not bounces_on_robot_half or events[0].time < FIT_WINDOW + 0.05:
                continue
            end = events[0].time + post_bounce_duration
            if len(events) > 1:
                end = min(end, events[1].time - 1e-6)
            keep = sample_times <= end
            index = len(trajectories)
            positions = sample_states[keep, i, POSITION] + rng.normal(0.0, noise_std, (int(keep.sum()), 3))
            trajectories.append(MeasuredTrajectory(
                name=f"synthetic_{index:03d}_{kinds[kind_index[i]]}", times=float(index) + sample_times[keep],
                positions=positions, spin=starts[i, SPIN].copy(), lines=np.zeros(int(keep.sum()), dtype=int),
            ))
            initial_states.append(starts[i])
            if len(trajectories) == n:
                break
    if len(trajectories) < n:
        raise RuntimeError(f"generate_trajectories: only {len(trajectories)} of {n} shots bounced on the table")
    return trajectories, np.array(initial_states)


def measured_bounce_index(trajectory: MeasuredTrajectory, physics: BallPhysicsParams) -> int | None:
    """The sample nearest the trajectory's first bounce on the table, from the data alone, or None.

    It is the lowest sample of the first run of samples over the table (|x| <= L/2, |y| <= W/2)
    and less than BOUNCE_HEIGHT_MARGIN above the resting height (z < r + margin). The ball falls
    before that sample and rises after it, so the bounce lies within one sample interval of it, on
    a side the samples do not tell: the sample before it is the last one before the bounce and the
    one after it the first after.
    """
    p = trajectory.positions
    near = ((np.abs(p[:, 0]) <= 0.5 * physics.table.length) & (np.abs(p[:, 1]) <= 0.5 * physics.table.width)
            & (p[:, 2] < physics.aero.ball_radius + BOUNCE_HEIGHT_MARGIN))
    if not near.any():
        return None
    start = int(np.argmax(near))
    stop = start + int(np.argmin(near[start:])) if not near[start:].all() else len(near)
    return start + int(np.argmin(p[start:stop, 2]))


def fit_window_samples(trajectory: MeasuredTrajectory, physics: BallPhysicsParams, fit_window: float = FIT_WINDOW) -> np.ndarray:
    """Indices of the samples the initial state is fitted to: those within ``fit_window`` s of the
    first sample and before the measured bounce (``measured_bounce_index``)."""
    inside = trajectory.times - trajectory.times[0] <= fit_window + 1e-9
    bounce = measured_bounce_index(trajectory, physics)
    if bounce is not None:
        inside[bounce:] = False
    return np.flatnonzero(inside)


def fit_initial_state(
    trajectory: MeasuredTrajectory,
    physics: BallPhysicsParams,
    fit_window: float = FIT_WINDOW,
    loss_scale: float = FIT_LOSS_SCALE,
) -> tuple[np.ndarray, dict]:
    """The ball state (9,) [p (m), v (m/s), the trajectory's spin (rad/s)] at the first sample time
    that best explains the samples of ``fit_window_samples``, and a dict about the fit.

    The flight model (eq. (1), RK4 steps of at most STEP s ending on every sample time) carries
    the state to the samples without contacts: the window is assumed free flight, which the
    bounce cut of ``fit_window_samples`` makes likely and ``info["contact_in_window"]`` checks (the
    kind of the fitted flight's first table, net or floor contact inside the window, else None).
    Least squares on the position residuals with a soft-l1 loss of scale ``loss_scale`` m, so that
    a few gross outliers pull little; the start is a parabola fitted to each axis. Raises
    ValueError for fewer than MIN_FIT_SAMPLES samples. info: samples, residual_rms_m (of the
    samples within 3 loss scales), nfev, success, contact_in_window.
    """
    window = fit_window_samples(trajectory, physics, fit_window)
    if window.size < MIN_FIT_SAMPLES:
        raise ValueError(f"fit_initial_state: trajectory {trajectory.name!r} has {window.size} samples before its bounce "
                         f"in the first {fit_window} s; at least {MIN_FIT_SAMPLES} are needed")
    times = trajectory.times[window] - trajectory.times[0]
    measured = trajectory.positions[window]
    steps, sample_steps = _steps_through(times)

    def residuals(p_and_v: np.ndarray) -> np.ndarray:
        state = np.concatenate([p_and_v, trajectory.spin])[None]
        return (rk4_trajectory(state, steps, physics.aero)[0, sample_steps, POSITION] - measured).ravel()

    parabola = np.polyfit(times, measured, 2)  # (3 powers, 3 axes), highest power first
    start = np.concatenate([parabola[2], parabola[1]])
    fit = least_squares(residuals, start, loss="soft_l1", f_scale=loss_scale, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    state0 = np.concatenate([fit.x, trajectory.spin])
    distance = np.linalg.norm(fit.fun.reshape(-1, 3), axis=1)
    inliers = distance[distance < 3.0 * loss_scale]
    window_flight = simulate(state0, physics, float(times[-1]), dt=STEP, kinds=DEFAULT_KINDS, record=False)
    contacts = window_flight.events[0]
    info = {
        "samples": int(window.size),
        "residual_rms_m": float(np.sqrt(np.mean(inliers**2))) if inliers.size else math.nan,
        "nfev": int(fit.nfev),
        "success": bool(fit.success),
        "contact_in_window": contacts[0].kind.name.lower() if contacts else None,
    }
    return state0, info


def _steps_through(times: np.ndarray, step: float = STEP) -> tuple[np.ndarray, np.ndarray]:
    """RK4 steps (n,) s from times[0] that end on every time of times (K,) s, none longer than
    ``step``, and the index (K,) of each time's state in ``rk4_trajectory``'s output."""
    intervals = np.diff(times)
    counts = np.maximum(np.ceil(intervals / step - 1e-9).astype(int), 1)
    return np.repeat(intervals / counts, counts), np.concatenate([[0], np.cumsum(counts)])


def states_at_times(initial_states: np.ndarray, physics: BallPhysicsParams, sample_times: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The model's ball states at given times: initial_states (N, 9) at t = 0 propagated with
    table, net and floor contacts (``simulate``, steps of STEP s), and sample_times[i] (T_i,) s >= 0
    ball i's times; returns N arrays (T_i, 9).

    A state at time t is the last recorded step or post-contact state at or before t carried by
    one RK4 step to t: no contact lies between them, so it is the model's state up to RK4's
    error, wherever t falls within a step."""
    initial_states = np.asarray(initial_states, dtype=float).reshape(-1, 9)
    duration = max(float(np.max(times, initial=0.0)) for times in sample_times)
    flights = simulate(initial_states, physics, duration, dt=STEP, kinds=DEFAULT_KINDS)
    result = []
    for i, times in enumerate(sample_times):
        times = np.asarray(times, dtype=float)
        step = np.clip(np.searchsorted(flights.times, times, side="right") - 1, 0, len(flights.times) - 1)
        anchor_times = flights.times[step].copy()
        anchor_states = flights.states[step, i].copy()
        for event in flights.events[i]:  # in time order: a later contact replaces an earlier anchor
            later = (event.time <= times) & (event.time >= anchor_times)
            anchor_times[later] = event.time
            anchor_states[later] = event.state_post
        result.append(rk4_step(anchor_states, times - anchor_times, physics.aero))
    return result


def compare(trajectory: MeasuredTrajectory, model_states: np.ndarray, physics: BallPhysicsParams) -> SampleErrors:
    """The position errors of the model's states (T, 9) at the trajectory's sample times, split at
    the measured bounce (``measured_bounce_index``; without one, every sample is before it)."""
    errors = np.linalg.norm(model_states[:, POSITION] - trajectory.positions, axis=1)
    bounce = measured_bounce_index(trajectory, physics)
    index = np.arange(len(trajectory))
    if bounce is None:
        return SampleErrors(errors, None, np.ones(len(trajectory), dtype=bool), np.zeros(len(trajectory), dtype=bool))
    return SampleErrors(errors, bounce, index < bounce, index > bounce)


def propagate_and_compare(trajectory: MeasuredTrajectory, state0: np.ndarray, physics: BallPhysicsParams) -> SampleErrors:
    """``compare`` for one trajectory: state0 (9,) at its first sample, propagated through table,
    net and floor contacts to its last sample (``states_at_times``)."""
    states = states_at_times(state0[None], physics, [trajectory.times - trajectory.times[0]])[0]
    return compare(trajectory, states, physics)


def default_models(params: BallPhysicsParams | None = None) -> dict[str, FlightModel]:
    """{"default": ``params`` (the paper's model if None) with the measured spins, "zero_spin":
    the same parameters with every spin set to zero}."""
    params = params or BallPhysicsParams()
    return {"default": FlightModel(params), "zero_spin": FlightModel(params, use_spin=False)}


FITTED_PARAMS = MODELS_DIR / "ball_physics_fitted.yaml"  # the match-fitted ball model (physics-fit)
AUTHORS_AERO = {"drag_model": "spin_ratio", "magnus_model": "refined"}  # the authors' published aerodynamics


def command_models(params_file=None) -> dict[str, FlightModel]:
    """The models of ``physics-validate --trajectories [--params FILE]``, side by side: the one of
    ``params_file`` first (its figures are the top level's; the paper's if None), then the paper's,
    the match-fitted one (``FITTED_PARAMS``), the paper's with the authors' published aerodynamics
    (``AUTHORS_AERO``: spin-ratio drag, refined Magnus) and the paper's with every spin set to zero."""
    paper = BallPhysicsParams()
    models = {Path(params_file).name if params_file else "paper": FlightModel(load_ball_params(params_file))}
    models.setdefault("paper", FlightModel(paper))
    if FITTED_PARAMS.is_file():
        models.setdefault("fitted (ball_physics_fitted.yaml)", FlightModel(load_ball_params(FITTED_PARAMS)))
    models["paper, authors' aerodynamics"] = FlightModel(dataclasses.replace(paper, aero=dataclasses.replace(paper.aero, **AUTHORS_AERO)))
    models["zero spin"] = FlightModel(paper, use_spin=False)
    return models


def validate_trajectories_with_params(path, params_file=None, progress: Callable[[str], None] = print) -> dict:
    """``ace-drake physics-validate --trajectories FILE [--params FILE]``: ``validate_trajectories``
    with ``command_models(params_file)``."""
    return validate_trajectories(path, command_models(params_file), progress=progress)


def evaluate_model(
    trajectories: Sequence[MeasuredTrajectory],
    model: FlightModel | BallPhysicsParams,
    fit_window: float = FIT_WINDOW,
) -> dict:
    """One model on trajectories that each have MIN_FIT_SAMPLES in their fit window: fits every
    initial state, propagates them together and returns the figures of ``validate_trajectories``
    (m) with ``fitted``, the trajectories that count, and ``skipped`` {reason: count}, those whose
    fit failed or whose fitted flight touches the table, net or floor inside the fit window."""
    model = model if isinstance(model, FlightModel) else FlightModel(model)
    kept, states0, skipped = [], [], {}
    for trajectory in trajectories:
        if not model.use_spin:
            trajectory = trajectory.with_spin(np.zeros(3))
        state0, info = fit_initial_state(trajectory, model.params, fit_window)
        reason = ("fit did not converge" if not info["success"]
                  else f"fitted flight touches the {info['contact_in_window']} inside the fit window" if info["contact_in_window"]
                  else None)
        if reason:
            skipped[reason] = skipped.get(reason, 0) + 1
            continue
        kept.append(trajectory)
        states0.append(state0)
    comparisons = []
    if kept:
        model_states = states_at_times(np.array(states0), model.params, [t.times - t.times[0] for t in kept])
        comparisons = [compare(t, states, model.params) for t, states in zip(kept, model_states)]
    return {
        "spin": "measured" if model.use_spin else "zero",
        "fitted": len(kept),
        "skipped": skipped,
        "pre_bounce_error_m": error_figures([c.last_pre_bounce_error for c in comparisons]),
        "pre_bounce_all_samples_error_m": error_figures(np.concatenate([c.errors[c.pre_bounce] for c in comparisons] or [[]])),
        "post_bounce_error_m": error_figures(np.concatenate([c.errors[c.post_bounce] for c in comparisons] or [[]])),
    }


def validate_trajectories(
    path,
    models: dict[str, FlightModel | BallPhysicsParams] | None = None,
    fit_window: float = FIT_WINDOW,
    progress: Callable[[str], None] = print,
) -> dict:
    """Every trajectory of the CSV ``path`` fitted and propagated with every model (module
    docstring); a JSON-ready dict.

    ``models``: name -> FlightModel, or BallPhysicsParams (used with the measured spins); default
    ``default_models()``; e.g. add "fitted": load_ball_params(yaml). The first model's figures are
    also the top level's. Figures are {median, p90, count} of position errors in m:

    - ``pre_bounce_error_m``: the error at each trajectory's last sample before the measured first
      bounce (its last sample if it has no bounce), one value per trajectory: how far the model
      has drifted by the end of the free flight;
    - ``pre_bounce_all_samples_error_m``: every sample before the bounce (the fit window included);
    - ``post_bounce_error_m``: every sample after it.

    Layout: {"trajectories": {data, fit_window_s, count (trajectories in the file), fitted and
    without_bounce (of the first model's trajectories), skipped {reason: count} (fewer than
    MIN_FIT_SAMPLES samples in the fit window, for every model), model (the first's name), the
    three figures, models {name: {spin, fitted, skipped (the model's own: its fit failed or
    touched a contact in the window), the three figures}}}}. The measured bounce uses the first
    model's ball radius and table.
    """
    models = default_models() if models is None else dict(models)
    if not models:
        raise ValueError("validate_trajectories: no models to validate")
    trajectories = load_trajectories(path)
    first_name = next(iter(models))
    first_params = models[first_name].params if isinstance(models[first_name], FlightModel) else models[first_name]
    usable, skipped = [], {}
    for trajectory in trajectories:
        if fit_window_samples(trajectory, first_params, fit_window).size < MIN_FIT_SAMPLES:
            reason = f"fewer than {MIN_FIT_SAMPLES} samples before the bounce in the first {fit_window} s"
            skipped[reason] = skipped.get(reason, 0) + 1
        else:
            usable.append(trajectory)
    by_model = {}
    for name, model in models.items():
        progress(f"trajectories: model {name}, {len(usable)} of {len(trajectories)} trajectories from {path}")
        by_model[name] = evaluate_model(usable, model, fit_window)
    first = by_model[first_name]
    return {"trajectories": {
        "data": str(path),
        "fit_window_s": fit_window,
        "count": len(trajectories),
        "fitted": first["fitted"],
        "without_bounce": sum(measured_bounce_index(t, first_params) is None for t in usable),
        "skipped": skipped,
        "model": first_name,
        **{key: first[key] for key in ("pre_bounce_error_m", "pre_bounce_all_samples_error_m", "post_bounce_error_m")},
        "models": by_model,
    }}


def format_trajectory_figures(result: dict) -> str:
    """A plain-text table of ``validate_trajectories``' figures, one row per model: median/p90 of
    the position error in mm at the last pre-bounce sample, at all pre-bounce samples, after it."""
    figures = result.get("trajectories", result)
    width = max(16, *(len(name) + 2 for name in figures["models"]))
    header = f"{'model':<{width}}{'spin':>9}{'fitted':>8}  {'pre-bounce last':>16}  {'pre-bounce all':>15}  {'post-bounce':>13}"
    lines = [header, "-" * len(header)]

    def cell(values: dict, cell_width: int) -> str:
        text = "-" if values["median"] is None else f"{values['median'] * 1e3:.1f}/{values['p90'] * 1e3:.1f}"
        return f"{text:>{cell_width}}"

    for name, model in figures["models"].items():
        lines.append(f"{name:<{width}}{model['spin']:>9}{model['fitted']:>8}  {cell(model['pre_bounce_error_m'], 16)}  "
                     f"{cell(model['pre_bounce_all_samples_error_m'], 15)}  {cell(model['post_bounce_error_m'], 13)}")
    lines.append(f"(median/p90 of the position error, mm; {figures['count']} trajectories, split at the measured bounce)")
    for reason, count in figures["skipped"].items():
        lines.append(f"skipped {count}: {reason}")
    for name, model in figures["models"].items():
        for reason, count in model["skipped"].items():
            lines.append(f"skipped {count} for {name}: {reason}")
    return "\n".join(lines)
