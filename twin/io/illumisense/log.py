"""ILLumiSense text logs: one record per line, as lab loggers save the stream (``twin replay``, ``replay://``).

Nobody publishes a log format; loggers write each record's payload (the text after the 4-byte length prefix)
as one line, so a line is read exactly as a payload (docs/protocols-illumisense.md): date, time, sample
number, channel blocks, optional sensor blocks, any line ending. All lines are tokenized in one pass.

- Lines end in LF, CR LF or CR alone, in any mixture; a UTF-8 byte-order mark before the first line is skipped.
  A last line without a line end was cut (the writer was stopped mid-line): it is left out, since its last
  number may be cut short (the reader reports the file as damaged).
- Lines before the first record that decodes (column names, comments, settings) are a header and skipped
  silently (at most ``max_header_lines``); a later line that does not decode is skipped and reported with its
  line number. A line that fails and holds a decimal comma is retried with commas read as points.
- The channel layout is decided by a consensus of the first records (:class:`LayoutConsensus`), so one odd
  first line does not throw away the rest: records of another layout are skipped and reported (a log is one
  file of one shape, so the layout is not re-learned).
- The sensor blocks are kept as the vendor's reconstruction, per sensor (:class:`VendorArrays`: curvature,
  angle, shape; the layout of the sensor's first block, rows absent for records without that block or with
  another G or N).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.frames import Frame
from twin.io.errors import FramingError
from twin.io.illumisense.codec import Record, decode_many, decode_record
from twin.io.illumisense.stream import LayoutConsensus
from twin.io.illumisense.vendor import VendorArrays

__all__ = ["LogContents", "VendorArrays", "read_log"]


@dataclass(frozen=True, eq=False)
class LogContents:
    """The frames of a log as arrays (n, …), the vendor's sensor blocks (one :class:`VendorArrays` per sensor,
    empty when the log has none), and what was skipped."""

    timestamps: np.ndarray
    sequences: np.ndarray
    wavelengths: np.ndarray
    powers: np.ndarray
    status: np.ndarray
    vendor: tuple[VendorArrays, ...]
    errors: list[str]
    odd_records: int


def read_log(path: str | Path, *, channels_as: str = "cores", n_cores: int | None = None,
             max_header_lines: int = 1000, quorum: int = 3, window: int = 5) -> LogContents:
    """Decode an ILLumiSense log file (module docstring).

    Raises
    ------
    ValueError
        When no line is a record (naming the file).
    """
    path = Path(path)
    data = path.read_bytes()
    # a UTF-8 byte-order mark (editors on Windows) is not part of the first line
    ends, starts, pos = [], [], 3 if data.startswith(b"\xef\xbb\xbf") else 0
    # lines end in LF, CR LF or CR alone (old tools), in any mixture (a header may end otherwise than the records)
    for line in data[pos:].splitlines(keepends=True):
        starts.append(pos)
        ends.append(pos + len(line.rstrip(b"\r\n")))
        pos += len(line)
    keep = [i for i, (a, b) in enumerate(zip(starts, ends, strict=True)) if data[a:b].strip()]
    if keep and keep[-1] == len(starts) - 1 and data[-1:] not in (b"\n", b"\r"):
        keep.pop()  # a last line without its line end was cut: its last number may be cut short (the reader says so)
    res = decode_many(data, [starts[i] for i in keep], [ends[i] for i in keep], channels_as=channels_as,
                      n_cores=n_cores)
    errors: list[str] = []
    decoded: list[tuple[int, Record]] = []
    header = 0
    for i, r in zip(keep, res, strict=True):
        line = data[starts[i] : ends[i]]
        if isinstance(r, FramingError) and b"," in line:
            try:
                r = decode_record(line.replace(b",", b"."), channels_as=channels_as, n_cores=n_cores)
            except FramingError:
                pass
        if isinstance(r, FramingError):
            if not decoded:
                header += 1
                if header > max_header_lines:
                    break
                continue
            errors.append(f"line {i + 1}: {r}")
            continue
        decoded.append((i + 1, r))
    consensus = LayoutConsensus(quorum, window, relearn=False)
    kept: list[Record] = []
    for _, r in decoded:
        kept += consensus.push(r)
    kept += consensus.finish()
    if not kept:
        raise ValueError(f"{path}: neither a twin HDF5 recording nor an ILLumiSense log (no line is a "
                         "TAB-separated record: date, time, sample, C, channel blocks…)")
    ids = {id(r) for r in kept}
    layout = kept[0].layout
    for no, r in decoded:
        if id(r) not in ids:
            errors.append(f"line {no}: channel layout {_describe(r.layout)} differs from the log's "
                          f"{_describe(layout)}")
    errors.sort(key=lambda e: int(e.split(":", 1)[0].split()[1]))
    frames = [r.frame for r in kept]
    n_sensors = max((len(r.sensors) for r in kept), default=0)
    vendor = tuple(VendorArrays.from_sensors([r.sensors[k] if len(r.sensors) > k else None for r in kept])
                   for k in range(n_sensors))
    batch = Frame.stack(frames)
    return LogContents(
        timestamps=batch.timestamp,
        sequences=batch.sequence,
        wavelengths=batch.wavelengths,
        powers=batch.powers,
        status=batch.status,
        vendor=vendor,
        errors=errors,
        odd_records=consensus.odd,
    )


def _describe(layout: tuple) -> str:
    gs = layout[1]
    return f"{len(gs)} channel(s) (G = {', '.join(map(str, gs))})"
