"""FiSpec-type USB-serial interrogator protocol (docs/protocols.md §2), one protocol in one package.

- :mod:`~twin.io.fispec.codec`: the wire format (encoders and decoders, both directions);
- :mod:`~twin.io.fispec.driver`: the ``fispec://`` source.

The driver imports the codec; neither imports this face.
"""

from twin.io.fispec.codec import (
    BAUDRATE,
    COMMAND_ARITY,
    END,
    SILENT_COMMANDS,
    Command,
    CommandParser,
    PeakReply,
    decode_identity,
    decode_parameters,
    decode_peaks,
    decode_pixel_wavelengths,
    decode_spectrum,
    default_pixel_wavelengths,
    encode_command,
    encode_identity,
    encode_parameters,
    encode_peaks,
    encode_pixel_wavelengths,
    encode_spectrum,
    parameter_items,
    peaks_to_frame,
    quantise_nm,
    synthetic_spectrum,
)
from twin.io.fispec.driver import FispecSource, open_fispec

__all__ = [
    "BAUDRATE",
    "COMMAND_ARITY",
    "END",
    "SILENT_COMMANDS",
    "Command",
    "CommandParser",
    "FispecSource",
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
    "open_fispec",
    "parameter_items",
    "peaks_to_frame",
    "quantise_nm",
    "synthetic_spectrum",
]
