"""Live frames from the NeRFCapture iOS app (CycloneDDS) into a VoxFusion session.

NeRFCapture (App Store, source: github.com/jc211/NeRFCapture) publishes, in its *Online* mode, one DDS
sample per captured ARKit frame on the topic ``Frames`` of DDS domain 0, with the IDL type
``NeRFCaptureData::NeRFCaptureFrame`` (the app's ``NeRFCaptureData.idl``, identical to the type in
instant-ngp's ``scripts/nerfcapture2nerf.py``)::

    module NeRFCaptureData {
      @final struct NeRFCaptureFrame {
        @key uint32 id;                   // frame counter
        double timestamp;                 // ARFrame.timestamp, seconds (device clock)
        float fl_x; float fl_y;           // ARCamera.intrinsics, pixels, for width x height
        float cx; float cy;
        float transform_matrix[16];       // ARCamera.transform: camera-to-world, ARKit (OpenGL) camera
                                          //   axes, column-major (simd_float4x4 columns one after another)
        uint32 width; uint32 height;      // ARCamera.imageResolution (e.g. 1920x1440)
        sequence<octet> image;            // RGB8, width*height*3 bytes, row-major
        boolean has_depth;                // LiDAR devices: ARFrame.sceneDepth present
        uint32 depth_width; uint32 depth_height;   // e.g. 256x192
        float depth_scale;                // multiplies depth_image to get metres (the app sends 1.0)
        sequence<octet> depth_image;      // float32 little-endian metres, depth_width*depth_height*4 bytes
      };
    };

(Later, unreleased revisions of the app's repository add an ``ImageFormat format`` enum after ``height``;
that type is not wire-compatible with this one and is not read here.)

Conversion (:func:`convert_nerfcapture`): the pose becomes row-major (``T_gl = M.reshape(4, 4).T``) and is
converted to OpenCV camera axes (:func:`~voxfusion.core.geometry.opengl_to_opencv`); the intrinsics are
sent for the colour image's resolution (the server scales them to the depth's, as it does for every
ARKit client) and ``RGBDFrame.K`` holds them scaled to the depth resolution; the colour is downscaled
(``color_width``, default 640) before JPEG encoding. Frames without depth are skipped (counted).

Decoding a full-resolution sample with cyclonedds' generic Python deserializer takes ~0.5 s (8 MB of
image as a list of ints); :class:`NeRFCaptureFrame` overrides ``deserialize`` with
:func:`parse_nerfcapture_cdr`, which reads the same CDR bytes (XCDR1 or XCDR2, either byte order) with
slices in ~1 ms and falls back to the generic deserializer for anything else. The DDS type (and so the
type information other participants see) is exactly the app's.

Example::

    from voxfusion.clients import Client
    from voxfusion.clients.nerfcapture import run_nerfcapture_bridge

    client = Client("http://127.0.0.1:8000")
    run_nerfcapture_bridge(client, domain_id=0,           # until Ctrl-C; the session is created
                           open_session=lambda: client.create_session("iphone", preset="iphone"))  # with frame 1
"""

# No ``from __future__ import annotations`` here: cyclonedds resolves the IDL field annotations of
# :class:`NeRFCaptureFrame` at run time, and string annotations would name the wrong ``types`` module.
import logging
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ConfigError, ValidationError
from voxfusion.core.geometry import make_intrinsics, opengl_to_opencv, scale_intrinsics
from voxfusion.proto import WireIntrinsics

from .base import BaseClient

try:
    import cyclonedds.idl as idl
    import cyclonedds.idl.annotations as annotate
    import cyclonedds.idl.types as types
    from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
except ImportError as e:  # pragma: no cover - depends on the environment
    raise ConfigError("cyclonedds", "the NeRFCapture bridge needs the 'cyclonedds' package: "
                                    "pip install 'voxfusion[iphone]' (or pip install cyclonedds)") from e

__all__ = [
    "TOPIC_NAME",
    "TYPE_NAME",
    "DEFAULT_DOMAIN_ID",
    "NeRFCaptureFrame",
    "parse_nerfcapture_cdr",
    "ConvertedFrame",
    "convert_nerfcapture",
    "dds_config_xml",
    "NeRFCaptureReceiver",
    "BridgeStats",
    "run_nerfcapture_bridge",
]

log = logging.getLogger("voxfusion.clients.nerfcapture")

TOPIC_NAME = "Frames"
"""The DDS topic NeRFCapture publishes frames on."""
TYPE_NAME = "NeRFCaptureData.NeRFCaptureFrame"
"""The IDL type name (module ``NeRFCaptureData``, struct ``NeRFCaptureFrame``)."""
DEFAULT_DOMAIN_ID = 0
"""NeRFCapture's DDS domain."""


