"""The ground-truth curve library: 6 planar and 6 spatial fibre shapes of 170 mm (importable without MuJoCo).

The reference paper does not give its shapes as formulas (docs/simulation.md §3), so these are ours, chosen to
span what it tested: curvature up to 0.675 1/cm (67.5 1/m), torsion up to 1.5 rad/cm (150 rad/m), planar arcs,
S-curves with inflections, bend planes that rotate slowly, quickly and through a near-zero curvature.

Each curve is defined by its curvature vector k(s) = (k_x, k_y) in a twist-free material (Bishop) frame, the
frame a fibre without mechanical twist carries. Positions and frames come from integrating R' = R û,
u = (−k_y, k_x, 0), p' = R e3 once with an 8th-order Runge–Kutta at rtol 1e-12 and dense output, so any arc
length is available to ≈ 1e-12 m. Every curve starts at the origin with the identity frame: tangent +z, d1 = +x.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.integrate import solve_ivp

__all__ = ["LENGTH", "ShapeCurve", "get", "library", "names"]

LENGTH = 0.17  #: m, the sensed length of the reference fibre


@dataclass(frozen=True, eq=False)
class ShapeCurve:
    """One ground-truth curve.

    Attributes
    ----------
    name : str
    planar : bool
        True when the curve lies in the x–z plane (k_y ≡ 0).
    curvature_fn : callable
        s (m, any shape) → (..., 2) curvature vector (k_x, k_y) in 1/m.
    description : str
    length : float
        m.
    """

    name: str
    planar: bool
    curvature_fn: Callable[[np.ndarray], np.ndarray] = field(repr=False)
    description: str = ""
    length: float = LENGTH

    def curvature(self, s) -> np.ndarray:
        """Curvature vector (k_x, k_y) in the twist-free material frame, 1/m, shape (..., 2)."""
        return self.curvature_fn(np.asarray(s, dtype=np.float64))

    def kappa(self, s) -> np.ndarray:
        """Curvature magnitude κ = |k|, 1/m."""
        k = self.curvature(s)
        return np.hypot(k[..., 0], k[..., 1])

    def torsion(self, s, ds: float = 1e-6) -> np.ndarray:
        """Frenet torsion τ = dθ_b/ds = (k_x k_y' − k_y k_x')/κ², rad/m (undefined where κ = 0)."""
        s = np.asarray(s, dtype=np.float64)
        k = self.curvature(s)
        dk = (self.curvature(s + ds) - self.curvature(s - ds)) / (2 * ds)
        with np.errstate(divide="ignore", invalid="ignore"):
            return (k[..., 0] * dk[..., 1] - k[..., 1] * dk[..., 0]) / (k[..., 0] ** 2 + k[..., 1] ** 2)

    @cached_property
    def _solution(self):
        def rhs(s, y):
            r = y[3:].reshape(3, 3)
            kx, ky = self.curvature_fn(np.asarray(s))
            uhat = np.array([[0.0, 0.0, kx], [0.0, 0.0, ky], [-kx, -ky, 0.0]])  # hat((−k_y, k_x, 0))
            return np.concatenate([r[:, 2], (r @ uhat).ravel()])

        y0 = np.concatenate([np.zeros(3), np.eye(3).ravel()])
        sol = solve_ivp(rhs, (0.0, self.length), y0, method="DOP853", rtol=1e-12, atol=1e-14, dense_output=True)
        if not sol.success:  # pragma: no cover - smooth analytic right-hand sides
            raise RuntimeError(f"shape {self.name}: integration failed ({sol.message})")
        return sol.sol

    def _state(self, s) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        if np.any((s < -1e-12) | (s > self.length + 1e-12)):
            raise ValueError(f"shape {self.name}: arc length outside [0, {self.length}] m")
        return self._solution(np.clip(s, 0.0, self.length).ravel()).T.reshape((*s.shape, 12))

    def positions(self, s) -> np.ndarray:
        """Centreline positions, m, shape (..., 3)."""
        return self._state(s)[..., :3]

    def frames(self, s) -> np.ndarray:
        """Material frames [d1 d2 d3] as columns, shape (..., 3, 3)."""
        return self._state(s)[..., 3:].reshape((*np.shape(s), 3, 3))

    def sample(self, step: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """A dense polyline: (s (n,), positions (n, 3)) with spacing ≤ ``step``."""
        n = int(np.ceil(self.length / step)) + 1
        s = np.linspace(0.0, self.length, n)
        return s, self.positions(s)


def _vec(kx, ky):
    return np.stack(np.broadcast_arrays(kx, ky), axis=-1)


L = LENGTH


def _gauss(s, centre, width):
    return np.exp(-(((s - centre) / width) ** 2))


_LIBRARY: tuple[ShapeCurve, ...] = (
    # ---- planar (the paper's grooved plate) ----
    ShapeCurve("arc", True, lambda s: _vec(25.0 + 0 * s, 0 * s), "constant curvature 0.25 1/cm"),
    ShapeCurve(
        "s-curve", True, lambda s: _vec(45.0 * np.sin(2 * np.pi * s / L + 0.3), 0 * s),
        "S-curve, inflections at 0.45 and 0.95 of the length, |κ| ≤ 0.45 1/cm",
    ),
    ShapeCurve(
        "tightening", True, lambda s: _vec(10.0 + 57.5 * (s / L) ** 2, 0 * s),
        "curvature rising from 0.1 to 0.675 1/cm (the paper's maximum)",
    ),
    ShapeCurve(
        "hook", True, lambda s: _vec(5.0 + 62.5 * _gauss(s, 0.125, 0.03), 0 * s),
        "gentle shaft with a tight distal hook, peak 0.675 1/cm",
    ),
    ShapeCurve(
        "wave", True, lambda s: _vec(30.0 * np.sin(3 * np.pi * s / L), 0 * s),
        "two inflections, |κ| ≤ 0.3 1/cm",
    ),
    ShapeCurve(
        "clothoid", True, lambda s: _vec(-(15.0 + 35.0 * s / L), 0 * s),
        "curvature growing linearly from 0.15 to 0.5 1/cm, bending toward −x",
    ),
    # ---- spatial (the paper's printed tubes) ----
    ShapeCurve(
        "helix", False, lambda s: _vec(40.0 * np.cos(30.0 * s), 40.0 * np.sin(30.0 * s)),
        "helix: κ = 0.4 1/cm, τ = 0.3 rad/cm",
    ),
    ShapeCurve(
        "rotating-bend", False,
        lambda s: _vec(35.0 * np.cos(30.0 * s**2 / L), 35.0 * np.sin(30.0 * s**2 / L)),
        "κ = 0.35 1/cm with the bend plane accelerating, τ from 0 to 0.6 rad/cm",
    ),
    ShapeCurve(
        "through-zero", False,
        lambda s: _vec(30.0 * np.sin(np.pi * (s - L / 2) / L), 3.7 + 0 * s),
        "bend reverses through a near-zero curvature of 0.037 1/cm: τ peaks at 1.5 rad/cm (the paper's maximum)",
    ),
    ShapeCurve(
        "mixed", False,
        lambda s: _vec(
            (35.0 + 25.0 * np.sin(2 * np.pi * s / L + 0.4)) * np.cos(1.8 * np.sin(np.pi * s / L)),
            (35.0 + 25.0 * np.sin(2 * np.pi * s / L + 0.4)) * np.sin(1.8 * np.sin(np.pi * s / L)),
        ),
        "κ between 0.1 and 0.6 1/cm, bend plane swinging out by 100° and back (|τ| ≤ 0.33 rad/cm)",
    ),
    ShapeCurve(
        "widening-helix", False,
        lambda s: _vec((20.0 + 35.0 * s / L) * np.cos(20.0 * s), (20.0 + 35.0 * s / L) * np.sin(20.0 * s)),
        "helix-like, κ from 0.2 to 0.55 1/cm, τ = 0.2 rad/cm",
    ),
    ShapeCurve(
        "two-plane", False,
        lambda s: _vec(40.0 * _gauss(s, 0.05, 0.03), 50.0 * _gauss(s, 0.12, 0.03)),
        "a bend in one plane, then one at right angles to it",
    ),
)


def library() -> tuple[ShapeCurve, ...]:
    """All 12 curves: the 6 planar ones first."""
    return _LIBRARY


def names() -> list[str]:
    return [c.name for c in _LIBRARY]


def get(name: str) -> ShapeCurve:
    """The curve called ``name`` (see :func:`names`)."""
    for c in _LIBRARY:
        if c.name == name:
            return c
    raise KeyError(f"no shape {name!r}; known shapes: {', '.join(names())}")
