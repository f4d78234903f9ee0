"""The racket contact run backwards: which blade normal and racket velocity send a ball off with
a wanted velocity (the inverse of paper eqs (7)-(8)), and the return that lands a ball on a
target point (``solve_return``: Newton's method through the flight model, eq. (1)). The
model-based returner (``control.returner``) and the scripted swing plan their hits with it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ace_drake.physics.contact import ResidualModel, racket_impact, racket_restitution
from ace_drake.physics.params import BallPhysicsParams, RacketParams
from ace_drake.physics.propagate import simulate
from ace_drake.physics.racket_residual import residual_model

_UP = np.array([0.0, 0.0, 1.0])


def contact_frame(normal: np.ndarray) -> np.ndarray:
    """R_WC (..., 3, 3) of a contact frame with z along ``normal`` (..., 3) and x in the normal's
    vertical plane (the racket model is isotropic in the blade's plane, so any x will do)."""
    normal = np.asarray(normal, dtype=float)
    x_axis = np.cross(np.cross(normal, _UP), normal)
    x_axis /= np.linalg.norm(x_axis, axis=-1, keepdims=True)
    return np.stack([x_axis, np.cross(normal, x_axis), normal], axis=-1)


def invert_racket_contact(
    v_in: np.ndarray,
    w_in: np.ndarray,
    v_out: np.ndarray,
    racket: RacketParams,
    radius: float,
    brush_speed: float = 0.0,
    iterations: int = 20,
    residual: ResidualModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The blade normals n (..., 3) and racket velocities v_WR (..., 3) with which the racket
    contact model (paper eqs (7)-(8), as ``physics.contact.racket_impact``) sends a ball arriving
    with velocity v_in (3,; m/s) and spin w_in (3,; rad/s) off at velocities v_out (..., 3; m/s).

    The racket moves along its normal at speed s plus ``brush_speed`` b (m/s) along the blade's
    upward tangent t (v_WR = s n + b t; b > 0 brushes up: topspin). In the contact frame, eq. (7)
    splits into the blade's plane and its normal (k = tangential_k, r the ball radius):

        v_out_t = (1 - k) v_in_t + k b t - k r (n x w_in)                    (tangential)
        v_out.n - s = -eps (v_in.n - s),  eps = eps_racket(|v_in.n - s|)      (normal)

    so a + k r (n x w_in), with a = v_out - (1 - k) v_in - k b t, has no tangential part: it is
    lambda n, lambda = n.a > 0 (the ball reverses). With W the cross-product matrix of w_in that
    is (lambda I + k r W) n = a; |n| = 1 fixes lambda^2 as the positive root of
    mu^2 + (C - |a|^2) mu - (a.w_hat)^2 C = 0, C = (k r |w_in|)^2 (W is skew, so
    |(lambda I + k r W)^-1 a|^2 = (a.w_hat)^2 / lambda^2 + |a_perp|^2 / (lambda^2 + C)). The
    tangent t depends on n, so with b != 0 this repeats to a fixed point. Then
    s = (v_out.n + eps v_in.n) / (1 + eps), eps iterated to consistency. Raises ValueError if
    some v_out cannot be made: the ball would not meet the blade (v_out.n <= v_in.n), or the spin
    turns it more than the racket can undo (no root mu > 0).

    With a ``residual`` correction (``physics.racket_residual``) the closed form no longer holds:
    it gives the start, and Newton's method on (n, s) makes the full model's v_out
    (``_newton_with_residual``). The residual sees the blade's centre as the contact point and the
    contact frame of ``contact_frame(n)``: the inverse does not know the blade's roll about n."""
    v_in, w_in, v_out = (np.asarray(x, dtype=float) for x in (v_in, w_in, v_out))
    k = racket.tangential_k
    coupling = k * radius * w_in  # k r w
    cross = np.array([[0.0, -coupling[2], coupling[1]], [coupling[2], 0.0, -coupling[0]], [-coupling[1], coupling[0], 0.0]])
    spin_squared = float(coupling @ coupling)  # C
    normal = v_out - v_in
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    for _ in range(iterations if brush_speed else 1):
        a = v_out - (1.0 - k) * v_in - k * brush_speed * _blade_up(normal)
        a_squared = np.sum(a * a, axis=-1)
        if spin_squared > 0.0:
            along_squared = (a @ coupling) ** 2 / spin_squared
            linear = spin_squared - a_squared
            mu = 0.5 * (-linear + np.sqrt(linear**2 + 4.0 * along_squared * spin_squared))
        else:
            mu = a_squared
        if np.any(mu <= 1e-12):
            raise ValueError("invert_racket_contact: the ball's spin turns it more than any racket state can undo")
        system = np.sqrt(mu)[..., None, None] * np.eye(3) + cross
        updated = np.linalg.solve(system, a[..., None])[..., 0]
        updated /= np.linalg.norm(updated, axis=-1, keepdims=True)
        converged = np.max(np.abs(updated - normal)) < 1e-12
        normal = updated
        if converged:
            break
    v_in_n, v_out_n = normal @ v_in, np.sum(v_out * normal, axis=-1)
    if np.any(v_out_n <= v_in_n):
        raise ValueError(f"invert_racket_contact: the ball would not meet the blade (v_out.n = {v_out_n} <= v_in.n = {v_in_n} m/s)")
    speed = v_in_n  # s; eps at the relative normal speed |v_in.n - s|
    for _ in range(10):
        eps = racket_restitution(v_in_n - speed, racket)
        speed = (v_out_n + eps * v_in_n) / (1.0 + eps)
    if residual is not None:
        normal, speed = _newton_with_residual(v_in, w_in, v_out, normal, speed, racket, radius, brush_speed, residual)
    return normal, speed[..., None] * normal + brush_speed * _blade_up(normal)


NEWTON_TOLERANCE = 1e-9  # m/s, of the outgoing velocity
NEWTON_STEP = 1e-6  # finite-difference step: rad of the normal's tilt, m/s of the speed


def _newton_with_residual(v_in, w_in, v_out, normal, speed, racket, radius, brush_speed, residual, iterations: int = 12):
    """Newton's method on the blade normal (two tilts about the current one) and the normal speed
    s so that ``racket_impact`` with ``residual`` sends the ball off at v_out (..., 3), from the
    closed form's (normal, speed); finite-difference Jacobians, all rows and perturbations in one
    call per iteration. Raises ValueError if some row does not converge."""
    shape = v_out.shape[:-1]
    v_out, normal, speed = v_out.reshape(-1, 3), normal.reshape(-1, 3).copy(), np.reshape(speed, -1).copy()
    rows = len(v_out)

    def outgoing(normals, speeds):
        racket_velocity = speeds[:, None] * normals + brush_speed * _blade_up(normals)
        v_post, _ = racket_impact(v_in, w_in, racket_velocity, contact_frame(normals), racket, radius, residual=residual)
        return v_post

    for _ in range(iterations):
        error = outgoing(normal, speed) - v_out
        if np.max(np.abs(error)) < NEWTON_TOLERANCE:
            break
        tilt_x = np.cross(normal, _blade_up(normal))  # two axes orthogonal to the normal
        tilt_y = _blade_up(normal)
        tilted = [normal + NEWTON_STEP * tilt_x, normal + NEWTON_STEP * tilt_y]
        tilted = [n / np.linalg.norm(n, axis=-1, keepdims=True) for n in tilted]
        perturbed = outgoing(np.concatenate([*tilted, normal]), np.concatenate([speed, speed, speed + NEWTON_STEP]))
        jacobian = np.stack([(perturbed[i * rows:(i + 1) * rows] - (error + v_out)) / NEWTON_STEP for i in range(3)], axis=-1)
        step = np.linalg.solve(jacobian, -error[..., None])[..., 0]
        normal = normal + step[:, :1] * tilt_x + step[:, 1:2] * tilt_y
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        speed = speed + step[:, 2]
    else:
        error = outgoing(normal, speed) - v_out
    if np.max(np.abs(error)) > 1e3 * NEWTON_TOLERANCE or not np.all(np.isfinite(error)):
        raise ValueError("invert_racket_contact: no racket state makes the outgoing velocity under the residual-corrected model")
    return normal.reshape(shape + (3,)), speed.reshape(shape)


def _blade_up(normal: np.ndarray) -> np.ndarray:
    """The blade's upward tangent (..., 3): world z projected onto the blade's plane, normalised."""
    tangent = _UP - normal[..., 2:3] * normal
    return tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class ReturnShot:
    """A solved return: the ball's velocity and spin just after the hit (3 each), the blade normal
    and racket velocity that produce them, where the ball lands (2; m) after ``flight_time`` (s),
    and the clearance of the ball's bottom over the net cord (m)."""

    v_out: np.ndarray
    w_out: np.ndarray
    normal: np.ndarray
    racket_velocity: np.ndarray
    landing: np.ndarray
    flight_time: float
    net_clearance: float


def solve_return(
    ball: np.ndarray,
    target: np.ndarray,
    flight_time: float,
    params: BallPhysicsParams,
    brush_speed: float = 0.0,
    v_guess: np.ndarray | None = None,
    steps: int = 8,
    iterations: int = 8,
    tolerance: float = 5e-3,
) -> ReturnShot | None:
    """The return of the ball ``ball`` (9,; the state just before the hit) that lands at
    ``target`` (x, y) (m) ``flight_time`` s after the hit. Newton's method on the outgoing
    velocity v_out (from ``v_guess``, m/s, or the ballistic one): the landing (ball centre one
    radius above the table plane) from the flight model (eq. (1), RK4 in ``steps`` steps: within
    1e-5 m of a 0.5 ms step), finite-difference Jacobians from one batch of four balls per
    iteration, and each ball's spin from the racket state that makes its v_out
    (``invert_racket_contact``, then ``racket_impact``: eqs (7)-(8), with the residual network that
    ``params.racket`` selects, which the BallPlant applies too, though in the contact frame of the
    blade's actual roll about its normal). None if it does not
    converge to ``tolerance`` (m), an iterate leaves the finite numbers (a near-singular
    Jacobian), or no racket state makes the velocity."""
    ball = np.asarray(ball, dtype=float)
    p_hit, v_in, w_in = ball[:3], ball[3:6], ball[6:9]
    radius = params.aero.ball_radius
    goal = np.array([target[0], target[1], radius])
    if v_guess is None:  # ballistic, without air
        v_guess = (goal - p_hit) / flight_time + np.array([0.0, 0.0, 0.5 * params.aero.gravity * flight_time])
    v_out = np.asarray(v_guess, dtype=float)
    step = 0.01  # m/s, finite-difference step
    correction = residual_model(params.racket)
    for _ in range(iterations):
        # The nominal v_out and three perturbed copies, each with the spin its own racket state
        # gives it (the spin moves with v_out by up to ~50 rad/s per m/s: it belongs in the Jacobian).
        velocities = v_out + np.vstack([np.zeros(3), step * np.eye(3)])
        try:
            normals, racket_velocities = invert_racket_contact(v_in, w_in, velocities, params.racket, radius, brush_speed, residual=correction)
        except ValueError:
            return None
        _, spins = racket_impact(v_in, w_in, racket_velocities, contact_frame(normals), params.racket, radius, residual=correction)  # eqs (7)-(8)
        starts = np.hstack([np.broadcast_to(p_hit, (4, 3)), velocities, spins])
        if not np.all(np.isfinite(starts)):
            return None
        flight = simulate(starts, params, flight_time, dt=flight_time / steps, kinds=())
        ends = flight.final_state[:, :3]
        residual = ends[0] - goal
        if np.linalg.norm(residual) < tolerance:
            return ReturnShot(v_out, spins[0], normals[0], racket_velocities[0], ends[0, :2].copy(), flight_time, _net_clearance(flight.states[:, 0], params))
        jacobian = (ends[1:] - ends[0]).T / step
        try:
            v_out = v_out - np.linalg.solve(jacobian, residual)
        except np.linalg.LinAlgError:
            return None
    return None


def _net_clearance(states: np.ndarray, params: BallPhysicsParams) -> float:
    """Height of the ball's bottom over the net cord where the sampled flight ``states`` (T, 9)
    crosses x = 0 (linear interpolation), m; -inf if it never crosses or dips to the table first."""
    x = states[:, 0]
    radius = params.aero.ball_radius
    crossing = np.flatnonzero((x[:-1] < 0.0) & (x[1:] >= 0.0))
    if crossing.size == 0:
        return -np.inf
    i = crossing[0]
    over_robot_half = (states[: i + 1, 0] > -0.5 * params.table.length) & (np.abs(states[: i + 1, 1]) < 0.5 * params.table.width)
    if np.any(states[: i + 1, 2][over_robot_half] < radius):
        return -np.inf
    fraction = -x[i] / (x[i + 1] - x[i])
    z = states[i, 2] + fraction * (states[i + 1, 2] - states[i, 2])
    return float(z - radius - params.net.height)

