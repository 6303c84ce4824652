"""A stand-in for the NeRFCapture iOS app: publishes synthetic frames on the DDS topic ``Frames`` with the
app's IDL type, written here independently of ``voxfusion.clients.nerfcapture`` (exactly as NeRFCapture's
``NeRFCaptureData.idl`` and instant-ngp's ``nerfcapture2nerf.py`` declare it), over loopback.

Usage: ``python nerfcapture_publisher.py DOMAIN_ID N_FRAMES`` — waits (up to 60 s) for a matched reader,
sends ``N_FRAMES`` frames of the synthetic room (depth 96x72 float32 metres, RGB 384x288, ARKit intrinsics
for 384x288, ARKit camera-to-world column-major), waits for the reader's acknowledgements, exits 0.
"""

# No ``from __future__ import annotations``: cyclonedds resolves the IDL annotations at run time.
import sys
import time
from dataclasses import dataclass

import cv2
import cyclonedds.idl as idl
import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as types
import numpy as np
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

IMAGE_SCALE = 4
LOOPBACK = ('<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/>'
            '</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto'
            '</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex><Peers>'
            '<Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')


@dataclass
@annotate.final
@annotate.autoid("sequential")
class NeRFCaptureFrame(idl.IdlStruct, typename="NeRFCaptureData.NeRFCaptureFrame"):
    id: types.uint32
    annotate.key("id")
    timestamp: types.float64
    fl_x: types.float32
    fl_y: types.float32
    cx: types.float32
    cy: types.float32
    transform_matrix: types.array[types.float32, 16]
    width: types.uint32
    height: types.uint32
    image: types.sequence[types.uint8]
    has_depth: bool
    depth_width: types.uint32
    depth_height: types.uint32
    depth_scale: types.float32
    depth_image: types.sequence[types.uint8]


def arkit_message(i: int, frame) -> NeRFCaptureFrame:
    """What the app sends for a frame: ARKit (OpenGL-axes) pose column-major, K for the colour image."""
    h, w = frame.depth_m.shape
    T_gl = frame.T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0])
    color = cv2.resize(frame.color, (w * IMAGE_SCALE, h * IMAGE_SCALE), interpolation=cv2.INTER_LINEAR)
    K = frame.K
    return NeRFCaptureFrame(
        id=i, timestamp=frame.timestamp_s,
        fl_x=K[0, 0] * IMAGE_SCALE, fl_y=K[1, 1] * IMAGE_SCALE, cx=K[0, 2] * IMAGE_SCALE, cy=K[1, 2] * IMAGE_SCALE,
        transform_matrix=[float(v) for v in T_gl.T.reshape(-1)],  # column-major, as simd_float4x4
        width=w * IMAGE_SCALE, height=h * IMAGE_SCALE, image=color.tobytes(),
        has_depth=True, depth_width=w, depth_height=h, depth_scale=1.0,
        depth_image=frame.depth_m.astype("<f4").tobytes())


def main() -> int:
    domain_id, n_frames = int(sys.argv[1]), int(sys.argv[2])
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=n_frames, width=96, height=72, seed=5)).frames())
    domain = Domain(domain_id, LOOPBACK)  # noqa: F841 - keeps the domain's configuration alive
    participant = DomainParticipant(domain_id)
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)))
    writer = DataWriter(participant, Topic(participant, "Frames", NeRFCaptureFrame, qos=qos), qos=qos)
    deadline = time.monotonic() + 60
    while writer.get_publication_matched_status().current_count == 0:
        if time.monotonic() > deadline:
            print("no reader matched", file=sys.stderr)
            return 3
        time.sleep(0.02)
    for i, frame in enumerate(frames):
        writer.write(arkit_message(i, frame))
    writer.wait_for_acks(duration(seconds=30))
    print(f"published {n_frames} frames", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
