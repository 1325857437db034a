"""goal_vae.py: Eq. 3's terms against torch.distributions for both latent families, no gradient into the world model,
the goal in the world model's feature space, draws of q(s | p), and a few updates that fit the encoder to the posterior."""
import pytest
import torch
import torch.nn.functional as F
from torch.distributions import Independent, Normal, OneHotCategorical, kl_divergence

import configs
import fidelity
import world_model as W
from tests.fixtures import random_batch
from configs import GoalVAEConfig
from goal_vae import GoalVAE

torch.set_num_threads(1)
D = 8


def models(discrete=0):
    cfg = configs.WorldModelConfig(**configs.PRESETS["wm"]["smoke"], discrete=discrete)
    world_model = W.WorldModel(cfg, 5, 2)
    vae = GoalVAE(GoalVAEConfig(**configs.PRESETS["goal"]["smoke"]), D, cfg.deter, world_model.latent)
    return world_model, vae


@pytest.mark.parametrize("discrete", [0, 4])
def test_goal_vae_passes_no_gradient_to_the_world_model(discrete):
    torch.manual_seed(0)
    world_model, vae = models(discrete)
    batch = random_batch("state", 5, 2, 3, 6, p_dim=D)
    _, _, post = world_model.loss(batch)  # post still carries the world model's graph
    loss, _ = vae.loss(batch["p"], post)
    loss.backward()
    assert all(p.grad is None for p in world_model.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in vae.parameters())


@pytest.mark.parametrize("discrete", [0, 4])
def test_eq3_terms_match_torch_distributions(discrete):
    torch.manual_seed(0)
    world_model, vae = models(discrete)
    latent, (B, T, H, Z) = vae.latent, (3, 4, vae.deter, vae.stoch)
    p = F.normalize(torch.randn(B, T, D), dim=-1)
    post_stats = latent.stats(2 * torch.randn(B, T, latent.out_dim))
    post = {"deter": torch.randn(B, T, H), "stoch": latent.sample(post_stats), **post_stats}
    loss, metrics = vae.loss(p, post)
    mean_h, std_h, stats = vae.distribution(p)
    if discrete:  # q(z | p_t): logits per variable, as the world model's posterior
        dist = lambda s: Independent(OneHotCategorical(probs=latent.mean(s).unflatten(-1, (world_model.cfg.stoch, discrete))), 1)
    else:
        dist = lambda s: Independent(Normal(s["mean"], s["std"]), 1)
    kl = kl_divergence(dist(stats), dist(post_stats)).mean()
    nll = -Independent(Normal(mean_h, std_h), 1).log_prob(post["deter"]).mean()
    assert abs(metrics["goal_kl"] - kl.item()) < 1e-4
    assert abs(metrics["goal_deter_nll"] - nll.item()) < 1e-3
    assert abs(metrics["goal_recon"] - vae.cfg.kappa * (1 - metrics["goal_cos"])) < 1e-4
    post_cos = (vae.decode(torch.cat([post["deter"], post["stoch"]], -1)) * p).sum(-1).mean()  # the decoder on posterior states
    assert abs(metrics["goal_post_cos"] - post_cos.item()) < 1e-5
    expected = metrics["goal_kl"] + metrics["goal_deter_nll"] + metrics["goal_recon"] + vae.cfg.kappa * (1 - post_cos.item())
    assert abs(loss.item() - expected) < 1e-3


@pytest.mark.parametrize("discrete", [0, 4])
def test_encode_goal_decode(discrete):
    torch.manual_seed(0)
    world_model, vae = models(discrete)
    p = F.normalize(torch.randn(5, 7, D), dim=-1)
    state = vae.encode(p)
    assert set(state) == set(world_model.state_keys) | {"deter_std"}
    assert state["deter"].shape == (5, 7, vae.deter) and state["stoch"].shape == (5, 7, vae.stoch) == (5, 7, world_model.latent.size)
    goal = vae.goal(p)
    assert torch.equal(goal, world_model.feat(state)) and goal.shape == (5, 7, world_model.feat_dim)
    if discrete:  # E[z]: each variable's probabilities
        assert torch.allclose(state["stoch"].unflatten(-1, (-1, discrete)).sum(-1), torch.ones(5, 7, world_model.cfg.stoch))
    # an imagination start: the world model steps from the goal encoder's state
    step = world_model.img_step({k: v[:, 0] for k, v in state.items()}, torch.zeros(5, 2))
    assert world_model.feat(step).shape == (5, world_model.feat_dim)
    p_hat = vae.decode(goal)
    assert p_hat.shape == (5, 7, D) and torch.allclose(p_hat.norm(dim=-1), torch.ones(5, 7), atol=1e-5)


@pytest.mark.parametrize("discrete", [0, 4])
def test_sample_goals_draws_q_of_s_given_p(discrete):
    """n draws s^g ~ q(s | p): h = mean_h + scale std_h eps; z a latent.sample from the same noise (Gaussian: mean + std eps)."""
    world_model, vae = models(discrete)
    p = F.normalize(torch.randn(1, D, generator=torch.Generator().manual_seed(0)), dim=-1)
    goals = fidelity.sample_goals(vae, p, 6, torch.Generator().manual_seed(3), scale=2.0)
    eps = 2.0 * torch.randn(6, vae.deter + vae.stoch, generator=torch.Generator().manual_seed(3))
    mean_h, std_h, stats = vae.distribution(p)
    assert goals.shape == (6, world_model.feat_dim) and torch.equal(goals[:, :vae.deter], mean_h + std_h * eps[:, :vae.deter])
    assert torch.equal(goals[:, vae.deter:], vae.latent.sample(stats, eps[:, vae.deter:]))
    if not discrete:  # the goal encoder's Gaussian over [h, z], mean + scale * std * eps
        assert torch.allclose(goals, vae.goal(p) + torch.cat([std_h, stats["std"]], -1) * eps)
    else:  # one-hot draws of each variable
        z = goals[:, vae.deter:].unflatten(-1, (-1, discrete))
        assert torch.equal(z.sum(-1), torch.ones(6, world_model.cfg.stoch)) and set(z.unique().tolist()) == {0.0, 1.0}


@pytest.mark.parametrize("discrete, updates", [(0, 150), (4, 300)])  # the categorical KL falls more slowly
def test_a_few_updates_fit_the_encoder_to_the_posterior(discrete, updates):
    """A posterior that is a fixed function of p_t: the KL, the h likelihood and the decoder all improve."""
    torch.manual_seed(0)
    _, vae = models(discrete)
    latent, H = vae.latent, vae.deter
    proj = torch.randn(D, H + latent.size)  # a categorical's logits: its size

    def sample(n):
        p = F.normalize(torch.randn(n, 1, D), dim=-1)
        target = torch.tanh(p @ proj)
        if discrete:  # sharp categoricals: logits up to +-3
            stats = latent.stats(3 * target[..., H:])
        else:
            stats = {"mean": target[..., H:], "std": torch.full((n, 1, latent.size), 0.2)}
        return p, {"deter": target[..., :H], "stoch": latent.mode(stats), **stats}

    p, post = sample(256)
    before = vae.loss(p, post)[1]
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)
    for _ in range(updates):
        loss = vae.loss(*sample(64))[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = vae.loss(p, post)[1]
    assert after["goal_kl"] < 0.3 * before["goal_kl"], (before, after)
    assert after["goal_deter_nll"] < before["goal_deter_nll"] - 5, (before, after)
    assert after["goal_cos"] > before["goal_cos"] + 0.4, (before, after)
    assert after["goal_post_cos"] > before["goal_post_cos"] + 0.4, (before, after)
