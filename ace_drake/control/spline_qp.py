"""The segment QP (paper, Methods *Optimization problem formulation*): per joint, a cubic spline
over one 32 ms segment from the current (q, v, a) to the mapped terminal (q_T, v_T), minimising the
integrated squared jerk, within the command limits at the 1 kHz samples.

With knots at the N samples (every h = 1 ms), a C2 cubic spline has piecewise-linear acceleration,
so it is fixed by the knot accelerations a_1 .. a_N (a_0 = the current acceleration):

    v_{k+1} = v_k + h (a_k + a_{k+1}) / 2,   q_{k+1} = q_k + h v_k + h^2 (2 a_k + a_{k+1}) / 6,
    integral of jerk^2 = sum_k (a_{k+1} - a_k)^2 / h,

a QP in N unknowns per joint with box bounds |a_k| <= A (tighter for a_N near the velocity
limit: ``CommandLimits.acceleration_bounds``, so that the reset can start there), two-sided rows |v_k| <= V and
lower <= q_k <= upper (k = 1 .. N-1; acceleration is linear between knots, so its bound holds
everywhere), and two equalities v_N = v_T, q_N = q_T. The terminal acceleration a_N is free: it is
the next segment's a_0. The matrices are built once; a solve changes only the linear cost term
and the bounds. Solved with DAQP (the paper's solver; an exact active-set method), after a
shortcut: the optimum under the two equalities alone (one precomputed KKT inverse for all eight
joints) is the QP's optimum wherever it meets every bound, so only the joints where a bound is
active (about 3 of 8 in rally strokes) reach DAQP; or, for
comparison, through Drake's MathematicalProgram with Clarabel (an interior-point method; OSQP,
first-order, left acceleration-bound violations of 2e-2 at its default tolerances and reported
the problem infeasible at 1e-9 ones, so it is not offered).
"""

from __future__ import annotations

import dataclasses

import daqp
import numba
import numpy as np

from ace_drake.control.trajectory import CommandLimits, acceleration_room
from ace_drake.robot.trajectory import JointTrajectory

EQUALITY = 5  # DAQP's sense flag for an equality row


@dataclasses.dataclass(frozen=True)
class SegmentSolution:
    """A spline QP's outcome: ``trajectory`` (N + 1 samples from the start) when ``success``;
    otherwise None, with the solver's ``status``. ``worst_violation`` is the largest constraint
    violation of the returned samples (rad or m, per s, per s^2), checked after every solve."""

    success: bool
    trajectory: JointTrajectory | None
    status: str
    worst_violation: float


