"""The BC loss terms of method.md section 3, one function each, batched over the first dimension.

Every function returns the batch mean as a scalar tensor; the weights live in `BCRLConfig`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def l1_loss(pred: Tensor, target: Tensor) -> Tensor:
    return F.l1_loss(pred, target)


def l2_loss(pred: Tensor, target: Tensor) -> Tensor:
    return F.mse_loss(pred, target)


def cosine_distance(pred: Tensor, target: Tensor, eps: float = 1e-8) -> Tensor:
    """1 - cos(angle) between the vectors of the last dimension: 0 aligned, 1 orthogonal, 2 opposite."""
    return (1.0 - F.cosine_similarity(pred, target, dim=-1, eps=eps)).mean()


def gripper_cross_entropy(gripper_logits: Tensor, gripper_class: Tensor, class_weights: Tensor) -> Tensor:
    """Class-weighted cross entropy (weighted mean, as torch defines it): sum w_y * nll / sum w_y."""
    return F.cross_entropy(gripper_logits, gripper_class, weight=class_weights)


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """MSE over the rows where `mask` is True (all rows if None); 0 when no row is valid."""
    squared_error = (pred - target).pow(2).mean(dim=-1)
    if mask is None:
        return squared_error.mean()
    mask = mask.reshape(squared_error.shape).to(squared_error.dtype)
    return (squared_error * mask).sum() / mask.sum().clamp_min(1.0)


def balanced_class_weights(closed_fraction: float, min_fraction: float = 0.01) -> Tensor:
    """[w_open, w_closed] with w_c = 0.5 / fraction_c, so both classes weigh the same in total."""
    closed = min(max(float(closed_fraction), min_fraction), 1.0 - min_fraction)
    return torch.tensor([0.5 / (1.0 - closed), 0.5 / closed], dtype=torch.float32)
