"""Compact per-finger contact summary for a real-time controller on CAN (docs/hand.md).

Pure encode/decode (struct + dataclasses, no python-can): the hand runtime encodes, a controller
or a test decodes with `decode_frame` / `SummaryDecoder`. Classic CAN frames, 8 data bytes each,
two frames per finger, all integers little-endian:

    id = id_base + 2*slot       "contact" frame
        byte 0      status bits (STATUS_BITS)
        byte 1      bits 7..4: contact count (saturates at 15); bits 3..0: rolling counter
        bytes 2-3   strongest contact x  int16, POSITION_SCALE_MM (0.01 mm) per LSB
        bytes 4-5   strongest contact y  int16, 0.01 mm
        bytes 6-7   strongest contact z  int16, 0.01 mm
    id = id_base + 2*slot + 1   "force" frame
        bytes 0-1   strongest contact Fx int16, FORCE_SCALE_N (0.001 N) per LSB
        bytes 2-3   strongest contact Fy int16, 0.001 N
        bytes 4-5   strongest contact Fz int16, 0.001 N
        bytes 6-7   |total force| of the finger  uint16, 0.001 N

Positions are the 3D centroid on the gel surface and forces the cluster's total force vector, both
in the sensor frame (docs/fields.md). "Strongest" = the contact with the largest |force|. A value
outside the integer range is clipped and the SATURATED bit is set. Both frames of one finger
carry the same counter nibble (frame 1 has it in no byte; pair them by arrival order per id).
"""
from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

POSITION_SCALE_MM = 0.01      # mm per LSB, int16 -> +-327.67 mm
FORCE_SCALE_N = 0.001         # N per LSB, int16 -> +-32.767 N, uint16 total -> 65.535 N
FRAMES_PER_FINGER = 2
MAX_COUNT = 15
STD_ID_MAX = 0x7FF
EXT_ID_MAX = 0x1FFFFFFF

STATUS_BITS = {
    "alive": 0,          # finger configured, camera delivering frames
    "contact": 1,        # at least one contact
    "camera_lost": 2,    # capture stalled or device gone
    "image_bad": 3,      # black or frozen frames
    "baseline": 4,       # no baseline yet (startup) - forces are zero, not measured
    "invalid": 5,        # a new calibration or model was rejected; running on the previous one
    "saturated": 6,      # a value was clipped to its integer range
    "stale": 7,          # no new frame within the stale timeout
}

_CONTACT = struct.Struct("<BBhhh")
_FORCE = struct.Struct("<hhhH")


@dataclass
class FingerSummary:
    """What the controller gets per finger. Units: mm, N."""
    count: int = 0
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    total_force_n: float = 0.0
    status: set[str] = field(default_factory=set)
    counter: int = 0

    def has(self, bit: str) -> bool:
        return bit in self.status


def summary_from_result(result, flags=()) -> FingerSummary:
    """A pipeline FrameResult (+ loop flags) -> FingerSummary of its strongest contact."""
    clusters = list(result.clusters)
    status = {"alive"}
    if clusters:
        status.add("contact")
    if result.fields is None:
        status.add("baseline")
    flags = set(flags) | set(result.flags)
    if flags & {"camera_stalled", "camera_lost"}:
        status.add("camera_lost")
    if flags & {"frame_black", "camera_frozen"}:
        status.add("image_bad")
    if flags & {"calibration_invalid", "model_invalid"}:
        status.add("invalid")
    total = float(sum(v * v for v in result.force_n) ** 0.5)
    if not clusters:
        return FingerSummary(0, status=status, total_force_n=total)
    best = max(clusters, key=lambda c: c.force_mag_n)
    return FingerSummary(len(clusters), tuple(map(float, best.position_mm)), tuple(map(float, best.force_n)),
                         total, status)


def _status_byte(status: set[str]) -> int:
    out = 0
    for name in status:
        if name not in STATUS_BITS:
            raise ValueError(f"CAN status bit {name!r}: expected one of {sorted(STATUS_BITS)}")
        out |= 1 << STATUS_BITS[name]
    return out


def _quant(value: float, scale: float, lo: int, hi: int) -> tuple[int, bool]:
    if value != value:          # NaN -> 0, flagged
        return 0, True
    q = round(value / scale)
    if q < lo or q > hi:
        return max(lo, min(hi, q)), True
    return int(q), False


