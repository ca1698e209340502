"""Writing a twin MCAP recording: ROS 2 messages (CDR) in a rosbag2-compatible MCAP file (``twin live --record
run.mcap``, ``twin export REC.h5 run.mcap``).

What a file holds (layout and message definitions: docs/ros.md):

==========================  ===========================================  ===============================================
topic                       type                                         per frame
==========================  ===========================================  ===============================================
``/fbg/wavelengths``        ``catheter_twin_msgs/msg/FbgWavelengths``    every frame: gratings × cores (nm), the
                                                                         sequence number, the peak status
``/catheter/shape``         ``nav_msgs/msg/Path``                        every frame with a usable reconstruction: one
                                                                         pose per output point, orientation = the
                                                                         material frame [d1 d2 d3], frame ``fiber_base``
``/catheter/tip``           ``geometry_msgs/msg/PoseStamped``            the same frames: the last pose
``/catheter/truth``         ``nav_msgs/msg/Path``                        frames with a truth (the simulator), frame
                                                                         ``world``; identity orientation without frames
``/fbg/vendor_shape``       ``catheter_twin_msgs/msg/FbgVendorShape``    one per sensor block the interrogator sent
==========================  ===========================================  ===============================================

Header stamps are the frames' timestamps (the source's clock; the exact float64 also rides in
``FbgWavelengths.acquisition_time``); a message's MCAP log time is when the live loop received it (ns since the
Unix epoch), its MCAP ``sequence`` the frame's row in the recording (0, 1, …), which ties the messages of one frame
together. The file's profile is ``ros2``, schemas are ``ros2msg`` text with their dependencies, channels carry
``offered_qos_profiles``, and a ``rosbag2`` metadata record with ``serialized_metadata`` (the bag's
metadata.yaml content) is written on close, as rosbag2's MCAP storage does; so ``ros2 bag info``, rosbags and
Foxglove open the file as a rosbag2. The fibre model and calibration are attachments (``fiber.toml``,
``calibration.toml``, TOML as ``twin`` writes them); metadata record ``catheter_twin`` holds the format, source
URL, nominal rate, creation time and software, and ``catheter_twin_truth`` the truth's arc lengths.

Durability: messages are gathered in chunks (LZ4, each with a CRC; zstd packs the float64 poses 10 % smaller but
3–5 times slower, too slow for 17 MB/s of poses at 1 kHz) that are written when they reach 1 MiB or
``flush_interval`` seconds after the last write, and on close; a writer killed at any point leaves a file readable
up to its last whole chunk (no summary: it reads as not closed cleanly, :mod:`twin.io.rosbag.bag_reader`).
"""

from __future__ import annotations

import datetime as _dt
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twin import so3
from twin.calibration import Calibration
from twin.extras import require
from twin.fiber import FiberModel
from twin.frames import Frame, Shape, VendorArrays, vendor_rows
from twin.io.rosbag import ros_messages as msgs

__all__ = ["FORMAT", "TOPICS", "McapRecorder"]

FORMAT = "twin-mcap"
VERSION = 1

#: topic → message type
TOPICS: dict[str, str] = {
    "/fbg/wavelengths": "catheter_twin_msgs/msg/FbgWavelengths",
    "/catheter/shape": "nav_msgs/msg/Path",
    "/catheter/tip": "geometry_msgs/msg/PoseStamped",
    "/catheter/truth": "nav_msgs/msg/Path",
    "/fbg/vendor_shape": "catheter_twin_msgs/msg/FbgVendorShape",
}

#: the QoS every topic is offered with (reliable, volatile, keep last 100), in rosbag2's metadata form (JSON is YAML)
_INFINITE = {"sec": 2147483647, "nsec": 4294967295}
QOS = [{"history": "keep_last", "depth": 100, "reliability": "reliable", "durability": "volatile",
        "deadline": _INFINITE, "lifespan": _INFINITE, "liveliness": "automatic",
        "liveliness_lease_duration": _INFINITE, "avoid_ros_namespace_conventions": False}]
_QOS_TEXT = json.dumps(QOS)


