"""Grip force from any Lab Streaming Layer stream (``[glove] kind = "lsl"``).

A glove whose vendor software (or a small bridge program) publishes its forces on LSL is found
by the stream's name and/or type (and, where several match, its source id). The rig file says
which channels are the left and the right hand (by index from 0, or by the channel's label in
the stream's description), and whether the values are newtons or raw values with a
calibration::

    [glove]
    kind = "lsl"
    name = "GripGlove"        # and/or type = "Grip"; source_id = "…" picks one of several
    unit = "N"                # or "raw", with [glove.calibration.left/right] gain, offset
    resolve_timeout_s = 5.0   # how long to look for the stream when the rig is opened
    [glove.channels]
    left = "grip_left"        # a label, or an index: left = 0
    right = "grip_right"

:class:`LslGripSource` resolves the stream (:func:`open_lsl`: a clear error naming it when
none or several answer), opens an inlet (recovering if the outlet restarts) and pulls chunks in
a thread of its own. Each sample's host arrival time is its reading's ``host_time_s``, so the
stream is watched exactly as the glove unit is: a stream that vanishes (its outlet closed, its
program stopped, the network gone) or pauses shows as the newest sample ageing, and the
engine aborts the trial once that age passes ``[safety] glove_timeout_s``, naming the stream.
A sample whose hand channel is not a finite number is skipped and counted (``bad_samples``).

:class:`SimulatedLslGrip` publishes a simulated subject's grip on an outlet for a simulated
rig. ``pylsl`` is imported only when a stream is opened or published: it reads its
configuration (``LSLAPICFG``) once, when first imported.
"""

from __future__ import annotations

import logging
import math
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar

from steerlab.hardware.grip.common import HANDS, Fields, ForceScale, force_scale
from steerlab.hardware.grip.paced import PacedWriter
from steerlab.hardware.grip.reader import GripReader, GripSourceError
from steerlab.hardware.grips import GripFunction
from steerlab.hardware.interfaces import GripReading

log = logging.getLogger(__name__)

FIELDS = (
    "kind",
    "name",
    "type",
    "source_id",
    "unit",
    "resolve_timeout_s",
    "channels",
    "calibration",
)
#: the stream properties a rig file may find it by, in the resolve predicate's order
STREAM_KEYS = ("name", "type", "source_id")
_MAX_CHUNK = 1024
#: How long :func:`open_lsl` listens, after a stream answered, for another that matches too
#: (liblsl's second query wave goes out 0.5 s after the first).
AMBIGUITY_WINDOW_S = 0.75


@dataclass(frozen=True)
class LslGripConfig:
    name: str | None  # the stream's name, or None: any name
    type: str | None  # the stream's content type, or None: any type
    source_id: str | None  # the stream's source id, or None: any
    left: int | str  # the left hand's channel: an index from 0, or a channel label
    right: int | str
    scale: ForceScale
    resolve_timeout_s: float = 5.0
    source: str = ""
    kind: ClassVar[str] = "lsl"

    @property
    def simulated(self) -> bool:
        return False  # a stream is found by name wherever it is published

    def predicate(self) -> str:
        """The XPath predicate pylsl resolves the stream by."""
        return " and ".join(f"{k}='{getattr(self, k)}'" for k in STREAM_KEYS if getattr(self, k))

    def wanted(self) -> str:
        """The stream sought, in words: "named 'GripGlove' of type 'Grip'"."""
        words = {"name": "named {!r}", "type": "of type {!r}", "source_id": "with source id {!r}"}
        return " ".join(words[k].format(getattr(self, k)) for k in STREAM_KEYS if getattr(self, k))

    def describe(self) -> dict[str, Any]:
        return {
            "glove_kind": self.kind,
            "glove_stream": {k: getattr(self, k) for k in STREAM_KEYS if getattr(self, k)},
            "glove_channels": {"left": self.left, "right": self.right},
            **self.scale.describe(),
        }


