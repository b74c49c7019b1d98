"""Request and response models of the JSON routes."""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator

from canonical_core.rendering import Colour, DepthMode
from canonical_core.scene import FoldReport
from canonical_core.config import public_model


def model_of_dataclass(cls: type, name: str) -> type[BaseModel]:
    """A response model with ``cls``'s fields (names, types, defaults; a field's
    ``metadata["description"]`` as its description), so a new field of the library type reaches the
    HTTP schema without a hand-kept copy."""
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        description = f.metadata.get("description")
        if f.default_factory is not dataclasses.MISSING:
            fields[f.name] = (hints[f.name], Field(default_factory=f.default_factory, description=description))
        else:
            default = ... if f.default is dataclasses.MISSING else f.default
            fields[f.name] = (hints[f.name], Field(default, description=description))
    return create_model(name, __doc__=cls.__doc__, **fields)


# The settings a client may choose, generated from SceneConfig (types, bounds, defaults, docs); the
# evaluation-only groups are left out, so they are unknown fields here (422).
SessionCreate = create_model(
    "SessionCreate", __base__=public_model("SessionSettings", doc="Scene settings of a new session"),
    __doc__="Scene settings of a new session (canonical_core.SceneConfig without its research group; without "
            "voxel_size, or with sensor.family auto, they are chosen from the first frame with depth) and its frame "
            "archive's retention.",
    archive_retention=(Literal["all", "keyframes", "none"] | None, Field(
        None, description="which frames the session keeps for pose corrections and frame removal: all, keyframes "
                          "(one in five) or none (corrections are refused); default: the service's "
                          "CANONICAL_ARCHIVE_RETENTION")))


class SessionCreated(BaseModel):
    id: str
    config: dict[str, Any]
    archive_retention: Literal["all", "keyframes", "none"] = Field(
        "all", description="which frames the session keeps for pose corrections and frame removal")


class SessionSummary(BaseModel):
    id: str
    frames: int | None = Field(description="None while the session is unavailable")
    voxels: int | None
    created: float = Field(description="unix time of its creation")
    last_active: float | None = Field(None, description=(
        "unix time of its last frame or correction: the newest change of its files, which every acknowledged "
        "frame makes (None while unavailable); what the retention policy reads"))
    voxel_size: float | None = Field(None, description="metres (None while unavailable, or until the first frame "
                                                       "with depth chooses it)")
    memory_bytes: int | None = Field(None, description="bytes its scene holds in memory (None while unavailable)")
    disk_bytes: int | None = Field(None, description="bytes of the files in its folder (None while unavailable)")
    archive_retention: Literal["all", "keyframes", "none"] | None = Field(
        None, description="which frames the session keeps for pose corrections (None while unavailable)")
    state: Literal["ok", "read_only", "unavailable"] = Field(
        "ok", description="read_only: its log cannot take frames until a restart; unavailable: its files need "
                          "`canonical repair` (or a backup), it is not served")
    problem: str | None = Field(None, description="what is wrong, when state is not ok")


class SessionList(BaseModel):
    sessions: list[SessionSummary]


class SessionStats(SessionSummary):
    archive_bytes: int = Field(0, description="bytes of the frame archive on disk (compressed frames and corrections)")
    archive_frames: int = Field(0, description="frames whose content the archive keeps")
    archive_problem: str | None = Field(None, description="why the archive cannot serve corrections, if it cannot")
    gaussians: int
    undo_bytes: int = Field(0, description="bytes of the undo records of the last folds, which make corrections of "
                                           "recent frames cheap (part of memory_bytes)")
    label_dim: int
    inconsistent_depth_below: float | None = Field(
        None, description="metres: the depth under which this session's consecutive frames disagree, likely under "
                          "the sensor's working range (the setting near can ignore it); None while they agree")
    sensor: str = Field("auto", description="the depth sensor family whose noise model the session uses (auto "
                                            "until the first frame chooses it)")
    chosen: dict[str, str] = Field(default_factory=dict, description=(
        "why voxel_size and sensor have their values: 'set', or the rule that chose them from the first frame"))
    snapshot_frames: int
    snapshot_error: str | None = Field(None, description="why the last snapshot failed (its frames stay durable in the log)")
    colours_solved_frames: int | None = Field(
        None, description="the frame count whose state the colours that renders show were solved for (equal to frames: "
                          "solved colours of the scene as it is; lower: a solve runs in the background while no frame "
                          "waits); None: none solved yet, or colour_solve.views is 0")
    colour_solves_stopped: int = Field(0, description="background colour solves of this session that gave way to one "
                                                      "of its frames since the service started (a frame that arrives "
                                                      "stops the solve running: streams never wait for it)")
    config: dict[str, Any]


class Digest(BaseModel):
    id: str
    frames: int
    voxels: int
    sha256: str