class McapRecorder:
    """Appends frames (and their reconstructions) to a rosbag2-compatible MCAP file; a live-loop sink.

    ``recorder(frames, shapes, status)`` appends the batch: its wavelengths, truth and vendor blocks, and the
    usable shapes with their tips.

    Parameters
    ----------
    path : str or Path
        File to create (an existing file is replaced).
    fiber, calibration : optional
        Stored as attachments (TOML).
    source_url : str
    rate : float, optional
        The source's nominal rate, Hz (metadata).
    flush_interval : float
        Write the chunk in progress at least this often, s.
    chunk_size : int
        Bytes of messages per chunk before it is written.

    Attributes
    ----------
    frames_written : int
        Frames appended (on disk after the next flush).
    shapes_written, truth_written, vendor_written : int
        Messages on those topics.
    vendor_dropped : int
        Sensor blocks not stored: of another layout (G, N, spacing) than that sensor's first block in the file,
        as the HDF5 recorder counts them (a reader has one layout per sensor).
    """

    def __init__(self, path: str | Path, *, fiber: FiberModel | None = None, calibration: Calibration | None = None,
                 source_url: str = "", rate: float | None = None, flush_interval: float = 0.5,
                 chunk_size: int = 1 << 20):
        writer = require("mcap.writer", "MCAP recording")
        from twin import __version__

        self.path = Path(path)
        self.flush_interval = float(flush_interval)
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise OSError(f"{self.path}: cannot create the recording ({exc})") from None
        self._w = writer.Writer(self._fh, chunk_size=int(chunk_size), compression=writer.CompressionType.LZ4)
        self._w.start(profile="ros2", library=f"catheter-twin {__version__}")
        self._schemas = {name: self._w.register_schema(name, "ros2msg", text) for name, text in msgs.SCHEMAS.items()}
        self._channels: dict[str, int] = {}
        self._queue: list[tuple] = []  # a batch's messages per topic, written frame by frame by _emit
        self._counts: dict[str, int] = {}
        self._t_first = self._t_last = None
        now = time.time_ns()
        for name, model in (("fiber.toml", fiber), ("calibration.toml", calibration)):
            if model is not None:
                import tomli_w

                self._w.add_attachment(now, now, name, "application/toml", tomli_w.dumps(model.to_dict()).encode())
        self._w.add_metadata("catheter_twin", {
            "format": FORMAT, "version": str(VERSION), "source_url": source_url,
            "rate_hz": repr(float(rate)) if rate else "", "created_utc": _dt.datetime.now(_dt.UTC).isoformat(
                timespec="seconds"), "software": f"twin {__version__}"})
        self._truth_s: np.ndarray | None = None
        self._last_flush = time.monotonic()
        self.frames_written = self.shapes_written = self.truth_written = self.vendor_written = 0
        self.vendor_dropped = 0
        self._vendor_layout: dict[int, tuple] = {}  # (G, N, spacing) of each sensor's first block
        self._closed = False

    # ---------------------------------------------------------------- sink interface
    def __call__(self, frames: Frame, shapes: Shape | None = None, status=None) -> None:
        """The live-loop sink: append a batch (an empty one is a heartbeat: flush when due)."""
        if len(frames):
            self.append(frames, shapes)
        elif time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def append(self, frames: Sequence[Frame] | Frame, shapes: Shape | None = None,
               received: float | np.ndarray | None = None, vendor: Sequence | None = None) -> None:
        """Write a batch: frames (a 1-D batch Frame, a single frame or a sequence of frames) and, optionally,
        their reconstructions (``shapes[i]`` of ``frames[i]``; unusable ones — not finite — are left out).

        ``received``: wall-clock time of the batch, or of each frame (n,), s since the Unix epoch (default now):
        the messages' log time (NaN: now). ``vendor``: the interrogator's blocks of the frames, one
        :class:`~twin.frames.VendorArrays` (n rows) per sensor; default: the batch's :attr:`Frame.vendor`.
        """
        if self._closed:
            raise ValueError(f"{self.path}: recorder is closed")
        items = [frames] if isinstance(frames, Frame) else list(frames)
        if not items:
            return
        batch = Frame.stack(items) if not (len(items) == 1 and items[0].batch_shape) else items[0]
        if vendor is None:
            vendor = vendor_rows(batch)
        n = len(batch)
        rows = self.frames_written + np.arange(n)
        now = time.time_ns()
        log = np.full(n, now, np.int64) if received is None else np.where(
            np.isfinite(received), np.rint(np.nan_to_num(np.broadcast_to(received, (n,))) * 1e9), now).astype(np.int64)
        t = batch.timestamp
        self._write("/fbg/wavelengths", msgs.encode_wavelengths(batch.wavelengths, t, batch.sequence, batch.powers,
                                                                batch.status), rows, log)
        if shapes is not None:
            ok = np.all(np.isfinite(shapes.positions.reshape(len(shapes.positions), -1)), axis=1)[:n]
            sel = np.flatnonzero(ok)
            if sel.size:
                q = so3.to_quaternion(shapes.frames[sel])
                self._write("/catheter/shape", msgs.encode_path(shapes.positions[sel], q, t[sel], "fiber_base"),
                            rows[sel], log[sel])
                self._write("/catheter/tip", msgs.encode_pose(shapes.positions[sel, -1], q[:, -1], t[sel],
                                                              "fiber_base"), rows[sel], log[sel])
                self.shapes_written += sel.size
        if batch.truth is not None:
            self._write_truth(batch, rows, log)
        if vendor:
            self._write_vendor(vendor, t, rows, log)
        self._emit()
        self.frames_written += n
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def _write(self, topic: str, payloads: list[bytes], rows: np.ndarray, log: np.ndarray) -> None:
        """Queue a topic's messages of the batch (:meth:`_emit` writes them)."""
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = self._w.register_channel(
                topic, "cdr", self._schemas[TOPICS[topic]], {"offered_qos_profiles": _QOS_TEXT})
            self._counts[topic] = 0
        self._queue.append((np.full(len(payloads), ch), rows, log, payloads))
        self._counts[topic] += len(payloads)
        if len(log):
            self._t_first = int(log.min()) if self._t_first is None else min(self._t_first, int(log.min()))
            self._t_last = int(log.max()) if self._t_last is None else max(self._t_last, int(log.max()))

    def _emit(self) -> None:
        """Write the queued messages frame by frame (a frame's wavelengths, shape, tip, truth, sensor blocks
        together), so that a file cut anywhere loses whole frames, and its readers meet a frame's messages at once."""
        if not self._queue:
            return
        ch, rows, log = (np.concatenate([q[i] for q in self._queue]) for i in range(3))
        payloads = [p for q in self._queue for p in q[3]]
        self._queue.clear()
        add = self._w.add_message
        for i in np.argsort(rows, kind="stable").tolist():  # stable: topics keep their order within a frame
            t = int(log[i])
            add(channel_id=int(ch[i]), log_time=t, data=payloads[i], publish_time=t, sequence=int(rows[i]) & 0xFFFFFFFF)

    def _write_truth(self, batch: Frame, rows: np.ndarray, log: np.ndarray) -> None:
        truth = batch.truth
        sel = np.flatnonzero(truth.all_present)
        if not sel.size:
            return
        if self._truth_s is None:
            self._truth_s = np.asarray(truth.s, dtype=np.float64)
            self._w.add_metadata("catheter_twin_truth", {"s": json.dumps(self._truth_s.tolist())})
        elif not np.array_equal(self._truth_s, truth.s):
            return  # another layout than the first: not stored (the reader has one arc-length axis)
        q = None if truth.frames is None else so3.to_quaternion(truth.frames[sel])
        self._write("/catheter/truth", msgs.encode_path(truth.positions[sel], q, batch.timestamp[sel], "world"),
                    rows[sel], log[sel])
        self.truth_written += sel.size

    def _write_vendor(self, sensors: Sequence[VendorArrays | None], t: np.ndarray, rows: np.ndarray,
                      log: np.ndarray) -> None:
        """Each sensor's blocks of the batch as one encoded batch; a sensor keeps its first layout (others
        counted in :attr:`vendor_dropped`)."""
        for k, arrays in enumerate(sensors):
            if arrays is None or not arrays.present.any():
                continue
            sel = np.flatnonzero(arrays.present)
            if self._vendor_layout.setdefault(k, arrays.layout) != arrays.layout:
                self.vendor_dropped += sel.size
                continue
            self._write("/fbg/vendor_shape", msgs.encode_vendor(
                k, arrays.curvature[sel], arrays.angle[sel], arrays.positions[sel], arrays.spacing, t[sel]),
                rows[sel], log[sel])
            self.vendor_written += sel.size

    def flush(self) -> None:
        """Write the chunk in progress and flush the file."""
        if not self._closed:
            self._w.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        """Write the rosbag2 metadata, the summary and the footer; close the file."""
        if self._closed:
            return
        self._closed = True
        try:
            self._w.add_metadata("rosbag2", {"serialized_metadata": self._bag_metadata()})
            self._w.finish()
        finally:
            self._fh.close()

    def _bag_metadata(self) -> str:
        """rosbag2's metadata.yaml content for this file (JSON, which is YAML)."""
        start = self._t_first or 0
        info = {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": (self._t_last or 0) - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(self._counts.values()),
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic, "type": TOPICS[topic], "serialization_format": "cdr",
                                    "offered_qos_profiles": QOS, "type_description_hash": ""},
                 "message_count": self._counts[topic]} for topic in self._channels],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": (self._t_last or 0) - start},
                       "message_count": sum(self._counts.values())}],
            "custom_data": {"recorded_by": "catheter-twin"},
            "ros_distro": "",
        }
        return json.dumps({"rosbag2_bagfile_information": info})

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
