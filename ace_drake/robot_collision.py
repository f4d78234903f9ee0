"""Sound collision checking of sampled joint trajectories, by conservative advancement.

The safety supervisor checks each 32 ms segment plus its reset trajectory (up to ~1 s at 1 kHz)
for robot self-collision and robot-court collision (table, net and posts, floor) before it
streams them. ``TrajectoryCollisionChecker.check`` is *sound*: when it reports ``free``, every
point of the robot's collision geometry stays at least ``margin`` (m) from the court and from its
own other collision geometries at every instant of the continuous motion, not only at the
samples. It may report as not free a motion that only comes within margin + 0.2 mm
(``DISTANCE_ERROR`` + ``PROOF_TOLERANCE``) of something; it never misses a collision.

The continuous motion. Between samples k and k + 1 (``period`` h apart) each joint follows the
cubic Hermite interpolant of (q_k, v_k) and (q_{k+1}, v_{k+1}) (``interpolate``); this is exact
for piecewise-cubic (constant-jerk) motion with its knots at the samples.

Distances. Drake's SceneGraph signed distances (``ComputeSignedDistancePairwiseClosestPoints``,
pairs within ``influence`` m) on the robot diagram owned by a ``SceneGraphCollisionChecker``,
restricted to the body pairs the checker does not filter: its filter matrix honours SceneGraph's
collision filters (the SDF's ``drake:collision_filter_group``s and the plant's adjacent-body
filters) and filters bodies welded together (the robot's base and the court). Drake's distances
for capsules, cylinders and boxes come from GJK and carry errors of order 1e-5 m (second
differences along smooth motions up to 2e-5 m, measured): they are trusted to within
``DISTANCE_ERROR`` = 1e-4 m, which every pair's budget gives up.

Speed bounds. A prismatic joint j moves every point downstream of it at |qdot_j|; a revolute
joint j at |qdot_j| times the point's distance from j's axis, at most rho_j(g) for the points of
geometry g over all configurations (``_Kinematics.axis_radius``):

- g on j's child body: its distance from the axis is fixed, and rho_j(g) is the exact maximum
  over the shape (boxes: their vertices; spheres and capsules: centres or segment ends plus the
  radius; cylinders: their two rims, sampled, plus a Lipschitz pad);
- g further down: the distance from j's axis of the next joint's origin (fixed on j's child
  body), plus the fixed distances between consecutive joint origins on each body further down (a
  revolute joint's origin lies on its axis and stays put as it turns; a prismatic joint's travels
  between its position limits), plus g's largest distance from its body's inboard joint origin.

``speed_radii`` r_j = max_g rho_j(g) (1 for prismatic joints) bounds every point's speed by
sum_j |qdot_j| r_j. For this robot (ace_robot.sdf): 1, 1, then shoulder_yaw 0.15 (arm offset)
+ 0.55 + 0.50 + 0.2954 (blade rim from the wrist: 0.22 + hypot(0.075, 0.007)) = 1.495 m,
shoulder_pitch 1.345, elbow 0.795, wrist_1 and wrist_2 0.295, wrist_3 0.0757 (the blade about
the handle axis).

Pair rates. Only joints on the kinematic path between a pair's two bodies change its distance (a
joint upstream of both moves them rigidly together), each at most at |qdot_j| rho_j of the
geometry it moves. Exact symmetries drop more: turning a revolute joint does not change the
distance to a sphere, capsule or cylinder lying on its axis on its parent body, or of one lying
on its axis on its child body (the forearm capsule and wrist_1; the handle and wrist_3). A shape
only symmetric to within eps (the SDF's 1.5708 for pi / 2) costs 2 eps of budget. So pair p's
distance falls at most at c_p . |qdot| m/s (``pair_rates``).

Joint speed bounds (``joint_speed_bounds``). On interval k the Hermite velocity of a joint is a
quadratic with Bernstein coefficients v_k, 3 (q_{k+1} - q_k) / h - v_k - v_{k+1}, v_{k+1}, so
|qdot| is at most the largest of their magnitudes; the bound also covers motion with linear
acceleration between the sampled a_k, a_{k+1} (max(|v_k|, |v_{k+1}|) + max(|a_k|, |a_{k+1}|) h / 4).
Integrating c_p . bound over the intervals gives each pair's cumulative swept bound S_p.

Height certificates. For a pair of a moving robot geometry A and a static geometry B (the court,
the robot's base), every point of B lies at or below B's top z_B, so the distance is at least the
height of A's lowest point above z_B; that height falls at most at c^z . |qdot|, where c^z is the
pair rate's coefficients with each joint whose axis is fixed in the world scaled by the fraction
of its motion that can be vertical (zero for the gantry's carriages and the shoulder's yaw:
``_Heights``). A swing over the table moves the racket mostly sideways, so at each query the
advancement takes, per such pair, whichever certificate proves the longer step.

Conservative advancement (``check``). From a configuration where the reported pairs have
distances d_p, every instant up to the furthest sample at which S_p has grown by at most
d_p - margin - slack_p for every pair (and the bound for all pairs, influence - margin for the
pairs not reported) is proven clear: the check jumps there (binary search) and queries again.
When not even the next sample is reachable (near something and fast) it steps inside the
interval along the Hermite interpolant by exactly the reachable time; a configuration whose
budget is below ``PROOF_TOLERANCE`` ends the check (this stops the steps shrinking without end
along a motion that grazes the margin). While steps are long, each step also queries one step
length beyond the next frontier, whose budgets prove an interval on both sides of it: when that
interval meets the frontier, the check skips to its end (about twice the progress per query).

Gating. Pairs whose distance depends on at most two joints (the carriages and the court, the
column and the upper arm, the racket and the forearm, ...) are mapped once, at construction, over
the joints' limits widened by ``GATE_PAD``: branch and bound with the pair rates as Lipschitz
constants proves where they cannot come within the margin. ``check`` filters out (in SceneGraph,
in a second context) every such pair that the trajectory's joint ranges (samples widened by the
Hermite's excursion) provably keep clear of, so a pair like the handle and the forearm (3 cm
apart at the ready pose, in contact with wrist_2 below about -1 rad) costs nothing unless the
wrist gets there. ``certified`` names the pairs proven clear over the whole box.

Cost (one core): ~20-40 us per query; a 32 ms segment plus a 0.5 s reset to the ready pose takes
a median of 6 queries and 0.3 ms, more when the motion passes close to the court (see
tests/test_robot_collision.py, which prints its measurement).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
from pydrake.common import Parallelism
from pydrake.geometry import Box, Capsule, CollisionFilterDeclaration, Cylinder, Ellipsoid, GeometrySet, Sphere
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.planning import RobotDiagramBuilder, SceneGraphCollisionChecker

from ace_drake.config import JOINT_NAMES, RobotScenario
from ace_drake.control.trajectory import JointTrajectory
from ace_drake.robot_model import MODELS_DIR, _joint_vector, add_robot_to_plant, check_joint_order, load_scenario

PROOF_TOLERANCE = 1e-4  # m: a clearance below margin + DISTANCE_ERROR + this counts as a collision
DISTANCE_ERROR = 1e-4  # m: Drake's signed distances are trusted to within this (module doc)
SYMMETRY_TOLERANCE = 1e-4  # m: geometry this close to symmetric about a joint axis counts as symmetric
GATE_PAD = 0.05  # rad or m: the gating box extends this far beyond each joint's position limits
GATE_MAX_JOINTS = 2  # pairs whose distance depends on more joints are not gated
GATE_MAX_QUERIES = 40000  # distance evaluations per pair when mapping where it may come close
GATE_RESOLUTION = 0.01  # m: cells whose Lipschitz spread is below this are not split further
_RIM_SAMPLES = 720  # points per cylinder rim when bounding its distance from an axis or point


@dataclasses.dataclass(frozen=True)
class CollisionReport:
    """The outcome of ``TrajectoryCollisionChecker.check``.

    free: every configuration of the continuous motion is at least ``margin`` clear.
    time: s from the trajectory's start of the first configuration found not provably margin
        clear (closer than margin + DISTANCE_ERROR + PROOF_TOLERANCE; every earlier instant is
        proven clear); None if free. With the query budget spent: how far the motion was proven.
    pairs: "body/geometry - body/geometry" names of the pairs that close there, closest first
        (robot geometry first); empty if free or the query budget was spent.
    queries: distance queries made (SceneGraph signed-distance calls).
    min_distance: the smallest distance of the pairs queried along the motion, m (capped at the
        influence distance; pairs left out by gating, see the module doc, are not queried).
    """

    free: bool
    time: float | None
    pairs: tuple[str, ...]
    queries: int
    min_distance: float


@dataclasses.dataclass(frozen=True)
class _Pair:
    """A checked pair of collision geometries: its name, its distance-rate coefficients c (8,)
    (m per rad or per m of each joint's motion), the budget it loses to inexact symmetry (m), and
    the SceneGraph ids (robot geometry first)."""

    name: str
    rate: np.ndarray
    slack: float
    id_A: object
    id_B: object


class TrajectoryCollisionChecker:
    """Sound collision checking of ``JointTrajectory``s of the robot in ``scenario`` (see the module
    doc). Joint vectors q (8,) are in JOINT_NAMES order, m and rad.

    margin: the clearance (m) every point of the robot must keep from the court and from itself.
    influence: distances beyond this (m) are not computed; must exceed margin (larger lets the
        advancement take longer steps when far from everything, at some cost per query).

    Attributes: ``speed_radii`` (8,) r_j (m per rad, 1 for the prismatic joints): every point of
    the robot's collision geometry moves at most sum_j |qdot_j| r_j m/s. ``certified``: names of
    the pairs proven at least margin apart over the whole box [box_lower, box_upper] (8,) (the
    position limits widened by GATE_PAD).
    """

    def __init__(
        self,
        scenario: RobotScenario | None = None,
        margin: float = 0.005,
        influence: float = 0.3,
        models_dir: str | Path = MODELS_DIR,
    ):
        if not (math.isfinite(margin) and margin >= 0.0):
            raise ValueError(f"TrajectoryCollisionChecker: margin must be a finite distance >= 0 (m), got {margin}")
        if not (math.isfinite(influence) and influence > margin + DISTANCE_ERROR + PROOF_TOLERANCE):
            raise ValueError(f"TrajectoryCollisionChecker: influence must be finite and > margin + {DISTANCE_ERROR + PROOF_TOLERANCE} m, got {influence} (margin {margin})")
        self.scenario = scenario or load_scenario()
        self.margin = float(margin)
        self.influence = float(influence)
        builder = RobotDiagramBuilder(time_step=0.0)
        robot = add_robot_to_plant(builder.plant(), self.scenario, models_dir)
        builder.plant().Finalize()
        check_joint_order(builder.plant(), robot)
        self.robot = robot
        # The checker owns the diagram and decides which body pairs are filtered; one thread.
        self.checker = SceneGraphCollisionChecker(
            model=builder.Build(), robot_model_instances=[robot], edge_step_size=0.05, implicit_context_parallelism=Parallelism(1)
        )
        self.plant = self.checker.plant()
        self.inspector = self.checker.model().scene_graph().model_inspector()
        self._kinematics = _Kinematics(self.plant, self.inspector)
        self.speed_radii = self._kinematics.speed_radii()
        self._pairs, self._pair_index = self._build_pairs()
        self._slacks = [pair.slack for pair in self._pairs]
        self._rate_matrix = np.array([pair.rate for pair in self._pairs]).reshape(-1, len(JOINT_NAMES))
        self._full = self.checker.MakeStandaloneModelContext()
        self._heights = self._build_heights()
        # Pairs whose distance depends on at most GATE_MAX_JOINTS joints: where in those joints'
        # box they may come within margin (nowhere: certified clear).
        self.box_lower = self.plant.GetPositionLowerLimits() - GATE_PAD
        self.box_upper = self.plant.GetPositionUpperLimits() + GATE_PAD
        gates = [gate for p in range(len(self._pairs)) if (gate := self._gate(p)) is not None]
        self.certified = tuple(self._pairs[gate.pair].name for gate in gates if not gate.bad)
        self._certified = np.array([gate.pair for gate in gates if not gate.bad], dtype=int)
        self._certified_joints = np.array([np.isin(np.arange(len(JOINT_NAMES)), gate.joints) for gate in gates if not gate.bad], dtype=bool).reshape(-1, len(JOINT_NAMES))
        self._gated = [gate for gate in gates if gate.bad]
        self._contexts: dict[tuple[int, ...], tuple[object, np.ndarray]] = {}

    # ------------------------------------------------------------------------------ configurations
    def clearance(self, q: np.ndarray) -> float:
        """The smallest signed distance (m) between the robot's collision geometry and the court
        or its own other (non-filtered) geometry at configuration q, capped at ``influence``."""
        distances = self._distances(_joint_vector(q, "q"), self._full)
        return min(self.influence, min((d for _, d in distances), default=self.influence))

    def check_config(self, q: np.ndarray) -> bool:
        """Whether configuration q is at least ``margin`` clear (``clearance(q) >= margin``)."""
        return self.clearance(q) >= self.margin

    def pair_distances(self, q: np.ndarray) -> list[tuple[str, float]]:
        """The checked geometry pairs within ``influence`` at q, as (name, signed distance m),
        closest first."""
        distances = self._distances(_joint_vector(q, "q"), self._full)
        return sorted(((self._pairs[p].name, d) for p, d in distances), key=lambda item: item[1])

    def pair_rates(self) -> dict[str, np.ndarray]:
        """Each checked geometry pair's distance-rate coefficients c (8,): its distance changes at
        most at c . |qdot| m/s (see the module doc)."""
        return {pair.name: pair.rate.copy() for pair in self._pairs}

    # ------------------------------------------------------------------------------ trajectories
    def check(self, trajectory: JointTrajectory, max_queries: int | None = None) -> CollisionReport:
        """Whether the continuous motion of ``trajectory`` (the Hermite interpolant of its samples)
        keeps the robot at least ``margin`` clear of the court and itself, by conservative
        advancement (module doc). Cost: one distance query (~20-40 us) per advancement step.

        max_queries: a budget; once spent, the report is not free, with ``time`` how far the motion
        was proven clear and no ``pairs`` (unproven rather than a collision found)."""
        if max_queries is not None and max_queries < 1:
            raise ValueError(f"check: max_queries must be >= 1, got {max_queries}")
        budget_left = math.inf if max_queries is None else max_queries
        q, v, a, period = _trajectory_arrays(trajectory)
        n = q.shape[0] - 1
        rates = np.ascontiguousarray(joint_speed_bounds(q, v, a, period).T)  # (8, n), joint-major
        context, global_rate = self._context_for(np.ascontiguousarray(q.T), rates, period)
        # Cumulative swept bounds at each sample (n + 1,): per pair (rows of `swept`) and for the
        # pairs not reported (`swept_all`).
        cumulative = np.zeros((len(JOINT_NAMES), n + 1))
        np.cumsum(rates, axis=1, out=cumulative[:, 1:])
        cumulative *= period
        swept = self._rate_matrix @ cumulative
        swept_all = global_rate @ cumulative
        heights = self._heights
        swept_height = heights.rate_matrix @ cumulative  # (H, n + 1): the height certificates'
        margin, influence, period_ = self.margin, self.influence, period
        index_get, slacks = self._pair_index.get, self._slacks
        height_of, height_pairs = heights.certificate, heights.pair_certificate
        # The query object is a live view of the context: it sees every position update.
        update, query_object = self.checker.UpdateContextPositions, context.GetQueryObject()
        distances = query_object.ComputeSignedDistancePairwiseClosestPoints
        queries, min_distance = 0, influence

        def probe(k: int, offset: float):
            """Queries the configuration at sample k + offset s: its budgets [(swept row, m)] (the
            pairs not reported first), or None if it is not provably margin clear."""
            nonlocal queries, min_distance
            config = q[k] if offset == 0.0 else interpolate(q[k], v[k], q[k + 1], v[k + 1], period_, offset)
            update(context, config)
            queries += 1
            budgets = [(swept_all, influence - margin - DISTANCE_ERROR)]
            closest = influence
            lowest = {}  # per robot geometry: its lowest point's height at this configuration, m
            for result in distances(max_distance=influence):
                p = index_get((result.id_A.get_value(), result.id_B.get_value()))
                if p is None:
                    continue
                d = result.distance
                if d < closest:
                    closest = d
                budget = d - margin - slacks[p]
                S = swept[p]
                h = height_pairs[p]
                if h >= 0:
                    # The pair's height certificate, if it proves more: the robot geometry's
                    # lowest point is above the top of the static one, and falls at most at
                    # the (smaller) vertical rate bound.
                    geometry, top, height_slack = height_of[h]
                    if geometry not in lowest:
                        lowest[geometry] = heights.lowest(query_object, geometry)
                    height_budget = lowest[geometry] - top - margin - height_slack
                    S_height = swept_height[h]
                    if height_budget * (S[k + 1] - S[k]) > budget * (S_height[k + 1] - S_height[k]) if k < n else height_budget > budget:
                        budget, S = height_budget, S_height
                if budget < PROOF_TOLERANCE:
                    return None
                budgets.append((S, budget))
            if closest < min_distance:
                min_distance = closest
            return budgets

        # Forward advancement from the frontier (k, offset), everything before it proven clear;
        # and, while steps are long, a speculative query one step length beyond the next
        # frontier, which proves an interval around itself (pending until the frontier meets it).
        k, offset = 0, 0.0
        pending = None  # (first, last) samples proven by a speculative query
        speculate = True  # off once a speculative query has found a collision
        while True:
            if queries >= budget_left:
                return CollisionReport(False, k * period + offset, (), queries, min_distance)
            budgets = probe(k, offset)
            if budgets is None:
                return self._collision_report(q, v, k, offset, period, context, queries, min_distance)
            if k == n:
                break
            fraction = 1.0 - offset / period  # of interval k still ahead
            furthest, step = n, math.inf
            for S, budget in budgets:
                interval = S[k + 1] - S[k]
                ahead = fraction * interval
                if ahead > budget:
                    step = min(step, budget * period / interval)  # budget / the pair's rate bound
                elif step == math.inf and furthest > k + 1:
                    furthest = min(furthest, int(S.searchsorted(S[k + 1] + budget - ahead, side="right")) - 1)
            if step < math.inf:
                offset += step  # strictly inside interval k: some pair cannot reach its end
                continue
            length = furthest - k
            k, offset = furthest, 0.0
            if pending is not None and pending[0] <= k:
                k, pending = max(k, pending[1]), None
            if k >= n:
                break
            if speculate and pending is None and length >= 2 and queries + 1 < budget_left:
                m = min(n, k + length)
                budgets = probe(m, 0.0)
                if budgets is None:
                    speculate = False  # not free: find the first such configuration going forward
                    continue
                first = max(int(S.searchsorted(S[m] - budget, side="left")) for S, budget in budgets)
                last = min(int(S.searchsorted(S[m] + budget, side="right")) - 1 for S, budget in budgets)
                if first <= k:
                    k = last
                    if k >= n:
                        break
                else:
                    pending = (first, last)
        return CollisionReport(True, None, (), queries, min_distance)

    # ------------------------------------------------------------------------------ internals
    def _distances(self, q: np.ndarray, context) -> list[tuple[int, float]]:
        """(pair, signed distance) of the checked pairs within ``influence`` at q."""
        self.checker.UpdateContextPositions(context, q)
        index = self._pair_index
        out = []
        for result in context.GetQueryObject().ComputeSignedDistancePairwiseClosestPoints(max_distance=self.influence):
            p = index.get((result.id_A.get_value(), result.id_B.get_value()))
            if p is not None:
                out.append((p, result.distance))
        return out

    def _collision_report(self, q, v, k: int, offset: float, period: float, context, queries: int, min_distance: float) -> CollisionReport:
        """The report of the configuration at sample k + offset s, not provably margin clear:
        names the pairs closer than margin + PROOF_TOLERANCE (after their symmetry slack),
        closest first."""
        config = q[k] if offset == 0.0 else interpolate(q[k], v[k], q[k + 1], v[k + 1], period, offset)
        distances = self._distances(config, context)
        close = sorted((d, self._pairs[p].name) for p, d in distances if d - self._pairs[p].slack < self.margin + PROOF_TOLERANCE)
        closest = min((d for _, d in distances), default=self.influence)
        return CollisionReport(False, k * period + offset, tuple(name for _, name in close), queries, min(min_distance, closest))

    def _context_for(self, q: np.ndarray, rates: np.ndarray, period: float) -> tuple[object, np.ndarray]:
        """The query context for a trajectory q (8, n + 1) with joint speed bounds rates (8, n),
        with the gated pairs it provably keeps clear of filtered out, and the rate coefficients
        of every pair left (elementwise max)."""
        # The Hermite on interval k stays within period * rate of both ends, so within half of
        # that of their midpoint: within [lower_k, upper_k], and all of it within [low, high].
        spread = 0.5 * period * rates.max(axis=1) if rates.shape[1] else 0.0
        low, high = q.min(axis=1) - spread, q.max(axis=1) + spread
        inside = (low >= self.box_lower) & (high <= self.box_upper)
        excluded = self._certified[~np.any(self._certified_joints & ~inside, axis=1)].tolist()
        intervals = None
        low_, high_ = low.tolist(), high.tolist()
        for gate in self._gated:
            if not inside[gate.joints].all():
                continue
            if gate.box_touches(low_, high_):
                if intervals is None:
                    middle, half = 0.5 * (q[:, :-1] + q[:, 1:]), 0.5 * period * rates
                    intervals = (middle - half, middle + half)
                if not rates.shape[1] or gate.touches(*intervals):
                    continue
            excluded.append(gate.pair)
        key = tuple(sorted(excluded))
        if key not in self._contexts:
            context = self.checker.MakeStandaloneModelContext()
            scene_graph = self.checker.model().scene_graph()
            manager = scene_graph.collision_filter_manager(scene_graph.GetMyMutableContextFromRoot(context.model_context()))
            for p in key:
                manager.Apply(CollisionFilterDeclaration().ExcludeBetween(GeometrySet(self._pairs[p].id_A), GeometrySet(self._pairs[p].id_B)))
            rates_left = [pair.rate for p, pair in enumerate(self._pairs) if p not in key]
            self._contexts[key] = (context, np.max(rates_left, axis=0) if rates_left else np.zeros(len(JOINT_NAMES)))
        return self._contexts[key]

    def _build_heights(self) -> "_Heights":
        """The height certificates of the pairs of a moving robot geometry and a static one (see
        ``_Heights``)."""
        kin, plant, inspector = self._kinematics, self.plant, self.inspector
        self.checker.UpdateContextPositions(self._full, np.asarray(self.scenario.ready_pose, dtype=float))
        query_object = self._full.GetQueryObject()
        sines = kin.vertical_sines(self._full.plant_context())
        geometries, tops, rates, slacks, pair_certificate = [], [], [], [], np.full(len(self._pairs), -1, dtype=int)
        for p, pair in enumerate(self._pairs):
            body_B = plant.GetBodyFromFrameId(inspector.GetFrameId(pair.id_B))
            if kin.upstream[int(body_B.index())]:
                continue  # both move: no fixed plane between them
            points, radius = kin._points(pair.id_B)
            X_WB = query_object.GetPoseInWorld(pair.id_B).GetAsMatrix4() @ np.linalg.inv(inspector.GetPoseInFrame(pair.id_B).GetAsMatrix4())
            top = float(np.max(points @ X_WB[:3, :3].T[:, 2] + X_WB[2, 3])) + radius
            rate, slack = kin.height_rate(pair.id_A, sines)
            pair_certificate[p] = len(geometries)
            geometries.append(pair.id_A)
            tops.append(top)
            rates.append(rate)
            slacks.append(slack)
        return _Heights(inspector, geometries, tops, np.array(rates).reshape(-1, len(JOINT_NAMES)), slacks, pair_certificate)

    def _build_pairs(self) -> tuple[list[_Pair], dict[tuple[int, int], int]]:
        """The geometry pairs the checker tests (SceneGraph candidates not in the checker's filter
        matrix, at least one on the robot), with their distance-rate coefficients."""
        plant, inspector, kin = self.plant, self.inspector, self._kinematics
        pairs: list[_Pair] = []
        index: dict[tuple[int, int], int] = {}
        for id_A, id_B in sorted(inspector.GetCollisionCandidates(), key=lambda ids: (ids[0].get_value(), ids[1].get_value())):
            body_A, body_B = (plant.GetBodyFromFrameId(inspector.GetFrameId(g)) for g in (id_A, id_B))
            if self.checker.IsCollisionFilteredBetween(body_A, body_B):
                continue
            if not (self.checker.IsPartOfRobot(body_A) or self.checker.IsPartOfRobot(body_B)):
                continue
            if not kin.upstream[int(body_A.index())] and kin.upstream[int(body_B.index())]:
                id_A, id_B, body_A, body_B = id_B, id_A, body_B, body_A  # moving geometry first
            rate, slack = kin.pair_rate(id_A, id_B)
            name = f"{body_A.name()}/{inspector.GetName(id_A)} - {body_B.name()}/{inspector.GetName(id_B)}"
            index[(id_A.get_value(), id_B.get_value())] = index[(id_B.get_value(), id_A.get_value())] = len(pairs)
            pairs.append(_Pair(name, rate, slack, id_A, id_B))
        return pairs, index

    def _gate(self, p: int) -> _Gate | None:
        """Where in the box pair p may come closer than margin + PROOF_TOLERANCE, by branch and
        bound on the joints its distance depends on (None if more than GATE_MAX_JOINTS, or the
        map takes more than GATE_MAX_QUERIES evaluations). Over a cell with centre c and
        half-widths w the distance lies within sum_j c_j w_j + slack of d(c) (the rate
        coefficients c_j bound its Lipschitz constant; slack covers the joints dropped by
        symmetry, held at the ready pose): cells proven clear are dropped, cells proven or not
        provably clear (at GATE_RESOLUTION) are kept as the gate's bad boxes."""
        pair = self._pairs[p]
        joints = np.flatnonzero(pair.rate)
        if len(joints) > GATE_MAX_JOINTS:
            return None
        if not len(joints):  # a constant distance: certified or never gated
            self.checker.UpdateContextPositions(self._full, np.asarray(self.scenario.ready_pose, dtype=float))
            d = self._full.GetQueryObject().ComputeSignedDistancePairClosestPoints(pair.id_A, pair.id_B).distance
            ok = d >= self.margin + PROOF_TOLERANCE + pair.slack
            return _Gate(p, joints, joints.astype(float), joints.astype(float), np.zeros(()), 0) if ok else None
        rate = pair.rate[joints]
        q = np.clip(np.asarray(self.scenario.ready_pose, dtype=float), self.box_lower, self.box_upper)
        required = self.margin + PROOF_TOLERANCE + pair.slack
        cells = [(self.box_lower[joints], self.box_upper[joints])]
        bad = []
        for _ in range(GATE_MAX_QUERIES):
            if not cells:
                return _Gate.from_boxes(p, joints, self.box_lower[joints], self.box_upper[joints], bad)
            lower, upper = cells.pop()
            centre, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
            q[joints] = centre
            self.checker.UpdateContextPositions(self._full, q)
            d = self._full.GetQueryObject().ComputeSignedDistancePairClosestPoints(pair.id_A, pair.id_B).distance
            spread = float(rate @ half)
            if d - spread >= required:
                continue  # clear everywhere in the cell
            if d + spread < required or spread <= GATE_RESOLUTION:
                bad.append((lower, upper))  # close everywhere in it, or not worth splitting
                continue
            split = int(np.argmax(rate * half))  # halve the cell along its most uncertain joint
            left_upper, right_lower = upper.copy(), lower.copy()
            left_upper[split] = right_lower[split] = centre[split]
            cells += [(lower, left_upper), (right_lower, upper)]
        return None


class _Heights:
    """Height certificates for the pairs of a moving robot geometry A and a static geometry B
    (the court, the robot's base): every point of B lies at or below B's top z_B, so the pair's
    distance is at least A's lowest point's height z_A minus z_B. z_A falls at most at
    sum_j |qdot_j| c_j sin(theta_j): a joint whose axis is fixed in the world (all joints above it
    prismatic) moves points vertically at sin(theta_j) of its full rate, theta_j its axis's angle
    from vertical (revolute; 0 for the shoulder's yaw) or from horizontal (prismatic; 0 for the
    gantry's carriages); ``_Kinematics.height_rate``. Over a table the robot mostly sweeps
    sideways, and this certificate proves much longer steps than the distance's.

    certificate[h] = (A's geometry id, z_B (m), slack (m)); rate_matrix (H, 8); pair_certificate
    (P,) the certificate of each pair, or -1."""

    def __init__(self, inspector, geometries, tops, rate_matrix, slacks, pair_certificate):
        self.certificate = [(g, top, slack) for g, top, slack in zip(geometries, tops, slacks)]
        self.rate_matrix = rate_matrix
        self.pair_certificate = pair_certificate.tolist()
        self._shapes = {}  # geometry id -> (kind, radius, half length, half extents or semi-axes)
        for g in set(geometries):
            shape = inspector.GetShape(g)
            if isinstance(shape, Sphere):
                self._shapes[g] = ("sphere", shape.radius(), 0.0, None)
            elif isinstance(shape, Capsule):
                self._shapes[g] = ("capsule", shape.radius(), 0.5 * shape.length(), None)
            elif isinstance(shape, Cylinder):
                self._shapes[g] = ("cylinder", shape.radius(), 0.5 * shape.length(), None)
            elif isinstance(shape, Box):
                self._shapes[g] = ("box", 0.0, 0.0, 0.5 * np.array([shape.width(), shape.depth(), shape.height()]))
            elif isinstance(shape, Ellipsoid):
                self._shapes[g] = ("ellipsoid", 0.0, 0.0, np.array([shape.a(), shape.b(), shape.c()]))
            else:
                raise ValueError(f"robot collision: unsupported collision shape {type(shape).__name__} ({inspector.GetName(g)})")

    def lowest(self, query_object, geometry) -> float:
        """z (m) of the geometry's lowest point in the query's configuration."""
        X_WG = query_object.GetPoseInWorld(geometry).GetAsMatrix34()
        z, row = X_WG[2, 3], X_WG[2, :3]  # height of the origin; the world z axis in the geometry's frame
        kind, radius, half_length, extents = self._shapes[geometry]
        if kind == "sphere":
            return z - radius
        if kind == "capsule":
            return z - abs(row[2]) * half_length - radius
        if kind == "cylinder":
            return z - abs(row[2]) * half_length - radius * math.sqrt(max(0.0, 1.0 - row[2] * row[2]))
        if kind == "box":
            return z - float(np.abs(row) @ extents)
        return z - float(np.linalg.norm(row * extents))  # ellipsoid: its support along -z


@dataclasses.dataclass(frozen=True)
class _Gate:
    """Where a pair whose distance depends only on ``joints`` (J,) may come within margin inside
    the checker's box: the bad boxes, rasterised on a grid of ``width`` (J,) cells from
    ``origin`` (J,) and stored as a summed-area table ``counts`` (shape + 1) for box queries.
    ``bad`` counts the bad cells (0: the pair is certified clear)."""

    pair: int
    joints: np.ndarray
    origin: np.ndarray
    width: np.ndarray
    counts: np.ndarray
    bad: int

    @staticmethod
    def from_boxes(pair: int, joints: np.ndarray, lower: np.ndarray, upper: np.ndarray, boxes: list) -> "_Gate":
        """The gate of the bad ``boxes`` [(lower, upper)] (cells of the bisection of the box
        [lower, upper], so on the grid of the smallest of them)."""
        if not boxes:
            return _Gate(pair, joints, lower, upper - lower, np.zeros((2,) * len(joints), dtype=np.int64), 0)
        width = np.min([hi - lo for lo, hi in boxes], axis=0)
        shape = np.maximum(np.round((upper - lower) / width).astype(int), 1)
        grid = np.zeros(shape, dtype=bool)
        for lo, hi in boxes:
            i0 = np.round((lo - lower) / width).astype(int)
            i1 = np.round((hi - lower) / width).astype(int)
            grid[tuple(slice(a, b) for a, b in zip(i0, i1))] = True
        counts = np.zeros(shape + 1, dtype=np.int64)
        summed = grid.astype(np.int64)
        for axis in range(len(joints)):
            summed = np.cumsum(summed, axis=axis)
        counts[(slice(1, None),) * len(joints)] = summed
        return _Gate(pair, joints, lower, width, counts, int(grid.sum()))

    def touches(self, lower: np.ndarray, upper: np.ndarray) -> bool:
        """Whether any of the boxes [lower, upper] (8, n), inside the gate's box, meets a bad cell
        (closed cells: touching counts)."""
        last = (np.array(self.counts.shape) - 2)[:, None]
        origin, width = self.origin[:, None], self.width[:, None]
        i0 = np.clip(np.floor((lower[self.joints] - origin) / width).astype(int), 0, last)
        i1 = np.clip(np.floor((upper[self.joints] - origin) / width).astype(int), 0, last) + 1
        c = self.counts
        if len(self.joints) == 1:
            inside = c[i1[0]] - c[i0[0]]
        else:
            inside = c[i1[0], i1[1]] - c[i0[0], i1[1]] - c[i1[0], i0[1]] + c[i0[0], i0[1]]
        return bool(np.any(inside > 0))

    def box_touches(self, lower: list[float], upper: list[float]) -> bool:
        """``touches`` for one box [lower, upper] (8,), in plain Python (fast)."""
        index = []
        for j, origin, width, size in zip(self.joints.tolist(), self.origin.tolist(), self.width.tolist(), self.counts.shape):
            i0 = min(max(math.floor((lower[j] - origin) / width), 0), size - 2)
            i1 = min(max(math.floor((upper[j] - origin) / width), 0), size - 2) + 1
            index.append((i0, i1))
        c = self.counts
        if len(index) == 1:
            (i0, i1), = index
            return bool(c[i1] - c[i0] > 0)
        (a0, a1), (b0, b1) = index
        return bool(c[a1, b1] - c[a0, b1] - c[a1, b0] + c[a0, b0] > 0)


# ---------------------------------------------------------------------------------- motion
def interpolate(q0: np.ndarray, v0: np.ndarray, q1: np.ndarray, v1: np.ndarray, period: float, t: float) -> np.ndarray:
    """The cubic Hermite interpolant of (q0, v0) at 0 and (q1, v1) at ``period`` (s), at time t."""
    s = t / period
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * q0 + (s3 - 2 * s2 + s) * period * v0 + (3 * s2 - 2 * s3) * q1 + (s3 - s2) * period * v1


def joint_speed_bounds(q: np.ndarray, v: np.ndarray, a: np.ndarray, period: float) -> np.ndarray:
    """Per interval and joint (n, 8), a bound on |qdot| over [t_k, t_{k+1}] for the Hermite
    interpolant of the samples (largest Bernstein coefficient of its quadratic velocity), and for
    motion with linear acceleration between the sampled a (max |v| + max |a| * period / 4)."""
    # max(|v_k|, |v_k+1|) + max(|a_k|, |a_k+1|) * period / 4 is at least the end-point Bernstein terms.
    linear = np.maximum(np.abs(v[:-1]), np.abs(v[1:])) + np.maximum(np.abs(a[:-1]), np.abs(a[1:])) * (period / 4.0)
    middle = np.abs((q[1:] - q[:-1]) * (3.0 / period) - v[:-1] - v[1:])
    return np.maximum(middle, linear)


def _trajectory_arrays(trajectory: JointTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    if not isinstance(trajectory, JointTrajectory):
        raise ValueError(f"check: expected a JointTrajectory, got {type(trajectory).__name__}")
    period = float(trajectory.period)
    if not (math.isfinite(period) and period > 0.0):
        raise ValueError(f"check: trajectory period must be a finite time > 0 (s), got {trajectory.period}")
    arrays = [np.asarray(x, dtype=float) for x in (trajectory.q, trajectory.v, trajectory.a)]
    if not math.isfinite(sum(float(x.sum()) for x in arrays)):  # fast path; finds NaN and inf
        for name, x in zip("qva", arrays):
            if not np.all(np.isfinite(x)):
                rows = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
                raise ValueError(f"check: trajectory {name} has non-finite values at samples {rows[:5].tolist()}")
    return arrays[0], arrays[1], arrays[2], period


# ---------------------------------------------------------------------------------- geometry
class _Kinematics:
    """The plant's kinematic tree and the geometry radii behind the speed bounds (module doc)."""

    def __init__(self, plant, inspector):
        self.plant, self.inspector = plant, inspector
        n_bodies = plant.num_bodies()
        self.inboard = [None] * n_bodies  # the joint whose child is each body
        for joint_index in plant.GetJointIndices():
            joint = plant.get_joint(joint_index)
            kind = joint.type_name()
            if kind not in ("revolute", "prismatic", "weld"):
                raise ValueError(f"robot collision: unsupported joint type {kind!r} ({joint.name()}); expected revolute, prismatic or weld")
            self.inboard[int(joint.child_body().index())] = joint
        # upstream[b]: the moving joints from body b up to the world, nearest first.
        self.upstream = []
        for b in range(n_bodies):
            chain, body = [], b
            while self.inboard[body] is not None:
                joint = self.inboard[body]
                if joint.type_name() != "weld":
                    chain.append(joint)
                body = int(joint.parent_body().index())
            self.upstream.append(chain)
        self.velocity_index = {int(j.index()): j.velocity_start() for b in self.upstream for j in b}

    # -- geometry extremes
    def _points(self, geometry_id) -> tuple[np.ndarray, float]:
        """Points (k, 3) in the body frame and a radius: the geometry lies within ``radius`` of
        their convex hull, and the farthest points of it from any point or line are within the
        returned bound (cylinders: rim samples, radius the Lipschitz pad)."""
        shape = self.inspector.GetShape(geometry_id)
        X_BG: RigidTransform = self.inspector.GetPoseInFrame(geometry_id)
        if isinstance(shape, Box):
            half = 0.5 * np.array([shape.width(), shape.depth(), shape.height()])
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
            return (X_BG.rotation().matrix() @ corners.T).T + X_BG.translation(), 0.0
        if isinstance(shape, Sphere):
            return X_BG.translation()[None, :], shape.radius()
        if isinstance(shape, Capsule):
            ends = np.array([[0, 0, -0.5 * shape.length()], [0, 0, 0.5 * shape.length()]])
            return (X_BG.rotation().matrix() @ ends.T).T + X_BG.translation(), shape.radius()
        if isinstance(shape, Cylinder):
            theta = np.linspace(0.0, 2 * np.pi, _RIM_SAMPLES, endpoint=False)
            r, h = shape.radius(), 0.5 * shape.length()
            rim = np.array([[r * np.cos(t), r * np.sin(t), z] for z in (-h, h) for t in theta])
            # Between rim samples a point is within r * pi / N of one (arc), so pad by that.
            return (X_BG.rotation().matrix() @ rim.T).T + X_BG.translation(), r * np.pi / _RIM_SAMPLES
        if isinstance(shape, Ellipsoid):
            return X_BG.translation()[None, :], max(shape.a(), shape.b(), shape.c())
        raise ValueError(f"robot collision: unsupported collision shape {type(shape).__name__} ({self.inspector.GetName(geometry_id)})")

    def _farthest(self, geometry_id, origin: np.ndarray, axis: np.ndarray | None = None) -> float:
        """An upper bound (m) on the distance of the geometry's points (body frame) from ``origin``,
        or, given a unit ``axis``, from the line through origin along it."""
        points, radius = self._points(geometry_id)
        d = points - origin
        if axis is not None:
            d = d - np.outer(d @ axis, axis)
        return float(np.max(np.linalg.norm(d, axis=1)) + radius)

    def symmetry_error(self, geometry_id, origin: np.ndarray, axis: np.ndarray) -> float:
        """How far (m) the geometry is from being symmetric about the line (body frame): a rigid
        motion moving no point further than this maps it onto a shape of revolution about the
        line; inf if it is not a sphere, capsule or cylinder."""
        shape = self.inspector.GetShape(geometry_id)
        X_BG = self.inspector.GetPoseInFrame(geometry_id)
        offset = X_BG.translation() - origin
        off_axis = float(np.linalg.norm(offset - (offset @ axis) * axis))
        if isinstance(shape, Sphere):
            return off_axis
        if isinstance(shape, (Capsule, Cylinder)):
            z = X_BG.rotation().matrix()[:, 2]
            tilt = math.acos(min(1.0, abs(float(z @ axis))))
            extent = 0.5 * shape.length() + shape.radius()  # farthest point from the centre, at most
            return off_axis + tilt * extent
        return math.inf

    # -- joint frames
    @staticmethod
    def _axis(joint) -> np.ndarray:
        axis = joint.revolute_axis() if joint.type_name() == "revolute" else joint.translation_axis()
        return np.asarray(axis, dtype=float) / np.linalg.norm(axis)

    def _origin_in_child(self, joint) -> np.ndarray:
        """Joint origin (its child frame M's origin) in the child body's frame."""
        return joint.frame_on_child().GetFixedPoseInBodyFrame().translation()

    def _origins_in_parent(self, joint) -> np.ndarray:
        """Where the joint origin can be in the parent body's frame (k, 3): revolute (M's origin
        is F's, on the axis), weld (fixed), prismatic (its travel's two ends; the distance from a
        point or a line is convex along it)."""
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame()
        kind = joint.type_name()
        if kind == "revolute":
            return X_PF.translation()[None, :]
        if kind == "weld":
            return X_PF.multiply(joint.X_FM()).translation()[None, :]
        lower, upper = joint.position_lower_limits()[0], joint.position_upper_limits()[0]
        if not (math.isfinite(lower) and math.isfinite(upper)):
            raise ValueError(f"robot collision: prismatic joint {joint.name()} below a revolute joint needs finite position limits")
        axis = X_PF.rotation().matrix() @ self._axis(joint)
        return np.array([X_PF.translation() + lower * axis, X_PF.translation() + upper * axis])

    def _axis_line_in_child(self, joint) -> tuple[np.ndarray, np.ndarray]:
        X_CM = joint.frame_on_child().GetFixedPoseInBodyFrame()
        return X_CM.translation(), X_CM.rotation().matrix() @ self._axis(joint)

    def _axis_line_in_parent(self, joint) -> tuple[np.ndarray, np.ndarray]:
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame()
        return X_PF.translation(), X_PF.rotation().matrix() @ self._axis(joint)

    # -- radii
    def axis_radius(self, joint, geometry_id) -> float:
        """rho_j(g): a bound (m) on the distance of geometry g's points from revolute joint j's
        axis over all configurations (1 for a prismatic joint); g's body must be downstream of j."""
        if joint.type_name() == "prismatic":
            return 1.0
        body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(geometry_id)).index())
        child = int(joint.child_body().index())
        # The bodies from j's child down to g's body, through their inboard joints.
        path, b = [], body
        while b != child:
            path.append(self.inboard[b])
            if path[-1] is None:
                raise ValueError(f"robot collision: geometry {self.inspector.GetName(geometry_id)} is not downstream of joint {joint.name()}")
            b = int(path[-1].parent_body().index())
        path.reverse()  # joints from j's child body down to g's body
        origin, axis = self._axis_line_in_child(joint)
        if not path:
            return self._farthest(geometry_id, origin, axis)
        # Distance from j's axis of the first joint origin (fixed on j's child body, up to travel).
        first = path[0]
        offsets = self._origins_in_parent(first) - origin
        total = float(np.max(np.linalg.norm(offsets - np.outer(offsets @ axis, axis), axis=1)))
        # Then from each joint's origin to the next one's, on the body between them.
        for inner, outer in zip(path[:-1], path[1:]):
            total += float(np.max(np.linalg.norm(self._origins_in_parent(outer) - self._origin_in_child(inner), axis=1)))
        return total + self._farthest(geometry_id, self._origin_in_child(path[-1]))

    def robot_geometries(self) -> list:
        """Collision geometries on bodies moved by a joint."""
        out = []
        for b in range(self.plant.num_bodies()):
            if self.upstream[b]:
                out.extend(self.plant.GetCollisionGeometriesForBody(self.plant.get_body(BodyIndex(b))))
        return out

    def speed_radii(self) -> np.ndarray:
        """r (8,): max over robot geometries downstream of each joint of rho_j (module doc)."""
        r = np.zeros(len(JOINT_NAMES))
        for g in self.robot_geometries():
            body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(g)).index())
            for joint in self.upstream[body]:
                i = self.velocity_index[int(joint.index())]
                r[i] = max(r[i], self.axis_radius(joint, g))
        return r

    def vertical_sines(self, plant_context) -> np.ndarray:
        """(8,) per joint: 1, or for a joint whose axis is fixed in the world (every moving joint
        above it prismatic) the fraction of its motion that can be vertical, sin of the axis's
        angle from vertical (revolute) or |axis_z| (prismatic)."""
        sines = np.ones(len(JOINT_NAMES))
        world = self.plant.world_frame()
        for joint_index in self.plant.GetJointIndices():
            joint = self.plant.get_joint(joint_index)
            if joint.type_name() not in ("revolute", "prismatic"):
                continue
            above = self.upstream[int(joint.parent_body().index())]
            if any(j.type_name() != "prismatic" for j in above):
                continue
            R_WF = self.plant.CalcRelativeTransform(plant_context, world, joint.frame_on_parent()).rotation().matrix()
            axis = R_WF @ self._axis(joint)
            vertical = abs(float(axis[2]))
            sine = math.sqrt(max(0.0, 1.0 - vertical * vertical)) if joint.type_name() == "revolute" else vertical
            sines[self.velocity_index[int(joint.index())]] = min(1.0, sine + 1e-12)
        return sines

    def height_rate(self, geometry_id, sines: np.ndarray) -> tuple[np.ndarray, float]:
        """The rate coefficients c (8,) of the height of the geometry's lowest point (it changes at
        most at c . |qdot| m/s) and its symmetry slack (m): each joint above the geometry at its
        axis radius times its vertical sine, except a revolute joint about whose axis the
        geometry, on its child body, is symmetric (turning it maps the shape onto itself)."""
        body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(geometry_id)).index())
        rate = np.zeros(len(JOINT_NAMES))
        eps = 0.0
        for joint in self.upstream[body]:
            i = self.velocity_index[int(joint.index())]
            if joint.type_name() == "revolute" and body == int(joint.child_body().index()):
                error = self.symmetry_error(geometry_id, *self._axis_line_in_child(joint))
                if error <= SYMMETRY_TOLERANCE:
                    eps += error
                    continue
            rate[i] = self.axis_radius(joint, geometry_id) * sines[i]
        return np.where(rate > 0, rate + eps, 0.0), 2.0 * eps

    def pair_rate(self, id_A, id_B) -> tuple[np.ndarray, float]:
        """The distance-rate coefficients c (8,) of a geometry pair and its symmetry slack (m)."""
        bodies = [int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(g)).index()) for g in (id_A, id_B)]
        upstream = [{int(j.index()) for j in self.upstream[b]} for b in bodies]
        rate = np.zeros(len(JOINT_NAMES))
        errors = []
        used = set()  # a geometry made symmetric about one axis cannot also be about another
        for side, (g, other_g) in enumerate(((id_A, id_B), (id_B, id_A))):
            for joint in self.upstream[bodies[side]]:
                if int(joint.index()) in upstream[1 - side]:
                    continue  # upstream of both: moves the pair rigidly
                candidates = []
                if joint.type_name() == "revolute":
                    # This joint turns g's side; g symmetric about its axis on its child body, or
                    # other_g on its parent body, makes the pair's distance independent of it.
                    if bodies[side] == int(joint.child_body().index()) and g not in used:
                        candidates.append((self.symmetry_error(g, *self._axis_line_in_child(joint)), g))
                    if bodies[1 - side] == int(joint.parent_body().index()) and other_g not in used:
                        candidates.append((self.symmetry_error(other_g, *self._axis_line_in_parent(joint)), other_g))
                error, geometry = min(candidates, default=(math.inf, None), key=lambda item: item[0])
                if error <= SYMMETRY_TOLERANCE:
                    errors.append(error)
                    used.add(geometry)
                    continue
                rate[self.velocity_index[int(joint.index())]] = self.axis_radius(joint, g)
        eps = sum(errors)
        # Replacing near-symmetric shapes by exact ones moves their points by <= eps: distance
        # budget 2 eps, and radii up to eps larger. And the computed distance may be off by
        # DISTANCE_ERROR.
        return np.where(rate > 0, rate + eps, 0.0), 2.0 * eps + DISTANCE_ERROR
