"""Replaying a recorded capture into a server session: paced like the recording, at a fixed rate, or as
fast as the server takes it; then finishing the session and downloading the mesh and the trajectory.

Example::

    from voxfusion.clients import Client, StreamOptions, stream_capture
    from voxfusion.core.datasets import open_capture

    with Client("http://127.0.0.1:8000") as client:
        client.create_session("desk", mode="offline")
        result = stream_capture(open_capture("rgbd_dataset_freiburg1_desk"), client,
                                StreamOptions(realtime=True), out_dir="out/desk")
        print(result.frames_sent, result.send_fps, result.mesh_path)
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ValidationError
from voxfusion.core.trajectory import write_tum_trajectory
from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.schemas import PoseOut

from .base import BaseClient, poses_to_trajectory

__all__ = ["StreamOptions", "StreamResult", "Pacer", "stream_frames", "stream_capture", "finish_and_download",
           "write_session_file", "session_summary",
           "format_pose"]


@dataclass(frozen=True)
class StreamOptions:
    """How :func:`stream_capture` paces and bounds a replay.

    Example::

        StreamOptions()                    # as fast as the server takes frames
        StreamOptions(realtime=True)       # at the recorded rate (frame timestamps)
        StreamOptions(fps=10, max_frames=100)
    """

    fps: float | None = None
    """Send at this fixed rate (frames per second); ``None``: see ``realtime``."""
    realtime: bool = False
    """Send each frame at its recorded time (``timestamp_s`` relative to the first frame)."""
    max_frames: int | None = None
    """Stop after this many frames; ``None``: the whole capture."""
    pose_poll_s: float = 0.5
    """Clients without a pose stream (HTTP) ask for the latest pose this often for the progress bar."""

    def __post_init__(self) -> None:
        if self.fps is not None and not self.fps > 0:
            raise ValidationError("fps", f"must be > 0 frames per second, got {self.fps}")
        if self.fps is not None and self.realtime:
            raise ValidationError("fps", "give either fps or realtime, not both")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValidationError("max_frames", f"must be >= 1, got {self.max_frames}")


@dataclass(frozen=True)
class StreamResult:
    """What a replay did.

    Attributes:
        session_id: the session streamed into.
        frames_sent: frames the server acknowledged.
        send_s: wall time from the first frame sent to the last one acknowledged.
        send_fps: ``frames_sent / send_s``.
        status: the session's status at the end (after finishing, when it was finished).
        mesh_path, trajectory_path: downloaded files, or ``None``.
    """

    session_id: str
    frames_sent: int
    send_s: float
    send_fps: float
    status: SessionStatusOut | None = None
    mesh_path: Path | None = None
    trajectory_path: Path | None = None


class Pacer:
    """Sleeps until each frame's send time: recorded timestamps (``realtime``), a fixed ``fps``, or never."""

    def __init__(self, options: StreamOptions) -> None:
        self.options = options
        self._t0_wall: float | None = None
        self._t0_frame: float | None = None
        self._i = 0

    def wait(self, frame: RGBDFrame) -> None:
        now = time.monotonic()
        if self._t0_wall is None:
            self._t0_wall, self._t0_frame = now, frame.timestamp_s
        if self.options.realtime:
            due = self._t0_wall + max(0.0, frame.timestamp_s - (self._t0_frame or 0.0))
        elif self.options.fps is not None:
            due = self._t0_wall + self._i / self.options.fps
        else:
            due = now
        self._i += 1
        if due > now:
            time.sleep(due - now)


def format_pose(pose: PoseOut | None) -> str:
    """``"#12 t=(0.12, -0.03, 1.40)"``: a short pose for progress bars (`` LOST`` / `` LIMITED`` appended when its
    tracking state is not ``normal``)."""
    if pose is None:
        return "-"
    t = np.asarray(pose.T_world_cam)[:3, 3]
    state = "" if pose.tracking_state == "normal" else f" {pose.tracking_state.upper()}"
    return f"#{pose.seq} t=({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}){state}"


class _LivePose:
    """The newest pose, followed over zenoh (subscription) or by polling (HTTP)."""

    def __init__(self, client: BaseClient, poll_s: float) -> None:
        self.client = client
        self.poll_s = poll_s
        self.pose: PoseOut | None = None
        self._lock = threading.Lock()
        self._last_poll = 0.0
        self._subscribed = False
        subscribe = getattr(client, "subscribe_poses", None)
        if subscribe is not None:
            subscribe(self._on_pose)
            self._subscribed = True

    def _on_pose(self, pose: PoseOut) -> None:
        with self._lock:
            if self.pose is None or pose.seq >= self.pose.seq:
                self.pose = pose

    def current(self) -> PoseOut | None:
        if not self._subscribed and time.monotonic() - self._last_poll >= self.poll_s:
            self._last_poll = time.monotonic()
            pose = self.client.latest_pose()
            if pose is not None:
                self._on_pose(pose)
        with self._lock:
            return self.pose


