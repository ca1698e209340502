"""Luna / Micron Optics Hyperion TCP protocol (docs/protocols.md §3), one protocol in one package.

- :mod:`~twin.io.hyperion.codec`: the wire format (encoders and decoders, both directions);
- :mod:`~twin.io.hyperion.driver`: the ``hyperion://`` source.

The driver imports the codec; neither imports this face.
"""

from twin.io.hyperion.codec import (
    COMMAND_PORT,
    STREAM_PEAKS_PORT,
    InstrumentState,
    PeakHeader,
    Request,
    RequestDecoder,
    Response,
    ResponseDecoder,
    decode_ascii,
    decode_i32_array,
    decode_peaks,
    decode_peaks_header,
    decode_request,
    decode_response,
    decode_u8,
    decode_u32,
    encode_peaks,
    encode_request,
    encode_response,
    encode_stream_frame,
    respond,
)
from twin.io.hyperion.driver import HyperionSource, assign_peaks, open_hyperion

__all__ = [
    "COMMAND_PORT",
    "STREAM_PEAKS_PORT",
    "HyperionSource",
    "InstrumentState",
    "PeakHeader",
    "Request",
    "RequestDecoder",
    "Response",
    "ResponseDecoder",
    "assign_peaks",
    "decode_ascii",
    "decode_i32_array",
    "decode_peaks",
    "decode_peaks_header",
    "decode_request",
    "decode_response",
    "decode_u8",
    "decode_u32",
    "encode_peaks",
    "encode_request",
    "encode_response",
    "encode_stream_frame",
    "open_hyperion",
    "respond",
]
