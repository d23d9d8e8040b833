"""SerialGloveUnit over in-process transports: loop:// and a failing fake port."""

from __future__ import annotations

import pytest
import serial

from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.glove.protocol import encode_frame
from steerlab.hardware.glove.unit import GloveUnitError, SerialGloveUnit
from steerlab.hardware.interfaces import GloveUnit, GripReading
from tests.helpers import assert_no_threads, wait_for

CAL = GloveCalibration.from_config(
    {
        "left": {"gain_n_per_count": 0.01, "offset_counts": 1000},
        "right": {"gain_n_per_count": 0.02, "offset_counts": 500},
    }
)


@pytest.fixture(autouse=True)
def no_thread_left_behind():
    yield
    assert_no_threads("glove-")


def test_exact_bytes_in_calibrated_reading_out():
    port = serial.serial_for_url("loop://", timeout=None)
    frames, events = [], []
    unit = SerialGloveUnit(
        port, CAL, on_frame=lambda f, r: frames.append((f, r)), on_event=events.append
    )
    assert isinstance(unit, GloveUnit)
    assert port.timeout == 0.05  # an unbounded read would block close()
    with unit:
        assert unit.latest() is None and unit.age_s() is None
        assert not unit.stream_alive()
        # The doc's example frame, byte for byte: left 1000 counts, right 70_000 counts.
        port.write(bytes.fromhex("a55a 0110 0e00 0201 40420f00 e8030000 70110100 e515"))
        wait_for(lambda: unit.latest() is not None)
        reading = unit.latest()
        assert reading == GripReading(
            left_n=0.0, right_n=0.02 * (70_000 - 500), host_time_s=reading.host_time_s,
            sequence=258,
        )  # fmt: skip
        assert reading.total_n == pytest.approx(1390.0)
        assert unit.latest_frame().device_time_us == 1_000_000
        assert unit.stream_alive(timeout_s=1.0)

        port.write(encode_frame(260, 1_020_000, 1100, 500))  # 259 lost on the line
        wait_for(lambda: unit.latest().sequence == 260)
        assert unit.latest().left_n == pytest.approx(1.0)
        stats = unit.stats()
        assert (stats.frames, stats.dropped_frames, stats.crc_errors) == (2, 1, 0)
        assert stats.running and stats.error is None
        assert [f.sequence for f, _ in frames] == [258, 260]
        assert [e.kind for e in events] == ["sequence_gap"]
    assert not unit.running
    assert not port.is_open
    unit.close()  # idempotent


def test_close_can_leave_the_port_open():
    port = serial.serial_for_url("loop://")
    SerialGloveUnit(port, CAL, close_port=False).start().close()
    assert port.is_open
    port.close()


def test_rate_and_age_follow_the_injected_clock():
    now = [100.0]
    port = serial.serial_for_url("loop://")
    with SerialGloveUnit(port, CAL, clock=lambda: now[0]) as unit:
        for i in range(11):
            now[0] = 100.0 + i * 0.01
            port.write(encode_frame(i, i * 10_000, 1000, 500))
            wait_for(lambda i=i: unit.stats().frames == i + 1)
        stats = unit.stats()
        assert stats.rate_hz == pytest.approx(100.0)
        assert stats.last_frame_age_s == pytest.approx(0.0)
        now[0] += 0.5
        assert unit.age_s() == pytest.approx(0.5)
        assert not unit.stream_alive(timeout_s=0.1)
        now[0] += 5.0
        assert unit.stats().rate_hz == 0.0  # nothing within the last second


class DyingPort:
    """Delivers some bytes, then fails like a USB adapter pulled out."""

    def __init__(self, data: bytes) -> None:
        self.timeout: float | None = 0.01
        self._data = bytearray(data)
        self.closed = False

    @property
    def in_waiting(self) -> int:
        return len(self._data)

    def read(self, size: int = 1) -> bytes:
        if not self._data:
            raise serial.SerialException("device reports readiness to read but returned no data")
        chunk = bytes(self._data[:size])
        del self._data[:size]
        return chunk

    def close(self) -> None:
        self.closed = True


def test_reader_failure_is_recorded_reported_and_raised():
    errors: list[BaseException] = []
    port = DyingPort(encode_frame(0, 0, 1000, 500) + encode_frame(1, 10_000, 2000, 500))
    unit = SerialGloveUnit(port, CAL, on_error=errors.append).start()
    wait_for(lambda: unit.error is not None)
    wait_for(lambda: not unit.running)
    assert isinstance(unit.error, serial.SerialException)
    assert errors == [unit.error]
    assert unit.latest().left_n == pytest.approx(10.0)  # the last good value stays readable
    assert not unit.stream_alive(timeout_s=60.0)  # a failed reader is never "alive"
    assert "SerialException" in unit.stats().error
    with pytest.raises(GloveUnitError) as info:
        unit.check()
    assert info.value.__cause__ is unit.error
    unit.close()
    assert port.closed


def test_a_raising_sink_stops_the_reader_with_that_error():
    def broken_sink(frame, reading):
        raise ZeroDivisionError("sink bug")

    port = serial.serial_for_url("loop://")
    unit = SerialGloveUnit(port, CAL, on_frame=broken_sink).start()
    port.write(encode_frame(0, 0, 1000, 500))
    wait_for(lambda: unit.error is not None)
    assert isinstance(unit.error, ZeroDivisionError)
    unit.close()


def test_a_raising_on_error_callback_does_not_hide_the_error():
    def bad_callback(exc):
        raise RuntimeError("callback bug")

    unit = SerialGloveUnit(DyingPort(b""), CAL, on_error=bad_callback).start()
    wait_for(lambda: unit.error is not None and not unit.running)
    assert isinstance(unit.error, serial.SerialException)
    unit.close()
