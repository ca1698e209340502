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

from twin.io.illumisense.codec import (
    ANGLE_LABEL,
    CURVATURE_LABEL,
    DEFAULT_MAX_PAYLOAD,
    DEFAULT_PORT,
    SHAPE_LABELS,
    SHAPE_SPACING,
    Record,
    VendorSensor,
    decode_many,
    decode_payload,
    decode_record,
    encode_payload,
    encode_record,
    format_timestamp,
    parse_timestamp,
)
from twin.io.illumisense.driver import IllumisenseSource, open_illumisense
from twin.io.illumisense.log import LogContents, read_log
from twin.io.illumisense.stream import LayoutConsensus, StreamDecoder
from twin.io.illumisense.vendor import VendorArrays

__all__ = [
    "ANGLE_LABEL",
    "CURVATURE_LABEL",
    "DEFAULT_MAX_PAYLOAD",
    "DEFAULT_PORT",
    "SHAPE_LABELS",
    "SHAPE_SPACING",
    "IllumisenseSource",
    "LayoutConsensus",
    "LogContents",
    "Record",
    "StreamDecoder",
    "VendorArrays",
    "VendorSensor",
    "decode_many",
    "decode_payload",
    "decode_record",
    "encode_payload",
    "encode_record",
    "format_timestamp",
    "open_illumisense",
    "parse_timestamp",
    "read_log",
]
