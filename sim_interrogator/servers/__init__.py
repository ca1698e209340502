"""Protocol servers: a simulated interrogator behind the ILLumiSense, FiSpec and Hyperion wire protocols.

Each server takes any :class:`twin.io.Source` (the simulator, the synthetic forward-model source, a replay) and
serves its frames with the codecs of :mod:`twin.io`, so the project's drivers — or a lab's own acquisition
software — read the twin as hardware. ``twin serve PROTOCOL`` (:mod:`sim_interrogator.serve`) runs them.
"""

from sim_interrogator.servers.common import FramePump, TcpBroadcaster
from sim_interrogator.servers.fispec_server import FispecServer
from sim_interrogator.servers.hyperion_server import HyperionServer
from sim_interrogator.servers.illumisense_server import IllumisenseServer

__all__ = ["FispecServer", "FramePump", "HyperionServer", "IllumisenseServer", "TcpBroadcaster"]