class PrunedSession(BaseModel):
    id: str
    reason: Literal["ttl", "disk_budget"] = Field(description="idle longer than session_ttl_s, or the oldest idle "
                                                              "while the data directory exceeded disk_budget_bytes")
    last_active: float = Field(description=(
        "unix time of the newest change of its files: its last frame or correction, or the snapshot written after them"))
    disk_bytes: int


class PruneReport(BaseModel):
    dry_run: bool = Field(description="true: nothing was removed, `removed` lists what would have been")
    removed: list[PrunedSession] = Field(description="oldest first")
    data_dir_bytes: int = Field(description="bytes of the data directory before")
    freed_bytes: int = Field(description="bytes of the removed sessions' files")
    session_ttl_s: float | None = Field(description="the service's setting (None: no time to live)")
    disk_budget_bytes: int | None = Field(description="the service's setting (None: no budget)")
    floor_s: float = Field(description="a session active more recently than this is never removed, whatever the settings")


class Deleted(BaseModel):
    id: str
    deleted: bool = True


FoldReportOut = model_of_dataclass(FoldReport, "FoldReportOut")


# frames one correction may name, checked before any item is: a bound on the items' validation; the
# body's own bound (max_json_body_bytes) comes first for most (4 MiB carries about 12,000 poses)
MAX_FRAME_KEYS = 1_000_000

Matrix3 = Annotated[list[Annotated[list[float], Field(min_length=3, max_length=3)]], Field(min_length=3, max_length=3)]
Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=3, max_length=4)]


class ViewRequest(BaseModel):
    """A camera to render at: K (pixels), c2w (OpenCV camera-to-world), image size."""

    model_config = ConfigDict(extra="forbid", strict=True)  # strict: no strings or booleans taken as numbers

    K: Matrix3
    c2w: Matrix4
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    max_gaussians: int | None = Field(None, ge=0, description="level of detail: the best-supported N Gaussians")
    background: Annotated[list[Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]], Field(min_length=3, max_length=3)] | None = Field(
        None, description="rgb in [0, 1] behind the Gaussians (default black)")
    colour: Colour = Field("normalised", description=(
        "render only: 'normalised' (default: each drawn pixel the blend over its accumulated weight, the "
        "expected colour of the surface the ray hits, i.e. straight, not premultiplied, colour next to "
        "alpha; the background only where nothing is drawn) or 'composited' (the 3DGS blend over the "
        "background)"))
    depth: DepthMode = Field("median", description=(
        "render only, msgpack's depth map: 'median' (default: the depth of the surface that covers most of "
        "each pixel, where its transmittance falls below 1/2; no depths between a foreground edge and the "
        "background) or 'expected' (the blend of every splat's depth on the ray)"))


class ErrorDetail(BaseModel):
    code: str
    message: str
    field: str | None


class ErrorBody(BaseModel):
    error: ErrorDetail


class Health(BaseModel):
    status: str
    sessions: int | None = None  # not told to a request without the token, where one is set


class Limits(BaseModel):
    """The service's limits on one request (its CANONICAL_* settings): larger requests get 413. A client
    that reads them can fit its frames first (the SDK downscales frames without depth to
    ``max_rgb_only_pixels``)."""

    max_body_bytes: int = Field(description="a frame's body")
    max_json_body_bytes: int = Field(description="any other body (JSON: views, settings, pose corrections)")
    max_image_pixels: int = Field(description="pixels of a frame's images or of a requested view")
    max_rgb_only_pixels: int = Field(description="pixels of a frame without depth")
    max_label_channels: int
    max_channel_values: int = Field(description="image pixels x channels of a frame's features or labels")
    max_response_bytes: int


