"""meshcat's command format, written out: the few commands and three.js objects the viewer sends.

A command travels over meshcat's zmq socket as three frames: its type (``set_object``, ``set_transform``,
``set_property``, ``delete``), its path, and the command itself as a msgpack map — which the server forwards
unchanged to the browser, where meshcat's viewer decodes it. Objects are three.js JSON (format 4.5: one
object, its geometry and material by uuid); numeric arrays travel as msgpack extension types that meshcat's
viewer turns into typed arrays (0x12 Uint8Array, 0x16 Uint32Array, 0x17 Float32Array), column-major, i.e. the
x y z of each vertex together. Paths are absolute in the browser's scene tree: ``/Cameras``, ``/Grid`` and
``/Axes`` are meshcat's own nodes, ``/twin`` ours.

Only ``umsgpack`` (a dependency of meshcat) is needed here; no meshcat class is used.
"""

from __future__ import annotations

import uuid

import numpy as np

__all__ = ["Command", "delete", "mesh", "points", "set_object", "set_property", "set_transform"]

_EXT = {np.dtype(np.uint8): 0x12, np.dtype(np.uint32): 0x16, np.dtype(np.float32): 0x17}

#: (type, path, packed command): what :class:`twin.viewer.client.SceneClient` sends
Command = tuple[str, str, bytes]


def _umsgpack():
    import umsgpack

    return umsgpack


def _array(a: np.ndarray, dtype) -> dict:
    """A (n, k) array as meshcat's buffer attribute: k values per item, typed array in msgpack's ext."""
    a = np.ascontiguousarray(np.asarray(a, dtype=dtype))
    return {"itemSize": int(a.shape[1]), "type": {0x12: "Uint8Array", 0x16: "Uint32Array", 0x17: "Float32Array"}[
        _EXT[a.dtype]], "array": _umsgpack().Ext(_EXT[a.dtype], a.tobytes()), "normalized": False}


def path_of(path: str) -> str:
    return "/" + path.strip("/")


def _pack(kind: str, path: str, **fields) -> Command:
    full = path_of(path)
    return kind, full, _umsgpack().packb({"type": kind, "path": full, **fields})


def material(kind: str = "MeshPhongMaterial", color: int = 0xFFFFFF, *, opacity: float = 1.0,
             vertex_colors: bool = False, side: int = 2, **extra) -> dict:
    """A three.js material: ``MeshPhongMaterial`` (lit), ``MeshBasicMaterial`` (unlit), ``PointsMaterial``."""
    data = {"uuid": str(uuid.uuid4()), "type": kind, "color": int(color), "opacity": float(opacity),
            "transparent": bool(opacity < 1.0), "vertexColors": bool(vertex_colors), "side": side}
    data.update(extra)
    return data


def _object(kind: str, geometry: dict, mat: dict, render_order: int = 0) -> dict:
    return {"metadata": {"version": 4.5, "type": "Object"}, "geometries": [geometry], "materials": [mat],
            "object": {"uuid": str(uuid.uuid4()), "type": kind, "geometry": geometry["uuid"],
                       "material": mat["uuid"], "matrix": np.eye(4).ravel().tolist(),
                       "renderOrder": int(render_order)}}


def mesh(vertices, faces, mat: dict, colors=None, render_order: int = 0) -> dict:
    """A triangle mesh object: vertices (n, 3), faces (m, 3) indices, optional per-vertex RGB (n, 3) in [0, 1]."""
    attributes = {"position": _array(vertices, np.float32)}
    if colors is not None:
        attributes["color"] = _array(colors, np.float32)
    geometry = {"uuid": str(uuid.uuid4()), "type": "BufferGeometry",
                "data": {"attributes": attributes, "index": _array(np.asarray(faces).reshape(-1, 1), np.uint32)}}
    return _object("Mesh", geometry, mat, render_order)


def points(positions, colors, size: float, render_order: int = 0) -> dict:
    """Square markers of ``size`` (scene units) at positions (n, 3), drawn over everything else."""
    geometry = {"uuid": str(uuid.uuid4()), "type": "BufferGeometry",
                "data": {"attributes": {"position": _array(positions, np.float32),
                                        "color": _array(colors, np.float32)}}}
    mat = {"uuid": str(uuid.uuid4()), "type": "PointsMaterial", "color": 0xFFFFFF, "size": float(size),
           "vertexColors": True, "depthTest": False, "transparent": True}
    return _object("Points", geometry, mat, render_order)


def set_object(path: str, obj: dict) -> Command:
    return _pack("set_object", path, object=obj)


def set_transform(path: str, matrix) -> Command:
    """Place the node at ``path``: a 4×4 homogeneous matrix (sent column-major, as three.js reads it)."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"set_transform: expected a 4×4 matrix, got {m.shape}")
    return _pack("set_transform", path, matrix=m.T.ravel().tolist())


def set_property(path: str, name: str, value) -> Command:
    return _pack("set_property", path, property=name, value=value)


def delete(path: str) -> Command:
    return _pack("delete", path)
