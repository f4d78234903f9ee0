"""Inverse kinematics for a hit: the configuration that puts the blade centre and its forehand
normal where a planned hit wants them (Drake's InverseKinematics with clearance, and a
Gauss-Newton refinement of a nearby solution), and the joint velocities that give the blade a
wanted velocity there.
"""

from __future__ import annotations

import time

import numpy as np
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import SnoptSolver, Solve

from ace_drake.robot.model import IkResult, RobotModel

# SNOPT's major iterations per IK solve: a solve that converges takes 10-50; a few wander for a
# second before converging, and 100 bounds them to ~60 ms (measured) at no loss of success.
IK_MAJOR_ITERATIONS = 100


def racket_joint_velocities(model: RobotModel, q: np.ndarray, v_WR: np.ndarray) -> np.ndarray:
    """Joint velocities (8,) that give the blade centre the velocity v_WR (3,; m/s) at q: the
    least-squares solution weighted by each joint's squared speed limit, so that fast joints do
    more of the work; the blade's angular velocity is left free."""
    jacobian = model.racket_jacobian(q)[3:]
    weights = np.diag(model.velocity_limit**2)
    return weights @ jacobian.T @ np.linalg.solve(jacobian @ weights @ jacobian.T, np.asarray(v_WR, dtype=float))


def solve_hit_ik(
    model: RobotModel,
    p_WR: np.ndarray,
    normal_W: np.ndarray,
    q_nominal: np.ndarray,
    seeds: list[np.ndarray],
    clearance: float,
    position_tolerance: float = 1e-3,
    angle_tolerance: float = np.radians(0.5),
) -> IkResult:
    """A configuration for a hit: the blade centre at ``p_WR`` (m) and the forehand normal along
    ``normal_W`` (the constraints of ``RobotModel.solve_racket_pose_ik``: joint limits, blade free
    to roll about its normal, ``clearance`` (m) between all robot and court geometry), nearest
    ``q_nominal`` in the metric sum (q - q_nominal)^2 / A_j (A_j: each joint's acceleration
    limit), i.e. preferring the joints that get there soonest (a joint needs ~ 2 sqrt(|dq| / A)
    for a move from rest to rest), the slow gantry least. Drake's InverseKinematics, from each
    seed in turn until one succeeds."""
    start = time.perf_counter()
    plant, world = model.plant, model.plant.world_frame()
    tolerance = np.full(3, position_tolerance)
    weights = np.diag(1.0 / model.acceleration_limit)
    result = None
    for attempt, seed in enumerate(seeds, start=1):
        ik = InverseKinematics(plant, model.plant_context, with_joint_limits=True)
        ik.AddPositionConstraint(model.racket_frame, np.zeros(3), world, p_WR - tolerance, p_WR + tolerance)
        ik.AddAngleBetweenVectorsConstraint(world, normal_W, model.racket_frame, [0.0, 0.0, 1.0], 0.0, angle_tolerance)
        ik.AddMinimumDistanceLowerBoundConstraint(clearance, clearance + 0.05)
        ik.prog().AddQuadraticErrorCost(weights, q_nominal, ik.q())
        ik.prog().SetSolverOption(SnoptSolver().solver_id(), "Major iterations limit", IK_MAJOR_ITERATIONS)
        result = Solve(ik.prog(), seed)
        if result.is_success():
            return IkResult(True, result.GetSolution(ik.q()), time.perf_counter() - start, attempt)
    q = result.GetSolution(ik.q()) if result is not None else np.asarray(q_nominal, dtype=float)
    return IkResult(False, q, time.perf_counter() - start, len(seeds))


def refine_hit_ik(
    model: RobotModel,
    q: np.ndarray,
    p_WR: np.ndarray,
    normal_W: np.ndarray,
    iterations: int = 3,
    position_tolerance: float = 1e-3,
    angle_tolerance: float = np.radians(0.5),
) -> np.ndarray | None:
    """Moves a hit configuration q (8,) onto a nearby racket target (``solve_hit_ik``'s blade
    centre and normal) by Gauss-Newton steps on the racket Jacobian, each the step of least
    sum dq^2 / A_j that removes the position error and the normal's tilt error (the roll about
    the normal is free). Returns None if it is not within the tolerances after ``iterations``
    steps or leaves the joint limits: the caller then solves the full IK (clearance included;
    a small correction of a clear configuration keeps most of its clearance)."""
    q = np.asarray(q, dtype=float).copy()
    inverse_weights = np.diag(model.acceleration_limit)
    for _ in range(iterations + 1):
        X_WR = model.racket_pose(q)
        normal = X_WR.rotation().matrix()[:, 2]
        position_error = p_WR - X_WR.translation()
        tilt = np.cross(normal, normal_W)  # rotation vector (small angles) taking normal to normal_W
        if np.linalg.norm(position_error) < position_tolerance and np.linalg.norm(tilt) < np.sin(angle_tolerance):
            return q
        jacobian = model.racket_jacobian(q)
        blade_plane = np.eye(3) - np.outer(normal, normal)  # rotations about the normal are free
        rows = np.vstack([jacobian[3:], blade_plane @ jacobian[:3]])
        error = np.concatenate([position_error, tilt])
        gram = rows @ inverse_weights @ rows.T + 1e-9 * np.eye(6)
        q = q + inverse_weights @ rows.T @ np.linalg.solve(gram, error)
        if np.any(q < model.lower) or np.any(q > model.upper):
            return None
    return None

