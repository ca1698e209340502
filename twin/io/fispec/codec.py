"""FiSpec-type USB-serial FBG interrogator: commands, replies, synthetic spectrum (docs/protocols.md §2).

**Provenance.** This protocol is *inferred from the one public client*, the PyPI package
``myfbgcommunication`` 2.0.2 (MIT), and from nothing else: it is not taken from a vendor manual, and a real
FiSpec device may differ wherever that client does not look. What the client relies on is reproduced exactly;
everything else is a documented choice of the simulator.

Wire format (serial 8N1; the client opens at 3,000,000 baud with a 1 ms timeout):

- Commands are ASCII, arguments comma-separated, each command terminated by ``>`` (no CR/LF).
- Replies (all little-endian):

  ================  =========================================================================================
  ``?>``            ASCII identity starting with ``FiSpec`` (simulator: ``FiSpec FBG X150``, no terminator)
  ``p?>``           ``#``-separated items ``Name_<int>``: ``Pixel_N``, ``Kanalanzahl_n``, ``tInt_µs``,
                    ``Mittelungen_n``, ``OBBerechnen_0|1`` (the client reads the integer after the first
                    ``_``)
  ``s>``            N × uint16 spectrum counts, then ``Ende`` (exactly 2N + 4 bytes)
  ``WLL>``          N × uint32 pixel wavelengths in 1e-4 nm, then ``Ende`` (exactly 4N + 4 bytes)
  ``P>``            per peak window: int32 wavelength × 1e4 nm and int32 amplitude (``OBB,0``), or int32
                    strain × 1e4 and int32 temperature × 100 °C (``OBB,1``); then int16 device temperature
                    × 100 °C, int16 0, 4 reserved bytes, ``Ende`` (exactly 8n + 12 bytes)
  ================  =========================================================================================

- Setters that get **no reply at all**: ``a>``, ``LED,1>``, ``iz,<µs>>``, ``Ke,<i>,<lo>,<hi>>``, ``KA,<n>>``,
  ``m,<n>>``, ``OBsTyp,<i>,<t>>`` (older client versions spell it ``OBsType``; both are accepted),
  ``OBN>``, ``OBsaT0,<T×100>>``, ``PeM,<0|1>>``, ``OBB,<0|1>>``.

The client spins forever on a reply one byte too long or too short, so every client-side decoder here
checks the exact length and the ``Ende`` trailer and raises :class:`~twin.io.errors.FramingError` otherwise.

Decisions where the client is silent: a missing peak (NaN) is sent as wavelength 0 and amplitude 0 and decoded
back to NaN with :attr:`~twin.frames.PeakStatus.MISSING` (the same convention as ILLumiSense); the two bytes
after the device temperature are sent as 0 and ignored on decode, the 4 reserved bytes likewise; the
on-board strain is encoded as given × 1e4 (the client divides by 1e4; the simulator passes µε).

Synthetic spectrum: the client's ``init()`` averages 10 spectra, copies pixel 3 into pixels 0–2, subtracts
pixel 0, runs ``scipy.signal.find_peaks(height=10, distance=50, prominence=100)`` and **drops the first peak
found**; :func:`synthetic_spectrum` therefore draws one extra leading reference peak and refuses peaks closer
than 50 pixels. The default pixel table (:func:`default_pixel_wavelengths`) has **2048 pixels spanning
1500.0–1600.0 nm** (≈ 0.0489 nm per pixel, values quantised to the protocol's 1e-4 nm), which holds the
reference fibre's gratings (1510–1595 nm, 5 nm ≈ 102 pixels apart) with room for the reference peak.

Why one module of this size: the codec holds both directions of one protocol (the simulator's server encodes
with it, the driver decodes), so that the two cannot drift apart.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from twin.frames import Frame, PeakStatus
from twin.io.errors import FramingError, OversizeFrameError, TruncatedFrameError

__all__ = [
    "BAUDRATE",
    "COMMAND_ARITY",
    "END",
    "SILENT_COMMANDS",
    "Command",
    "CommandParser",
    "PeakReply",
    "decode_identity",
    "decode_parameters",
    "decode_peaks",
    "decode_pixel_wavelengths",
    "decode_spectrum",
    "default_pixel_wavelengths",
    "encode_command",
    "encode_identity",
    "encode_parameters",
    "encode_peaks",
    "encode_pixel_wavelengths",
    "encode_spectrum",
    "parameter_items",
    "peaks_to_frame",
    "quantise_nm",
    "synthetic_spectrum",
]

PROTOCOL = "fispec"
BAUDRATE = 3_000_000
END = b"Ende"
TERMINATOR = b">"
WAVELENGTH_UNIT_NM = 1e-4  #: native resolution: wavelengths travel as integers of 0.1 pm
DEFAULT_IDENTITY = "FiSpec FBG X150"

#: Commands the client sends, with their number of arguments.
COMMAND_ARITY: dict[str, int] = {
    "?": 0,
    "p?": 0,
    "s": 0,
    "WLL": 0,
    "P": 0,
    "a": 0,
    "LED": 1,
    "iz": 1,
    "Ke": 3,
    "KA": 1,
    "m": 1,
    "OBsTyp": 2,
    "OBsType": 2,
    "OBN": 0,
    "OBsaT0": 1,
    "PeM": 1,
    "OBB": 1,
}
#: Setters that must get no reply at all (any byte sent back desynchronises the client's next read).
SILENT_COMMANDS: frozenset[str] = frozenset(
    {"a", "LED", "iz", "Ke", "KA", "m", "OBsTyp", "OBsType", "OBN", "OBsaT0", "PeM", "OBB"}
)
_PRINTABLE = bytes(range(0x21, 0x7F))


def _is_int(text: str) -> bool:
    """An optionally negative ASCII decimal integer (``str.isdigit`` alone would pass ``--5`` or ``²``)."""
    digits = text[1:] if text.startswith("-") else text
    return digits.isascii() and digits.isdigit()


def quantise_nm(wavelengths: np.ndarray | Sequence[float] | float) -> np.ndarray:
    """Round wavelengths (nm) to the protocol's native 1e-4 nm; NaN stays NaN."""
    w = np.asarray(wavelengths, dtype=np.float64)
    return np.round(w * 1e4) / 1e4


