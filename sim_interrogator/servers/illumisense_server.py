"""ILLumiSense TCP stream server: pushes one record per frame of a Source to every client
(docs/protocols-illumisense.md).

By default the records have the layout ILLumiSense sends with its shape output on: the channel blocks, then
one sensor block filled from a reconstruction of the frame's own wavelengths — the project's default
:class:`~twin.reconstruct.Reconstructor` with the source's fibre model (for the twin, its datasheet fibre: no
calibration, as a vendor box set up from the datasheet would be), curvature |κ| and bending angle at the
gratings, shape points every 1 mm in the vendor frame (x along the fibre axis,
:data:`twin.io.illumisense.vendor.VENDOR_FROM_BASE`). ``blocks="engineering"`` sends the older layout instead
(E = every grating's optical strain in µε), ``blocks="none"`` the channel blocks alone. The client sends
nothing; clients may connect and disconnect at any time, and each one gets the records from the moment it
connected (a client that falls ~4 s behind, or takes no data for 30 s, is dropped; at most 32 at once, one more
evicts the one furthest behind: :mod:`sim_interrogator.servers.common`).
"""

from __future__ import annotations

import numpy as np

from sim_interrogator.servers.common import IDLE_TIMEOUT, MAX_CLIENTS, FramePump, TcpBroadcaster, log
from twin.frames import Frame
from twin.io import illumisense
from twin.io.source import Source

__all__ = ["BLOCKS", "IllumisenseServer"]

BLOCKS = ("sensors", "engineering", "none")


class IllumisenseServer:
    """Serve a Source as an ILLumiSense TCP stream.

    Parameters
    ----------
    source : Source
        Frames to serve (owned: closed by :meth:`close`).
    host, port : str, int
        Where to listen (127.0.0.1 by default; port 0 picks a free port, see :attr:`address`).
    rate : float, optional
        Extra pacing for sources that are not real-time, Hz (see :class:`FramePump`).
    channels_as : {"cores", "single"}
        One channel per core (default) or all cores spliced onto one channel.
    blocks : {"sensors", "engineering", "none"}
        What follows the channel blocks (module docstring). "sensors" and "engineering" need ``source.fiber``;
        without it nothing follows.
    log : bool
        Print client connects and disconnects on stderr.
    max_clients, idle_timeout : int, float
        Most clients at once (one more evicts the one furthest behind); longest a client may take no data, s
        (:class:`~sim_interrogator.servers.common.TcpBroadcaster`).
    """

    def __init__(self, source: Source, host: str = "127.0.0.1", port: int = illumisense.DEFAULT_PORT, *,
                 rate: float | None = None, channels_as: str = "cores", blocks: str = "sensors", log: bool = False,
                 max_clients: int = MAX_CLIENTS, idle_timeout: float = IDLE_TIMEOUT):
        if blocks not in BLOCKS:
            raise ValueError(f"blocks: expected one of {', '.join(BLOCKS)}, got {blocks!r}")
        self.source = source
        self.channels_as = channels_as
        self.blocks = blocks
        self.fiber = getattr(source, "fiber", None)
        self._rec = None
        if blocks == "sensors" and self.fiber is not None:
            from twin.reconstruct import Reconstructor

            self._rec = Reconstructor(self.fiber)
        self.broadcaster = TcpBroadcaster(host, port, name="illumisense", log=log, max_clients=max_clients,
                                          idle_timeout=idle_timeout)
        self.pump = FramePump(source, rate=rate)
        self.pump.subscribe(self._publish)
        self.records_sent = 0
        self.encode_errors = 0

    @property
    def address(self) -> tuple[str, int]:
        return self.broadcaster.address

    def encode(self, frame: Frame) -> bytes:
        """The wire record of one frame."""
        f = self.fiber
        fits = f is not None and frame.wavelengths.shape == (f.n_gratings, f.n_cores)
        if self.blocks == "engineering" and fits:
            eps = (frame.wavelengths - f.lambda0) / f.lambda0 * 1e6
            return illumisense.encode_record(frame, strain=eps, channels_as=self.channels_as)
        sensors = None
        if self._rec is not None and fits:
            from twin.io.illumisense.vendor import vendor_sensors

            shape = self._rec(frame.wavelengths[None])
            if np.isfinite(shape.positions).all():
                sensors = vendor_sensors(shape)
        return illumisense.encode_record(frame, sensors=sensors, channels_as=self.channels_as)

    def _publish(self, frame: Frame) -> None:
        if self.broadcaster.clients == 0:
            return  # nobody listens: save the encoding
        try:
            data = self.encode(frame)
        except (ValueError, FloatingPointError) as exc:  # a frame the codec cannot write must not stop the pump
            self.encode_errors += 1
            if self.encode_errors == 1:
                log(f"illumisense: a frame could not be encoded: {exc}")
            return
        self.broadcaster.publish(data)
        self.records_sent += 1

    def start(self) -> IllumisenseServer:
        self.broadcaster.start()
        self.pump.start()
        return self

    def close(self) -> None:
        self.pump.stop()
        self.broadcaster.close()
        self.source.close()

    def stats(self) -> dict:
        b = self.broadcaster
        return {"frames": self.pump.frames, "records_sent": self.records_sent, "clients": b.clients,
                "connections": b.connections, "disconnects": b.disconnects, "dropped_slow": b.dropped_slow,
                "dropped_idle": b.dropped_idle, "evicted": b.evicted,
                "encode_errors": self.encode_errors}

    def __enter__(self) -> IllumisenseServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
