"""Glove acquisition: wire protocol, stream decoder, serial driver, calibration, simulator.

Typical use (the same in the lab and in a simulated session)::

    port = serial.Serial("/dev/ttyUSB0", baudrate=921600)   # or SimulatedGloveUnit(...).port
    with SerialGloveUnit(port, GloveCalibration.from_config(cfg)) as glove:
        reading = glove.latest()          # GripReading in N, or None
        glove.check()                     # raises if the reader thread failed

The protocol is specified in docs/glove-protocol.md. The simulator lives in
hardware.glove.simulated and is not imported here: it needs POSIX ptys, the driver does not.
"""

from steerlab.hardware.glove.alignment import (
    AlignedStream,
    AlignmentSummary,
    ClockFit,
    align_zoh,
    fit_clock,
    unwrap_device_time,
)
from steerlab.hardware.glove.calibration import CalibrationError, GloveCalibration, HandCalibration
from steerlab.hardware.glove.decoder import (
    DecodeEvent,
    DecodeEventKind,
    DecoderStats,
    GloveDecoder,
    GloveFrame,
)
from steerlab.hardware.glove.protocol import crc16_ccitt_false, encode_frame
from steerlab.hardware.glove.unit import GloveUnitError, GloveUnitStats, SerialGloveUnit

__all__ = [
    "AlignedStream",
    "AlignmentSummary",
    "CalibrationError",
    "ClockFit",
    "DecodeEvent",
    "DecodeEventKind",
    "DecoderStats",
    "GloveCalibration",
    "GloveDecoder",
    "GloveFrame",
    "GloveUnitError",
    "GloveUnitStats",
    "HandCalibration",
    "SerialGloveUnit",
    "align_zoh",
    "crc16_ccitt_false",
    "encode_frame",
    "fit_clock",
    "unwrap_device_time",
]