# ------------------------------------------------------------------------------------------------ commands


@dataclass(frozen=True)
class Command:
    """One command received by the server.

    Attributes
    ----------
    name : str
        The text before the first comma, e.g. ``"Ke"``.
    args : tuple of int
        The integer arguments (every known command takes integers only).
    offset : int
        Byte offset of the command's first byte in the stream fed to the parser.
    """

    name: str
    args: tuple[int, ...] = ()
    offset: int = 0

    @property
    def silent(self) -> bool:
        """True for setters that must get no reply."""
        return self.name in SILENT_COMMANDS


def encode_command(name: str, *args: int) -> bytes:
    """The bytes of a command as the client sends it, e.g. ``encode_command("Ke", 0, 15085000, 15115000)``."""
    if name not in COMMAND_ARITY:
        raise ValueError(f"unknown FiSpec command {name!r}; known: {sorted(COMMAND_ARITY)}")
    if len(args) != COMMAND_ARITY[name]:
        raise ValueError(f"command {name!r} takes {COMMAND_ARITY[name]} argument(s), got {len(args)}")
    return ",".join([name, *(str(int(a)) for a in args)]).encode("ascii") + TERMINATOR


class CommandParser:
    """Server side: split the incoming byte stream on ``>`` into :class:`Command` objects.

    Tolerates garbage: whitespace and NUL bytes around a command are stripped (a terminal or a USB reset can
    inject them); a chunk that is not a known command with the right number of integer arguments is dropped
    and counted, as is a run of more than ``max_length`` bytes without a ``>``. Never raises for any input.

    Parameters
    ----------
    max_length : int
        Longest command accepted, bytes (the longest real one, ``Ke,<i>,<lo>,<hi>``, is about 30).

    Attributes
    ----------
    commands : int
        Commands parsed.
    errors : int
        Chunks dropped (unknown command, wrong arguments, over-long garbage).
    last_error : FramingError or None
        Why the last chunk was dropped.
    recent_errors : collections.deque of FramingError
        The last 16 such errors.
    """

    def __init__(self, *, max_length: int = 256) -> None:
        self.max_length = max_length
        self._buf = bytearray()
        self._base = 0
        self.commands = 0
        self.errors = 0
        self.last_error: FramingError | None = None
        self.recent_errors: deque[FramingError] = deque(maxlen=16)

    def feed(self, data: bytes) -> list[Command]:
        """Consume bytes; return the complete commands among them, in order."""
        self._buf += data
        out: list[Command] = []
        start = 0
        while True:
            k = self._buf.find(TERMINATOR, start)
            if k < 0:
                break
            cmd = self._parse(bytes(self._buf[start:k]), self._base + start)
            if cmd is not None:
                out.append(cmd)
            start = k + 1
        del self._buf[:start]
        self._base += start
        if len(self._buf) > self.max_length:
            self._error(
                FramingError(
                    f"{len(self._buf)} bytes without a '>' terminator",
                    offset=self._base,
                    expected=f"a command of at most {self.max_length} bytes",
                    protocol=PROTOCOL,
                )
            )
            self._base += len(self._buf)
            self._buf.clear()
        return out

    def _error(self, err: FramingError) -> None:
        self.errors += 1
        self.last_error = err
        self.recent_errors.append(err)

    def _parse(self, chunk: bytes, offset: int) -> Command | None:
        stripped = chunk.lstrip(b" \t\r\n\x00")
        offset += len(chunk) - len(stripped)
        stripped = stripped.rstrip(b" \t\r\n\x00")
        if not stripped:
            return None  # stray '>' or whitespace: nothing to count
        if len(stripped) > self.max_length or stripped.translate(None, _PRINTABLE):
            self._error(
                FramingError(
                    f"non-printable bytes or over-long command {stripped[:20]!r}",
                    offset=offset,
                    expected="an ASCII command",
                    protocol=PROTOCOL,
                )
            )
            return None
        name, *raw = stripped.decode("ascii").split(",")
        arity = COMMAND_ARITY.get(name)
        if arity is None:
            self._error(
                FramingError(
                    f"unknown command {name[:20]!r}",
                    offset=offset,
                    expected=f"one of {sorted(COMMAND_ARITY)}",
                    protocol=PROTOCOL,
                )
            )
            return None
        if len(raw) != arity or not all(_is_int(a) for a in raw):
            self._error(
                FramingError(
                    f"command {name!r} with arguments {raw!r}",
                    offset=offset,
                    expected=f"{arity} integer argument(s)",
                    protocol=PROTOCOL,
                )
            )
            return None
        self.commands += 1
        return Command(name, tuple(int(a) for a in raw), offset)


