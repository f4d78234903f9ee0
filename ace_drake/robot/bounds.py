"""The robot's forward kinematics and swept bounding boxes of its collision geometry: the broad
phase of the trajectory collision check (``robot.collision``).

Why. Drake's SceneGraph answers one configuration per call (10-40 us). A rally plan is 300-500
samples at 1 kHz that keep most geometry pairs far apart, and proving that with SceneGraph,
query after query, costs milliseconds: conservative advancement between queries has to integrate
worst-case speed bounds (sum_j |qdot_j| r_j), which overestimate the racket's travel over a
stroke several times. Here the robot's actual positions at every sample come from forward
kinematics, and only the motion *between* two samples (1 ms) is bounded, to second order; blocks
of samples whose swept bounding boxes are far enough apart are proven clear at once. What this
cannot prove is left to Drake's exact distances.

Forward kinematics (``KinematicTree``). The plant's tree of revolute, prismatic and weld joints is
read once: each joint's frame on the parent body F (X_PF), its frame on the child body M (X_CM)
and its unit axis. The child's pose in its parent is X_PC(q) = X_PF X_FM(q) X_CM^-1, with X_FM a
rotation about the axis (Rodrigues: I + sin q K + (1 - cos q) K^2, K the axis's cross-product
matrix) or a translation q along it, so its 3 x 4 matrix is B0 + sin q B1 + (1 - cos q) B2
(revolute) or B0 + q B1 (prismatic) with constant B0, B1, B2; the poses compose from the world
outwards. tests/test_robot_bounds.py checks them against Drake's to 1e-9.

Bounding volumes. Of each bounded pair one geometry, the *covered* one (the smaller, never a box),
is bounded by its world box, which ``Shape.support`` gives in closed form from its pose, and
where that is not enough by spheres that contain it (``sphere_cover``: a chain along a capsule's
axis, a grid of cells over a cylinder); the other, the *boxed* one, by its world box (for the
court's axis-aligned boxes: the box itself).

Motion between samples. A point x of a geometry g deviates from the chord between its positions
at the two samples of an interval of length h by at most h^2 / 8 max |xddot| (the linear
interpolation error of a C^2 curve). With x's lever arms rho_j(g) about the joints (its largest
distance from joint j's axis; 1 for a prismatic joint; ``robot.collision._Kinematics``), dx/dq_j
has norm at most rho_j, and d2x/dq_i dq_j at most 2 rho_j for a joint i upstream of a revolute
joint j (it is (a_i x a_j) x w + a_j x (a_i x w), w from j's axis to x), rho_j for i = j, 1 for a
revolute joint upstream of a prismatic one, 0 for a prismatic one upstream of anything; so
|xddot| <= sum_j rho_j (A_j + V_j (V_j + 4 U_j)), with V_j and A_j bounds on the joint's speed and
acceleration over the interval and U_j the sum of V over the joints upstream of j. The caller
passes h^2 / 8 (A_j + V_j (V_j + 4 U_j)) per joint and interval (``bend``); a geometry's
deviation is its dot product with rho(g), ~0.3 mm at full speed for the racket (a first-order
bound, half the interval's travel, would be ~1 cm). Every point of g then stays, during the
interval, in the hull of g's world boxes at its two samples padded by that deviation, and every
point of a covering sphere (centre c, radius r) within r plus it of the chord of c. A sphere
centre outside its geometry (a cylinder's rim cells) is further from the joint axes by at most
its distance from the geometry, which pads its lever arms.

Swept boxes (``SweptBounds.open_intervals``). Per pair and block of ``block`` intervals: the
distance between the hulls of the two geometries' world boxes at the block's samples, less both
deviations, is at most the pair's distance at any instant of the block; above the threshold
(the margin) the block is clear. Else the same with the covering spheres' centres; else interval
by interval, geometry boxes then spheres; an interval that none of these clears is left open for
the exact check.

Shapes: boxes, spheres, capsules and cylinders; a pair of two boxes, or with a shape of another
kind, is not bounded here (``SweptBounds.bounded``) and is left to the exact check.

Compiled. The per-sample work is loops compiled with numba, over samples innermost (poses are
stored as 12 rows of [R | p] entries by samples), which LLVM vectorises; sin and cos are
``sin_cos``'s polynomials for the same reason. ~100 us for a 500-sample plan, where NumPy array
operations take several hundred (each of the ~75 operations per plan costs microseconds of
overhead on arrays this small) and SceneGraph milliseconds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numba
import numpy as np
from pydrake.geometry import Box, Capsule, Cylinder, Sphere
from pydrake.multibody.tree import BodyIndex

COVER_SPHERES = 48  # spheres per covered geometry, at most
COVER_EXCESS = 0.003  # m: covers use fewer spheres where they reach no further than this outside


# ---------------------------------------------------------------------------------- kinematics
class KinematicTree:
    """Forward kinematics of a finalized MultibodyPlant whose joints are revolute, prismatic or
    welds, compiled (module doc). ``arrays``: what the kernels need, (position index of each
    joint (welds read a zero beyond q's end), whether it is revolute, its parent and child body,
    its terms B0, B1, B2 (J, 3, 12), the static bodies' poses (num_bodies, 12))."""

    def __init__(self, plant):
        context = plant.CreateDefaultContext()
        self.num_bodies = plant.num_bodies()
        self.num_positions = plant.num_positions()
        inboard = {}
        for joint_index in plant.GetJointIndices():
            joint = plant.get_joint(joint_index)
            if joint.type_name() not in ("revolute", "prismatic", "weld"):
                raise ValueError(f"KinematicTree: unsupported joint type {joint.type_name()!r} ({joint.name()}); expected revolute, prismatic or weld")
            inboard[int(joint.child_body().index())] = joint
        # Bodies no joint moves (the world and what is welded to it) keep their default poses.
        moved = [self._is_moved(b, inboard) for b in range(self.num_bodies)]
        static_poses = np.zeros((self.num_bodies, 12))
        for b in range(self.num_bodies):
            if not moved[b]:
                static_poses[b] = plant.EvalBodyPoseInWorld(context, plant.get_body(BodyIndex(b))).GetAsMatrix34().ravel()
        # The joints into moved bodies, parents before children.
        order = sorted((b for b in range(self.num_bodies) if moved[b]), key=lambda b: self._depth(b, inboard))
        joints = [inboard[b] for b in order]
        self.arrays = (
            np.array([j.position_start() if j.num_positions() else self.num_positions for j in joints], dtype=np.int64),
            np.array([j.type_name() == "revolute" for j in joints], dtype=np.bool_),
            np.array([int(j.parent_body().index()) for j in joints], dtype=np.int64),
            np.array(order, dtype=np.int64),
            np.array([self._terms_of(j) for j in joints]).reshape(len(joints), 3, 12),
            static_poses,
        )

    @staticmethod
    def _is_moved(body: int, inboard: dict) -> bool:
        while body in inboard:
            if inboard[body].type_name() != "weld":
                return True
            body = int(inboard[body].parent_body().index())
        return False

    @staticmethod
    def _depth(body: int, inboard: dict) -> int:
        depth = 0
        while body in inboard:
            body, depth = int(inboard[body].parent_body().index()), depth + 1
        return depth

    @staticmethod
    def _terms_of(joint) -> np.ndarray:
        """B0, B1, B2 (3, 3, 4): X_PC = B0 + c1 B1 + c2 B2 (its top 3 x 4 rows), with (c1, c2) =
        (sin q, 1 - cos q) for a revolute joint, (q, 0) for a prismatic one, (0, 0) for a weld."""
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame().GetAsMatrix4()
        X_MC = joint.frame_on_child().GetFixedPoseInBodyFrame().inverse().GetAsMatrix4()
        R_PF, p_PF = X_PF[:3, :3], X_PF[:3, 3]
        terms = np.zeros((3, 3, 4))
        kind = joint.type_name()
        if kind == "weld":
            terms[0] = (X_PF @ joint.X_FM().GetAsMatrix4() @ X_MC)[:3]
            return terms
        axis = np.asarray(joint.revolute_axis() if kind == "revolute" else joint.translation_axis(), dtype=float)
        axis = axis / np.linalg.norm(axis)
        terms[0] = R_PF @ X_MC[:3]
        terms[0][:, 3] += p_PF
        if kind == "revolute":
            K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
            terms[1] = R_PF @ K @ X_MC[:3]
            terms[2] = R_PF @ K @ K @ X_MC[:3]
        else:
            terms[1][:, 3] = R_PF @ axis
        return terms

    def pose_rows(self, q: np.ndarray) -> np.ndarray:
        """X_WB (num_bodies, 12, S): every body's pose in world, its 3 x 4 matrix row-major, at
        configurations q (num_positions, S), one per column, rad and m."""
        q = np.ascontiguousarray(q, dtype=float)
        X = np.empty((self.num_bodies, 12, q.shape[1]))
        _body_poses(q, self.arrays, X)
        return X


@numba.njit(cache=True)
def _body_poses(q, tree, X):
    """X (num_bodies, 12, S), in place: the 3 x 4 matrices of the poses X_WB, row-major, at
    configurations q (num_positions, S) (one per column); tree: ``KinematicTree.arrays``."""
    position, revolute, parent, child, terms, static_poses = tree
    samples = q.shape[1]
    for b in range(static_poses.shape[0]):
        for e in range(12):
            X[b, e, :] = static_poses[b, e]
    c1, c2 = np.empty(samples), np.empty(samples)
    local = np.empty((12, samples))  # X_PC of the joint
    for j in range(child.shape[0]):
        if position[j] >= q.shape[0]:  # a weld
            c1[:] = 0.0
            c2[:] = 0.0
        elif revolute[j]:
            angle = q[position[j]]
            for s in range(samples):
                sine, cosine = sin_cos(angle[s])
                c1[s], c2[s] = sine, 1.0 - cosine
        else:
            c1[:] = q[position[j]]
            c2[:] = 0.0
        for e in range(12):
            B0, B1, B2 = terms[j, 0, e], terms[j, 1, e], terms[j, 2, e]
            for s in range(samples):
                local[e, s] = B0 + c1[s] * B1 + c2[s] * B2
        compose_pose(X[parent[j]], local, X[child[j]])


@numba.njit(cache=True)
def sin_cos(x):
    """(sin x, cos x) to within 2e-16 for |x| < 1e5 rad, as fdlibm computes them: x = r + n pi / 2
    with |r| <= pi / 4 (Cody-Waite reduction, pi / 2 in two parts), then its kernel polynomials
    for sin r and cos r, swapped and negated by the quadrant n mod 4. No calls and no branches
    but selects, so the compiler vectorises loops of it (libm's sin and cos take ~15 ns each here: half of the
    forward kinematics). tests/test_robot_bounds.py compares it with math.sin and math.cos."""
    n = round(x * 6.36619772367581382433e-01)  # 2 / pi
    r = (x - n * 1.57079632673412561417e00) - n * 6.07710050650619224932e-11
    z = r * r
    sine = r + z * r * (-1.66666666666666324348e-01 + z * (8.33333333332248946124e-03 + z * (-1.98412698298579493134e-04 + z * (2.75573137070700676789e-06 + z * (-2.50507602534068634195e-08 + z * 1.58969099521155010221e-10)))))
    tail = z * z * (4.16666666666666019037e-02 + z * (-1.38888888888741095749e-03 + z * (2.48015872894767294178e-05 + z * (-2.75573143513906633035e-07 + z * (2.08757232129817482790e-09 + z * -1.13596475577881948265e-11)))))
    w = 1.0 - 0.5 * z
    cosine = w + (((1.0 - w) - 0.5 * z) + tail)
    quadrant = int(n) & 3  # sin x, cos x = (s, c), (c, -s), (-s, -c), (-c, s) for quadrants 0-3
    swap = quadrant & 1
    sign_sine, sign_cosine = 1 - 2 * ((quadrant >> 1) & 1), 1 - 2 * (((quadrant + 1) >> 1) & 1)
    return sign_sine * (cosine if swap else sine), sign_cosine * (sine if swap else cosine)


@numba.njit(cache=True)
def compose_pose(X_AB, X_BC, X_AC):
    """X_AC = X_AB X_BC, in place, for 3 x 4 poses stored as 12 rows (row-major entries) by
    samples."""
    for r in range(3):
        a0, a1, a2, a3 = X_AB[4 * r], X_AB[4 * r + 1], X_AB[4 * r + 2], X_AB[4 * r + 3]
        for c in range(4):
            out, b0, b1, b2 = X_AC[4 * r + c], X_BC[c], X_BC[4 + c], X_BC[8 + c]
            for s in range(out.shape[0]):
                out[s] = a0[s] * b0[s] + a1[s] * b1[s] + a2[s] * b2[s]
        for s in range(a3.shape[0]):
            X_AC[4 * r + 3, s] += a3[s]


@numba.njit(cache=True)
def _compose_fixed(X_AB, X_BC, X_AC, count):
    """``compose_pose`` with a constant X_BC (3, 4), for the first ``count`` samples."""
    for r in range(3):
        a0, a1, a2, a3 = X_AB[4 * r], X_AB[4 * r + 1], X_AB[4 * r + 2], X_AB[4 * r + 3]
        for c in range(4):
            out, b0, b1, b2 = X_AC[4 * r + c], X_BC[0, c], X_BC[1, c], X_BC[2, c]
            for s in range(count):
                out[s] = a0[s] * b0 + a1[s] * b1 + a2[s] * b2
        out = X_AC[4 * r + 3]
        for s in range(count):
            out[s] += a3[s]


# ---------------------------------------------------------------------------------- shapes
@dataclasses.dataclass(frozen=True)
class Shape:
    """A convex collision shape in its frame G: the points within ``rounding`` (m) of the box
    |x_i| <= half_i (a box; a capsule's segment along z; a sphere's centre), or of the disc of
    radius ``radius`` in G's xy plane swept along z over |z| <= half_2 (a cylinder)."""

    half: np.ndarray
    radius: float
    rounding: float

    @staticmethod
    def of(shape) -> "Shape | None":
        """The Shape of a Drake Box, Sphere, Capsule or Cylinder; None for other kinds."""
        if isinstance(shape, Box):
            return Shape(0.5 * np.array([shape.width(), shape.depth(), shape.height()]), 0.0, 0.0)
        if isinstance(shape, Sphere):
            return Shape(np.zeros(3), 0.0, shape.radius())
        if isinstance(shape, Capsule):
            return Shape(np.array([0.0, 0.0, 0.5 * shape.length()]), 0.0, shape.radius())
        if isinstance(shape, Cylinder):
            return Shape(np.array([0.0, 0.0, 0.5 * shape.length()]), shape.radius(), 0.0)
        return None

    @property
    def circumradius(self) -> float:
        """The radius (m) of the smallest sphere about G's origin that contains the shape."""
        return math.hypot(float(np.linalg.norm(self.half)), self.radius) + self.rounding

    def support(self, u: np.ndarray) -> np.ndarray:
        """max over the shape's points x of u . x, for unit directions u (..., 3) in G."""
        return np.abs(u) @ self.half + self.radius * np.sqrt(np.maximum(0.0, 1.0 - u[..., 2] ** 2)) + self.rounding

    def lowest(self, X_WG: np.ndarray) -> np.ndarray:
        """z (m) of the shape's lowest point at poses X_WG (..., 3 or 4, 4)."""
        return X_WG[..., 2, 3] - self.support(X_WG[..., 2, :3])

    def distance(self, p_G: np.ndarray) -> np.ndarray:
        """Distance (m) of points p_G (..., 3) in G from the shape (0 inside)."""
        radial = np.maximum(np.hypot(p_G[..., 0], p_G[..., 1]) - self.radius, 0.0) if self.radius else None
        outside = np.maximum(np.abs(p_G) - self.half, 0.0)
        if radial is not None:  # a cylinder: the core's half extents across the axis are 0
            outside[..., 0], outside[..., 1] = radial, 0.0
        return np.linalg.norm(outside, axis=-1) - self.rounding


def sphere_cover(shape, excess: float = COVER_EXCESS, max_spheres: int = COVER_SPHERES) -> tuple[np.ndarray, np.ndarray]:
    """Spheres that together contain ``shape`` (a Drake Sphere, Capsule or Cylinder, in its frame
    G): centres (m, 3) in G and radii (m,), m. The fewest spheres that reach no further than
    ``excess`` (m) beyond the shape's sides, or, if that takes more than ``max_spheres``, the
    closest such fit with at most that many.

    Capsule (radius r, length l): m spheres along the axis, spaced s = l / (m - 1), each of
    radius sqrt(r^2 + (s / 2)^2) (every point within r of the axis is within s / 2 of a centre
    along it); one sphere of radius r + l / 2 if m = 1. Cylinder (radius R, length l): a sphere
    per cell of an n x n x layers grid over its bounding box (``_cylinder_cells``), reaching
    beyond the flat faces by its radius less half a layer and beyond the rim by up to its radius
    less its centre's distance from it; 45 spheres reach 1.3 cm beyond the racket's blade."""
    if isinstance(shape, Sphere):
        key = ("sphere", shape.radius())
    elif isinstance(shape, Capsule):
        key = ("capsule", shape.radius(), shape.length())
    elif isinstance(shape, Cylinder):
        key = ("cylinder", shape.radius(), shape.length())
    else:
        raise ValueError(f"sphere_cover: unsupported shape {type(shape).__name__}; expected Sphere, Capsule or Cylinder")
    # A pure function of the shape's dimensions: computed once per process (a cylinder's search
    # takes ~0.1 s); callers get their own copies.
    cache_key = (*key, float(excess), int(max_spheres))
    if cache_key not in _COVERS:
        _COVERS[cache_key] = _sphere_cover(shape, excess, max_spheres)
    centres, radii = _COVERS[cache_key]
    return centres.copy(), radii.copy()


_COVERS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # sphere_cover's results by shape and parameters


def _sphere_cover(shape, excess: float, max_spheres: int) -> tuple[np.ndarray, np.ndarray]:
    """``sphere_cover``, computed."""
    if isinstance(shape, Sphere):
        return np.zeros((1, 3)), np.array([shape.radius()])
    if isinstance(shape, Capsule):
        r, length = shape.radius(), shape.length()
        for m in range(1, max_spheres + 1):
            radius = r + 0.5 * length if m == 1 else math.hypot(r, 0.5 * length / (m - 1))
            if radius - r <= excess:
                break
        z = np.zeros(1) if m == 1 else np.linspace(-0.5 * length, 0.5 * length, m)
        return np.column_stack([np.zeros((m, 2)), z]), np.full(m, radius)
    if isinstance(shape, Cylinder):
        R, half_length = shape.radius(), 0.5 * shape.length()
        fits = []  # (reach beyond the shape, count, centres, radii)
        for n in range(1, max_spheres + 1):
            for layers in range(1, max_spheres + 1):
                centres, radii = _cylinder_cells(R, half_length, n, layers)
                if len(radii) <= max_spheres:
                    # Beyond the flat faces, and radially beyond the rim at the mid-plane.
                    reach = max(np.max(radii) - half_length / layers, np.max(np.hypot(centres[:, 0], centres[:, 1]) + radii) - R)
                    fits.append((reach, len(radii), centres, radii))
        good = [fit for fit in fits if fit[0] <= excess]
        _, _, centres, radii = min(good, key=lambda fit: fit[1]) if good else min(fits, key=lambda fit: fit[0])
        return centres, radii
    raise ValueError(f"sphere_cover: unsupported shape {type(shape).__name__}; expected Sphere, Capsule or Cylinder")


def _cylinder_cells(R: float, half_length: float, n: int, layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Spheres over the cells of an n x n x layers grid over the cylinder's bounding box that meet
    it, each through the corners of the box that bounds the cell's part of the cylinder: the
    cell's x range clipped to the disc's half width sqrt(R^2 - y^2) at the cell's smallest |y|
    (and likewise y), times the layer. Centres (m, 3) and radii (m,), m."""
    side, height = 2.0 * R / n, 2.0 * half_length / layers
    edges = -R + side * np.arange(n + 1)
    lower, upper = edges[:-1], edges[1:]
    nearest = np.where(lower > 0, lower, np.where(upper < 0, upper, 0.0))  # |x| closest to the axis
    reach = np.sqrt(np.maximum(R * R - nearest**2, 0.0))  # the disc's half width there
    i, j = np.nonzero(np.hypot(nearest[:, None], nearest[None, :]) <= R)
    # The cell's x range, clipped to the disc's width at the cell's y closest to the axis.
    x0, x1 = np.maximum(lower[i], -reach[j]), np.minimum(upper[i], reach[j])
    y0, y1 = np.maximum(lower[j], -reach[i]), np.minimum(upper[j], reach[i])
    z = -half_length + height * (np.arange(layers) + 0.5)
    count = len(i)
    centres = np.column_stack([np.tile(0.5 * (x0 + x1), layers), np.tile(0.5 * (y0 + y1), layers), np.repeat(z, count)])
    radii = np.tile(0.5 * np.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2 + height * height), layers)
    return centres, radii


# ---------------------------------------------------------------------------------- swept bounds
class SweptBounds:
    """Which intervals of a sampled motion swept bounding boxes prove clear for each of a set of
    geometry pairs (module doc).

    plant, inspector: the finalized plant and its SceneGraph inspector. pairs: [(id_A, id_B)] of
    collision geometries. lever_arms: geometry id -> (num_positions,) rho_j(g), the largest
    distance of g's points from joint j's axis (1 for a prismatic joint upstream of g, 0 for a
    joint not upstream of it), m. Attributes: ``kinematics``; ``bounded`` (P,) bool, whether a
    pair gets bounds; ``covers``, each covered geometry's sphere centres (m, 3) in its frame G and
    radii (m,), m."""

    def __init__(self, plant, inspector, pairs: list[tuple[object, object]], lever_arms: Callable[[object], np.ndarray]):
        self.kinematics = KinematicTree(plant)
        sides = [self._sides(inspector, id_A, id_B) for id_A, id_B in pairs]
        self.bounded = np.array([side is not None for side in sides], dtype=bool)
        covered = sorted({side[0] for side in sides if side}, key=lambda g: g.get_value())
        boxed = sorted({side[1] for side in sides if side}, key=lambda g: g.get_value())
        self._pair_covered = np.array([covered.index(side[0]) if side else 0 for side in sides], dtype=np.int64)
        self._pair_boxed = np.array([boxed.index(side[1]) if side else 0 for side in sides], dtype=np.int64)
        self.covers = {g: sphere_cover(inspector.GetShape(g)) for g in covered}
        # A sphere centre outside its geometry (a cylinder's rim cells) is that much further from
        # the joint axes than the geometry's points.
        outside = [float(np.max(Shape.of(inspector.GetShape(g)).distance(self.covers[g][0]))) for g in covered]
        arms = [np.asarray(lever_arms(g), dtype=float) for g in covered]
        self._covered = self._geometries(plant, inspector, covered, [np.where(arm > 0, arm + pad, 0.0) for arm, pad in zip(arms, outside)])
        self._spheres = (
            np.concatenate([[0], np.cumsum([len(self.covers[g][1]) for g in covered])]).astype(np.int64),
            np.concatenate([self.covers[g][0] for g in covered]).reshape(-1, 3),
            np.concatenate([self.covers[g][1] for g in covered]),
        )
        self._boxed = self._geometries(plant, inspector, boxed, [np.asarray(lever_arms(g), dtype=float) for g in boxed])
        self._pair_arrays = {}  # pairs (dtype, shape, bytes) -> their geometries and which are used (open_intervals)

    def _geometries(self, plant, inspector, ids: list, arms: list) -> tuple:
        """The kernel's arrays for geometries ``ids``: body, X_BG (3 x 4), Shape's half, radius and
        rounding, lever arms (num_positions,), whether a joint moves it."""
        count, positions = len(ids), self.kinematics.num_positions
        shapes = [Shape.of(inspector.GetShape(g)) for g in ids]
        arms = np.array(arms, dtype=float).reshape(count, positions)
        return (
            np.array([int(plant.GetBodyFromFrameId(inspector.GetFrameId(g)).index()) for g in ids], dtype=np.int64),
            np.array([inspector.GetPoseInFrame(g).GetAsMatrix34() for g in ids]).reshape(count, 3, 4),
            np.array([shape.half for shape in shapes]).reshape(count, 3),
            np.array([shape.radius for shape in shapes]),
            np.array([shape.rounding for shape in shapes]),
            arms,
            np.any(arms > 0, axis=1),
        )

    @staticmethod
    def _sides(inspector, id_A, id_B):
        """(covered id, boxed id), or None if the pair is not bounded: the covered geometry is the
        one with the smaller circumradius among those that can be covered (not boxes)."""
        shapes = [inspector.GetShape(g) for g in (id_A, id_B)]
        exact = [Shape.of(shape) for shape in shapes]
        if exact[0] is None or exact[1] is None:
            return None
        candidates = [i for i in (0, 1) if isinstance(shapes[i], (Sphere, Capsule, Cylinder))]
        if not candidates:
            return None
        i = min(candidates, key=lambda side: exact[side].circumradius)
        ids = (id_A, id_B)
        return ids[i], ids[1 - i]

    def open_intervals(self, q: np.ndarray, bend: np.ndarray, block: int, pairs: np.ndarray, threshold: float) -> tuple[np.ndarray, float, np.ndarray]:
        """Which intervals of a sampled motion the swept boxes do not prove at least
        ``threshold`` (m) clear for each of ``pairs`` (indices of bounded pairs): (P, n) bool;
        the smallest bound (m) of the blocks and intervals they proved clear (inf if none); and
        the body poses at the samples (``KinematicTree.pose_rows``). q (num_positions, n + 1),
        n >= 1: the samples, one per column; bend (num_positions, n): per joint and interval,
        h^2 / 8 (A_j + V_j (V_j + 4 U_j)) (module doc); block: intervals per block."""
        pairs = np.asarray(pairs)
        key = (pairs.dtype.str, pairs.shape, pairs.tobytes())  # the checker asks for one set of pairs nearly always
        if key not in self._pair_arrays:
            if len(self._pair_arrays) >= 64:
                self._pair_arrays.clear()
            covered, boxed = self._pair_covered[pairs], self._pair_boxed[pairs]
            covered_used, boxed_used = np.zeros(len(self._covered[0]), dtype=bool), np.zeros(len(self._boxed[0]), dtype=bool)
            covered_used[covered] = boxed_used[boxed] = True
            self._pair_arrays[key] = covered, boxed, covered_used, boxed_used
        covered, boxed, covered_used, boxed_used = self._pair_arrays[key]
        return _open_intervals(
            np.ascontiguousarray(q, dtype=float), np.ascontiguousarray(bend, dtype=float), int(block), float(threshold),
            self.kinematics.arrays, self._covered, covered_used, self._spheres, self._boxed, boxed_used, covered, boxed,
        )


@numba.njit(cache=True)
def _open_intervals(q, bend, block, threshold, tree, covered, covered_used, spheres, boxed, boxed_used, pair_covered, pair_boxed):
    """``SweptBounds.open_intervals``. tree: ``KinematicTree.arrays``; covered, boxed:
    ``SweptBounds._geometries`` of each side's geometries, with which of them the pairs use;
    spheres: the covers (first sphere of each covered geometry, centres in its frame G, radii);
    pair_covered, pair_boxed (P,): each pair's geometries."""
    samples = q.shape[1]
    n = samples - 1
    X = np.empty((tree[5].shape[0], 12, samples))
    _body_poses(q, tree, X)
    covered_pose, covered_box, covered_bend = _geometry_boxes(X, bend, covered, covered_used, True)
    _, boxed_box, boxed_bend = _geometry_boxes(X, bend, boxed, boxed_used, False)
    covered_hull, covered_most = _block_hulls(covered_box, covered_bend, covered_used, block)
    boxed_hull, boxed_most = _block_hulls(boxed_box, boxed_bend, boxed_used, block)
    sphere_start, sphere_centre, sphere_radius = spheres
    centres = np.empty((sphere_radius.shape[0], 3, block + 1))  # at the samples of block centres_of[c]
    centres_of = np.full(covered_used.shape[0], -1)
    covered_pair, boxed_pair = np.empty((2, 3)), np.empty((2, 3))  # boxes over one interval
    open_ = np.zeros((pair_covered.shape[0], n), dtype=np.bool_)
    smallest = np.inf
    for b in range(covered_hull.shape[0]):
        first, last = b * block, min((b + 1) * block, n)
        for p in range(pair_covered.shape[0]):
            c, g = pair_covered[p], pair_boxed[p]
            # The block's boxes, then its spheres' boxes.
            pad = covered_most[b, c] + boxed_most[b, g]
            bound = _box_distance(covered_hull[b, c], boxed_hull[b, g], pad)
            if bound < threshold:
                if centres_of[c] != b:
                    _sphere_centres(covered_pose[c], first, last, sphere_start[c], sphere_start[c + 1], sphere_centre, centres)
                    centres_of[c] = b
                bound = max(bound, _nearest_sphere(centres, 0, last - first, sphere_start[c], sphere_start[c + 1], sphere_radius, boxed_hull[b, g], pad))
            if bound >= threshold:
                smallest = min(smallest, bound)
                continue
            # Interval by interval: geometry boxes, then sphere boxes.
            for k in range(first, last):
                _hull_of_two(covered_box[c], k, covered_pair)
                _hull_of_two(boxed_box[g], k, boxed_pair)
                pad = covered_bend[c, k] + boxed_bend[g, k]
                bound = _box_distance(covered_pair, boxed_pair, pad)
                if bound < threshold:
                    bound = max(bound, _nearest_sphere(centres, k - first, k - first + 1, sphere_start[c], sphere_start[c + 1], sphere_radius, boxed_pair, pad))
                if bound >= threshold:
                    smallest = min(smallest, bound)
                else:
                    open_[p, k] = True
    return open_, smallest, X


@numba.njit(cache=True)
def _geometry_boxes(X, bend, geometries, used, keep_poses):
    """From the body poses X (num_bodies, 12, n + 1): each used geometry's poses X_WG (G, 12,
    n + 1) (if ``keep_poses``, else only a scratch pose (1, 12, n + 1)), world boxes (G, 2, 3,
    n + 1) (low and high corners by sample) and deviation from the chords per interval (G, n), m
    (module doc)."""
    body, X_BG, half, radius, rounding, arms, moving = geometries
    count, samples = used.shape[0], X.shape[2]
    pose, box, deviation = np.empty((count if keep_poses else 1, 12, samples)), np.empty((count, 2, 3, samples)), np.zeros((count, samples - 1))
    for g in range(count):
        if not used[g]:
            continue
        slot = g if keep_poses else 0
        computed = samples if moving[g] else 1  # what no joint moves: its first pose, copied
        _compose_fixed(X[body[g]], X_BG[g], pose[slot], computed)
        for r in range(3):  # the support along world axis r: row r of R_WG, in G
            u0, u1, u2, p = pose[slot, 4 * r], pose[slot, 4 * r + 1], pose[slot, 4 * r + 2], pose[slot, 4 * r + 3]
            low, high = box[g, 0, r], box[g, 1, r]
            for s in range(computed):
                extent = abs(u0[s]) * half[g, 0] + abs(u1[s]) * half[g, 1] + abs(u2[s]) * half[g, 2] + rounding[g]
                low[s], high[s] = p[s] - extent, p[s] + extent
            if radius[g] > 0.0:  # a cylinder's disc
                for s in range(computed):
                    extent = radius[g] * math.sqrt(max(0.0, 1.0 - u2[s] * u2[s]))
                    low[s] -= extent
                    high[s] += extent
        if not moving[g]:
            if keep_poses:
                for e in range(12):
                    pose[g, e, :] = pose[g, e, 0]
            for side in range(2):
                for r in range(3):
                    box[g, side, r, :] = box[g, side, r, 0]
            continue
        for j in range(arms.shape[1]):
            if arms[g, j] > 0.0:
                for k in range(samples - 1):
                    deviation[g, k] += bend[j, k] * arms[g, j]
    return pose, box, deviation


@numba.njit(cache=True)
def _block_hulls(box, deviation, used, block):
    """Per block: the hull (B, G, 2, 3) of each used geometry's boxes (G, 2, 3, n + 1) at the
    block's samples, and its largest deviation (B, G) in the block's intervals."""
    count, n = used.shape[0], box.shape[3] - 1
    blocks = (n + block - 1) // block
    hull, most = np.empty((blocks, count, 2, 3)), np.zeros((blocks, count))
    for g in range(count):
        if not used[g]:
            continue
        low0, low1, low2, high0, high1, high2 = box[g, 0, 0], box[g, 0, 1], box[g, 0, 2], box[g, 1, 0], box[g, 1, 1], box[g, 1, 2]
        for b in range(blocks):
            first, last = b * block, min((b + 1) * block, n)
            # The six extremes side by side (each over the samples in order): independent
            # chains of min and max run in parallel where one at a time waits on each step.
            x0, x1, x2, y0, y1, y2 = low0[first], low1[first], low2[first], high0[first], high1[first], high2[first]
            for s in range(first + 1, last + 1):
                x0, x1, x2 = min(x0, low0[s]), min(x1, low1[s]), min(x2, low2[s])
                y0, y1, y2 = max(y0, high0[s]), max(y1, high1[s]), max(y2, high2[s])
            hull[b, g, 0, 0], hull[b, g, 0, 1], hull[b, g, 0, 2] = x0, x1, x2
            hull[b, g, 1, 0], hull[b, g, 1, 1], hull[b, g, 1, 2] = y0, y1, y2
            largest = 0.0
            for k in range(first, last):
                largest = max(largest, deviation[g, k])
            most[b, g] = largest
    return hull, most


@numba.njit(cache=True)
def _sphere_centres(pose, first, last, start, stop, sphere_centre, centres):
    """centres (spheres, 3, block + 1), in place: spheres start..stop - 1's centres at samples
    first..last (columns 0..last - first) of a covered geometry with poses X_WG (12, n + 1)."""
    for i in range(start, stop):
        x, y, z = sphere_centre[i, 0], sphere_centre[i, 1], sphere_centre[i, 2]
        for r in range(3):
            u0, u1, u2, p = pose[4 * r], pose[4 * r + 1], pose[4 * r + 2], pose[4 * r + 3]
            out = centres[i, r]
            for s in range(first, last + 1):
                out[s - first] = u0[s] * x + u1[s] * y + u2[s] * z + p[s]


@numba.njit(cache=True)
def _nearest_sphere(centres, first, last, start, stop, radius, other, pad):
    """The smallest distance (m) between the box ``other`` (2, 3) and the boxes of spheres
    start..stop - 1 over their centres' columns first..last, all padded by ``pad`` (m)."""
    nearest = np.inf
    sphere_box = np.empty((2, 3))
    for i in range(start, stop):
        for r in range(3):
            smallest, largest = np.inf, -np.inf
            for s in range(first, last + 1):
                smallest, largest = min(smallest, centres[i, r, s]), max(largest, centres[i, r, s])
            sphere_box[0, r], sphere_box[1, r] = smallest, largest
        nearest = min(nearest, _box_distance(sphere_box, other, pad + radius[i]))
    return nearest


@numba.njit(cache=True)
def _hull_of_two(box, k, hull):
    """hull (2, 3), in place: that of a geometry's boxes (2, 3, n + 1) at samples k and k + 1."""
    for r in range(3):
        hull[0, r] = min(box[0, r, k], box[0, r, k + 1])
        hull[1, r] = max(box[1, r, k], box[1, r, k + 1])


@numba.njit(cache=True)
def _box_distance(a, b, pad):
    """The distance (m) between the boxes a and b ((low, high) corners (2, 3) each) when padded by
    ``pad`` (m) in total between them; 0 if they meet."""
    squared = 0.0
    for r in range(3):
        gap = max(b[0, r] - a[1, r], a[0, r] - b[1, r]) - pad
        if gap > 0.0:
            squared += gap * gap
    return math.sqrt(squared)
