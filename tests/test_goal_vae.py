"""goal_vae.py: Eq. 3's terms against torch.distributions, no gradient into the world model, the goal in the world
model's feature space, and a few updates that fit the encoder to the posterior."""
import torch
import torch.nn.functional as F
from torch.distributions import Independent, Normal, kl_divergence

import presets
import world_model as W
from goal_vae import GoalVAE, GoalVAEConfig

torch.set_num_threads(1)
D = 8


def models():
    cfg = W.WorldModelConfig(**presets.PRESETS["wm"]["smoke"])
    world_model = W.WorldModel(cfg, 5, 2)
    vae = GoalVAE(GoalVAEConfig(**presets.PRESETS["goal"]["smoke"]), D, cfg.deter, cfg.stoch)
    return world_model, vae


def test_goal_vae_passes_no_gradient_to_the_world_model():
    torch.manual_seed(0)
    world_model, vae = models()
    batch = W.random_batch("state", 5, 2, 3, 6, p_dim=D)
    _, _, post = world_model.loss(batch)  # post still carries the world model's graph
    loss, _ = vae.loss(batch["p"], post)
    loss.backward()
    assert all(p.grad is None for p in world_model.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in vae.parameters())


def test_eq3_terms_match_torch_distributions():
    torch.manual_seed(0)
    _, vae = models()
    B, T, H, Z = 3, 4, vae.deter, vae.stoch
    p = F.normalize(torch.randn(B, T, D), dim=-1)
    post = {"deter": torch.randn(B, T, H), "stoch": torch.randn(B, T, Z), "mean": torch.randn(B, T, Z), "std": torch.rand(B, T, Z) + 0.1}
    loss, metrics = vae.loss(p, post)
    mean, std = vae.distribution(p)
    mean_h, mean_z = mean.split([H, Z], -1)
    std_h, std_z = std.split([H, Z], -1)
    kl = kl_divergence(Independent(Normal(mean_z, std_z), 1), Independent(Normal(post["mean"], post["std"]), 1)).mean()
    nll = -Independent(Normal(mean_h, std_h), 1).log_prob(post["deter"]).mean()
    assert abs(metrics["goal_kl"] - kl.item()) < 1e-4
    assert abs(metrics["goal_deter_nll"] - nll.item()) < 1e-3
    assert abs(metrics["goal_recon"] - vae.cfg.kappa * (1 - metrics["goal_cos"])) < 1e-4
    post_cos = (vae.decode(torch.cat([post["deter"], post["stoch"]], -1)) * p).sum(-1).mean()  # the decoder on posterior states
    assert abs(metrics["goal_post_cos"] - post_cos.item()) < 1e-5
    expected = metrics["goal_kl"] + metrics["goal_deter_nll"] + metrics["goal_recon"] + vae.cfg.kappa * (1 - post_cos.item())
    assert abs(loss.item() - expected) < 1e-3


def test_encode_goal_decode():
    torch.manual_seed(0)
    world_model, vae = models()
    p = F.normalize(torch.randn(5, 7, D), dim=-1)
    state = vae.encode(p)
    assert state["deter"].shape == (5, 7, vae.deter) and state["stoch"].shape == (5, 7, vae.stoch)
    goal = vae.goal(p)
    assert torch.equal(goal, world_model.feat(state)) and goal.shape == (5, 7, world_model.feat_dim)
    p_hat = vae.decode(goal)
    assert p_hat.shape == (5, 7, D) and torch.allclose(p_hat.norm(dim=-1), torch.ones(5, 7), atol=1e-5)


def test_a_few_updates_fit_the_encoder_to_the_posterior():
    """A posterior that is a fixed function of p_t: the KL, the h likelihood and the decoder all improve."""
    torch.manual_seed(0)
    _, vae = models()
    H, Z = vae.deter, vae.stoch
    proj = torch.randn(D, H + Z)

    def sample(n):
        p = F.normalize(torch.randn(n, 1, D), dim=-1)
        target = torch.tanh(p @ proj)
        return p, {"deter": target[..., :H], "stoch": target[..., H:], "mean": target[..., H:], "std": torch.full((n, 1, Z), 0.2)}

    p, post = sample(256)
    before = vae.loss(p, post)[1]
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)
    for _ in range(150):
        loss = vae.loss(*sample(64))[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = vae.loss(p, post)[1]
    assert after["goal_kl"] < 0.3 * before["goal_kl"], (before, after)
    assert after["goal_deter_nll"] < before["goal_deter_nll"] - 5, (before, after)
    assert after["goal_cos"] > before["goal_cos"] + 0.4, (before, after)
    assert after["goal_post_cos"] > before["goal_post_cos"] + 0.4, (before, after)
