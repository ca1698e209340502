"""Reading a twin MCAP recording back (``twin replay run.mcap``, ``replay://run.mcap``).

:class:`McapRecording` has the read interface of :class:`twin.io.record.RecordingReader` (``len``, ``frames``,
``truth``, ``vendor``, ``received``, ``chunks``, ``damage``…), so ``twin replay`` and ``replay://`` treat an MCAP
recording like an HDF5 one: they reconstruct from the recorded wavelengths (``/fbg/wavelengths``) and compare
with the recorded truth (``/catheter/truth``) and the interrogator's own shape (``/fbg/vendor_shape``). The
recorded reconstructions (``/catheter/shape``, ``/catheter/tip``) are for other tools; replay makes its own.
The messages of one frame are tied by their MCAP ``sequence`` (the frame's row, :mod:`twin.io.rosbag.bag_writer`).

Bounded memory: opening reads the file once, record by record, and keeps an index of its data records (chunks,
and messages written outside chunks): each one's byte offset and the frame rows it holds, a few dozen bytes per
chunk (about 1 MiB of messages). Frames are read back a slice at a time (:meth:`McapRecording.frames`,
:meth:`~McapRecording.chunks`) from the records that hold them. No record is read whole whose length exceeds
``max_record`` (64 MiB by default; the writer's chunks are 1 MiB), a chunk is decompressed to at most its
declared size and only when that is within ``max_record``, and records the reader does not need (indexes,
statistics, schemas) are stepped over unread; so the memory a file takes is bounded by ``max_record`` and the
slice asked for, whatever its size or its headers claim.

Damage, as for HDF5 recordings: a file that ends inside a record was cut (``the file is cut short at byte B of
S``); a record claiming more bytes than the file holds or than ``max_record``, a chunk that fails its CRC or
does not decompress to its declared size, a record that does not parse, or frame messages that do not decode
are damage at their byte offset. :attr:`McapRecording.damage` names it, ``len`` counts the frames before it,
and the caller decides (``twin replay`` refuses without ``--salvage``). Truth or sensor-block messages that do
not decode are damage confined to them: those rows come back without truth (or blocks), the frames kept. A
file that ends cleanly between records without its summary was left by a writer that did not close it
(killed): not complete, not damaged, every written chunk readable. Nothing here waits or retries.
"""

from __future__ import annotations

import io
import json
import os
import stat
import tomllib
import zlib
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from twin import so3
from twin.calibration import Calibration
from twin.extras import require
from twin.fiber import FiberModel
from twin.frames import Frame, Truth, VendorArrays
from twin.io.errors import brief
from twin.io.reading import ReaderBase
from twin.io.rosbag import ros_messages as msgs
from twin.io.rosbag.bag_writer import FORMAT

__all__ = ["MAGIC", "MAX_RECORD", "McapRecording", "is_mcap"]

MAGIC = b"\x89MCAP0\r\n"
#: the longest record (and decompressed chunk) the reader takes into memory, bytes
MAX_RECORD = 64 << 20

_WAVELENGTHS, _TRUTH, _VENDOR = "/fbg/wavelengths", "/catheter/truth", "/fbg/vendor_shape"
_TOPICS = (_WAVELENGTHS, _TRUTH, _VENDOR)
# MCAP opcodes (the specification's numbers)
_HEADER, _FOOTER, _CHANNEL, _MESSAGE, _CHUNK, _ATTACHMENT, _METADATA = 0x01, 0x02, 0x04, 0x05, 0x06, 0x09, 0x0C
_READ = {_HEADER, _FOOTER, _CHANNEL, _MESSAGE, _CHUNK, _ATTACHMENT, _METADATA}  # others are stepped over
_ATTACHMENTS = {"fiber.toml", "calibration.toml"}
#: the metadata records this reader reads (any other is skipped unkept)
_METADATA_NAMES = {"catheter_twin", "catheter_twin_truth"}


def is_mcap(head: bytes) -> bool:
    """Whether a file's first bytes are MCAP's magic."""
    return head[:8] == MAGIC


class _Cut(Exception):
    """The file ends inside the record at this offset."""


class _Damaged(Exception):
    """A record that cannot be read: the message names its place."""


