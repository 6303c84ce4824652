"""``voxfusion bridge``: live devices into a server session.

Example::

    voxfusion serve &
    voxfusion bridge nerfcapture --server http://127.0.0.1:8000           # NeRFCapture app, Online mode
    voxfusion bridge nerfcapture --zenoh default --domain-id 0 --out out/live

``nerfcapture`` receives the NeRFCapture iOS app's frames over CycloneDDS (topic ``Frames``, domain 0 by
default; the phone and this machine on the same network), converts them (ARKit pose to OpenCV axes,
column-major to row-major, intrinsics with their resolution) and streams them into a new session (or
``--session``/``--token``). The new session is created when the first frame with depth arrives, and its id,
viewer link and mesh URL are printed then: a bridge no phone ever sends to leaves no empty session behind,
even when it is killed (deleting an empty session on exit would not survive ``kill -9``, and would hold one
of the server's session slots while waiting). It stops on Ctrl-C, after ``--max-frames`` or
``--idle-timeout`` seconds without a frame; then it finishes the session and, with ``--out``, downloads
``mesh.ply`` and ``trajectory.txt`` (``--out`` is refused when it holds another command's outputs, unless
``--force``: :mod:`voxfusion.commands.outputs`). Details: ``docs/iphone.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .outputs import claim_output_dir
from .stream import check_session_args, connect_client, open_session, print_session_links

__all__ = ["register"]

bridge_app = typer.Typer(help="Stream live devices (NeRFCapture iPhone app) into a server session.",
                         no_args_is_help=True)


@bridge_app.command("nerfcapture")
def nerfcapture_command(
    server: Annotated[str | None, typer.Option("--server", help="Server URL, e.g. http://127.0.0.1:8000.")] = None,
    zenoh: Annotated[str | None, typer.Option("--zenoh", help="Zenoh client config (JSON5), or 'default'.")] = None,
    zenoh_connect: Annotated[list[str] | None, typer.Option("--zenoh-connect", help="Zenoh endpoint, e.g. "
                                                                                    "tcp/HOST:7447.")] = None,
    domain_id: Annotated[int, typer.Option("--domain-id", help="DDS domain NeRFCapture publishes on.")] = 0,
    interface: Annotated[str | None, typer.Option("--interface", help="Network interface (name or address) "
                                                                      "DDS uses, e.g. en0 or 192.168.1.20.")] = None,
    dds_config: Annotated[Path | None, typer.Option("--dds-config", help="CycloneDDS XML config file (replaces "
                                                                         "--interface).")] = None,
    loopback: Annotated[bool, typer.Option("--loopback", help="DDS on 127.0.0.1 only (testing with a local "
                                                              "publisher).")] = False,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after N frames.")] = None,
    idle_timeout: Annotated[float | None, typer.Option("--idle-timeout", help="Stop after this many seconds "
                                                                              "without a frame.")] = None,
    color_width: Annotated[int, typer.Option("--color-width", help="Downscale colour to this width before "
                                                                   "sending (0: no colour).")] = 640,
    out: Annotated[Path | None, typer.Option("--out", help="Write mesh.ply, trajectory.txt, session.json here.")]
    = None,
    session: Annotated[str | None, typer.Option("--session", help="Stream into this existing session.")] = None,
    token: Annotated[str | None, typer.Option("--token", help="Token of the existing --session.")] = None,
    api_key: Annotated[str | None, typer.Option("--api-key", envvar="VOXFUSION_API_KEY",
                                                help="Server API key (to create sessions).")] = None,
    preset: Annotated[str | None, typer.Option("--preset", help="Server config preset.")] = "iphone",
    set_: Annotated[list[str] | None, typer.Option("--set", help="Engine override, e.g. tracking.iters=20.")] = None,
    finish: Annotated[bool, typer.Option("--finish/--no-finish", help="Finish the session at the end.")] = True,
    force: Annotated[bool, typer.Option("--force", help="Delete other commands' outputs in --out instead of "
                                                        "refusing the folder.")] = False,
) -> None:
    """Receive NeRFCapture's live frames (CycloneDDS) and stream them into a session."""
    from voxfusion.clients.nerfcapture import NeRFCaptureReceiver, dds_config_xml, run_nerfcapture_bridge
    from voxfusion.clients.stream import finish_and_download, format_pose, session_summary, write_session_file

    check_session_args(session, token)
    for path in claim_output_dir(out, "bridge", force):
        typer.echo(f"--force: deleted {path} (another command's output)")
    xml = dds_config.read_text() if dds_config is not None else dds_config_xml(interface=interface, loopback=loopback)
    receiver = NeRFCaptureReceiver(domain_id, xml)
    client = connect_client(server, zenoh, zenoh_connect=zenoh_connect, api_key=api_key)
    from tqdm import tqdm

    def announce() -> None:
        print_session_links(client, echo=tqdm.write)
        tqdm.write(f"mesh: {client.mesh_url}")
        if out is not None:
            write_session_file(client, out)

    def create() -> None:
        open_session(client, session=None, token=None, name="nerfcapture", preset=preset, overrides=set_,
                     mode="realtime")
        announce()

    with client:
        if session is not None:
            open_session(client, session=session, token=token, name=None, preset=None, overrides=None, mode=None)
            announce()
        typer.echo(f"waiting for NeRFCapture frames on DDS domain {domain_id}, topic 'Frames' "
                   "(app in Online mode, same network); "
                   + ("" if session is not None else "the session is created with the first frame; ")
                   + "Ctrl-C to stop")
        bar = tqdm(unit="frame", desc="nerfcapture", dynamic_ncols=True)

        def progress(stats: object) -> None:
            bar.update(1)
            if bar.n % 10 == 1:
                bar.set_postfix_str(f"pose {format_pose(client.latest_pose())}", refresh=False)

        try:
            stats = run_nerfcapture_bridge(client, receiver=receiver, max_frames=max_frames,
                                           idle_timeout_s=idle_timeout, color_width=color_width or 0,
                                           on_frame=progress, open_session=create if session is None else None)
        finally:
            bar.close()
        typer.echo(f"received {stats.received}, sent {stats.sent}, skipped {stats.skipped_no_depth} without depth, "
                   f"{stats.invalid} invalid")
        if session is None and stats.sent == 0:
            typer.echo("no frame with depth arrived: no session was created")
            return
        if finish and stats.sent > 0:
            status, mesh_path, traj_path = finish_and_download(client, out)
            typer.echo(session_summary(status))
            if mesh_path is not None:
                typer.echo(f"wrote {mesh_path} and {traj_path}")
        typer.echo(f"session {client.session.id}, mesh: {client.mesh_url}")


def register(app: typer.Typer) -> None:
    app.add_typer(bridge_app, name="bridge")
