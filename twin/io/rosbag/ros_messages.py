"""The ROS 2 messages of a twin MCAP recording: their definitions, and CDR encoding/decoding as numpy batches.

Standard messages (the definitions ROS 2 ships, repeated in each schema as rosbag2 writes them):
``nav_msgs/msg/Path`` (the shape, the truth), ``geometry_msgs/msg/PoseStamped`` (the tip). Two of the project's
own, package ``catheter_twin_msgs`` (their text: :data:`FBG_WAVELENGTHS_MSG`, :data:`FBG_VENDOR_SHAPE_MSG`;
docs/ros.md): ``FbgWavelengths`` (one interrogator sample: gratings × cores in nm, the sequence number, the peak
status) and ``FbgVendorShape`` (one sensor block of the interrogator's own reconstruction).

Encoding: CDR as ROS 2 writes it (XCDR1, little endian: the 4-byte encapsulation header ``00 01 00 00``, then
each primitive aligned to its size counted from after that header; a string is a uint32 length including its
NUL, the bytes and the NUL; a sequence a uint32 count, then its elements). A message of given string lengths and
sequence counts has a fixed layout, so a batch of n messages is one (n, size) byte array filled and read by
column (:class:`Layout`): no Python work per frame or per point, only per message to hand its bytes to the
container. Decoding checks that a message has the layout its own lengths and counts imply (else ValueError).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = [
    "FBG_VENDOR_SHAPE_MSG",
    "FBG_WAVELENGTHS_MSG",
    "SCHEMAS",
    "Layout",
    "decode_path",
    "decode_vendor",
    "decode_wavelengths",
    "encode_path",
    "encode_pose",
    "encode_vendor",
    "encode_wavelengths",
    "stamps",
]

CDR_LE = b"\x00\x01\x00\x00"

TIME_MSG = "int32 sec\nuint32 nanosec\n"
HEADER_MSG = "builtin_interfaces/Time stamp\nstring frame_id\n"
POINT_MSG = "float64 x\nfloat64 y\nfloat64 z\n"
QUATERNION_MSG = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
POSE_MSG = "Point position\nQuaternion orientation\n"
POSE_STAMPED_MSG = "std_msgs/Header header\nPose pose\n"
PATH_MSG = "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n"

FBG_WAVELENGTHS_MSG = """\
# One sample of a multi-core FBG interrogator (catheter-twin, docs/ros.md).
# header.stamp: the acquisition time (the interrogator's clock); header.frame_id: "fiber_base".
std_msgs/Header header
float64 acquisition_time   # s, the source's clock as recorded (NaN when unknown; header.stamp is then 0)
int64 sequence             # the interrogator's sample number (-1 when unknown); a gap means lost samples
uint32 n_gratings
uint32 n_cores
float64[] wavelengths      # peak wavelengths, nm, n_gratings x n_cores grating-major; NaN where missing
float32[] powers           # peak powers as reported (NaN when not reported), same order
uint8[] status             # peak status bits, same order: 0 ok, 1 missing, 2 out of slot, 4 channel error,
                           # 8 invalid value
