"""The voxfusion streaming server: FastAPI over a multi-session manager around the ``core`` engine.

``create_app(settings)`` builds the app (``voxfusion serve`` runs it on uvicorn); ``SessionManager`` is the
transport-independent API the HTTP routes and the zenoh bridge share.
"""

from .app import create_app
from .manager import SessionManager
from .settings import ServerSettings

__all__ = ["create_app", "SessionManager", "ServerSettings"]
