"""``voxfusion stream``: replay a recorded capture into a server session over HTTP or zenoh.

Example::

    voxfusion serve &                                                    # HTTP :8000, zenoh 127.0.0.1:7447
    voxfusion stream ../shared/data/tum_fr1_desk --server http://127.0.0.1:8000 --realtime --out out/desk-stream
    voxfusion stream recording.r3d --zenoh default --fps 10 --max-frames 300 --out out/r3d
    voxfusion stream --synthetic 60 --server http://127.0.0.1:8000 --out out/synth

Any capture the readers know (TUM, 7-Scenes, Replica, ScanNet, Stray Scanner, Record3D ``.r3d``, and
synthetic captures written by ``voxfusion synth``) is sent frame by frame: at its recorded rate
(``--realtime``), at a fixed rate (``--fps``), or as fast as the server takes it (default). A progress bar
shows the frames sent, the live pose and the send rate. The session id and, over HTTP, the live viewer's link
(``<server>/sessions/<id>/view?token=<token>``) are printed as soon as the session exists. Then the session is
finished and ``mesh.ply``, ``trajectory.txt`` (TUM) and ``session.json`` (id, token, mesh location; readable
by you only) are written to ``--out``; the summary gives the frames the server received, tracked, lost and
dropped (realtime sessions skip what tracking cannot keep up with), the mesh URL, and the ATE when the
capture has reference poses. ``--out`` must not hold another command's outputs (``voxfusion run``'s
``metrics.json`` would describe another mesh): such a folder is refused unless ``--force`` deletes them
(:mod:`voxfusion.commands.outputs`).

A new session gets the preset ``voxfusion run`` would pick for the capture (:func:`session_preset`: the
capture's kind, e.g. ``iphone`` for Stray / Record3D / 3D Scanner App captures, at the sizes of the server's
device as ``/healthz`` reports it; printed), unless ``--preset`` names one, and the capture's facts as settings
under any ``--set`` (``mapping.max_depth_m``, ``mapping.min_confidence``, ``loss.w_color``: what the reader's
profile says, see :func:`voxfusion.core.slam.presets.profile_overrides`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from voxfusion.clients.base import BaseClient, EncodeOptions
from voxfusion.clients.stream import StreamOptions, finish_and_download, session_summary, stream_frames
from voxfusion.core.datasets.frame import Capture, RGBDFrame
from voxfusion.core.errors import ValidationError
from voxfusion.core.trajectory import Trajectory

from .outputs import claim_output_dir

__all__ = ["register", "connect_client", "open_session", "open_source", "check_session_args", "SessionPreset",
           "session_preset", "wire_preset", "print_session_links"]

_SERVER_KEYS = ("device", "mode")
"""Config keys a session request may not set: the server chooses them (``voxfusion serve --device``, the
session's ``mode``)."""


@dataclass(frozen=True)
class SessionPreset:
    """The preset :func:`session_preset` chose for a new session.

    Attributes:
        name: the preset, e.g. ``iphone+cpu`` (a name or a ``kind+size`` composition; :func:`open_session`
            sends a composition as :func:`wire_preset` says).
        reason: one line for people: what was picked and why.
    """

    name: str
    reason: str


def _changed(full: dict, base: dict) -> dict:
    """The entries of nested ``full`` that differ from ``base``, nested as in ``full``."""
    out: dict = {}
    for key, value in full.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            sub = _changed(value, base[key])
            if sub:
                out[key] = sub
        elif key not in base or base[key] != value:
            out[key] = value
    return out


def wire_preset(name: str) -> tuple[str, dict[str, Any]]:
    """``(preset for the session request, settings)`` for preset ``name``: a session request names one preset
    (``SessionCreate.preset`` takes no ``+``), so a composition ``kind+size`` is sent as ``kind`` plus, as
    settings, every number the composition changes (``device`` and ``mode`` left to the server); a single
    name is sent as it is. The server then builds the same configuration as ``load_preset(name)``.

    Example: ``wire_preset("tum+cpu")`` -> ``("tum", {"sized_for": "cpu", "field": {"sdf_hidden": 64, ...}, ...})``.

    Raises:
        ConfigError: an unknown preset name.
    """
    from voxfusion.core.config import config_to_dict
    from voxfusion.core.slam.presets import load_preset

    kind, plus, _ = str(name).partition("+")
    if not plus:
        return str(name), {}
    full = config_to_dict(load_preset(name))
    base = config_to_dict(load_preset(kind))
    return kind, {k: v for k, v in _changed(full, base).items() if k not in _SERVER_KEYS}


def session_preset(capture: Capture, server_device: str | None, sets: list[str] | None = None) -> SessionPreset:
    """The preset for a new session streaming ``capture``: what ``voxfusion run`` picks
    (:func:`voxfusion.core.slam.presets.preset_for`: the capture's kind, composed with ``cpu`` without CUDA)
    for the *server's* device ``server_device`` (``cpu``, ``cuda``; ``None`` where the transport does not
    report it, zenoh: this machine's device is assumed). ``sets`` (``key=value``) are checked on the way.

    Example: a Stray Scanner capture streamed to a CPU server gets ``iphone+cpu``.
    """
    from voxfusion.core.slam.presets import KIND_PRESETS, preset_for

    cuda = server_device is not None and server_device.startswith("cuda")
    if cuda:
        import torch

        if not torch.cuda.is_available():
            # preset_for checks for a CUDA device on this machine; the server has one: the kind preset alone
            profile = capture.profile
            name = KIND_PRESETS[profile.kind]
            reason = (f"preset {name}: {capture.name} is {profile.sensor or 'a capture of unknown kind'} (kind "
                      f"{profile.kind}; {profile.describe()}); the server has a CUDA device: GPU sizes")
            return SessionPreset(name, reason)
    device = server_device if cuda else ("cpu" if server_device is not None else "auto")
    choice = preset_for(capture, device, sets,
                        cpu_why="the server has no CUDA device" if server_device is not None else None)
    where = (f"; the server's device is {server_device} (/healthz)" if server_device is not None
             else "; sized for this machine's device (zenoh does not report the server's)")
    return SessionPreset(choice.preset, choice.reason + where)


def print_session_links(client: BaseClient, echo: Callable[[str], object] = typer.echo) -> None:
    """Print (with ``echo``) the session id and, for HTTP clients, the live viewer's link (it carries the
    session token: share it as you would the token)."""
    echo(f"session {client.session.id}")
    viewer = getattr(client, "viewer_url", None)
    if viewer is not None:
        echo(f"viewer: {viewer}")


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


def open_source(capture: Path | None, synthetic: int | None, synthetic_size: str = "320x240", *, stride: int = 1,
                limit: int | None = None) -> Capture:
    """The frames a command sends: the capture at ``capture`` (any format ``open_capture`` reads; ``stride``,
    ``limit``), or ``synthetic`` frames of the synthetic room at ``synthetic_size`` (``WIDTHxHEIGHT``).

    Raises:
        ValidationError: both or neither given (field ``capture``), a bad size (``synthetic_size``).
    """
    if (capture is None) == (synthetic is None):
        raise ValidationError("capture", "give a capture path or --synthetic N (not both)")
    if synthetic is not None:
        from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

        try:
            width, height = (int(v) for v in synthetic_size.lower().split("x"))
        except ValueError as e:
            raise ValidationError("synthetic_size", f"must look like 320x240, got {synthetic_size!r}") from e
        return SyntheticCapture(SyntheticConfig(n_frames=synthetic, width=width, height=height))
    from voxfusion.core.datasets import open_capture

    return open_capture(capture, stride=stride, limit=limit)


def check_session_args(session: str | None, token: str | None) -> None:
    """``--session`` and ``--token`` come together or not at all."""
    if session is not None and not token:
        raise ValidationError("token", "--session needs the session's --token")
    if session is None and token:
        raise ValidationError("token", "--token is for an existing session: give --session too")


def open_session(client: BaseClient, *, session: str | None, token: str | None, name: str | None,
                 preset: str | None, overrides: dict | list[str] | None, mode: str | None) -> None:
    """Attach to ``session`` (with its ``token``) or create a new session; a composed ``preset``
    (``iphone+cpu``) is sent as :func:`wire_preset` says."""
    check_session_args(session, token)
    if session is not None and token:
        client.attach(session, token)
        return
    if preset is not None and "+" in preset:
        from voxfusion.core.config import merge_dicts, parse_overrides

        preset, settings = wire_preset(preset)
        extra = parse_overrides(overrides) if isinstance(overrides, list) else (overrides or {})
        overrides = merge_dicts(settings, extra)
    client.create_session(name, overrides or None, preset=preset, mode=mode)


def _flat(tree: dict, prefix: str = "") -> str:
    """``{"mapping": {"max_depth_m": 4.0}}`` -> ``"mapping.max_depth_m=4.0"``."""
    return " ".join(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else f"{prefix}{k}={v}" for k, v in tree.items())


def _recording_references(frames: Iterator[RGBDFrame], refs: list[tuple[float, np.ndarray]],
                           stamps: list[float]) -> Iterator[RGBDFrame]:
    """``frames``, noting each one's timestamp (seconds) and its reference pose (when it has one)."""
    for frame in frames:
        stamps.append(frame.timestamp_s)
        if frame.T_world_cam is not None:
            refs.append((frame.timestamp_s, frame.T_world_cam))
        yield frame


def _pace_line(sent: int, send_s: float, stamps: list[float], options: StreamOptions) -> str:
    """``sent 942 frames in 15.8 s (59.6 frames/s; the capture's own rate: 60.0 frames/s over 15.7 s)``."""
    line = f"sent {sent} frames in {send_s:.1f} s ({sent / max(send_s, 1e-9):.1f} frames/s"
    span = (stamps[sent - 1] - stamps[0]) if sent >= 2 and len(stamps) >= sent else 0.0
    if options.realtime and span > 0:
        line += f"; the capture's own rate: {(sent - 1) / span:.1f} frames/s over {span:.1f} s"
    elif options.fps is not None:
        line += f"; paced at {options.fps:g} frames/s"
    return line + ")"


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
        realtime: Annotated[bool, typer.Option("--realtime", help="Send at the capture's own rate (its frame "
                                                                  "timestamps).")] = False,
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
        preset: Annotated[str | None, typer.Option("--preset", help="Session preset (tum, iphone+cpu, ...); "
                                                   "default: the one `voxfusion run` picks for the capture, "
                                                   "at the server's device's sizes.")] = None,
        set_: Annotated[list[str] | None, typer.Option("--set", help="Engine override, e.g. tracking.iters=20.")]
        = None,
        mode: Annotated[str | None, typer.Option("--mode", help="offline (every frame) or realtime (may skip "
                                                                "frames); default: offline unless paced.")] = None,
        force: Annotated[bool, typer.Option("--force", help="Delete other commands' outputs in --out (e.g. a "
                                                            "run's metrics.json) instead of refusing the "
                                                            "folder.")] = False,
        depth_encoding: Annotated[str, typer.Option("--depth-encoding", help="zstd_u16_mm, png16_mm, zstd_f16_m "
                                                                             "or raw_f32_m.")] = "zstd_u16_mm",
        finish: Annotated[bool, typer.Option("--finish/--no-finish", help="Finish the session and download "
                                                                          "the results at the end.")] = True,
    ) -> None:
        """Stream a recorded capture to a VoxFusion server, then download its mesh and trajectory."""
        options = StreamOptions(fps=fps, realtime=realtime, max_frames=max_frames)
        cap = open_source(capture, synthetic, synthetic_size, stride=stride, limit=max_frames)
        if mode is None and session is None:
            mode = "realtime" if (realtime or fps is not None) else "offline"
        check_session_args(session, token)
        removed = claim_output_dir(out, "stream", force)
        if removed:
            typer.echo(f"--force: deleted {', '.join(p.name for p in removed)} from {out} (another command's outputs)")
        client = connect_client(server, zenoh, zenoh_connect=zenoh_connect, api_key=api_key,
                                depth_encoding=depth_encoding)
        with client:
            overrides: dict | list[str] | None = set_
            if session is None:
                from voxfusion.core.config import merge_dicts, parse_overrides
                from voxfusion.core.slam.presets import profile_overrides

                if preset is None:
                    choice = session_preset(cap, client.server_device(), set_)
                    preset = choice.name
                    typer.echo(choice.reason)
                else:
                    typer.echo(f"preset {preset} (--preset)")
                facts = profile_overrides(cap.profile)
                if facts:
                    overrides = merge_dicts(facts, parse_overrides(set_ or []))
                    typer.echo(f"capture: {cap.profile.sensor or cap.name} ({cap.profile.describe()}); session "
                               f"settings from it: {_flat(facts)}")
            open_session(client, session=session, token=token, name=name or (capture.name if capture else "synthetic"),
                         preset=preset, overrides=overrides, mode=mode)
            print_session_links(client)
            if out is not None:
                from voxfusion.clients.stream import write_session_file

                write_session_file(client, out)
            refs: list[tuple[float, np.ndarray]] = []
            stamps: list[float] = []
            sent, send_s = stream_frames(_recording_references(cap.frames(), refs, stamps), client, options,
                                         total=len(cap))
            typer.echo(_pace_line(sent, send_s, stamps, options))
            if not finish:
                typer.echo(f"mesh: {client.mesh_url}")
                return
            status, mesh_path, traj_path = finish_and_download(client, out)
            typer.echo(session_summary(status))
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
