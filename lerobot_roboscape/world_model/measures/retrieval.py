"""Retrieval: does each rollout lie nearest its own real future among K?"""

import numpy as np


def retrieval_accuracy(similarity_KK: np.ndarray) -> float:
    """similarity[i, j]: rollout i against real future j. The share of rollouts whose most similar future is their
    own; a tie among the most similar counts as 1 / (tied futures) when their own is among them."""
    hits = []
    for i, row in enumerate(similarity_KK):
        best = np.isclose(row, row.max(), rtol=0, atol=1e-6)
        hits.append(best[i] / best.sum())
    return float(np.mean(hits))
