"""cloning.py: hindsight cloning's loss against torch.distributions, and advantage weights that favour actions bringing
the goal nearer."""
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


def toy_chain(B=64, good_share=0.5, seed=0):
    """A chain where each state holds a good recorded action (+0.8: one step nearer the goal) and a bad one (-0.8: no
    step), the goal 20 steps ahead, phi the position in steps (V(s, g) = -|g - s|): feat, goal, action, final_goal, value."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, 10, (B,), generator=g).float()
    good = torch.rand(B, generator=g) < good_share
    nxt = torch.where(good, x + 1, x)
    feat = torch.stack([torch.stack([x, nxt], 1) / 10, torch.ones(B, 2)], -1)  # (B, 2, 2): the position, a constant
    action = torch.zeros(B, 2, 1)
    action[:, 1, 0] = torch.where(good, 0.8, -0.8)  # a_0 = action[:, 1]
    final_goal = torch.tensor([2.0, 1.0]).expand(B, 2)
    phi_post = torch.stack([x, nxt], 1)[..., None]  # (B, 2, 1)
    value = (phi_post, phi_post.clone(), torch.full((B, 1), 20.0), 0.99)
    return feat, feat.clone(), action, final_goal, value


def test_advantage_weighted_clone_picks_the_good_action_where_plain_cloning_averages():
    """On the toy chain the advantage of the good action is (1 - gamma)(g - s - 1) >= 0 and of the bad one about -1:
    exp(10 A) clones the good action; plain cloning (beta 0) the average of the two, near 0."""
    feat, goal, action, final_goal, value = toy_chain()
    adv = C.advantage(value[0][:, 0], value[0][:, 1], value[2], value[3])
    good = action[:, 1, 0] > 0
    assert torch.allclose(adv[good], 0.01 * (20 - value[0][good, 0, 0] - 1)) and (adv[~good] <= -0.8 + 1e-6).all()
    means = {}
    for beta in (0.0, 10.0):
        torch.manual_seed(0)
        actor = P.Actor(configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"]), 2, 2, 1)
        opt = torch.optim.Adam(actor.parameters(), lr=3e-3)
        for _ in range(300):
            loss, _ = C.bc_loss(actor, feat, goal, action, final_goal, 1.0, value, beta)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            means[beta] = actor.act(feat[:, 0], final_goal).mean().item()
    assert means[10.0] > 0.6, means
    assert abs(means[0.0]) < 0.3, means


def test_td_phi_is_the_distance_in_steps():
    """DistanceNet.phi: d(s, g) = (1 - gamma) ||phi(s) - phi(g)||, the value the clone's advantage reads."""
    import distance as D
    cfg = configs.DistanceConfig(units=16, layers=2, input="feat", reading="td")
    net = D.DistanceNet(cfg, 6)
    s, g = torch.randn(4, 3, 6), torch.randn(4, 3, 6)
    assert torch.allclose(net(s, g), (1 - cfg.gamma) * (net.phi(s) - net.phi(g)).norm(dim=-1), atol=1e-6)