class McapRecording(ReaderBase):
    """A twin MCAP recording opened for reading (module docstring); the interface of
    :class:`twin.io.record.RecordingReader`.

    Parameters
    ----------
    path : str or Path
    max_record : int
        Longest record (and decompressed chunk) taken into memory, bytes; a longer one is damage.

    Attributes
    ----------
    path : Path
    kind : str
        ``"twin-mcap"``.
    fiber, calibration : FiberModel, Calibration or None
        From the attachments.
    source_url : str
    complete : bool
        The writer closed the file (summary and footer present) and nothing is damaged.
    rate : float or None
    errors : list of str
        Always empty (logs' skipped lines).
    damage : list of str
    frames_recorded : int
        ``/fbg/wavelengths`` messages found (frames before the first damage).
    notes : list of str
        What the reader had to assume (a truth without its arc lengths…).
    """

    kind = "twin-mcap"

    def __init__(self, path: str | Path, *, max_record: int = MAX_RECORD):
        self._records = require("mcap.records", "MCAP replay")
        from mcap.data_stream import ReadDataStream

        self._stream = ReadDataStream
        self.path = Path(path)
        self.max_record = int(max_record)
        self.errors: list[str] = []
        self.damage: list[str] = []
        self.notes: list[str] = []
        self.fiber = self.calibration = None
        self.source_url = ""
        self.rate = None
        self._closed_cleanly = False
        self._topics: dict[int, str] = {}  # channel id → topic, of the topics read
        self._units: list[tuple[int, int, int, int]] = []  # (offset, frame messages, lowest row, highest row)
        self._tied = True  # message sequence fields are the frames' rows
        self._n = 0
        self._truth_ok = self._vendor_ok = 1 << 62  # rows from which truth / sensor blocks are damaged
        self._layout: dict = {}  # (G, C) of the frames, m truth points, (G, N, spacing) per sensor
        self._first_truth: np.ndarray | None = None
        self._empty: dict = {}  # zero-row columns of the frame messages
        self._cache: tuple = (None, None)  # the last span read and its columns
        self._unit_cache: tuple = (None, None)  # the last data record read and its messages
        try:
            self._fh = open(self.path, "rb")
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.path}: no such recording") from None
        except IsADirectoryError:
            raise IsADirectoryError(f"{self.path}: is a directory, not a recording") from None
        try:
            if not stat.S_ISREG(os.fstat(self._fh.fileno()).st_mode):
                raise ValueError(f"{self.path}: not a regular file (a device or a pipe)")
            self._size = self._fh.seek(0, 2)
            self._fh.seek(0)
            if not is_mcap(self._fh.read(8)):
                raise ValueError(f"{self.path}: not an MCAP file")
            meta, attachments = self._scan()
            self._meta(meta, attachments)
            self._truth_s = self._arc_lengths(meta)
        except BaseException:
            self._fh.close()
            raise
        self.frames_recorded = self._n
        self._sensors = len(self._layout.get("vendor", ()))
        index = np.array(self._units, np.int64).reshape(-1, 4)
        self._at, self._count, self._lo, self._hi = index.T
        self._first = np.concatenate([[0], np.cumsum(self._count)[:-1]]).astype(np.int64)  # file-order rows
        if not self._tied:
            # not written by twin (or rows lost in between): frames in file order, no truth or vendor ties
            self.notes.append("message sequence fields are not the frames' rows: truth and vendor blocks not tied")
            self._first_truth, self._truth_ok, self._vendor_ok, self._sensors = None, 0, 0, 0

    # ---------------------------------------------------------------- reading the file once: the index
    def _record(self, at: int) -> tuple[int, int, bytes | None]:
        """(opcode, end, body) of the record at byte ``at``; body None for a record the reader steps over."""
        fh = self._fh
        fh.seek(at)
        head = fh.read(9)
        if len(head) < 9:
            raise _Cut
        opcode, length = head[0], int.from_bytes(head[1:], "little")
        if length > self._size:
            raise _Damaged(f"record at byte {at} claims {length} bytes, more than the file's {self._size}")
        end = at + 9 + length
        if end > self._size:
            raise _Cut
        if opcode not in _READ:
            return opcode, end, None
        if length > self.max_record:
            raise _Damaged(f"record at byte {at} holds {length} bytes, more than the reader takes "
                           f"({self.max_record}, max_record)")
        body = fh.read(length)
        if len(body) < length:
            raise _Cut
        return opcode, end, body

    def _parse(self, cls, body: bytes, at: int, *args):
        try:
            return cls.read(self._stream(io.BytesIO(body)), *args)
        except Exception as exc:  # short fields, bad UTF-8: the record does not parse
            raise _Damaged(f"unreadable record at byte {at} ({brief(exc)})") from None

    def _chunk_messages(self, body: bytes, at: int) -> list:
        """The messages (and channels) in a chunk record, decompressed within its declared size."""
        chunk = self._parse(self._records.Chunk, body, at)
        size = chunk.uncompressed_size
        if size > self.max_record:
            raise _Damaged(f"chunk at byte {at} claims {size} bytes uncompressed, more than the reader takes "
                           f"({self.max_record}, max_record)")
        try:
            data = _decompress(chunk.compression, chunk.data, size)
        except Exception as exc:
            raise _Damaged(f"chunk at byte {at} unreadable ({brief(exc)})") from None
        if len(data) != size:
            raise _Damaged(f"chunk at byte {at} unreadable (decompresses to {len(data)} bytes, not {size})")
        if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
            raise _Damaged(f"chunk at byte {at} unreadable (CRC mismatch)")
        from mcap.stream_reader import breakup_chunk

        try:
            return breakup_chunk(replace(chunk, compression="", data=data, uncompressed_crc=0))
        except Exception as exc:
            raise _Damaged(f"chunk at byte {at} unreadable ({brief(exc)})") from None

    def _scan(self) -> tuple[dict, dict]:
        """Read the file once, record by record: channels, metadata, attachments, and the index of the data
        records (each checked: CRC, decompression, its frame messages decoded and dropped)."""
        records = self._records
        meta: dict[str, dict] = {}
        attachments: dict[str, bytes] = {}
        at = 8  # the end of the last whole record
        while at < self._size:
            try:
                opcode, end, body = self._record(at)
                if opcode in (_CHUNK, _MESSAGE):
                    inner = self._chunk_messages(body, at) if opcode == _CHUNK else \
                        [self._parse(records.Message, body, at, len(body))]
                    self._index(inner, at)
                elif opcode == _CHANNEL:
                    self._channel(self._parse(records.Channel, body, at))
                elif opcode == _HEADER:
                    profile = self._parse(records.Header, body, at).profile
                    if profile != "ros2":
                        raise ValueError(f"{self.path}: MCAP profile {profile!r}, not a ROS 2 recording")
                elif opcode == _ATTACHMENT:
                    a = self._parse(records.Attachment, body, at)
                    if a.name in _ATTACHMENTS:
                        attachments[a.name] = a.data
                elif opcode == _METADATA:
                    m = self._parse(records.Metadata, body, at)
                    if m.name in _METADATA_NAMES:  # only ours are kept: memory stays bounded whatever else a file holds
                        meta[m.name] = m.metadata
                elif opcode == _FOOTER:
                    self._fh.seek(end)
                    self._closed_cleanly = self._fh.read(8) == MAGIC  # else cut in the closing magic: no frame lost
                    break
            except _Cut:
                self.damage.append(f"the file is cut short at byte {at} of {self._size} (a record is incomplete)")
                break
            except _Damaged as exc:
                self.damage.append(str(exc))
                break
            at = end
        return meta, attachments

    def _channel(self, ch) -> None:
        if ch.topic in _TOPICS:
            self._topics[ch.id] = ch.topic

    def _index(self, inner: list, at: int) -> None:
        """Index one data record (its frame messages decoded to check them, then dropped)."""
        by_topic = self._messages(inner)
        rows_w = by_topic[_WAVELENGTHS][0]
        if rows_w.size:
            try:
                cols = _grouped(by_topic[_WAVELENGTHS][2], msgs.decode_wavelengths)
                shape = cols["wavelengths"].shape[1:]
                if self._layout.setdefault("frames", shape) != shape:
                    raise ValueError(f"{shape[0]} gratings × {shape[1]} cores, earlier frames "
                                     f"{self._layout['frames'][0]} × {self._layout['frames'][1]}")
            except ValueError as exc:
                raise _Damaged(f"{_WAVELENGTHS} messages at byte {at} undecodable ({brief(exc)})") from None
            self._empty = self._empty or {k: v[:0] for k, v in cols.items() if not isinstance(v, str)}
            if not np.array_equal(rows_w, self._n + np.arange(rows_w.size)):
                self._tied = False
        rows_t = by_topic[_TRUTH][0]
        if rows_t.size and rows_t.min() < self._truth_ok:
            try:
                pos = _grouped(by_topic[_TRUTH][2], msgs.decode_path)["positions"]
                if self._layout.setdefault("truth", pos.shape[1]) != pos.shape[1]:
                    raise ValueError(f"{pos.shape[1]} points, earlier truths {self._layout['truth']}")
                if self._first_truth is None:
                    self._first_truth = pos[0]
            except ValueError as exc:
                self._truth_ok = int(rows_t.min())
                self.damage.append(f"{_TRUTH} messages at byte {at} undecodable ({brief(exc)}); frames from "
                                   f"row {self._truth_ok} on replayed without truth")
        rows_v = by_topic[_VENDOR][0]
        if rows_v.size and rows_v.min() < self._vendor_ok:
            try:
                d = _grouped(by_topic[_VENDOR][2], msgs.decode_vendor)
                known = self._layout.setdefault("vendor", {})
                for k in np.unique(d["sensor"]).tolist():
                    i = int(np.flatnonzero(d["sensor"] == k)[0])
                    layout = (d["curvature"].shape[1], d["points"].shape[1], float(d["spacing"][i]))
                    if known.setdefault(k, layout) != layout:
                        raise ValueError(f"sensor {k}: layout {layout}, earlier blocks {known[k]}")
            except ValueError as exc:
                self._vendor_ok = int(rows_v.min())
                self.damage.append(f"{_VENDOR} messages at byte {at} undecodable ({brief(exc)}); frames from "
                                   f"row {self._vendor_ok} on replayed without them")
        rows = np.concatenate([rows_w, rows_t, rows_v])
        if rows.size:
            self._units.append((at, rows_w.size, int(rows.min()), int(rows.max())))
            self._n += rows_w.size

    def _messages(self, inner: list) -> dict[str, tuple[np.ndarray, np.ndarray, list[bytes]]]:
        """A data record's messages of the topics read: topic → (rows, log times, payloads)."""
        records = self._records
        found: dict[str, tuple[list, list, list]] = {t: ([], [], []) for t in _TOPICS}
        for r in inner:
            if isinstance(r, records.Channel):
                self._channel(r)
            elif isinstance(r, records.Message):
                topic = self._topics.get(r.channel_id)
                if topic is not None:
                    rows, log, data = found[topic]
                    rows.append(r.sequence)
                    log.append(r.log_time)
                    data.append(r.data)
        return {t: (np.array(v[0], np.int64), np.array(v[1], np.int64), v[2]) for t, v in found.items()}

    def _meta(self, meta: dict, attachments: dict) -> None:
        info = meta.get("catheter_twin")
        if info is None or info.get("format") != FORMAT:
            raise ValueError(f"{self.path}: MCAP file is not a twin recording (no catheter_twin metadata"
                             + (f"; {self.damage[0]}" if self.damage else "") + ")")
        self.source_url = info.get("source_url", "")
        try:
            rate = float(info.get("rate_hz") or "nan")
        except ValueError:
            rate = float("nan")
        self.rate = rate if np.isfinite(rate) and rate > 0 else None
        for name, cls, attr in (("fiber.toml", FiberModel, "fiber"), ("calibration.toml", Calibration,
                                                                         "calibration")):
            if name in attachments:
                where = f"{self.path}: attachment {name}"
                try:
                    setattr(self, attr, cls.from_dict(tomllib.loads(attachments[name].decode()), source=where))
                except Exception as exc:  # TOML errors, wrong types: one line naming the place
                    msg = str(exc)
                    raise ValueError(msg if msg.startswith(str(self.path)) else f"{where}: {msg}") from None

    def _arc_lengths(self, meta: dict) -> np.ndarray | None:
        """The truth's arc lengths: stored, else along the first truth's points (noted)."""
        if self._first_truth is None:
            return None
        m = self._first_truth.shape[0]
        try:
            s = np.asarray(json.loads(meta["catheter_twin_truth"]["s"]), dtype=np.float64)
        except (ValueError, KeyError, TypeError):
            s = None
        if s is None or s.shape != (m,):
            p = self._first_truth
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            self.notes.append("truth arc lengths not stored: taken along the first truth's points")
        return s

    # ---------------------------------------------------------------- reading a span of frames
    def _unit(self, k: int) -> dict:
        """The messages of data record ``k`` (read again; the last one kept: consecutive spans share it)."""
        if self._unit_cache[0] == k:
            return self._unit_cache[1]
        at = int(self._at[k])
        try:
            opcode, _, body = self._record(at)
            inner = self._chunk_messages(body, at) if opcode == _CHUNK else \
                [self._parse(self._records.Message, body, at, len(body))]
        except (_Cut, _Damaged) as exc:
            raise ValueError(f"{self.path}: changed since it was opened ({str(exc) or f'cut at byte {at}'})") \
                from None
        found = self._messages(inner)
        if not self._tied:  # rows in file order
            rows = found[_WAVELENGTHS][0]
            found[_WAVELENGTHS] = (self._first[k] + np.arange(rows.size), *found[_WAVELENGTHS][1:])
        self._unit_cache = (k, found)
        return found

    def _span_columns(self, start: int, stop: int) -> dict:
        """Everything recorded of frames ``start:stop``: frame columns, log times, truth, sensor blocks."""
        if self._cache[0] == (start, stop):
            return self._cache[1]
        if self._tied:
            sel = np.flatnonzero((self._hi >= start) & (self._lo < stop))
        else:
            sel = np.flatnonzero((self._first < stop) & (self._first + self._count > start))
        got: dict[str, tuple[list, list, list]] = {t: ([], [], []) for t in _TOPICS}
        for k in sel.tolist():
            for topic, (rows, log, data) in self._unit(k).items():
                keep = np.flatnonzero((rows >= start) & (rows < stop))
                got[topic][0].append(rows[keep])
                got[topic][1].append(log[keep])
                got[topic][2].extend(data[i] for i in keep.tolist())
        (rows, log, data), m = (_joined(got[_WAVELENGTHS]), stop - start)
        if rows.size != m or not np.array_equal(np.sort(rows), start + np.arange(m)):
            raise ValueError(f"{self.path}: frames {start}–{stop - 1} not found where the index put them")
        cols = dict(self._empty)
        times = np.zeros(m, np.int64)
        if m:
            decoded = _grouped(data, msgs.decode_wavelengths)
            cols = {k: _placed(decoded[k], rows - start, m) for k in self._empty}
            times[rows - start] = log
        out = {"frame": Frame(cols["wavelengths"], cols["timestamp"], cols["sequence"], powers=cols["powers"],
                              status=cols["status"]),
               "log": times, "truth": self._span_truth(_joined(got[_TRUTH]), start, m),
               "vendor": self._span_vendor(_joined(got[_VENDOR]), start, m)}
        self._cache = ((start, stop), out)
        return out

    def _span_truth(self, found: tuple, start: int, m: int) -> Truth | None:
        if not self.has_truth:
            return None
        rows, _, data = found
        keep = np.flatnonzero(rows < self._truth_ok)
        p = self._truth_s.shape[0]
        pos, frames = np.full((m, p, 3), np.nan), np.full((m, p, 3, 3), np.nan)
        present = np.zeros(m, bool)
        if keep.size:
            d = _grouped([data[i] for i in keep.tolist()], msgs.decode_path)
            at = rows[keep] - start
            pos[at], frames[at], present[at] = d["positions"], so3.from_quaternion(d["quaternions"]), True
        return Truth(s=self._truth_s, positions=pos, frames=frames, present=present)

    def _span_vendor(self, found: tuple, start: int, m: int) -> tuple:
        if not self._sensors:
            return ()
        rows, _, data = found
        keep = np.flatnonzero(rows < self._vendor_ok)
        out = [VendorArrays.absent(m, self._layout["vendor"][k]) for k in range(self._sensors)]
        if keep.size:
            d = _grouped([data[i] for i in keep.tolist()], msgs.decode_vendor)
            at = rows[keep] - start
            for k, a in enumerate(out):
                sel = np.flatnonzero(d["sensor"] == k)
                a.curvature[at[sel]], a.angle[at[sel]], a.positions[at[sel]] = (
                    d["curvature"][sel], d["angle"][sel], d["points"][sel])
                a.present[at[sel]] = True
        return tuple(out)

    # ---------------------------------------------------------------- the RecordingReader interface
    def damage_line(self) -> str:
        """One line for a damaged file: the file, frames readable of how many, the first damage, what to do."""
        why = self.damage[0] if self.damage else "no damage"
        return (f"{self.path}: damaged recording: {self._n} frames readable ({why}); --salvage "
                "(replay://FILE?salvage=1) uses the readable frames")

    @property
    def shape(self) -> tuple[int, int] | None:
        return self._layout.get("frames") if self._n else None

    @property
    def has_truth(self) -> bool:
        return self._truth_s is not None and self._truth_ok > 0

    @property
    def has_vendor(self) -> bool:
        return bool(self._sensors)

    def refresh(self) -> int:
        """Frames available (the file is indexed when opened)."""
        return self._n

    def frames(self, start: int = 0, stop: int | None = None, *, truth: bool = True) -> Frame:
        """Frames ``start:stop`` as one batch (with their truth when recorded and ``truth``)."""
        if not self._n:
            return Frame(np.zeros((0, 0, 0)))
        cols = self._span_columns(*self._span(start, stop))
        batch = cols["frame"]
        if truth and cols["truth"] is not None:
            batch = replace(batch, truth=cols["truth"])
        return batch

    def truth(self, start: int = 0, stop: int | None = None, fields: Sequence[str] | None = None) -> Truth | None:
        """Truth of frames ``start:stop`` (positions and material frames), or None without one."""
        if not self.has_truth or not self._n:
            return None
        return self._span_columns(*self._span(start, stop))["truth"]

    def vendor(self, start: int = 0, stop: int | None = None) -> tuple:
        """The interrogator's own reconstruction of frames ``start:stop``, one VendorArrays per sensor."""
        if not self._sensors or not self._n:
            return ()
        return self._span_columns(*self._span(start, stop))["vendor"]

    def received(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """When the live loop received frames ``start:stop`` (the messages' log time), s since the epoch."""
        if not self._n:
            return np.zeros(0)
        return self._span_columns(*self._span(start, stop))["log"] * 1e-9

    def close(self) -> None:
        self._fh.close()
        self._cache = self._unit_cache = (None, None)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    """A chunk's records, decompressed to no more than ``size`` (+1, to tell a longer one) bytes."""
    if compression == "":
        return data
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)).read(size + 1)
    raise ValueError(f"compression {compression!r} unknown")


