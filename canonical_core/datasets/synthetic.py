"""A generated RGB-D sample: textured boxes on a textured ground, ray-cast exactly.

The scene (world z up, metres): a ground square at z = 0 and a few axis-aligned boxes standing on
it, each surface with its own procedural texture (checker, diagonal stripes or random colour
cells) times a fine 1 cm grain of random brightness, so that image features tell surface points
apart. Shading is Lambertian from a fixed light, hence view-independent: two views of one point
have the same colour. Depth is the analytic ray-plane / ray-box (slab) intersection, exact up to
float32 storage; pixels that see the sky have depth 0 (missing).

Example:
    >>> seq = synthetic_rgbd(num_frames=3, width=64, height=48, seed=1)
    >>> f = seq[0]
    >>> f.rgb.shape, f.depth.shape, bool((f.depth > 0).any())
    (torch.Size([48, 64, 3]), torch.Size([48, 64]), True)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .sequence import FrameSequence

if TYPE_CHECKING:
    from ..camera import Camera
    from ..frame import Frame

PATTERNS = ("checker", "stripes", "noise")
_PALETTE_SIZE = 4096
_GRAIN = 0.01  # metres: the fine brightness grain on every surface
_LIGHT = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
_EPS = 1e-9


@dataclass(frozen=True, eq=False)
class BoxScene:
    """Geometry and textures of a generated scene (world z up, metres).

    Attributes:
        boxes: [B, 2, 3] min and max corners of axis-aligned boxes.
        ground_half_size: the ground is the square |x|, |y| <= this at z = 0.
        patterns: [S] index into PATTERNS per surface (0 = ground, 1 + b = box b).
        colors: [S, 2, 3] the two colours of each surface's checker / stripes, in [0, 1].
        cells: [S] pattern period of each surface, metres.
        palette: [P, 3] random colours that hashed texture cells index, in [0, 1].
    """

    boxes: np.ndarray
    ground_half_size: float
    patterns: np.ndarray
    colors: np.ndarray
    cells: np.ndarray
    palette: np.ndarray


def make_scene(seed: int = 0, num_boxes: int = 5) -> BoxScene:
    """A random scene of ``num_boxes`` boxes (0.12-0.32 m wide, 0.1-0.4 m tall) within 0.45 m of
    the origin, on a 3 m x 3 m ground; the same seed gives the same scene."""
    if isinstance(num_boxes, bool) or not isinstance(num_boxes, (int, np.integer)) or num_boxes < 1:
        raise ValueError(f"num_boxes: expected a positive integer, got {num_boxes!r}")
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, num_boxes)
    radius = 0.45 * np.sqrt(rng.uniform(0, 1, num_boxes))
    centre = np.stack([radius * np.cos(angle), radius * np.sin(angle)], -1)
    half = rng.uniform(0.06, 0.16, (num_boxes, 2))
    height = rng.uniform(0.1, 0.4, num_boxes)
    boxes = np.zeros((num_boxes, 2, 3))
    boxes[:, 0, :2], boxes[:, 1, :2], boxes[:, 1, 2] = centre - half, centre + half, height
    # every pattern appears among the boxes (when there are at least 3), in a seed-dependent order
    box_patterns = np.resize(rng.permutation(len(PATTERNS)), num_boxes)
    first = rng.uniform(0.15, 0.95, (num_boxes + 1, 3))
    # the second colour roughly complements the first, so checker and stripes always show contrast
    colors = np.stack([first, np.clip(1.1 - first + rng.uniform(-0.1, 0.1, first.shape), 0.05, 0.95)], 1)
    return BoxScene(
        boxes=boxes,
        ground_half_size=1.5,
        patterns=np.concatenate([[PATTERNS.index("checker")], box_patterns]),
        colors=colors,
        cells=np.concatenate([[0.1], rng.uniform(0.03, 0.08, num_boxes)]),
        palette=rng.uniform(0.1, 1.0, (_PALETTE_SIZE, 3)),
    )


def _hash(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:  # [N] palette index
    # spatial hash of integer cells (wrapping int64 products are fine for a hash)
    with np.errstate(over="ignore"):
        return ((i * 73856093) ^ (j * 19349663) ^ (k * 83492791)) % _PALETTE_SIZE


def cast_rays(
    scene: BoxScene,
    origins: np.ndarray,  # [N, 3]
    directions: np.ndarray,  # [N, 3], any non-zero length
) -> tuple[np.ndarray, np.ndarray]:  # t [N] float64 (inf = miss), rgb [N, 3] uint8
    """First hit of each ray ``origins + t * directions`` (t > 0, in units of |direction|) and the
    colour seen there (sky colour for misses)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.shape != d.shape or o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f"origins, directions: expected equal shapes [N, 3], got {list(o.shape)} and {list(d.shape)}")
    n = len(o)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
        p = o + t_ground[:, None] * d
        on_ground = (t_ground > _EPS) & (np.abs(p[:, :2]) <= scene.ground_half_size).all(-1)
        t_ground = np.where(on_ground, t_ground, np.inf)
        # slab test: the ray is inside box b for t in [max of per-axis entries, min of per-axis exits]
        inv = 1.0 / d
        t0 = (scene.boxes[None, :, 0] - o[:, None]) * inv[:, None]  # [N, B, 3]
        t1 = (scene.boxes[None, :, 1] - o[:, None]) * inv[:, None]
        t_enter_axis = np.minimum(t0, t1)
        t_enter = t_enter_axis.max(-1)
        t_exit = np.maximum(t0, t1).min(-1)
        t_box = np.where((t_enter <= t_exit) & (t_enter > _EPS), t_enter, np.inf)
    t_all = np.concatenate([t_ground[:, None], t_box], 1)  # [N, 1 + B]
    surface = t_all.argmin(1)
    t = t_all[np.arange(n), surface]
    hit = np.isfinite(t)

    # normal of the hit face: +z on the ground; on a box, the axis the ray entered through
    box_axis = t_enter_axis.argmax(-1)[np.arange(n), np.maximum(surface - 1, 0)]
    axis = np.where(surface > 0, box_axis, 2)
    sign = np.where(surface > 0, -np.sign(d[np.arange(n), axis]), 1.0)
    normal = np.zeros((n, 3))
    normal[np.arange(n), axis] = sign

    # texture coordinates: the two world coordinates spanning the face
    p = o + np.where(hit, t, 0.0)[:, None] * d
    a = p[np.arange(n), (axis + 1) % 3]
    b = p[np.arange(n), (axis + 2) % 3]
    face = surface * 8 + axis * 2 + (sign > 0)  # distinct hash stream per face
    cell = scene.cells[surface]
    ia, ib = np.floor(a / cell).astype(np.int64), np.floor(b / cell).astype(np.int64)
    pattern = scene.patterns[surface]
    parity = np.where(pattern == PATTERNS.index("checker"), (ia + ib) & 1, np.floor((a + b) / cell).astype(np.int64) & 1)
    base = np.where(
        (pattern == PATTERNS.index("noise"))[:, None],
        scene.palette[_hash(ia, ib, face)],
        scene.colors[surface, parity],
    )
    # face ids stay below 64, so offsets of 4096 / 8192 give the grain and the tint hash streams of their own
    base = base * (0.8 + 0.2 * scene.palette[_hash(ia, ib, face + 8192), 1])[:, None]  # cells of a checker differ
    ga, gb = np.floor(a / _GRAIN).astype(np.int64), np.floor(b / _GRAIN).astype(np.int64)
    grain = 0.7 + 0.3 * scene.palette[_hash(ga, gb, face + 4096), 0]
    shade = 0.35 + 0.65 * np.clip(normal @ _LIGHT, 0.0, None)
    color = base * (grain * shade)[:, None]
    elevation = np.clip(d[:, 2] / np.linalg.norm(d, axis=1), 0.0, 1.0)[:, None]
    sky = (1 - elevation) * np.array([0.75, 0.82, 0.92]) + elevation * np.array([0.35, 0.5, 0.85])
    color = np.where(hit[:, None], color, sky)
    return t, np.clip(np.round(color * 255), 0, 255).astype(np.uint8)


