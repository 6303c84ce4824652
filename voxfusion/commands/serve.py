"""``voxfusion serve``: the streaming SLAM server (FastAPI on uvicorn; OpenAPI docs at ``/docs``).

Example::

    voxfusion serve                                   # 127.0.0.1:8000, data in ./voxfusion-data
    voxfusion serve --host 0.0.0.0 --data-dir /data   # what the Docker image runs
    VOXFUSION_API_KEY=... voxfusion serve             # creating / listing sessions needs the key

Everything is embedded: SQLite for session metadata, the data folder for recordings and checkpoints,
and (``--zenoh``, on by default when the ``zenoh`` package is installed) an in-process zenoh peer.
"""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Annotated

import typer

__all__ = ["register", "serve_command"]


def serve_command(
    host: Annotated[str, typer.Option(help="Interface to listen on (0.0.0.0: every interface).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.")] = 8000,
    data_dir: Annotated[Path, typer.Option("--data-dir", help="Sessions database, recordings and checkpoints.")]
    = Path("voxfusion-data"),
    device: Annotated[str, typer.Option(help="auto, cpu or cuda: where every session's engine runs.")] = "auto",
    config: Annotated[str | None, typer.Option("--config", help="Default preset of new sessions (configs/<name>."
                                                                "yaml, or kind+cpu); default cpu on CPU, default "
                                                                "on CUDA.")] = None,
    zenoh: Annotated[bool | None, typer.Option("--zenoh/--no-zenoh", help="Start the zenoh bridge (default: when "
                                                                            "the zenoh package is installed).")]
    = None,
    zenoh_config: Annotated[Path | None, typer.Option("--zenoh-config", help="zenoh JSON5 config file.")] = None,
    zenoh_listen: Annotated[list[str] | None, typer.Option(
        "--zenoh-listen", help="zenoh endpoint to listen on, replacing the config's (repeatable; e.g. "
                               "tcp/0.0.0.0:7447 for every interface). Implies --zenoh.")] = None,
    zenoh_secrets: Annotated[Path | None, typer.Option(
        "--zenoh-secrets", help="LAN setup: keep zenoh credentials in this folder (generated once) and serve with "
                                "authentication and access control; clients use DIR/client.json5.")] = None,
    zenoh_insecure: Annotated[bool, typer.Option(
        "--zenoh-insecure", help="Allow zenoh to listen beyond loopback without authentication.")] = False,
    max_sessions: Annotated[int, typer.Option(help="Open sessions held at once (more get 503).")] = 8,
    max_sessions_per_client: Annotated[int, typer.Option(
        help="Open sessions one client address beyond loopback may hold when the server has no API key (more "
             "get 429; 0: no limit).")] = 2,
    session_idle_timeout_s: Annotated[float, typer.Option(
        help="Close a session that received no frame for this many seconds (map checkpointed, recording kept, "
             "slot freed; it resumes on its next frame or POST /resume). 0: never.")] = 600.0,
    max_frame_mb: Annotated[float, typer.Option(help="Largest request body in MiB (more get 413).")] = 32.0,
    max_pending_frames: Annotated[int, typer.Option(help="Per-session ingest queue bound (more get 429).")] = 32,
    checkpoint_interval_s: Annotated[float, typer.Option(help="Periodic map checkpoint interval.")] = 30.0,
    session_workers: Annotated[str, typer.Option(
        help="Where each session's engine runs: process (a worker process per session: fair sharing of the "
             "cores, a crash stays in its session) or thread (in the server process).")] = "process",
    worker_threads: Annotated[int, typer.Option(
        help="Torch threads per session worker (0: the cores this process may use / (2 x max-sessions), "
             "at least 1).")] = 0,
    ray_address: Annotated[str | None, typer.Option(
        "--ray-address", help="Run session workers as actors on this Ray cluster (host:6379, ray://host:10001, "
                              "auto); the data folder must be a path every node shares.")] = None,
    cpus_per_session: Annotated[float, typer.Option(help="Logical CPUs per session actor (Ray).")] = 1.0,
    gpus_per_session: Annotated[float, typer.Option(
        help="GPUs per session actor (Ray; a fraction shares a GPU, e.g. 0.25).")] = 0.0,
    worker_restarts: Annotated[int, typer.Option(
        help="Restarts of a session's dead worker process (replaying its recording) before it is failed.")] = 3,
    log_level: Annotated[str, typer.Option(help="debug, info, warning or error.")] = "info",
) -> None:
    """Run the streaming server until interrupted (Ctrl-C stops it cleanly; a hard kill loses nothing
    acknowledged: open sessions resume from their recordings)."""
    import logging

    import uvicorn

    from voxfusion.server import ServerSettings, create_app

    if (zenoh_listen or zenoh_secrets) and zenoh is False:
        raise typer.BadParameter("--zenoh-listen / --zenoh-secrets need the zenoh bridge; drop --no-zenoh",
                                 param_hint="--zenoh-listen")
    if config is not None:  # the server checks it again at startup; here a bad name is one line, not a traceback
        from voxfusion.core.errors import ConfigError
        from voxfusion.core.slam.presets import check_preset_name

        try:
            check_preset_name(config)
        except ConfigError as e:
            raise typer.BadParameter(e.problem, param_hint="--config") from None
    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = ServerSettings.from_env(
        data_dir=data_dir, device=device, default_preset=config,
        zenoh=True if zenoh_listen or zenoh_secrets else zenoh, zenoh_config=zenoh_config,
        zenoh_secrets=zenoh_secrets, zenoh_insecure=zenoh_insecure,
        zenoh_listen=tuple(zenoh_listen) if zenoh_listen else None,
        max_sessions=max_sessions, max_sessions_per_client=max_sessions_per_client,
        session_idle_timeout_s=session_idle_timeout_s, max_frame_bytes=int(max_frame_mb * 1024 * 1024),
        max_pending_frames=max_pending_frames, checkpoint_interval_s=checkpoint_interval_s,
        session_workers="ray" if ray_address and session_workers == "process" else session_workers,
        worker_threads=worker_threads, worker_restarts=worker_restarts, ray_address=ray_address,
        cpus_per_session=cpus_per_session, gpus_per_session=gpus_per_session)
    exposed = [e for e in zenoh_listen or [] if not _on_loopback(e)]
    if exposed and not (zenoh_secrets or zenoh_config or zenoh_insecure):
        raise typer.BadParameter(f"zenoh on {', '.join(exposed)} without authentication would let any peer on that "
                                 "network read session tokens: add --zenoh-secrets DIR (clients then use "
                                 "DIR/client.json5), or --zenoh-insecure on a network you trust",
                                 param_hint="--zenoh-listen")
    problem = _port_problem(host, port)
    if problem:  # uvicorn would start the app (sessions, zenoh; "ready" logged) before failing to bind
        raise typer.BadParameter(problem, param_hint="--port")
    typer.echo(f"voxfusion server on http://{host}:{port} (docs: /docs), data in {data_dir}")
    from voxfusion.server.auth import RedactTokens

    for name in ("uvicorn.access", "uvicorn.error"):  # the viewer link and the pose WebSocket carry ?token=
        logging.getLogger(name).addFilter(RedactTokens())
    uvicorn.run(create_app(settings), host=host, port=port, log_level=log_level.lower(), timeout_graceful_shutdown=30)


def _port_problem(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be listened on (bound as uvicorn binds it: ``SO_REUSEADDR``, so a port in
    TIME_WAIT is fine), or None. Checked before the app starts, so a busy port is one line and exit code 2."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        return f"cannot resolve --host {host!r}: {e.strerror}"
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as e:
            hint = ("another program (perhaps another voxfusion serve) is listening there: stop it or pick "
                    "another --port" if e.errno == errno.EADDRINUSE else "pick another --host or --port")
            return f"cannot listen on {host}:{port}: {e.strerror}; {hint}"
    return None


def _on_loopback(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0]
    return host.startswith("127.") or host in ("[::1]", "localhost")


def register(app: typer.Typer) -> None:
    """Add ``serve`` to the ``voxfusion`` app."""
    app.command("serve")(serve_command)
