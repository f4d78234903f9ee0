"""SegmentCameraArray: the nine frame cameras and the triangulator of B environments."""

from __future__ import annotations

import numpy as np

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.camera_segment import CameraSegment
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import PendingMeasurement
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

    def _sample(self, flight, ticks: np.ndarray, first: np.ndarray, seeds: np.ndarray) -> list[tuple]:
        sampled: list[tuple] = [()] * self.batch
        groups: dict[tuple, list[int]] = {}
        for row in range(self.batch):
            groups.setdefault(tuple(self._triggers(first[row]) - first[row]), []).append(row)
        for offsets, rows in groups.items():
            if not offsets:
                continue
            rows = np.array(rows)
            indices = np.asarray(offsets)
            triggers = first[rows, None] + indices[None, :]  # episode samples (k, m)
            measured = self.cameras.measure(
                flight.samples[rows][:, indices, :3], self.timing.seconds(triggers), seeds[rows].astype(np.uint64), triggers // self._trigger + 1
            )
            for k, row in enumerate(rows):
                sampled[row] = tuple(
                    PendingMeasurement(float(measured.capture_time[k, i]), float(measured.release_time[k, i]), measured.value[k, i], measured.covariance[k, i])
                    for i in np.flatnonzero(measured.valid[k])
                )
        return sampled