# --------------------------------------------------------------------------------------------------- replies


def encode_identity(name: str = DEFAULT_IDENTITY) -> bytes:
    """Reply to ``?>``: the identity string as ASCII, without terminator. It must start with ``FiSpec``."""
    if not name.startswith("FiSpec"):
        raise ValueError(
            f"identity {name!r} must start with 'FiSpec' (the client checks the first 6 characters)"
        )
    return name.encode("ascii")


def decode_identity(reply: bytes) -> str:
    """Client side of ``?>``: the identity, trailing CR/LF/NUL stripped; FramingError unless ``FiSpec…``."""
    text = reply.rstrip(b"\r\n\x00 ")
    if not text.startswith(b"FiSpec") or text.translate(None, bytes(range(0x20, 0x7F))):
        raise FramingError(
            f"identity {reply[:32]!r}",
            offset=0,
            expected="printable ASCII starting with 'FiSpec'",
            protocol=PROTOCOL,
        )
    return text.decode("ascii")


def parameter_items(
    *,
    pixels: int,
    channels: int,
    integration_time_us: int,
    averages: int = 1,
    onboard: bool = False,
    extra: Mapping[str, int] | None = None,
) -> dict[str, int]:
    """The parameter items the client checks, by their device names.

    Parameters
    ----------
    pixels : int
        Spectrometer pixel count N (``Pixel``).
    channels : int
        Active peak windows (``Kanalanzahl``, set by ``KA``).
    integration_time_us : int
        Integration time, µs (``tInt``, set by ``iz``).
    averages : int
        Averaged spectra (``Mittelungen``, set by ``m``).
    onboard : bool
        On-board strain/temperature calculation (``OBBerechnen``, set by ``OBB``).
    extra : mapping of str to int, optional
        Further items to report.
    """
    items = {
        "Pixel": int(pixels),
        "Kanalanzahl": int(channels),
        "tInt": int(integration_time_us),
        "Mittelungen": int(averages),
        "OBBerechnen": int(bool(onboard)),
    }
    items.update(extra or {})
    return items


