"""voxfusion: real-time dense RGB-D SLAM (Vox-Fusion) as a library, a CLI and a streaming server.

The engine lives in :mod:`voxfusion.core` (repository folder ``core/``); the server, wire format and
clients in :mod:`voxfusion.server`, :mod:`voxfusion.proto` and :mod:`voxfusion.clients`.
"""

__version__ = "0.1.0"
