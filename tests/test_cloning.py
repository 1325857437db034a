"""cloning.py: hindsight cloning's loss against torch.distributions."""
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

import cloning as C
import configs
import policy as P

torch.set_num_threads(1)


def test_bc_loss_is_tanh_gaussian_nll_of_dataset_actions():
    """bc_loss = -log pi(a_t | s_t, g) of the recorded a_t = action[:, t + 1], checked against torch.distributions."""
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    actor = P.Actor(cfg, 6, 6, 3)
    B, T = 5, 2  # T = 2: only t = 0, whose goal is frame 1 and action action[:, 1]
    feat, goal, action = torch.randn(B, T, 6), torch.randn(B, T, 6), torch.rand(B, T, 3) * 1.6 - 0.8
    loss, _ = C.bc_loss(actor, feat, goal, action)
    mean, std = actor.distribution(feat[:, 0], goal[:, 1])
    dist = TransformedDistribution(Normal(mean, std), [TanhTransform()])
    assert loss.item() == pytest.approx(-dist.log_prob(action[:, 1]).sum(-1).mean().item(), rel=1e-4)
    # T = 3: both t = 0 and t = 1 count; t = 1's goal can only be frame 2, t = 0's is frame 1 or 2 at random
    feat, goal, action = torch.randn(B, 3, 6), torch.randn(B, 3, 6), torch.rand(B, 3, 3) * 1.6 - 0.8
    torch.manual_seed(1)
    loss, _ = C.bc_loss(actor, feat, goal, action)
    torch.manual_seed(1)
    later0 = 1 + (torch.rand(B, 2)[:, 0] * 2).long()  # the draw bc_loss makes
    rows = torch.arange(B)
    logp = lambda t, later: TransformedDistribution(Normal(*actor.distribution(feat[:, t], goal[rows, later])), [TanhTransform()]).log_prob(action[:, t + 1]).sum(-1)
    expected = -(logp(0, later0).sum() + logp(1, torch.full((B,), 2)).sum()) / (2 * B)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-4)

    # final_share = 1: every step's goal is the episode's last-frame goal
    final_goal = torch.randn(B, 6)
    loss, _ = C.bc_loss(actor, feat, goal, action, final_goal, final_share=1.0)
    logp_final = lambda t: TransformedDistribution(Normal(*actor.distribution(feat[:, t], final_goal)), [TanhTransform()]).log_prob(action[:, t + 1]).sum(-1)
    assert loss.item() == pytest.approx(-(logp_final(0).sum() + logp_final(1).sum()).item() / (2 * B), rel=1e-4)

