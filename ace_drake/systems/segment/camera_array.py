"""SegmentCameraArray: the nine frame cameras and the triangulator of B environments."""

from __future__ import annotations

import numpy as np

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.camera_segment import CameraSegment
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import PendingBatch
from ace_drake.systems.segment.position_sensor import SegmentPositionSensor


class SegmentCameraArray(SegmentPositionSensor):
    """The continuous-time ``ApsCameraArray`` (analytic mode) and ``Triangulator`` for B
    environments in one system (paper, Methods *Ball triangulation*;
    ``perception.camera_segment.CameraSegment``): at each 200 Hz trigger inside a tick every
    camera detects the ball or not (pixel noise, dropout, the table's occlusion), the frame is
    triangulated (multi-view DLT, Gauss-Newton, outlier rejection) and released after the
    triangulation latency. The draws of trigger k of an episode come from [seed, k + 1], as the
    reference's. Ports, state and events as the SegmentPositionSensor's (the position path's
    other choice; the wiring is the same).
    """

    def __init__(self, cameras: CameraSegment, history_capacity: int, batch: int, timing: SegmentTiming):
        """Args: cameras, the batched camera array; history_capacity, the measurements the output
        keeps; batch, B; timing, the segment time line."""
        self.cameras = cameras
        super().__init__(PositionSensorParams(history_capacity=history_capacity), batch, timing)

    def _trigger_period(self) -> float:
        return self.cameras.period

    def _sample(self, flight, ticks: np.ndarray, first: np.ndarray, seeds: np.ndarray) -> PendingBatch:
        """Every environment's PendingMeasurements of the tick's triggers: all the triggers of
        all environments detected and triangulated in one call (``CameraSegment.frames``; each
        trigger's draws depend on its seed and number only)."""
        triggers, valid = self._trigger_grid(first)
        sample_rows, columns = np.nonzero(valid)  # row by row, in trigger order
        if sample_rows.size == 0:
            return PendingBatch.empty()
        sample_triggers = triggers[sample_rows, columns]  # episode samples
        capture_times = self.timing.seconds(sample_triggers)
        p_W = flight.samples[sample_rows, sample_triggers - first[sample_rows], :3]
        _, frames = self.cameras.frames(p_W, seeds[sample_rows].astype(np.uint64), (sample_triggers // self._trigger + 1).astype(np.uint64))
        return PendingBatch.from_samples(sample_rows, capture_times, capture_times + self.cameras.params.latency, frames.position, frames.covariance,
                                         frames.valid)
