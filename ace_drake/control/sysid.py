"""System identification of the joints (paper, Methods *Robot dynamics*).

From a logged trace of commanded and measured positions per joint, fit a continuous-time process
model with input delay, K w^2 / (s^2 + 2 zeta w s + w^2) e^{-tau s}, by output-error least squares
on the exactly sampled model (``joint_model.simulate_joint``), then convert it to the state-space
form of paper eq. (9). The delay enters the fit as a continuous parameter; a grid over it seeds
the search because the output error is not convex in the delay.

Log format: a CSV with a ``time`` column (s, uniformly sampled) and, per joint, the columns
``<joint>_command`` and ``<joint>_position`` (rad or m).
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml
from scipy.optimize import least_squares

from ace_drake.artefacts import data_file, sidecar_path, write_sidecar
from ace_drake.config import MODELS_DIR, ConfigError, InputError, load_config
from ace_drake.control.joint_model import ProcessModel, ramp_tracking_lag, simulate_joint
from ace_drake.robot.params import JOINT_NAMES, JointDynamicsParams, RobotDynamicsParams

DELAY_GRID_STEP = 0.25e-3  # s
MAX_DELAY = 0.02  # s


class JointLogError(InputError):
    """A joint log is missing, malformed or not uniformly sampled; the message says which."""


@dataclasses.dataclass(frozen=True)
class JointLog:
    """Uniformly sampled trace: times (N,) s, and per joint name the commanded and measured (N,)."""

    times: np.ndarray
    commands: dict[str, np.ndarray]
    positions: dict[str, np.ndarray]

    @property
    def period(self) -> float:
        """Sample period, s."""
        return float(np.median(np.diff(self.times)))


@dataclasses.dataclass(frozen=True)
class SysidResult:
    """The identified process model and its eq. (9) form, with the fit's quality.

    rms_error: RMS of measured minus simulated position (rad or m); fit_percent: 100 (1 -
    |error| / |measured - mean|), the usual normalised fit of identification toolboxes.
    """

    process: ProcessModel
    params: JointDynamicsParams
    rms_error: float
    fit_percent: float


def identify_joint(times: np.ndarray, command: np.ndarray, measured: np.ndarray) -> SysidResult:
    """Fits gain, natural frequency, damping ratio and delay to one joint's trace."""
    times, command, measured = (np.asarray(a, dtype=float) for a in (times, command, measured))
    if not (times.shape == command.shape == measured.shape) or times.ndim != 1:
        raise JointLogError(f"identify_joint: time, command and position must be equal-length 1-D arrays, got {times.shape}, {command.shape}, {measured.shape}")
    if times.size < 100:
        raise JointLogError(f"identify_joint: need at least 100 samples, got {times.size}")
    if not (np.all(np.isfinite(command)) and np.all(np.isfinite(measured)) and np.all(np.isfinite(times))):
        raise JointLogError("identify_joint: the trace contains NaN or inf")
    period = _uniform_period(times)
    if np.ptp(command) == 0:
        raise JointLogError("identify_joint: the command never changes; the joint is not excited")

    def residuals(theta: np.ndarray) -> np.ndarray:
        gain, frequency, damping, delay = theta
        joint = ProcessModel(gain, frequency, damping, delay).to_state_space()
        return simulate_joint(joint, command, period) - measured

    lower = np.array([0.5, 10.0, 0.1, 0.0])
    upper = np.array([2.0, 1e4, 3.0, MAX_DELAY])
    best = None
    for delay in np.arange(0.0, MAX_DELAY, DELAY_GRID_STEP):
        # Gain, frequency and damping for this delay, from a generic start.
        fit = least_squares(
            lambda x: residuals(np.r_[x, delay]), x0=[1.0, 500.0, 0.8],
            bounds=(lower[:3], upper[:3]), x_scale=[1.0, 100.0, 0.1], max_nfev=60,
        )
        if best is None or fit.cost < best[0]:
            best = (fit.cost, np.r_[fit.x, delay])
    final = least_squares(residuals, best[1], bounds=(lower, upper), x_scale=[1.0, 100.0, 0.1, 1e-3], max_nfev=200)
    process = ProcessModel(*(float(v) for v in final.x))
    error = residuals(final.x)
    return SysidResult(
        process=process,
        params=process.to_state_space(),
        rms_error=float(np.sqrt(np.mean(error**2))),
        fit_percent=float(100.0 * (1.0 - np.linalg.norm(error) / np.linalg.norm(measured - measured.mean()))),
    )


