"""The ILLumiSense byte stream: :class:`StreamDecoder` (framing, resynchronisation, batch decoding) and
:class:`LayoutConsensus` (the channel layout decided by a consensus of records, issue 11.6). Both are also
importable from :mod:`twin.io.illumisense`; records are decoded by :mod:`twin.io.illumisense.codec`.

Framing: the payload is printable text with no NUL and no LF before its end, and the length prefix of any payload
under 16 MiB starts with a NUL byte. After an error the decoder hunts: it skips to the next NUL byte that could
start a record (one compiled pass, :func:`~twin.io.illumisense.scan.hunt`, so a flood of NUL bytes costs no Python
step a byte), reads a candidate length, rejects it at once when it is out of bounds or when the bytes already
received for it hold a NUL or an early LF, and accepts it only when the payload decodes. In sync, a record still
waiting for the rest of its payload is checked the same way as its bytes arrive, so a corrupted prefix that is still
in bounds does not make the decoder wait for bytes the later prefixes prove wrong. Every loss of sync counts once in
:attr:`StreamDecoder.framing_errors`; skipped bytes in ``bytes_discarded``. The channel layout is learned from a
consensus (:class:`LayoutConsensus`), not from the first record alone: records of another layout are counted in
``odd_records`` and dropped, and a new layout that persists is re-learned.
"""

from __future__ import annotations

from collections import Counter, deque
from itertools import pairwise

import numpy as np

from twin.frames import Frame
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError
from twin.io.illumisense import scan as _scan
from twin.io.illumisense.codec import (
    _PREFIX_LIMIT,
    DEFAULT_MAX_PAYLOAD,
    MIN_PAYLOAD,
    PROTOCOL,
    ChannelsAs,
    Record,
    _decode_groups,
)
from twin.io.sequence import SequenceCounter

__all__ = ["LayoutConsensus", "StreamDecoder"]


# --------------------------------------------------------------------------------------------------- layout


class LayoutConsensus:
    """Decides the channel layout from a consensus of records, not from the first one alone (issue 11.6).

    Until a layout is known, records are held; the first layout seen ``quorum`` times among the first
    ``window`` records wins (or, after ``window`` records, the most frequent, ties to the latest). Held
    records of other layouts are counted in :attr:`odd` and dropped. Once known, a record of another layout is
    held in a run; a run of ``window`` consecutive records of one new layout re-learns it (:attr:`changes`),
    a run interrupted by the known layout is counted odd. ``quorum=0`` passes every record through.

    Parameters
    ----------
    quorum, window : int
    relearn : bool
        Re-learn a persistent new layout (a stream); False keeps the first decision (a log file).
    """

    def __init__(self, quorum: int = 3, window: int = 5, relearn: bool = True):
        if quorum < 0 or window < max(1, quorum):
            raise ValueError(f"LayoutConsensus: need 0 <= quorum <= window, window >= 1; got {quorum}, {window}")
        self.quorum, self.window, self.relearn = quorum, window, relearn
        self.layout: tuple | None = None
        self.odd = 0
        self.changes = 0
        self._held: list[Record] = []
        self._run: list[Record] = []

    @property
    def holding(self) -> int:
        """Records held while the layout is being decided."""
        return len(self._held)

    def push(self, rec: Record) -> list[Record]:
        """Admit one record; returns the records released by it (possibly earlier held ones), in order."""
        if self.quorum == 0:
            return [rec]
        key = rec.layout
        if self.layout is None:
            self._held.append(rec)
            votes = Counter(r.layout for r in self._held)
            if votes[key] >= self.quorum:
                return self._adopt(key)
            if len(self._held) >= self.window:
                return self.settle()
            return []
        if key == self.layout:
            self.odd += len(self._run)
            self._run = []
            return [rec]
        if not self.relearn:
            self.odd += 1
            return []
        if self._run and self._run[0].layout != key:
            self.odd += len(self._run)
            self._run = []
        self._run.append(rec)
        if len(self._run) >= self.window:
            self.layout, out, self._run = key, self._run, []
            self.changes += 1
            return out
        return []

    def admits(self, key) -> bool:
        """Whether a record of layout ``key`` would pass :meth:`push` at once (and alone)."""
        return self.quorum == 0 or (self.layout is not None and key == self.layout)

    def admit(self, n: int) -> None:
        """Account for ``n`` records that :meth:`admits` passes, as ``n`` calls of :meth:`push` would (the batch
        path of the stream decoder: the records are not built)."""
        if n and self.quorum:
            self.odd += len(self._run)
            self._run = []

    def settle(self) -> list[Record]:
        """Decide now on the records held so far (the most frequent layout, ties to the latest)."""
        if not self._held:
            return []
        votes = Counter(r.layout for r in self._held)
        top = max(votes.values())
        key = next(r.layout for r in reversed(self._held) if votes[r.layout] == top)
        return self._adopt(key)

    def finish(self) -> list[Record]:
        """End of the records: settle what is held; an unfinished run of another layout is odd."""
        out = self.settle()
        self.odd += len(self._run)
        self._run = []
        return out

    def _adopt(self, key) -> list[Record]:
        out = [r for r in self._held if r.layout == key]
        self.odd += len(self._held) - len(out)
        self._held = []
        self.layout = key
        return out


