"""The VoxFusion wire format: one versioned binary frame container (HTTP and zenoh) and the JSON API schemas.

The byte-level specification is ``proto/README.md``; a client in any language can be written from it.

Example::

    from voxfusion.proto import decode_frame, encode_frame

    data = encode_frame(frame, seq=0, session="desk")   # bytes, Content-Type MEDIA_TYPE
    decoded = decode_frame(data)                        # DecodedFrame(frame=RGBDFrame, seq, session, header)
"""

from .codecs import (
    COLOR_ENCODINGS,
    CONFIDENCE_ENCODINGS,
    CONFIDENCE_LEVELS,
    DEPTH_ENCODINGS,
    ColorEncoding,
    ConfidenceEncoding,
    DepthEncoding,
)
from .container import (
    ERROR_FIELDS,
    MAGIC,
    MEDIA_TYPE,
    WIRE_VERSION,
    FrameDecodeError,
    FrameEncodingError,
    FrameValueError,
)
from .frame_codec import (
    DecodedFrame,
    DecodeLimits,
    FrameHeader,
    PoseConvention,
    WireIntrinsics,
    decode_frame,
    encode_frame,
    read_header,
)

__all__ = [
    "MAGIC",
    "WIRE_VERSION",
    "MEDIA_TYPE",
    "ERROR_FIELDS",
    "FrameDecodeError",
    "FrameValueError",
    "FrameEncodingError",
    "DEPTH_ENCODINGS",
    "COLOR_ENCODINGS",
    "CONFIDENCE_ENCODINGS",
    "CONFIDENCE_LEVELS",
    "DepthEncoding",
    "ColorEncoding",
    "ConfidenceEncoding",
    "PoseConvention",
    "WireIntrinsics",
    "DecodeLimits",
    "FrameHeader",
    "DecodedFrame",
    "encode_frame",
    "decode_frame",
    "read_header",
]