def frame_ids(id_base: int, slot: int) -> tuple[int, int]:
    """(contact frame id, force frame id) of finger `slot`."""
    return id_base + FRAMES_PER_FINGER * slot, id_base + FRAMES_PER_FINGER * slot + 1


def check_id_range(id_base: int, n_slots: int, extended: bool = False) -> None:
    top = id_base + FRAMES_PER_FINGER * n_slots - 1
    limit = EXT_ID_MAX if extended else STD_ID_MAX
    if id_base < 0 or top > limit:
        raise ValueError(f"CAN id_base 0x{id_base:X} with {n_slots} finger slot(s) needs ids up to "
                         f"0x{top:X}, beyond the {'29' if extended else '11'}-bit limit 0x{limit:X}")


def encode_finger(s: FingerSummary, id_base: int, slot: int) -> list[tuple[int, bytes]]:
    """FingerSummary -> [(arbitration id, 8 data bytes), ...] (two frames)."""
    sat = False
    qs = []
    for v in s.position_mm:
        q, clipped = _quant(float(v), POSITION_SCALE_MM, -32768, 32767)
        qs.append(q)
        sat |= clipped
    fs = []
    for v in s.force_n:
        q, clipped = _quant(float(v), FORCE_SCALE_N, -32768, 32767)
        fs.append(q)
        sat |= clipped
    tot, clipped = _quant(abs(float(s.total_force_n)), FORCE_SCALE_N, 0, 65535)
    sat |= clipped
    status = set(s.status) | ({"saturated"} if sat or s.count > MAX_COUNT else set())
    count = min(max(int(s.count), 0), MAX_COUNT)
    nib = (count << 4) | (int(s.counter) & 0x0F)
    a, b = frame_ids(id_base, slot)
    return [(a, _CONTACT.pack(_status_byte(status), nib, *qs)), (b, _FORCE.pack(*fs, tot))]


def _status_set(byte: int) -> set[str]:
    return {name for name, bit in STATUS_BITS.items() if byte & (1 << bit)}


@dataclass
class SummaryDecoder:
    """Subscriber side: feed (id, data) frames, read `fingers[slot]` (a FingerSummary).

    A finger's summary is complete once its force frame arrives after its contact frame;
    `updated` counts complete summaries per slot. Frames outside the id range are ignored.
    """
    id_base: int
    n_slots: int
    fingers: dict[int, FingerSummary] = field(default_factory=dict)
    updated: dict[int, int] = field(default_factory=dict)
    _pending: dict[int, FingerSummary] = field(default_factory=dict)

    def feed(self, arbitration_id: int, data: bytes) -> int | None:
        """Returns the slot whose summary was just completed, else None."""
        rel = arbitration_id - self.id_base
        if rel < 0 or rel >= FRAMES_PER_FINGER * self.n_slots:
            return None
        slot, kind = divmod(rel, FRAMES_PER_FINGER)
        data = bytes(data)
        if len(data) != 8:
            raise ValueError(f"CAN id 0x{arbitration_id:X}: {len(data)} data bytes, expected 8")
        if kind == 0:
            st, nib, x, y, z = _CONTACT.unpack(data)
            self._pending[slot] = FingerSummary(nib >> 4, (x * POSITION_SCALE_MM, y * POSITION_SCALE_MM,
                                                           z * POSITION_SCALE_MM),
                                                status=_status_set(st), counter=nib & 0x0F)
            return None
        s = self._pending.pop(slot, None)
        if s is None:
            return None
        fx, fy, fz, tot = _FORCE.unpack(data)
        s.force_n = (fx * FORCE_SCALE_N, fy * FORCE_SCALE_N, fz * FORCE_SCALE_N)
        s.total_force_n = tot * FORCE_SCALE_N
        self.fingers[slot] = s
        self.updated[slot] = self.updated.get(slot, 0) + 1
        return slot


def decode_frames(frames, id_base: int, n_slots: int) -> dict[int, FingerSummary]:
    """[(id, data), ...] -> {slot: newest complete FingerSummary}."""
    dec = SummaryDecoder(id_base, n_slots)
    for arb, data in frames:
        dec.feed(arb, data)
    return dec.fingers