class SegmentQp:
    """The jerk-minimising spline QP for the eight joints (module docstring), built once.

    ``solve`` is the fast path (DAQP, one small QP per joint); ``solver`` "clarabel" solves the
    same problem as one MathematicalProgram through Drake instead.
    """

    def __init__(self, limits: CommandLimits, samples: int = 32, period: float = 0.001, knot_samples: int = 1, solver: str = "daqp", tolerance: float = 1e-6):
        """limits: the command limits; samples N and period h (s): the segment's 1 kHz samples;
        knot_samples: samples per spline piece (N must be a multiple); solver: "daqp" or
        "clarabel"; tolerance: the largest constraint violation (in the constraints'
        units) accepted from a solver before the solve counts as failed."""
        if samples < 2 or period <= 0 or knot_samples < 1 or samples % knot_samples:
            raise ValueError(f"SegmentQp: need samples >= 2, period > 0 s and samples a multiple of knot_samples, got {samples}, {period}, {knot_samples}")
        if solver not in ("daqp", "clarabel"):
            raise ValueError(f"SegmentQp: solver must be daqp or clarabel, got {solver!r}")
        self.limits, self.samples, self.period, self.solver, self.tolerance = limits, samples, period, solver, tolerance
        N, h = samples, period
        M = samples // knot_samples  # spline pieces
        self.knots = M
        # Sample accelerations from the knots' (linear interpolation), then sample velocities and
        # positions as linear maps of the sample accelerations (the v0, q0 terms apart): exact,
        # since the acceleration is linear between consecutive samples too.
        knot_times = np.arange(M + 1) * knot_samples
        self._interpolation = np.array([np.interp(k, knot_times, np.eye(M + 1)[j]) for k in range(N + 1) for j in range(M + 1)]).reshape(N + 1, M + 1)
        velocity_map = np.zeros((N + 1, N + 1))
        position_map = np.zeros((N + 1, N + 1))
        for k in range(N):
            velocity_map[k + 1] = velocity_map[k]
            velocity_map[k + 1, k] += h / 2
            velocity_map[k + 1, k + 1] += h / 2
            position_map[k + 1] = position_map[k] + h * velocity_map[k]
            position_map[k + 1, k] += h * h / 3
            position_map[k + 1, k + 1] += h * h / 6
        self._velocity_map = velocity_map @ self._interpolation  # (N + 1, M + 1) over the knots
        self._position_map = position_map @ self._interpolation
        self._times = h * np.arange(N + 1)
        difference = np.diff(np.eye(M + 1), axis=0)  # (M, M + 1): a_{j+1} - a_j
        hessian = 2.0 / (knot_samples * h) * difference.T @ difference  # of 0.5 x' H x over [a_0, x]
        # Rows: v_1 .. v_{N-1}, q_1 .. q_{N-1}, then v_N, q_N (the equalities).
        rows = np.concatenate([self._velocity_map[1:N], self._position_map[1:N], self._velocity_map[N:], self._position_map[N:]])
        # DAQP works on a scaled problem: unknowns x = a / A (per joint) and unit-norm rows.
        self._row_norms = np.linalg.norm(rows[:, 1:], axis=1)
        self._rows_start = rows[:, 0]
        self._rows = np.ascontiguousarray(rows[:, 1:] / self._row_norms[:, None])
        self._hessian = np.ascontiguousarray(hessian[1:, 1:])
        self._hessian_cross = hessian[1:, 0]  # times a_0: the linear term
        self._sense = np.zeros(M + rows.shape[0], dtype=np.int32)
        self._sense[-2:] = EQUALITY
        self._bound_scale = np.concatenate([np.ones(M), 1.0 / self._row_norms])
        # The optimum with the two equalities only (KKT of min 0.5 a' H a + f' a, E a = b): when
        # it meets every inequality it is the QP's optimum, and most joints need no active-set
        # solve. solution = [a; multipliers] = kkt_inverse @ [-f; b].
        equality_rows = rows[-2:, 1:]
        kkt = np.block([[hessian[1:, 1:], equality_rows.T], [equality_rows, np.zeros((2, 2))]])
        self._kkt_inverse = np.linalg.inv(kkt)
        self._all_rows = np.ascontiguousarray(rows[:, 1:])  # unscaled, over a_1 .. a_M
        # The right-hand matrices of the per-call products (transposed views, as they were taken per call).
        self._kkt_inverse_T, self._inequality_rows_T = self._kkt_inverse.T, self._all_rows[:-2].T
        self._velocity_map_T, self._position_map_T, self._interpolation_T = self._velocity_map.T, self._position_map.T, self._interpolation.T
        self._daqp = daqp.Model()
        self._daqp.settings = {**self._daqp.settings, "primal_tol": 1e-9}
        self._daqp.setup(self._hessian, np.zeros(M), self._rows, np.ones(self._sense.size), -np.ones(self._sense.size), self._sense)
        self._program = None

    # ------------------------------------------------------------------------------ solving
    def solve(self, q0, v0, a0, q_terminal, v_terminal) -> SegmentSolution:
        """The segment from (q0, v0, a0) to (q_terminal, v_terminal), each (8,), in rad or m,
        per s and per s^2."""
        values = [np.asarray(x, dtype=float) for x in (q0, v0, a0, q_terminal, v_terminal)]
        if not all(x.shape == (8,) and np.all(np.isfinite(x)) for x in values):
            raise ValueError("SegmentQp.solve: q0, v0, a0, q_terminal, v_terminal must each be 8 finite values")
        return self.solve_batch(*(x[None] for x in values)).solution(0)

    def solve_batch(self, q0, v0, a0, q_terminal, v_terminal) -> "SegmentBatch":
        """The segments of B environments at once, from (q0, v0, a0) to (q_terminal,
        v_terminal), each (B, 8) in rad or m, per s and per s^2; row b equals ``solve`` of row b.
        The equality-constrained optimum (one precomputed KKT inverse) is computed for every
        joint of every row at once and checked against every bound; DAQP solves only the joints
        where one binds, in row then joint order (as a loop of ``solve`` would)."""
        q0, v0, a0, q_terminal, v_terminal = (np.asarray(x, dtype=float) for x in (q0, v0, a0, q_terminal, v_terminal))
        shape = q0.shape
        if len(shape) != 2 or shape[1] != 8 or not all(x.shape == shape for x in (v0, a0, q_terminal, v_terminal)):
            self._raise_invalid(q0, v0, a0, q_terminal, v_terminal)
        rows, M = shape[0], self.knots
        # The bounds (B, 8, M + rows) of [x; rows x] with the start's contribution moved to the
        # right, the cost's linear term (B, 8, M) and the KKT right-hand side [-f; b] (8 B, M + 2).
        lower, upper = np.empty((rows, 8, self._sense.size)), np.empty((rows, 8, self._sense.size))
        linear, right = np.empty((rows, 8, M)), np.empty((rows * 8, M + 2))
        limits = self.limits
        if not _row_bounds(q0, v0, a0, q_terminal, v_terminal, self._times, self._rows_start, self._hessian_cross, limits.acceleration,
                           limits.velocity, limits.jerk, limits.lower, limits.upper, lower, upper, linear, right):
            self._raise_invalid(q0, v0, a0, q_terminal, v_terminal)
        if self.solver == "daqp":
            accelerations, status, failed = self._solve_daqp(linear, lower, upper, right)
        else:
            solved = [self._solve_program(linear[row], lower[row], upper[row]) for row in range(rows)]
            failed = np.array([x is None for x, _ in solved], dtype=bool)
            accelerations = np.stack([np.zeros((8, self.knots)) if x is None else x for x, _ in solved])
            status = [text for _, text in solved]
        return self._checked(q0, v0, a0, accelerations, q_terminal, v_terminal, status, failed)

    @staticmethod
    def _raise_invalid(*values) -> None:
        raise ValueError(f"SegmentQp.solve_batch: q0, v0, a0, q_terminal, v_terminal must each be (B, 8) finite values, got shapes {[np.shape(x) for x in values]}")

    def _solve_daqp(self, linear, lower, upper, right):
        """The QP per joint (of rows (B, 8, ...); right: the KKT right-hand sides [-f; b] (8 B,
        M + 2)): the equality-constrained optimum where it meets every bound (then it is the
        QP's optimum), else DAQP on a scaled problem: unknowns x = a / A and each row divided by
        its norm, so row . a <= b becomes (row / |row|) . x <= b / (A |row|), and the cost
        0.5 a' H a + f' a becomes (up to the factor A^2) 0.5 x' H x + (f / A)' x. H and the rows
        are then the same for every joint: one DAQP workspace, set up once, takes new cost
        vectors and bounds. Returns the accelerations (B, 8, M), each row's status and whether it
        failed (B,) (a row stops at its first joint DAQP fails on)."""
        M = self.knots
        rows = linear.shape[0]
        solution = _product(right, self._kkt_inverse_T)[:, :M]
        flat_lower, flat_upper, flat_linear = (x.reshape(rows * 8, -1) for x in (lower, upper, linear))
        inside = np.empty(rows * 8, dtype=np.bool_)
        _meets_bounds(solution, _product(solution, self._inequality_rows_T), flat_lower, flat_upper, self.tolerance * 1e-3, inside)
        status = ["daqp: solved"] * rows
        failed = np.zeros(rows, dtype=bool)
        if inside.all():
            return solution.reshape(rows, 8, M), status, failed
        for index in np.flatnonzero(~inside):
            row, joint = divmod(int(index), 8)
            if failed[row]:
                continue
            A = self.limits.acceleration[joint]
            scale = self._bound_scale / A
            # The sense flags reset the working set: a cold start, so that a joint's solution
            # does not depend on the problems solved before it.
            self._daqp.update(f=flat_linear[index] / A, bupper=flat_upper[index] * scale, blower=flat_lower[index] * scale, sense=self._sense)
            x, _, exitflag, _ = self._daqp.solve()
            if exitflag < 1:
                status[row], failed[row] = f"daqp exit flag {exitflag} on joint {joint}", True
                continue
            solution[index] = A * x
        return solution.reshape(rows, 8, M), status, failed

    def _solve_program(self, linear, lower, upper):
        # Lazy: Drake's solvers serve only the solver='clarabel' reference; control is NumPy + DAQP.
        from pydrake.solvers import ClarabelSolver

        if self._program is None:
            self._build_program()
        program, variables, cost, box, rows = self._program
        N = self.knots
        cost.evaluator().UpdateCoefficients(np.kron(np.eye(8), self._hessian), linear.ravel())
        box.evaluator().set_bounds(lower[:, :N].ravel(), upper[:, :N].ravel())
        rows.evaluator().set_bounds(lower[:, N:].ravel(), upper[:, N:].ravel())
        result = ClarabelSolver().Solve(program)
        if not result.is_success():
            return None, f"{self.solver}: {result.get_solution_result()}"
        return result.GetSolution(variables).reshape(8, N), f"{self.solver}: solved"

    def _build_program(self) -> None:
        """The same QP for all eight joints as one MathematicalProgram (block-diagonal)."""
        from pydrake.solvers import MathematicalProgram  # lazy, as in _solve_program

        N = self.knots
        program = MathematicalProgram()
        variables = program.NewContinuousVariables(8 * N, "a")
        cost = program.AddQuadraticCost(np.kron(np.eye(8), self._hessian), np.zeros(8 * N), variables, is_convex=True)
        box = program.AddBoundingBoxConstraint(np.zeros(8 * N), np.zeros(8 * N), variables)
        rows_per_joint = self._rows.shape[0]
        unscaled = self._rows * self._row_norms[:, None]
        rows = program.AddLinearConstraint(np.kron(np.eye(8), unscaled), np.zeros(8 * rows_per_joint), np.zeros(8 * rows_per_joint), variables)
        self._program = (program, variables, cost, box, rows)

    # ------------------------------------------------------------------------------ checking
    def _checked(self, q0, v0, a0, accelerations, q_terminal, v_terminal, status, failed) -> "SegmentBatch":
        """Samples of the solved splines (B rows), each row accepted only if it meets every
        constraint to within the tolerance (never execute a solver's garbage); rows that
        ``failed`` in the solver keep their status and no samples."""
        rows, M, N = q0.shape[0], self.knots, self.samples
        knots = np.concatenate([a0[..., None], accelerations], axis=-1).reshape(rows * 8, M + 1)
        # Samples as (B, N + 1, 8), contiguous per row, and each row's worst violation.
        q, v, a, worst = np.empty((rows, N + 1, 8)), np.empty((rows, N + 1, 8)), np.empty((rows, N + 1, 8)), np.empty(rows)
        limits, tolerance = self.limits, self.tolerance
        _samples(q0, v0, knots, _product(knots, self._velocity_map_T), _product(knots, self._position_map_T), _product(knots, self._interpolation_T),
                 self._times, q_terminal, v_terminal, limits.acceleration, limits.velocity, limits.lower, limits.upper, q, v, a, worst)
        success = ~failed & np.isfinite(worst) & (worst <= tolerance)
        if not success.all():
            status = list(status)
            worst = np.where(failed, np.inf, worst)
            for row in np.flatnonzero(~failed & ~success):
                status[row] = f"{status[row]}, but a constraint is violated by {worst[row]:.3g}"
        return SegmentBatch(self.period, success, status, worst, q, v, a)


