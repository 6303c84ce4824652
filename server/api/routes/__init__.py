"""One router per resource; :data:`ROUTERS` lists them in the order the app includes them."""

from . import exports, frames, health, poses, render, sessions, viewer

__all__ = ["ROUTERS"]

ROUTERS = (health.router, sessions.router, frames.router, poses.router, render.router, exports.router, viewer.router)
