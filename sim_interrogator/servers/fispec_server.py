"""FiSpec-type serial interrogator on pseudo-terminals (docs/protocols.md §2): one pty per fibre core.

A FiSpec device measures one channel, so the server opens one pseudo-terminal per served core and answers the
commands the ``myfbgcommunication`` client (and :class:`twin.io.fispec.driver.FispecSource`) send, from the latest
frame of the Source:

- ``?>`` identity ``FiSpec FBG X150``. It also discards replies still waiting in the pty from an earlier
  client (a new session starts with ``?>``).
- ``p?>`` the parameters as set: ``Pixel_2048#Kanalanzahl_<KA>#tInt_<iz>#Mittelungen_<m>#OBBerechnen_<OBB>``.
- ``s>`` a synthetic spectrum (:func:`twin.io.fispec.synthetic_spectrum`) with the core's present peaks plus
  the leading reference peak the client drops; peaks closer than the client's 50-pixel detection distance are
  left out of the spectrum (a real spectrometer would merge them too).
- ``WLL>`` the pixel table, 1500–1600 nm over 2048 pixels.
- ``P>`` for each of the ``KA`` windows set with ``Ke``: the peak of the core whose wavelength lies in the
  window (the one nearest its centre when several do), in 1e-4 nm, with amplitude 20000; 0 and 0 when none
  does or the window is unset. With ``OBB,1`` the on-board values: strain × 1e4 in µε relative to the peak at
  the last ``OBN`` (zeroing; the window centre before any), temperature × 100 from ``OBsaT0``.
- every setter (``a``, ``LED``, ``iz``, ``Ke``, ``KA``, ``m``, ``OBsTyp``, ``OBN``, ``OBsaT0``, ``PeM``, ``OBB``)
  is applied and gets no reply at all.

The pty follows the harness of docs/protocols.md §2.5: ``master, slave = os.openpty(); tty.setraw(master)``; the server
keeps ``slave`` open for its whole life, so clients may open and close the port path (``os.ttyname(slave)``)
as often as they like. ``link`` adds a stable symlink to the pty path (like socat's ``link=``), which survives
server restarts for clients that reconnect by path.
"""

from __future__ import annotations

import os
import select
import termios
import threading
import time
import tty
from pathlib import Path

import numpy as np

from sim_interrogator.servers.common import FramePump, log
from twin.frames import Frame
from twin.io import fispec
from twin.io.source import Source

__all__ = ["FispecPort", "FispecServer"]

AMPLITUDE = 20000  #: counts reported per peak (and the spectrum's peak height)


