"""Reading a twin MCAP recording back (``twin replay run.mcap``, ``replay://run.mcap``).

:class:`McapRecording` has the read interface of :class:`twin.io.record.RecordingReader` (``len``, ``frames``,
``truth``, ``vendor``, ``received``, ``chunks``, ``damage``…), so ``twin replay`` and ``replay://`` treat an MCAP
recording like an HDF5 one: they reconstruct from the recorded wavelengths (``/fbg/wavelengths``) and compare
with the recorded truth (``/catheter/truth``) and the interrogator's own shape (``/fbg/vendor_shape``). The
recorded reconstructions (``/catheter/shape``, ``/catheter/tip``) are for other tools; replay makes its own.

The file is read once, record by record (the ``mcap`` package's stream reader, chunks checked against their CRC),
and its frames are held in memory as arrays (about 1.2 kB a frame for 18 gratings × 4 cores; a truth of m points
adds 96·m bytes). The messages of one frame are tied by their MCAP ``sequence`` (the frame's row,
:mod:`twin.io.rosbag.bag_writer`).

Damage, as for HDF5 recordings: a file that ends inside a record was cut (``the file is cut short at byte B of
S``), a chunk that fails its CRC or does not decompress, a record that does not parse, or a message that does not
decode is damage at its byte offset; :attr:`McapRecording.damage` names it, ``len`` counts the frames before it,
and the caller decides (``twin replay`` refuses without ``--salvage``). A file that ends cleanly between records
without its summary was left by a writer that did not close it (killed): not complete, not damaged, every
written chunk readable. Nothing here waits or retries; a record's declared length is bounded by the file's size
and a chunk's by 1 GiB, so garbage cannot make the reader allocate without bound.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from twin import so3
from twin.calibration import Calibration
from twin.extras import require
from twin.fiber import FiberModel
from twin.frames import Frame, Truth
from twin.io.rosbag import ros_messages as msgs
from twin.io.rosbag.bag_writer import FORMAT

__all__ = ["MAGIC", "McapRecording", "is_mcap"]

MAGIC = b"\x89MCAP0\r\n"
_MAX_CHUNK = 1 << 30


def is_mcap(head: bytes) -> bool:
    """Whether a file's first bytes are MCAP's magic."""
    return head[:8] == MAGIC


def _brief(exc: BaseException) -> str:
    return (str(exc).strip() or type(exc).__name__).splitlines()[0][:200]


class McapRecording:
    """A twin MCAP recording opened for reading (module docstring); the interface of
    :class:`twin.io.record.RecordingReader`.

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

    def __init__(self, path: str | Path):
        stream_reader = require("mcap.stream_reader", "MCAP replay")
        records = require("mcap.records", "MCAP replay")
        self.path = Path(path)
        self.errors: list[str] = []
        self.damage: list[str] = []
        self.notes: list[str] = []
        self.fiber = self.calibration = None
        self.source_url = ""
        self.rate = None
        self._closed_cleanly = False
        topics: dict[int, str] = {}
        found: dict[str, list] = {"/fbg/wavelengths": [], "/catheter/truth": [], "/fbg/vendor_shape": []}
        meta: dict[str, dict] = {}
        attachments: dict[str, bytes] = {}
        try:
            fh = open(self.path, "rb")
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.path}: no such recording") from None
        with fh:
            size = fh.seek(0, 2)
            fh.seek(0)
            if not is_mcap(fh.read(8)):
                raise ValueError(f"{self.path}: not an MCAP file")
            fh.seek(0)
            reader = stream_reader.StreamReader(fh, emit_chunks=True, record_size_limit=max(size, 1))
            good = 8  # bytes up to the end of the last whole record
            it = reader.records
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except Exception as exc:  # EndOfFile, short reads, bad lengths: where did the file stop making sense
                    if fh.tell() >= size and good == size:
                        break  # ends between records: a writer that never closed the file
                    if fh.tell() >= size:
                        self.damage.append(f"the file is cut short at byte {good} of {size} (a record is "
                                           "incomplete)")
                    else:
                        self.damage.append(f"unreadable record at byte {good} ({_brief(exc)})")
                    break
                start, good = good, fh.tell()
                if isinstance(rec, records.Header):
                    if rec.profile != "ros2":
                        raise ValueError(f"{self.path}: MCAP profile {rec.profile!r}, not a ROS 2 recording")
                elif isinstance(rec, records.Chunk):
                    if rec.uncompressed_size > _MAX_CHUNK:
                        self.damage.append(f"chunk at byte {start} claims {rec.uncompressed_size} bytes")
                        break
                    try:
                        inner = stream_reader.breakup_chunk(rec, validate_crc=True)
                    except Exception as exc:
                        self.damage.append(f"chunk at byte {start} unreadable ({_brief(exc)})")
                        break
                    for r in inner:
                        self._take(r, records, topics, found, start)
                elif isinstance(rec, records.Attachment):
                    attachments[rec.name] = rec.data
                elif isinstance(rec, records.Metadata):
                    meta[rec.name] = rec.metadata
                elif isinstance(rec, records.Footer):
                    self._closed_cleanly = True
                else:
                    self._take(rec, records, topics, found, start)
        self._meta(meta, attachments)
        self._decode(found, meta)

    def _take(self, rec, records, topics: dict, found: dict, where: int) -> None:
        if isinstance(rec, records.Channel):
            topics[rec.id] = rec.topic
        elif isinstance(rec, records.Message):
            topic = topics.get(rec.channel_id)
            if topic in found:
                found[topic].append((rec.sequence, rec.log_time, rec.data, where))

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

    def _decode(self, found: dict, meta: dict) -> None:
        w = found["/fbg/wavelengths"]
        rows = np.array([m[0] for m in w], np.int64)
        n = len(w)
        cols = None
        if n:
            try:
                cols = _grouped([m[2] for m in w], msgs.decode_wavelengths)
            except ValueError as exc:
                self.damage.append(f"/fbg/wavelengths messages from byte {w[0][3]} undecodable ({_brief(exc)})")
                n = 0
        if n and not np.array_equal(rows, np.arange(n)):
            # not written by twin (or rows lost in between): frames in file order, no truth or vendor ties
            self.notes.append("message sequence fields are not the frames' rows: truth and vendor blocks not tied")
            found = {k: [] if k != "/fbg/wavelengths" else v for k, v in found.items()}
        self.frames_recorded = self._n = n
        self._log_time = np.array([m[1] for m in w[:n]], np.int64)
        if n:
            self._mem = Frame(cols["wavelengths"], cols["timestamp"], cols["sequence"], powers=cols["powers"],
                              status=cols["status"])
        else:
            self._mem = Frame(np.zeros((0, 0, 0)))
        self._truth = self._decode_truth(found["/catheter/truth"], meta, n)
        self._vendor = self._decode_vendor(found["/fbg/vendor_shape"], n)

    def _decode_truth(self, items: list, meta: dict, n: int) -> Truth | None:
        items = [m for m in items if m[0] < n]
        if not items:
            return None
        try:
            d = _grouped([m[2] for m in items], msgs.decode_path)
        except ValueError as exc:
            self.damage.append(f"/catheter/truth messages from byte {items[0][3]} undecodable ({_brief(exc)}); "
                               "replayed without truth")
            return None
        pos, quat = d["positions"], d["quaternions"]
        rows = np.array([m[0] for m in items], np.int64)
        s = None
        if "catheter_twin_truth" in meta:
            try:
                s = np.asarray(json.loads(meta["catheter_twin_truth"]["s"]), dtype=np.float64)
            except (ValueError, KeyError, TypeError):
                s = None
        if s is None or s.shape != (pos.shape[1],):
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos[0], axis=0), axis=1))])
            self.notes.append("truth arc lengths not stored: taken along the first truth's points")
        full = np.full((n, *pos.shape[1:]), np.nan)
        full[rows] = pos
        frames = np.full((n, pos.shape[1], 3, 3), np.nan)
        frames[rows] = so3.from_quaternion(quat)
        present = np.zeros(n, bool)
        present[rows] = True
        return Truth(s=s, positions=full, frames=frames, present=present)

    def _decode_vendor(self, items: list, n: int) -> tuple:
        items = [m for m in items if m[0] < n]
        if not items:
            return ()
        from twin.frames import VendorArrays

        try:
            d = _grouped([m[2] for m in items], msgs.decode_vendor)
        except ValueError as exc:
            self.damage.append(f"/fbg/vendor_shape messages from byte {items[0][3]} undecodable ({_brief(exc)}); "
                               "replayed without them")
            return ()
        rows = np.array([m[0] for m in items], np.int64)
        out = []
        for k in range(int(d["sensor"].max()) + 1):
            sel = np.flatnonzero(d["sensor"] == k)
            if not sel.size:
                break
            G, N = d["curvature"][sel[0]].shape[0], d["points"][sel[0]].shape[0]
            spacing = float(d["spacing"][sel[0]])
            cu, an = np.full((n, G), np.nan), np.full((n, G), np.nan)
            pts, present = np.full((n, N, 3), np.nan), np.zeros(n, bool)
            cu[rows[sel]], an[rows[sel]], pts[rows[sel]] = d["curvature"][sel], d["angle"][sel], d["points"][sel]
            present[rows[sel]] = True
            out.append(VendorArrays(cu, an, pts, present, spacing))
        return tuple(out)

    # ---------------------------------------------------------------- the RecordingReader interface
    @property
    def complete(self) -> bool:
        return self._closed_cleanly and not self.damage

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    def __len__(self) -> int:
        return self._n

    def damage_line(self) -> str:
        """One line for a damaged file: the file, frames readable of how many, the first damage, what to do."""
        why = self.damage[0] if self.damage else "no damage"
        return (f"{self.path}: damaged recording: {self._n} frames readable ({why}); --salvage "
                "(replay://FILE?salvage=1) uses the readable frames")

    @property
    def shape(self) -> tuple[int, int] | None:
        return tuple(self._mem.wavelengths.shape[1:]) if self._n else None

    @property
    def has_truth(self) -> bool:
        return self._truth is not None

    @property
    def has_vendor(self) -> bool:
        return bool(self._vendor)

    def refresh(self) -> int:
        """Frames available (a file is read whole when opened)."""
        return self._n

    def _span(self, start: int, stop: int | None) -> tuple[int, int]:
        stop = self._n if stop is None else min(stop, self._n)
        return max(0, min(start, stop)), stop

    def frames(self, start: int = 0, stop: int | None = None, *, truth: bool = True) -> Frame:
        """Frames ``start:stop`` as one batch (with their truth when recorded and ``truth``)."""
        start, stop = self._span(start, stop)
        batch = self._mem[start:stop]
        if truth and self._truth is not None:
            batch = Frame(batch.wavelengths, batch.timestamp, batch.sequence, batch.powers, batch.status,
                          self._truth[start:stop])
        return batch

    def truth(self, start: int = 0, stop: int | None = None, fields: Sequence[str] | None = None) -> Truth | None:
        """Truth of frames ``start:stop`` (positions and material frames), or None without one."""
        if self._truth is None:
            return None
        start, stop = self._span(start, stop)
        return self._truth[start:stop]

    def vendor(self, start: int = 0, stop: int | None = None) -> tuple:
        """The interrogator's own reconstruction of frames ``start:stop``, one VendorArrays per sensor."""
        start, stop = self._span(start, stop)
        return tuple(a[start:stop] for a in self._vendor)

    def received(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """When the live loop received frames ``start:stop`` (the messages' log time), s since the epoch."""
        start, stop = self._span(start, stop)
        return self._log_time[start:stop] * 1e-9

    def chunks(self, size: int = 1024, *, truth: bool = True) -> Iterator[tuple[int, Frame]]:
        """(start, batch) for consecutive slices of ``size`` frames."""
        for start in range(0, self._n, max(1, size)):
            yield start, self.frames(start, start + size, truth=truth)

    def close(self) -> None:
        pass

    def __enter__(self) -> McapRecording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


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
