"""OpenVLA's action tokenizer: each normalised action dimension falls into one of 256 uniform bins over
[-1, 1], and bin b (1..256, `np.digitize` convention) is the Llama token id `vocab_size - b`, i.e. the 256
least-used ids 31744..31999 of Llama-2's 32000-token vocabulary. The bins are OpenVLA's float64
`np.linspace` (torch.linspace rounds 104 of the 256 edges differently), so decoded actions are its values
exactly."""

import numpy as np
import torch
from torch import Tensor


class OpenVLAActionTokenizer:
    def __init__(self, n_bins: int = 256, vocab_size: int = 32000):
        self.n_bins = n_bins
        self.vocab_size = vocab_size
        self.bins = torch.from_numpy(np.linspace(-1.0, 1.0, n_bins))  # float64
        self.bin_centers = (self.bins[:-1] + self.bins[1:]) / 2  # n_bins - 1 centres

    @property
    def first_token_id(self) -> int:
        return self.vocab_size - self.n_bins

    def encode(self, action: Tensor) -> Tensor:
        """Normalised actions (..., D) -> token ids (..., D), long."""
        clipped = action.clamp(-1.0, 1.0).double()
        # np.digitize(x, bins) with right=False counts the edges <= x: searchsorted(..., right=True).
        bin_index = torch.searchsorted(self.bins.to(action.device), clipped.contiguous(), right=True)
        return self.vocab_size - bin_index

    def decode(self, token_ids: Tensor) -> Tensor:
        """Token ids (..., D) -> normalised actions (..., D), float64, at the bin centres; as OpenVLA, the top
        bin shares the last centre."""
        bin_index = (self.vocab_size - token_ids - 1).clamp(0, self.bin_centers.numel() - 1)
        return self.bin_centers.to(token_ids.device)[bin_index]

    def action_ids_to_slots(self, token_ids: Tensor) -> Tensor:
        """Token ids -> positions 0..n_bins-1 within the action-token slice of the vocabulary."""
        return token_ids - self.first_token_id

    def slots_to_action_ids(self, slots: Tensor) -> Tensor:
        return slots + self.first_token_id
