"""The CanonicalGS Fusion HTTP service (FastAPI): parses, validates, calls canonical_core, encodes.

Entry point: `server.app.create_app` (``canonical serve`` or ``uvicorn server.app:create_app --factory``).
"""