"""

FBG_VENDOR_SHAPE_MSG = """\
# One sensor block of the interrogator's own reconstruction (ILLumiSense), SI (catheter-twin, docs/ros.md).
# header.stamp: the frame's; header.frame_id: "fbg_vendor" (the interrogator's frame, x along the fibre).
std_msgs/Header header
uint32 sensor              # the block's index in the record
float64 spacing            # arc length between the shape points, m
float64[] curvature        # curvature magnitude at the sensor's gratings, 1/m
float64[] angle            # bending direction at the gratings, rad
geometry_msgs/Point[] points   # the shape, m, from arc length 0 every `spacing`
"""

_RULE = "=" * 80


def _schema(main: str, deps: list[tuple[str, str]]) -> bytes:
    parts = [main] + [f"{_RULE}\nMSG: {name}\n{text}" for name, text in deps]
    return "\n".join(parts).encode()


_HEADER_DEPS = [("std_msgs/Header", HEADER_MSG), ("builtin_interfaces/Time", TIME_MSG)]
_POSE_DEPS = [("geometry_msgs/Pose", POSE_MSG), ("geometry_msgs/Point", POINT_MSG),
              ("geometry_msgs/Quaternion", QUATERNION_MSG)]

#: type name → the schema text rosbag2 stores (the definition, then each dependency after a rule)
SCHEMAS: dict[str, bytes] = {
    "nav_msgs/msg/Path": _schema(PATH_MSG, [*_HEADER_DEPS, ("geometry_msgs/PoseStamped", POSE_STAMPED_MSG),
                                            *_POSE_DEPS]),
    "geometry_msgs/msg/PoseStamped": _schema(POSE_STAMPED_MSG, [*_HEADER_DEPS, *_POSE_DEPS]),
    "catheter_twin_msgs/msg/FbgWavelengths": _schema(FBG_WAVELENGTHS_MSG, _HEADER_DEPS),
    "catheter_twin_msgs/msg/FbgVendorShape": _schema(FBG_VENDOR_SHAPE_MSG,
                                                     [*_HEADER_DEPS, ("geometry_msgs/Point", POINT_MSG)]),
}


# ------------------------------------------------------------------------------------------------ layout
@dataclass
class Layout:
    """Byte offsets of the fields of one CDR message of fixed string lengths and sequence counts.

    ``fields[name] = (offset, dtype, count)``; offsets count from the start of the message (the encapsulation
    header included); ``size`` is the message's length in bytes.
    """

    fields: dict
    size: int

    @classmethod
    def build(cls, spec: list[tuple[str, str, int]]) -> Layout:
        """``spec``: (name, dtype code, count) in order; dtype ``"str"`` takes count = the text's length (its
        uint32 length field is ``name + ".len"``); a name ending in ``"#"`` is a uint32 sequence count."""
        fields: dict = {}
        pos = 0  # from after the encapsulation header

        def put(name, dtype, count):
            nonlocal pos
            size = np.dtype(dtype).itemsize
            pos += -pos % size
            fields[name] = (4 + pos, np.dtype(dtype), count)
            pos += size * count

        for name, code, count in spec:
            if code == "str":
                put(name + ".len", "<u4", 1)
                put(name, "u1", count + 1)
            elif count == 0:  # an empty sequence's elements: no bytes, no alignment
                fields[name] = (4 + pos, np.dtype(code), 0)
            else:
                put(name, code, count)
        return cls(fields, 4 + pos)

    def empty(self, n: int) -> np.ndarray:
        buf = np.zeros((n, self.size), np.uint8)
        buf[:, :4] = np.frombuffer(CDR_LE, np.uint8)
        return buf

    def put(self, buf: np.ndarray, name: str, values) -> None:
        """Write ``values`` (broadcast to (n, count)) into field ``name`` of every row of ``buf``."""
        off, dtype, count = self.fields[name]
        if count == 0:
            return
        v = np.asarray(values, dtype=dtype)
        # a scalar or one row is the same for every message; else one row per message
        v = np.broadcast_to(v, (len(buf), count)) if v.ndim == 0 or v.shape == (count,) else v.reshape(len(buf), count)
        v = np.ascontiguousarray(v)
        buf[:, off:off + count * dtype.itemsize] = v.view(np.uint8)

    def get(self, buf: np.ndarray, name: str) -> np.ndarray:
        """Field ``name`` of every row, shape (n, count)."""
        off, dtype, count = self.fields[name]
        return np.ascontiguousarray(buf[:, off:off + count * dtype.itemsize]).view(dtype)


def _header(name: str, frame_id_len: int) -> list[tuple[str, str, int]]:
    return [(f"{name}sec", "<i4", 1), (f"{name}nanosec", "<u4", 1), (f"{name}frame_id", "str", frame_id_len)]


def _put_header(lay: Layout, buf: np.ndarray, prefix: str, frame_id: bytes, sec, nsec) -> None:
    lay.put(buf, f"{prefix}sec", sec)
    lay.put(buf, f"{prefix}nanosec", nsec)
    lay.put(buf, f"{prefix}frame_id.len", len(frame_id) + 1)
    lay.put(buf, f"{prefix}frame_id", np.frombuffer(frame_id + b"\0", np.uint8))


def stamps(t) -> tuple[np.ndarray, np.ndarray]:
    """(sec int32, nanosec uint32) of times t, s (NaN → 0, 0), rounded to the nanosecond."""
    ns = np.rint(np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0) * 1e9).astype(np.int64)
    return (ns // 1_000_000_000).astype(np.int32), (ns % 1_000_000_000).astype(np.uint32)


def _frame_id(buf: np.ndarray, lay: Layout, prefix: str = "") -> str:
    off, _, count = lay.fields[f"{prefix}frame_id"]
    return bytes(buf[0, off:off + count - 1]).decode("utf-8", "replace")


def _rows(payloads: list[bytes], what: str) -> np.ndarray:
    """Messages of one length as an (n, size) byte array (ValueError when the lengths differ)."""
    sizes = {len(p) for p in payloads}
    if len(sizes) != 1:
        raise ValueError(f"{what}: messages of different lengths in one batch")
    buf = np.frombuffer(b"".join(payloads), np.uint8).reshape(len(payloads), -1)
    if buf.shape[1] < 12 or bytes(buf[0, :4]) != CDR_LE or np.any(buf[:, :4] != buf[0, :4]):
        raise ValueError(f"{what}: not little-endian CDR")
    return buf


def _u32(buf: np.ndarray, off: int) -> np.ndarray:
    if buf.shape[1] < off + 4:
        raise ValueError("message too short")
    return np.ascontiguousarray(buf[:, off:off + 4]).view("<u4")[:, 0]


def _one(values: np.ndarray, what: str) -> int:
    if values.size == 0 or np.any(values != values[0]):
        raise ValueError(f"{what} differs between the messages of one batch")
    return int(values[0])


def _check(lay: Layout, buf: np.ndarray, what: str) -> None:
    if buf.shape[1] != lay.size:
        raise ValueError(f"{what}: {buf.shape[1]} bytes, its fields take {lay.size}")


# ------------------------------------------------------------------------------------------------ Path
@lru_cache(maxsize=64)
def _path_layout(frame_id_len: int, m: int) -> tuple[Layout, np.ndarray, np.ndarray, np.ndarray]:
    """The Path layout, and byte indices of every pose's stamp (m, 8), position (m, 24), orientation (m, 32)."""
    spec = [*_header("", frame_id_len), ("poses#", "<u4", 1)]
    for k in range(m):
        spec += [*_header(f"p{k}.", frame_id_len), (f"p{k}.position", "<f8", 3), (f"p{k}.orientation", "<f8", 4)]
    lay = Layout.build(spec)

    def idx(part: str, nbytes: int) -> np.ndarray:
        return np.array([lay.fields[f"p{k}.{part}"][0] for k in range(m)], np.int64)[:, None] + np.arange(nbytes)

    stamp_idx = idx("sec", 8)
    pos_idx, quat_idx = idx("position", 24), idx("orientation", 32)
    return lay, stamp_idx, pos_idx, quat_idx