class PosesRequest(BaseModel):
    """One correction: new camera-to-world poses and/or frames to remove, applied as one re-fold.

    A key in ``poses`` (a string) names a frame by its ``frame_id``, else, where it is digits and no
    frame has it as its ``frame_id``, by its arrival index. ``poses_by_arrival`` and the integers of
    ``remove`` name frames by their arrival index only: a client whose frame ids are numbers too
    (line numbers, timestamps) says which it means."""

    model_config = ConfigDict(extra="forbid", strict=True)

    # bounded first: each item that fails validation would otherwise make an error object of its own
    poses: dict[str, Matrix4] = Field(default_factory=dict, max_length=MAX_FRAME_KEYS,
                                      description="frame key -> 4x4 (or 3x4) c2w, OpenCV axes, metres")
    # JSON's keys are strings: an arrival index is one of digits (`_arrivals`)
    poses_by_arrival: dict[str, Matrix4] = Field(default_factory=dict, max_length=MAX_FRAME_KEYS,
                                                 description="arrival index (digits) -> 4x4 (or 3x4) c2w, as poses")
    # items checked one by one after the bound (`_keys`): a union type made two error objects an invalid item
    remove: list[Any] = Field(default_factory=list, max_length=MAX_FRAME_KEYS,
                              description="frames to remove: frame keys (strings, as poses') or arrival indices (integers)")
    wait: bool = Field(True, description="answer once the scene is corrected (200), unless the re-fold is long "
                                         "(then 202 and a status to poll); false: always 202 at once")

    @field_validator("poses_by_arrival")
    @classmethod
    def _arrivals(cls, poses: dict) -> dict:
        """Keys of digits (as ``Frame-Index``: no sign, space or underscore) as integers, none twice."""
        out: dict = {}
        for key, c2w in poses.items():
            if not (key.isascii() and key.isdigit() and len(key) <= 18):
                raise ValueError(f"poses_by_arrival.{key}: expected an arrival index (digits)")
            if int(key) in out:
                raise ValueError(f"poses_by_arrival.{key}: names arrival {int(key)}, which another key names too")
            out[int(key)] = c2w
        return out

    @field_validator("remove")
    @classmethod
    def _keys(cls, keys: list) -> list:
        for k, key in enumerate(keys):
            if not (isinstance(key, str) or (type(key) is int and key >= 0)):
                raise ValueError(f"remove.{k}: expected a frame key (a string) or an arrival index (an integer >= 0), "
                                 f"got {type(key).__name__}")
        return keys


class Correction(BaseModel):
    id: str
    frames: int = Field(description="frames the scene holds after the correction")
    frames_before: int
    corrected: int = Field(description="frames given a new pose")
    removed: int = Field(description="frames removed on request")
    dropped: int = Field(description="frames the archive did not keep (retention 'keyframes'), left out of the re-fold")
    state: Literal["pending", "running", "done", "failed"] = Field(
        "done", description="done; or, in a 202 answer, pending: the scene re-folds in the background")
    correction_id: str | None = Field(None, description="a background correction's id (GET .../corrections/{id})")


class CorrectionStatus(BaseModel):
    """A background correction: the old scene is served until ``state`` is done, then the corrected one."""

    correction_id: str
    state: Literal["pending", "running", "done", "failed"] = Field(
        description="failed: the old scene is still served and the correction is undone in the "
                    "archive, so frames go on and a restart does not retry it (only where that cannot "
                    "be written is the session read-only until a restart, which retries it)")
    refolded: int = Field(description="frames re-folded so far")
    total: int = Field(description="frames to re-fold, including those that arrived meanwhile")
    error: str | None = None
    result: Correction | None = Field(None, description="what the correction did, once done")


# -- the viewer's data ------------------------------------------------------------------------------
class ViewerInfo(BaseModel):
    """The colours the service draws pictures in, so that the page's scale bar and legend match them."""

    depth_colormap: list[list[int]] = Field(description="[R, G, B] 0-255 per step, near first: the depth pictures' "
                                                        "colour map")
    label_palette: list[list[int]] = Field(description="[R, G, B] 0-255: entry k + 1 is label k's colour, entry 0 "
                                                       "where no label is drawn")
    max_picture_pixels: int = Field(description="the most pixels of a colour or depth picture the service renders "
                                                "(max_image_pixels, and max_response_bytes for its five float maps)")


class _LastFold(BaseModel):
    last_fold: float | None = Field(None, description="unix time of its last fold (null: none known, or unavailable)")


class ViewerSessionStats(SessionStats, _LastFold):
    """A served session in the viewer's list."""


class ViewerSessionSummary(SessionSummary, _LastFold):
    """An unavailable session in the viewer's list (no stats: its files need `canonical repair`)."""


class ViewerSessionList(BaseModel):
    sessions: list[ViewerSessionStats | ViewerSessionSummary] = Field(
        description="served sessions with their stats, then the unavailable ones")


class InputCamera(BaseModel):
    """One input camera of a session (`server.track.camera_json`)."""

    frame_index: int = Field(description="the frame's arrival index in the session")
    width: int = Field(description="image width, pixels")
    height: int = Field(description="image height, pixels")
    K: list[float] = Field(description="fx, fy, cx, cy in pixels", min_length=4, max_length=4)
    c2w: list[float] = Field(description="camera-to-world pose, 16 numbers row-major, OpenCV axes",
                             min_length=16, max_length=16)


class InputCamerasOut(_LastFold):
    """A session's input cameras, oldest first, and when it last folded."""

    id: str
    frames: int = Field(description="frames the session holds")
    label_dim: int = Field(description="its label channels (0: none)")
    last_fold_age: float | None = Field(description="seconds since its last fold on the service's clock, so that "
                                                    "a client's own clock's skew does not matter (null: none known)")
    cameras: list[InputCamera]