def lsl_config(table: dict[str, Any], source: str) -> LslGripConfig:
    """A ``[glove]`` table of ``kind = "lsl"``, checked."""
    f = Fields(table, source, "glove", FIELDS)
    stream = {}
    for key in STREAM_KEYS:
        value = f.text(key, f"the stream's {key.replace('_', ' ')}, a non-empty string")
        if value is not None and "'" in value:
            raise f.fail(key, f"must not contain a single quote ('), got {value!r}")
        stream[key] = value
    if not (stream["name"] or stream["type"]):
        raise f.fail("name", "required: the stream's name or its type (or both)")
    scale = force_scale(f)
    timeout = f.positive("resolve_timeout_s", 5.0)
    channels = f.subtable("channels")
    assert channels is not None
    c = Fields(channels, source, "glove.channels", HANDS)
    hands: dict[str, int | str] = {}
    for hand in HANDS:
        value = c.required(hand, "the channel's index (from 0) or its label")
        if isinstance(value, bool) or not (
            (isinstance(value, int) and value >= 0) or (isinstance(value, str) and value)
        ):
            raise c.fail(
                hand, f"must be a channel index (a whole number ≥ 0) or a label, got {value!r}"
            )
        if hands and value == hands["left"]:
            raise c.fail(hand, f"{value!r} is already the left hand's channel")
        hands[hand] = value
    return LslGripConfig(
        stream["name"], stream["type"], stream["source_id"], hands["left"], hands["right"],
        scale, timeout, source,
    )  # fmt: skip


# -- the source -----------------------------------------------------------------------------------


@dataclass
class LslGripStats:
    samples: int = 0  # good samples
    bad_samples: int = 0  # skipped: a hand's channel not a finite number
    last_bad_reason: str | None = None
    rate_hz: float = 0.0  # good samples per host second, over the last rate window
    last_sample_age_s: float | None = None
    running: bool = False
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class LslGripSource(GripReader[float]):
    """An LSL inlet's grip, read by a thread of its own (build it with :func:`open_lsl`).
    The raw item kept with each reading is the sample's LSL timestamp (the sender's clock)."""

    thread_name = "grip-lsl-reader"

    def __init__(
        self,
        inlet: Any,
        info: Any,
        left: int,
        right: int,
        scale: ForceScale,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
        pull_timeout_s: float = 0.05,
        rate_window_s: float = 1.0,
    ) -> None:
        super().__init__(clock=clock, on_error=on_error, rate_window_s=rate_window_s)
        self._inlet = inlet
        self._name, self._type = info.name(), info.type()
        self._left, self._right = left, right
        self._scale = scale
        self._pull_timeout_s = pull_timeout_s
        self._stats = LslGripStats()

    def describe(self) -> str:
        kind = f" of type {self._type!r}" if self._type else ""
        return f"LSL stream {self._name!r}{kind}"

    def latest_device_time_s(self) -> float | None:
        """The newest sample's LSL timestamp (the sender's clock), or None."""
        newest = self._newest
        return None if newest is None else newest[0]

    def stats(self) -> LslGripStats:
        with self._lock:
            counts = replace(self._stats)
        return replace(counts, last_sample_age_s=self.age_s(), **self._common_stats())

    def _stop_detail(self) -> str:
        st = self.stats()
        if not st.bad_samples:
            return super()._stop_detail()
        return (
            f" from {self.describe()} ({st.bad_samples} bad samples so far; the last: "
            f"{st.last_bad_reason})"
        )

    def _release(self) -> None:
        inlet, self._inlet = self._inlet, None
        try:
            inlet.close_stream()
        finally:
            del inlet  # the only reference: liblsl destroys the inlet now

    def _read_once(self) -> None:
        # Block (up to the pull timeout) for one sample, then take whatever else is already
        # there, so a burst is handled in one go with one host timestamp. (A pull_chunk with a
        # timeout would wait out the whole timeout to fill its buffer: 50 ms late, in bursts.)
        sample, stamp = self._inlet.pull_sample(timeout=self._pull_timeout_s)
        if stamp is None:
            return
        chunk, stamps = self._inlet.pull_chunk(timeout=0.0, max_samples=_MAX_CHUNK)
        chunk, stamps = [sample, *chunk], [stamp, *stamps]
        now = self._clock()
        bad = None
        with self._lock:
            st = self._stats
            items = []
            for sample, stamp in zip(chunk, stamps, strict=True):
                left, right = sample[self._left], sample[self._right]
                if not (math.isfinite(left) and math.isfinite(right)):
                    st.bad_samples += 1
                    bad = st.last_bad_reason = (
                        f"channel {self._left} (left) = {left!r}, channel {self._right} "
                        f"(right) = {right!r}: not finite numbers"
                    )
                    continue
                st.samples += 1
                reading = GripReading(*self._scale.to_newtons(left, right), now, st.samples)
                items.append((stamp, reading))
            self._publish(items)
        n = self._stats.bad_samples
        if bad is not None and (n <= 3 or n % 1000 == 0):
            log.warning("%s: bad sample %d: %s", self.describe(), n, bad)


