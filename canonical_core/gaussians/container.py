"""The Gaussian container that the decoder produces and the renderer and exporters consume."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
    """Colour in [0, 1] -> degree-0 SH coefficient (the 3DGS convention: colour = 0.5 + C0 * dc)."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
    return dc * SH_C0 + 0.5


def sh_degree_from_bases(num_bases: int) -> int:
    degree = int(round(num_bases**0.5)) - 1
    if (degree + 1) ** 2 != num_bases or not 0 <= degree <= 3:
        raise ValueError(f"sh: expected 1, 4, 9 or 16 SH bases per channel, got {num_bases}")
    return degree


GEOMETRY = ("means", "scales", "quats", "opacities")  # the fields that say where and how opaque a Gaussian is
ALL_FIELDS = (*GEOMETRY, "sh", "features", "labels")


def check_finite(gaussians: "Gaussians", fields: tuple[str, ...] = ALL_FIELDS) -> None:
    """ValueError naming the first of ``fields`` that holds NaN or inf: a render would drop such a
    Gaussian (or draw NaN), and one NaN in a colour solve's system spreads to every Gaussian it fits.
    A float64 sum of float32 or float16 values is finite exactly when every value is (it cannot
    overflow), and costs a fraction of an elementwise test (float64 fields get the elementwise one). A
    field found finite is not tested again while it holds the same tensor object, unchanged by torch's
    in-place operations (its version counter), so the renders of one decode pay once; writes through a
    numpy view of it (``.numpy()``) are not seen.

    Example:
        >>> g = Gaussians.empty(); g.means = torch.tensor([[0.0, float("nan"), 1.0]]); check_finite(g, ("means",))
        Traceback (most recent call last):
        ValueError: means: NaN or inf among its values
    """
    checked = gaussians.__dict__.setdefault("_finite", {})  # field -> (weak reference, version) found finite
    for name in fields:
        t = getattr(gaussians, name)
        if t is None or not t.numel():
            continue
        ref, version = checked.get(name, (None, None))
        if ref is not None and ref() is t and version == t._version:  # the same object (an id may be reused)
            continue
        values = t.detach()  # a trained model's parameters: the check takes no part in their gradients
        finite = bool(torch.isfinite(values).all()) if t.dtype == torch.float64 else \
            math.isfinite(float(values.sum(dtype=torch.float64)))
        if not finite:
            raise ValueError(f"{name}: NaN or inf among its values")
        checked[name] = (weakref.ref(t), t._version)


@dataclass(eq=False)
class Gaussians:
    """A set of 3D Gaussians (the 3DGS parametrisation, activated values).

    Attributes:
        means: [N, 3] centres, world coordinates.
        scales: [N, 3] standard deviations along the principal axes (linear, not log).
        quats: [N, 4] rotations, (w, x, y, z): unit, or within float16's rounding of unit as a scene's
            decode keeps them (norms 1 +- 1e-3); the renderer and the exports normalise them.
        opacities: [N] in [0, 1].
        sh: [N, K, 3] spherical-harmonics colour coefficients, K = (degree + 1)^2, DC first.
        features: optional [N, L] fused features (the "feature splat" channels).
        labels: optional [N, S] fused label scores.
    """

    means: Tensor  # [N, 3]
    scales: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    opacities: Tensor  # [N]
    sh: Tensor  # [N, K, 3]
    features: Tensor | None = None  # [N, L]
    labels: Tensor | None = None  # [N, S]

    def __post_init__(self):
        n = self.means.shape[0] if isinstance(self.means, Tensor) and self.means.ndim == 2 else -1
        expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,)}
        for name, shape in expected.items():
            t = getattr(self, name)
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                got = list(t.shape) if isinstance(t, Tensor) else type(t).__name__
                want = ["N" if s == -1 else s for s in shape] if n == -1 else list(shape)
                raise ValueError(f"{name}: expected shape [{', '.join(map(str, want))}], got {got}")
        for name in ("means", "scales", "quats", "opacities", "sh", "features", "labels"):
            t = getattr(self, name)
            if isinstance(t, Tensor) and not t.is_floating_point():  # the backends would disagree on what it means
                raise ValueError(f"{name}: expected a floating-point tensor, got dtype {t.dtype}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh: expected shape [{n}, K, 3], got {list(self.sh.shape)}")
        sh_degree_from_bases(self.sh.shape[1])
        for name in ("features", "labels"):
            t = getattr(self, name)
            if t is not None and (t.ndim != 2 or t.shape[0] != n):
                raise ValueError(f"{name}: expected shape [{n}, C], got {list(t.shape)}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def colours(self) -> Tensor:  # [N, 3]
        """View-independent colour (the DC term), clamped to [0, 1]."""
        return sh_dc_to_rgb(self.sh[:, 0]).clamp(0.0, 1.0)

    @classmethod
    def empty(cls, sh_degree: int = 0, feature_dim: int | None = None, label_dim: int | None = None) -> "Gaussians":
        k = (sh_degree + 1) ** 2
        return cls(
            means=torch.zeros(0, 3),
            scales=torch.zeros(0, 3),
            quats=torch.zeros(0, 4),
            opacities=torch.zeros(0),
            sh=torch.zeros(0, k, 3),
            features=None if feature_dim is None else torch.zeros(0, feature_dim),
            labels=None if label_dim is None else torch.zeros(0, label_dim),
        )

    def map(self, fn) -> "Gaussians":
        """Apply ``fn`` to every tensor field (optional fields that are None stay None)."""
        return replace(self, **{f.name: (None if getattr(self, f.name) is None else fn(getattr(self, f.name))) for f in fields(self)})

    def index(self, idx: Tensor) -> "Gaussians":
        """A subset (boolean mask or integer indices)."""
        return self.map(lambda t: t[idx])

    def to(self, *args, **kwargs) -> "Gaussians":
        return self.map(lambda t: t.to(*args, **kwargs))

    def detach(self) -> "Gaussians":
        return self.map(Tensor.detach)

    def __repr__(self) -> str:
        extra = "".join(
            f", {name}={getattr(self, name).shape[1]}" for name in ("features", "labels") if getattr(self, name) is not None
        )
        return f"Gaussians(n={len(self)}, sh_degree={self.sh_degree}{extra})"
