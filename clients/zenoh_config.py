"""Loading zenoh configurations (JSON5 files) for the server bridge and the clients.

The defaults ship in ``configs/zenoh/`` (package ``voxfusion.configs``): ``server.json5`` (a peer listening
on ``tcp/127.0.0.1:7447`` only, scouting off) and ``client.json5`` (a zenoh client connecting there).

Example::

    cfg = load_zenoh_config(None, "client", connect=["tcp/192.168.1.20:7447"])
    session = zenoh.open(cfg)
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from voxfusion.core.errors import ConfigError

if TYPE_CHECKING:
    import zenoh

__all__ = ["default_zenoh_config_path", "load_zenoh_config", "require_zenoh"]


def require_zenoh() -> object:
    """Import ``zenoh`` (package ``eclipse-zenoh``), or raise a :class:`ConfigError` saying how to install it."""
    try:
        import zenoh
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ConfigError("zenoh", "the zenoh transport needs the 'eclipse-zenoh' package: "
                                   "pip install 'voxfusion[server]' (or pip install eclipse-zenoh)") from e
    return zenoh


def default_zenoh_config_path(kind: Literal["server", "client"]) -> Path:
    """Path of the shipped ``configs/zenoh/<kind>.json5``."""
    if kind not in ("server", "client"):
        raise ConfigError("kind", f"must be 'server' or 'client', got {kind!r}")
    return Path(str(resources.files("voxfusion.configs").joinpath("zenoh", f"{kind}.json5")))


def load_zenoh_config(path: str | Path | None, kind: Literal["server", "client"] = "client", *,
                      listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Config:
    """A :class:`zenoh.Config` from a JSON5 file (``None``: the shipped default for ``kind``).

    Args:
        path: JSON5 config file.
        kind: which default to use when ``path`` is ``None``.
        listen: replaces ``listen/endpoints`` (e.g. ``["tcp/127.0.0.1:0"]``).
        connect: replaces ``connect/endpoints`` (e.g. ``["tcp/127.0.0.1:7447"]``).

    Raises:
        ConfigError: the file is missing or zenoh refuses it (the message names the file).
    """
    z = require_zenoh()
    path = Path(path) if path is not None else default_zenoh_config_path(kind)
    if not path.is_file():
        raise ConfigError("zenoh_config", f"zenoh config file {path} does not exist")
    try:
        cfg = z.Config.from_file(str(path))  # type: ignore[attr-defined]
        if listen is not None:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect is not None:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except Exception as e:  # zenoh.ZError: a malformed file or a bad endpoint
        raise ConfigError("zenoh_config", f"{path}: {e}") from e
    return cfg
