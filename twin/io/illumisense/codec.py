"""FBGS ILLumiSense TCP data stream: record codec and batch decoder (docs/protocols-illumisense.md).

Wire format (ILLumiSense pushes one record per sample on TCP; the client sends nothing)::

    LEN (4 bytes, big-endian unsigned payload length) PAYLOAD
    PAYLOAD = date TAB time TAB sample TAB C
              { TAB ch TAB G TAB s1 TAB s2 TAB s3 TAB s4 {TAB λ}×G {TAB power}×G }×C       channel blocks
              { TAB "Curvature [1/cm]" {TAB κ}×G TAB "Curvature angle [rad]" {TAB φ}×G
                TAB "Shape x [cm]" TAB N {TAB x}×N TAB "Shape y [cm]" TAB N {TAB y}×N
                TAB "Shape z [cm]" TAB N {TAB z}×N }×S                                      sensor blocks
              [line ending: CR LF, LF or none]

This one module holds both directions — :func:`encode_record` for the simulator's server, :func:`decode_record`
and :func:`decode_many` for the stream decoder and the log reader — because they share the layout and its
decisions (the tokenizer lives in :mod:`twin.io.illumisense.scan`, the stream decoder in
:mod:`twin.io.illumisense.stream`, the log reader in :mod:`twin.io.illumisense.log`, the building of the
vendor's sensor blocks from our shapes in :mod:`twin.io.illumisense.vendor`).

Decoding (what is known and what is assumed: docs/protocols-illumisense.md):

- **Channel = core**, in record order (channel numbers, from 1, kept in :attr:`Record.channel_numbers`). With
  ``channels_as="single"`` one channel carries all gratings, core-major. Ragged channels are NaN-padded to the
  largest G and flagged MISSING; a padding beyond ``max_cells`` values is a :class:`FramingError`.
- **Missing peak**: wavelength 0 → NaN + MISSING, its power NaN (assumed: no public source shows a lost peak).
  Negative or non-finite wavelength → NaN + INVALID_VALUE. Any non-zero channel status → CHANNEL_ERROR.
- **Sensor blocks** follow the channel blocks, zero or more. The label text is the delimiter: a block starts at
  a field whose text begins ``Curvature`` (not ``Curvature angle``); its curvatures run to the next text field
  (so G needs no channel grouping), which must be the ``Curvature angle`` label, followed by as many angles;
  then ``Shape x``, N and N values, ``Shape y`` and ``Shape z`` with the same N. Units are read from the
  brackets (``1/cm``, ``1/m``, ``1/mm``; ``rad``, ``deg``; ``cm``, ``mm``, ``m``; the vendor's when absent)
  and converted to SI: :class:`VendorSensor` holds curvature in 1/m, angle in rad, positions in m (shape
  points 1 mm apart from the sensor's start, the vendor's frame: x along the fibre axis).
- **Engineering values**: a count E and E numbers after the channel blocks (an older ILLumiSense output that
  public clients also read) are kept in :attr:`Record.engineering`.
- Anything after that the decoder does not recognise is ignored and counted in :attr:`Record.extra_fields`.
- **Timestamp**: ``YYYY/MM/DD`` or ``YYYY-MM-DD`` and ``HH:MM:SS`` with or without a fraction, read as UTC; NaN
  when they are not a time (never an error).
- Integers are a sign and digits; except the sample number they have at most 15 digits.

Encoding (the simulator's choices): date ``YYYY/MM/DD``, time ``HH:MM:SS.ffffff`` UTC, wavelengths 4 decimals
(0.1 pm), powers 2 decimals, a lost peak as ``0`` ``0``, channels from 1, status ``1 0 0 0`` for a channel
with a CHANNEL_ERROR peak, sensor blocks with curvature 6 decimals (1/cm), angle 5 decimals (rad), shape 5
decimals (cm), line ending CR LF.

Speed: once a layout is known (the stream's steady state), its records are read in one compiled pass that
knows what each field must be and writes the Frame arrays directly
(:func:`twin.io.illumisense.scan.parse_layout`); it reads only what the general path would read with the same
values, and leaves every other record (damaged, of another layout, a number off the exact fast path) to it.
The general path tokenizes payloads in one compiled pass (:func:`twin.io.illumisense.scan.scan`); records whose
layout matches a known layout (same token count, counts, labels) are checked and extracted as one batch
(compiled: :func:`~twin.io.illumisense.scan.match_layout`, :func:`~twin.io.illumisense.scan.channels`); only
the others are walked field by field, which also builds the layout for the next ones. The batch stays a set
of arrays until a caller asks for Records (:func:`decode_many`) or frames; the stream decoder's
``feed_batch`` hands it over as one batch Frame.

Why one module of this size: the record layout is written once, for both directions (the simulator's server
encodes with it, the driver and the log reader decode), so that the two cannot drift apart.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np

from twin.frames import VENDOR_SHAPE_SPACING, Frame, PeakStatus, VendorArrays, VendorSensor
from twin.io.errors import FramingError, TruncatedFrameError
from twin.io.illumisense import scan as _scan
from twin.io.sequence import clamp

__all__ = [
    "ANGLE_LABEL",
    "CURVATURE_LABEL",
    "DEFAULT_MAX_PAYLOAD",
    "DEFAULT_PORT",
    "SHAPE_LABELS",
    "Record",
    "VendorSensor",
    "decode_many",
    "decode_payload",
    "decode_record",
    "encode_payload",
    "encode_record",
    "format_timestamp",
    "parse_timestamp",
]

PROTOCOL = "illumisense"
DEFAULT_PORT = 2055
DEFAULT_MAX_PAYLOAD = 1 << 20  #: 1 MiB: ~100× a 7-core × 18-grating record with its sensor block
MIN_PAYLOAD = 7  #: ``d TAB t TAB 0 TAB 0``: no channel, no line ending
_PREFIX_LIMIT = 1 << 24  # resync relies on the first prefix byte being NUL
_INT64 = 1 << 63
CURVATURE_LABEL = "Curvature [1/cm]"
ANGLE_LABEL = "Curvature angle [rad]"
SHAPE_LABELS = ("Shape x [cm]", "Shape y [cm]", "Shape z [cm]")
SHAPE_SPACING = VENDOR_SHAPE_SPACING  #: m between the vendor's shape points (the public client's assumption)

ChannelsAs = Literal["cores", "single"]

_EPOCH_ORDINAL = _dt.date(1970, 1, 1).toordinal()
_NAN_DATE, _NAN_TIME = "0000/00/00", "00:00:00"
_MISSING = np.uint8(PeakStatus.MISSING)
_CHANNEL_ERROR = np.uint8(PeakStatus.CHANNEL_ERROR)
_INVALID = np.uint8(PeakStatus.INVALID_VALUE)
_NUMBER_KINDS = (_scan.INT, _scan.DEC)
_UNITS = {
    "curvature": ({"1/cm": 100.0, "1/m": 1.0, "1/mm": 1000.0}, "1/cm"),
    "angle": ({"rad": 1.0, "deg": math.pi / 180.0}, "rad"),
    "shape": ({"cm": 0.01, "mm": 1e-3, "m": 1.0}, "cm"),
}


@dataclass(frozen=True, eq=False)
class Record:
    """One decoded ILLumiSense record: the :class:`~twin.frames.Frame` plus what the Frame has no room for.

    Attributes
    ----------
    frame : Frame
        Wavelengths (n_gratings, n_cores) nm (NaN where missing), powers, status, sequence = sample number,
        timestamp s (UTC epoch or NaN), ``vendor`` = :attr:`sensors` (None when the record has none).
    channel_numbers, grating_counts : ndarray of int64, shape (n_channels,)
        As sent, in record order.
    channel_status : ndarray of int64, shape (n_channels, 4)
        The four status integers of each channel (0 = OK).
    sensors : tuple of VendorSensor
        The sensor blocks, in record order.
    engineering : ndarray of float64, shape (E,)
        Engineering values when the record has an E block (empty otherwise).
    date, time : str
        The date and time fields as sent (Latin-1).
    extra_fields : int
        Fields after the last recognised block (ignored).
    layout : tuple
        The channel layout (channel numbers, grating counts): what :class:`LayoutConsensus` votes on.
    absent_sensors : int
        Sensor blocks left out of :attr:`sensors`: from the first block without gratings or shape points on
        (such a block carries no shape; a sensor's index keeps its meaning, as in :attr:`Frame.vendor`).
    """

    frame: Frame
    channel_numbers: np.ndarray
    grating_counts: np.ndarray
    channel_status: np.ndarray
    sensors: tuple[VendorSensor, ...]
    engineering: np.ndarray
    date: str
    time: str
    extra_fields: int = 0
    layout: tuple = ()
    absent_sensors: int = 0


# --------------------------------------------------------------------------------------------------- encode


def format_timestamp(timestamp: float, *, time_digits: int = 6, date_sep: str = "/") -> tuple[str, str]:
    """UTC date and time fields for an epoch timestamp.

    Parameters
    ----------
    timestamp : float
        Seconds since 1970-01-01 UTC; NaN or ±inf gives the placeholder ``0000/00/00`` ``00:00:00[.000000]``.
    time_digits : int
        Decimals of the seconds, 0–6 (0 writes ``HH:MM:SS`` as real streams may).
    date_sep : str
        ``"/"`` (the vendor's, default) or ``"-"``.

    Returns
    -------
    (date, time) : tuple of str
    """
    if not 0 <= time_digits <= 6:
        raise ValueError(f"time_digits: expected 0 to 6, got {time_digits}")
    if date_sep not in ("/", "-"):
        raise ValueError(f"date_sep: expected '/' or '-', got {date_sep!r}")
    frac_fmt = f".{{:0{time_digits}d}}" if time_digits else ""
    if not np.isfinite(timestamp):
        return _NAN_DATE.replace("/", date_sep), _NAN_TIME + (frac_fmt.format(0) if time_digits else "")
    scale = 10**time_digits
    units = round(float(timestamp) * scale)
    days, rem = divmod(units, 86400 * scale)
    secs, frac = divmod(rem, scale)
    try:
        date = _dt.date.fromordinal(_EPOCH_ORDINAL + days)
    except (ValueError, OverflowError) as exc:
        raise ValueError(f"timestamp {timestamp} s is outside the calendar (years 1 to 9999)") from exc
    h, rem = divmod(secs, 3600)
    m, s = divmod(rem, 60)
    time = f"{h:02d}:{m:02d}:{s:02d}" + (frac_fmt.format(frac) if time_digits else "")
    return f"{date.year:04d}{date_sep}{date.month:02d}{date_sep}{date.day:02d}", time


def _fmt(values, spec: str) -> list[str]:
    a = np.asarray(values, dtype=np.float64).ravel()
    f = ("{:" + spec + "}").format
    if np.isfinite(a).all():
        return list(map(f, a.tolist()))
    return [f(x) if math.isfinite(x) else "nan" for x in a.tolist()]


def encode_payload(
    frame: Frame,
    *,
    sensors: Sequence[VendorSensor] | None = None,
    strain: np.ndarray | None = None,
    channels_as: ChannelsAs = "cores",
    channel_status: np.ndarray | None = None,
    time_digits: int = 6,
    line_ending: bytes = b"\r\n",
) -> bytes:
    """The ASCII payload of one record (without the 4-byte length prefix).

    Parameters
    ----------
    frame : Frame
        Wavelengths nm (NaN, zero, negative or non-finite → a lost peak ``0``), powers (None → 0), sequence →
        sample number, timestamp s → UTC date/time.
    sensors : sequence of VendorSensor, optional
        Sensor blocks to append (curvature 1/m, angle rad, positions m; written in 1/cm, rad, cm).
    strain : ndarray, shape (n_gratings, n_cores), optional
        An engineering-value block (E = every grating, channel-major, µε with 1 decimal) — the older output;
        written before the sensor blocks. None (default) writes none.
    channels_as : {"cores", "single"}
    channel_status : ndarray of int, shape (n_channels, 4), optional
        By default ``1 0 0 0`` for a channel with any CHANNEL_ERROR peak, else zeros.
    time_digits : int
        Decimals of the time field (6 by default, 0 for ``HH:MM:SS``).
    line_ending : bytes
        ``b"\\r\\n"`` (default), ``b"\\n"`` or ``b""``.

    Returns
    -------
    bytes
    """
    if line_ending not in (b"\r\n", b"\n", b""):
        raise ValueError(f"line_ending: expected CR LF, LF or nothing, got {line_ending!r}")
    w = frame.wavelengths
    n_g, n_c = w.shape
    if channels_as == "cores":
        lam = w.T
    elif channels_as == "single":
        lam = w.T.reshape(1, n_g * n_c)
    else:
        raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
    n_ch, g = lam.shape
    present = np.isfinite(lam) & (lam > 0)
    pw = frame.powers.T.reshape(n_ch, g) if frame.powers is not None else np.zeros((n_ch, g))
    pw = np.where(np.isfinite(pw), pw, 0.0)
    if channel_status is None:
        cs = np.zeros((n_ch, 4), dtype=np.int64)
        if frame.status is not None:
            cs[:, 0] = ((frame.status.T.reshape(n_ch, g) & _CHANNEL_ERROR) != 0).any(axis=1)
    else:
        cs = np.asarray(channel_status, dtype=np.int64)
        if cs.shape != (n_ch, 4):
            raise ValueError(f"channel_status: expected shape ({n_ch}, 4), got {cs.shape}")
    date, time = format_timestamp(frame.timestamp, time_digits=time_digits)
    parts = [date, time, str(int(frame.sequence)), str(n_ch)]
    lost = np.flatnonzero(~present.ravel()).tolist()
    lam_txt = list(map("{:.4f}".format, np.where(present, lam, 0.0).ravel().tolist()))
    pw_txt = list(map("{:.2f}".format, pw.ravel().tolist()))
    for i in lost:
        lam_txt[i] = pw_txt[i] = "0"
    for k in range(n_ch):
        parts.append(f"{k + 1}\t{g}\t" + "\t".join(map(str, cs[k].tolist())))
        parts.extend(lam_txt[k * g : (k + 1) * g])
        parts.extend(pw_txt[k * g : (k + 1) * g])
    if strain is not None:
        eps = np.asarray(strain, dtype=np.float64)
        if eps.shape != (n_g, n_c):
            raise ValueError(f"strain: expected shape {(n_g, n_c)} like the wavelengths, got {eps.shape}")
        parts.append(str(eps.size))
        parts.extend(_fmt(eps.T, ".1f"))
    text = "\t".join(parts).encode("ascii")
    blocks = []
    for sensor in sensors or ():
        p = np.asarray(sensor.positions, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"sensor positions: expected shape (N, 3), got {p.shape}")
        k_ = np.asarray(sensor.curvature, dtype=np.float64).ravel()
        a_ = np.asarray(sensor.angle, dtype=np.float64).ravel()
        if k_.size != a_.size:
            raise ValueError(f"sensor: {k_.size} curvatures but {a_.size} angles")
        n_pts = str(p.shape[0]).encode()
        for label, body in ((CURVATURE_LABEL, _scan.format_fixed(k_ / 100.0, 6)),
                            (ANGLE_LABEL, _scan.format_fixed(a_, 5)),
                            *((SHAPE_LABELS[i], n_pts + (b"\t" if p.shape[0] else b"") +
                               _scan.format_fixed(p[:, i] * 100.0, 5)) for i in range(3))):
            blocks.append(label.encode() + (b"\t" + body if body else b""))
    if blocks:
        text += b"\t" + b"\t".join(blocks)
    return text + line_ending


def encode_record(frame: Frame, **kw) -> bytes:
    """One complete wire record: 4-byte big-endian payload length, then :func:`encode_payload` (same keywords)."""
    payload = encode_payload(frame, **kw)
    return len(payload).to_bytes(4, "big") + payload


# --------------------------------------------------------------------------------------------------- decode


def parse_timestamp(date: bytes, time: bytes) -> float:
    """Epoch seconds (UTC) from the date (``YYYY/MM/DD`` or ``YYYY-MM-DD``) and time (``HH:MM:SS[.f…]``)
    fields; NaN when they do not read as a time. Never raises."""
    try:
        if len(date) != 10 or date[4:5] not in (b"-", b"/") or date[7:8] != date[4:5]:
            return float("nan")
        y, mo, d = date[:4], date[5:7], date[8:10]
        if not (y + mo + d).isdigit():
            return float("nan")
        day = float((_dt.date(int(y), int(mo), int(d)).toordinal() - _EPOCH_ORDINAL) * 86400)
        h, m, s = time.split(b":")
        if len(h) != 2 or len(m) != 2 or not (h + m).isdigit() or len(s) < 2 or not s[:2].isdigit():
            return float("nan")
        if len(s) > 2 and (s[2:3] != b"." or not (s[3:].isdigit() or s[3:] == b"")):
            return float("nan")
        hh, mm, ss = int(h), int(m), float(s)
    except ValueError:
        return float("nan")
    if hh > 23 or mm > 59 or not ss < 61.0:
        return float("nan")
    return day + (hh * 3600 + mm * 60) + ss


def _label(text: bytes) -> tuple[str, float] | None:
    """(kind, scale to SI) of a block label, None when it is not one of the vendor's labels."""
    try:
        t = text.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    name, _, unit = t.partition("[")
    name = name.strip()
    kind = {"Curvature": "curvature", "Curvature angle": "angle", "Shape x": "x", "Shape y": "y",
            "Shape z": "z"}.get(name)
    if kind is None:
        return None
    table, default = _UNITS["shape" if kind in ("x", "y", "z") else kind]
    unit = unit.rstrip("]").strip() if unit else default
    scale = table.get(unit)
    return None if scale is None else (kind, scale)


@dataclass(frozen=True, eq=False)
class _Layout:
    """Where everything sits in the tokens of records of one layout (token indices; ``n`` = NaN padding)."""

    n: int
    key: tuple
    wl: np.ndarray  # (c, g_max)
    pw: np.ndarray
    status: np.ndarray  # (c, 4)
    ints: np.ndarray  # must be INT tokens
    fixed: np.ndarray  # must hold fixed_val
    fixed_val: np.ndarray
    numbers: np.ndarray  # must be numbers
    labels: np.ndarray  # must be these labels
    label_hash: np.ndarray
    sensors: tuple  # (curv (G,), angle (G,), xyz (N, 3), (k_scale, a_scale, p_scale))
    eng: np.ndarray | None
    extra: int
    single: int  # n_cores for channels_as="single", else 0

    @cached_property
    def roles(self) -> tuple[np.ndarray, np.ndarray] | None:
        """What each token must be, for :func:`~twin.io.illumisense.scan.parse_layout` (role, want); None when
        the layout's checks do not map one role to each token (then only the general path reads it)."""
        n = self.n
        role = np.full(n, _scan.ROLE_ANY, np.int8)
        want = np.zeros(n)
        role[self.numbers] = _scan.ROLE_NUMBER
        role[self.ints] = _scan.ROLE_INT
        if not np.isin(self.fixed, self.ints).all() or np.isin(self.labels, np.r_[self.ints, self.numbers]).any():
            return None
        role[self.fixed] = _scan.ROLE_FIXED
        want[self.fixed] = self.fixed_val
        role[self.labels] = _scan.ROLE_LABEL
        want[self.labels] = self.label_hash
        if self.extra or n < 2 or (role[2:] == _scan.ROLE_ANY).any():  # only the date and time are free text
            return None
        return role, want


class _Tokens:
    """The tokens of one payload (views into a :func:`scan` result), for the field-by-field walk."""

    def __init__(self, data: bytes, off: int, kind, value, ts, te):
        self.data, self.off, self.kind, self.value, self.ts, self.te = data, off, kind, value, ts, te
        self.n = kind.size

    def raw(self, j: int) -> bytes:
        return self.data[self.ts[j] : self.te[j]]

    def at(self, j: int) -> int:
        return int(self.ts[j] - self.off) if j < self.n else int(self.te[-1] - self.off) if self.n else 0

    def fail(self, j: int, what: str, expected: str, cls=FramingError):
        raise cls(what, offset=self.at(j), expected=expected, protocol=PROTOCOL)

    def int(self, j: int, name: str, lo: int = -_INT64, hi: int = _INT64 - 1) -> int:
        if j >= self.n:
            self.fail(j, f"record ends before {name}", "more fields", TruncatedFrameError)
        if self.kind[j] == _scan.INT:
            v = int(self.value[j])
        else:
            tok = self.raw(j)
            body = tok[1:] if tok[:1] in (b"+", b"-") else tok
            if not (body.isdigit() and body.isascii()) or j != 2:  # only the sample number may exceed 15 digits
                self.fail(j, f"{name} {tok[:20]!r} is not an integer", "a decimal integer")
            v = int(tok)
            if j == 2:  # a sample number beyond int64 is as absurd as it was, not a bad record (twin.io.sequence)
                v = clamp(v) if v >= 0 else v if v >= lo else -1  # below int64: unknown, as any negative
        if not lo <= v <= hi:
            self.fail(j, f"{name} {v} is out of range", f"{lo} to {hi}")
        return v

    def numbers(self, a: int, b: int) -> None:
        if b > self.n:
            self.fail(self.n, "record ends inside a block of numbers", "more fields", TruncatedFrameError)
        k = self.kind[a:b]
        bad = np.flatnonzero((k != _scan.INT) & (k != _scan.DEC))
        if bad.size:
            j = a + int(bad[0])
            self.fail(j, f"field {j} {self.raw(j)[:20]!r} is not a number", "a decimal number")


def _walk(t: _Tokens, channels_as: str, n_cores: int | None, max_cells: int) -> _Layout:
    """Read one record's structure field by field (FramingError naming the offset when it is not a record)."""
    n = t.n
    if n < 4:
        t.fail(n, f"record has {n} fields", "at least date, time, sample and C", TruncatedFrameError)
    t.int(2, "sample number")
    c = t.int(3, "channel count C", 0, (n - 4) // 6)
    pos, ints, fixed, fixed_val, nums = 4, [2, 3], [3], [c], []
    wl_at, gs, numbers_, status = [], [], [], []
    for k in range(c):
        numbers_.append(t.int(pos, f"channel {k} number"))
        g = t.int(pos + 1, f"channel {k} grating count G", 0, (n - pos - 6 - 6 * (c - k - 1)) // 2)
        for j in range(4):
            t.int(pos + 2 + j, f"channel {k} status {j + 1}")
        ints += list(range(pos, pos + 6))
        fixed += [pos, pos + 1]
        fixed_val += [numbers_[-1], g]
        status.append(list(range(pos + 2, pos + 6)))
        t.numbers(pos + 6, pos + 6 + 2 * g)
        nums += range(pos + 6, pos + 6 + 2 * g)
        wl_at.append(pos + 6)
        gs.append(g)
        pos += 6 + 2 * g
    g_max = max(gs, default=0)
    if channels_as == "single":
        if n_cores is None or n_cores < 1:
            raise ValueError("decode: channels_as='single' needs n_cores >= 1")
        if c != 1 or gs[0] % n_cores:
            t.fail(3, f"record has {c} channel(s) with G = {gs}", f"one channel with a multiple of {n_cores} gratings")
    if g_max * c > max_cells:
        t.fail(3, f"channel layout {c} channels × up to {g_max} gratings exceeds {max_cells} values",
               "fewer or less ragged channels")
    sensors, labels, label_hash, eng = [], [], [], None
    text = np.flatnonzero(t.kind == _scan.TEXT)
    while pos < n:
        if t.kind[pos] == _scan.TEXT:
            lab = _label(t.raw(pos))
            if lab is None or lab[0] != "curvature":
                break
            k_next = int(np.searchsorted(text, pos, side="right"))  # not text[text > pos]: quadratic in blocks
            q = int(text[k_next]) if k_next < text.size else n
            g_s = q - pos - 1
            t.numbers(pos + 1, q)
            lab2 = _label(t.raw(q)) if q < n else None
            if lab2 is None or lab2[0] != "angle":
                t.fail(q, "sensor block without its curvature angle label", f"{ANGLE_LABEL!r}")
            t.numbers(q + 1, q + 1 + g_s)
            blk = {"curv": np.arange(pos + 1, q), "angle": np.arange(q + 1, q + 1 + g_s)}
            labels += [pos, q]
            scales = [lab[1], lab2[1]]
            p, n_pts, xyz = q + 1 + g_s, None, []
            for axis in ("x", "y", "z"):
                la = _label(t.raw(p)) if p < n and t.kind[p] == _scan.TEXT else None
                if la is None or la[0] != axis:
                    t.fail(p, f"sensor block without its shape {axis} label", f"'Shape {axis} [cm]'")
                m = t.int(p + 1, f"shape {axis} point count N", 0, 1 << 40)
                if p + 2 + m > n:
                    t.fail(n, f"record ends inside shape {axis} ({m} points announced)", "more fields",
                           TruncatedFrameError)
                if n_pts is not None and m != n_pts:
                    t.fail(p + 1, f"shape {axis} has {m} points, shape x has {n_pts}", f"{n_pts}")
                n_pts = m
                t.numbers(p + 2, p + 2 + m)
                labels.append(p)
                ints.append(p + 1)
                fixed.append(p + 1)
                fixed_val.append(m)
                xyz.append(np.arange(p + 2, p + 2 + m))
                scales.append(la[1])
                p += 2 + m
            if len(set(scales[2:])) != 1:
                t.fail(p, "shape axes in different units", "one unit for x, y and z")
            nums += [*blk["curv"], *blk["angle"], *np.concatenate(xyz)]
            sensors.append((blk["curv"], blk["angle"], np.stack(xyz, axis=1), tuple(scales[:3])))
            pos = p
        elif t.kind[pos] == _scan.INT and eng is None and not sensors:
            e = int(t.value[pos])
            stop = pos + 1 + e
            if e < 0 or stop > n or not np.isin(t.kind[pos + 1 : stop], _NUMBER_KINDS).all():
                break
            ints.append(pos)
            fixed.append(pos)
            fixed_val.append(e)
            nums += range(pos + 1, stop)
            eng = np.arange(pos + 1, stop)
            pos = stop
        else:
            break
    for j in labels:
        label_hash.append(float(t.value[j]))
    wl = np.full((c, g_max), n, dtype=np.int64)
    pw = np.full((c, g_max), n, dtype=np.int64)
    for k, (a, g) in enumerate(zip(wl_at, gs, strict=True)):
        wl[k, :g] = np.arange(a, a + g)
        pw[k, :g] = np.arange(a + g, a + 2 * g)
    i64 = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return _Layout(
        n=n, key=(tuple(numbers_), tuple(gs)), wl=wl, pw=pw, status=i64(status).reshape(c, 4), ints=i64(ints),
        fixed=i64(fixed), fixed_val=np.asarray(fixed_val, np.float64), numbers=i64(nums), labels=i64(labels),
        label_hash=np.asarray(label_hash, np.float64), sensors=tuple(sensors), eng=eng, extra=n - pos,
        single=n_cores if channels_as == "single" else 0,
    )


def _matches(lay: _Layout, K: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Rows of (K, V) (tokens of records with ``lay.n`` tokens) that are records of this layout."""
    return _scan.match_layout(K, V, lay.ints, lay.fixed, lay.fixed_val, lay.numbers, lay.labels, lay.label_hash)


@dataclass(frozen=True, eq=False)
class _Group:
    """Records of one layout decoded as one batch: the arrays a Frame batch is made of, and what a
    :class:`Record` adds, built per record only when asked for (:meth:`record`, :meth:`frame`)."""

    lay: _Layout
    wavelengths: np.ndarray  # (m, n_gratings, n_cores) float64
    powers: np.ndarray  # (m, n_gratings, n_cores) float64
    status: np.ndarray  # (m, n_gratings, n_cores) uint8
    status4: np.ndarray  # (m, c, 4) int64
    sequence: np.ndarray  # (m,) int64
    timestamp: np.ndarray  # (m,) float64
    sensors: tuple  # ((m, G) 1/m, (m, G) rad, (m, N, 3) m) per sensor block
    engineering: np.ndarray | None  # (m, E)
    data: bytes
    dt_bounds: np.ndarray  # (m, 4): date start, date end, time start, time end in data

    @cached_property
    def usable_sensors(self) -> int:
        """Sensor blocks before the first without gratings or shape points (a block of the format, but no shape
        to compare with: absent, issue 23 B4); the later ones are absent too, so that indices keep their meaning."""
        return next((j for j, (k, _, p) in enumerate(self.sensors) if not (k.shape[1] and p.shape[1])),
                    len(self.sensors))

    def vendor(self, i: int) -> tuple:
        return tuple(VendorSensor(k[i], a[i], p[i]) for k, a, p in self.sensors[: self.usable_sensors])

    def frame(self, i: int, vendor: tuple | None = None) -> Frame:
        """The single Frame of row i (no validation: the arrays are built with the dtypes and shapes it needs)."""
        if vendor is None and self.sensors:
            vendor = self.vendor(i)
        return Frame._trusted(self.wavelengths[i], float(self.timestamp[i]), int(self.sequence[i]),
                              self.powers[i], self.status[i], vendor or None)

    def batch(self, i0: int, i1: int) -> Frame:
        """Rows i0:i1 as one batch Frame (views), the sensor blocks as :class:`VendorArrays` per sensor."""
        vendor = None
        if self.usable_sensors:
            present = np.ones(i1 - i0, bool)
            vendor = tuple(VendorArrays(k[i0:i1], a[i0:i1], p[i0:i1], present)
                           for k, a, p in self.sensors[: self.usable_sensors])
        return Frame._trusted(self.wavelengths[i0:i1], self.timestamp[i0:i1], self.sequence[i0:i1],
                              self.powers[i0:i1], self.status[i0:i1], vendor)

    @cached_property
    def _channels(self) -> tuple[np.ndarray, np.ndarray]:
        """Channel numbers and grating counts, shared by the group's records (built once, not per record)."""
        return np.array(self.lay.key[0], dtype=np.int64), np.array(self.lay.key[1], dtype=np.int64)

    def record(self, i: int) -> Record:
        lay = self.lay
        v = self.vendor(i)
        d0, d1, t0, t1 = self.dt_bounds[i].tolist()
        eng = self.engineering[i] if self.engineering is not None else np.zeros(0)
        return Record(self.frame(i, v), *self._channels, self.status4[i], v, eng, self.data[d0:d1].decode("latin-1"),
                      self.data[t0:t1].decode("latin-1"), lay.extra, lay.key,
                      len(self.sensors) - self.usable_sensors)


def _extract(lay: _Layout, V: np.ndarray, stamps: np.ndarray, data: bytes, dt_bounds: np.ndarray,
             *channels: np.ndarray, seq: np.ndarray | None = None) -> _Group:
    """Records of layout ``lay`` from their token values V (m, lay.n), as one batch (``channels``: the channel
    arrays when they are made already; ``seq``: the sample numbers, default token 2)."""
    lam, pw, st, status4 = channels or _scan.channels(V, lay.wl, lay.pw, lay.status, lay.single or lay.wl.shape[0],
                                                      _MISSING, _CHANNEL_ERROR, _INVALID)
    if seq is None:
        seq = V[:, 2].astype(np.int64)
    sens = tuple((V[:, curv] * ks, V[:, ang] * as_, V[:, xyz] * ps) for curv, ang, xyz, (ks, as_, ps) in lay.sensors)
    eng = V[:, lay.eng] if lay.eng is not None else None
    return _Group(lay, lam, pw, st, status4, np.asarray(seq, np.int64), np.asarray(stamps, np.float64), sens, eng,
                  data, dt_bounds)


def _decode_groups(data: bytes, starts, ends, *, channels_as: ChannelsAs = "cores", n_cores: int | None = None,
                   max_cells: int = 1 << 20, layouts: list | None = None
                   ) -> tuple[list, list[_Group], np.ndarray, np.ndarray]:
    """:func:`decode_many` without building a Record per record.

    Returns
    -------
    errors : list
        Per payload, the FramingError it raised, or None.
    groups : list of _Group
    gid, gidx : ndarray of int64 (n,)
        Payload i is row ``gidx[i]`` of ``groups[gid[i]]`` (−1 for an error). The rows of a group are in
        payload order.
    """
    if channels_as not in ("cores", "single"):
        raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
    starts = np.asarray(starts, dtype=np.int64)
    ends = np.asarray(ends, dtype=np.int64)
    n_rec = starts.size
    buf = np.frombuffer(data, np.uint8)
    layouts = [] if layouts is None else layouts
    single = n_cores if channels_as == "single" else 0
    # the common case first: the records of the layout the general path would try first, read in one pass
    ok = found = None
    lay = next((x for x in layouts if not x.extra and x.single == single), None)
    if n_rec and lay is not None and lay.roles is not None:
        ok, *arrays = _scan.parse_layout(buf, starts, ends, *lay.roles, lay.wl, lay.pw, lay.status,
                                         lay.single or lay.wl.shape[0], _MISSING, _CHANNEL_ERROR, _INVALID)
        n_ok = int(np.count_nonzero(ok))
        if n_ok == n_rec:  # all of them: one group, no other bookkeeping
            return [None] * n_rec, [_extract(lay, *arrays[:2], data, *arrays[2:])], np.zeros(n_rec, np.int64), \
                np.arange(n_rec)
        if n_ok:
            V, stamp, dtb, *chan = [a[ok] for a in arrays]
            found = _extract(lay, V, stamp, data, dtb, *chan)
    gid = np.full(n_rec, -1, np.int64)
    gidx = np.full(n_rec, -1, np.int64)
    errors: list = [None] * n_rec
    groups: list[_Group] = []

    def add(rows, grp):
        gid[rows] = len(groups)
        gidx[rows] = np.arange(rows.size)
        groups.append(grp)

    if found is not None:
        add(np.flatnonzero(ok), found)
    if n_rec:
        _decode_general(data, buf, starts, ends, None if ok is None else np.flatnonzero(~ok), channels_as, n_cores,
                        max_cells, layouts, errors, add)
    return errors, groups, gid, gidx


def _decode_general(data: bytes, buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, subset: np.ndarray | None,
                    channels_as: ChannelsAs, n_cores: int | None, max_cells: int, layouts: list, errors: list,
                    add) -> None:
    """The records ``subset`` (all when None) through the tokenizer: matched against the known layouts, the
    others walked field by field (which learns their layout). ``errors[i]`` is set for payload i that is not a
    record; ``add(rows, group)`` takes each decoded group (rows: payload indices)."""
    if subset is not None:
        starts, ends = starts[subset], ends[subset]
    n_rec = starts.size
    counts, kind, value, ts, te, stamp, bad, _ = _scan.scan(buf, starts, ends)
    for j in np.flatnonzero(kind == _scan.SLOW).tolist():
        try:
            value[j] = float(data[ts[j] : te[j]])
            kind[j] = _scan.DEC
        except ValueError:
            kind[j] = _scan.TEXT
            value[j] = 0.0
    for r in np.flatnonzero(stamp == _scan.TIME_SLOW).tolist():
        c0 = counts[r]
        stamp[r] = parse_timestamp(data[ts[c0] : te[c0]], data[ts[c0 + 1] : te[c0 + 1]])
    index = np.arange(n_rec) if subset is None else subset  # payload index of each record here
    ntok = np.diff(counts)
    todo = np.flatnonzero(bad < 0)
    for r in (np.flatnonzero(bad >= 0).tolist() if todo.size < n_rec else ()):
        errors[int(index[r])] = FramingError("NUL, CR or LF inside the record", offset=int(bad[r]),
                                             expected="one line of text", protocol=PROTOCOL)

    def dt_bounds(rows):
        c0 = counts[rows]
        return np.stack([ts[c0], te[c0], ts[c0 + 1], te[c0 + 1]], axis=1)

    single = n_cores if channels_as == "single" else 0
    while todo.size:
        done = np.zeros(todo.size, bool)
        for lay in layouts:
            if lay.extra or lay.single != single:
                continue
            sel = np.flatnonzero(~done & (ntok[todo] == lay.n))
            if not sel.size:
                continue
            rows = todo[sel]
            first = counts[rows[0]]
            if rows[-1] - rows[0] == rows.size - 1 and counts[rows[-1] + 1] - first == rows.size * lay.n:
                K = kind[first : first + rows.size * lay.n].reshape(rows.size, lay.n)  # consecutive: a view
                V = value[first : first + rows.size * lay.n].reshape(rows.size, lay.n)
            else:
                idx = counts[rows][:, None] + np.arange(lay.n)
                K, V = kind[idx], value[idx]
            ok = _matches(lay, K, V)
            if not ok.all():
                if not ok.any():
                    continue
                rows, V = rows[ok], V[ok]
            add(index[rows], _extract(lay, V, stamp[rows], data, dt_bounds(rows)))
            done[sel[ok]] = True
        rest = todo[~done]
        # the rest matched no known layout: walked one by one, until one teaches a new layout, which the records
        # after it are matched against first (matching the rest again after a bad line, with no new layout to
        # match, was numpy work over the whole block per bad line)
        todo = rest[:0]
        for k, r in enumerate(rest.tolist()):
            a, b = counts[r], counts[r + 1]
            tok = _Tokens(data, int(starts[r]), kind[a:b], value[a:b], ts[a:b], te[a:b])
            try:
                lay = _walk(tok, channels_as, n_cores, max_cells)
            except FramingError as exc:
                # without its traceback: the traceback's frames hold this list, so each kept error was a
                # reference cycle that only the cyclic collector frees (memory grew with the bad lines)
                errors[int(index[r])] = exc.with_traceback(None)
                continue
            new = not lay.extra and not any(
                x.n == lay.n and x.key == lay.key and np.array_equal(x.labels, lay.labels) for x in layouts)
            if new:
                layouts.insert(0, lay)
                del layouts[8:]
            rows = np.array([r])
            seq = np.array([tok.int(2, "sample number")], dtype=np.int64)
            add(index[rows], _extract(lay, value[a:b][None], stamp[rows], data, dt_bounds(rows), seq=seq))
            if new:
                todo = rest[k + 1 :]
                break


def decode_many(
    data: bytes,
    starts: Sequence[int] | np.ndarray,
    ends: Sequence[int] | np.ndarray,
    *,
    channels_as: ChannelsAs = "cores",
    n_cores: int | None = None,
    max_cells: int = 1 << 20,
    layouts: list | None = None,
) -> list[Record | FramingError]:
    """Decode many payloads ``data[starts[i]:ends[i]]`` at once.

    Parameters
    ----------
    data : bytes
    starts, ends : sequences of int
        Payload bounds (without the 4-byte length prefix).
    channels_as, n_cores, max_cells
        See :func:`decode_record`.
    layouts : list, optional
        A cache of layouts, kept between calls by the stream decoder (most recent first).

    Returns
    -------
    list of Record or FramingError
        One per payload, in order: the record, or the error that payload raised (offsets within the payload).
    """
    errors, groups, gid, gidx = _decode_groups(data, starts, ends, channels_as=channels_as, n_cores=n_cores,
                                               max_cells=max_cells, layouts=layouts)
    return [e if g < 0 else groups[g].record(i) for e, g, i in zip(errors, gid.tolist(), gidx.tolist(), strict=True)]


def decode_record(payload: bytes, *, channels_as: ChannelsAs = "cores", n_cores: int | None = None,
                  max_cells: int = 1 << 20) -> Record:
    """Decode one record payload (the bytes after the length prefix; any line ending or none).

    Parameters
    ----------
    payload : bytes
    channels_as : {"cores", "single"}
        "cores": channel k is core k. "single": one channel whose gratings are core-major (``n_cores`` needed).
    n_cores : int, optional
    max_cells : int
        Upper bound on n_gratings × n_cores (guards the NaN padding of ragged layouts).

    Raises
    ------
    FramingError
        For anything that is not a well-formed record, with the byte offset within ``payload``.
    """
    payload = bytes(payload)
    (res,) = decode_many(payload, [0], [len(payload)], channels_as=channels_as, n_cores=n_cores,
                         max_cells=max_cells)
    if isinstance(res, FramingError):
        raise res
    return res


def decode_payload(payload: bytes, **kw) -> Frame:
    """Decode one record payload to a :class:`~twin.frames.Frame` (keywords of :func:`decode_record`)."""
    return decode_record(payload, **kw).frame