@dataclass
@annotate.final
@annotate.autoid("sequential")
class NeRFCaptureFrame(idl.IdlStruct, typename=TYPE_NAME):
    """One NeRFCapture sample (module docstring). ``image`` / ``depth_image`` are ``bytes`` when decoded by
    the fast path and lists of ints from cyclonedds' generic deserializer; both are accepted everywhere."""

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

    @classmethod
    def deserialize(cls, data: bytes, has_header: bool = True,
                    use_version_2: bool | None = None) -> "NeRFCaptureFrame":
        """Fast path (:func:`parse_nerfcapture_cdr`) for a sample with its encapsulation header; anything it
        does not handle goes to cyclonedds' generic deserializer."""
        if has_header:
            try:
                return parse_nerfcapture_cdr(data)
            except _NotHandledError:
                pass
        return cls.__idl__.deserialize(data, has_header=has_header, use_version_2=use_version_2)


class _NotHandledError(ValueError):
    """An encapsulation the fast parser does not read (handed to the generic deserializer)."""


# CDR encapsulation identifiers (DDS-XTYPES 1.3, 7.6.3.1.2) -> (little-endian, max alignment).
_ENCAPSULATIONS = {0x0000: (False, 8), 0x0001: (True, 8),      # CDR_BE / CDR_LE (XCDR1)
                   0x0006: (False, 4), 0x0007: (True, 4)}      # PLAIN_CDR2_BE / _LE (XCDR2, final struct)


def parse_nerfcapture_cdr(data: bytes | bytearray | memoryview) -> NeRFCaptureFrame:
    """Decode one serialized :class:`NeRFCaptureFrame` (4-byte encapsulation header + CDR body).

    Reads XCDR1 (8-byte alignment of the ``double``) and XCDR2 plain encoding (4-byte alignment; a final
    struct has no DHEADER), little- or big-endian; the two octet sequences come back as ``bytes`` slices.

    Raises:
        ValidationError: truncated or inconsistent data (``field`` names the member).
    """
    buf = memoryview(data).cast("B")
    if len(buf) < 4:
        raise ValidationError("cdr", f"sample of {len(buf)} bytes has no encapsulation header")
    kind = (buf[0] << 8) | buf[1]
    if kind not in _ENCAPSULATIONS:
        raise _NotHandledError(f"encapsulation 0x{kind:04x}")
    little, max_align = _ENCAPSULATIONS[kind]
    order = "<" if little else ">"
    body = buf[4:]
    pos = 0

    def take(fmt: str, size: int, field: str) -> tuple[Any, ...]:
        nonlocal pos
        pos += -pos % min(size, max_align)
        n = struct.calcsize(order + fmt)
        if pos + n > len(body):
            raise ValidationError(field, f"sample truncated at byte {pos + 4} of {len(buf)}")
        out = struct.unpack_from(order + fmt, body, pos)
        pos += n
        return out

    def octets(field: str) -> bytes:
        nonlocal pos
        (n,) = take("I", 4, field)
        if pos + n > len(body):
            raise ValidationError(field, f"sequence of {n} bytes runs past the end of the {len(buf)}-byte sample")
        out = body[pos:pos + n].tobytes()
        pos += n
        return out

    (id_,) = take("I", 4, "id")
    (timestamp,) = take("d", 8, "timestamp")
    fl_x, fl_y, cx, cy = take("4f", 4, "intrinsics")
    matrix = list(take("16f", 4, "transform_matrix"))
    width, height = take("2I", 4, "width")
    image = octets("image")
    (has_depth,) = take("?", 1, "has_depth")
    depth_width, depth_height = take("2I", 4, "depth_width")
    (depth_scale,) = take("f", 4, "depth_scale")
    depth_image = octets("depth_image")
    return NeRFCaptureFrame(id=id_, timestamp=timestamp, fl_x=fl_x, fl_y=fl_y, cx=cx, cy=cy,
                            transform_matrix=matrix, width=width, height=height, image=image,  # type: ignore[arg-type]
                            has_depth=bool(has_depth), depth_width=depth_width, depth_height=depth_height,
                            depth_scale=depth_scale, depth_image=depth_image)  # type: ignore[arg-type]


def _as_bytes(seq: Any) -> bytes:
    if isinstance(seq, (bytes, bytearray, memoryview)):
        return bytes(seq)
    return np.asarray(seq, dtype=np.uint8).tobytes()


@dataclass(frozen=True, eq=False)
class ConvertedFrame:
    """A NeRFCapture sample ready to send.

    Attributes:
        frame: depth float32 metres at the depth resolution, ``K`` for that resolution, the ARKit pose in
            OpenCV axes as ``T_world_cam_device``, ``index`` = the sample's ``id``; no colour (see ``color``).
        color: ``[Hc, Wc, 3]`` uint8 RGB (downscaled to ``color_width``), or ``None``.
        intrinsics: ARKit's intrinsics for the full colour resolution (what goes on the wire).
    """

    frame: RGBDFrame
    color: np.ndarray | None
    intrinsics: WireIntrinsics


