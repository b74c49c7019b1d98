"""The training loop: the decoder's heads, trained through a differentiable renderer.

Each step takes one fused sample of the pool (`data.draw_pool`: N sampled input views of a
training capture, folded once) and one of its target frames, decodes the sample with the decoder
(`data.decode`, gradients to every head), renders a random window of the target (`draw_crop`,
`crop_camera`) with the PyTorch reference renderer (gsplat's fused one on CUDA, where installed)
in the evaluation's "normalised" colour, and
takes an Adam step on `losses.render_loss` over the window.
The fold does not depend on the decoder, which is why the pool can be folded up front.

What trains (`decode.checkpoint.TRAINED_HEADS`, or the subset `TrainSettings.heads` names): the opacity
head on support and the free-space penalty (monotone by construction: their weights are clamped
non-negative in the forward pass, so no step can break the monotonicity), and the heads on F_scene
(mean offset, log-scale delta, colour delta). `TrainSettings.coverage_weight` adds a term that
makes leaving a measured surface uncovered cost something (`losses.coverage_loss`).
The appearance uncertainty U_app is not trained: it acts inside the numba fold, so no gradient
reaches it through a pool folded once.

Deterministic with a seed: the pool, the order of the steps and the initial parameters follow from
it, and the reference renderer is deterministic on the CPU. ``minutes`` stops early on the clock,
which makes the number of steps (recorded in the checkpoint) depend on the machine.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tqdm import tqdm

from ..camera import Camera
from ..decode import GaussianDecoder
from ..frame import Frame
from ..eval.methods import SplatModel
from ..eval.report import check_writable
from ..eval.run import score
from ..rendering import render
from ..rendering.gsplat_backend import gsplat_available
from ..rendering.splat_geometry import TILE_SIZE
from ..scene import Scene
from ..decode.checkpoint import TRAINED_HEADS, save_checkpoint
from .data import Capture, FusedSample, decode, draw_pool, load_captures, scene_config
from .losses import SSIM_WEIGHT, coverage_loss, render_loss

Device = Literal["cpu", "cuda"]


@dataclass(frozen=True)
class TrainSettings:
    """What a training run does; recorded in its checkpoint."""

    seed: int = 0
    steps: int = 400
    """Optimisation steps (one sampled scene and one target frame each)."""
    minutes: float | None = None
    """Stop after this much wall time even if ``steps`` are not done."""
    width: int = 160
    """Training images are resized to about this many pixels across."""
    views: tuple[int, ...] = (2, 4, 8, 16)
    """N, input views per sample, drawn uniformly from these."""
    pool: int = 48
    """Fused samples drawn up front (each folded once), round-robin over the captures."""
    crop: int = 64
    """Each step renders a random window of this many pixels square of its target (the loss is
    over the window), a few tiles instead of the whole image."""
    lr: float = 1e-2
    """Adam's learning rate."""
    ssim_weight: float = SSIM_WEIGHT
    coverage_weight: float = 0.0
    """Weight of `losses.coverage_loss` next to the render loss: the mean (1 - alpha)^2 over the
    window's pixels where the target frame measured depth. The normalised colour that the loss and
    the evaluation compare is blind to how much of the image a scene covers, so without it a head
    can gain covered PSNR by drawing fewer pixels."""
    heads: tuple[str, ...] = TRAINED_HEADS
    """The heads that train (`decode.checkpoint.TRAINED_HEADS` names); the others keep their
    analytic start, and the checkpoint holds only these."""
    device: Device = "cpu"

    def __post_init__(self):
        for name, low in (("seed", 0), ("steps", 0), ("width", 32), ("pool", 1), ("crop", 16)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        if self.minutes is not None and not (isinstance(self.minutes, (int, float)) and self.minutes > 0):
            raise ValueError(f"minutes: expected a positive number, got {self.minutes!r}")
        if not self.views or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 64 for v in self.views):
            raise ValueError(f"views: expected input view counts in 1..64, got {self.views!r}")
        if not (isinstance(self.lr, float) and self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"lr: expected a positive float, got {self.lr!r}")
        for name in ("ssim_weight", "coverage_weight"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{name}: expected a non-negative number, got {value!r}")
        if not self.heads or len(set(self.heads)) != len(self.heads) or any(h not in TRAINED_HEADS for h in self.heads):
            raise ValueError(f"heads: expected distinct names from {list(TRAINED_HEADS)}, got {list(self.heads)!r}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device: expected 'cpu' or 'cuda', got {self.device!r}")
        if self.device == "cuda" and not torch.cuda.is_available():
            raise ValueError("device: 'cuda' requested, but torch sees no CUDA device")


@dataclass
class TrainResult:
    """A finished run: its decoder, per-step losses and the held-out report."""

    decoder: GaussianDecoder
    losses: list[float]
    steps: int
    seconds: float
    heldout: list[dict] = field(default_factory=list)  # per capture: PSNR before / after


def new_decoder(feature_dim: int = 16) -> GaussianDecoder:
    """The training-free decoder a new scene starts with (`SceneConfig` defaults)."""
    config = scene_config(1.0)
    return GaussianDecoder(feature_dim, opacity_slope=config.decoder.opacity_slope, opacity_bias=config.opacity_bias)


def _to(sample: FusedSample, device: torch.device) -> FusedSample:
    if device.type == "cpu":
        return sample
    move = lambda t: t.to(device) if isinstance(t, torch.Tensor) else t  # noqa: E731
    return FusedSample(sample.capture, {k: move(v) for k, v in sample.fields.items()}, move(sample.support),
                       move(sample.free), sample.unit, sample.voxel_size, sample.targets)


def crop_camera(camera: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The camera whose image is the ``width`` x ``height`` window at (x0, y0) of ``camera``'s: same
    pose, principal point shifted. Rendering it gives those pixels of the full render (each pixel's
    blend depends on its own ray alone) at the cost of the window's tiles only: exactly for splats
    centred in the window; a splat centred well outside it has its projection's Jacobian clamped
    to the window's field of view instead of the image's (3DGS's clamp), which changes its tail."""
    K = camera.K64().copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return Camera(K, camera.c2w64(), width, height)


def step_loss(decoder: GaussianDecoder, sample: FusedSample, target: int, ssim_weight: float = SSIM_WEIGHT,
              crop: tuple[int, int, int, int] | None = None, coverage_weight: float = 0.0) -> torch.Tensor:
    """The render loss of ``decoder`` on ``sample`` at its target frame number ``target``, over the
    whole image or the window ``crop`` = (x0, y0, width, height), plus ``coverage_weight`` x
    `losses.coverage_loss` where the target has depth."""
    frame = sample.targets[target]
    x0, y0, w, h = crop if crop is not None else (0, 0, frame.width, frame.height)
    gaussians = decode(decoder, sample)
    device = sample.support.device
    # Both differentiable backends: gsplat's fused CUDA kernels where they run, else the PyTorch reference.
    backend = "gsplat" if device.type == "cuda" and gsplat_available() else "reference"
    view = render(gaussians, crop_camera(frame.camera, x0, y0, w, h), outputs=("rgb", "alpha"), colour="normalised",
                  backend=backend)
    truth = frame.rgb[y0: y0 + h, x0: x0 + w].to(device).float() / 255.0
    loss = render_loss(view.rgb, truth, ssim_weight)
    if coverage_weight and frame.depth is not None:
        loss = loss + coverage_weight * coverage_loss(view.alpha, frame.depth[y0: y0 + h, x0: x0 + w].to(device) > 0)
    return loss


def draw_crop(frame: Frame, size: int, rng: np.random.Generator) -> tuple[int, int, int, int]:
    """A random ``size`` x ``size`` window of ``frame`` (the whole image where it is smaller), on the
    renderer's tile grid so that it costs (size / 16)^2 tiles."""
    w, h = min(size, frame.width), min(size, frame.height)
    x0 = int(rng.integers(0, (frame.width - w) // TILE_SIZE + 1)) * TILE_SIZE
    y0 = int(rng.integers(0, (frame.height - h) // TILE_SIZE + 1)) * TILE_SIZE
    return x0, y0, w, h


def heldout_report(decoder: GaussianDecoder, captures: Sequence[Capture]) -> list[dict]:
    """Per capture: PSNR (all pixels and covered) at its protocol held-out frames of a scene fused
    from its protocol inputs (`data.REPORT_VIEWS` views), decoded with ``decoder``."""
    rows = []
    for capture in captures:
        scene = Scene(scene_config(capture.voxel_size))
        for p in capture.report_inputs:
            scene.fold(capture.frames[p])
        scene.decoder.load_state_dict({k: v.detach().cpu() for k, v in decoder.state_dict().items()})
        metrics = score(SplatModel(scene.decode()), [capture.frames[p] for p in capture.heldout], capture.voxel_size).metrics
        rows.append({"capture": capture.name, "views": len(capture.report_inputs), "psnr": metrics["psnr"],
                     "psnr_covered": metrics["psnr_covered"], "coverage": metrics["coverage"]})
    return rows


def train(captures: Sequence[Capture], settings: TrainSettings = TrainSettings(), progress: bool = False,
          report: bool = True) -> TrainResult:
    """Train the decoder's heads on ``captures`` (module docstring); with ``report``, the held-out
    PSNR before and after."""
    t0 = time.perf_counter()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    device = torch.device(settings.device)
    decoder = new_decoder().to(device)
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    if report:
        say(f"train: held-out PSNR before training, {len(captures)} captures")
        before = heldout_report(decoder, captures)
    else:
        before = []
    say(f"train: folding the {settings.pool} training samples")
    pool = [_to(s, device) for s in draw_pool(captures, settings.pool, settings.seed, settings.views)]
    for name, p in decoder.named_parameters():  # the heads not trained keep their analytic start
        p.requires_grad_(name.split(".")[0] in settings.heads)
    optimiser = torch.optim.Adam([p for p in decoder.parameters() if p.requires_grad], lr=settings.lr)
    losses: list[float] = []
    bar = tqdm(total=settings.steps, disable=not progress, file=sys.stderr, desc="train", unit="step", dynamic_ncols=True)
    deadline = None if settings.minutes is None else t0 + 60.0 * settings.minutes
    for _ in range(settings.steps):
        if deadline is not None and time.perf_counter() > deadline:
            break
        sample = pool[int(rng.integers(len(pool)))]
        target = int(rng.integers(len(sample.targets)))
        crop = draw_crop(sample.targets[target], settings.crop, rng)
        optimiser.zero_grad()
        loss = step_loss(decoder, sample, target, settings.ssim_weight, crop, settings.coverage_weight)
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
        bar.set_postfix_str(f"loss {np.mean(losses[-20:]):.4f}")
        bar.update()
    bar.close()
    decoder = decoder.cpu().requires_grad_(True)
    if report:
        say("train: held-out PSNR after training")
    after = heldout_report(decoder, captures) if report else []
    heldout = [{"capture": b["capture"], "views": b["views"], "before": b, "after": a} for b, a in zip(before, after)]
    return TrainResult(decoder, losses, len(losses), time.perf_counter() - t0, heldout)


def write_report(result: TrainResult, settings: TrainSettings, captures: Sequence[str], folder: Path) -> None:
    """``folder``/loss.png (per-step loss and its running mean), report.json and report.md."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    steps = np.arange(1, len(result.losses) + 1)
    ax.plot(steps, result.losses, lw=0.5, alpha=0.4, label="step")
    if result.losses:
        k = max(1, min(25, len(result.losses) // 10))
        smooth = np.convolve(result.losses, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, lw=1.5, label=f"mean of {k}")
    ax.set_xlabel("step")
    coverage = f" + {settings.coverage_weight:g} coverage" if settings.coverage_weight else ""
    ax.set_ylabel(f"MSE + {settings.ssim_weight:g} (1 - SSIM){coverage}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(folder / "loss.png", dpi=120)
    plt.close(fig)
    doc = {"captures": list(captures), "settings": _settings_dict(settings), "steps": result.steps,
           "seconds": result.seconds, "losses": result.losses, "heldout": result.heldout}
    (folder / "report.json").write_text(json.dumps(doc, indent=1))
    lines = ["| capture | N | PSNR before | PSNR after | covered before | covered after |", "|---|---|---|---|---|---|"]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    for row in result.heldout:
        b, a = row["before"], row["after"]
        lines.append(f"| {row['capture']} | {row['views']} | {fmt(b['psnr'])} | {fmt(a['psnr'])} | "
                     f"{fmt(b['psnr_covered'])} | {fmt(a['psnr_covered'])} |")
    (folder / "report.md").write_text(f"# Training report\n\n{result.steps} steps in {result.seconds / 60:.1f} min; "
                                      f"held-out PSNR (dB) of the training captures' own held-out frames:\n\n"
                                      + "\n".join(lines) + "\n")


def _settings_dict(settings: TrainSettings) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(settings).items()}


def _check_writable(out: Path) -> None:
    """ValueError naming ``out`` unless its folder can be made and written (`report.check_writable`)
    and ``out`` is no folder, before the captures are loaded and trained on (minutes that a late
    failure to save would waste)."""
    check_writable(out.parent, "out")
    if out.is_dir():
        raise ValueError(f"out: {out} is a folder; expected a .safetensors file to write")


def run_training(capture_paths: Sequence[str | Path], out: str | Path, settings: TrainSettings = TrainSettings(),
                 progress: bool = True, K=None, depth_scale: float | None = None) -> TrainResult:
    """``canonical train``: load the captures (with ``K`` and ``depth_scale``, `data.load_captures`),
    train, write the checkpoint at ``out`` and the report folder next to it (``<out stem>_report/``)."""
    out = Path(out)
    if out.suffix != ".safetensors":
        raise ValueError(f"out: expected a path ending in .safetensors, got {str(out)!r}")
    _check_writable(out)
    captures = load_captures(capture_paths, settings.width, K=K, depth_scale=depth_scale)
    result = train(captures, settings, progress=progress)
    names = [c.name for c in captures]
    save_checkpoint(out, result.decoder, {**_settings_dict(settings), "captures": names, "steps_done": result.steps},
                    heads=settings.heads)
    write_report(result, settings, names, out.with_name(out.stem + "_report"))
    return result