def encode_parameters(items: Mapping[str, int]) -> bytes:
    """Reply to ``p?>``: ``Name_<int>`` items joined by ``#`` (see :func:`parameter_items`)."""
    parts = []
    for name, value in items.items():
        if not name or "#" in name or "_" in name or not name.isascii() or not name.isprintable():
            raise ValueError(f"parameter name {name!r}: expected printable ASCII without '#' or '_'")
        parts.append(f"{name}_{int(value)}")
    return "#".join(parts).encode("ascii")


def decode_parameters(reply: bytes) -> dict[str, int]:
    """Client side of ``p?>``: the items with a ``_``, as the client reads them (integer after the first _).

    Raises
    ------
    FramingError
        Non-ASCII bytes, an item whose text after the first ``_`` is not an integer, or no ``Pixel`` item.
    """
    if reply.translate(None, bytes(range(0x20, 0x7F))):
        bad = next(i for i, b in enumerate(reply) if not 0x20 <= b < 0x7F)
        raise FramingError(
            "non-printable byte in the parameter string",
            offset=bad,
            expected="printable ASCII",
            protocol=PROTOCOL,
        )
    out: dict[str, int] = {}
    offset = 0
    for item in reply.decode("ascii").split("#"):
        if "_" in item:
            name, value = item.split("_")[:2]
            if not _is_int(value):
                raise FramingError(
                    f"parameter item {item[:32]!r}",
                    offset=offset,
                    expected="Name_<integer>",
                    protocol=PROTOCOL,
                )
            out[name] = int(value)
        offset += len(item) + 1
    if "Pixel" not in out:
        raise FramingError(
            "parameter string has no Pixel_<N> item", offset=0, expected="Pixel_<N>", protocol=PROTOCOL
        )
    return out


def _check_binary(reply: bytes, n_bytes: int, what: str) -> None:
    if n_bytes < 4:
        raise ValueError(f"{what}: the element count must be >= 0")
    if len(reply) < n_bytes:
        raise TruncatedFrameError(
            f"{what} reply of {len(reply)} bytes",
            offset=len(reply),
            expected=f"exactly {n_bytes} bytes ending in 'Ende'",
            protocol=PROTOCOL,
        )
    if len(reply) > n_bytes:
        raise OversizeFrameError(
            f"{what} reply of {len(reply)} bytes",
            offset=n_bytes,
            expected=f"exactly {n_bytes} bytes ending in 'Ende'",
            protocol=PROTOCOL,
        )
    if reply[-4:] != END:
        raise FramingError(
            f"{what} reply ends with {bytes(reply[-4:])!r}",
            offset=n_bytes - 4,
            expected="the trailer 'Ende'",
            protocol=PROTOCOL,
        )


def encode_spectrum(counts: np.ndarray | Sequence[int]) -> bytes:
    """Reply to ``s>``: N × uint16 LE counts, then ``Ende`` (2N + 4 bytes)."""
    c = np.asarray(counts)
    if c.ndim != 1 or not np.issubdtype(c.dtype, np.number):
        raise ValueError(f"spectrum: expected a 1-D array of counts, got shape {c.shape} dtype {c.dtype}")
    if c.size and (np.any(c < 0) or np.any(c > 65535) or not np.all(np.isfinite(c))):
        raise ValueError("spectrum: counts must lie in 0..65535")
    return np.round(c).astype("<u2").tobytes() + END


