"""FBGS ILLumiSense TCP data stream (docs/protocols-illumisense.md), one protocol in one package.

The package's public face re-exports what users of the protocol need; the modules hold one job each:

- :mod:`~twin.io.illumisense.codec`: record encoder and batch decoder (one payload or many at once);
- :mod:`~twin.io.illumisense.scan`: the compiled tokenizer the decoders share;
- :mod:`~twin.io.illumisense.stream`: the stream decoder (length prefixes, resync, layout consensus);
- :mod:`~twin.io.illumisense.vendor`: the vendor's sensor (shape) blocks;
- :mod:`~twin.io.illumisense.log`: the vendor's log files;
- :mod:`~twin.io.illumisense.driver`: the ``illumisense://`` source.

Imports run one way: scan ← codec ← stream ← log, driver; no module of the package imports this face.
"""

from twin.io.illumisense import codec, driver, log, stream
from twin.io.illumisense.codec import *  # noqa: F403 -- the face: every public name of its modules
from twin.io.illumisense.codec import SHAPE_SPACING
from twin.io.illumisense.driver import *  # noqa: F403
from twin.io.illumisense.log import *  # noqa: F403
from twin.io.illumisense.stream import *  # noqa: F403

__all__ = [*codec.__all__, "SHAPE_SPACING", *stream.__all__, *log.__all__, *driver.__all__]