def convert_nerfcapture(msg: NeRFCaptureFrame, *, color_width: int | None = 640) -> ConvertedFrame | None:
    """Convert one sample (module docstring); ``None`` when it has no depth (non-LiDAR device).

    Args:
        msg: the sample.
        color_width: downscale the colour to this width (aspect kept, ``cv2.INTER_AREA``); ``None``: keep
            the full resolution; 0: send no colour.

    Raises:
        ValidationError: sizes that do not match the payloads, bad intrinsics or pose.
    """
    if not msg.has_depth:
        return None
    w, h, dw, dh = int(msg.width), int(msg.height), int(msg.depth_width), int(msg.depth_height)
    if min(w, h, dw, dh) < 1:
        raise ValidationError("width", f"image {w}x{h} / depth {dw}x{dh} must not be empty")
    raw_depth = _as_bytes(msg.depth_image)
    if len(raw_depth) != 4 * dw * dh:
        raise ValidationError("depth_image", f"{len(raw_depth)} bytes, expected {4 * dw * dh} "
                                             f"(float32, {dw}x{dh})")
    scale = float(msg.depth_scale) if np.isfinite(msg.depth_scale) and msg.depth_scale > 0 else 1.0
    depth_m = np.frombuffer(raw_depth, dtype="<f4").reshape(dh, dw).astype(np.float32) * np.float32(scale)
    depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0

    color = None
    if color_width != 0:
        raw_image = _as_bytes(msg.image)
        if len(raw_image) != 3 * w * h:
            raise ValidationError("image", f"{len(raw_image)} bytes, expected {3 * w * h} (RGB8, {w}x{h})")
        color = np.frombuffer(raw_image, dtype=np.uint8).reshape(h, w, 3)
        if color_width is not None and w > color_width:
            ch = max(1, round(h * color_width / w))
            color = cv2.resize(color, (int(color_width), ch), interpolation=cv2.INTER_AREA)

    M = np.asarray(msg.transform_matrix, dtype=np.float64)
    if M.shape != (16,) or not np.all(np.isfinite(M)):
        raise ValidationError("transform_matrix", "must be 16 finite numbers")
    T_world_cam_gl = M.reshape(4, 4).T  # column-major -> row-major
    T_world_cam_cv = opengl_to_opencv(T_world_cam_gl)

    intr = WireIntrinsics(float(msg.fl_x), float(msg.fl_y), float(msg.cx), float(msg.cy), w, h)
    K_depth = scale_intrinsics(make_intrinsics(intr.fx, intr.fy, intr.cx, intr.cy), (w, h), (dw, dh))
    frame = RGBDFrame(depth_m=depth_m, K=K_depth, timestamp_s=float(msg.timestamp),
                      T_world_cam_device=T_world_cam_cv, index=int(msg.id))
    return ConvertedFrame(frame=frame, color=color, intrinsics=intr)


def dds_config_xml(*, interface: str | None = None, loopback: bool = False, receive_buffer: str = "10MB") -> str:
    """A CycloneDDS configuration (XML) for the bridge.

    Args:
        interface: network interface name or address to use (e.g. ``en0``, ``192.168.1.20``); ``None``:
            CycloneDDS picks one.
        loopback: this machine only: 127.0.0.1, no multicast, unicast discovery of 127.0.0.1 (tests).
        receive_buffer: socket receive buffer to ask for (full-resolution NeRFCapture samples are ~8 MB; the
            operating system may grant less, e.g. Linux's ``net.core.rmem_max``: not an error).
    """
    general = ""
    discovery = ""
    if loopback:
        general = ('<General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
                   '<AllowMulticast>false</AllowMulticast></General>')
        discovery = ('<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>60'
                     '</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>')
    elif interface:
        attr = "address" if interface[:1].isdigit() else "name"
        general = f'<General><Interfaces><NetworkInterface {attr}="{interface}"/></Interfaces></General>'
    return (f'<CycloneDDS><Domain id="any">{general}{discovery}<Internal><SocketReceiveBufferSize '
            f'min="default" max="{receive_buffer}"/></Internal></Domain></CycloneDDS>')