def decode_spectrum(reply: bytes, n_pixels: int) -> np.ndarray:
    """Client side of ``s>``: uint16 counts, shape (n_pixels,); exactly 2N + 4 bytes ending ``Ende``."""
    _check_binary(reply, 2 * n_pixels + 4, "spectrum")
    return np.frombuffer(reply, dtype="<u2", count=n_pixels).astype(np.uint16)


def encode_pixel_wavelengths(wavelengths_nm: np.ndarray | Sequence[float]) -> bytes:
    """Reply to ``WLL>``: N × uint32 LE pixel wavelengths in 1e-4 nm, then ``Ende`` (4N + 4 bytes)."""
    w = np.asarray(wavelengths_nm, dtype=np.float64)
    if w.ndim != 1 or not np.all(np.isfinite(w)) or np.any(w < 0) or np.any(w * 1e4 > 2**32 - 1):
        raise ValueError("pixel wavelengths: expected a 1-D array of finite nm in 0..429496.7295")
    return np.round(w * 1e4).astype("<u4").tobytes() + END


def decode_pixel_wavelengths(reply: bytes, n_pixels: int) -> np.ndarray:
    """Client side of ``WLL>``: pixel wavelengths, nm, shape (n_pixels,); exact length checked."""
    _check_binary(reply, 4 * n_pixels + 4, "WLL")
    return np.frombuffer(reply, dtype="<u4", count=n_pixels) / 1e4


@dataclass(frozen=True, eq=False)
class PeakReply:
    """A decoded ``P>`` reply.

    Attributes
    ----------
    first, second : ndarray of float64, shape (n,)
        ``OBB,0``: peak wavelength, nm (NaN where the device sent 0), and amplitude (counts).
        ``OBB,1``: strain (the int32 / 1e4) and temperature, °C (the int32 / 100).
    device_temperature : float
        Device temperature, °C.
    onboard : bool
        Which of the two layouts ``first``/``second`` hold.
    """

    first: np.ndarray
    second: np.ndarray
    device_temperature: float
    onboard: bool = False

    @property
    def wavelengths(self) -> np.ndarray:
        """Peak wavelengths, nm (only for ``OBB,0`` replies)."""
        if self.onboard:
            raise ValueError("an OBB,1 reply carries strain and temperature, not wavelengths")
        return self.first


def encode_peaks(
    first: np.ndarray | Sequence[float],
    second: np.ndarray | Sequence[float] | None = None,
    *,
    device_temperature: float = 21.0,
    onboard: bool = False,
) -> bytes:
    """Reply to ``P>`` (8n + 12 bytes).

    Parameters
    ----------
    first : array_like, shape (n,)
        ``onboard=False``: peak wavelengths, nm (NaN or ≤ 0 → a missing peak, sent as 0 with amplitude 0);
        ``onboard=True``: strain (sent × 1e4; the simulator passes µε).
    second : array_like, shape (n,), optional
        ``onboard=False``: amplitudes, counts (default 0); ``onboard=True``: temperature, °C (sent × 100).
    device_temperature : float
        Device temperature, °C (int16 × 100).
    onboard : bool
        Layout of the two int32 per peak.
    """
    a = np.atleast_1d(np.asarray(first, dtype=np.float64))
    b = np.zeros_like(a) if second is None else np.atleast_1d(np.asarray(second, dtype=np.float64))
    if a.ndim != 1 or b.shape != a.shape:
        raise ValueError(f"peaks: expected two 1-D arrays of one length, got {a.shape} and {b.shape}")
    if onboard:
        ia, ib = np.round(a * 1e4), np.round(b * 100)
        if not (np.all(np.isfinite(ia)) and np.all(np.isfinite(ib))):
            raise ValueError("peaks: on-board strain and temperature must be finite")
    else:
        present = np.isfinite(a) & (a > 0)
        ia = np.where(present, np.round(np.where(present, a, 0.0) * 1e4), 0.0)
        ib = np.where(present & np.isfinite(b), np.round(np.where(np.isfinite(b), b, 0.0)), 0.0)
    lim = 2.0**31
    if np.any(np.abs(ia) >= lim) or np.any(np.abs(ib) >= lim):
        raise ValueError("peaks: a value does not fit the int32 field")
    t = round(device_temperature * 100)
    if not -32768 <= t <= 32767:
        raise ValueError(f"device_temperature {device_temperature} °C does not fit the int16 field")
    body = np.empty((a.size, 2), dtype="<i4")
    body[:, 0], body[:, 1] = ia, ib
    tail = np.array([t, 0], dtype="<i2").tobytes() + bytes(4)
    return body.tobytes() + tail + END