# --------------------------------------------------------------------------------------------------- stream


class StreamDecoder:
    """Incremental decoder of the ILLumiSense TCP byte stream: feed it whatever ``recv`` returned.

    Handles arbitrary chunking, refuses a length prefix above ``max_payload`` from its 4 bytes, never raises
    for bad bytes, counts framing errors and resynchronises (module docstring), decodes every complete record
    of a chunk as one batch, and filters records through a :class:`LayoutConsensus`. :meth:`feed_batch` hands
    the records of a chunk over as one batch Frame (the live path), :meth:`feed` as one Frame per record,
    :meth:`feed_records` as one :class:`Record` per record; all three count and filter alike.

    Parameters
    ----------
    max_payload : int
        Largest accepted payload, bytes (default 1 MiB; below 16 MiB so every prefix starts with NUL).
    channels_as, n_cores, max_cells
        Passed to :func:`decode_many`.
    layout_quorum, layout_window : int
        Of the :class:`LayoutConsensus` (``layout_quorum=0``: no layout filtering).
    keep_errors : int
        How many of the most recent errors :attr:`errors` keeps.

    Attributes
    ----------
    records : int
        Records delivered.
    framing_errors, bytes_discarded : int
    odd_records, layout_changes : int
        From the consensus: records dropped for their layout; layouts re-learned.
    sequence : SequenceCounter
        Gaps, lost samples and resets of the delivered records' sample numbers.
    sensor_blocks_absent : int
        Sensor blocks of delivered records left out of :attr:`Frame.vendor` (:attr:`Record.absent_sensors`).
    last_error : FramingError or None
    errors : collections.deque of FramingError
    """

    def __init__(self, *, max_payload: int = DEFAULT_MAX_PAYLOAD, channels_as: ChannelsAs = "cores",
                 n_cores: int | None = None, max_cells: int = 1 << 20, layout_quorum: int = 3,
                 layout_window: int = 5, keep_errors: int = 16) -> None:
        if not MIN_PAYLOAD <= max_payload < _PREFIX_LIMIT:
            raise ValueError(f"max_payload: expected {MIN_PAYLOAD} to {_PREFIX_LIMIT - 1} bytes, got {max_payload}")
        if channels_as not in ("cores", "single"):
            raise ValueError(f"channels_as: expected 'cores' or 'single', got {channels_as!r}")
        if channels_as == "single" and (n_cores is None or n_cores < 1):
            raise ValueError("StreamDecoder: channels_as='single' needs n_cores >= 1")
        self.max_payload = max_payload
        self._kw = {"channels_as": channels_as, "n_cores": n_cores, "max_cells": max_cells}
        self._layouts: list = []
        self.consensus = LayoutConsensus(layout_quorum, layout_window)
        self._buf = bytearray()
        self._pos = 0
        self._base = 0
        self._hunting = False
        self._scanned = 0
        self.sequence = SequenceCounter()
        self.records = 0
        self.sensor_blocks_absent = 0
        self.framing_errors = 0
        self.bytes_discarded = 0
        self.last_error: FramingError | None = None
        self.errors: deque[FramingError] = deque(maxlen=keep_errors)

    @property
    def pending(self) -> int:
        """Bytes received but not yet consumed."""
        return len(self._buf) - self._pos

    @property
    def in_sync(self) -> bool:
        """False between a framing error and the next good record."""
        return not self._hunting

    @property
    def odd_records(self) -> int:
        return self.consensus.odd

    @property
    def layout_changes(self) -> int:
        return self.consensus.changes

    @property
    def holding(self) -> int:
        """Records decoded but held while the layout is decided (see :meth:`settle`)."""
        return self.consensus.holding

    def feed(self, data: bytes) -> list[Frame]:
        """Consume bytes; return the frames of every record completed (and admitted) by them, in order."""
        out = []
        for item in self._feed(data):
            if isinstance(item, Record):
                out.append(item.frame)
            else:
                grp, i0, i1 = item
                out += [grp.frame(i) for i in range(i0, i1)]
        return out

    def feed_records(self, data: bytes) -> list[Record]:
        """Like :meth:`feed`, returning the full :class:`Record` of each record."""
        out = []
        for item in self._feed(data):
            if isinstance(item, Record):
                out.append(item)
            else:
                grp, i0, i1 = item
                out += [grp.record(i) for i in range(i0, i1)]
        return out

    def feed_batch(self, data: bytes) -> list[Frame]:
        """Like :meth:`feed`, with the frames of consecutive records of one decoded group as one batch Frame.

        The batch-first path of the live loop: no Python object is built per record (sensor blocks ride on
        the batch as :class:`~twin.frames.VendorArrays`). Records released by the layout consensus come as
        single frames; a layout change starts a new batch.

        Returns
        -------
        list of Frame
            Single frames and 1-D batches (one per run of consecutive records of one decoded group), in record
            order; ``sum(len(f) if f.batch_shape else 1 ...)`` frames
            in all, the same (values, sequence numbers, timestamps) as :meth:`feed` would return.
        """
        out: list[Frame] = []
        for item in self._feed(data):
            if isinstance(item, Record):
                out.append(item.frame)
                continue
            grp, i0, i1 = item
            out.append(grp.batch(i0, i1))  # views of the group's arrays; the driver joins consecutive batches
        return out

    def _feed(self, data: bytes) -> list:
        """Consume bytes; the admitted records in order, as Records (released by the consensus) and
        (group, i0, i1) runs of rows of one decoded group that the consensus admits without building them."""
        self._buf += data
        out: list = []
        seqs: list = []
        cons = self.consensus
        fast = True
        while True:
            spans = self._frame(fast)
            if spans is None:
                break
            prefix, end, compiled = spans
            n = prefix.size
            lo, hi = int(prefix[0]), int(end[-1])
            chunk = bytes(memoryview(self._buf)[lo:hi])  # one copy (the view is released at once)
            errors, groups, gid, gidx = _decode_groups(chunk, prefix + (4 - lo), end - lo, layouts=self._layouts,
                                                       **self._kw)
            if len(groups) == 1 and groups[0].sequence.size == n:  # the common case: every record, one group
                n_ok, runs = n, [(groups[0], 0, n)]
            else:
                failed = np.flatnonzero(gid < 0)
                n_ok = int(failed[0]) if failed.size else n
                # runs of consecutive records of one group
                cuts = [0, *(np.flatnonzero(np.diff(gid[:n_ok])) + 1).tolist(), n_ok] if n_ok else [0]
                runs = [(groups[int(gid[s0])], int(gidx[s0]), int(gidx[s0]) + s1 - s0) for s0, s1 in pairwise(cuts)]
            if n_ok:
                self._pos = int(end[n_ok - 1])
                self._scanned = 0
                self._hunting = False
            for grp, i, i1 in runs:
                key = grp.lay.key
                while i < i1 and not cons.admits(key):  # the layout is being decided: record by record
                    released = cons.push(grp.record(i))
                    out += released
                    seqs += [x.frame.sequence for x in released]
                    self.sensor_blocks_absent += sum(x.absent_sensors for x in released)
                    i += 1
                if i < i1:
                    cons.admit(i1 - i)
                    self.sensor_blocks_absent += (i1 - i) * (len(grp.sensors) - grp.usable_sensors)
                    out.append((grp, i, i1))
                    seqs.append(grp.sequence[i:i1])
            if n_ok < n:
                p = int(prefix[n_ok])
                e = errors[n_ok]
                off = None if e.offset is None else self._base + p + 4 + e.offset
                self._fail(p, type(e)(e.what, offset=off, expected=e.expected, protocol=PROTOCOL))
            elif self._pos < hi:
                break
            # after a run from the compiled framing decoded whole, that framing would stop where it stopped
            fast = n_ok < n or not compiled
        if self._pos > 65536 and self._pos * 2 > len(self._buf):
            del self._buf[: self._pos]
            self._base += self._pos
            self._pos = 0
        self._count_seq(seqs)
        return out

    def _count_seq(self, seqs: list) -> None:
        if seqs:
            seq = seqs[0] if len(seqs) == 1 and isinstance(seqs[0], np.ndarray) else np.concatenate(
                [np.atleast_1d(np.asarray(x, np.int64)) for x in seqs])
            self.records += self.sequence.count_many(seq).size

    def _count(self, out: list[Record]) -> list[Record]:
        self._count_seq([r.frame.sequence for r in out])
        self.sensor_blocks_absent += sum(r.absent_sensors for r in out)
        return out

    def _frame(self, fast: bool = True) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """Complete candidate records from the current position: (prefix offsets, payload ends, whether the
        compiled pass found them) in the buffer, or None. While hunting, at most one (it is accepted only if it
        decodes). ``fast=False`` skips the compiled pass (the caller knows it would find nothing: it stopped
        here before and no byte has come since)."""
        buf = self._buf
        if fast and not self._hunting and len(buf) - self._pos >= 4:
            # in sync, the run of well-formed prefixes is found in one compiled pass; a bad prefix after
            # them is left to the loop below on the next call
            view = np.frombuffer(buf, np.uint8)
            prefix, end = _scan.spans(view, self._pos, MIN_PAYLOAD, self.max_payload)
            del view  # a live view would forbid resizing the bytearray
            if prefix.size:
                return prefix, end, True
        spans = self._frame_slowly()
        return (np.array([p for p, _ in spans], np.int64), np.array([e for _, e in spans], np.int64), False) \
            if spans else None

    def _frame_slowly(self) -> list[tuple[int, int]]:
        """:meth:`_frame` byte by byte: hunting, at a bad prefix, or waiting for the rest of a payload."""
        buf = self._buf
        spans: list[tuple[int, int]] = []
        p = self._pos
        while True:
            if self._hunting and not spans:
                # straight to the next candidate the checks below could accept (compiled: a flood of NUL bytes
                # or of bad prefixes would otherwise cost a Python step a byte)
                view = np.frombuffer(buf, np.uint8)
                q = _scan.hunt(view, p, MIN_PAYLOAD, self.max_payload, self._scanned)
                del view  # a live view would forbid resizing the bytearray
                if q != p:  # the candidate waited for (if any) is rejected: what was scanned of it is not ours
                    self._scanned = 0
                self.bytes_discarded += q - p
                self._pos = p = q
            if len(buf) - p < 4:
                return spans
            length = int.from_bytes(buf[p : p + 4], "big")
            if length > self.max_payload or length < MIN_PAYLOAD:
                if spans:
                    return spans
                cls, what = ((OversizeFrameError, f"length prefix {length} exceeds the {self.max_payload}-byte "
                              "bound") if length > self.max_payload
                             else (FramingError, f"length prefix {length} is shorter than any record"))
                self._fail(p, cls(what, offset=self._base + p, expected=f"{MIN_PAYLOAD} to {self.max_payload}",
                                  protocol=PROTOCOL))
                p = self._pos
                continue
            end = p + 4 + length
            start_scan = p + 4 + self._scanned
            hi = min(end - 1, len(buf))  # the last payload byte may be the LF
            # in sync, the tokenizer finds a NUL or LF inside a complete payload; hunting, or in sync waiting
            # for the rest of a payload, the candidate is rejected as soon as one arrives (a corrupted prefix
            # in sync would otherwise wait for bytes that the later prefixes' NULs already prove wrong)
            if (self._hunting or len(buf) < end) and hi > start_scan:
                bad = [i for i in (buf.find(b"\x00", start_scan, hi), buf.find(b"\n", start_scan, hi)) if i >= 0]
                if bad:
                    if spans:
                        return spans
                    self._fail(p, FramingError("NUL or LF inside a payload", offset=self._base + min(bad),
                                               expected=f"a {length}-byte payload", protocol=PROTOCOL))
                    p = self._pos
                    continue
                self._scanned = hi - p - 4
            if len(buf) < end:
                return spans
            spans.append((p, end))
            if self._hunting:
                return spans
            p = end

    def settle(self) -> list[Frame]:
        """Release the records held for the layout decision now (a driver calls this when they wait too long)."""
        return [r.frame for r in self._count(self.consensus.settle())]

    def finish(self) -> list[Frame]:
        """Declare the end of the stream: an incomplete record left over is an error; held records are settled
        and returned."""
        left = self.pending
        if left and not self._hunting:
            self._fail(self._pos, TruncatedFrameError(f"stream ended inside a record ({left} bytes pending)",
                                                      offset=self._base + len(self._buf),
                                                      expected="a complete record", protocol=PROTOCOL))
        self.bytes_discarded += self.pending
        self._base += len(self._buf)
        self._buf.clear()
        self._pos = 0
        self._scanned = 0
        self._hunting = False
        return [r.frame for r in self._count(self.consensus.finish())]

    def _fail(self, p: int, err: FramingError) -> None:
        if not self._hunting:
            self.framing_errors += 1
            self.last_error = err
            self.errors.append(err)
            self._hunting = True
        self._pos = p + 1
        self._scanned = 0
        self.bytes_discarded += 1
