"""Luna / Micron Optics Hyperion TCP protocol (docs/protocols.md §3), one protocol in one package.

- :mod:`~twin.io.hyperion.codec`: the wire format (encoders and decoders, both directions);
- :mod:`~twin.io.hyperion.stream`: the peak stream's framing and resynchronisation;
- :mod:`~twin.io.hyperion.driver`: the ``hyperion://`` source.

The driver imports the codec and the stream decoder; none imports this face.
"""

from twin.io.hyperion import codec, driver, stream
from twin.io.hyperion.codec import *  # noqa: F403 -- the face: every public name of the codec and the driver
from twin.io.hyperion.driver import *  # noqa: F403
from twin.io.hyperion.stream import *  # noqa: F403

__all__ = [*codec.__all__, *stream.__all__, *driver.__all__]