class NeRFCaptureReceiver:
    """A DDS reader of NeRFCapture's ``Frames`` topic (reliable, as the app's writer).

    Args:
        domain_id: DDS domain (the app uses 0).
        dds_config: CycloneDDS XML (:func:`dds_config_xml`); ``None``: CycloneDDS's defaults (or the
            ``CYCLONEDDS_URI`` environment variable).
    """

    def __init__(self, domain_id: int = DEFAULT_DOMAIN_ID, dds_config: str | None = None) -> None:
        if not 0 <= int(domain_id) <= 232:
            raise ValidationError("domain_id", f"must be in 0..232, got {domain_id}")
        self.domain_id = int(domain_id)
        self._domain = Domain(self.domain_id, dds_config) if dds_config is not None else None
        self.participant = DomainParticipant(self.domain_id)
        qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)))
        self.topic = Topic(self.participant, TOPIC_NAME, NeRFCaptureFrame, qos=qos)
        self.reader = DataReader(self.participant, self.topic, qos=qos)
        self._condition = ReadCondition(self.reader, ViewState.Any | InstanceState.Any | SampleState.NotRead)
        self._waitset = WaitSet(self.participant)
        self._waitset.attach(self._condition)

    def publishers(self) -> int:
        """Matched writers now (NeRFCapture apps in Online mode on this domain)."""
        return int(self.reader.get_subscription_matched_status().current_count)

    def receive(self, timeout_s: float = 0.5, max_samples: int = 16) -> list[NeRFCaptureFrame]:
        """Samples that arrived (waits up to ``timeout_s`` for the first); ``[]`` on timeout."""
        samples = self.reader.take(N=max_samples, condition=self._condition)
        if not samples:
            self._waitset.wait(duration(seconds=timeout_s))
            samples = self.reader.take(N=max_samples, condition=self._condition)
        return [s for s in samples if isinstance(s, NeRFCaptureFrame)]


@dataclass
class BridgeStats:
    """Counters of :func:`run_nerfcapture_bridge`."""

    received: int = 0
    """Samples taken from DDS."""
    sent: int = 0
    """Frames acknowledged by the server."""
    skipped_no_depth: int = 0
    """Samples without depth (devices without LiDAR)."""
    invalid: int = 0
    """Samples that could not be converted (logged)."""


def run_nerfcapture_bridge(client: BaseClient, *, receiver: NeRFCaptureReceiver | None = None,
                           domain_id: int = DEFAULT_DOMAIN_ID, dds_config: str | None = None,
                           max_frames: int | None = None, idle_timeout_s: float | None = None,
                           stop: threading.Event | None = None, color_width: int | None = 640,
                           on_frame: Callable[[BridgeStats], None] | None = None,
                           open_session: Callable[[], object] | None = None) -> BridgeStats:
    """Forward NeRFCapture samples to the client's current session until stopped.

    Frames are sent in arrival order with ``send_frame_async`` (at most ``client.max_in_flight`` waiting;
    DDS keeps later samples meanwhile). Stops after ``max_frames`` frames sent, after ``idle_timeout_s``
    without a sample (counted from the start, or from the last sample), when ``stop`` is set, or on
    Ctrl-C; always waits for the frames in flight.

    ``open_session``: called once, just before the first frame is sent, to create the session (e.g.
    ``lambda: client.create_session("iphone", preset="iphone")``); so a bridge no phone ever sends a frame
    with depth to leaves no empty session on the server. ``None``: the client already has its session.

    Raises:
        ServerError / TransportError: the server refused a frame (or the session) or went away.
    """
    receiver = receiver or NeRFCaptureReceiver(domain_id, dds_config)
    stats = BridgeStats()
    pending: list[Any] = []
    last_sample = time.monotonic()
    try:
        while stop is None or not stop.is_set():
            if max_frames is not None and stats.sent + len(pending) >= max_frames:
                break
            samples = receiver.receive(timeout_s=0.25)
            if not samples:
                if idle_timeout_s is not None and time.monotonic() - last_sample > idle_timeout_s:
                    break
            for msg in samples:
                last_sample = time.monotonic()
                stats.received += 1
                if max_frames is not None and stats.sent + len(pending) >= max_frames:
                    break
                try:
                    conv = convert_nerfcapture(msg, color_width=color_width)
                except ValidationError as e:
                    stats.invalid += 1
                    log.warning("NeRFCapture sample %s skipped: %s", msg.id, e)
                    continue
                if conv is None:
                    stats.skipped_no_depth += 1
                    if stats.skipped_no_depth == 1:
                        log.warning("NeRFCapture sends frames without depth (a device without LiDAR?); skipping them")
                    continue
                if open_session is not None:
                    open_session()
                    open_session = None
                pending.append(client.send_frame_async(conv.frame, color=conv.color, intrinsics=conv.intrinsics))
            while pending and pending[0].done():
                pending.pop(0).result()
                stats.sent += 1
                if on_frame is not None:
                    on_frame(stats)
    except KeyboardInterrupt:
        log.info("NeRFCapture bridge interrupted")
    finally:
        client.flush()
    for fut in pending:
        fut.result()
        stats.sent += 1
        if on_frame is not None:
            on_frame(stats)
    return stats
