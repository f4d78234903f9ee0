"""The racket residual MLP (paper, Methods *Ball-racket contact model*): zero start, fit, storage."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from ace_drake.physics.contact import racket_contact_features, racket_impact, racket_restitution
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.racket_residual import (
    RacketResidualMLP,
    fit_racket_residual,
    load_residual,
    save_residual,
)

PARAMS = BallPhysicsParams()
RADIUS = PARAMS.aero.ball_radius


def _unit(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _contacts(n, seed):
    """Random approaching contacts: (pre (n, 9), racket velocity (n, 3), R_WC (n, 3, 3), offsets (n, 2))."""
    rng = np.random.default_rng(seed)
    R_WC = Rotation.random(n, random_state=seed).as_matrix()
    v = _unit(rng, n) * rng.uniform(2.0, 15.0, (n, 1))  # m/s
    w = _unit(rng, n) * rng.uniform(0.0, 500.0, (n, 1))  # rad/s
    v_racket = _unit(rng, n) * rng.uniform(0.0, 10.0, (n, 1))  # m/s
    # The ball must approach the blade (v_rel_C z < 0): turn the frame over (180 deg about x) if not.
    receding = np.einsum("nij,ni->nj", R_WC, v - v_racket)[:, 2] >= 0.0
    R_WC[receding] = R_WC[receding] @ np.diag([1.0, -1.0, -1.0])
    offsets = rng.uniform(-0.05, 0.05, (n, 2))  # m
    pre = np.concatenate([rng.uniform(-1.0, 1.0, (n, 3)), v, w], axis=1)
    return pre, v_racket, R_WC, offsets


def _planted(features):
    """A smooth distortion in C the linear model cannot represent: (n, 6) [m/s x3, rad/s x3].

    The normal restitution is scaled by 1 + 0.05 tanh(w_z / 200 + |v_t| / 5 - 1), and the spin gains
    3 tanh(|v_t| / 3) (-v_y, v_x, 0) rad/s, saturating in the tangential relative speed |v_t|.
    """
    v, w = features[:, :3], features[:, 3:6]
    v_t = np.hypot(v[:, 0], v[:, 1])
    eps = racket_restitution(v[:, 2], PARAMS.racket)
    out = np.zeros((len(features), 6))
    out[:, 2] = -eps * v[:, 2] * 0.05 * np.tanh(w[:, 2] / 200.0 + v_t / 5.0 - 1.0)
    gain = 3.0 * np.tanh(v_t / 3.0)
    out[:, 3] = -gain * v[:, 1]
    out[:, 4] = gain * v[:, 0]
    return out


def _observed(pre, v_racket, R_WC, offsets, rng=None):
    """'True' post states = linear model + planted distortion (+ small noise if rng); and the distortion."""
    v, w = pre[:, 3:6], pre[:, 6:9]
    distortion = _planted(racket_contact_features(v, w, v_racket, R_WC, offsets))
    v_lin, w_lin = racket_impact(v, w, v_racket, R_WC, PARAMS.racket, RADIUS)
    post = pre.copy()
    post[:, 3:6] = v_lin + np.einsum("nij,nj->ni", R_WC, distortion[:, :3])
    post[:, 6:9] = w_lin + np.einsum("nij,nj->ni", R_WC, distortion[:, 3:])
    if rng is not None:
        post[:, 3:6] += 0.005 * rng.standard_normal((len(pre), 3))  # m/s
        post[:, 6:9] += 0.5 * rng.standard_normal((len(pre), 3))  # rad/s
    return post, distortion


def _r2(predicted, planted):
    return 1.0 - np.sum((predicted - planted) ** 2) / np.sum((planted - planted.mean(axis=0)) ** 2)


def test_fresh_model_is_exactly_the_linear_model():
    model = RacketResidualMLP()
    assert model.hidden == (64, 64, 32)
    out = model(torch.randn(50, 8) * 100.0)
    assert out.shape == (50, 6)
    assert torch.all(out == 0.0)

    pre, v_racket, R_WC, offsets = _contacts(200, seed=3)
    v, w = pre[:, 3:6], pre[:, 6:9]
    residual = model.as_numpy()
    correction = residual(racket_contact_features(v, w, v_racket, R_WC, offsets))
    assert correction.dtype == np.float64 and correction.shape == (200, 6)
    assert np.all(correction == 0.0)
    plain = racket_impact(v, w, v_racket, R_WC, PARAMS.racket, RADIUS)
    corrected = racket_impact(v, w, v_racket, R_WC, PARAMS.racket, RADIUS, offsets, residual=residual)
    for a, b in zip(plain, corrected):
        np.testing.assert_array_equal(a, b)
    # Unbatched inputs go through the same adapter.
    single = racket_impact(v[0], w[0], v_racket[0], R_WC[0], PARAMS.racket, RADIUS, residual=residual)
    np.testing.assert_array_equal(single[0], plain[0][0])


def test_contact_features_are_what_racket_impact_passes():
    pre, v_racket, R_WC, offsets = _contacts(100, seed=4)
    v, w = pre[:, 3:6], pre[:, 6:9]
    seen = []
    constant = np.array([0.1, -0.2, 0.3, 10.0, -20.0, 30.0])

    def recording(features):
        seen.append(features.copy())
        return np.tile(constant, (len(features), 1))

    v_post, w_post = racket_impact(v, w, v_racket, R_WC, PARAMS.racket, RADIUS, offsets, recording)
    features = racket_contact_features(v, w, v_racket, R_WC, offsets)
    np.testing.assert_array_equal(seen[0], features)
    np.testing.assert_allclose(features[:, :3], np.einsum("nji,nj->ni", R_WC, v - v_racket), atol=1e-12)
    np.testing.assert_allclose(features[:, 3:6], np.einsum("nji,nj->ni", R_WC, w), atol=1e-12)
    np.testing.assert_array_equal(features[:, 6:], offsets)
    np.testing.assert_array_equal(racket_contact_features(v, w, v_racket, R_WC)[:, 6:], 0.0)
    # The correction is added in C: post - linear post = R_WC constant.
    v_lin, w_lin = racket_impact(v, w, v_racket, R_WC, PARAMS.racket, RADIUS)
    np.testing.assert_allclose(v_post - v_lin, R_WC @ constant[:3], atol=1e-12)
    np.testing.assert_allclose(w_post - w_lin, R_WC @ constant[3:], atol=1e-9)


def test_fit_recovers_planted_distortion():
    pre, v_racket, R_WC, offsets = _contacts(3000, seed=0)
    post, _ = _observed(pre, v_racket, R_WC, offsets, rng=np.random.default_rng(10))
    history = []
    model, report = fit_racket_residual(
        pre, v_racket, R_WC, post, PARAMS, offsets,
        epochs=100, lr=3e-3, batch_size=128, seed=0,
        progress=lambda epoch, train, val: history.append((epoch, train, val)),
    )
    print(
        f"\nvelocity RMS {report.velocity_rms_before:.4f} -> {report.velocity_rms_after:.4f} m/s, "
        f"spin RMS {report.spin_rms_before:.3f} -> {report.spin_rms_after:.3f} rad/s "
        f"({report.n_train} train / {report.n_validation} validation, best epoch {report.best_epoch})"
    )
    assert report.n_samples == 3000 and report.n_validation == 600
    assert len(history) == report.epochs_run and history[-1][2] < history[0][2]
    assert report.velocity_rms_after < 0.25 * report.velocity_rms_before
    assert report.spin_rms_after < 0.25 * report.spin_rms_before

    # On fresh contacts the predicted correction is the planted distortion.
    pre, v_racket, R_WC, offsets = _contacts(2000, seed=1)
    _, planted = _observed(pre, v_racket, R_WC, offsets)
    predicted = model.as_numpy()(racket_contact_features(pre[:, 3:6], pre[:, 6:9], v_racket, R_WC, offsets))
    r2_velocity, r2_spin = _r2(predicted[:, :3], planted[:, :3]), _r2(predicted[:, 3:], planted[:, 3:])
    print(f"held-out R^2 of the correction: velocity {r2_velocity:.4f}, spin {r2_spin:.4f}")
    assert r2_velocity > 0.8
    assert r2_spin > 0.8


def _small_fit(seed):
    pre, v_racket, R_WC, offsets = _contacts(400, seed=5)
    post, _ = _observed(pre, v_racket, R_WC, offsets)
    return fit_racket_residual(
        pre, v_racket, R_WC, post, PARAMS, offsets, hidden=(16, 8), epochs=4, batch_size=64, seed=seed
    )


def test_same_seed_same_weights():
    first, report_a = _small_fit(seed=7)
    torch.manual_seed(123)  # the global RNG state must not matter
    second, report_b = _small_fit(seed=7)
    other, _ = _small_fit(seed=8)
    state_a, state_b, state_c = first.state_dict(), second.state_dict(), other.state_dict()
    assert all(torch.equal(state_a[k], state_b[k]) for k in state_a)
    assert report_a == report_b
    assert not all(torch.equal(state_a[k], state_c[k]) for k in state_a)


def test_save_load_round_trip(tmp_path):
    model, report = _small_fit(seed=0)
    path = tmp_path / "residual" / "racket_residual.pt"
    sidecar = save_residual(model, path, {"data": "synthetic", "report": report.as_dict()})
    assert sidecar == path.with_suffix(".json")
    record = json.loads(sidecar.read_text())
    assert record["data"] == "synthetic" and record["report"]["n_samples"] == 400
    assert record["architecture"] == {"in_features": 8, "hidden": [16, 8], "out_features": 6, "activation": "silu"}

    loaded = load_residual(path)
    x = torch.randn(64, 8) * torch.tensor([5, 5, 5, 200, 200, 200, 0.03, 0.03])
    with torch.no_grad():
        assert torch.equal(model(x), loaded(x))
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])

    relu = RacketResidualMLP((8,), activation="relu")
    save_residual(relu, tmp_path / "relu.pt", {})
    assert load_residual(tmp_path / "relu.pt").activation == "relu"


def test_bad_inputs_raise_value_error():
    pre, v_racket, R_WC, offsets = _contacts(50, seed=6)
    post, _ = _observed(pre, v_racket, R_WC, offsets)
    good = dict(pre_states=pre, racket_velocities=v_racket, R_WC=R_WC, post_states=post, params=PARAMS)
    cases = [
        (dict(pre_states=pre[:, :6]), r"pre_states must have shape \(N, 9\)"),
        (dict(racket_velocities=v_racket[:-1]), r"racket_velocities must have shape \(N, 3\) with N = 50"),
        (dict(R_WC=R_WC[:, :2]), r"R_WC must have shape \(N, 3, 3\)"),
        (dict(post_states=post.T), r"post_states must have shape \(N, 9\)"),
        (dict(contact_offsets=offsets[:, :1]), r"contact_offsets must have shape \(N, 2\)"),
        (dict(R_WC=2.0 * R_WC), r"R_WC must hold rotation matrices"),
        (dict(post_states=np.where(post > 0, np.nan, post)), r"post_states must be finite"),
        (dict(validation_fraction=1.0), r"validation_fraction"),
        (dict(hidden=(16, 0)), r"hidden must be"),
        (dict(epochs=0), r"epochs must be a positive integer"),
    ]
    for override, message in cases:
        with pytest.raises(ValueError, match=message):
            fit_racket_residual(**{**good, **override})
    with pytest.raises(ValueError, match=r"features must have shape \(N, 8\)"):
        RacketResidualMLP().as_numpy()(np.zeros((3, 7)))
    with pytest.raises(ValueError, match="activation"):
        RacketResidualMLP(activation="tanh")