def encode_path(positions: np.ndarray, quaternions: np.ndarray | None, t, frame_id: str) -> list[bytes]:
    """nav_msgs/Path messages, one per row.

    Parameters
    ----------
    positions : ndarray (n, m, 3)
        Pose positions, m.
    quaternions : ndarray (n, m, 4) or None
        Orientations (x, y, z, w); None: identity.
    t : array_like (n,)
        Header stamps (of the path and of each pose), s.
    frame_id : str
    """
    p = np.asarray(positions, dtype="<f8")
    n, m = p.shape[:2]
    fid = frame_id.encode()
    lay, stamp_idx, pos_idx, quat_idx = _path_layout(len(fid), m)
    buf = lay.empty(n)
    sec, nsec = stamps(t)
    _put_header(lay, buf, "", fid, sec, nsec)
    lay.put(buf, "poses#", m)
    if n == 0:
        return []
    if m:
        # every pose repeats the path's header (stamp, frame_id): 12 + len + 1 contiguous bytes from offset 4
        head = buf[:, 4:lay.fields["frame_id"][0] + len(fid) + 1]
        buf[:, stamp_idx[:, :1] + np.arange(head.shape[1])] = head[:, None, :]
        buf[:, pos_idx] = np.ascontiguousarray(p).view(np.uint8).reshape(n, m, 24)
        if quaternions is None:
            q = np.zeros((n, m, 4))
            q[..., 3] = 1.0
        else:
            q = np.asarray(quaternions, dtype="<f8")
        buf[:, quat_idx] = np.ascontiguousarray(q, dtype="<f8").view(np.uint8).reshape(n, m, 32)
    raw = buf.tobytes()
    return [raw[i * lay.size:(i + 1) * lay.size] for i in range(n)]


