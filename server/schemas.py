"""Request and response models of the JSON routes."""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from canonical_core import SceneConfig
from canonical_core.rendering import Colour


def _session_create_model() -> type[BaseModel]:
    # Mirrors SceneConfig's fields (names, types, defaults) so the API follows the library without a
    # hand-kept copy; SceneConfig itself still does the value checks (e.g. voxel_size > 0).
    hints = typing.get_type_hints(SceneConfig)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(SceneConfig):
        default = ... if f.default is dataclasses.MISSING else f.default
        fields[f.name] = (hints[f.name], default)
    return create_model(
        "SessionCreate",
        __config__=ConfigDict(extra="forbid"),
        __doc__="Scene settings of a new session (canonical_core.SceneConfig); voxel_size is required.",
        **fields,
    )


SessionCreate = _session_create_model()


class SessionCreated(BaseModel):
    id: str
    config: dict[str, Any]


class SessionSummary(BaseModel):
    id: str
    frames: int
    voxels: int
    created: float


class SessionList(BaseModel):
    sessions: list[SessionSummary]


class SessionStats(SessionSummary):
    gaussians: int
    memory_bytes: int
    disk_bytes: int
    label_dim: int
    snapshot_frames: int
    config: dict[str, Any]


class Digest(BaseModel):
    id: str
    frames: int
    voxels: int
    sha256: str


class Deleted(BaseModel):
    id: str
    deleted: bool = True


class FoldReportOut(BaseModel):
    frame_index: int
    observations: int
    new_voxels: int
    updated_voxels: int
    representative_switches: int
    ms: float
    pending: bool = Field(False, description="a frame without depth waiting for a partner view (folded later)")
    also_folded: int = Field(0, description="earlier waiting frames this call folded")
    completed_pixels: int = Field(0, description="pixels whose missing depth the plane sweep filled (depth_completion)")
    denoised: bool = Field(False, description="the frame's depth was far rougher than its noise model and was replaced by a local median (depth_denoise_radius)")
    warnings: list[str] = Field(default_factory=list, description="problems with the input that did not stop the fold, each 'field: problem' (e.g. depth that gave no observation)")


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
    background: Annotated[list[float], Field(min_length=3, max_length=3)] | None = Field(
        None, description="rgb in [0, 1] behind the Gaussians (default black)")
    colour: Colour = Field("normalised", description=(
        "render only: 'normalised' (default: each drawn pixel the blend over its accumulated weight, the "
        "expected colour of the surface the ray hits, i.e. straight, not premultiplied, colour next to "
        "alpha; the background only where nothing is drawn) or 'composited' (the 3DGS blend over the "
        "background)"))


class ErrorDetail(BaseModel):
    code: str
    message: str
    field: str | None


class ErrorBody(BaseModel):
    error: ErrorDetail


class Health(BaseModel):
    status: str
    sessions: int