def open_lsl(config: LslGripConfig, **options: Any) -> LslGripSource:
    """Resolve the stream ``config`` names, open an inlet on it and start reading;
    :class:`GripSourceError` naming the stream when it cannot (none or several answer, a hand's
    channel is not in it, it does not answer)."""
    import pylsl
    from pylsl.util import LostError
    from pylsl.util import TimeoutError as LslTimeout

    where = f"({config.source}: [glove])" if config.source else ""
    found = pylsl.resolve_bypred(config.predicate(), 1, config.resolve_timeout_s)
    if found and config.source_id is None:
        # The first answer ends a resolve: listen a little longer for a second stream that
        # matches as well (two gloves of one type, a program started twice). A source id is
        # the stream's own: no need.
        found = pylsl.resolve_bypred(config.predicate(), 2, AMBIGUITY_WINDOW_S) or found
    if not found:
        raise GripSourceError(
            f"no LSL stream {config.wanted()} found within {config.resolve_timeout_s:g} s: is "
            f"the glove's program running and publishing it on this network? {where}"
        )
    if len(found) > 1:
        listing = "; ".join(
            f"{i.name()!r} of type {i.type()!r} on {i.hostname()} (source id {i.source_id()!r})"
            for i in found
        )
        raise GripSourceError(
            f"{len(found)} LSL streams {config.wanted()} answer ({listing}): give the one to "
            f"use by its source_id (or a name or type that only it has) {where}"
        )
    info = found[0]
    name = f"LSL stream {info.name()!r}"
    if info.channel_format() == pylsl.cf_string:
        raise GripSourceError(f"{name} sends text (channel format string), not numbers {where}")
    inlet = pylsl.StreamInlet(info, max_buflen=10, recover=True)
    try:
        try:
            full = inlet.info(timeout=config.resolve_timeout_s)
            left, right = (_channel(full, config, hand, name, where) for hand in HANDS)
            inlet.open_stream(timeout=config.resolve_timeout_s)
        except (LslTimeout, LostError) as e:
            raise GripSourceError(
                f"{name} was found but did not answer within {config.resolve_timeout_s:g} s "
                f"({type(e).__name__}) {where}"
            ) from None
        return LslGripSource(inlet, full, left, right, config.scale, **options).start()
    except BaseException:
        inlet.close_stream()
        raise


def _channel(info: Any, config: LslGripConfig, hand: str, name: str, where: str) -> int:
    """The index of ``hand``'s channel in the stream (its config gives an index or a label)."""
    wanted = getattr(config, hand)
    n = info.channel_count()
    if isinstance(wanted, int):
        if wanted >= n:
            raise GripSourceError(
                f"{name} has {n} channel{'s' if n != 1 else ''} (0..{n - 1}): "
                f"[glove.channels] {hand} = {wanted} is not one of them {where}"
            )
        return wanted
    labels = info.get_channel_labels() or []
    matches = [i for i, label in enumerate(labels) if label == wanted]
    if len(matches) != 1:
        have = ", ".join(repr(label) for label in labels if label) or "none"
        problem = "no channel" if not matches else f"{len(matches)} channels"
        raise GripSourceError(
            f"{name} has {problem} labelled {wanted!r} ([glove.channels] {hand}); its channel "
            f"labels: {have} {where}"
        )
    return matches[0]


# -- a simulated stream ---------------------------------------------------------------------------


