"""Measurement and MeasurementHistory: validation, numbering, what a consumer reads since."""

import numpy as np
import pytest

from ace_drake.perception.measurements import Measurement, MeasurementHistory


def measurement(sequence: int) -> Measurement:
    return Measurement(sequence, 0.005 * sequence, 0.005 * sequence + 0.01, np.full(3, float(sequence)), np.eye(3))


def test_since_gives_the_measurements_numbered_above_oldest_first():
    history = MeasurementHistory(capacity=4)
    for sequence in range(1, 7):  # 1 and 2 drop out beyond the capacity
        history = history.appended(measurement(sequence))
    assert [m.sequence for m in history.measurements] == [3, 4, 5, 6]
    assert [m.sequence for m in history.since(0)] == [3, 4, 5, 6]
    assert [m.sequence for m in history.since(4)] == [5, 6]
    assert history.since(6) == () and history.since(9) == ()
    assert MeasurementHistory().since(0) == ()


def test_a_measurement_owns_read_only_copies_and_refuses_bad_values():
    value = np.array([1.0, 2.0, 3.0])
    dut = Measurement(1, 0.0, 0.01, value, np.eye(3))
    value[0] = 9.0
    assert dut.value[0] == 1.0 and not dut.value.flags.writeable
    with pytest.raises(ValueError, match="finite"):
        Measurement(1, 0.0, 0.01, [np.nan, 0.0, 0.0], np.eye(3))
    with pytest.raises(ValueError, match="before its capture"):
        Measurement(1, 0.02, 0.01, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="sequence 1 does not follow 1"):
        MeasurementHistory().appended(dut).appended(dut)