def render_rgbd(scene: BoxScene, camera: Camera) -> tuple[np.ndarray, np.ndarray]:  # rgb [H, W, 3], depth [H, W]
    """Ray-cast every pixel centre of ``camera``: uint8 colour and float32 z-depth (0 = sky)."""
    K, c2w = camera.K64(), camera.c2w64()
    v, u = np.meshgrid(np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64), indexing="ij")
    # camera-frame directions with z = 1, so the ray parameter t is the z-depth
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    t, rgb = cast_rays(scene, np.broadcast_to(c2w[:3, 3], rays.shape), rays @ c2w[:3, :3].T)
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
    return rgb.reshape(camera.height, camera.width, 3), depth.reshape(camera.height, camera.width)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:  # [4, 4] camera-to-world, OpenCV axes
    """Camera-to-world pose at ``eye`` looking at ``target`` with image up along ``up``."""
    eye, target, up = (np.asarray(x, dtype=np.float64) for x in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError(f"up: {up.tolist()} is parallel to the viewing direction {forward.tolist()}")
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)  # x right, y down, z forward
    T[:3, 3] = eye
    return T


@dataclass(frozen=True, eq=False)
class _SyntheticView:
    frame_id: str
    scene: BoxScene
    camera: Camera

    def load(self) -> Frame:
        # torch loads with the first frame read, not when a capture is listed (`sequence`)
        from ..frame import Frame

        rgb, depth = render_rgbd(self.scene, self.camera)
        return Frame(rgb=rgb, camera=self.camera, depth=depth, frame_id=self.frame_id)

    def view(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        """`FrameSource.view` (a made sample holds its `Camera` already)."""
        return self.camera.K64(), self.camera.c2w64(), self.camera.width, self.camera.height


def synthetic_rgbd(num_frames: int = 24, width: int = 320, height: int = 240, seed: int = 0) -> FrameSequence:
    """RGB-D frames of `make_scene(seed)` from a camera on a 120-degree arc (radius 1.2 m, about
    0.75 m high) looking at the scene centre; rendered lazily, identical for equal arguments.

    K: fx = fy = 0.8 * width (about 64 degrees horizontal field of view), principal point at the
    image centre. Frame ids are ``000000``, ``000001``, ...

    Example:
        >>> seq = synthetic_rgbd(num_frames=2, width=32, height=24)
        >>> seq[1].camera.fx, seq.frame_ids
        (25.6, ['000000', '000001'])
    """
    for name, value, low in (("num_frames", num_frames, 1), ("width", width, 8), ("height", height, 8)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    from ..camera import Camera  # torch loads with the first sample made, not with the loaders (`sequence`)

    scene = make_scene(seed)
    K = [[0.8 * width, 0.0, (width - 1) / 2], [0.0, 0.8 * width, (height - 1) / 2], [0.0, 0.0, 1.0]]
    angles = np.linspace(-np.pi / 3, np.pi / 3, num_frames) if num_frames > 1 else np.zeros(1)
    views = []
    for i, angle in enumerate(angles):
        eye = (1.2 * np.cos(angle), 1.2 * np.sin(angle), 0.75 + 0.1 * np.sin(3 * angle))
        camera = Camera(K, look_at(eye, (0.0, 0.0, 0.1)), int(width), int(height))
        views.append(_SyntheticView(f"{i:06d}", scene, camera))
    return FrameSequence(f"synthetic(seed={seed})", views)