def _product(x: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """x @ matrix for x (8 B, k): one (8, k) product per environment (a 3-D matmul), so that a
    row's result does not depend on the batch it is in (one (8 B, k) product rounds differently
    with B, and OpenBLAS runs it on threads that here cost far more than they save)."""
    return np.matmul(x.reshape(-1, 8, x.shape[-1]), matrix).reshape(x.shape[0], matrix.shape[1])


@numba.njit(cache=True)
def _row_bounds(q0, v0, a0, q_terminal, v_terminal, times, rows_start, hessian_cross, acceleration, velocity, jerk, lower_q, upper_q,
                lower, upper, linear, right):
    """For starts and targets (B, 8) (rad or m, per s, per s^2): the bounds lower, upper (B, 8, M
    + 2 (N - 1) + 2) of [x; rows x] (x the knot accelerations a_1 .. a_M: box |a_k| <= A, the
    last within ``acceleration_room`` of v_T, so that the reset can start there; then v_1 ..
    v_{N-1} within +-V, q_1 .. q_{N-1} within the position limits, then v_N = v_T, q_N = q_T),
    with the start's contribution (rows_start: each row's a_0 coefficient) moved to the right;
    the cost's linear term a_0 H_cross (B, 8, M) and the KKT right-hand side [-f; b] (8 B, M +
    2). False if an input is not finite (the outputs are then meaningless)."""
    B, M, N = q0.shape[0], linear.shape[2], times.shape[0] - 1
    finite = True
    for b in range(B):
        for j in range(8):
            x0, x1, x2, x3, x4 = q0[b, j], v0[b, j], a0[b, j], q_terminal[b, j], v_terminal[b, j]
            if not (np.isfinite(x0) and np.isfinite(x1) and np.isfinite(x2) and np.isfinite(x3) and np.isfinite(x4)):
                finite = False
            r = 8 * b + j
            for k in range(M):
                linear[b, j, k] = x2 * hessian_cross[k]
                right[r, k] = -linear[b, j, k]
                upper[b, j, k] = acceleration[j]
                lower[b, j, k] = -acceleration[j]
            # The terminal acceleration starts the reset: no more than its jerk-limited ramp to
            # zero can take without passing the velocity limit.
            lower[b, j, M - 1] = -acceleration_room(-x4, velocity[j], acceleration[j], jerk[j])
            upper[b, j, M - 1] = acceleration_room(x4, velocity[j], acceleration[j], jerk[j])
            for k in range(N - 1):
                start_v = x1 + x2 * rows_start[k]
                upper[b, j, M + k] = velocity[j] - start_v
                lower[b, j, M + k] = -velocity[j] - start_v
                start_q = x0 + x1 * times[k + 1] + x2 * rows_start[N - 1 + k]
                upper[b, j, M + N - 1 + k] = upper_q[j] - start_q
                lower[b, j, M + N - 1 + k] = lower_q[j] - start_q
            v_gap = x4 - (x1 + x2 * rows_start[2 * N - 2])
            q_gap = x3 - (x0 + x1 * times[N] + x2 * rows_start[2 * N - 1])
            lower[b, j, M + 2 * N - 2] = upper[b, j, M + 2 * N - 2] = right[r, M] = v_gap
            lower[b, j, M + 2 * N - 1] = upper[b, j, M + 2 * N - 1] = right[r, M + 1] = q_gap
    return finite


@numba.njit(cache=True)
def _meets_bounds(solution, values, lower, upper, slack, inside):
    """inside (R,): whether joint problem r's accelerations solution[r] (M) and row values
    values[r] (2 (N - 1)) lie within its inequality bounds lower[r], upper[r] (their first M + 2
    (N - 1) entries), to within ``slack``."""
    M = solution.shape[1]
    for r in range(solution.shape[0]):
        ok = True
        for k in range(lower.shape[1] - 2):
            x = solution[r, k] if k < M else values[r, k - M]
            if not (x >= lower[r, k] - slack and x <= upper[r, k] + slack):
                ok = False
                break
        inside[r] = ok


@numba.njit(cache=True)
def _samples(q0, v0, knots, velocity_terms, position_terms, accelerations, times, q_terminal, v_terminal, acceleration, velocity, lower, upper,
             q, v, a, worst):
    """The splines' samples q, v, a (B, N + 1, 8) from the starts (B, 8) and the knot
    accelerations' contributions (8 B, N + 1) (v = v0 + velocity_terms, q = q0 + v0 t +
    position_terms), and each row's largest violation (B,) of |a_k| <= A at the knots (8 B, M +
    1; k >= 1), |v| <= V, the position limits and the terminal state, at least 0 (NaN if any is
    NaN)."""
    B, samples = q0.shape[0], times.shape[0]
    for b in range(B):
        largest, nan = -np.inf, False
        for j in range(8):
            r = 8 * b + j
            for k in range(1, knots.shape[1]):
                x = abs(knots[r, k]) - acceleration[j]
                nan |= x != x
                largest = max(largest, x)
            for k in range(samples):
                v[b, k, j] = v0[b, j] + velocity_terms[r, k]
                q[b, k, j] = q0[b, j] + v0[b, j] * times[k] + position_terms[r, k]
                a[b, k, j] = accelerations[r, k]
                x = abs(v[b, k, j]) - velocity[j]
                y = max(q[b, k, j] - upper[j], lower[j] - q[b, k, j])
                nan |= x != x or y != y
                largest = max(largest, x, y)
            x = abs(v[b, samples - 1, j] - v_terminal[b, j])
            y = abs(q[b, samples - 1, j] - q_terminal[b, j])
            nan |= x != x or y != y
            largest = max(largest, x, y)
        worst[b] = np.nan if nan else max(largest, 0.0)


@dataclasses.dataclass(frozen=True)
class SegmentBatch:
    """The outcomes of ``SegmentQp.solve_batch`` for B rows: ``success`` (B,) booleans,
    ``status`` (B strings), ``worst_violation`` (B,) (inf where the solver failed), and the
    samples q, v, a (B, N + 1, 8) (rad or m, per s, per s^2; meaningful only where
    ``success``). ``solution(b)`` is row b as ``SegmentQp.solve`` returns it."""

    period: float
    success: np.ndarray
    status: list[str]
    worst_violation: np.ndarray
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray

    def __len__(self) -> int:
        return self.success.shape[0]

    def solution(self, row: int) -> SegmentSolution:
        """Row ``row`` as a SegmentSolution (its trajectory views this batch's samples)."""
        trajectory = JointTrajectory(self.period, self.q[row], self.v[row], self.a[row]) if self.success[row] else None
        return SegmentSolution(bool(self.success[row]), trajectory, self.status[row], float(self.worst_violation[row]))
