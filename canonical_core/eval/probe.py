"""A linear probe: a multinomial logistic regression on standardised features, fitted by full-batch
L-BFGS in float64 (the same inputs give the same probe). The segmentation experiment trains one on
feature splats to read labels off them (`eval.segmentation`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

PROBE_STEPS = 200  # L-BFGS iterations
PROBE_WEIGHT_DECAY = 1e-4  # L2 on the weights, per training pixel


@dataclass(frozen=True)
class LinearProbe:
    """A multinomial logistic regression on standardised features."""

    mean: Tensor  # [C]
    std: Tensor  # [C]
    weight: Tensor  # [C, S]
    bias: Tensor  # [S]

    def predict(self, features: Tensor) -> Tensor:  # [M, C] -> [M] int64 class index
        x = (features.double() - self.mean) / self.std
        return (x @ self.weight + self.bias).argmax(-1)


def fit_probe(
    features: Tensor,  # [M, C] float
    labels: Tensor,  # [M] int64 class index in [0, classes)
    classes: int,
    steps: int = PROBE_STEPS,
    weight_decay: float = PROBE_WEIGHT_DECAY,
) -> LinearProbe:
    """Fit a `LinearProbe` by full-batch L-BFGS on the mean cross-entropy plus ``weight_decay`` x
    the squared weights, from zero, in float64: the same inputs give the same probe."""
    if features.ndim != 2 or len(features) == 0:
        raise ValueError(f"features: expected shape [M, C] with M > 0, got {list(features.shape)}")
    if labels.shape != (len(features),):
        raise ValueError(f"labels: expected shape [{len(features)}], got {list(labels.shape)}")
    if isinstance(classes, bool) or not isinstance(classes, int) or classes < 1:
        raise ValueError(f"classes: expected a positive integer, got {classes!r}")
    if int(labels.min()) < 0 or int(labels.max()) >= classes:
        raise ValueError(f"labels: class indices must lie in [0, {classes})")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected a positive integer, got {steps!r}")
    x = features.double()
    mean, std = x.mean(0), x.std(0, unbiased=False).clamp_min(1e-6)
    x = (x - mean) / std
    y = labels.long()
    weight = torch.zeros(x.shape[1], classes, dtype=torch.float64, requires_grad=True)
    bias = torch.zeros(classes, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.LBFGS([weight, bias], max_iter=steps, tolerance_grad=1e-9, tolerance_change=1e-12,
                                  line_search_fn="strong_wolfe")

    def loss() -> Tensor:
        optimiser.zero_grad()
        value = torch.nn.functional.cross_entropy(x @ weight + bias, y) + weight_decay * (weight ** 2).sum()
        value.backward()
        return value

    optimiser.step(loss)
    return LinearProbe(mean, std, weight.detach(), bias.detach())