class SimulatedLslGrip(PacedWriter):
    """Publishes ``grip(t)`` on an LSL outlet at ``rate_hz``: the stream ``config`` names, with a
    source id of its own (:attr:`address`), so that a host finds this one and no other
    simulated rig's. Channels by index sit at their index; channels by label get that label
    (the others are labelled ``ch<i>``, the hands by index ``left``/``right``)."""

    thread_name = "grip-lsl-sim"
    sim_name = "simulated LSL grip stream"
    #: fault names :meth:`inject` knows (a simulated lab's glove faults)
    faults = ("glove_hang_up", "glove_stop")
    DEFAULT_NAME = "SteerlabSimulatedGrip"
    DEFAULT_TYPE = "Grip"

    def __init__(
        self,
        grip: GripFunction,
        config: LslGripConfig,
        *,
        rate_hz: float = 100.0,
        source_id: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        super().__init__(host_period_s=1.0 / rate_hz, clock=clock, on_error=on_error)
        self._grip = grip
        self.config = config
        self._rate_hz = rate_hz
        self.source_id = source_id or f"steerlab-sim-{uuid.uuid4().hex[:12]}"
        self.name = config.name or self.DEFAULT_NAME
        self.type = config.type or self.DEFAULT_TYPE
        taken = [v for v in (config.left, config.right) if isinstance(v, int)]
        n = max(taken, default=-1) + 1
        self._positions = {}
        for hand in HANDS:
            want = getattr(config, hand)
            if isinstance(want, int):
                self._positions[hand] = want
            else:
                self._positions[hand] = n
                n += 1
        self._labels = [f"ch{i}" for i in range(max(n, 2))]
        for hand, position in self._positions.items():
            want = getattr(config, hand)
            self._labels[position] = want if isinstance(want, str) else hand
        self._outlet: Any = None
        self.samples_pushed = 0
        self.samples_skipped = 0  # not pushed: stopped streaming, hung up, or suspended

    @property
    def address(self) -> str:
        """Where the host finds the stream: its source id."""
        return self.source_id

    def start(self):
        if self._outlet is None and not self._closed and not self._hung_up.is_set():
            import pylsl

            info = pylsl.StreamInfo(
                self.name, self.type, len(self._labels), self._rate_hz, pylsl.cf_float32,
                self.source_id,
            )  # fmt: skip
            info.set_channel_labels(self._labels)
            info.set_channel_units(["N" if self.config.scale.unit == "N" else "raw"] * len(
                self._labels))  # fmt: skip
            self._outlet = pylsl.StreamOutlet(info)
        return super().start()

    def inject(self, fault: str) -> None:
        if fault == "glove_hang_up":
            self.hang_up()
        elif fault == "glove_stop":
            self.stop_streaming()
        else:
            raise ValueError(f"unknown glove fault {fault!r} (known: {', '.join(self.faults)})")

    def _emit(self, t: float) -> None:
        with self._lock:
            streaming = self._streaming
        outlet = self._outlet
        if not streaming or outlet is None:
            self.samples_skipped += 1
            return
        import numpy as np

        left, right = (float(np.float32(v)) for v in self.config.scale.from_newtons(*self._grip(t)))
        sample = np.zeros(len(self._labels), dtype=np.float32)
        sample[self._positions["left"]], sample[self._positions["right"]] = left, right
        outlet.push_sample(sample)
        self.samples_pushed += 1

    def _skip(self, n: int) -> None:
        self.samples_skipped += n

    def _hang_up_now(self) -> None:
        self._hung_up.set()
        self._outlet = None  # the only reference: liblsl destroys the outlet, the stream is gone

    def _release(self) -> None:
        self._outlet = None


class _LslKind:
    name = "lsl"

    def config(self, table: dict[str, Any], source: str) -> LslGripConfig:
        return lsl_config(table, source)

    def open(self, config: LslGripConfig) -> LslGripSource:
        return open_lsl(config)

    def simulate(self, config: LslGripConfig, grip: GripFunction) -> SimulatedLslGrip:
        return SimulatedLslGrip(grip, config)

    def at(self, config: LslGripConfig, address: str) -> LslGripConfig:
        return replace(config, source_id=address)


KIND = _LslKind()
