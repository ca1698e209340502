"""ILLumiSense text logs: one record per line, as lab loggers save the stream (``twin replay``, ``replay://``).

Nobody publishes a log format; loggers write each record's payload (the text after the 4-byte length prefix)
as one line, so a line is read exactly as a payload (docs/protocols-illumisense.md): date, time, sample
number, channel blocks, optional sensor blocks, any line ending. The lines are found in one compiled pass and
decoded a block of lines at a time into arrays (one batch per layout; no object per record), so what reading
takes beyond the file, its frames and the message naming each bad line after the first record is bounded by a
block, and a file of junk is refused after its header lines without the rest being decoded.

- Lines end in LF, CR LF or CR alone, in any mixture; a UTF-8 byte-order mark before the first line is skipped.
  A last line without a line end was cut (the writer was stopped mid-line): it is left out, since its last
  number may be cut short (the reader reports the file as damaged).
- Lines before the first record that decodes (column names, comments, settings) are a header and skipped
  silently (at most ``max_header_lines``); a later line that does not decode is skipped, counted
  (``skipped_lines``) and, for the first :data:`MAX_EXAMPLES`, reported with its line number: a file of a
  million bad lines keeps ten messages, not a million. A line that fails and holds a decimal comma is retried
  with commas read as points.
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
from typing import NamedTuple

import numpy as np

from twin.frames import VENDOR_SHAPE_SPACING, VendorArrays
from twin.io.illumisense import scan as _scan
from twin.io.illumisense.codec import _decode_groups
from twin.io.illumisense.stream import LayoutConsensus

__all__ = ["MAX_EXAMPLES", "LogContents", "VendorArrays", "read_log"]

#: skipped lines reported by message (the first, in line order); the others are only counted
MAX_EXAMPLES = 10


@dataclass(frozen=True, eq=False)
class LogContents:
    """The frames of a log as arrays (n, …), the vendor's sensor blocks (one :class:`VendorArrays` per sensor,
    empty when the log has none), and what was skipped: ``skipped_lines`` lines, the first :data:`MAX_EXAMPLES`
    of them named in ``errors`` (line number and reason, in line order)."""

    timestamps: np.ndarray
    sequences: np.ndarray
    wavelengths: np.ndarray
    powers: np.ndarray
    status: np.ndarray
    vendor: tuple[VendorArrays, ...]
    errors: list[str]
    odd_records: int
    skipped_lines: int


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
    starts, ends, number = _scan.lines(np.frombuffer(data, np.uint8), 3 if data.startswith(b"\xef\xbb\xbf") else 0)
    kw = {"channels_as": channels_as, "n_cores": n_cores}
    layouts: list = []  # the layouts learned, shared by the blocks (later blocks read on the one-pass path)
    groups: list = []
    errors: list[str] = []  # the first MAX_EXAMPLES lines that do not decode
    failed = 0  # all of them
    decoded: list[_Row] = []
    header = 0
    # decoded a block of lines at a time into arrays, one group per layout (no Frame per record): what a block
    # needs (tokens, a refusal per bad line) is bounded by the block, not by the file
    for b0 in range(0, starts.size, _BLOCK_LINES):
        s, e = starts[b0 : b0 + _BLOCK_LINES], ends[b0 : b0 + _BLOCK_LINES]
        res, more, gid, gidx = _decode_groups(data, s, e, layouts=layouts, **kw)
        gid = np.where(gid >= 0, gid + len(groups), gid)
        groups += more
        # lines that failed and hold a decimal comma: retried with commas read as points, all at once
        retry = [k for k in np.flatnonzero(gid < 0).tolist() if b"," in data[s[k] : e[k]]]
        if retry:
            lines = [data[s[k] : e[k]].replace(b",", b".") for k in retry]
            lens = np.array([len(x) for x in lines], np.int64)
            s2 = np.concatenate([[0], np.cumsum(lens + 1)[:-1]])
            _, more, gid2, gidx2 = _decode_groups(b"\n".join(lines), s2, s2 + lens, **kw)
            ok = gid2 >= 0
            gid[np.array(retry)[ok]] = gid2[ok] + len(groups)
            gidx[np.array(retry)[ok]] = gidx2[ok]
            groups += more
        for k, line in enumerate(number[b0 : b0 + _BLOCK_LINES].tolist()):
            if gid[k] < 0:
                if not decoded:
                    header += 1
                    if header > max_header_lines:
                        break
                    continue
                failed += 1
                if len(errors) < MAX_EXAMPLES:
                    errors.append(f"line {line}: {res[k]}")
                continue
            g = int(gid[k])
            decoded.append(_Row(groups[g].lay.key, line, g, int(gidx[k])))
        if header > max_header_lines:
            break
    consensus = LayoutConsensus(quorum, window, relearn=False)
    kept: list[_Row] = []
    for r in decoded:
        kept += consensus.push(r)
    kept += consensus.finish()
    if not kept:
        raise ValueError(f"{path}: neither a twin HDF5 recording nor an ILLumiSense log (no line is a "
                         "TAB-separated record: date, time, sample, C, channel blocks…)")
    lines_kept = {r.line for r in kept}
    layout = kept[0].layout
    odd = [r for r in decoded if r.line not in lines_kept]
    # the first examples of either kind, in line order (each list is in line order already)
    errors += [f"line {r.line}: channel layout {_describe(r.layout)} differs from the log's {_describe(layout)}"
               for r in odd[:MAX_EXAMPLES]]
    errors.sort(key=lambda e: int(e.split(":", 1)[0].split()[1]))
    kept.sort(key=lambda r: r.line)
    return _arrays(kept, groups, errors[:MAX_EXAMPLES], consensus.odd, failed + len(odd))


#: lines decoded at once: bounds the tokenizer's arrays and the block's refusals, whatever the file's size
_BLOCK_LINES = 1 << 12


class _Row(NamedTuple):
    """A decoded line: its layout (what :class:`LayoutConsensus` votes on), line number, group and row."""

    layout: tuple
    line: int
    group: int
    row: int


def _arrays(kept: list[_Row], groups: list, errors: list[str], odd: int, skipped: int) -> LogContents:
    """The kept rows, in line order, gathered from their groups' arrays."""
    g_of = np.array([r.group for r in kept])
    i_of = np.array([r.row for r in kept])
    n = len(kept)
    first = groups[kept[0].group]
    out = {name: np.empty((n, *getattr(first, name).shape[1:]), getattr(first, name).dtype)
           for name in ("wavelengths", "powers", "status", "timestamp", "sequence")}
    sensor_layouts: list[tuple] = []  # (G, N) of each sensor's first kept block
    for g in np.unique(g_of).tolist():
        at = np.flatnonzero(g_of == g)
        grp = groups[g]
        for name, arr in out.items():
            arr[at] = getattr(grp, name)[i_of[at]]
        for k, (curv, _, xyz) in enumerate(_usable(grp)):
            if k == len(sensor_layouts):
                sensor_layouts.append((curv.shape[1], xyz.shape[1]))
    # sensor k in the layout of its first block in line order; rows of another layout or without it absent
    vendor = []
    for k in range(len(sensor_layouts)):
        ref = next(_usable(groups[r.group])[k] for r in kept if len(_usable(groups[r.group])) > k)
        arrays = VendorArrays.absent(n, (ref[0].shape[1], ref[2].shape[1], VENDOR_SHAPE_SPACING))
        for g in np.unique(g_of).tolist():
            sens = _usable(groups[g])
            if len(sens) <= k or sens[k][0].shape[1] != ref[0].shape[1] or sens[k][2].shape[1] != ref[2].shape[1]:
                continue
            at = np.flatnonzero(g_of == g)
            curv, ang, xyz = sens[k]
            arrays.curvature[at], arrays.angle[at], arrays.positions[at] = curv[i_of[at]], ang[i_of[at]], xyz[i_of[at]]
            arrays.present[at] = True
        vendor.append(arrays)
    return LogContents(timestamps=out["timestamp"], sequences=out["sequence"], wavelengths=out["wavelengths"],
                       powers=out["powers"], status=out["status"], vendor=tuple(vendor), errors=errors,
                       odd_records=odd, skipped_lines=skipped)


def _usable(group) -> tuple:
    """A group's sensor blocks that carry a shape (the decoder's rule: blocks from the first without gratings or
    shape points on are absent)."""
    return group.sensors[: group.usable_sensors]


def _describe(layout: tuple) -> str:
    gs = layout[1]
    return f"{len(gs)} channel(s) (G = {', '.join(map(str, gs))})"
