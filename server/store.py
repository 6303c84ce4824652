"""Session metadata in SQLite (stdlib ``sqlite3``, WAL journal): ids, hashed tokens, configs, states.

The database (``<data_dir>/sessions.sqlite3``) lists every session across restarts; frames, maps and
poses live in the session folders. One connection, serialised by a lock (writes are tiny and rare:
creation, state changes, final statistics).
"""

from __future__ import annotations

import json
import sqlite3
import threading
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = ["SessionRow", "SessionStore"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    name TEXT,
    token_sha256 TEXT NOT NULL,
    preset TEXT NOT NULL,
    config_json TEXT NOT NULL,
    mode TEXT NOT NULL,
    state TEXT NOT NULL,
    created_at TEXT NOT NULL,
    updated_at TEXT NOT NULL,
    last_error TEXT,
    stats_json TEXT
)
"""


@dataclass(frozen=True)
class SessionRow:
    """One session's metadata.

    Attributes:
        config: the full resolved engine configuration (``config_to_dict`` form), so a session replays
            with the configuration it was created with even if presets change.
        stats: final counters (``SessionStatus`` fields) saved when the session finished or failed.
    """

    id: str
    name: str | None
    token_sha256: str
    preset: str
    config: dict[str, Any]
    mode: str
    state: str
    created_at: datetime
    updated_at: datetime
    last_error: str | None
    stats: dict[str, Any] | None


def _now() -> str:
    return datetime.now(UTC).isoformat()


def _row(r: sqlite3.Row) -> SessionRow:
    return SessionRow(
        id=r["id"], name=r["name"], token_sha256=r["token_sha256"], preset=r["preset"],
        config=json.loads(r["config_json"]), mode=r["mode"], state=r["state"],
        created_at=datetime.fromisoformat(r["created_at"]), updated_at=datetime.fromisoformat(r["updated_at"]),
        last_error=r["last_error"], stats=json.loads(r["stats_json"]) if r["stats_json"] else None)


class SessionStore:
    """CRUD of :class:`SessionRow` in ``path`` (created with its folder if missing)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute(_SCHEMA)

    def insert(self, session_id: str, name: str | None, token_sha256: str, preset: str, config: dict[str, Any],
               mode: str, state: str) -> SessionRow:
        now = _now()
        with self._lock:
            self._db.execute(
                "INSERT INTO sessions (id, name, token_sha256, preset, config_json, mode, state, created_at, "
                "updated_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (session_id, name, token_sha256, preset, json.dumps(config), mode, state, now, now))
        created = datetime.fromisoformat(now)
        return SessionRow(session_id, name, token_sha256, preset, config, mode, state, created, created, None, None)

    def get(self, session_id: str) -> SessionRow | None:
        with self._lock:
            r = self._db.execute("SELECT * FROM sessions WHERE id = ?", (session_id,)).fetchone()
        return None if r is None else _row(r)

    def all(self) -> list[SessionRow]:
        with self._lock:
            rows = self._db.execute("SELECT * FROM sessions ORDER BY created_at").fetchall()
        return [_row(r) for r in rows]

    def set_state(self, session_id: str, state: str, last_error: str | None = None,
                  stats: dict[str, Any] | None = None) -> None:
        """Update the state (and the error / final statistics when given; ``last_error=""`` clears it)."""
        sets, args = ["state = ?", "updated_at = ?"], [state, _now()]
        if last_error is not None:
            sets.append("last_error = ?")
            args.append(last_error or None)
        if stats is not None:
            sets.append("stats_json = ?")
            args.append(json.dumps(stats))
        with self._lock:
            self._db.execute(f"UPDATE sessions SET {', '.join(sets)} WHERE id = ?", (*args, session_id))

    def delete(self, session_id: str) -> None:
        with self._lock:
            self._db.execute("DELETE FROM sessions WHERE id = ?", (session_id,))

    def close(self) -> None:
        with self._lock:
            self._db.close()
