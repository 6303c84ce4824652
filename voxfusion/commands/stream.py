"""``voxfusion stream``: replay a recorded capture into a server session over HTTP or zenoh.

Example::

    voxfusion serve &                                                    # HTTP :8000, zenoh 127.0.0.1:7447
    voxfusion stream ../shared/data/tum_fr1_desk --server http://127.0.0.1:8000 --realtime --out out/desk
    voxfusion stream recording.r3d --zenoh default --fps 10 --max-frames 300 --out out/r3d
    voxfusion stream --synthetic 60 --server http://127.0.0.1:8000 --out out/synth

Any capture the readers know (TUM, 7-Scenes, Replica, ScanNet, Stray Scanner, Record3D ``.r3d``, and
synthetic captures written by ``voxfusion synth``) is sent frame by frame: at its recorded rate
(``--realtime``), at a fixed rate (``--fps``), or as fast as the server takes it (default). A progress bar
shows the frames sent, the live pose and the send rate. Then the session is finished and ``mesh.ply``,
``trajectory.txt`` (TUM) and ``session.json`` (id, token, mesh location; readable by you only) are written
to ``--out``; the session id and the mesh URL are printed, and the ATE when the capture has reference
poses.

A new session gets the capture's facts as settings under any ``--set`` (``mapping.max_depth_m``,
``mapping.min_confidence``, ``loss.w_color``: what the reader's profile says, see
:func:`voxfusion.core.slam_config.profile_overrides`), so it needs no preset that knows the capture; the
server still chooses the sizes (its default preset, or ``--preset``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from voxfusion.clients.base import BaseClient, EncodeOptions
from voxfusion.clients.stream import StreamOptions, finish_and_download, stream_frames
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ValidationError
from voxfusion.core.trajectory import Trajectory

__all__ = ["register", "connect_client", "open_session"]


def connect_client(server: str | None, zenoh_config: str | None, *, zenoh_connect: list[str] | None = None,
                   api_key: str | None = None, depth_encoding: str = "zstd_u16_mm") -> BaseClient:
    """An HTTP client (``server`` URL) or a zenoh client (``zenoh_config``: a JSON5 file or ``default``)."""
    if (server is None) == (zenoh_config is None):
        raise ValidationError("server", "give exactly one of --server URL or --zenoh CONFIG")
    encode = EncodeOptions(depth_encoding=depth_encoding)  # type: ignore[arg-type]
    if server is not None:
        from voxfusion.clients.http_client import Client

        return Client(server, api_key=api_key, encode=encode)
    from voxfusion.clients.zenoh_client import ZenohClient

    config = None if zenoh_config in ("default", "") else zenoh_config
    return ZenohClient(config, connect=zenoh_connect or None, api_key=api_key, encode=encode)


def open_session(client: BaseClient, *, session: str | None, token: str | None, name: str | None,
                 preset: str | None, overrides: dict | list[str] | None, mode: str | None) -> None:
    """Attach to ``session`` (with its ``token``) or create a new session."""
    if session is not None:
        if not token:
            raise ValidationError("token", "--session needs the session's --token")
        client.attach(session, token)
        return
    if token:
        raise ValidationError("token", "--token is for an existing session: give --session too")
    client.create_session(name, overrides or None, preset=preset, mode=mode)


def _flat(tree: dict, prefix: str = "") -> str:
    """``{"mapping": {"max_depth_m": 4.0}}`` -> ``"mapping.max_depth_m=4.0"``."""
    return " ".join(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else f"{prefix}{k}={v}" for k, v in tree.items())


def _recording_references(frames: Iterator[RGBDFrame], refs: list[tuple[float, np.ndarray]]) -> Iterator[RGBDFrame]:
    for frame in frames:
        if frame.T_world_cam is not None:
            refs.append((frame.timestamp_s, frame.T_world_cam))
        yield frame


def register(app: typer.Typer) -> None:
    @app.command("stream")
    def stream_command(
        capture: Annotated[Path | None, typer.Argument(help="Capture folder or .r3d file (any format voxfusion "
                                                            "reads); omit with --synthetic.")] = None,
        server: Annotated[str | None, typer.Option("--server", help="Server URL, e.g. http://127.0.0.1:8000.")] = None,
        zenoh: Annotated[str | None, typer.Option("--zenoh", help="Zenoh client config (JSON5), or 'default' "
                                                                 "for configs/zenoh/client.json5.")] = None,
        zenoh_connect: Annotated[list[str] | None, typer.Option("--zenoh-connect", help="Zenoh endpoint to "
                                                                "connect to, e.g. tcp/192.168.1.20:7447.")] = None,
        fps: Annotated[float | None, typer.Option("--fps", help="Send at this fixed rate.")] = None,
        realtime: Annotated[bool, typer.Option("--realtime", help="Send at the recorded rate.")] = False,
        out: Annotated[Path | None, typer.Option("--out", help="Write mesh.ply, trajectory.txt, session.json "
                                                               "here.")] = None,
        token: Annotated[str | None, typer.Option("--token", help="Token of the existing --session.")] = None,
        session: Annotated[str | None, typer.Option("--session", help="Stream into this existing session.")] = None,
        api_key: Annotated[str | None, typer.Option("--api-key", envvar="VOXFUSION_API_KEY",
                                                    help="Server API key (to create sessions).")] = None,
        max_frames: Annotated[int | None, typer.Option("--max-frames", help="Send at most N frames.")] = None,
        synthetic: Annotated[int | None, typer.Option("--synthetic", help="Stream N frames of the synthetic "
                                                                          "room instead of a capture.")] = None,
        synthetic_size: Annotated[str, typer.Option("--synthetic-size", help="WIDTHxHEIGHT of --synthetic "
                                                                             "frames.")] = "320x240",
        stride: Annotated[int, typer.Option("--stride", help="Use every N-th frame of the capture.")] = 1,
        name: Annotated[str | None, typer.Option("--name", help="Session name.")] = None,
        preset: Annotated[str | None, typer.Option("--preset", help="Server config preset (tum, iphone, ...).")]
        = None,
        set_: Annotated[list[str] | None, typer.Option("--set", help="Engine override, e.g. tracking.iters=20.")]
        = None,
        mode: Annotated[str | None, typer.Option("--mode", help="offline (every frame) or realtime (may skip "
                                                                "frames); default: offline unless paced.")] = None,
        depth_encoding: Annotated[str, typer.Option("--depth-encoding", help="zstd_u16_mm, png16_mm, zstd_f16_m "
                                                                             "or raw_f32_m.")] = "zstd_u16_mm",
        finish: Annotated[bool, typer.Option("--finish/--no-finish", help="Finish the session and download "
                                                                          "the results at the end.")] = True,
    ) -> None:
        """Stream a recorded capture to a VoxFusion server, then download its mesh and trajectory."""
        options = StreamOptions(fps=fps, realtime=realtime, max_frames=max_frames)
        if (capture is None) == (synthetic is None):
            raise ValidationError("capture", "give a capture path or --synthetic N (not both)")
        if synthetic is not None:
            from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

            try:
                width, height = (int(v) for v in synthetic_size.lower().split("x"))
            except ValueError as e:
                raise ValidationError("synthetic_size", f"must look like 320x240, got {synthetic_size!r}") from e
            cap = SyntheticCapture(SyntheticConfig(n_frames=synthetic, width=width, height=height))
        else:
            from voxfusion.core.datasets import open_capture

            cap = open_capture(capture, stride=stride, limit=max_frames)
        if mode is None and session is None:
            mode = "realtime" if (realtime or fps is not None) else "offline"
        client = connect_client(server, zenoh, zenoh_connect=zenoh_connect, api_key=api_key,
                                depth_encoding=depth_encoding)
        overrides: dict | list[str] | None = set_
        if session is None:
            from voxfusion.core.config import merge_dicts, parse_overrides
            from voxfusion.core.slam_config import profile_overrides

            facts = profile_overrides(cap.profile)
            if facts:
                overrides = merge_dicts(facts, parse_overrides(set_ or []))
                typer.echo(f"capture: {cap.profile.sensor or cap.name} ({cap.profile.describe()}); session settings "
                           f"from it: {_flat(facts)}")
        with client:
            open_session(client, session=session, token=token, name=name or (capture.name if capture else "synthetic"),
                         preset=preset, overrides=overrides, mode=mode)
            typer.echo(f"session {client.session.id}")
            if out is not None:
                from voxfusion.clients.stream import write_session_file

                write_session_file(client, out)
            refs: list[tuple[float, np.ndarray]] = []
            sent, send_s = stream_frames(_recording_references(cap.frames(), refs), client, options, total=len(cap))
            typer.echo(f"sent {sent} frames in {send_s:.1f} s ({sent / max(send_s, 1e-9):.1f} fps)")
            if not finish:
                typer.echo(f"mesh: {client.mesh_url}")
                return
            status, mesh_path, traj_path = finish_and_download(client, out)
            typer.echo(f"session {status.id} {status.state.value}: {status.frames_tracked} tracked, "
                       f"{status.keyframes} keyframes, {status.voxels} voxels"
                       + (f", error: {status.last_error}" if status.last_error else ""))
            if len(refs) >= 3 and status.frames_tracked >= 3:
                from voxfusion.clients.base import poses_to_trajectory
                from voxfusion.core.eval import compute_ate

                ref = Trajectory(np.array([t for t, _ in refs]), np.array([T for _, T in refs]))
                try:
                    ate = compute_ate(poses_to_trajectory(client.trajectory()), ref)
                    typer.echo(f"ATE rmse {100 * ate.rmse_m:.2f} cm over {ate.n} poses against the capture's "
                               "reference poses (SE(3)-aligned; for phone captures these are ARKit's own)")
                except ValidationError as e:
                    typer.echo(f"ATE not computed: {e}")
            if mesh_path is not None:
                typer.echo(f"wrote {mesh_path} and {traj_path}")
            typer.echo(f"mesh: {client.mesh_url}")