def stream_frames(frames: Iterable[RGBDFrame], client: BaseClient, options: StreamOptions | None = None, *,
                  total: int | None = None, progress: bool = True,
                  on_frame: Callable[[int], None] | None = None) -> tuple[int, float]:
    """Send ``frames`` to the client's current session in order (pipelined with ``send_frame_async``).

    Args:
        frames: the frames (any iterable; consumed lazily).
        client: a client with a current session.
        options: pacing and limits.
        total: number of frames for the progress bar.
        progress: show a tqdm bar (sent frames, live pose, send rate).
        on_frame: called with the count of frames sent so far after each one.

    Returns:
        ``(frames acknowledged, seconds from the first send to the last acknowledgement)``.

    Raises:
        ServerError / TransportError: a frame was refused or got no answer (the first such error).
    """
    options = options or StreamOptions()
    pacer = Pacer(options)
    live = _LivePose(client, options.pose_poll_s)
    if options.max_frames is not None:
        total = min(total, options.max_frames) if total is not None else options.max_frames
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc="streaming", dynamic_ncols=True)
    futures: list[Future[int]] = []
    t0: float | None = None
    sent = 0
    try:
        for frame in frames:
            if options.max_frames is not None and sent >= options.max_frames:
                break
            pacer.wait(frame)
            if t0 is None:
                t0 = time.monotonic()
            futures.append(client.send_frame_async(frame))
            sent += 1
            while futures and futures[0].done():
                futures.pop(0).result()  # raises the first refusal
            if bar is not None:
                elapsed = max(time.monotonic() - t0, 1e-9)
                bar.set_postfix_str(f"{sent / elapsed:.1f} fps, pose {format_pose(live.current())}", refresh=False)
                bar.update(1)
            if on_frame is not None:
                on_frame(sent)
        client.flush()
        for fut in futures:
            fut.result()
    finally:
        if bar is not None:
            bar.close()
    return sent, (time.monotonic() - t0) if t0 is not None else 0.0


def finish_and_download(client: BaseClient, out_dir: str | Path | None, *,
                        finish_timeout_s: float = 3600.0) -> tuple[SessionStatusOut, Path | None, Path | None]:
    """Finish the session, then write ``mesh.ply`` and ``trajectory.txt`` (TUM) into ``out_dir``.

    Returns ``(final status, mesh path or None, trajectory path or None)``; nothing is downloaded when
    ``out_dir`` is ``None``.
    """
    status = client.finish(timeout_s=finish_timeout_s)
    if out_dir is None:
        return status, None, None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh_path = out / "mesh.ply"
    client.download_mesh(mesh_path, format="ply")
    traj_path = write_tum_trajectory(out / "trajectory.txt", poses_to_trajectory(client.trajectory()))
    return status, mesh_path, traj_path


def session_summary(status: SessionStatusOut) -> str:
    """One line on what the server did with a session's frames, e.g.
    ``session 3f2a... finished: 942 received, 310 tracked (2 lost, 1 limited), 632 dropped by the server, 31 keyframes,
    2210 voxels``.

    ``dropped``: frames recorded but skipped by tracking to keep up (realtime sessions; they stay in the
    recording); ``lost``: tracked frames whose tracking failed (``frames_lost``: their pose is the motion
    model's guess and they are not fused); ``limited``: tracked frames whose cost jumped (``frames_limited``:
    the pose may be wrong; they are fused).
    """
    line = (f"session {status.id} {status.state.value}: {status.frames_received} received, "
            f"{status.frames_tracked} tracked ({status.frames_lost} lost, {status.frames_limited} limited), "
            f"{status.frames_dropped} dropped by the "
            f"server, {status.keyframes} keyframes, {status.voxels} voxels")
    return line + (f", error: {status.last_error}" if status.last_error else "")


def write_session_file(client: BaseClient, out_dir: Path) -> None:
    """``session.json`` (id, token, where the mesh is): enough to query the session again; owner-only."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "session.json"
    info = {"id": client.session.id, "token": client.session.token, "mesh": client.mesh_url}
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(info, f, indent=2)


def stream_capture(frames: Iterable[RGBDFrame], client: BaseClient, options: StreamOptions | None = None, *,
                   out_dir: str | Path | None = None, finish: bool = True, progress: bool = True,
                   total: int | None = None) -> StreamResult:
    """Stream a capture into the client's current session, then (``finish``) finish it and download
    ``mesh.ply`` and ``trajectory.txt`` into ``out_dir`` (with ``session.json``: id, token, mesh location).
    """
    if total is None and hasattr(frames, "__len__"):
        total = len(frames)  # type: ignore[arg-type]
    if hasattr(frames, "frames"):  # a Capture: iterate lazily
        frames = frames.frames()  # type: ignore[union-attr]
    if out_dir is not None:
        write_session_file(client, Path(out_dir))
    sent, send_s = stream_frames(frames, client, options, total=total, progress=progress)
    fps = sent / send_s if send_s > 0 else 0.0
    if not finish:
        return StreamResult(client.session.id, sent, send_s, fps, client.status())
    status, mesh_path, traj_path = finish_and_download(client, out_dir)
    return StreamResult(client.session.id, sent, send_s, fps, status, mesh_path, traj_path)
