"""The service's settings: one class, read from ``CANONICAL_*`` environment variables.

Example:
    >>> Settings(data_dir="/tmp/x", queue_limit=4).queue_limit
    4
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from canonical_core.config import MAX_VOXELS
from canonical_core.scene.scene import DEFAULT_UNDO_DEPTH

from .scheduler import INGEST_NICE, RENDER_NICE, SOLVE_NICE


def default_memory_budget() -> int:
    """Half the machine's RAM (8 GiB where the system does not say): the rest is the process itself,
    decoded Gaussians, renders, request bodies and the page cache that the log and archive lean on."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


class Settings(BaseSettings):
    """Service settings (env prefix ``CANONICAL_``, e.g. ``CANONICAL_DATA_DIR``, ``CANONICAL_API_TOKEN``)."""

    model_config = SettingsConfigDict(env_prefix="CANONICAL_", extra="ignore")

    data_dir: Path = Field(Path("./data"), description="where sessions are stored (one folder per session)")
    api_token: SecretStr | None = Field(None, description="when set, every route but /healthz needs 'Authorization: Bearer <token>'")
    max_body_bytes: int = Field(64 * 1024 * 1024, gt=0, description="larger request bodies get 413")
    max_json_body_bytes: int = Field(4 * 1024 * 1024, gt=0, description=(
        "larger bodies other than frames (JSON: views, settings, pose corrections of about 12,000 frames) get "
        "413: JSON is parsed whole, on the event loop, into up to a hundred times its bytes"))
    max_image_pixels: int = Field(4096 * 4096, gt=0, description="larger images (frames or requested views) get 413")
    max_rgb_only_pixels: int = Field(1280 * 1024, gt=0, description="larger frames without depth get 413 (they are plane-swept and kept whole until folded)")
    max_label_channels: int = Field(64, gt=0, description="frames with more label channels get 413 (each is a float per voxel)")
    max_channel_values: int = Field(1 << 25, gt=0, description="image pixels x channels of a frame's features or labels above this get 413")
    max_response_bytes: int = Field(256 * 1024 * 1024, gt=0, description="views whose float maps (pixels x channels x 4 bytes) exceed this get 413")
    header_timeout_s: float = Field(10.0, gt=0, description="a connection whose request head has not arrived in this time is closed")
    read_timeout_s: float = Field(15.0, gt=0, description="a request body that stalls this long between reads gets 408")
    send_timeout_s: float = Field(60.0, gt=0, description=(
        "a client that takes no bytes of a large answer (a render, an export) for this long has its connection "
        "closed, so that the answer does not stay in the service's memory"))
    body_timeout_s: float = Field(120.0, gt=0, description="a request body not complete in this time gets 408")
    max_inflight_body_bytes: int = Field(1 << 30, gt=0, description=(
        "the request bodies being received or held, all requests together, counted as their bytes arrive; a "
        "request whose body would pass it gets 429 with Retry-After naming this setting (at least max_body_bytes)"))
    max_event_streams_per_session: int = Field(32, gt=0, description=(
        "open event streams (GET /v1/sessions/{id}/events) of one session; one more gets 429"))
    max_event_streams: int = Field(256, gt=0, description=(
        "open event streams of all sessions together; one more gets 429 (every fold is sent to its session's)"))
    max_sessions: int = Field(64, gt=0, description="creating one more session gets 409")
    max_session_voxels: int = Field(8_000_000, gt=0, le=MAX_VOXELS, description=(
        "the voxels a session may hold: its max_voxels when it sets none, and the most it may set (422 above); "
        "about 400 bytes of memory a voxel"))
    memory_budget_bytes: int = Field(default_factory=default_memory_budget, gt=0, description=(
        "the sessions' scenes, the folds under way and the decoded frames waiting for them together; a frame whose "
        "fold (one new voxel per pixel it lifts, at worst) or decoded arrays could pass it gets 413 naming this "
        "budget, or 429 where only what is under way leaves too little (default: half the machine's RAM)"))
    archive_retention: Literal["all", "keyframes", "none"] = Field("all", description=(
        "the frames new sessions keep for pose corrections and frame removal: all, keyframes (one in five; a "
        "correction then re-folds those alone) or none (corrections get 409)"))
    correction_background_frames: int = Field(64, ge=0, description=(
        "a pose correction that would re-fold more frames than this re-folds in the background: POST /poses "
        "answers 202 and the client polls its status"))
    correction_undo_frames: int = Field(DEFAULT_UNDO_DEPTH, ge=0, le=1024, description=(
        "a session keeps undo records of its last this many folds, so that a pose correction of them rolls "
        "back in place and re-folds only them; each record costs about the rows its fold touched (megabytes "
        "at 640x480), counted in the session's memory_bytes; past the newest 5, the oldest are dropped while "
        "the records hold more than half the bytes of the session's voxel map"))
    preallocate_voxels: int = Field(0, ge=0, le=MAX_VOXELS, description=(
        "each session's scene commits the memory of this many voxels up front (at most its max_voxels; about "
        "150 bytes a voxel, counted in its memory_bytes), so that folds growing the map up to that size never "
        "wait for fresh pages: steadier fold times for sessions whose size is known, at that memory per session"))
    snapshot_every_frames: int = Field(50, gt=0, description="snapshot a session after this many frames since its last one")
    snapshot_every_seconds: float = Field(60.0, gt=0, description="... or when its oldest unsnapshotted frame is this old")
    session_ttl_s: float | None = Field(None, gt=0, description=(
        "a session idle (no frame, no correction) longer than this is removed (default: never); one active in the "
        "last 24 hours never is, whatever this says"))
    disk_budget_bytes: int | None = Field(None, gt=0, description=(
        "while the data directory holds more than this, the sessions idle longest are removed, oldest first, down to "
        "those active in the last 24 hours (default: no budget); damaged (unavailable) sessions count but are kept"))
    retention_every_s: float = Field(300.0, gt=0, description=(
        "how often the service applies session_ttl_s and disk_budget_bytes (POST /v1/sessions/prune applies them now)"))
    frame_order_wait_s: float = Field(30.0, gt=0, description=(
        "a frame numbered with Frame-Index waits for the frames before it (posted on other connections) until no "
        "frame has been folded for this long, then gets 409; numbered frames fold in their numbers' order"))
    queue_limit: int = Field(8, gt=0, description=(
        "compute jobs of one session and one kind (frames and corrections; renders, exports and other work; the "
        "viewer's pictures) running or waiting; one more of that session and kind gets 429 with Retry-After, "
        "other sessions and kinds are not affected"))
    frame_workers: int = Field(2, gt=0, description=(
        "threads that fold frames (and run corrections, session creation and deletion): one session's one at a "
        "time, the sessions in turn"))
    ingest_workers: int = Field(2, gt=0, description=(
        "threads that read, decode and check frames' bodies, beside the folds: a client's next frames are "
        "ready when the fold before them ends"))
    ingest_nice: int = Field(INGEST_NICE, ge=0, le=19, description=(
        "how much lower the OS priority (nice) of the ingest workers is than the service's, so that a frame's "
        "decode takes the cores the fold under way leaves rather than one of its threads (its parallel kernels "
        "wait for their slowest thread); below render_nice, so decodes still go before renders (0: the same)"))
    render_workers: int = Field(2, gt=0, description=(
        "threads that run renders, views, exports, stats and the viewer's pictures, after the frames"))
    render_nice: int = Field(RENDER_NICE, ge=0, le=19, description=(
        "how much lower the OS priority (nice) of the render workers is than the service's, so that a fold, and "
        "a frame's decode (ingest_nice), running beside a render get the cores first (0: the same)"))
    solve_workers: int = Field(1, gt=0, description=(
        "threads that solve the sessions' colours in the background (colour_solve.views), at the lowest OS "
        "priority, while a session has no frame waiting: a session's one at a time, the sessions in turn"))
    solve_nice: int = Field(SOLVE_NICE, ge=0, le=19, description=(
        "how much lower the OS priority (nice) of the solve workers is than the service's (19: the lowest, so "
        "that folds and renders get the cores first; on a machine that other work keeps busy a solve then waits "
        "for idle cores, and a lower value trades fold time for solved colours sooner)"))
    threads: int | None = Field(None, gt=0, description="CPU threads per job for numba and torch (default: their own)")
    warm_up: bool = Field(True, description="fold, decode and render a tiny scene at start-up, so the first request does not pay for loading the kernels")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)

    @field_validator("max_inflight_body_bytes")
    @classmethod
    def _body_fits_in_flight(cls, value: int, info: ValidationInfo) -> int:
        largest = info.data.get("max_body_bytes")  # absent when it was refused itself
        if largest is not None and value < largest:
            raise ValueError(f"must be at least max_body_bytes ({largest}): a largest body would never be taken")
        return value

    @field_validator("api_token")
    @classmethod
    def _token_not_blank(cls, value: SecretStr | None) -> SecretStr | None:
        # an empty token would be a check anyone passes with "Authorization: Bearer "
        if value is not None and not value.get_secret_value().strip():
            raise ValueError("is empty: unset it to serve without a token, or set a long random string")
        return value
