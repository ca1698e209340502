"""The fibre model: where the cores sit, where the gratings are, and how the gratings respond.

Conventions (docs/math.md §1): the fibre's material frame is (d1, d2, d3) with d3 the tangent from base to tip;
core ``i`` sits at ``core_radii[i] * (cos θ_i, sin θ_i)`` in (d1, d2), with θ_i counted counter-clockwise about
+d3 when ``handedness`` is +1. A vendor drawing that counts angles clockwise is entered as written with
``handedness = -1``; everything downstream then uses the effective CCW angles ``handedness * core_angles``.

A *spun* fibre (``spin_rate`` ≠ 0, docs/spun-fibers.md) has its outer cores wound helically: core ``i`` sits at
θ_i + Ω s in the material frame, Ω = 2π·``spin_rate`` (turns/m, in the same sense as the core angles). Zero, the
default, is today's straight-core fibre.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin._validate import check_bragg_nm, check_field_types, check_table, frozen, real_array

__all__ = ["FiberModel"]

_OWNER = "FiberModel"

#: longest arc length a model may hold, m: a catheter's or an endoscope's sensor is a few metres long; this
#: leaves room and refuses lengths in mm or µm before anything is sized by them (issue 23 B15)
MAX_LENGTH = 20.0

#: what each field of a fibre file holds (checked before anything is converted)
FIELD_KINDS = {
    "core_angles": "numbers",
    "core_radii": "numbers",
    "grating_s": "numbers",
    "lambda0": "rows",
    "central_core": "integer",
    "strain_sensitivity": "number",
    "temperature_sensitivity": "number or numbers",
    "handedness": "integer",
    "length": "number",
    "name": "text",
    "spin_rate": "number",
}


@dataclass(frozen=True, eq=False)
class FiberModel:
    """A multi-core (or multi-fibre) FBG sensor.

    Parameters
    ----------
    core_angles : array_like, shape (n_cores,)
        Angular position of each core in the cross-section, rad, within ±2π (see module docstring for the sense).
    core_radii : array_like, shape (n_cores,)
        Distance of each core from the fibre's neutral axis, m; 0 for a central core.
    grating_s : array_like, shape (n_gratings,)
        Arc length of each grating from the base (the reconstruction's origin), m, strictly increasing, at most
        :data:`MAX_LENGTH` (``length`` too).
    lambda0 : array_like, shape (n_gratings, n_cores)
        Nominal Bragg wavelength of each grating in each core, unstrained at the reference temperature, nm.
    central_core : int or None
        Index of the core on the neutral axis (radius 0), or None when there is none.
    strain_sensitivity : float
        S_ε = 1 − p_e, the relative Bragg shift per unit strain (dimensionless, ≈ 0.78 for silica).
    temperature_sensitivity : float or array_like, shape (n_cores,)
        S_T, the relative Bragg shift per kelvin, 1/K (≈ 6.6e-6). Per core when the cores differ.
    handedness : {+1, -1}
        +1 when ``core_angles`` are counted counter-clockwise about the tangent, −1 when clockwise.
    length : float or None
        Arc length to reconstruct up to, m; None means the last grating.
    name : str
        Free text identifying the sensor.
    spin_rate : float
        Turns per metre of the cores about the axis in a spun fibre, counted in the sense of ``core_angles``
        (negative: the other helix sense); 0 for straight cores.
    """

    core_angles: np.ndarray
    core_radii: np.ndarray
    grating_s: np.ndarray
    lambda0: np.ndarray
    central_core: int | None = None
    strain_sensitivity: float = 0.777
    temperature_sensitivity: float | np.ndarray = 6.6e-6
    handedness: int = 1
    length: float | None = None
    name: str = ""
    spin_rate: float = 0.0

    def __post_init__(self) -> None:
        angles = real_array(self.core_angles, "core_angles", shape=(None,), unit="rad", owner=_OWNER)
        n_c = angles.size
        if n_c < 2:
            raise ValueError(f"{_OWNER}.core_angles: expected at least 2 cores, got {n_c}")
        if np.any(np.abs(angles) > 2 * np.pi + 1e-9):
            i = int(np.argmax(np.abs(angles) > 2 * np.pi + 1e-9))
            raise ValueError(f"{_OWNER}.core_angles: core {i} at {angles[i]} rad; expected angles in rad within "
                             "±2π (120° is 2.0944)")
        radii = real_array(self.core_radii, "core_radii", shape=(None,), unit="m", owner=_OWNER)
        if radii.size != n_c:
            raise ValueError(_core_count_mismatch(n_c, radii.size, self.lambda0))
        if np.any(radii < 0):
            i = int(np.argmax(radii < 0))
            raise ValueError(f"{_OWNER}.core_radii: expected radii >= 0 m, got {radii[i]} for core {i}")
        if np.any(radii > 0.01):
            i = int(np.argmax(radii > 0.01))
            raise ValueError(
                f"{_OWNER}.core_radii: core {i} at {radii[i]} m from the axis; radii are in metres "
                "(37.5 µm is 3.75e-05)"
            )
        s = real_array(self.grating_s, "grating_s", shape=(None,), unit="m", owner=_OWNER)
        n_g = s.size
        if n_g < 1:
            raise ValueError(f"{_OWNER}.grating_s: expected at least one grating")
        if np.any(s < 0):
            raise ValueError(f"{_OWNER}.grating_s: expected arc lengths >= 0 m, got {s.min()}")
        if s[-1] > MAX_LENGTH:
            raise ValueError(f"{_OWNER}.grating_s: grating {n_g - 1} at {s[-1]} m from the base; expected arc lengths "
                             f"in m up to {MAX_LENGTH:g} m (170 mm is 0.17)")
        if np.any(np.diff(s) <= 0):
            i = int(np.argmax(np.diff(s) <= 0))
            raise ValueError(
                f"{_OWNER}.grating_s: expected strictly increasing arc lengths, got {s[i]} then {s[i + 1]} "
                f"at gratings {i}, {i + 1}"
            )
        lam = real_array(self.lambda0, "lambda0", shape=(n_g, n_c), unit="nm", owner=_OWNER)
        check_bragg_nm(lam, f"{_OWNER}.lambda0")
        central = self.central_core
        if central is not None:
            if isinstance(central, bool) or not isinstance(central, int | np.integer):
                raise ValueError(f"{_OWNER}.central_core: expected a core index or None, got {central!r}")
            central = int(central)
            if not 0 <= central < n_c:
                raise ValueError(f"{_OWNER}.central_core: expected an index in 0..{n_c - 1}, got {central}")
            if radii[central] != 0:
                raise ValueError(
                    f"{_OWNER}.central_core: core {central} has radius {radii[central]} m; a central core "
                    "sits on the neutral axis (radius 0)"
                )
        n_bending = int(np.count_nonzero(radii > 0))
        if n_bending < 2:
            raise ValueError(f"{_OWNER}.core_radii: expected at least 2 off-axis cores, got {n_bending}")
        s_eps = float(self.strain_sensitivity)
        if not (np.isfinite(s_eps) and 0 < s_eps <= 2):
            raise ValueError(f"{_OWNER}.strain_sensitivity: expected S_ε in (0, 2], got {self.strain_sensitivity}")
        s_t = np.asarray(self.temperature_sensitivity, dtype=np.float64)
        if s_t.ndim == 0:
            s_t_value: float | np.ndarray = float(s_t)
        else:
            s_t_value = frozen(
                real_array(s_t, "temperature_sensitivity", shape=(n_c,), unit="1/K", owner=_OWNER)
            )
        if not np.all(np.isfinite(s_t)) or np.any(np.abs(s_t) > 1e-3):
            raise ValueError(
                f"{_OWNER}.temperature_sensitivity: expected S_T in 1/K (≈ 6.6e-06), got {self.temperature_sensitivity}"
            )
        if self.handedness not in (1, -1):
            raise ValueError(f"{_OWNER}.handedness: expected +1 (CCW) or -1 (CW), got {self.handedness!r}")
        length = self.length
        if length is not None:
            length = float(length)
            if not (np.isfinite(length) and s[-1] <= length <= MAX_LENGTH and length > 0):
                raise ValueError(
                    f"{_OWNER}.length: expected a length in m at or beyond the last grating ({s[-1]} m) and up to "
                    f"{MAX_LENGTH:g} m, got {length}"
                )
        # Freeze: the model is shared by reconstructors, calibrations and the simulator.
        for name, value in (("core_angles", angles), ("core_radii", radii), ("grating_s", s), ("lambda0", lam)):
            object.__setattr__(self, name, frozen(value))
        object.__setattr__(self, "central_core", central)
        object.__setattr__(self, "strain_sensitivity", s_eps)
        object.__setattr__(self, "temperature_sensitivity", s_t_value)
        object.__setattr__(self, "handedness", int(self.handedness))
        object.__setattr__(self, "length", length)
        object.__setattr__(self, "name", str(self.name))
        object.__setattr__(self, "spin_rate", _check_spin_rate(self.spin_rate))

    # ---------------------------------------------------------------- derived quantities
    @property
    def n_cores(self) -> int:
        return self.core_angles.size

    @property
    def n_gratings(self) -> int:
        return self.grating_s.size

    @property
    def sensed_length(self) -> float:
        """Arc length reconstructed, m: ``length`` or the last grating's position."""
        return float(self.grating_s[-1]) if self.length is None else self.length

    @property
    def ccw_angles(self) -> np.ndarray:
        """Core angles counter-clockwise about +d3, rad (``handedness * core_angles``)."""
        return self.handedness * self.core_angles

    @property
    def bending_cores(self) -> np.ndarray:
        """Indices of the off-axis cores."""
        return np.flatnonzero(self.core_radii > 0)

    @property
    def gains(self) -> np.ndarray:
        """g_i = r_i · S_ε per core, m: the only combination of radius and S_ε that shapes depend on."""
        return self.core_radii * self.strain_sensitivity

    @property
    def spin_omega(self) -> float:
        """Ω, the cores' angular rate about +d3 counter-clockwise, rad/m (0 for straight cores)."""
        return self.handedness * 2.0 * np.pi * self.spin_rate

    @property
    def helix_cos2(self) -> np.ndarray:
        """cos²α per core, α = atan(r_i Ω) the helix angle (1 for straight cores and the central core)."""
        return 1.0 / (1.0 + (self.core_radii * self.spin_omega) ** 2)

    def core_phase(self, s) -> np.ndarray:
        """Effective CCW angle of every core at arc lengths ``s``, θ_i + Ω s, rad, shape (*s.shape, n_cores)."""
        s = np.asarray(s, dtype=np.float64)
        return self.ccw_angles + self.spin_omega * s[..., None]

    def with_origin(self, origin: str) -> FiberModel:
        """This model, remembering where it came from (a file, a recording) for error messages."""
        object.__setattr__(self, "_origin", str(origin))
        return self

    def replace(self, **changes) -> FiberModel:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # ---------------------------------------------------------------- the reference fibre
    @classmethod
    def paper(cls) -> FiberModel:
        """The fibre of Al-Ahmad et al.: a 7-core MCF read on its central core and 3 adjacent outer cores.

        Outer cores at 0, π/3, 2π/3 (Δθ = π/3), r = 37.5 µm, S_ε = 0.777, 18 gratings every 10 mm from the base
        (0 … 170 mm). The paper does not list grating wavelengths; here grating n sits at 1510 + 5 n nm in every
        core, spanning the 1510–1595 nm range of a WDM interrogator.
        """
        return cls(
            core_angles=[0.0, 0.0, np.pi / 3, 2 * np.pi / 3],
            core_radii=[0.0, 37.5e-6, 37.5e-6, 37.5e-6],
            name="Al-Ahmad et al. 7-core MCF (centre + 3 adjacent outer cores)",
            **_paper_gratings(),
        ).with_origin("the reference fibre FiberModel.paper()")

    @classmethod
    def spun(cls, spin_rate: float = 50.0, radius: float = 35e-6) -> FiberModel:
        """A spun 4-core fibre: a central core and 3 outer cores 120° apart at ``radius`` (m), wound at
        ``spin_rate`` turns/m (Khan et al., Sens. Actuators A 317:112442 (2021): 50 turns/m, r ≈ 35 µm), with
        the paper fibre's 18 gratings every 10 mm at 1510 + 5 n nm."""
        return cls(
            core_angles=[0.0, 0.0, 2 * np.pi / 3, 4 * np.pi / 3],
            core_radii=[0.0, radius, radius, radius],
            **_paper_gratings(),
            name=f"spun 4-core MCF (centre + 3 outer cores at 120°, {spin_rate:g} turns/m)",
            spin_rate=spin_rate,
        )

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        """Plain TOML-ready mapping (SI units, wavelengths in nm)."""
        d: dict = {"name": self.name}
        if self.central_core is not None:
            d["central_core"] = self.central_core
        d["handedness"] = self.handedness
        d["strain_sensitivity"] = self.strain_sensitivity
        s_t = self.temperature_sensitivity
        d["temperature_sensitivity"] = s_t.tolist() if isinstance(s_t, np.ndarray) else s_t
        if self.length is not None:
            d["length"] = self.length
        if self.spin_rate != 0:
            d["spin_rate"] = self.spin_rate
        d["core_angles"] = self.core_angles.tolist()
        d["core_radii"] = self.core_radii.tolist()
        d["grating_s"] = self.grating_s.tolist()
        d["lambda0"] = self.lambda0.tolist()
        return d

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "") -> FiberModel:
        """Build from a mapping as written by :meth:`to_dict`; unknown or missing fields, and values of the wrong
        type (a list, table, date or boolean where a number belongs), are errors naming ``source`` and the
        field. The model remembers ``source`` (:func:`origin`) so later errors can name it too."""
        where = f"{source}: " if source else ""
        check_table(data, cls, "fiber", where)
        required = ("core_angles", "core_radii", "grating_s", "lambda0")
        missing = [k for k in required if k not in data]
        if missing:
            raise ValueError(f"{where}missing required field(s) {', '.join(missing)}")
        check_field_types(data, FIELD_KINDS, where)
        try:
            model = cls(**data)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}{exc}") from None
        return model.with_origin(source) if source else model

    def save(self, path: str | Path) -> None:
        """Write the model as TOML."""
        import tomli_w

        header = "# twin fibre model: SI units (m, rad, 1/K); wavelengths in nm\n"
        Path(path).write_text(header + tomli_w.dumps(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> FiberModel:
        """Read a TOML fibre model, validating every field."""
        path = Path(path)
        return cls.from_dict(read_toml(path, "fibre model"), source=str(path))


def _core_count_mismatch(n_angles: int, n_radii: int, lambda0) -> str:
    """The error for ``core_angles`` and ``core_radii`` of different lengths: it names both, and blames the one
    that disagrees with ``lambda0``'s cores per grating when that settles it."""
    shape = np.shape(lambda0) if isinstance(lambda0, list | tuple | np.ndarray) else ()
    n_lam = shape[1] if len(shape) == 2 else None
    both = f"core_angles has {n_angles} entries, core_radii {n_radii}: both need one per core"
    if n_lam == n_radii:
        return f"{_OWNER}.core_angles: {both} (lambda0 has {n_lam} cores per grating)"
    if n_lam == n_angles:
        return f"{_OWNER}.core_radii: {both} (lambda0 has {n_lam} cores per grating)"
    return f"{_OWNER}.core_angles, core_radii: {both}"


def _paper_gratings() -> dict:
    """What the reference fibre and the spun one share: 18 gratings every 10 mm on 4 cores (core 0 central) at
    1510 + 5 n nm, and the sensitivities."""
    n_g = 18
    return {"grating_s": 0.01 * np.arange(n_g),
            "lambda0": np.repeat((1510.0 + 5.0 * np.arange(n_g))[:, None], 4, axis=1),
            "central_core": 0, "strain_sensitivity": 0.777, "temperature_sensitivity": 6.6e-6, "handedness": 1}


def origin(obj, default: str = "") -> str:
    """The file (or recording attribute) a FiberModel or Calibration was read from, or ``default``."""
    return getattr(obj, "_origin", "") or default


def read_toml(path: Path, what: str) -> dict:
    """Read a TOML file; one-line errors naming the file (missing, unreadable, not text, not TOML)."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such {what} file") from None
    except OSError as exc:
        raise OSError(f"{path}: cannot read the {what} file ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path}: not a {what} file: byte {exc.start} is not UTF-8 text (a TOML file is expected)"
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    except ValueError as exc:  # an integer of more digits than Python converts (4300): its first sentence
        raise ValueError(f"{path}: not valid TOML ({str(exc).split(':')[0]})") from None
    except RecursionError:  # arrays or tables nested thousands deep: tomllib reads them recursively
        raise ValueError(f"{path}: not valid TOML (arrays or tables nested too deeply)") from None


#: Largest accepted |spin rate|, turns/m: a 1 mm pitch, far tighter than any drawn spun fibre (≈ 6–50 mm).
MAX_SPIN_RATE = 1000.0


def _check_spin_rate(value) -> float:
    """The spin rate as a float, turns/m, or a one-line error naming the field."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{_OWNER}.spin_rate: expected a number in turns/m (0 for straight cores), got {value!r}")
    v = float(value)
    if not np.isfinite(v) or abs(v) > MAX_SPIN_RATE:
        raise ValueError(
            f"{_OWNER}.spin_rate: expected turns/m with |spin_rate| <= {MAX_SPIN_RATE:g} (a pitch of 1 mm or more; "
            f"spun fibres have 20–170 turns/m), got {v}"
        )
    return v
