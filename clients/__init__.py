"""Clients of the VoxFusion server: :class:`Client` (HTTP) and :class:`ZenohClient` (zenoh) with the same
verbs, capture streaming (:func:`stream_capture`) and the live NeRFCapture iPhone bridge
(:mod:`voxfusion.clients.nerfcapture`).

Example::

    from voxfusion.clients import Client

    with Client("http://127.0.0.1:8000") as client:
        client.create_session("desk")
        seq = client.send_frame(frame)          # durably recorded by the server when this returns
        pose = client.latest_pose()             # PoseOut: 4x4 camera-to-world, OpenCV axes
        depth = client.render_depth(pose.T_world_cam, frame.K, 256, 192)
        client.finish()
        client.download_mesh("mesh.ply")

``ZenohClient`` needs ``eclipse-zenoh`` and ``voxfusion.clients.nerfcapture`` needs ``cyclonedds``; both
are imported only when used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .base import EncodeOptions, SessionHandle, poses_to_trajectory
from .errors import ClientError, ServerError, TransportError
from .http_client import Client
from .stream import StreamOptions, StreamResult, stream_capture, stream_frames

if TYPE_CHECKING:
    from .zenoh_client import ZenohClient

__all__ = [
    "Client",
    "ZenohClient",
    "SessionHandle",
    "EncodeOptions",
    "ClientError",
    "ServerError",
    "TransportError",
    "StreamOptions",
    "StreamResult",
    "stream_capture",
    "stream_frames",
    "poses_to_trajectory",
]


def __getattr__(name: str) -> Any:  # noqa: ANN401 - lazy import of the optional zenoh client
    if name == "ZenohClient":
        from .zenoh_client import ZenohClient

        return ZenohClient
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
