"""FBGS ILLumiSense TCP data stream: record codec and incremental stream decoder (docs/protocols.md §1).

Wire format (what ILLumiSense pushes on TCP port 2055, one record per sample, the client sends nothing)::

    LEN (4 bytes, big-endian unsigned payload length) PAYLOAD
    PAYLOAD = date TAB time TAB sample TAB C { TAB ch TAB G TAB s1 TAB s2 TAB s3 TAB s4
              {TAB λ}×G {TAB power}×G }×C TAB E {TAB value}×E CR LF

This module holds both directions: :func:`encode_record` for the simulator's server and
:func:`decode_record` / :func:`decode_payload` / :class:`StreamDecoder` for the driver. All of them are pure
functions over bytes; sockets live elsewhere.

Decisions where docs/protocols.md is silent (the simulator makes one documented choice, the driver is
tolerant):

- **Channel = core**, in the order the channels appear in the record (not sorted by channel number; the
  numbers are kept in :attr:`Record.channel_numbers` for a driver that must remap). With
  ``channels_as="single"`` the record carries one channel whose G = n_gratings·n_cores gratings are ordered
  core-major (core 0's gratings first), as when the cores are spliced in series on one WDM channel.
- **Ragged channels** (channels with different G) are NaN-padded to the largest G, the padding flagged
  :attr:`PeakStatus.MISSING`; a layout so ragged that padding would exceed ``max_cells`` values is a
  :class:`FramingError` (it would otherwise let 1 MiB of text allocate gigabytes).
- **Missing peak**: wavelength 0 (any precision) → NaN + MISSING, its power NaN. A wavelength that parses but
  is negative or not finite (``nan``, ``inf``, ``1e999``) → NaN + INVALID_VALUE. A field that does not parse
  as a number is a :class:`FramingError` naming its byte offset; numeric fields may only contain
  ``0-9 . + - e E`` and the letters of ``nan``/``inf``/``infinity`` (Python's ``float`` would also take
  ``_`` and blanks, which a corrupted byte could turn into a silently different number).
- **Channel status**: any of the four status integers non-zero → CHANNEL_ERROR on all of the channel's peaks.
- **Timestamp**: date and time are opaque text. When they read as ``YYYY-MM-DD`` and ``HH:MM:SS[.f…]`` they
  are taken as **UTC** and converted to epoch seconds, otherwise the frame's timestamp is NaN (never an
  error). The simulator writes UTC; a NaN timestamp is written as ``0000-00-00`` ``00:00:00.000000``, which
  decodes back to NaN.
- **Engineering values** (E of them) are parsed and returned in :attr:`Record.engineering`; the simulator
  sends the optical strain of each grating in µε with one decimal, channel-major, ``nan`` where the peak is
  missing (both public clients parse that with ``std::stod`` / ``float``), or E = 0 when no strain is given.
- **Fields after the engineering values** are ignored (counted in :attr:`Record.extra_fields`): the vendor
  software can append further data, and both public clients stop reading after the engineering values.
- **Formatting** (simulator): wavelengths 4 decimals (0.1 pm), powers 2 decimals, engineering values 1
  decimal, a missing peak as the literal ``0`` for both wavelength and power, channels numbered from 1,
  status ``1 0 0 0`` for a core whose peaks carry CHANNEL_ERROR, else ``0 0 0 0``.

Stream resynchronisation (:class:`StreamDecoder`): TCP delivers the bytes in order, so framing is only lost
through a sender bug or a corrupted length. The payload is printable text that never contains a NUL byte or
an LF before its end, and the length prefix of any payload under 16 MiB starts with a NUL byte. After an error
the decoder therefore hunts: it skips to the next NUL byte, reads a candidate length, rejects it at once if
the length is out of bounds or if the bytes already received for that payload hold a NUL or an early LF, and
accepts it only when the whole payload ends in LF and decodes. Every error that takes the decoder out of sync
counts once in :attr:`StreamDecoder.framing_errors` (the candidates rejected while hunting do not), and the
skipped bytes are counted in :attr:`StreamDecoder.bytes_discarded`. A payload that has a sane length and ends
in LF but does not parse is skipped the same way (hunting resumes one byte after its prefix and lands on the
next prefix, since the payload holds no NUL). Reconnecting is therefore never required by the decoder; a
driver may still reconnect when errors persist.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from twin.frames import Frame, PeakStatus
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError
from twin.io.sequence import SequenceCounter

__all__ = [
    "DEFAULT_MAX_PAYLOAD",
    "DEFAULT_PORT",
    "Record",
    "StreamDecoder",
    "decode_payload",
    "decode_record",
    "encode_payload",
    "encode_record",
    "format_timestamp",
    "parse_timestamp",
]

PROTOCOL = "illumisense"
DEFAULT_PORT = 2055
DEFAULT_MAX_PAYLOAD = 1 << 20  #: 1 MiB: ~250× a 7-core × 18-grating record
#: Shortest conceivable payload: ``d TAB t TAB 0 TAB 0 TAB 0 LF`` (no channels, no engineering values).
MIN_PAYLOAD = 10
_PREFIX_LIMIT = 1 << 24  # resync relies on the first prefix byte being NUL
_INT64 = 1 << 63

ChannelsAs = Literal["cores", "single"]

# bytes a numeric field may contain (decimal numbers, exponent, nan/inf/infinity in any case)
_NUMERIC = b"0123456789.+-eEnNaAiIfFtTyY\t"
_EPOCH_ORDINAL = _dt.date(1970, 1, 1).toordinal()
_DAY_CACHE: dict[bytes, float] = {}
_NAN_DATE, _NAN_TIME = "0000-00-00", "00:00:00"
# numpy sees IntFlag members as int64; uint8 constants keep the in-place ORs on uint8 arrays legal
_MISSING = np.uint8(PeakStatus.MISSING)
_CHANNEL_ERROR = np.uint8(PeakStatus.CHANNEL_ERROR)
_INVALID = np.uint8(PeakStatus.INVALID_VALUE)


@dataclass(frozen=True, eq=False)
class Record:
    """One decoded ILLumiSense record: the :class:`~twin.frames.Frame` plus what the Frame has no room for.

    Attributes
    ----------
    frame : Frame
        Wavelengths (n_gratings, n_cores) nm with NaN where missing, powers, status, sequence = sample number,
        timestamp s (UTC epoch, NaN when the date/time fields are not ``YYYY-MM-DD`` / ``HH:MM:SS.f``).
    channel_numbers : ndarray of int64, shape (n_channels,)
        Channel numbers as sent, in record order (core ``k`` is the ``k``-th channel of the record).
    grating_counts : ndarray of int64, shape (n_channels,)
        G of each channel.
    channel_status : ndarray of int64, shape (n_channels, 4)
        The four status integers of each channel (0 = OK).
    engineering : ndarray of float64, shape (E,)
        The engineering values (strain in µε in the vendor software and in the simulator).
    date, time : str
        The opaque date and time fields (decoded as Latin-1, so any byte survives).
    extra_fields : int
        Number of fields after the engineering values (ignored).
    """

    frame: Frame
    channel_numbers: np.ndarray
    grating_counts: np.ndarray
    channel_status: np.ndarray
    engineering: np.ndarray
    date: str
    time: str
    extra_fields: int = 0


# --------------------------------------------------------------------------------------------------- encode


def format_timestamp(timestamp: float, *, time_digits: int = 6) -> tuple[str, str]:
    """UTC date and time fields for an epoch timestamp.

    Parameters
    ----------
    timestamp : float
        Seconds since 1970-01-01 UTC; NaN or ±inf gives the placeholder ``0000-00-00`` / ``00:00:00.000000``.
    time_digits : int
        Decimals of the seconds, 0–6 (the simulator writes 6, ``HH:MM:SS.ffffff``).

    Returns
    -------
    (date, time) : tuple of str
        ``YYYY-MM-DD`` and ``HH:MM:SS.f…``, the time rounded to ``10**-time_digits`` s.
    """
    if not 0 <= time_digits <= 6:
        raise ValueError(f"time_digits: expected 0 to 6, got {time_digits}")
    frac_fmt = f".{{:0{time_digits}d}}" if time_digits else ""
    if not np.isfinite(timestamp):
        return _NAN_DATE, _NAN_TIME + (frac_fmt.format(0) if time_digits else "")
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
    return date.isoformat(), time


def encode_payload(
    frame: Frame,
    *,
    strain: np.ndarray | None = None,
    channels_as: ChannelsAs = "cores",
    channel_status: np.ndarray | None = None,
    time_digits: int = 6,
) -> bytes:
    """The ASCII payload of one record (without the 4-byte length prefix), ending in CR LF.

    Parameters
    ----------
    frame : Frame
        Wavelengths nm (NaN, zero, negative or non-finite → sent as a missing peak ``0``), powers (None → 0),
        sequence → sample number, timestamp s → UTC date/time (see :func:`format_timestamp`).
    strain : ndarray, shape (n_gratings, n_cores), optional
        Engineering values, optical strain in µε (1 decimal, ``nan`` where not finite). None sends E = 0.
    channels_as : {"cores", "single"}
        "cores": one channel per core (channel k+1 = core k). "single": one channel carrying all gratings,
        core-major.
    channel_status : ndarray of int, shape (n_channels, 4), optional
        Status integers to send; by default ``1 0 0 0`` for a channel with any CHANNEL_ERROR peak, else zeros.
    time_digits : int
        Decimals of the time field (6 by default; 3 reproduces the example in docs/protocols.md).

    Returns
    -------
    bytes
        The payload; ASCII only.
    """
    w = frame.wavelengths
    n_g, n_c = w.shape
    if channels_as == "cores":
        lam = w.T  # (channels, gratings)
    elif channels_as == "single":
        lam = w.T.reshape(1, n_g * n_c)
    else:
        raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
    n_ch, g = lam.shape
    present = np.isfinite(lam) & (lam > 0)
    if frame.powers is not None:
        pw = frame.powers.T.reshape(n_ch, g)
    else:
        pw = np.zeros((n_ch, g))
    pw = np.where(np.isfinite(pw), pw, 0.0)
    if channel_status is None:
        cs = np.zeros((n_ch, 4), dtype=np.int64)
        if frame.status is not None:
            bad = (frame.status.T.reshape(n_ch, g) & _CHANNEL_ERROR) != 0
            cs[:, 0] = bad.any(axis=1)
    else:
        cs = np.asarray(channel_status, dtype=np.int64)
        if cs.shape != (n_ch, 4):
            raise ValueError(f"channel_status: expected shape ({n_ch}, 4), got {cs.shape}")

    date, time = format_timestamp(frame.timestamp, time_digits=time_digits)
    parts = [date, time, str(int(frame.sequence)), str(n_ch)]
    lam_txt = [
        f"{x:.4f}" if ok else "0"
        for x, ok in zip(lam.ravel().tolist(), present.ravel().tolist(), strict=True)
    ]
    pw_txt = [
        f"{x:.2f}" if ok else "0" for x, ok in zip(pw.ravel().tolist(), present.ravel().tolist(), strict=True)
    ]
    for k in range(n_ch):
        parts.append(f"{k + 1}\t{g}\t" + "\t".join(map(str, cs[k].tolist())))
        parts.extend(lam_txt[k * g : (k + 1) * g])
        parts.extend(pw_txt[k * g : (k + 1) * g])
    if strain is None:
        parts.append("0")
    else:
        eps = np.asarray(strain, dtype=np.float64)
        if eps.shape != (n_g, n_c):
            raise ValueError(f"strain: expected shape {(n_g, n_c)} like the wavelengths, got {eps.shape}")
        vals = eps.T.ravel().tolist()
        parts.append(str(len(vals)))
        parts.extend(f"{x:.1f}" if math.isfinite(x) else "nan" for x in vals)
    return ("\t".join(parts) + "\r\n").encode("ascii")


def encode_record(
    frame: Frame,
    *,
    strain: np.ndarray | None = None,
    channels_as: ChannelsAs = "cores",
    channel_status: np.ndarray | None = None,
    time_digits: int = 6,
) -> bytes:
    """One complete wire record: 4-byte big-endian payload length, then :func:`encode_payload`'s payload.

    Parameters are those of :func:`encode_payload`.

    Returns
    -------
    bytes
        ``len(payload).to_bytes(4, "big") + payload``.
    """
    payload = encode_payload(
        frame, strain=strain, channels_as=channels_as, channel_status=channel_status, time_digits=time_digits
    )
    return len(payload).to_bytes(4, "big") + payload


# --------------------------------------------------------------------------------------------------- decode


def parse_timestamp(date: bytes, time: bytes) -> float:
    """Epoch seconds (UTC) from the opaque date and time fields, NaN when they do not read as a time.

    Parameters
    ----------
    date : bytes
        ``YYYY-MM-DD``.
    time : bytes
        ``HH:MM:SS`` with any number of decimals.

    Returns
    -------
    float
        Seconds since 1970-01-01 UTC, or NaN. Never raises for any input.
    """
    day = _DAY_CACHE.get(date)
    if day is None:
        try:
            y, mo, d = date.split(b"-")
            if len(y) != 4 or len(mo) != 2 or len(d) != 2 or not (y + mo + d).isdigit():
                return float("nan")
            day = float((_dt.date(int(y), int(mo), int(d)).toordinal() - _EPOCH_ORDINAL) * 86400)
        except ValueError:
            return float("nan")
        if len(_DAY_CACHE) > 256:  # a long run crosses few dates; garbage must not grow the cache forever
            _DAY_CACHE.clear()
        _DAY_CACHE[date] = day
    try:
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


def _offset(fields: list[bytes], k: int, base: int = 0) -> int:
    """Byte offset of field ``k`` in the TAB-joined ``fields`` (error path only)."""
    return base + sum(len(f) for f in fields[:k]) + k


def _int_field(fields: list[bytes], k: int, name: str, lo: int = -_INT64, hi: int = _INT64 - 1) -> int:
    tok = fields[k]
    try:
        v = int(tok)
    except ValueError:
        v = None
    if v is None or not tok.lstrip(b"+-").isdigit():
        raise FramingError(
            f"{name} {tok[:20]!r} is not an integer",
            offset=_offset(fields, k),
            expected="a decimal integer",
            protocol=PROTOCOL,
        )
    if not lo <= v <= hi:
        raise FramingError(
            f"{name} {v} is out of range",
            offset=_offset(fields, k),
            expected=f"{lo} to {hi}",
            protocol=PROTOCOL,
        )
    return v


def _numbers(fields: list[bytes], start: int, stop: int) -> np.ndarray:
    """Fields ``start:stop`` as float64 in one conversion; FramingError naming the first bad field."""
    chunk = fields[start:stop]
    joined = b"\t".join(chunk)
    if joined.translate(None, _NUMERIC) or b"\t\t" in joined:
        bad = next(i for i, f in enumerate(chunk) if not f or f.translate(None, _NUMERIC))
        tok = chunk[bad]
        raise FramingError(
            f"field {start + bad} {tok[:20]!r} is not a number",
            offset=_offset(fields, start + bad),
            expected="a decimal number",
            protocol=PROTOCOL,
        )
    try:
        return np.array(chunk, dtype=np.float64)
    except ValueError:
        for i, f in enumerate(chunk):
            try:
                float(f)
            except ValueError:
                raise FramingError(
                    f"field {start + i} {f[:20]!r} is not a number",
                    offset=_offset(fields, start + i),
                    expected="a decimal number",
                    protocol=PROTOCOL,
                ) from None
        raise  # unreachable: numpy and float() agree on what parses


def decode_record(
    payload: bytes,
    *,
    channels_as: ChannelsAs = "cores",
    n_cores: int | None = None,
    max_cells: int = 1 << 20,
) -> Record:
    """Decode one record payload (the bytes after the length prefix).

    Parameters
    ----------
    payload : bytes
        ASCII fields separated by TAB, ending in CR LF or a bare LF, optionally with one TAB before it.
    channels_as : {"cores", "single"}
        "cores": channel k is core k (ragged channels NaN-padded to the largest G). "single": exactly one
        channel whose gratings are core-major; ``n_cores`` must then be given and divide G.
    n_cores : int, optional
        Number of cores for ``channels_as="single"``.
    max_cells : int
        Upper bound on n_gratings × n_cores of the decoded frame (guards the NaN padding of ragged layouts).

    Returns
    -------
    Record

    Raises
    ------
    FramingError
        For anything that is not a well-formed record, with the byte offset within ``payload``.
    """
    if channels_as not in ("cores", "single"):
        raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
    body = bytes(payload)
    if not body.endswith(b"\n"):
        raise TruncatedFrameError(
            "record does not end with LF", offset=len(body), expected="CR LF", protocol=PROTOCOL
        )
    body = body[:-2] if body.endswith(b"\r\n") else body[:-1]
    if body.endswith(b"\t"):
        body = body[:-1]
    if b"\n" in body or b"\x00" in body:
        k = min(i for i in (body.find(b"\n"), body.find(b"\x00")) if i >= 0)
        raise FramingError(
            "LF or NUL byte inside the record",
            offset=k,
            expected="one record ending in LF",
            protocol=PROTOCOL,
        )
    fields = body.split(b"\t")
    n = len(fields)
    if n < 5:
        raise TruncatedFrameError(
            f"record has {n} fields",
            offset=len(body),
            expected="at least date, time, sample, C and E",
            protocol=PROTOCOL,
        )
    seq = _int_field(fields, 2, "sample number")
    c = _int_field(fields, 3, "channel count C", 0, (n - 5) // 6)
    pos = 4
    wl_at: list[int] = []
    gs: list[int] = []
    numbers: list[int] = []
    status: list[list[int]] = []
    for k in range(c):
        # each channel needs its 6 header fields, its 2G values, and room for E after the last channel;
        # c <= (n - 5) // 6 and this bound on G keep every index below in range
        numbers.append(_int_field(fields, pos, f"channel {k} number"))
        room = (n - pos - 6 - 1 - 6 * (c - k - 1)) // 2
        gk = _int_field(fields, pos + 1, f"channel {k} grating count G", 0, room)
        status.append([_int_field(fields, pos + 2 + j, f"channel {k} status {j + 1}") for j in range(4)])
        wl_at.append(pos + 6)
        gs.append(gk)
        pos += 6 + 2 * gk
    e = _int_field(fields, pos, "engineering value count E", 0, n - pos - 1)
    end = pos + 1 + e
    nums = _numbers(fields, 4, end)  # index i of fields is nums[i - 4]

    status4 = np.array(status, dtype=np.int64).reshape(c, 4)
    g_max = max(gs, default=0)
    if channels_as == "single":
        if n_cores is None or n_cores < 1:
            raise ValueError("decode_record: channels_as='single' needs n_cores >= 1")
        if c != 1 or gs[0] % n_cores:
            raise FramingError(
                f"record has {c} channel(s) with G = {gs}",
                offset=_offset(fields, 3),
                expected=f"one channel with a multiple of {n_cores} gratings",
                protocol=PROTOCOL,
            )
    if g_max * c > max_cells:
        raise FramingError(
            f"channel layout {c} channels × up to {g_max} gratings exceeds {max_cells} values",
            offset=_offset(fields, 3),
            expected="fewer or less ragged channels",
            protocol=PROTOCOL,
        )

    lam = np.full((c, g_max), np.nan)
    pw = np.full((c, g_max), np.nan)
    st = np.zeros((c, g_max), dtype=np.uint8)
    for k, (a, gk) in enumerate(zip(wl_at, gs, strict=True)):
        i = a - 4
        lam[k, :gk] = nums[i : i + gk]
        pw[k, :gk] = nums[i + gk : i + 2 * gk]
        st[k, gk:] = _MISSING  # NaN padding of a channel shorter than the longest
    padded = st != 0
    st[np.any(status4 != 0, axis=1)] |= _CHANNEL_ERROR
    zero = lam == 0.0
    invalid = ~(np.isfinite(lam) & (lam > 0)) & ~zero & ~padded
    st[zero] |= _MISSING
    st[invalid] |= _INVALID
    lam[zero | invalid] = np.nan
    pw[zero] = np.nan

    if channels_as == "single":
        lam = lam.reshape(n_cores, -1)
        pw = pw.reshape(n_cores, -1)
        st = st.reshape(n_cores, -1)
    frame = Frame(
        wavelengths=np.ascontiguousarray(lam.T),
        timestamp=parse_timestamp(fields[0], fields[1]),
        sequence=seq,
        powers=np.ascontiguousarray(pw.T),
        status=np.ascontiguousarray(st.T),
    )
    return Record(
        frame=frame,
        channel_numbers=np.array(numbers, dtype=np.int64),
        grating_counts=np.array(gs, dtype=np.int64),
        channel_status=status4,
        engineering=nums[end - 4 - e : end - 4].copy(),
        date=fields[0].decode("latin-1"),
        time=fields[1].decode("latin-1"),
        extra_fields=n - end,
    )


def decode_payload(
    payload: bytes,
    *,
    channels_as: ChannelsAs = "cores",
    n_cores: int | None = None,
    max_cells: int = 1 << 20,
) -> Frame:
    """Decode one record payload to a :class:`~twin.frames.Frame` (see :func:`decode_record`).

    Raises
    ------
    FramingError
        For anything that is not a well-formed record.
    """
    return decode_record(payload, channels_as=channels_as, n_cores=n_cores, max_cells=max_cells).frame


# --------------------------------------------------------------------------------------------------- stream


class StreamDecoder:
    """Incremental decoder of the ILLumiSense TCP byte stream: feed it whatever ``recv`` returned.

    Handles arbitrary chunking (a record split anywhere, many records per chunk), refuses a length prefix
    above ``max_payload`` as soon as the 4 prefix bytes are in (nothing is allocated from a length), never
    raises for bad bytes, counts framing errors and resynchronises (strategy in the module docstring).

    Parameters
    ----------
    max_payload : int
        Largest accepted payload, bytes (default 1 MiB; at most 16 MiB − 1 so every prefix starts with NUL).
    channels_as, n_cores, max_cells
        Passed to :func:`decode_record`.
    keep_errors : int
        How many of the most recent errors :attr:`errors` keeps.

    Attributes
    ----------
    records : int
        Records decoded.
    framing_errors : int
        Times the stream was found out of framing (a bad prefix, a payload that does not end in LF or does
        not decode, bytes left over at :meth:`finish`).
    bytes_discarded : int
        Bytes skipped while resynchronising.
    sequence : SequenceCounter
        Gaps, lost samples and resets of the records' sample numbers.
    last_error : FramingError or None
        The most recent error (offsets count bytes since the decoder was created).
    errors : collections.deque of FramingError
        The most recent ``keep_errors`` errors.
    """

    def __init__(
        self,
        *,
        max_payload: int = DEFAULT_MAX_PAYLOAD,
        channels_as: ChannelsAs = "cores",
        n_cores: int | None = None,
        max_cells: int = 1 << 20,
        keep_errors: int = 16,
    ) -> None:
        if not MIN_PAYLOAD <= max_payload < _PREFIX_LIMIT:
            raise ValueError(
                f"max_payload: expected {MIN_PAYLOAD} to {_PREFIX_LIMIT - 1} bytes, got {max_payload}"
            )
        if channels_as not in ("cores", "single"):
            raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
        if channels_as == "single" and (n_cores is None or n_cores < 1):
            raise ValueError("StreamDecoder: channels_as='single' needs n_cores >= 1")
        self.max_payload = max_payload
        self._decode_kw = {"channels_as": channels_as, "n_cores": n_cores, "max_cells": max_cells}
        self._buf = bytearray()
        self._pos = 0  # start of the current candidate record in _buf
        self._base = 0  # stream offset of _buf[0]
        self._hunting = False
        self._scanned = 0  # payload bytes of the current candidate already checked for NUL / early LF
        self.sequence = SequenceCounter()
        self.records = 0
        self.framing_errors = 0
        self.bytes_discarded = 0
        self.last_error: FramingError | None = None
        self.errors: deque[FramingError] = deque(maxlen=keep_errors)

    @property
    def pending(self) -> int:
        """Bytes received but not yet consumed (part of a record, or bytes being hunted through)."""
        return len(self._buf) - self._pos

    @property
    def in_sync(self) -> bool:
        """False between a framing error and the next good record."""
        return not self._hunting

    def feed(self, data: bytes) -> list[Frame]:
        """Consume bytes; return the frames of every record completed by them, in order."""
        return [r.frame for r in self.feed_records(data)]

    def feed_records(self, data: bytes) -> list[Record]:
        """Like :meth:`feed`, returning the full :class:`Record` of each completed record."""
        buf = self._buf
        buf += data
        out: list[Record] = []
        while True:
            p = self._pos
            if self._hunting:
                q = buf.find(b"\x00", p)
                if q < 0:
                    self.bytes_discarded += len(buf) - p
                    self._pos = len(buf)
                    break
                self.bytes_discarded += q - p
                self._pos = p = q
            if len(buf) - p < 4:
                break
            length = int.from_bytes(buf[p : p + 4], "big")
            if length > self.max_payload:
                self._fail(
                    p,
                    OversizeFrameError(
                        f"length prefix {length} exceeds the {self.max_payload}-byte bound",
                        offset=self._base + p,
                        expected=f"at most {self.max_payload}",
                        protocol=PROTOCOL,
                    ),
                )
                continue
            if length < MIN_PAYLOAD:
                self._fail(
                    p,
                    FramingError(
                        f"length prefix {length} is shorter than any record",
                        offset=self._base + p,
                        expected=f"at least {MIN_PAYLOAD}",
                        protocol=PROTOCOL,
                    ),
                )
                continue
            end = p + 4 + length
            lo = p + 4 + self._scanned
            hi = min(end - 1, len(buf))  # the last payload byte is the LF
            if hi > lo:
                bad = [i for i in (buf.find(b"\x00", lo, hi), buf.find(b"\n", lo, hi)) if i >= 0]
                if bad:
                    self._fail(
                        p,
                        FramingError(
                            "NUL or LF inside a payload",
                            offset=self._base + min(bad),
                            expected=f"a {length}-byte payload ending in LF",
                            protocol=PROTOCOL,
                        ),
                    )
                    continue
                self._scanned = hi - p - 4
            if len(buf) < end:
                break
            if buf[end - 1] != 0x0A:
                self._fail(
                    p,
                    FramingError(
                        "payload does not end with LF",
                        offset=self._base + end - 1,
                        expected="CR LF at the length the prefix gives",
                        protocol=PROTOCOL,
                    ),
                )
                continue
            try:
                rec = decode_record(bytes(buf[p + 4 : end]), **self._decode_kw)
            except FramingError as exc:
                off = None if exc.offset is None else self._base + p + 4 + exc.offset
                self._fail(p, type(exc)(exc.what, offset=off, expected=exc.expected, protocol=PROTOCOL))
                continue
            self._pos = end
            self._scanned = 0
            self._hunting = False
            self.sequence.count(rec.frame.sequence)
            self.records += 1
            out.append(rec)
        if self._pos > 65536 and self._pos * 2 > len(buf):  # amortised O(n): drop consumed bytes now and then
            del buf[: self._pos]
            self._base += self._pos
            self._pos = 0
        return out

    def finish(self) -> None:
        """Declare the end of the stream (connection closed): an incomplete record left over is an error."""
        left = self.pending
        if left and not self._hunting:
            self._fail(
                self._pos,
                TruncatedFrameError(
                    f"stream ended inside a record ({left} bytes pending)",
                    offset=self._base + len(self._buf),
                    expected="a complete record",
                    protocol=PROTOCOL,
                ),
            )
        self.bytes_discarded += self.pending
        self._base += len(self._buf)
        self._buf.clear()
        self._pos = 0
        self._scanned = 0
        self._hunting = False

    def _fail(self, p: int, err: FramingError) -> None:
        if not self._hunting:
            self.framing_errors += 1
            self.last_error = err
            self.errors.append(err)
            self._hunting = True
        self._pos = p + 1
        self._scanned = 0
        self.bytes_discarded += 1

