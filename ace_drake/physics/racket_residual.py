"""Learned residual correction to the ball-racket contact model (paper, Methods *Ball-racket contact model*).

The paper corrects the linear model of eqs (7)-(8) with "a small multilayer perceptron trained on
game data", which reduces the velocity and spin error by 4% on average; the authors' config uses
hidden layers (64, 64, 32). Here the network sees the contact in the contact frame C (z along the
blade normal, towards the ball) and predicts additive corrections to the post-contact state:

    features (N, 8) = [v_rel_C (3, m/s), w_C (3, rad/s), contact offset in C's x-y (2, m)]
    output   (N, 6) = [delta v+_C (3, m/s), delta w+_C (3, rad/s)]

``racket_impact(..., residual=model.as_numpy())`` adds them to the linear model's post-contact
velocity (relative to the racket) and spin before rotating back to world. A fresh network outputs
exactly zero, so an untrained model is the linear model. ``contact.racket_contact_features``
computes the features; ``fit_racket_residual`` fits a network to observed (pre, post) contact
pairs; ``save_residual`` / ``load_residual`` store it.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn

from ace_drake.artefacts import dumps, sidecar_path, write_sidecar
from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.physics.contact import racket_contact_features, racket_impact
from ace_drake.physics.flight import SPIN, VELOCITY
from ace_drake.physics.params import BallPhysicsParams, RacketParams

N_FEATURES = 8  # [v_rel_C (3), w_C (3), contact offset (2)]
N_OUTPUTS = 6  # [delta v+_C (3), delta w+_C (3)]
DEFAULT_HIDDEN = (64, 64, 32)  # authors' config
_ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU}
_FORMAT_VERSION = 1


class RacketResidualMLP(nn.Module):
    """MLP correction to the racket contact model (paper, Methods *Ball-racket contact model*).

    ``forward`` maps physical features (N, 8) to physical corrections (N, 6), units as in the
    module docstring. Inputs are standardised with the ``feature_mean`` / ``feature_std`` buffers
    and outputs multiplied by ``target_scale`` (m/s for the first three, rad/s for the last three;
    ``fit_racket_residual`` sets one value per group, the targets' RMS component),
    so a saved state_dict is self-contained. The last layer starts at zero: a fresh module outputs
    exactly 0 and leaves the linear model unchanged.

    Args:
        hidden: hidden layer widths; (64, 64, 32) as in the authors' config.
        activation: "silu" (default, smooth) or "relu".
    """

    def __init__(self, hidden: Sequence[int] = DEFAULT_HIDDEN, activation: str = "silu"):
        super().__init__()
        self.hidden = _check_hidden(hidden)
        if activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        self.activation = activation
        layers: list[nn.Module] = []
        width = N_FEATURES
        for size in self.hidden:
            layers += [nn.Linear(width, size), _ACTIVATIONS[activation]()]
            width = size
        last = nn.Linear(width, N_OUTPUTS)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*layers, last)
        self.register_buffer("feature_mean", torch.zeros(N_FEATURES))
        self.register_buffer("feature_std", torch.ones(N_FEATURES))
        self.register_buffer("target_scale", torch.ones(N_OUTPUTS))

    def forward_normalised(self, features: torch.Tensor) -> torch.Tensor:
        """Network output in normalised units (corrections divided by ``target_scale``), (N, 6)."""
        return self.net((features - self.feature_mean) / self.feature_std)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Corrections (N, 6) [m/s x3, rad/s x3] in C for features (N, 8) in physical units."""
        return self.forward_normalised(features) * self.target_scale

    def as_numpy(self) -> "NumpyResidual":
        """A numpy callable (N, 8) -> (N, 6) float64 for ``racket_impact(..., residual=...)``."""
        return NumpyResidual(self)


class NumpyResidual:
    """Wraps a ``RacketResidualMLP`` as ``features (N, 8) ndarray -> corrections (N, 6) float64``.

    Evaluates a float64 copy of the module under ``torch.no_grad``, so that the returner's Newton
    iterations through it see a smooth function (float32 rounding at 10 m/s inputs is ~1e-6, the
    size of their finite-difference steps); the copy is refreshed when the module's weights change.
    """

    def __init__(self, model: RacketResidualMLP):
        self.model = model
        self._copy, self._version = None, None

    def __call__(self, features: np.ndarray) -> np.ndarray:
        features = np.asarray(features)
        if features.ndim != 2 or features.shape[1] != N_FEATURES:
            raise ValueError(f"features must have shape (N, {N_FEATURES}), got {features.shape}")
        version = tuple(parameter._version for parameter in self.model.state_dict().values())
        if self._copy is None or version != self._version:
            self._copy = copy.deepcopy(self.model).double().eval()
            self._version = version
        with torch.no_grad():
            out = self._copy(torch.as_tensor(features, dtype=torch.float64))
        return out.numpy()


@dataclasses.dataclass(frozen=True)
class ResidualFitReport:
    """Validation errors of the post-contact state, before (linear model) and after the residual.

    RMS values are sqrt(mean |error|^2) over the validation contacts of the 3-vector error:
    velocity in m/s, spin in rad/s (frame-independent).
    """

    n_samples: int
    n_train: int
    n_validation: int
    velocity_rms_before: float  # m/s
    velocity_rms_after: float  # m/s
    spin_rms_before: float  # rad/s
    spin_rms_after: float  # rad/s
    epochs_run: int
    best_epoch: int  # 1-based epoch whose weights were kept (lowest validation loss)
    best_validation_loss: float  # MSE of normalised targets

    def as_dict(self) -> dict:
        """Plain-dict form (JSON-ready), e.g. for the ``save_residual`` sidecar."""
        return dataclasses.asdict(self)


def fit_racket_residual(
    pre_states,
    racket_velocities,
    R_WC,
    post_states,
    params: BallPhysicsParams,
    contact_offsets=None,
    hidden: Sequence[int] = DEFAULT_HIDDEN,
    epochs: int = 500,
    lr: float = 1e-3,
    batch_size: int = 128,
    seed: int = 0,
    validation_fraction: float = 0.2,
    progress: Callable[[int, float, float], None] | None = None,
    patience: int = 50,
    activation: str = "silu",
    groups: Sequence | None = None,
) -> tuple[RacketResidualMLP, ResidualFitReport]:
    """Fits the racket residual MLP to observed contacts (paper, Methods *Ball-racket contact model*).

    The target is the linear model's error expressed in C: R_WC^T (v+_obs - v+_lin) (m/s; the
    racket velocity cancels, so it is also the error of the relative velocity) and
    R_WC^T (w+_obs - w+_lin) (rad/s), with (v+_lin, w+_lin) = ``racket_impact(..., residual=None)``.
    Features are standardised on the training split and targets divided by one RMS scale per group
    (velocity, spin); Adam minimises the MSE of the normalised targets and the weights with the
    lowest validation loss are kept (early stopping after ``patience`` epochs without improvement).
    Deterministic for a given ``seed`` (weights, split and batches); runs single-threaded and
    restores the global torch RNG and thread count.

    Args:
        pre_states, post_states: (N, 9) ball states [p (m), v (m/s), w (rad/s)] in world just
            before and after the contact.
        racket_velocities: (N, 3) velocity of the racket's material point at the contact, m/s.
        R_WC: (N, 3, 3) contact frame in world (z = blade normal towards the ball).
        params: ball physics; uses ``params.racket`` and ``params.aero.ball_radius``.
        contact_offsets: (N, 2) contact point on the blade in C's x-y, m; None is the centre.
        hidden, activation: network architecture, see ``RacketResidualMLP``.
        epochs, lr, batch_size, patience: Adam training; epochs is the maximum.
        seed: seeds the network initialisation, the validation split and the batch order.
        validation_fraction: share of samples held out for early stopping and the report.
        progress: optional callable(epoch, train_loss, val_loss), called after every epoch.
        groups: (N,) a label per sample (e.g. its game): the validation split then takes whole
            groups (about ``validation_fraction`` of the samples), so that early stopping judges
            the network on contacts uncorrelated with its training ones; None splits samples.
    Returns (model, report); the model is in eval mode.
    """
    pre_states = _as_array("pre_states", pre_states, ("N", 9))
    n = pre_states.shape[0]
    racket_velocities = _as_array("racket_velocities", racket_velocities, ("N", 3), n)
    R_WC = _as_array("R_WC", R_WC, ("N", 3, 3), n)
    post_states = _as_array("post_states", post_states, ("N", 9), n)
    if contact_offsets is not None:
        contact_offsets = _as_array("contact_offsets", contact_offsets, ("N", 2), n)
    orthonormality = np.abs(np.einsum("nji,njk->nik", R_WC, R_WC) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((orthonormality > 1e-6) | (np.linalg.det(R_WC) < 0.0))
    if bad.size:
        raise ValueError(f"R_WC must hold rotation matrices; R_WC[{bad[0]}] is not one")
    hidden = _check_hidden(hidden)
    if not 0.0 < validation_fraction < 1.0:
        raise ValueError(f"validation_fraction must be in (0, 1), got {validation_fraction}")
    n_val = int(round(validation_fraction * n))
    if n_val < 1 or n - n_val < 1:
        raise ValueError(
            f"pre_states: {n} samples leave an empty training or validation split "
            f"(validation_fraction={validation_fraction})"
        )
    for name, value in (("epochs", epochs), ("batch_size", batch_size), ("patience", patience)):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value}")
    if not lr > 0.0:
        raise ValueError(f"lr must be positive, got {lr}")

    racket, radius = params.racket, params.aero.ball_radius
    v_pre, w_pre = pre_states[:, VELOCITY], pre_states[:, SPIN]
    v_obs, w_obs = post_states[:, VELOCITY], post_states[:, SPIN]
    features = racket_contact_features(v_pre, w_pre, racket_velocities, R_WC, contact_offsets)
    v_lin, w_lin = racket_impact(v_pre, w_pre, racket_velocities, R_WC, racket, radius)
    targets = np.concatenate(
        [np.einsum("nji,nj->ni", R_WC, v_obs - v_lin), np.einsum("nji,nj->ni", R_WC, w_obs - w_lin)], -1
    )

    rng = np.random.default_rng(seed)
    if groups is None:
        order = rng.permutation(n)
        val_idx, train_idx = np.sort(order[:n_val]), np.sort(order[n_val:])
    else:
        labels = np.asarray(groups)
        if labels.shape != (n,):
            raise ValueError(f"groups must have shape ({n},), got {labels.shape}")
        names, counts = np.unique(labels, return_counts=True)
        if names.size < 2:
            raise ValueError("groups: a split by group needs at least 2 groups")
        order = rng.permutation(names.size)
        taken = np.cumsum(counts[order])
        chosen = names[order[: max(1, min(names.size - 1, int(np.searchsorted(taken, n_val)) + 1))]]
        held = np.isin(labels, chosen)
        val_idx, train_idx = np.flatnonzero(held), np.flatnonzero(~held)
        n_val = val_idx.size

    feature_mean = features[train_idx].mean(axis=0)
    feature_std = features[train_idx].std(axis=0)
    feature_std = np.where(feature_std > 1e-9, feature_std, 1.0)  # constant feature (e.g. no offsets)
    # One scale per group (velocity, spin), the RMS of its components: a per-component scale would
    # blow up components that are mostly noise (e.g. a distortion along the normal only).
    group_rms = np.sqrt(np.mean(targets[train_idx].reshape(-1, 2, 3) ** 2, axis=(0, 2)))
    target_scale = np.repeat(np.where(group_rms > 1e-12, group_rms, 1.0), 3)

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = RacketResidualMLP(hidden, activation)
        model.feature_mean.copy_(torch.as_tensor(feature_mean, dtype=torch.float32))
        model.feature_std.copy_(torch.as_tensor(feature_std, dtype=torch.float32))
        model.target_scale.copy_(torch.as_tensor(target_scale, dtype=torch.float32))

        x = torch.as_tensor(features, dtype=torch.float32)
        y = torch.as_tensor(targets / target_scale, dtype=torch.float32)
        x_train, y_train = x[train_idx], y[train_idx]
        x_val, y_val = x[val_idx], y[val_idx]
        optimiser = torch.optim.Adam(model.parameters(), lr=lr)
        best_loss, best_epoch, best_state = np.inf, 0, _clone_state(model)
        epochs_run = 0
        for epoch in range(1, int(epochs) + 1):
            model.train()
            batches = rng.permutation(len(train_idx))
            total = 0.0
            for start in range(0, len(batches), int(batch_size)):
                batch = torch.as_tensor(batches[start : start + int(batch_size)])
                loss = torch.mean((model.forward_normalised(x_train[batch]) - y_train[batch]) ** 2)
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                total += loss.item() * len(batch)
            model.eval()
            with torch.no_grad():
                val_loss = torch.mean((model.forward_normalised(x_val) - y_val) ** 2).item()
            epochs_run = epoch
            if progress is not None:
                progress(epoch, total / len(batches), val_loss)
            if val_loss < best_loss:
                best_loss, best_epoch, best_state = val_loss, epoch, _clone_state(model)
            elif epoch - best_epoch >= patience:
                break
        model.load_state_dict(best_state)
        model.eval()

        v_fit, w_fit = racket_impact(
            v_pre[val_idx],
            w_pre[val_idx],
            racket_velocities[val_idx],
            R_WC[val_idx],
            racket,
            radius,
            None if contact_offsets is None else contact_offsets[val_idx],
            residual=model.as_numpy(),
        )
    finally:
        torch.set_num_threads(threads)

    report = ResidualFitReport(
        n_samples=n,
        n_train=len(train_idx),
        n_validation=n_val,
        velocity_rms_before=_rms(v_obs[val_idx] - v_lin[val_idx]),
        velocity_rms_after=_rms(v_obs[val_idx] - v_fit),
        spin_rms_before=_rms(w_obs[val_idx] - w_lin[val_idx]),
        spin_rms_after=_rms(w_obs[val_idx] - w_fit),
        epochs_run=epochs_run,
        best_epoch=best_epoch,
        best_validation_loss=float(best_loss),
    )
    return model, report


def save_residual(model: RacketResidualMLP, path, sidecar: dict | None = None) -> Path:
    """Writes the model (torch state_dict plus architecture) to ``path`` and its JSON sidecar.

    The sidecar (``artefacts.write_sidecar``), ``path`` with suffix ``.json``, records ``sidecar``
    (must be JSON-serialisable, e.g. the fit report's ``as_dict()`` and the data's provenance)
    plus the architecture under "architecture", with the command, date and the model file's
    sha256. Returns the sidecar's path.
    """
    path = Path(path)
    if path.suffix == ".json":
        raise ValueError(f"path must not end in .json (that name is the sidecar's), got {path}")
    architecture = {
        "in_features": N_FEATURES,
        "hidden": list(model.hidden),
        "out_features": N_OUTPUTS,
        "activation": model.activation,
    }
    record = dict(sidecar or {})
    record["architecture"] = architecture
    try:
        dumps(record)  # before anything is written
    except (TypeError, ValueError) as error:
        raise ValueError(f"sidecar must be JSON-serialisable: {error}") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    record_pt = {
        "format_version": _FORMAT_VERSION,
        "hidden": list(model.hidden),
        "activation": model.activation,
        "state_dict": state,
    }
    torch.save(record_pt, path)
    write_sidecar(path, **record)
    return sidecar_path(path)


def load_residual(path) -> RacketResidualMLP:
    """Loads a model written by ``save_residual``; it reproduces the saved outputs exactly (eval mode)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"racket residual model not found: {path}")
    data = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(data, dict) or data.get("format_version") != _FORMAT_VERSION:
        raise ValueError(f"{path}: not a racket residual model (format_version {_FORMAT_VERSION})")
    model = RacketResidualMLP(tuple(data["hidden"]), data["activation"])
    model.load_state_dict(data["state_dict"])
    model.eval()
    return model


def residual_path(racket: RacketParams) -> Path | None:
    """The network file that ``racket.residual`` names (relative to models/ unless absolute), or
    None when it names none."""
    if not racket.residual:
        return None
    path = Path(racket.residual)
    return path if path.is_absolute() else MODELS_DIR / path


_LOADED: dict[tuple, NumpyResidual] = {}


def residual_model(racket: RacketParams) -> NumpyResidual | None:
    """The racket residual that ``racket.residual`` selects, as ``racket_impact``'s ``residual``
    callable, or None. Loaded once per process and file, so the BallPlants and the returner's
    inverse share one network; a file written again is loaded again. A missing or malformed file
    is a ConfigError naming it."""
    path = residual_path(racket)
    if path is None:
        return None
    try:
        stat = path.resolve().stat()
        key = (path.resolve(), stat.st_mtime_ns, stat.st_size)
        if key not in _LOADED:
            _LOADED[key] = load_residual(path).as_numpy()
    except (FileNotFoundError, ValueError, RuntimeError, KeyError) as error:
        raise ConfigError(f"racket.residual: {error}") from None
    return _LOADED[key]


def _check_hidden(hidden) -> tuple[int, ...]:
    hidden = tuple(hidden)
    if not all(isinstance(h, (int, np.integer)) and h > 0 for h in hidden):
        raise ValueError(f"hidden must be a sequence of positive integers, got {hidden}")
    return tuple(int(h) for h in hidden)


def _as_array(name: str, value, shape: tuple, n: int | None = None) -> np.ndarray:
    """Finite float64 array of ``shape`` ("N" = n samples, any n >= 1 if None); ValueError naming ``name``."""
    array = np.asarray(value, dtype=float)
    expected = "(" + ", ".join(str(s) for s in shape) + ")" + ("" if n is None else f" with N = {n}")
    want = tuple(n if s == "N" else s for s in shape)
    if array.ndim != len(want) or any(w is not None and a != w for a, w in zip(array.shape, want)):
        raise ValueError(f"{name} must have shape {expected}, got {array.shape}")
    if array.shape[0] == 0:
        raise ValueError(f"{name} must hold at least one sample, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite")
    return array


def _clone_state(model: nn.Module) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _rms(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(error**2, axis=-1))))
