"""Metric-learning losses for time-contrastive training."""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F


def npairs_loss(anchors: torch.Tensor, positives: torch.Tensor, labels: torch.Tensor,
                reg_lambda: float = 0.002) -> torch.Tensor:
    """The n-pairs loss as TensorFlow's `npairs_loss`, which the official TCN code used.

    logits = anchors @ positives^T; softmax cross-entropy against targets spread evenly over the
    positives that share the anchor's label; plus 0.25 * reg_lambda * (mean ||a||^2 + mean ||p||^2).
    Embeddings are not L2-normalised.
    """
    reg = 0.25 * reg_lambda * (anchors.pow(2).sum(1).mean() + positives.pow(2).sum(1).mean())
    logits = anchors @ positives.T
    same = (labels[:, None] == labels[None, :]).to(logits.dtype)
    targets = same / same.sum(1, keepdim=True)
    xent = -(targets * F.log_softmax(logits, dim=1)).sum(1).mean()
    return xent + reg


def multiview_npairs_loss(embeddings: torch.Tensor, reg_lambda: float = 0.002) -> torch.Tensor:
    """n-pairs over a multi-view batch [views, K, D]: row k of every view is time step k.

    Same time step in another view = positive; every other time step in any view = negative. For each
    pair of views (i < j) view i gives the anchors and view j the positives; the mean over pairs is
    returned (with two views, exactly one n-pairs loss).
    """
    views, count, _ = embeddings.shape
    if views < 2:
        raise ValueError("multi-view n-pairs needs at least two views")
    labels = torch.arange(count, device=embeddings.device)
    losses = [npairs_loss(embeddings[i], embeddings[j], labels, reg_lambda)
              for i, j in itertools.combinations(range(views), 2)]
    return torch.stack(losses).mean()
