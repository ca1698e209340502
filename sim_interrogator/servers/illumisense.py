"""ILLumiSense TCP stream server: pushes one record per frame of a Source to every client (docs/protocols.md §1).

The records are :func:`twin.io.illumisense.encode_record` of each frame (wavelengths with 4 decimals, i.e. the
protocol's 0.1 pm), with the optical strain of every grating in µε as the engineering values when the source
knows its fibre model. The client sends nothing; clients may connect and disconnect at any time, and each
one gets the records from the moment it connected (a client that falls ~4 s behind is dropped).
"""

from __future__ import annotations

from sim_interrogator.servers.common import FramePump, TcpBroadcaster
from twin.frames import Frame
from twin.io import illumisense
from twin.io.source import Source

__all__ = ["IllumisenseServer"]


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
    strain : bool
        Send the optical strain (µε) as engineering values (needs ``source.fiber``); else E = 0.
    log : bool
        Print client connects and disconnects on stderr.
    """

    def __init__(self, source: Source, host: str = "127.0.0.1", port: int = illumisense.DEFAULT_PORT, *,
                 rate: float | None = None, channels_as: str = "cores", strain: bool = True, log: bool = False):
        self.source = source
        self.channels_as = channels_as
        fiber = getattr(source, "fiber", None)
        self._lambda0 = fiber.lambda0 if (strain and fiber is not None) else None
        self.broadcaster = TcpBroadcaster(host, port, name="illumisense", log=log)
        self.pump = FramePump(source, rate=rate)
        self.pump.subscribe(self._publish)
        self.records_sent = 0

    @property
    def address(self) -> tuple[str, int]:
        return self.broadcaster.address

    def encode(self, frame: Frame) -> bytes:
        """The wire record of one frame."""
        eps = None
        if self._lambda0 is not None and frame.wavelengths.shape == self._lambda0.shape:
            eps = (frame.wavelengths - self._lambda0) / self._lambda0 * 1e6
        return illumisense.encode_record(frame, strain=eps, channels_as=self.channels_as)

    def _publish(self, frame: Frame) -> None:
        if self.broadcaster.clients == 0:
            return  # nobody listens: save the encoding
        self.broadcaster.publish(self.encode(frame))
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
                "connections": b.connections, "disconnects": b.disconnects, "dropped_slow": b.dropped_slow}

    def __enter__(self) -> IllumisenseServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


