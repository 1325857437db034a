"""cloning.py: hindsight cloning's loss against torch.distributions, and advantage weights that favour actions bringing
the goal nearer."""
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

import cloning as C
import policy as P
import presets

torch.set_num_threads(1)


def test_bc_loss_is_tanh_gaussian_nll_of_dataset_actions():
    """bc_loss = -log pi(a_t | s_t, g) of the recorded a_t = action[:, t + 1], checked against torch.distributions."""
    torch.manual_seed(0)
    cfg = P.ActorCriticConfig(**presets.PRESETS["ac"]["smoke"])
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


def test_advantage_weights_favour_actions_that_bring_the_goal_nearer():
    """--ac-bc-awr: with V = 0 the advantage is -d(s_{t+1}, g), so of two actions from the same state the one whose next
    state is nearer the goal gets the larger weight; weights have mean 1, large ones are clipped at AWR_MAX (before the
    mean is taken), and a weigh of ones gives plain bc_loss exactly."""
    class Near(torch.nn.Module):  # d(s, g) = |s - g|, the distance a perfect Eq. 6 would learn in this toy
        def forward(self, a, b):
            return (a - b).norm(dim=-1)
    critic = lambda feat, goal: torch.zeros(feat.shape[:-1])
    feat, goal = torch.zeros(4, 2), torch.tensor([[1.0, 0.0]]).expand(4, -1)
    next_feat = torch.tensor([[0.9, 0.0], [0.5, 0.0], [0.0, 0.0], [-0.5, 0.0]])  # from nearest the goal to furthest
    w = C.advantage_weights(critic, Near(), feat, next_feat, goal, 0.99, beta=1.0)
    assert torch.all(w[:-1] > w[1:]) and w.mean().item() == pytest.approx(1.0)
    assert torch.allclose(C.advantage_weights(critic, Near(), feat, next_feat, goal, 0.99, beta=0.0), torch.ones(4))
    clipped = C.advantage_weights(critic, Near(), feat, next_feat, goal, 0.99, beta=100.0)
    assert clipped[0] == clipped[1] and clipped[0].item() == pytest.approx(2.0, rel=1e-3)  # 20, 20, ~0, ~0 over their mean 10
    torch.manual_seed(0)
    actor = P.Actor(P.ActorCriticConfig(**presets.PRESETS["ac"]["smoke"]), 6, 6, 3)
    post, goals, action = torch.randn(5, 4, 6), torch.randn(5, 4, 6), torch.rand(5, 4, 3) * 1.6 - 0.8
    torch.manual_seed(1)
    plain, _ = C.bc_loss(actor, post, goals, action)
    torch.manual_seed(1)
    ones, m = C.bc_loss(actor, post, goals, action, weigh=lambda s, s_next, g: torch.ones(len(s)))
    assert ones.item() == pytest.approx(plain.item(), rel=1e-6) and m["bc_weight_max"] == 1.0