def load_joint_log(path: str | Path) -> JointLog:
    """Reads a joint log CSV (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise JointLogError(f"joint log not found: {path}")
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        columns = reader.fieldnames or []
        if "time" not in columns:
            raise JointLogError(f"{path}: no 'time' column (columns: {columns})")
        joints = [c[: -len("_command")] for c in columns if c.endswith("_command")]
        missing = [f"{j}_position" for j in joints if f"{j}_position" not in columns]
        if not joints or missing:
            raise JointLogError(f"{path}: expected '<joint>_command' and '<joint>_position' column pairs; missing {missing or 'all'}")
        try:
            rows = [{k: float(v) for k, v in row.items()} for row in reader]
        except (TypeError, ValueError) as error:
            raise JointLogError(f"{path}: non-numeric value: {error}") from None
    if not rows:
        raise JointLogError(f"{path}: no samples")
    times = np.array([r["time"] for r in rows])
    _uniform_period(times, str(path))
    return JointLog(
        times=times,
        commands={j: np.array([r[f"{j}_command"] for r in rows]) for j in joints},
        positions={j: np.array([r[f"{j}_position"] for r in rows]) for j in joints},
    )


def write_joint_log(path: str | Path, log: JointLog) -> None:
    """Writes ``log`` in the CSV format ``load_joint_log`` reads."""
    joints = list(log.commands)
    with Path(path).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["time"] + [f"{j}_{kind}" for j in joints for kind in ("command", "position")])
        for n, t in enumerate(log.times):
            writer.writerow([f"{t:.6f}"] + [f"{a[j][n]:.9g}" for j in joints for a in (log.commands, log.positions)])


def synthetic_joint_log(
    joints: dict[str, JointDynamicsParams],
    duration: float = 4.0,
    period: float = 1e-3,
    noise: float = 1e-4,
    seed: int = 0,
) -> JointLog:
    """A log of each joint's response to a random staircase of commands (held 20-200 ms, steps of
    up to 0.3 rad or m) with Gaussian measurement noise of ``noise`` (rad or m); for tests and
    tutorials, and for checking an identification before trusting it on a real robot."""
    rng = np.random.default_rng(seed)
    n = int(round(duration / period))
    times = np.arange(n) * period
    commands, positions = {}, {}
    for name, joint in joints.items():
        command = np.zeros(n)
        index, level = 0, 0.0
        while index < n:
            hold = int(rng.integers(20, 200))
            command[index : index + hold] = level
            index += hold
            level = float(np.clip(level + rng.uniform(-0.3, 0.3), -1.0, 1.0))
        commands[name] = command
        positions[name] = simulate_joint(joint, command, period) + noise * rng.standard_normal(n)
    return JointLog(times, commands, positions)


def _uniform_period(times: np.ndarray, where: str = "identify_joint") -> float:
    steps = np.diff(times)
    if steps.size == 0 or np.any(steps <= 0):
        raise JointLogError(f"{where}: time must increase strictly")
    period = float(np.median(steps))
    if np.max(np.abs(steps - period)) > 0.01 * period:
        raise JointLogError(f"{where}: samples are not uniform (period {period:.6g} s, steps from {steps.min():.6g} to {steps.max():.6g} s)")
    return period


def identify_and_write(log, out=MODELS_DIR / "joint_dynamics_identified.yaml", progress: Callable[[str], None] = print) -> dict:
    """``ace-drake sysid``: identifies each joint of the joint log CSV ``log`` (``identify_joint``)
    and writes ``out``, a ``RobotDynamicsParams`` YAML (joints absent from the log keep the
    defaults), and its sidecar (``artefacts.write_sidecar``: the log, per joint the process model
    with its fit and ramp tracking lag in s, the defaulted joints). Returns the sidecar; raises
    ConfigError for a joint the robot does not have."""
    joint_log = load_joint_log(log)
    unknown = sorted(set(joint_log.commands) - set(JOINT_NAMES))
    if unknown:
        raise ConfigError(f"{log}: unknown joint(s) {unknown}; the robot's joints are {list(JOINT_NAMES)}")
    defaults = RobotDynamicsParams()
    identified = {}
    for name in joint_log.commands:
        progress(f"identifying {name} from {joint_log.times.size} samples at {1 / joint_log.period:.0f} Hz")
        result = identify_joint(joint_log.times, joint_log.commands[name], joint_log.positions[name])
        identified[name] = result
        progress(f"  K {result.process.gain:.4f}  w {result.process.natural_frequency:.1f} rad/s  "
                 f"zeta {result.process.damping_ratio:.3f}  tau_d {1000 * result.process.delay:.3f} ms  fit {result.fit_percent:.2f} %")
    joints = [identified[n].params if n in identified else defaults.joints[i] for i, n in enumerate(JOINT_NAMES)]
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = (
        "# Joint dynamics (paper eq. (9)) identified by `ace-drake sysid`; joints in the order\n"
        f"# {', '.join(JOINT_NAMES)}. Joints absent from the log keep the defaults. See {sidecar_path(out).name}.\n"
    )
    body = {"joints": [{"a": list(j.a), "b": list(j.b), "delay": j.delay} for j in joints],
            "command_period": joint_log.period}
    out.write_text(header + yaml.safe_dump(body, sort_keys=False))
    load_config(RobotDynamicsParams, out)  # what was written must load
    report = {
        name: {**dataclasses.asdict(r.process), "rms_error": r.rms_error, "fit_percent": r.fit_percent,
               "ramp_tracking_lag_s": ramp_tracking_lag(r.params)}
        for name, r in identified.items()
    }
    sidecar = write_sidecar(
        out,
        log=data_file(log, samples=int(joint_log.times.size)),
        identified=report,
        defaulted=[n for n in JOINT_NAMES if n not in identified],
    )
    progress(f"wrote {out} and {sidecar_path(out)}")
    return sidecar
