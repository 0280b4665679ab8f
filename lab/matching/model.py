"""The Siamese descriptor matcher network (paper §3.3), in one readable torch file.

Paper: a shared-weight branch applies a Conv1d over each 128-D descriptor, max-pools it to 64 and
applies dropout; the two branch outputs are concatenated (128) and classified with a sigmoid.

Our deviations (documented in MODEL_CARD.md):

* The head sees symmetric pair features ``[|e_a - e_b|, e_a * e_b]`` (still 128 = 2 x 64) instead of
  the plain concatenation ``[e_a, e_b]``. A linear layer on a concatenation is separable,
  ``w1.e_a + w2.e_b``, so it cannot measure how *similar* two descriptors are; the symmetric features
  can, and they make the score symmetric: ``s(a, b) == s(b, a)``.
* The head is a small MLP (one hidden layer) instead of a single linear layer.
* The head also gets the raw descriptor cosine ``a . b``, so it starts from what nearest-neighbour
  matching already knows and only has to learn corrections.

Inference contract (ONNX, dynamic sizes): ``desc_a`` [Na, 128] and ``desc_b`` [Nb, 128] float32,
``idx_a`` and ``idx_b`` [M] int64 index the candidate pairs, output ``scores`` [M] in [0, 1]. Each
descriptor goes through the branch once, however many candidate pairs it is part of.
"""

from __future__ import annotations

import torch
from torch import nn


class SiameseMatcherNet(nn.Module):
    """Shared Conv1d branch (128 -> 64 per descriptor) and an MLP similarity head with a sigmoid."""

    def __init__(self, descriptor_dim: int = 128, channels: int = 8, kernel_size: int = 5, hidden: int = 64,
                 dropout: float = 0.1) -> None:
        super().__init__()
        if descriptor_dim % 2:
            raise ValueError("descriptor_dim must be even (the branch max-pools it by 2)")
        self.descriptor_dim = descriptor_dim
        self.embedding_dim = descriptor_dim // 2
        self.branch = nn.Sequential(
            nn.Conv1d(1, channels, kernel_size, padding=kernel_size // 2),  # local patterns along the descriptor
            nn.ReLU(),
            nn.MaxPool1d(2),  # 128 -> 64
            nn.Conv1d(channels, 1, 1),  # back to one value per position: a 64-D embedding
            nn.Flatten(1),
            nn.Dropout(dropout),
        )
        self.head = nn.Sequential(
            nn.Linear(2 * self.embedding_dim + 1, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 1),
        )

    def embed(self, descriptors: torch.Tensor) -> torch.Tensor:
        """Branch output (N, 64) for descriptors (N, 128)."""
        return self.branch(descriptors.unsqueeze(1))

    def pair_logits(self, emb_a: torch.Tensor, emb_b: torch.Tensor, cosine: torch.Tensor) -> torch.Tensor:
        """Logits (M,) of aligned embedding pairs (M, 64) with their raw descriptor cosine (M,)."""
        features = torch.cat([(emb_a - emb_b).abs(), emb_a * emb_b, cosine.unsqueeze(1)], dim=1)
        return self.head(features).squeeze(1)

    def logits(self, desc_a: torch.Tensor, desc_b: torch.Tensor) -> torch.Tensor:
        """Logits (M,) of aligned descriptor pairs (M, 128): the training path."""
        return self.pair_logits(self.embed(desc_a), self.embed(desc_b), (desc_a * desc_b).sum(1))

    def forward(self, desc_a: torch.Tensor, desc_b: torch.Tensor, idx_a: torch.Tensor,
                idx_b: torch.Tensor) -> torch.Tensor:
        """Similarity scores in [0, 1] of the candidate pairs ``(desc_a[idx_a], desc_b[idx_b])``: the ONNX graph."""
        emb_a = self.embed(desc_a).index_select(0, idx_a)
        emb_b = self.embed(desc_b).index_select(0, idx_b)
        cosine = (desc_a.index_select(0, idx_a) * desc_b.index_select(0, idx_b)).sum(1)
        return torch.sigmoid(self.pair_logits(emb_a, emb_b, cosine))
