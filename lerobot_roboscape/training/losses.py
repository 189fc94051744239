"""Losses shared by the models of several stages."""

import torch
import torch.nn.functional as F


def balanced_bce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy with each class averaged on its own, then the two averaged: a rare positive class
    weighs as much as the common negative one (a class absent from the batch drops out). Written with weights, not
    boolean indexing, so that it never waits on the device (no data-dependent shapes)."""
    per_item = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    positive = (labels > 0.5).to(per_item.dtype)
    means, present = [], []
    for weight in (positive, 1 - positive):
        count = weight.sum()
        means.append((per_item * weight).sum() / count.clamp(min=1))
        present.append((count > 0).to(per_item.dtype))
    return (means[0] * present[0] + means[1] * present[1]) / (present[0] + present[1]).clamp(min=1)
