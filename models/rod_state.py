"""Reading the catheter rod's state from MuJoCo: centreline, material frames, discrete Darboux vector.

MuJoCo's vertex bodies only translate and the generated twist bodies sit at the origin, so ``xmat`` is not the
material frame (docs/simulation.md §2). Per edge e the frame is rebuilt, vectorised over all edges:

1. tangent t_e from consecutive ``flexvert_xpos``;
2. reference director: ``u_old`` parallel-transported from ``t_old`` to t_e. ``mjData.plastic`` at
   ``flex_plasticadr`` holds, verified by experiment, ``6 n`` numbers interleaved per edge, (t_old, u_old) of
   edge 0, then of edge 1, …, followed by ``n − 1`` reference twists of the interior vertices (MuJoCo docs:
   XMLreference ``flex/elasticity`` "State"). After ``mj_step`` t_old equals the current tangent to 1e-16, so
   the transport is an identity then; it matters after the caller moves vertices by hand. ``plastic`` is zero
   until the first step: the reader then rebuilds the frames the way MuJoCo restarts them (twist-free
   transport along the rod from the clamped edge), in a one-off Python loop;
3. rotated about t_e by the twist-joint angle θ_e (``qpos`` of ``<rod>_twist_<e>`` / ``<rod>_twist``; 0 for
   the clamped edge, which has no joint): d1 = cos θ u + sin θ (t × u), d2 = t × d1, R_e = [d1 d2 t].
   The sign was checked: with +θ, (θ_i − θ_{i−1} + reftwist_i) reproduces the twist of the frames (see below);
   with −θ it is off by 107 rad/m on a twisted helix;
4. a constant roll about the tangent so that d1 of the clamped edge is the x axis of the site ``<rod>_base``
   (MuJoCo chooses the first reference director from the tangent alone: the parent's +y for a rod along +z).

The discrete Darboux vector at interior vertex i is log(R_{i−1}ᵀ R_i) / l̄_i with l̄_i the mean rest length of
the two edges: (κ1, κ2, τ) in the material frame, the body-frame rotation rate u of R' = R û (docs/math.md
§1). Hence the project's curvature vector is (k_x, k_y) = (u2, −u1) = (κ2, −κ1), as docs/simulation.md §2
says; tests/test_models.py checks it against bends of known direction (a tip load along +y gives k_y > 0 and
k_x ≈ 0; the library's "arc", which bends toward +x, gives k_x = +25 1/m).

The twist from the logarithm is not MuJoCo's DER twist (θ_i − θ_{i−1} + reftwist_i)/l̄_i exactly: the rotation
log of "bend by φ about the binormal, then twist by m about the tangent" has axial part m (1 − φ²/12 + …), so
the two differ by a relative φ²/12 (1.07e-3 on the library helix at 2.8 mm segments, φ = 0.113 rad; measured
1.07e-3). Both vanish together, and for a straight rod they agree to rounding.

Cost: the per-edge arithmetic of :meth:`RodReader.read` and :meth:`RodState.frames_at` is compiled
(:mod:`models._rod_kernels`, numba): ≈ 4 µs for 100 segments, where the numpy formulation took ≈ 50 µs. The
sensor-rate read of :class:`RodView` takes the small angles by their series (≈ 1.6 µs; equal to the exact read
to rounding) and keeps its last read while MuJoCo reports the rod asleep and nothing it reads has changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.interpolate import CubicSpline

from models import _rod_kernels
from twin._numba_entry import compiled_entry
from twin.frames import Truth

__all__ = ["RodReader", "RodState", "RodTruth", "RodView", "read_rod", "so3_exp", "so3_log"]


def _log_from_parts(w: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """Rotation vectors (3, n) from the antisymmetric parts w = vee(Q − Qᵀ) (3, n) and traces (n,)."""
    sin2 = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])  # 2 sin φ
    phi = np.arctan2(0.5 * sin2, 0.5 * (trace - 1.0))
    # φ / (2 sin φ) → 1/2 + φ²/12 as φ → 0; the series keeps full precision at a fine rod's small angles.
    big = sin2 > 1e-6
    return w * np.where(big, phi / np.where(big, sin2, 1.0), 0.5 + phi * phi / 12.0)


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (Rodrigues, stable at small angles)."""
    w = np.asarray(rotvec, dtype=np.float64)
    th2 = np.sum(w * w, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-4
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    z = np.zeros_like(wx)
    k = np.stack([np.stack([z, -wz, wy], -1), np.stack([wz, z, -wx], -1), np.stack([-wy, wx, z], -1)], -2)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), for angles below π."""
    r = np.asarray(r, dtype=np.float64)
    w = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]])
    return np.moveaxis(_log_from_parts(w, r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]), 0, -1)


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


class _Interpolator:
    """Interpolation matrices from the interior-vertex grid to query points, cached per query array."""

    def __init__(self, grid: np.ndarray, max_entries: int = 32) -> None:
        self.grid = np.asarray(grid, dtype=np.float64)
        self.max_entries = max_entries
        self._cache: dict[tuple, np.ndarray] = {}
        self._truth_s: np.ndarray | None = None

    def truth_s(self, s: np.ndarray, sensed_length: float) -> np.ndarray:
        """0, the vertices ``s`` inside (0, sensed_length) and sensed_length (one rod: computed once)."""
        if self._truth_s is None:
            inside = s[(s > 0.0) & (s < sensed_length)]
            self._truth_s = np.concatenate([[0.0], inside, [sensed_length]])
            self._truth_s.setflags(write=False)
        return self._truth_s

    def basis(self, s, method: str) -> np.ndarray:
        q = np.ascontiguousarray(s, dtype=np.float64).ravel()
        key = (method, q.tobytes())
        w = self._cache.get(key)
        if w is None:
            if not np.all(np.isfinite(q)):
                raise ValueError(f"RodState: arc lengths must be finite, got {q[~np.isfinite(q)][0]}")
            w = self._build(q, method)
            if len(self._cache) >= self.max_entries:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = w
        return w

    def _build(self, q: np.ndarray, method: str) -> np.ndarray:
        g = self.grid
        qc = np.clip(q, g[0], g[-1])
        eye = np.eye(g.size)
        if method == "cubic":
            w = CubicSpline(g, eye, axis=0, bc_type="not-a-knot")(qc)
        elif method == "linear":
            i = np.clip(np.searchsorted(g, qc, side="right") - 1, 0, g.size - 2)
            a = ((qc - g[i]) / (g[i + 1] - g[i]))[:, None]
            w = (1.0 - a) * eye[i] + a * eye[i + 1]
        else:
            raise ValueError(f"RodState: interpolation method must be 'cubic' or 'linear', got {method!r}")
        w = np.ascontiguousarray(w)
        w.setflags(write=False)
        return w


@dataclass(frozen=True, eq=False)
class RodState:
    """The rod's state at one instant (fibre arc length: s = 0 at the start of the sensed region).

    Attributes
    ----------
    time : float
        ``mjData.time``, s.
    s : ndarray, shape (n_vertices,)
        Rest arc length of each vertex, m (the clamp is at −base_length).
    positions : ndarray, shape (n_vertices, 3)
        Vertex positions (the centreline) in world coordinates, m.
    edge_s : ndarray, shape (n_edges,)
        Arc length of each edge midpoint, m.
    edge_frames : ndarray, shape (n_edges, 3, 3)
        Material frames [d1 d2 d3] (columns, world coordinates) of the edges.
    darboux : ndarray, shape (n_vertices − 2, 3)
        Discrete Darboux vector (κ1, κ2, τ) at the interior vertices ``s[1:-1]``, material frame, 1/m and
        rad/m.
    sensed_length : float
        Length of the sensed region, m (the fibre runs over s ∈ [0, sensed_length]).
    """

    time: float
    s: np.ndarray
    positions: np.ndarray
    edge_s: np.ndarray
    edge_frames: np.ndarray
    darboux: np.ndarray
    sensed_length: float
    _interp: _Interpolator | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self._interp is None:
            object.__setattr__(self, "_interp", _Interpolator(self.s[1:-1]))

    # -- at the vertices --
    @property
    def interior_s(self) -> np.ndarray:
        """Arc length of the interior vertices, where :attr:`darboux` lives, m."""
        return self.s[1:-1]

    @property
    def curvature(self) -> np.ndarray:
        """(k_x, k_y) = (κ2, −κ1) at the interior vertices, 1/m, shape (n_vertices − 2, 2) (docs/math.md §1)."""
        return np.stack([self.darboux[:, 1], -self.darboux[:, 0]], axis=-1)

    @property
    def twist(self) -> np.ndarray:
        """Material twist rate τ at the interior vertices, rad/m."""
        return self.darboux[:, 2]

    # -- anywhere --
    def darboux_at(self, s, method: str = "cubic") -> np.ndarray:
        """Darboux vector (κ1, κ2, τ) at arc lengths ``s`` (any shape), shape (..., 3).

        ``method`` is ``"cubic"`` (not-a-knot cubic spline through the interior vertices) or ``"linear"``.
        Outside the interior vertices the end values are held (the discrete rod has no curvature at its end
        vertices). The interpolation is a fixed linear map of the vertex values for given ``s``; it is built
        once per set of query points and shared by all states of a :class:`RodReader` (the first call costs
        ≈ 0.3 ms, later ones ≈ 5 µs).
        """
        basis = self._interp.basis(s, method)
        q = np.shape(s)
        return (basis @ self.darboux).reshape((*q, 3))

    def curvature_at(self, s, method: str = "cubic") -> np.ndarray:
        """Curvature vector (k_x, k_y) = (κ2, −κ1) at arc lengths ``s``, 1/m, shape (..., 2)."""
        d = self.darboux_at(s, method)
        return np.stack([d[..., 1], -d[..., 0]], axis=-1)

    def twist_at(self, s, method: str = "cubic") -> np.ndarray:
        """Material twist rate τ at arc lengths ``s``, rad/m, shape (...)."""
        return self.darboux_at(s, method)[..., 2]

    def frames_at(self, s) -> np.ndarray:
        """Material frames at arc lengths ``s``, shape (..., 3, 3).

        Geodesic interpolation between the edge frames: between the midpoints of edges e and e+1 the frame
        turns at the constant rate of the Darboux vector of the vertex between them, so the result is
        consistent with :attr:`darboux`. Outside the first/last edge midpoints the end edges' frames are held.
        """
        q = np.asarray(s, dtype=np.float64)
        out = np.empty((q.size, 3, 3))
        _rod_kernels.frames_at(self.edge_s, self.edge_frames, self.darboux, np.ascontiguousarray(q.ravel()), out)
        return out.reshape((*q.shape, 3, 3))

    def positions_at(self, s) -> np.ndarray:
        """Centreline positions at arc lengths ``s`` (linear along the polyline; clamped to the rod), m."""
        q = np.asarray(s, dtype=np.float64)
        out = np.empty((q.size, 3))
        _rod_kernels.positions_at(self.s, self.positions, np.ascontiguousarray(q.ravel()), out)
        return out.reshape((*q.shape, 3))

    def to_truth(
        self,
        grating_s,
        *,
        sample_s=None,
        temperature=None,
        fixture=None,
        method: str = "cubic",
    ) -> Truth:
        """The ground truth for one sample.

        Parameters
        ----------
        grating_s : array_like, shape (n_gratings,)
            Arc length of the gratings, m.
        sample_s : array_like or None
            Where to sample the centreline and frames, m; default: 0, the vertices inside the sensed region,
            and ``sensed_length``.
        temperature, fixture
            Passed through to :class:`twin.frames.Truth`.
        """
        g = np.asarray(grating_s, dtype=np.float64)
        ss = self.truth_s() if sample_s is None else np.asarray(sample_s, dtype=np.float64)
        d = self.darboux_at(g, method)
        return Truth(
            s=ss,
            positions=self.positions_at(ss),
            frames=self.frames_at(ss),
            curvature=np.stack([d[..., 1], -d[..., 0]], axis=-1),
            twist=d[..., 2],
            temperature=temperature,
            fixture=fixture,
        )

    def truth_s(self) -> np.ndarray:
        """The default samples of :meth:`to_truth`: 0, the vertices inside the sensed region and
        ``sensed_length``, m (computed once per rod and shared by its states)."""
        return self._interp.truth_s(self.s, self.sensed_length)


class RodReader:
    """Reads :class:`RodState` of the rod ``name`` from ``mjData``; addresses are looked up once.

    Parameters
    ----------
    model : mujoco.MjModel
    name : str
        The flexcomp's name (:attr:`models.catheter.CatheterSpec.name`).

    Notes
    -----
    The fibre arc length offset comes from the custom numeric ``<name>_s0`` (the clamp's arc length,
    written by :class:`models.catheter.Scene`; 0 when absent) and the sensed length from
    ``<name>_sensed_length`` (default: the rod's length from s = 0).
    """

    def __init__(self, model: mujoco.MjModel, name: str = "cath") -> None:
        fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, name)
        if fid < 0:
            raise KeyError(f"RodReader: model has no rod (flex) named {name!r}")
        if model.flex_dim[fid] != 1:
            raise ValueError(f"RodReader: flex {name!r} has dim {model.flex_dim[fid]}, expected a 1D rod")
        self.name = name
        self.model = model
        va, nv = int(model.flex_vertadr[fid]), int(model.flex_vertnum[fid])
        ea, ne = int(model.flex_edgeadr[fid]), int(model.flex_edgenum[fid])
        if ne != nv - 1:
            raise ValueError(f"RodReader: flex {name!r} is not an open chain ({nv} vertices, {ne} edges)")
        edges = model.flex_edge[ea : ea + ne]
        if not np.array_equal(edges, np.stack([np.arange(ne), np.arange(1, ne + 1)], axis=1)):
            raise ValueError(f"RodReader: flex {name!r}: edges are not ordered 0-1, 1-2, ... along the chain")
        pa = int(model.flex_plasticadr[fid])
        if pa < 0 or model.nplastic < pa + 6 * ne + (ne - 1):
            raise ValueError(
                f"RodReader: flex {name!r} has no rod state in mjData.plastic (needs MuJoCo >= 4.0)"
            )
        self._va, self._nv, self._ne, self._pa = va, nv, ne, pa

        l0 = np.array(model.flexedge_length0[ea : ea + ne], dtype=np.float64)
        s0 = _numeric(model, f"{name}_s0", 0.0)
        s = s0 + np.concatenate([[0.0], np.cumsum(l0)])
        self.s = s
        self.edge_s = 0.5 * (s[:-1] + s[1:])
        self.lbar = 0.5 * (l0[:-1] + l0[1:])
        self._inv_lbar = 1.0 / self.lbar
        self.sensed_length = _numeric(model, f"{name}_sensed_length", float(s[-1]))
        self._interp = _Interpolator(s[1:-1])
        _readonly(self.s, self.edge_s, self.lbar)

        # Twist joint of each edge (none for a clamped edge): qpos addresses gathered once.
        names = [f"{name}_twist_{e}" for e in range(ne - 1)] + [f"{name}_twist"]
        ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names])
        self._tw_edges = np.flatnonzero(ids >= 0)
        self._tw_joints = ids[ids >= 0]
        self._tw_qadr = model.jnt_qposadr[self._tw_joints].astype(np.int64)
        self._all_twist = self._tw_edges.size == ne
        self._theta_buf = np.zeros(ne)
        self._site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{name}_base")
        self._no_site = np.zeros(3)

    @property
    def n_vertices(self) -> int:
        return self._nv

    def interpolation_matrix(self, s, method: str = "cubic") -> np.ndarray:
        """The fixed matrix B (len(s), n_vertices − 2) with :meth:`RodState.darboux_at` (s) = B @ darboux."""
        return self._interp.basis(s, method)

    def _theta(self, data: mujoco.MjData) -> np.ndarray:
        """Twist-joint angle per edge (0 for the clamped edge), rad, in a buffer the reader reuses."""
        if self._all_twist:
            return np.take(data.qpos, self._tw_qadr, out=self._theta_buf)
        self._theta_buf[self._tw_edges] = data.qpos[self._tw_qadr]
        return self._theta_buf

    def _restart_frames(self, t: np.ndarray, data: mujoco.MjData) -> np.ndarray:
        """Reference directors as MuJoCo restarts them (plastic still zero): twist-free from edge 0."""
        if self._site >= 0:
            u = data.site_xmat[self._site].reshape(3, 3)[:, 0].copy()
        else:
            u = np.array([1.0, 0.0, 0.0]) if abs(t[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u -= t[0] * (u @ t[0])
        out = np.empty_like(t)
        out[0] = u / np.linalg.norm(u)
        for e in range(1, self._ne):  # one-off (before the first mj_step): a loop is fine here
            out[e] = _transport(t[e - 1, :, None], t[e, :, None], out[e - 1, :, None])[:, 0]
        return out

    def kernel_inputs(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What :func:`models._rod_kernels.frames_and_darboux` reads from ``data``: vertex positions (n_vertices, 3)
        (a view of ``data``), MuJoCo's reference frames (6 n_edges,), twist angles (n_edges,) (a buffer the reader
        reuses) and the base site's x axis (3,); before the first step, the frames as MuJoCo restarts them. (Callers
        at the sensor rate read through a :class:`RodView` instead.)"""
        x = data.flexvert_xpos[self._va : self._va + self._nv]
        p = data.plastic[self._pa : self._pa + 6 * self._ne]
        if not (p[3] or p[4] or p[5]):
            # plastic is zero before the first step: frames as MuJoCo restarts them, given as (t, u) per edge
            seg = np.diff(x, axis=0)
            t = seg / np.linalg.norm(seg, axis=1, keepdims=True)
            p = np.concatenate([t, self._restart_frames(t, data)], axis=1).ravel()
        site_x = data.site_xmat[self._site, 0::3] if self._site >= 0 else self._no_site
        return x, p, self._theta(data), site_x

    @property
    def inverse_lbar(self) -> np.ndarray:
        """1 / mean rest length of the two edges at each interior vertex, 1/m, shape (n_vertices − 2,)."""
        return self._inv_lbar

    def compute(self, data: mujoco.MjData, frames: np.ndarray, darboux: np.ndarray) -> np.ndarray:
        """Fill ``frames`` (n_edges, 3, 3) and ``darboux`` (n_vertices − 2, 3) from ``data``; return the vertex
        positions (a view of ``data``). The lean path for callers that keep their own buffers."""
        x, p, theta, site_x = self.kernel_inputs(data)
        _rod_kernels.frames_and_darboux(x, p, theta, site_x, self._inv_lbar, frames, darboux)
        return x

    def state(self, data: mujoco.MjData, frames: np.ndarray, darboux: np.ndarray) -> RodState:
        """A :class:`RodState` from frames and Darboux vectors already computed for ``data`` (e.g. by
        :meth:`compute` or a fused compiled call); copies them, so the caller may reuse its buffers."""
        x = data.flexvert_xpos[self._va : self._va + self._nv].copy()
        frames, darboux = frames.copy(), darboux.copy()
        _readonly(x, frames, darboux)
        return RodState(
            float(data.time), self.s, x, self.edge_s, frames, darboux, self.sensed_length, self._interp
        )

    def read(self, data: mujoco.MjData) -> RodState:
        """The rod's :class:`RodState` now (after ``mj_step``/``mj_forward``); the per-edge work is compiled."""
        frames = np.empty((self._ne, 3, 3))
        darboux = np.empty((self._ne - 1, 3))
        x = self.compute(data, frames, darboux).copy()
        _readonly(x, frames, darboux)
        return RodState(
            float(data.time), self.s, x, self.edge_s, frames, darboux, self.sensed_length, self._interp
        )

    __call__ = read

    def bind(self, data: mujoco.MjData) -> RodView:
        """This reader bound to ``data``, for reading the rod at the sensor rate (:class:`RodView`)."""
        return RodView(self, data)


class RodView:
    """A :class:`RodReader` bound to one ``mjData``: the views of its arrays taken once, frame and Darboux
    buffers, and one compiled call that fills them (:meth:`compute`).

    Taking ``data.flexvert_xpos``, ``plastic``, ``qpos`` and ``site_xmat`` anew, slicing them and gathering the
    twist angles cost a few microseconds a frame in Python; MuJoCo keeps an ``mjData``'s arrays where they are
    for its lifetime, so views taken once stay valid.

    The read (:func:`models._rod_kernels.view_read`) takes the small angles by their series (equal to the exact
    read to rounding: frames within 1e-15, Darboux vectors within ≈ 1e-15/l̄; :mod:`models._rod_kernels`), and
    while MuJoCo reports the rod asleep and its inputs are bit for bit those of the last read it keeps the
    buffers as they are.

    Attributes
    ----------
    reader : RodReader
    data : mujoco.MjData
    frames : ndarray, shape (n_edges, 3, 3)
        Material frames of the last :meth:`compute` (a buffer: overwritten by the next).
    darboux : ndarray, shape (n_vertices − 2, 3)
        Darboux vectors (κ1, κ2, τ) of the last :meth:`compute`, 1/m and rad/m (a buffer).
    """

    def __init__(self, reader: RodReader, data: mujoco.MjData) -> None:
        r = reader
        model = r.model
        self.reader, self.data = reader, data
        self.positions = data.flexvert_xpos[r._va : r._va + r._nv]  # a view: the vertices now, m
        self.plastic = data.plastic[r._pa : r._pa + 6 * r._ne]
        self.qpos = data.qpos
        self.site_row = data.site_xmat[r._site] if r._site >= 0 else np.zeros(9)
        self.tree_asleep = data.tree_asleep
        # the kinematic trees whose sleep the read watches: those of the vertices, the twist joints and the base
        bodies = [model.flex_vertbodyid[r._va : r._va + r._nv], model.jnt_bodyid[r._tw_joints]]
        if r._site >= 0:
            bodies.append(model.site_bodyid[[r._site]])
        trees = np.unique(model.body_treeid[np.concatenate(bodies)])
        trees = trees[trees >= 0]  # −1: a static body (the world), never moves
        index = np.concatenate([[r._tw_edges.size], r._tw_edges, r._tw_qadr, trees])
        ne = r._ne
        self._buffer = np.zeros(_rod_kernels.READ_HEADER + (ne - 1) + ne + 3 * (ne + 1) + 7 * ne + 9 + 9 * ne
                                + 3 * (ne - 1) + _rod_kernels.SCRATCH_ROWS * ne + index.size)
        self._header, inv_lbar, self.theta, _, self.frames, self.darboux, _, index_part = _rod_kernels.view_parts(
            self._buffer, ne)
        inv_lbar[:] = r._inv_lbar  # the clamped edge's θ stays 0
        index_part[:] = index  # integers far below 2⁵³: exact as floats
        # past numba's dispatcher (twin/_numba_entry.py): these arguments keep their types
        self._kernel = compiled_entry(_rod_kernels.view_read, *self.read_arguments())

    def read_arguments(self) -> tuple:
        """The arguments of :func:`models._rod_kernels.view_read`, for callers that fuse the rod read into a
        compiled call of their own (:mod:`sim_interrogator.frame_path`)."""
        return self.positions, self.plastic, self.qpos, self.site_row, self.tree_asleep, self._buffer

    def kernel_arguments(self) -> tuple:
        """The arguments of :func:`models._rod_kernels.bound_frames_and_darboux` (the exact read, into this view's
        buffers), for callers that fuse it into a compiled call of their own (:mod:`models._lumen_kernels`). A
        view read that way must not be read by :meth:`compute` as well (its kept inputs would not describe the
        buffers)."""
        r = self.reader
        return (self.positions, self.plastic, self.qpos, r._tw_edges, r._tw_qadr, self.theta, self.site_row,
                r._inv_lbar, self.frames, self.darboux)

    @property
    def reads(self) -> int:
        """How many times the buffers were filled afresh (a read that kept them, asleep, does not count)."""
        return int(self._header[1])

    def compute(self) -> None:
        """Fill :attr:`frames` and :attr:`darboux` from the bound ``mjData`` now (after ``mj_step``)."""
        if self._kernel(*self.read_arguments()) < 0:
            self.restart()

    def restart(self) -> None:
        """Fill the buffers while ``mjData.plastic`` is still zero (before the first step: frames as MuJoCo
        restarts them, :meth:`RodReader.compute`)."""
        self.reader.compute(self.data, self.frames, self.darboux)
        self._header[0] = 0.0  # the kept inputs no longer describe the buffers
        self._header[1] += 1.0

    def state(self) -> RodState:
        """The :class:`RodState` of the last :meth:`compute` (copies: the view's buffers are reused)."""
        r = self.reader
        x, frames, darboux = self.positions.copy(), self.frames.copy(), self.darboux.copy()
        _readonly(x, frames, darboux)
        return RodState(float(self.data.time), r.s, x, r.edge_s, frames, darboux, r.sensed_length, r._interp)


class RodTruth:
    """The :class:`twin.frames.Truth` of a bound rod, as :meth:`RodState.to_truth` (default samples, cubic) makes
    it, in one compiled call (:func:`models._rod_kernels.truth_samples`) from the view's last :meth:`RodView.
    compute`; equal to it within rounding (tests/test_sim.py).

    Parameters
    ----------
    view : RodView
    grating_s : array_like, shape (n_gratings,)
        Arc length of the gratings, m (the truth's curvature and twist are there).
    """

    def __init__(self, view: RodView, grating_s) -> None:
        r = view.reader
        self.view = view
        self.grating_s = np.array(grating_s, dtype=np.float64)
        if self.grating_s.ndim != 1:
            raise ValueError(f"RodTruth: grating_s must have shape (n_gratings,), got {self.grating_s.shape}")
        self.s = s = r._interp.truth_s(r.s, r.sensed_length)
        self._basis_t = np.ascontiguousarray(r.interpolation_matrix(self.grating_s).T)
        self._m, self._n_g = s.size, self.grating_s.size
        # where each sample falls, fixed for the rod: the searches of positions_at and frames_at done once
        grid, n = r.s, r.s.size
        i = np.clip(np.searchsorted(grid, s, side="right") - 1, 0, n - 2)
        a = (s - grid[i]) / (grid[i + 1] - grid[i])
        self._lerp_index = np.stack([i, i + 1], axis=1).astype(np.int64)
        self._lerp_index[s <= grid[0]] = 0  # held at the ends: x[0] and x[-1] exactly, as positions_at
        self._lerp_index[s >= grid[-1]] = n - 1
        self._lerp_weight = np.where((s <= grid[0]) | (s >= grid[-1]), 0.0, a)
        es = r.edge_s
        sq = np.clip(s, es[0], es[-1])
        self._frame_edge = np.clip(np.searchsorted(es, sq, side="right") - 1, 0, es.size - 2).astype(np.int64)
        self._frame_h = sq - es[self._frame_edge]
        self._kernel = compiled_entry(  # past numba's dispatcher (twin/_numba_entry.py): the types of every call
            _rod_kernels.truth_samples, view.positions, view.frames, view.darboux, self._lerp_index,
            self._lerp_weight, self._frame_edge, self._frame_h, self._basis_t, np.empty((self._m, 3)),
            np.empty((self._m, 3, 3)), np.empty((self._n_g, 2)), np.empty(self._n_g))

    def __call__(self, temperature: np.ndarray, fixture: np.ndarray | None = None) -> Truth:
        """The truth now, with ``temperature`` (n_gratings,) K (copied) and ``fixture`` passed through."""
        v = self.view
        positions = np.empty((self._m, 3))
        frames = np.empty((self._m, 3, 3))
        curvature = np.empty((self._n_g, 2))
        twist = np.empty(self._n_g)
        self._kernel(v.positions, v.frames, v.darboux, self._lerp_index, self._lerp_weight, self._frame_edge,
                     self._frame_h, self._basis_t, positions, frames, curvature, twist)
        return Truth._trusted(self.s, positions, frames, curvature, twist, temperature.copy(), fixture)


def _transport(t_from: np.ndarray, t_to: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Parallel-transport vectors u (3, n) from unit tangents t_from (3, n) to t_to (3, n).

    The minimal rotation taking a to b is R = I + 2 b aᵀ − (a + b)(a + b)ᵀ / (1 + a·b) (two reflections),
    exact for a·b > −1 and free of cross products.
    """
    w = t_from + t_to
    c = (t_from * t_to).sum(0)
    return u + (2.0 * (t_from * u).sum(0)) * t_to - ((w * u).sum(0) / (1.0 + c)) * w


def _numeric(model: mujoco.MjModel, name: str, default: float) -> float:
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if i < 0:
        return default
    return float(model.numeric_data[model.numeric_adr[i]])


def read_rod(model: mujoco.MjModel, data: mujoco.MjData, name: str = "cath") -> RodState:
    """One-off read (builds a :class:`RodReader`, ≈ 1 ms); keep a reader for repeated reads."""
    return RodReader(model, name).read(data)