class FispecPort:
    """One simulated FiSpec device on a pseudo-terminal, serving core ``core`` of the pump's frames.

    Attributes
    ----------
    path : str
        The pty path a client opens.
    link : Path or None
        The symlink to it, when asked for.
    commands, errors : int
        Commands answered / chunks the parser dropped.
    """

    def __init__(self, pump: FramePump, core: int, *, link: str | Path | None = None,
                 pixel_wavelengths: np.ndarray | None = None, strain_sensitivity: float = 0.777):
        self.pump, self.core = pump, int(core)
        self.pixels = fispec.default_pixel_wavelengths() if pixel_wavelengths is None else pixel_wavelengths
        self.s_eps = strain_sensitivity
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.link = Path(link) if link else None
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.path)
            tmp.replace(self.link)  # atomic: a reconnecting client never sees a missing link
        self.parser = fispec.CommandParser()
        # device settings, as the setters leave them
        self.ka = 0
        self.windows: dict[int, tuple[int, int]] = {}
        self.integration_us = 50_000
        self.averages = 1
        self.onboard = False
        self.t0_centi = 2100
        self.zero: dict[int, float] = {}
        self.commands = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"fispec-core{core}", daemon=True)

    @property
    def errors(self) -> int:
        return self.parser.errors

    def start(self) -> FispecPort:
        self._thread.start()
        return self

    # ---------------------------------------------------------------- the current peaks
    def _core_peaks(self) -> np.ndarray:
        frame: Frame | None = self.pump.latest
        if frame is None or self.core >= frame.wavelengths.shape[1]:
            return np.empty(0)
        w = frame.wavelengths[:, self.core]
        return fispec.quantise_nm(w[np.isfinite(w) & (w > 0)])

    def _window_peaks(self) -> np.ndarray:
        """Peak wavelength per window, nm (NaN where the window holds no peak)."""
        peaks = self._core_peaks()
        out = np.full(self.ka, np.nan)
        for i in range(self.ka):
            win = self.windows.get(i)
            if win is None or peaks.size == 0:
                continue
            lo, hi = win[0] * 1e-4, win[1] * 1e-4
            inside = peaks[(peaks >= lo) & (peaks <= hi)]
            if inside.size:
                out[i] = inside[np.argmin(np.abs(inside - 0.5 * (lo + hi)))]
        return out

    def spectrum(self) -> np.ndarray:
        """The uint16 spectrum of the current peaks, as ``s>`` sends it."""
        peaks = np.sort(self._core_peaks())
        pix = np.interp(peaks, self.pixels, np.arange(self.pixels.size))
        keep, last = [], 16.0  # the reference peak sits at pixel 16
        for p, px in zip(peaks, pix, strict=True):
            if round(px) - round(last) >= 50 and 4 < px < self.pixels.size - 5:
                keep.append(p)
                last = px
        try:
            return fispec.synthetic_spectrum(keep, self.pixels, amplitude=AMPLITUDE)
        except ValueError:
            return fispec.synthetic_spectrum([], self.pixels, amplitude=AMPLITUDE)

    # ---------------------------------------------------------------- commands
    def reply(self, cmd: fispec.Command) -> bytes:
        """The bytes to send for one command (empty for setters)."""
        name, args = cmd.name, cmd.args
        if name == "?":
            # a new session: replies an earlier client left unread must not reach this one
            termios.tcflush(self.slave, termios.TCIFLUSH)
            return fispec.encode_identity()
        if name == "p?":
            return fispec.encode_parameters(fispec.parameter_items(
                pixels=self.pixels.size, channels=self.ka, integration_time_us=self.integration_us,
                averages=self.averages, onboard=self.onboard))
        if name == "s":
            return fispec.encode_spectrum(self.spectrum())
        if name == "WLL":
            return fispec.encode_pixel_wavelengths(self.pixels)
        if name == "P":
            lam = self._window_peaks()
            if not self.onboard:
                amp = np.where(np.isnan(lam), 0.0, AMPLITUDE)
                return fispec.encode_peaks(lam, amp)
            ref = np.array([self.zero.get(i, 0.5e-4 * sum(self.windows.get(i, (0, 0)))) for i in range(self.ka)])
            with np.errstate(invalid="ignore", divide="ignore"):
                ue = np.where(np.isfinite(lam) & (ref > 0), (lam - ref) / np.where(ref > 0, ref, 1) / self.s_eps
                              * 1e6, 0.0)
            temp = np.full(self.ka, self.t0_centi / 100)
            return fispec.encode_peaks(ue, temp, onboard=True)
        if name == "Ke":
            i, lo, hi = args
            if 0 <= i < 4096 and 0 <= lo < hi:
                self.windows[i] = (lo, hi)
        elif name == "KA":
            self.ka = max(0, min(int(args[0]), 4096))
        elif name == "iz":
            self.integration_us = int(args[0])
        elif name == "m":
            self.averages = int(args[0])
        elif name == "OBB":
            self.onboard = bool(args[0])
        elif name == "OBsaT0":
            self.t0_centi = int(args[0])
        elif name == "OBN":
            lam = self._window_peaks()
            self.zero = {i: float(v) for i, v in enumerate(lam) if np.isfinite(v)}
        return b""  # setters ('a', 'LED', 'OBsTyp', 'PeM', … too) get no reply

    def _write(self, data: bytes, timeout: float = 2.0) -> None:
        deadline = time.monotonic() + timeout
        view = memoryview(data)
        while view:
            if time.monotonic() > deadline:
                termios.tcflush(self.slave, termios.TCIFLUSH)  # nobody reads: drop the reply
                return
            _, ready, _ = select.select([], [self.master], [], 0.1)
            if ready:
                try:
                    n = os.write(self.master, view)
                except BlockingIOError:
                    continue
                view = view[n:]

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.master], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(self.master, 4096)
            except OSError:
                if self._stop.is_set():
                    break
                time.sleep(0.05)
                continue
            for cmd in self.parser.feed(data):
                self.commands += 1
                try:
                    out = self.reply(cmd)
                except (ValueError, OSError) as exc:
                    log(f"fispec core {self.core}: {cmd.name}: {exc}")
                    continue
                if out:
                    try:
                        self._write(out)
                    except OSError:
                        pass

    def close(self) -> None:
        """Stop serving and close the pty (clients see the device disappear)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.link is not None:
            try:
                if self.link.is_symlink() and os.readlink(self.link) == self.path:
                    self.link.unlink()
            except OSError:
                pass


class FispecServer:
    """Serve a Source as FiSpec devices, one pseudo-terminal per core.

    Parameters
    ----------
    source : Source
        Frames (owned: closed by :meth:`close`).
    cores : sequence of int, optional
        Cores to serve, one pty each (default every core of ``source.fiber``, else core 0).
    link : str, optional
        Symlink prefix: core ``k`` gets ``{link}{k}`` pointing at its pty.
    rate : float, optional
        Extra pacing, Hz (see :class:`FramePump`).
    """

    def __init__(self, source: Source, *, cores: list[int] | None = None, link: str | None = None,
                 rate: float | None = None):
        self.source = source
        fiber = getattr(source, "fiber", None)
        if cores is None:
            cores = list(range(fiber.n_cores)) if fiber is not None else [0]
        s_eps = fiber.strain_sensitivity if fiber is not None else 0.777
        self.pump = FramePump(source, rate=rate)
        self.ports = [FispecPort(self.pump, c, link=f"{link}{c}" if link else None, strain_sensitivity=s_eps)
                      for c in cores]

    @property
    def paths(self) -> list[str]:
        return [p.path for p in self.ports]

    def start(self) -> FispecServer:
        self.pump.start()
        for p in self.ports:
            p.start()
        return self

    def close(self) -> None:
        for p in self.ports:
            p.close()
        self.pump.stop()
        self.source.close()

    def stats(self) -> dict:
        return {"frames": self.pump.frames, "commands": sum(p.commands for p in self.ports),
                "command_errors": sum(p.errors for p in self.ports)}

    def __enter__(self) -> FispecServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
