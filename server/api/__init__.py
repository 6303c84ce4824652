"""The HTTP API: dependencies (:mod:`.deps`) and one router per resource (:mod:`.routes`)."""

from .routes import ROUTERS

__all__ = ["ROUTERS"]