def decode_path(payloads: list[bytes], what: str = "nav_msgs/Path") -> dict:
    """Decode Path messages of one layout (same frame_id, pose count and per-pose frame_ids).

    Returns
    -------
    dict
        ``frame_id`` str, ``sec``/``nanosec`` (n,), ``positions`` (n, m, 3) m, ``quaternions`` (n, m, 4) xyzw.
    """
    buf = _rows(payloads, what)
    fid_len = _one(_u32(buf, 12), f"{what}: frame_id") - 1
    count_off = 4 + ((8 + 4 + fid_len + 1) + (-(8 + 4 + fid_len + 1) % 4))
    m = _one(_u32(buf, count_off), f"{what}: pose count")
    if m > buf.shape[1]:
        raise ValueError(f"{what}: pose count {m} exceeds the message")
    lay, _, pos_idx, quat_idx = _path_layout(fid_len, m)
    _check(lay, buf, what)
    for k in (0, m - 1) if m else ():
        if np.any(lay.get(buf, f"p{k}.frame_id.len")[:, 0] != fid_len + 1):
            raise ValueError(f"{what}: poses with another frame_id length than the path's (not twin's layout)")
    return {
        "frame_id": _frame_id(buf, lay),
        "sec": lay.get(buf, "sec")[:, 0],
        "nanosec": lay.get(buf, "nanosec")[:, 0],
        "positions": np.ascontiguousarray(buf[:, pos_idx]).view("<f8").reshape(len(buf), m, 3),
        "quaternions": np.ascontiguousarray(buf[:, quat_idx]).view("<f8").reshape(len(buf), m, 4),
    }


# ------------------------------------------------------------------------------------------------ PoseStamped
@lru_cache(maxsize=8)
def _pose_layout(frame_id_len: int) -> Layout:
    return Layout.build([*_header("", frame_id_len), ("position", "<f8", 3), ("orientation", "<f8", 4)])


def encode_pose(positions: np.ndarray, quaternions: np.ndarray, t, frame_id: str) -> list[bytes]:
    """geometry_msgs/PoseStamped messages: positions (n, 3) m, quaternions (n, 4) xyzw, stamps t (n,) s."""
    fid = frame_id.encode()
    lay = _pose_layout(len(fid))
    n = len(positions)
    buf = lay.empty(n)
    _put_header(lay, buf, "", fid, *stamps(t))
    lay.put(buf, "position", positions)
    lay.put(buf, "orientation", quaternions)
    raw = buf.tobytes()
    return [raw[i * lay.size:(i + 1) * lay.size] for i in range(n)]


# ------------------------------------------------------------------------------------------------ FbgWavelengths
@lru_cache(maxsize=8)
def _wavelengths_layout(frame_id_len: int, k: int) -> Layout:
    return Layout.build([*_header("", frame_id_len), ("acquisition_time", "<f8", 1), ("sequence", "<i8", 1),
                         ("n_gratings", "<u4", 1), ("n_cores", "<u4", 1), ("wavelengths#", "<u4", 1),
                         ("wavelengths", "<f8", k), ("powers#", "<u4", 1), ("powers", "<f4", k),
                         ("status#", "<u4", 1), ("status", "u1", k)])


def encode_wavelengths(wavelengths: np.ndarray, timestamp, sequence, powers: np.ndarray | None,
                       status: np.ndarray | None, frame_id: str = "fiber_base") -> list[bytes]:
    """catheter_twin_msgs/FbgWavelengths messages of a batch: wavelengths (n, g, c) nm, timestamps (n,) s,
    sequence numbers (n,), powers and status (n, g, c) or None (NaN powers, status 0 or MISSING where NaN)."""
    w = np.asarray(wavelengths, dtype=np.float64)
    n, g, c = w.shape
    fid = frame_id.encode()
    lay = _wavelengths_layout(len(fid), g * c)
    buf = lay.empty(n)
    t = np.asarray(timestamp, dtype=np.float64)
    _put_header(lay, buf, "", fid, *stamps(t))
    lay.put(buf, "acquisition_time", t.reshape(n, 1))
    lay.put(buf, "sequence", np.asarray(sequence, dtype=np.int64).reshape(n, 1))
    lay.put(buf, "n_gratings", g)
    lay.put(buf, "n_cores", c)
    for name in ("wavelengths#", "powers#", "status#"):
        lay.put(buf, name, g * c)
    lay.put(buf, "wavelengths", w.reshape(n, -1))
    lay.put(buf, "powers", np.full((n, g * c), np.nan) if powers is None else np.asarray(powers).reshape(n, -1))
    st = np.isnan(w).astype(np.uint8) if status is None else np.asarray(status, np.uint8)
    lay.put(buf, "status", st.reshape(n, -1))
    raw = buf.tobytes()
    return [raw[i * lay.size:(i + 1) * lay.size] for i in range(n)]


