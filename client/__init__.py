"""Client side of CanonicalGS Fusion: the Python SDK (`Client`) and the ``canonical`` CLI. HTTP only."""

from .sdk import CanonicalError, Client, Session

__all__ = ["CanonicalError", "Client", "Session"]
