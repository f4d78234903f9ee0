"""SegmentObservationBuilder: the policy's observation s_t of B environments."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ace_drake.contracts import SKILL_SIZE, ObservationLayout
from ace_drake.control.hit_prediction import HitPredictor
from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.measurements import MeasurementHistoryBatch
from ace_drake.systems.observation_builder import DEFAULT_SKILL, assemble_observation, hit_prediction_parts


class SegmentObservationBuilder(LeafSystem):
    """The continuous-time ``ObservationBuilder`` for B environments (paper, Methods *States*;
    ``observation_builder.assemble_observation``), built at each tick's start, the observation
    instant 5 ms before the segment the tick decides.

    Input ports:
        position_measurements, spin_measurements (abstract MeasurementHistoryBatch, or a tuple of B
            MeasurementHistory).
        robot_state (abstract float (B, 24)): [q, v, a] where the next segment starts.
        end_effector_state (abstract float (B, 13)): the racket frame's state there.
        ball_state_estimate (abstract float (B, 9)), estimate_status (abstract float (B, 3)).
        episode_ticks (abstract int64 (B,)): the EpisodeClock's.
    Output ports:
        observation (abstract float (B, layout.size)): ``ObservationLayout`` rows.
    State:
        abstract float (B, 3): each episode's skill [y_desired (m), w_p, w_s]; with
        ``hit_memory``, abstract float (B,): the episode time (s) of the hit the last observation
        predicted (NaN for none).
    Events (with ``hit_memory``): periodic unrestricted update every T (offset 0) storing it.
    """

    def __init__(self, layout: ObservationLayout, batch: int, timing: SegmentTiming, predictor: HitPredictor | None = None, hit_memory: bool = False):
        """Args: layout, the history lengths; batch, B; timing; predictor, the HitPredictor of the
        ``hit_prediction`` part (None: zeros there); hit_memory, keep the predicted hit between
        observations (needs a predictor)."""
        super().__init__()
        if hit_memory and predictor is None:
            raise ValueError("SegmentObservationBuilder: hit_memory needs a predictor (the hit_prediction part)")
        self.layout = layout
        self.batch = int(batch)
        self.timing = timing
        self.predictor = predictor
        self.hit_memory = hit_memory
        B = self.batch
        self._no_kept_hits = np.full(B, np.nan)  # without hit_memory: no row keeps a hit
        self._no_kept_hits.flags.writeable = False
        self.position_measurements_port = self.DeclareAbstractInputPort("position_measurements", AbstractValue.Make(()))
        self.spin_measurements_port = self.DeclareAbstractInputPort("spin_measurements", AbstractValue.Make(()))
        self.robot_state_port = self.DeclareAbstractInputPort("robot_state", AbstractValue.Make(np.zeros((B, 24))))
        self.end_effector_state_port = self.DeclareAbstractInputPort("end_effector_state", AbstractValue.Make(np.zeros((B, 13))))
        self.ball_state_estimate_port = self.DeclareAbstractInputPort("ball_state_estimate", AbstractValue.Make(np.zeros((B, 9))))
        self.estimate_status_port = self.DeclareAbstractInputPort("estimate_status", AbstractValue.Make(np.zeros((B, 3))))
        self.episode_ticks_port = self.DeclareAbstractInputPort("episode_ticks", AbstractValue.Make(np.zeros(B, dtype=np.int64)))
        self._skill_index = self.DeclareAbstractState(AbstractValue.Make(np.tile(np.asarray(DEFAULT_SKILL, dtype=float), (B, 1))))
        self._memory_index = self.DeclareAbstractState(AbstractValue.Make(np.full(B, np.nan)))
        self.observation_port = self.DeclareAbstractOutputPort(
            "observation", lambda: AbstractValue.Make(np.zeros((B, layout.size))), self.CalcObservation
        )
        if hit_memory:
            self.DeclarePeriodicUnrestrictedUpdateEvent(timing.duration, 0.0, self.UpdateHitMemory)

    def SetSkills(self, context, rows, skills) -> None:
        """Sets the skills (k, 3) [y_desired (m), w_p in [0, 1], w_s in [-1, 1]] of environments
        ``rows`` and forgets their kept hits (a new episode)."""
        rows = np.asarray(rows, dtype=int)
        skills = np.asarray(skills, dtype=float).reshape(rows.size, -1)
        if skills.shape[1] != SKILL_SIZE or not np.all(np.isfinite(skills)):
            raise ValueError(f"SegmentObservationBuilder.SetSkills: expected ({rows.size}, {SKILL_SIZE}) finite values, got {skills.shape}")
        if not (np.all((0.0 <= skills[:, 1]) & (skills[:, 1] <= 1.0)) and np.all(np.abs(skills[:, 2]) <= 1.0)):
            raise ValueError(f"SegmentObservationBuilder.SetSkills: w_p must be in [0, 1] and w_s in [-1, 1], got {skills[:, 1:]}")
        all_skills, memory = self.skills(context).copy(), context.get_abstract_state(self._memory_index).get_value().copy()
        all_skills[rows], memory[rows] = skills, np.nan
        context.SetAbstractState(self._skill_index, all_skills)
        context.SetAbstractState(self._memory_index, memory)

    def skills(self, context) -> np.ndarray:
        """The skills (B, 3) in this system's ``context`` (read only)."""
        return context.get_abstract_state(self._skill_index).get_value()

    def CalcObservation(self, context, output):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        # Every row's histories in one array operation (a tuple of MeasurementHistory is converted).
        positions, spins = (
            (h if isinstance(h, MeasurementHistoryBatch) else MeasurementHistoryBatch.from_histories(h)).as_array(count, now)
            for h, count in ((self.position_measurements_port.Eval(context), self.layout.position_history),
                             (self.spin_measurements_port.Eval(context), self.layout.spin_history))
        )
        robot, effector = self.robot_state_port.Eval(context), self.end_effector_state_port.Eval(context)
        estimate, status = self.ball_state_estimate_port.Eval(context), self.estimate_status_port.Eval(context)
        skills, kept = self.skills(context), context.get_abstract_state(self._memory_index).get_value()
        observation = np.empty((self.batch, self.layout.size))
        hits = [None] * self.batch
        if self.predictor is not None:  # every row's hit_prediction part in one call
            kept_hits = kept if self.hit_memory else self._no_kept_hits
            hits = hit_prediction_parts(self.predictor, np.asarray(now, dtype=float), estimate, status, kept_hits)
        for row in range(self.batch):
            observation[row] = assemble_observation(
                self.layout, self.predictor, float(now[row]), positions[row], spins[row], robot[row], effector[row],
                skills[row], estimate[row], status[row], kept[row] if self.hit_memory else np.nan, hits[row],
            )
        output.set_value(observation)

    def UpdateHitMemory(self, context, state):
        now = self.timing.tick_time(self.episode_ticks_port.Eval(context))
        hit = self.observation_port.Eval(context)[:, self.layout.slice("hit_prediction")]
        kept = np.where(hit[:, 0] > 0.5, now + hit[:, 1], np.nan)
        state.get_mutable_abstract_state(self._memory_index).set_value(kept)
