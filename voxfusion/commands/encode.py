"""``voxfusion encode``: one frame of a capture as the server's upload bodies, in files.

Example::

    voxfusion encode ../shared/data/tum_fr1_desk_9frames --frame 0 --out out/frame.vxfr
    curl -H "Authorization: Bearer $TOKEN" -H "Content-Type: application/vnd.voxfusion.frame" \\
         --data-binary @out/frame.vxfr http://127.0.0.1:8000/sessions/$ID/frames      # -> 202 {"seq": 0, ...}
    voxfusion encode ../shared/data/tum_fr1_desk_9frames --frame 1 --parts out/frame1   # the multipart parts
    voxfusion encode --synthetic 10 --frame 3 --out out/synth3.vxfr                     # the synthetic room

``--out FILE`` writes one wire-format message (``proto/README.md``): what ``voxfusion stream`` would send for
that frame (depth, colour and confidence when the capture has them, the intrinsics for the depth's
resolution, the timestamp in seconds, the device pose of ARKit captures; never the reference pose).
``--parts DIR`` writes the same frame as the parts of a multipart upload (``server/ingest.py``):
``metadata.json``, ``depth_mm.png`` (16-bit millimetres), ``color.jpg`` and ``confidence.png`` (levels 0/1/2)
when the frame has them, and prints the ``curl -F`` arguments that send them.

The header's ``seq`` is the frame number unless ``--seq`` says otherwise; it names no session unless
``--session`` does (a frame that names none is taken by the session it is posted to).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ValidationError

from .stream import open_source

__all__ = ["register", "write_parts"]


def write_parts(frame: RGBDFrame, folder: Path, *, seq: int, session: str | None = None,
                jpeg_quality: int = 90) -> list[Path]:
    """Write ``frame`` as the parts of a multipart upload into ``folder``; returns the files.

    ``metadata.json``: ``seq``, ``timestamp_s`` (seconds), ``intrinsics`` (pixels, for the depth's
    resolution), ``depth_encoding`` (``png16_mm``), the colour / confidence encodings, ``device_pose``
    (OpenCV camera-to-world, row-major) when the frame has one, ``session`` when given. ``depth_mm.png``:
    uint16 millimetres, 0 = invalid (depth beyond 65.535 m is clipped to it). ``color.jpg``, ``confidence.png``:
    when the frame has them.
    """
    import cv2

    from voxfusion.proto import WireIntrinsics

    folder.mkdir(parents=True, exist_ok=True)
    h, w = frame.depth_m.shape
    meta: dict = {"seq": int(seq), "timestamp_s": float(frame.timestamp_s),
                  "intrinsics": WireIntrinsics.from_K(frame.K, w, h).to_json(), "depth_encoding": "png16_mm"}
    if session is not None:
        meta["session"] = session
    written = [folder / "metadata.json", folder / "depth_mm.png"]
    depth_mm = np.clip(np.round(np.nan_to_num(frame.depth_m, nan=0.0) * 1000.0), 0, 65535).astype(np.uint16)
    if not cv2.imwrite(str(written[1]), depth_mm):
        raise ValidationError("parts", f"could not write {written[1]}")
    if frame.color is not None:
        meta["color_encoding"] = "jpeg"
        path = folder / "color.jpg"
        cv2.imwrite(str(path), cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        written.append(path)
    if frame.confidence is not None:
        meta["confidence_encoding"] = "png8"
        path = folder / "confidence.png"
        cv2.imwrite(str(path), frame.confidence.astype(np.uint8))
        written.append(path)
    if frame.T_world_cam_device is not None:
        meta["device_pose"] = {"convention": "opencv",
                               "matrix": [float(v) for v in np.asarray(frame.T_world_cam_device).reshape(-1)]}
    written[0].write_text(json.dumps(meta, indent=1) + "\n")
    return written


def register(app: typer.Typer) -> None:
    @app.command("encode")
    def encode_command(
        capture: Annotated[Path | None, typer.Argument(help="Capture folder or .r3d file (any format voxfusion "
                                                            "reads); omit with --synthetic.")] = None,
        frame: Annotated[int, typer.Option("--frame", help="Frame number N in the capture (0 = first; after "
                                                           "--stride).")] = 0,
        out: Annotated[Path | None, typer.Option("--out", help="Write the binary frame message here, e.g. "
                                                               "out/frame.vxfr.")] = None,
        parts: Annotated[Path | None, typer.Option("--parts", help="Write the multipart upload's parts "
                                                                   "(metadata.json, depth_mm.png, ...) into "
                                                                   "this folder.")] = None,
        seq: Annotated[int | None, typer.Option("--seq", help="The header's sequence number (default: N).")]
        = None,
        session: Annotated[str | None, typer.Option("--session", help="Session id to name in the header "
                                                                      "(default: none).")] = None,
        stride: Annotated[int, typer.Option("--stride", help="Count every N-th frame of the capture.")] = 1,
        synthetic: Annotated[int | None, typer.Option("--synthetic", help="A synthetic room of N frames instead "
                                                                          "of a capture.")] = None,
        synthetic_size: Annotated[str, typer.Option("--synthetic-size", help="WIDTHxHEIGHT of --synthetic "
                                                                             "frames.")] = "320x240",
        depth_encoding: Annotated[str, typer.Option("--depth-encoding", help="--out: zstd_u16_mm, png16_mm, "
                                                                             "zstd_f16_m or raw_f32_m.")]
        = "zstd_u16_mm",
        color_encoding: Annotated[str, typer.Option("--color-encoding", help="--out: jpeg, png, raw_rgb8, or "
                                                                             "none (no colour).")] = "jpeg",
    ) -> None:
        """Write frame N of CAPTURE as a binary frame message (--out) and/or multipart parts (--parts), the
        bodies POST /sessions/<id>/frames takes."""
        from voxfusion.proto import COLOR_ENCODINGS, DEPTH_ENCODINGS, encode_frame, read_header

        if out is None and parts is None:
            raise ValidationError("out", "give --out FILE (a binary frame message) and/or --parts DIR")
        if depth_encoding not in DEPTH_ENCODINGS:
            raise ValidationError("depth_encoding", f"must be one of {', '.join(DEPTH_ENCODINGS)}, "
                                                    f"got {depth_encoding!r}")
        color = None if color_encoding.lower() == "none" else color_encoding
        if color is not None and color not in COLOR_ENCODINGS:
            raise ValidationError("color_encoding", f"must be one of {', '.join(COLOR_ENCODINGS)} or none, "
                                                    f"got {color_encoding!r}")
        if out is not None and out.is_dir():
            raise ValidationError("out", f"{out} is a folder; give the file to write, e.g. {out / 'frame.vxfr'}")
        cap = open_source(capture, synthetic, synthetic_size, stride=stride)
        if not 0 <= frame < len(cap):
            raise ValidationError("frame", f"must be in 0..{len(cap) - 1} ({cap.name} has {len(cap)} frames), "
                                           f"got {frame}")
        rgbd = cap[frame]
        seq = frame if seq is None else seq
        if out is not None:
            data = encode_frame(rgbd, seq=seq, session=session, depth_encoding=depth_encoding,  # type: ignore[arg-type]
                                color_encoding=color)  # type: ignore[arg-type]
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(data)
            h = read_header(data)
            typer.echo(f"wrote {out}: frame {frame} of {cap.name} as seq {h.seq} ({len(data)} bytes): depth "
                       f"{h.depth_width}x{h.depth_height} {h.depth_encoding}, colour "
                       + (f"{h.color_width}x{h.color_height} {h.color_encoding}" if h.color_encoding else "none")
                       + f", confidence {h.confidence_encoding or 'none'}, timestamp {h.timestamp_s:.6f} s, "
                       + f"device pose {'yes' if h.device_pose is not None else 'no'}"
                       + (f", session {h.session}" if h.session else ", no session named"))
        if parts is not None:
            files = write_parts(rgbd, parts, seq=seq, session=session)
            names = {"metadata.json": "metadata", "depth_mm.png": "depth", "color.jpg": "color",
                     "confidence.png": "confidence"}
            typer.echo(f"wrote {', '.join(str(p) for p in files)}: frame {frame} of {cap.name} as seq {seq}; "
                       "send with curl " + " ".join(f"-F {names[p.name]}=@{p}" for p in files))