def _joined(found: tuple[list, list, list]) -> tuple[np.ndarray, np.ndarray, list[bytes]]:
    rows, log, data = found
    return (np.concatenate(rows) if rows else np.zeros(0, np.int64),
            np.concatenate(log) if log else np.zeros(0, np.int64), data)


def _placed(values: np.ndarray, at: np.ndarray, m: int) -> np.ndarray:
    """``values`` (rows in message order) put at rows ``at`` of an (m, …) array."""
    out = np.empty((m, *values.shape[1:]), values.dtype)
    out[at] = values
    return out


def _grouped(payloads: list[bytes], decode) -> dict:
    """Decode messages grouped by length (one layout per group) and put the rows back in order."""
    sizes = np.fromiter((len(p) for p in payloads), np.int64, len(payloads))
    groups = np.unique(sizes)
    if groups.size == 1:
        return decode(payloads)
    parts = [(np.flatnonzero(sizes == g), decode([payloads[i] for i in np.flatnonzero(sizes == g)])) for g in groups]
    out: dict = {}
    for key, value in parts[0][1].items():
        if isinstance(value, str):
            out[key] = value
            continue
        shapes = {v[key].shape[1:] for _, v in parts}
        if len(shapes) != 1:
            raise ValueError(f"messages of different layouts ({key}: {sorted(shapes)})")
        arr = np.empty((len(payloads), *value.shape[1:]), value.dtype)
        for idx, v in parts:
            arr[idx] = v[key]
        out[key] = arr
    return out