def decode_wavelengths(payloads: list[bytes], what: str = "FbgWavelengths") -> dict:
    """Decode FbgWavelengths messages of one layout: ``timestamp`` (n,) s, ``sequence`` (n,), ``wavelengths``
    and ``powers`` (n, g, c) float64, ``status`` (n, g, c) uint8, ``frame_id``."""
    buf = _rows(payloads, what)
    fid_len = _one(_u32(buf, 12), f"{what}: frame_id") - 1
    probe = _wavelengths_layout(fid_len, 0)
    g = _one(probe.get(buf, "n_gratings")[:, 0], f"{what}: n_gratings")
    c = _one(probe.get(buf, "n_cores")[:, 0], f"{what}: n_cores")
    if g * c > buf.shape[1]:
        raise ValueError(f"{what}: {g} gratings × {c} cores exceed the message")
    lay = _wavelengths_layout(fid_len, g * c)
    _check(lay, buf, what)
    for name in ("wavelengths#", "powers#", "status#"):
        if np.any(lay.get(buf, name)[:, 0] != g * c):
            raise ValueError(f"{what}: {name[:-1]} count is not n_gratings × n_cores")
    n = len(buf)
    return {"frame_id": _frame_id(buf, lay), "timestamp": lay.get(buf, "acquisition_time")[:, 0],
            "sequence": lay.get(buf, "sequence")[:, 0],
            "wavelengths": lay.get(buf, "wavelengths").reshape(n, g, c),
            "powers": lay.get(buf, "powers").astype(np.float64).reshape(n, g, c),
            "status": lay.get(buf, "status").reshape(n, g, c)}


# ------------------------------------------------------------------------------------------------ FbgVendorShape
@lru_cache(maxsize=16)
def _vendor_layout(frame_id_len: int, G: int, N: int) -> Layout:
    return Layout.build([*_header("", frame_id_len), ("sensor", "<u4", 1), ("spacing", "<f8", 1),
                         ("curvature#", "<u4", 1), ("curvature", "<f8", G), ("angle#", "<u4", 1),
                         ("angle", "<f8", G), ("points#", "<u4", 1), ("points", "<f8", 3 * N)])


def encode_vendor(sensor: int, curvature: np.ndarray, angle: np.ndarray, points: np.ndarray, spacing: float, t,
                  frame_id: str = "fbg_vendor") -> list[bytes]:
    """catheter_twin_msgs/FbgVendorShape messages of one sensor over n frames: curvature and angle (n, G),
    points (n, N, 3) m, stamps t (n,) s."""
    curvature = np.asarray(curvature, dtype=np.float64)
    n, G = curvature.shape
    N = np.shape(points)[1]
    fid = frame_id.encode()
    lay = _vendor_layout(len(fid), G, N)
    buf = lay.empty(n)
    _put_header(lay, buf, "", fid, *stamps(t))
    lay.put(buf, "sensor", sensor)
    lay.put(buf, "spacing", spacing)
    lay.put(buf, "curvature#", G)
    lay.put(buf, "angle#", G)
    lay.put(buf, "points#", N)
    lay.put(buf, "curvature", curvature)
    lay.put(buf, "angle", angle)
    lay.put(buf, "points", np.asarray(points, dtype=np.float64).reshape(n, -1))
    raw = buf.tobytes()
    return [raw[i * lay.size:(i + 1) * lay.size] for i in range(n)]


def decode_vendor(payloads: list[bytes], what: str = "FbgVendorShape") -> dict:
    """Decode FbgVendorShape messages of one layout: ``sensor`` (n,), ``spacing`` (n,) m, ``curvature`` and
    ``angle`` (n, G), ``points`` (n, N, 3) m."""
    buf = _rows(payloads, what)
    fid_len = _one(_u32(buf, 12), f"{what}: frame_id") - 1
    probe = _vendor_layout(fid_len, 0, 0)
    G = _one(probe.get(buf, "curvature#")[:, 0], f"{what}: grating count")
    if 2 * G * 8 > buf.shape[1]:
        raise ValueError(f"{what}: {G} gratings exceed the message")
    probe = _vendor_layout(fid_len, G, 0)
    N = _one(probe.get(buf, "points#")[:, 0], f"{what}: point count")
    if N * 24 > buf.shape[1]:
        raise ValueError(f"{what}: {N} points exceed the message")
    lay = _vendor_layout(fid_len, G, N)
    _check(lay, buf, what)
    n = len(buf)
    return {"sensor": lay.get(buf, "sensor")[:, 0], "spacing": lay.get(buf, "spacing")[:, 0],
            "curvature": lay.get(buf, "curvature"), "angle": lay.get(buf, "angle"),
            "points": lay.get(buf, "points").reshape(n, N, 3)}