def decode_peaks(reply: bytes, n_peaks: int, *, onboard: bool = False) -> PeakReply:
    """Client side of ``P>`` for ``n_peaks`` windows (the ``KA`` setting); exact length 8n + 12 checked.

    A wavelength of 0 decodes to NaN (a missing peak).
    """
    if n_peaks < 0:
        raise ValueError(f"n_peaks: expected >= 0, got {n_peaks}")
    _check_binary(reply, 8 * n_peaks + 12, "P")
    body = np.frombuffer(reply, dtype="<i4", count=2 * n_peaks).reshape(n_peaks, 2).astype(np.float64)
    temp = int.from_bytes(reply[8 * n_peaks : 8 * n_peaks + 2], "little", signed=True) / 100
    if onboard:
        return PeakReply(body[:, 0] / 1e4, body[:, 1] / 100, temp, onboard=True)
    lam = body[:, 0] / 1e4
    lam[body[:, 0] <= 0] = np.nan
    amp = np.where(np.isnan(lam), np.nan, body[:, 1])
    return PeakReply(lam, amp, temp, onboard=False)


def peaks_to_frame(reply: PeakReply, *, sequence: int = -1, timestamp: float = float("nan")) -> Frame:
    """A one-core :class:`~twin.frames.Frame` (shape (n, 1)) from an ``OBB,0`` peak reply.

    Amplitudes become the powers; a missing peak gets NaN and :attr:`~twin.frames.PeakStatus.MISSING`.
    """
    lam = reply.wavelengths[:, None]
    status = np.where(np.isnan(lam), np.uint8(PeakStatus.MISSING), np.uint8(0)).astype(np.uint8)
    return Frame(
        wavelengths=lam, timestamp=timestamp, sequence=sequence, powers=reply.second[:, None], status=status
    )


# ------------------------------------------------------------------------------------------------- spectrum


def default_pixel_wavelengths(
    n_pixels: int = 2048, start_nm: float = 1500.0, stop_nm: float = 1600.0
) -> np.ndarray:
    """The simulator's pixel → wavelength table: linear ``start_nm`` to ``stop_nm``, quantised to 1e-4 nm.

    Returns
    -------
    ndarray of float64, shape (n_pixels,)
        Pixel wavelengths, nm; exactly what :func:`decode_pixel_wavelengths` returns after a round trip.
    """
    if n_pixels < 2 or not stop_nm > start_nm > 0:
        raise ValueError("pixel table: expected n_pixels >= 2 and 0 < start_nm < stop_nm")
    return np.round(np.linspace(start_nm, stop_nm, n_pixels) * 1e4) / 1e4


