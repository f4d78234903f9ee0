"""BallPlant: the ball's true state under flight, table, net, floor and racket contact."""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.framework import (
    BasicVector,
    LeafSystem,
    UnrestrictedUpdateEvent,
    WitnessFunctionDirection,
)

from ace_drake.physics import contact
from ace_drake.physics.contact import ResidualModel
from ace_drake.physics.flight import one_ball_flight_acceleration
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind, apply_impact, contact_gap, contact_gap_lower_bound, is_contact
from ace_drake.systems.random_seed import declare_seed_port, episode_seed

# m: a witness returns a cheap lower bound on its gap while that bound exceeds this (far above the
# bounds' round-off of a few 1e-16 m), else the gap itself (BallPlant's docstring).
WITNESS_BOUND_MARGIN = 1e-9


class BallPlant(LeafSystem):
    """The table-tennis ball: ground truth for every other system (paper, Methods *Simulation*).

    Input ports:
        racket_pose (abstract RigidTransform): X_WR, the racket frame R in world; R's origin is the
            blade centre and its z axis the blade normal. Unconnected: there is no racket.
        racket_spatial_velocity (abstract SpatialVelocity): V_WR of R's origin in world,
            [w (rad/s), v (m/s)]. Needed when racket_pose is connected.
        random_seed (1,), random uniform, only with ``perturb``: the seed of the post-table
            contact perturbations, drawn by Drake's random context (``systems.random_seed``).
            Unconnected: the seed parameter.
    Output ports:
        ball_state (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)] in world (DESIGN.md frame).
        contact_events (abstract tuple[ContactEvent]): the contacts of this episode, in order, with
            kind, time (s) and the (9,) states before and after.
    State:
        continuous (9,): [p, v, w]; spin is constant in flight (paper eq. (1)).
        abstract: the tuple of contact events.
    Parameters:
        numeric (1,): the seed of the perturbations while random_seed is unconnected.
    Events:
        witness functions on the table, net, floor and (when connected) racket gaps; each
        triggers an unrestricted update applying that contact's impact map from ``physics/``.

    Contact times are located by the Simulator's witness isolation: use ``diagrams.make_simulator``
    (maximum step 1 ms, accuracy 1e-6), which keeps a racket from being tunnelled through at relative
    speeds up to 50 m/s and places contacts within 1e-6 s.

    The witnesses are evaluated at both ends of every integrator step, thousands of times per
    simulated second. Drake's triggering and isolation look only at the signs of witness values,
    so while a cheap lower bound on a gap exceeds WITNESS_BOUND_MARGIN a witness returns that bound
    (``physics.propagate.contact_gap_lower_bound``; for the racket, the distance between the ball's
    and the blade's centres less the ball's radius and the blade's half-diagonal), and otherwise
    the exact gap: every sign, hence every contact time, is the exact gap's. Given the box the
    blade's centre never leaves (``racket_reach``, from ``robot.model.racket_reach_box``), the
    racket witness first bounds the gap by the ball's distance to that box, which needs no racket
    pose (and so no joint propagation and kinematics): for most of a ball's flight on the far side.
    """

    def __init__(
        self,
        params: BallPhysicsParams | None = None,
        perturb: bool = False,
        seed: int = 0,
        racket_residual: ResidualModel | None = None,
        racket_reach: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """Args: params, the ball model; perturb, apply the paper's post-table perturbations
        (seeded by the random_seed input; unconnected, by the context's seed parameter, ``seed``
        by default); racket_residual, an optional correction model for racket contacts (see
        physics/racket_residual.py); racket_reach, the lower and upper corners (3,) (m, world) of
        a box that contains the racket frame's origin at all times, or None (no such knowledge)."""
        super().__init__()
        self.params = params or BallPhysicsParams()
        self._perturb = perturb
        self._residual = racket_residual
        self._reach = None
        if racket_reach is not None:
            lower, upper = (np.asarray(corner, dtype=float).reshape(-1) for corner in racket_reach)
            if lower.shape != (3,) or upper.shape != (3,) or not np.all(np.isfinite(lower) & np.isfinite(upper) & (lower <= upper)):
                raise ValueError(f"BallPlant: racket_reach must be two finite corners (3,) with lower <= upper, got {racket_reach}")
            self._reach = (lower.tolist(), upper.tolist())
        # Every point of the blade lies within this distance of its centre, m.
        self._blade_half_diagonal = contact.blade_half_diagonal(self.params.racket)
        self._state_index = self.DeclareContinuousState(9)
        self._events_index = self.DeclareAbstractState(AbstractValue.Make(()))
        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.racket_pose_port = self.DeclareAbstractInputPort("racket_pose", AbstractValue.Make(RigidTransform()))
        self.racket_velocity_port = self.DeclareAbstractInputPort(
            "racket_spatial_velocity", AbstractValue.Make(SpatialVelocity())
        )
        self.random_seed_port = declare_seed_port(self) if perturb else None
        self.ball_state_port = self.DeclareVectorOutputPort(
            "ball_state", 9, self.CalcBallState, prerequisites_of_calc={self.xc_ticket()}
        )
        self.contact_events_port = self.DeclareAbstractOutputPort(
            "contact_events",
            lambda: AbstractValue.Make(()),
            self.CalcContactEvents,
            prerequisites_of_calc={self.abstract_state_ticket(self._events_index)},
        )
        direction = WitnessFunctionDirection.kPositiveThenNonPositive
        self._static_witnesses = [
            self.MakeWitnessFunction(
                kind.name.lower(),
                direction,
                lambda context, kind=kind: self.CalcStaticGap(context, kind),
                UnrestrictedUpdateEvent(lambda context, event, state, kind=kind: self._ApplyContact(context, state, kind)),
            )
            for kind in (ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR)
        ]
        self._racket_witness = self.MakeWitnessFunction(
            "racket", direction, self.CalcRacketGap, UnrestrictedUpdateEvent(self._ApplyRacketContact)
        )

    # ------------------------------------------------------------------------------ set-up
    def SetBallState(self, context, state: np.ndarray) -> None:
        """Starts an episode: sets the ball state (9,) and clears the contact events."""
        state = np.asarray(state, dtype=float)
        if state.shape != (9,) or not np.all(np.isfinite(state)):
            raise ValueError(f"BallPlant.SetBallState: expected 9 finite values [p, v, w], got {state}")
        context.SetContinuousState(state)
        context.get_mutable_abstract_state(self._events_index).set_value(())

    def SetSeed(self, context, seed: int) -> None:
        """Sets the seed of the post-table perturbations for this context, used while the
        random_seed input is unconnected (a diagram's random context seeds it otherwise)."""
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    # ------------------------------------------------------------------------------ dynamics
    def DoCalcTimeDerivatives(self, context, derivatives):
        _, _, _, vx, vy, vz, wx, wy, wz = self._state(context).tolist()
        acceleration = one_ball_flight_acceleration((vx, vy, vz), (wx, wy, wz), self.params.aero)  # paper eq. (1)
        derivatives.get_mutable_vector().SetFromVector([vx, vy, vz, *acceleration, 0.0, 0.0, 0.0])

    def DoGetWitnessFunctions(self, context):
        if self.racket_pose_port.HasValue(context):
            return self._static_witnesses + [self._racket_witness]
        return self._static_witnesses

    # ------------------------------------------------------------------------------ outputs
    def CalcBallState(self, context, output):
        output.SetFromVector(self._state(context))

    def CalcContactEvents(self, context, output):
        output.set_value(context.get_abstract_state(self._events_index).get_value())

    def CalcRacketGap(self, context) -> float:
        """Distance from the ball's surface to the blade (a disc of radius R_b, thickness t), m;
        while the ball is clear of the blade's bounding sphere, a lower bound on it (the class
        docstring)."""
        p_WB = self._state(context)[:3]
        x, y, z = p_WB.tolist()
        if self._reach is not None:  # the distance to the box the blade's centre stays in
            (x_lo, y_lo, z_lo), (x_hi, y_hi, z_hi) = self._reach
            dx, dy, dz = max(x_lo - x, 0.0, x - x_hi), max(y_lo - y, 0.0, y - y_hi), max(z_lo - z, 0.0, z - z_hi)
            bound = math.sqrt(dx * dx + dy * dy + dz * dz) - self._blade_half_diagonal - self.params.aero.ball_radius
            if bound > WITNESS_BOUND_MARGIN:
                return bound
        X_WR = self.racket_pose_port.Eval(context)
        x_R, y_R, z_R = X_WR.translation().tolist()
        bound = math.sqrt((x - x_R) ** 2 + (y - y_R) ** 2 + (z - z_R) ** 2) - self._blade_half_diagonal - self.params.aero.ball_radius
        if bound > WITNESS_BOUND_MARGIN:
            return bound
        return float(contact.racket_gap(p_WB, X_WR.translation(), X_WR.rotation().matrix(), self.params.racket, self.params.aero.ball_radius))

    def CalcStaticGap(self, context, kind: ContactKind) -> float:
        """The witness of a table, net or floor contact, m: the gap (``contact_gap``), or a lower
        bound on it while that is clearly positive (the class docstring)."""
        state = self._state(context)
        bound = contact_gap_lower_bound(kind, state[:3].tolist(), self.params)
        if bound > WITNESS_BOUND_MARGIN:
            return bound
        return float(contact_gap(kind, state, self.params))

    # ------------------------------------------------------------------------------ contacts
    def _ApplyContact(self, context, state, kind: ContactKind) -> None:
        pre = self._state(context)
        if not is_contact(kind, pre, self.params):
            return
        rng = None
        if self._perturb and kind == ContactKind.TABLE:
            seed = episode_seed(self.random_seed_port, context, context.get_numeric_parameter(self._seed_index).GetAtIndex(0))
            rng = np.random.default_rng([seed, len(self._events(context))])
        post = apply_impact(kind, pre, self.params, rng)
        self._record(context, state, kind, pre, post)

    def _ApplyRacketContact(self, context, event, state) -> None:
        pre = self._state(context)
        X_WR = self.racket_pose_port.Eval(context)
        V_WR = self.racket_velocity_port.Eval(context)
        post, impact = contact.racket_contact(
            pre, X_WR.translation(), X_WR.rotation().matrix(), V_WR.rotational(), V_WR.translational(),
            self.params.racket, self.params.aero.ball_radius, residual=self._residual,
        )  # paper eqs (7)-(8); a separating touch (a graze) is no impact
        if impact:
            self._record(context, state, ContactKind.RACKET, pre, post)

    def _record(self, context, state, kind, pre, post) -> None:
        state.get_mutable_continuous_state().SetFromVector(post)
        event = ContactEvent(kind, float(context.get_time()), pre.copy(), np.asarray(post, dtype=float).copy())
        state.get_mutable_abstract_state(self._events_index).set_value(self._events(context) + (event,))

    def _state(self, context) -> np.ndarray:
        return context.get_continuous_state_vector().CopyToVector()

    def _events(self, context) -> tuple:
        return context.get_abstract_state(self._events_index).get_value()
