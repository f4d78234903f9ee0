"""ObservationBuilder: the rally controller's observation vector from sensors, estimator and plan."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem

from ace_drake.contracts import (
    END_EFFECTOR_SIZE,
    ESTIMATE_SIZE,
    ESTIMATE_STATUS_SIZE,
    ROBOT_STATE_SIZE,
    SKILL_SIZE,
    ObservationLayout,
)
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.perception.measurements import MeasurementHistory

DEFAULT_SKILL = (0.0, 1.0, 0.0)  # y_desired 0 m (the centre line), w_p = 1, w_s = 0


def assemble_observation(layout: ObservationLayout, predictor: HitPredictor | None, now: float, positions, spins, robot_state, end_effector,
                         skill, estimate, status, kept_hit: float = np.nan, hit_prediction: np.ndarray | None = None) -> np.ndarray:
    """The observation vector (layout.size,) at time ``now`` (s) from the sensors' histories, the
    robot state and end effector where the next segment starts, the skill and the estimator's
    outputs; the ``hit_prediction`` part from ``predictor`` (zeros without one), keeping the hit at
    time ``kept_hit`` (s; NaN for none) while it is still a candidate, or ``hit_prediction``
    (HIT_PREDICTION_SIZE,) when given (computed for many rows at once by
    ``hit_prediction_parts``). ``positions`` and ``spins``: MeasurementHistory, or their
    ``as_array`` rows at ``now`` already computed (the segment-stepped builder's, for all rows at
    once). The ObservationBuilder's rule, shared by the segment-stepped builder."""
    hit = hit_prediction
    if hit is None and predictor is not None:
        keep = kept_hit - now if np.isfinite(kept_hit) else None
        hit = predictor.features(estimate, valid=status[0] > 0.5, keep=keep)
    return layout.assemble(
        positions=positions if isinstance(positions, np.ndarray) else positions.as_array(layout.position_history, now),
        spins=spins if isinstance(spins, np.ndarray) else spins.as_array(layout.spin_history, now),
        robot_state=robot_state,
        end_effector=end_effector,
        skill=skill,
        estimate=estimate,
        estimate_status=status,
        hit_prediction=hit,
    )


def hit_prediction_parts(predictor: HitPredictor, now, estimates, statuses, kept_hits) -> np.ndarray:
    """``assemble_observation``'s ``hit_prediction`` parts of B rows at once, (B,
    HIT_PREDICTION_SIZE): row b is the part ``assemble_observation`` computes from now[b] (s),
    estimates[b] (9,), statuses[b] (3,) and kept_hits[b] (s, NaN for none), bit for bit
    (``HitPredictor.features_batch``)."""
    now, kept_hits = np.asarray(now, dtype=float), np.asarray(kept_hits, dtype=float)
    statuses = np.asarray(statuses, dtype=float).reshape(len(now), -1)
    keep = np.where(np.isfinite(kept_hits), kept_hits - now, np.nan)
    return predictor.features_batch(np.asarray(estimates, dtype=float).reshape(len(now), -1), statuses[:, 0] > 0.5, keep)


