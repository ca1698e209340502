"""FiSpec-type USB-serial interrogator protocol (docs/protocols.md §2), one protocol in one package.

- :mod:`~twin.io.fispec.codec`: the wire format (encoders and decoders, both directions);
- :mod:`~twin.io.fispec.driver`: the ``fispec://`` source.

The driver imports the codec; neither imports this face.
"""

from twin.io.fispec import codec, driver
from twin.io.fispec.codec import *  # noqa: F403 -- the face: every public name of the codec and the driver
from twin.io.fispec.driver import *  # noqa: F403

__all__ = [*codec.__all__, *driver.__all__]
