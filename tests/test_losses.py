import math

import torch

from mftcn_bench.encoders.losses import multiview_npairs_loss, npairs_loss


def test_npairs_matches_hand_computed_value():
    anchors = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    positives = torch.tensor([[1.0, 0.0], [1.0, 1.0]])
    labels = torch.tensor([0, 1])
    # logits = a @ p^T = [[1, 1], [0, 1]]
    # row 0: target class 0: -log(e^1 / (e^1 + e^1)) = log 2
    # row 1: target class 1: -log(e^1 / (e^0 + e^1)) = log(1 + e^-1)
    xent = (math.log(2) + math.log(1 + math.exp(-1))) / 2
    # reg: 0.25 * 0.002 * (mean ||a||^2 = 1 + mean ||p||^2 = (1 + 2) / 2)
    reg = 0.25 * 0.002 * (1.0 + 1.5)
    assert abs(npairs_loss(anchors, positives, labels).item() - (xent + reg)) < 1e-6


def test_npairs_spreads_target_over_equal_labels():
    anchors = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    positives = torch.tensor([[0.5, 0.0], [0.0, 1.0], [2.0, 0.0]])
    labels = torch.tensor([0, 1, 0])
    logits = anchors @ positives.T
    same = (labels[:, None] == labels[None, :]).float()
    target = same / same.sum(1, keepdim=True)
    expected = -(target * torch.log_softmax(logits, 1)).sum(1).mean()
    expected += 0.25 * 0.1 * ((anchors**2).sum(1).mean() + (positives**2).sum(1).mean())
    assert torch.allclose(npairs_loss(anchors, positives, labels, reg_lambda=0.1), expected)


def test_multiview_loss_two_views_is_one_npairs():
    torch.manual_seed(0)
    emb = torch.randn(2, 5, 3)
    expected = npairs_loss(emb[0], emb[1], torch.arange(5))
    assert torch.allclose(multiview_npairs_loss(emb), expected)


def test_multiview_loss_averages_view_pairs():
    torch.manual_seed(1)
    emb = torch.randn(3, 4, 2)
    labels = torch.arange(4)
    pairs = [npairs_loss(emb[i], emb[j], labels) for i, j in ((0, 1), (0, 2), (1, 2))]
    assert torch.allclose(multiview_npairs_loss(emb), torch.stack(pairs).mean())


def test_loss_is_low_when_views_agree_and_time_steps_differ():
    good = torch.eye(4).repeat(2, 1, 1) * 10
    bad = torch.ones(2, 4, 4)
    assert multiview_npairs_loss(good, reg_lambda=0) < 1e-3 < multiview_npairs_loss(bad, reg_lambda=0)