class ObservationBuilder(LeafSystem):
    """Builds s_t (paper, Methods *States*; layout in ``contracts``) on demand, at
    whatever time the PolicyController evaluates it (5 ms before its segment starts).

    Input ports:
        position_measurements (abstract MeasurementHistory): ball positions (m), any position sensor.
        spin_measurements (abstract MeasurementHistory): ball spins (rad/s).
        robot_state (24,): [q, v, a] where the next segment starts (SafetySupervisor's
            segment_start_state).
        end_effector_state (13,): the racket frame's state there (RobotKinematics of that state).
        ball_state_estimate (9,), estimate_status (3,): the BallEstimator's outputs.
    Output ports:
        observation (layout.size,): the vector of ``ObservationLayout``; history ages are
            measured from the context's time; the ``hit_prediction`` part from the estimate by
            ``predictor`` (zeros without one).
    Parameters:
        numeric skill (3,): [y_desired (m), w_p, w_s], fixed for an episode (paper eq. (11)).
    State: none; with ``hit_memory``, discrete [the time (s) of the hit the last observation
        predicted, NaN for none], so that the ``hit_prediction`` part keeps that hit while it is
        still a candidate (``HitPredictor.preferred_hit``'s ``keep``: the model-based returner's
        memory of its hit time) instead of switching between segment boundaries as the estimate
        moves.
    Events (with ``hit_memory``): periodic discrete update at the PolicyController's instants
        (every T, offset T - observation lead), storing the hit of the observation it reads.
    """

    def __init__(self, layout: ObservationLayout | None = None, skill=DEFAULT_SKILL, predictor: HitPredictor | None = None,
                 hit_memory: bool = False):
        """Args: layout, the history lengths; skill, the default skill parameter; predictor, the
        HitPredictor of the observation's ``hit_prediction`` part (None: zeros there);
        hit_memory: keep the predicted hit from one observation to the next (class docstring;
        needs a predictor)."""
        super().__init__()
        if hit_memory and predictor is None:
            raise ValueError("ObservationBuilder: hit_memory needs a predictor (the hit_prediction part)")
        self.layout = layout or ObservationLayout()
        self.predictor = predictor
        self.hit_memory = hit_memory
        self.position_measurements_port = self.DeclareAbstractInputPort("position_measurements", AbstractValue.Make(MeasurementHistory()))
        self.spin_measurements_port = self.DeclareAbstractInputPort("spin_measurements", AbstractValue.Make(MeasurementHistory()))
        self.robot_state_port = self.DeclareVectorInputPort("robot_state", ROBOT_STATE_SIZE)
        self.end_effector_state_port = self.DeclareVectorInputPort("end_effector_state", END_EFFECTOR_SIZE)
        self.ball_state_estimate_port = self.DeclareVectorInputPort("ball_state_estimate", ESTIMATE_SIZE)
        self.estimate_status_port = self.DeclareVectorInputPort("estimate_status", ESTIMATE_STATUS_SIZE)
        if len(skill) != SKILL_SIZE:
            raise ValueError(f"ObservationBuilder: skill must have {SKILL_SIZE} values, got {len(skill)}")
        self._skill_index = self.DeclareNumericParameter(BasicVector(np.asarray(skill, dtype=float)))
        self.observation_port = self.DeclareVectorOutputPort("observation", self.layout.size, self.CalcObservation)
        if hit_memory:
            self._memory_index = self.DeclareDiscreteState(BasicVector([np.nan]))
            segment, lead = predictor.segment, predictor.lead
            self.DeclarePeriodicDiscreteUpdateEvent(segment, segment - lead, self.UpdateHitMemory)

    def SetSkill(self, context, skill) -> None:
        """Sets the episode's skill [y_desired (m), w_p in [0, 1], w_s in [-1, 1]] in ``context``."""
        skill = np.asarray(skill, dtype=float)
        if skill.shape != (SKILL_SIZE,) or not np.all(np.isfinite(skill)):
            raise ValueError(f"ObservationBuilder.SetSkill: expected {SKILL_SIZE} finite values, got {skill}")
        if not (0.0 <= skill[1] <= 1.0 and -1.0 <= skill[2] <= 1.0):
            raise ValueError(f"ObservationBuilder.SetSkill: w_p must be in [0, 1] and w_s in [-1, 1], got {skill[1:]}")
        context.get_mutable_numeric_parameter(self._skill_index).SetFromVector(skill)

    def GetSkill(self, context) -> np.ndarray:
        """The episode's skill [y_desired (m), w_p, w_s] (3,) in ``context`` (a copy)."""
        return context.get_numeric_parameter(self._skill_index).get_value().copy()

    def CalcObservation(self, context, output: BasicVector) -> None:
        kept = context.get_discrete_state(self._memory_index).get_value()[0] if self.hit_memory else np.nan
        output.SetFromVector(
            assemble_observation(
                self.layout, self.predictor, context.get_time(), self.position_measurements_port.Eval(context),
                self.spin_measurements_port.Eval(context), self.robot_state_port.Eval(context), self.end_effector_state_port.Eval(context),
                context.get_numeric_parameter(self._skill_index).get_value(), self.ball_state_estimate_port.Eval(context),
                self.estimate_status_port.Eval(context), kept,
            )
        )

    def UpdateHitMemory(self, context, discrete_state) -> None:
        """Stores the time (s) of the hit the observation now predicts (NaN: none)."""
        hit = self.layout.part(self.observation_port.Eval(context), "hit_prediction")
        kept = context.get_time() + hit[1] if hit[0] > 0.5 else np.nan
        discrete_state.get_mutable_vector(self._memory_index).SetFromVector([kept])
