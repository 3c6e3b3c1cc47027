"""InfoNCE on L2-normalised global descriptors (paper, Sec. "Network Training", Eq. InfoNCE; tau = 0.1)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["info_nce", "info_nce_in_batch"]


def info_nce(query: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor,
             tau: float = 0.1) -> torch.Tensor:
    """Mean over queries of -log( exp(q.p/tau) / (exp(q.p/tau) + sum_j exp(q.n_j/tau)) ).

    Args:
        query: (B, D), positive: (B, D), negatives: (B, N, D); all L2-normalised (inner product = cosine).
    """
    pos = (query * positive).sum(dim=-1, keepdim=True)  # (B, 1)
    neg = torch.einsum("bd,bnd->bn", query, negatives)  # (B, N)
    logits = torch.cat([pos, neg], dim=1) / tau
    return F.cross_entropy(logits, torch.zeros(len(query), dtype=torch.long, device=query.device))


def info_nce_in_batch(anchors: torch.Tensor, positives: torch.Tensor, tau: float = 0.1,
                      symmetric: bool = True) -> torch.Tensor:
    """InfoNCE where each anchor's negatives are all *other* images of the batch (2B - 2 of them).

    The sampler guarantees those images lie outside the negative radius. With ``symmetric`` each positive
    also serves as an anchor (its pair as positive), doubling the signal per forward pass.

    Args:
        anchors, positives: (B, D) L2-normalised descriptors; row i of each forms a positive pair.
    """
    b = anchors.shape[0]
    allv = torch.cat([anchors, positives], dim=0)  # (2B, D)
    sim = allv @ allv.T / tau  # (2B, 2B)
    self_mask = torch.eye(2 * b, dtype=torch.bool, device=sim.device)
    sim = sim.masked_fill(self_mask, float("-inf"))
    target = torch.cat([torch.arange(b, 2 * b), torch.arange(0, b)]).to(sim.device)
    n = 2 * b if symmetric else b
    return F.cross_entropy(sim[:n], target[:n])