def synthetic_spectrum(
    peaks_nm: np.ndarray | Sequence[float],
    pixel_wavelengths_nm: np.ndarray,
    *,
    amplitude: float | np.ndarray = 20000.0,
    baseline: float = 1000.0,
    fwhm_nm: float = 0.2,
    lead_pixel: int = 16,
    noise_counts: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """A uint16 spectrum whose peaks the ``myfbgcommunication`` client finds at ``peaks_nm``.

    Gaussian reflection peaks (FWHM ``fwhm_nm``) on a flat ``baseline``, plus one leading reference peak at
    pixel ``lead_pixel`` because the client drops the first peak it finds. The result is verified with the
    client's own detection (pixels 0–2 replaced by pixel 3, minus pixel 0, ``find_peaks(height=10,
    distance=50, prominence=100)``, first peak dropped), so a spectrum the client would misread is never
    returned.

    Parameters
    ----------
    peaks_nm : array_like, shape (n,)
        Peak wavelengths, nm, increasing; quantised to 1e-4 nm. Each must fall at least 50 pixels after the
        previous one (and after the reference peak) and 4 pixels inside the table's end.
    pixel_wavelengths_nm : ndarray, shape (N,)
        Increasing pixel → wavelength table, nm (e.g. :func:`default_pixel_wavelengths`).
    amplitude : float or array_like, shape (n,)
        Peak heights above the baseline, counts (the reference peak uses the largest).
    baseline : float
        Background level, counts.
    fwhm_nm : float
        Full width at half maximum of each peak, nm.
    lead_pixel : int
        Pixel of the extra leading reference peak (at least 8, clear of the pixels the client overwrites).
    noise_counts : float
        Standard deviation of additive Gaussian noise, counts (0: none). Keep it well below 100/3 so noise
        cannot pass the client's prominence threshold.
    rng : numpy.random.Generator, optional
        Source of the noise.

    Returns
    -------
    ndarray of uint16, shape (N,)

    Raises
    ------
    ValueError
        Peaks outside the table, closer than 50 pixels, a spectrum that would not fit uint16, or one the
        client would not read back as exactly these peaks.
    """
    from scipy.signal import find_peaks  # scipy is a runtime dependency; imported here to keep import light

    wl = np.asarray(pixel_wavelengths_nm, dtype=np.float64)
    n_pix = wl.size
    if wl.ndim != 1 or n_pix < 2 or np.any(np.diff(wl) <= 0):
        raise ValueError("pixel_wavelengths_nm: expected an increasing 1-D table")
    peaks = quantise_nm(np.atleast_1d(np.asarray(peaks_nm, dtype=np.float64)))
    if peaks.ndim != 1 or not np.all(np.isfinite(peaks)):
        raise ValueError("peaks_nm: expected finite wavelengths, nm")
    amp = np.broadcast_to(np.asarray(amplitude, dtype=np.float64), peaks.shape)
    if not 8 <= lead_pixel < n_pix:
        raise ValueError(f"lead_pixel: expected 8 to {n_pix - 1}, got {lead_pixel}")
    if np.any(peaks < wl[0]) or np.any(peaks > wl[-1]):
        raise ValueError(f"peaks_nm: every peak must lie in the table's {wl[0]}–{wl[-1]} nm")
    pix = np.interp(peaks, wl, np.arange(n_pix, dtype=np.float64))
    all_pix = np.concatenate([[float(lead_pixel)], pix])
    if np.any(np.diff(np.round(all_pix)) < 50):
        raise ValueError(
            "peaks_nm: peaks (and the leading reference peak at pixel "
            f"{lead_pixel}) must be at least 50 pixels apart; pixels {np.round(pix).astype(int)}"
        )
    if np.any(np.round(pix) > n_pix - 5):
        raise ValueError("peaks_nm: a peak within 4 pixels of the table's end cannot be detected")
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    centres = np.concatenate([[wl[lead_pixel]], peaks])
    heights = np.concatenate([[amp.max() if amp.size else 20000.0], amp])
    spec = np.full(n_pix, float(baseline))
    for c, h in zip(centres, heights, strict=True):
        # each peak only touches ±8σ around it; cheaper than a dense (n_peaks, N) matrix
        lo, hi = np.searchsorted(wl, [c - 8 * sigma, c + 8 * sigma])
        spec[lo:hi] += h * np.exp(-0.5 * ((wl[lo:hi] - c) / sigma) ** 2)
    if noise_counts > 0:
        spec += (rng or np.random.default_rng()).normal(0.0, noise_counts, n_pix)
    if np.any(spec < 0) or np.any(spec > 65535):
        raise ValueError("synthetic spectrum exceeds the uint16 range; lower amplitude or baseline")
    out = np.round(spec).astype(np.uint16)

    seen = out.astype(np.float64)
    seen[0:3] = seen[3]
    found, _ = find_peaks(seen - seen[0], height=10, distance=50, prominence=100)
    want = np.round(all_pix).astype(int)
    if found.size != want.size or np.any(np.abs(found - want) > 1):
        raise ValueError(
            f"synthetic spectrum: the client would find peaks at pixels {found.tolist()}, "
            f"not {want.tolist()} (amplitude too low, or noise too high?)"
        )
    return out
