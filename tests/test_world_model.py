"""world_model.py: the KLs of both latent families against torch.distributions, the categorical's straight-through
sample and unimix, shapes for both observation modes and both families, the lean observe loop against img_step,
is_first resets, and a few Adam steps that lower Eq. 2's loss on a learnable system."""
import pytest
import torch
import torch.nn.functional as F
from torch.distributions import Categorical, Independent, Normal, OneHotCategorical, kl_divergence

import configs
import evaluate
import world_model as W
from tests.fixtures import random_batch

torch.set_num_threads(1)


def smoke_model(obs="state", obs_dim=5, action_dim=2, **overrides):
    cfg = configs.WorldModelConfig(**{**configs.PRESETS["wm"]["smoke"], "obs": obs, **overrides})
    obs_shape = obs_dim if obs == "state" else (64, 64, 3)
    return W.WorldModel(cfg, obs_shape, action_dim), obs_shape


def test_gaussian_kl_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    mean_q, mean_p = torch.randn(7, 5, 4, generator=g), torch.randn(7, 5, 4, generator=g)
    std_q, std_p = torch.rand(7, 5, 4, generator=g) + 0.1, torch.rand(7, 5, 4, generator=g) + 0.1
    expected = kl_divergence(Independent(Normal(mean_q, std_q), 1), Independent(Normal(mean_p, std_p), 1))
    assert torch.allclose(W.gaussian_kl(mean_q, std_q, mean_p, std_p), expected, atol=1e-5)


def categorical(stoch=3, discrete=5, unimix=0.01):
    return W.make_latent(configs.WorldModelConfig(stoch=stoch, discrete=discrete, unimix=unimix))


def test_categorical_kl_matches_torch_distributions():
    latent, g = categorical(), torch.Generator().manual_seed(0)
    q, p = (latent.stats(3 * torch.randn(7, 5, latent.out_dim, generator=g)) for _ in range(2))
    dist = lambda stats: Independent(OneHotCategorical(probs=latent.mean(stats).unflatten(-1, (3, 5))), 1)
    expected = kl_divergence(dist(q), dist(p))  # (7, 5): summed over the 3 variables
    per_variable = kl_divergence(Categorical(logits=q["logits"].unflatten(-1, (3, 5))), Categorical(logits=p["logits"].unflatten(-1, (3, 5))))
    assert torch.allclose(latent.kl(q, p), expected, atol=1e-5) and torch.allclose(expected, per_variable.sum(-1), atol=1e-5)
    assert torch.allclose(latent.entropy(q), dist(q).entropy(), atol=1e-5)
    assert torch.allclose(latent.kl(q, q), torch.zeros(7, 5), atol=1e-6)


def test_gaussian_latent_sample_mode_and_entropy():
    latent, g = W.make_latent(configs.WorldModelConfig(stoch=4)), torch.Generator().manual_seed(0)
    stats = latent.stats(torch.randn(6, latent.out_dim, generator=g))
    noise = torch.randn(6, latent.size, generator=g)
    assert torch.equal(latent.sample(stats, noise), stats["mean"] + stats["std"] * noise)
    assert torch.equal(latent.mode(stats), stats["mean"]) and torch.equal(latent.mean(stats), stats["mean"])
    assert torch.allclose(latent.entropy(stats), Independent(Normal(stats["mean"], stats["std"]), 1).entropy(), atol=1e-5)


def test_unimix_mixes_a_uniform_into_the_probabilities():
    latent, x = categorical(unimix=0.01), 10 * torch.randn(4, 15, generator=torch.Generator().manual_seed(0))
    probs = latent.mean(latent.stats(x)).unflatten(-1, (3, 5))  # (4, 3, 5)
    assert (probs >= 0.01 / 5 - 1e-7).all() and torch.allclose(probs.sum(-1), torch.ones(4, 3))
    assert torch.allclose(probs, 0.99 * x.unflatten(-1, (3, 5)).softmax(-1) + 0.01 / 5, atol=1e-6)


def test_straight_through_one_hot_sample():
    """Forward: exact one-hots, distributed as the probabilities; backward: the probabilities' gradient."""
    latent, g = categorical(), torch.Generator().manual_seed(0)
    x = torch.randn(2, latent.out_dim, generator=g, requires_grad=True)
    stats = latent.stats(x)
    for z in (latent.sample(stats), latent.mode(stats)):
        z = z.unflatten(-1, (3, 5))
        assert ((z == 0) | (z == 1)).all() and torch.equal(z.sum(-1), torch.ones(2, 3))
    assert torch.equal(latent.mode(stats).unflatten(-1, (3, 5)).argmax(-1), stats["logits"].unflatten(-1, (3, 5)).argmax(-1))
    w = torch.randn(2, latent.size, generator=g)
    grad, = torch.autograd.grad((latent.sample(stats) * w).sum(), x, retain_graph=True)
    expected, = torch.autograd.grad((latent.mean(stats) * w).sum(), x)
    assert grad.abs().sum() > 0 and torch.allclose(grad, expected)
    # Gumbel-max from the standard normal noise draws each class with its probability
    many = {k: v.detach().expand(20000, -1, -1) for k, v in stats.items()}  # (20000, 2, size)
    freq = latent.sample(many, torch.randn(20000, 2, latent.size, generator=g)).mean(0)
    assert (freq - latent.mean(stats)).abs().max() < 0.015, (freq, latent.mean(stats))


@pytest.mark.parametrize("obs, discrete", [("state", 0), ("pixels", 0), ("state", 4)])
def test_shapes_through_observe_imagine_loss(obs, discrete):
    torch.manual_seed(0)
    model, obs_shape = smoke_model(obs, discrete=discrete)
    cfg, (B, T, A) = model.cfg, (3, 6, 2)
    Z = cfg.stoch * (discrete or 1)  # the width of z in feat
    assert model.feat_dim == cfg.deter + Z and model.state_keys == ("deter", "stoch") + (("logits",) if discrete else ("mean", "std"))
    batch = random_batch(obs, obs_shape, A, B, T)
    post, prior = model.observe(batch[obs], batch["action"], batch["is_first"])
    stat_shapes = {"logits": (B, T, Z)} if discrete else {"mean": (B, T, Z), "std": (B, T, Z)}
    for state in (post, prior):
        assert {k: tuple(v.shape) for k, v in state.items()} == {"deter": (B, T, cfg.deter), "stoch": (B, T, Z), **stat_shapes}
        if discrete:
            assert torch.equal(state["stoch"].unflatten(-1, (cfg.stoch, discrete)).sum(-1), torch.ones(B, T, cfg.stoch))
        else:
            assert (state["std"] >= cfg.min_std).all()
    assert {k: tuple(v.shape) for k, v in model.initial_state(B).items()} == {k: (B, s[-1]) for k, s in {"deter": (cfg.deter,), "stoch": (Z,), **stat_shapes}.items()}
    feat = model.feat(post)
    assert feat.shape == (B, T, model.feat_dim)
    assert model.decode(feat).shape == (B, T) + model.obs_shape
    loss, metrics, post = model.loss(batch)
    assert loss.shape == () and torch.isfinite(loss) and {"wm_loss", "recon", "kl", "post_ent", "prior_ent"} <= metrics.keys()
    start = {k: v[:, -1] for k, v in post.items()}  # (B, .)
    states, actions = model.imagine(start, lambda f: torch.tanh(f[:, :A]), horizon=4)
    assert {k: tuple(v.shape) for k, v in states.items()} == {k: (B, 5, s[-1]) for k, s in {"deter": (cfg.deter,), "stoch": (Z,), **stat_shapes}.items()}
    assert evaluate.open_loop(model, batch, context=3)[0].shape == (B, T - 3, model.feat_dim)
    assert actions.shape == (B, 4, A) and torch.equal(states["deter"][:, 0], start["deter"])
    error = evaluate.open_loop_error(model, batch, context=3)
    assert error > 0 and error == error  # finite, not NaN


@pytest.mark.parametrize("discrete, sample", [(0, True), (0, False), (4, True), (4, False)])
def test_lean_observe_loop_equals_plain_steps(discrete, sample):
    """observe's regrouped loop = the plain definitions: prior via img_step, posterior via post_in on [h_t, e_t];
    sample=False: z_t the posterior's mode."""
    torch.manual_seed(0)
    model, obs_shape = smoke_model(discrete=discrete)
    latent = model.latent
    batch = random_batch("state", obs_shape, 2, 3, 6, seed=1)
    post, prior = model.observe(batch["state"], batch["action"], batch["is_first"], sample=sample)
    for t in range(1, 6):
        step = model.img_step({k: v[:, t - 1] for k, v in post.items()}, batch["action"][:, t], sample=False)
        for key in ("deter",) + latent.stat_keys:
            assert torch.allclose(step[key], prior[key][:, t], atol=1e-5), (t, key)
        assert torch.equal(step["stoch"], latent.mode(step))
    embed = model.encode(batch["state"])
    stats = latent.stats(model.post_out(F.silu(model.post_in(torch.cat([post["deter"], embed], -1)))))
    for key in latent.stat_keys:
        assert torch.allclose(stats[key], post[key], atol=1e-5), key
    if not sample:
        assert torch.equal(post["stoch"], latent.mode(post))
    elif discrete:  # a draw, not the mode, yet one-hot
        assert not torch.equal(post["stoch"], latent.mode(post)) and set(post["stoch"].unique().tolist()) == {0.0, 1.0}
    # continuing from a given state: the suffix's first h is one GRU step from that state
    suffix, _ = model.observe(batch["state"][:, 3:], batch["action"][:, 3:], batch["is_first"][:, 3:], {k: v[:, 2] for k, v in post.items()})
    assert torch.allclose(suffix["deter"][:, 0], post["deter"][:, 3], atol=1e-5)


def test_is_first_resets_the_state():
    torch.manual_seed(0)
    model, obs_shape = smoke_model()
    batch = random_batch("state", obs_shape, 2, 3, 8, seed=2)
    k = 4
    batch["is_first"][:, k] = True  # a new episode starts mid-segment; action[:, k] is non-zero and must be ignored
    assert batch["action"][:, k].abs().sum() > 0
    post, _ = model.observe(batch["state"], batch["action"], batch["is_first"])
    fresh, _ = model.observe(batch["state"][:, k:], batch["action"][:, k:], batch["is_first"][:, k:])
    for key in ("deter",) + model.latent.stat_keys:
        assert torch.allclose(post[key][:, k], fresh[key][:, 0], atol=1e-6), key
    no_reset = batch["is_first"].clone()
    no_reset[:, k] = False
    carried, _ = model.observe(batch["state"], batch["action"], no_reset)
    assert not torch.allclose(carried["deter"][:, k], fresh["deter"][:, 0], atol=1e-3)


def linear_system(B, T, g, obs_dim=4, action_dim=2):
    """o_t = M o_{t-1} + N a_{t-1}: a fixed, stable, learnable system with random actions, in collect.py's layout."""
    rot = torch.tensor([[0.95, -0.2], [0.2, 0.95]])
    M = torch.block_diag(rot, rot)
    N = torch.tensor([[0.3, 0.0], [0.0, 0.3], [0.2, 0.1], [-0.1, 0.2]])
    action = torch.rand(B, T, action_dim, generator=g) * 2 - 1
    action[:, 0] = 0
    obs = [torch.randn(B, obs_dim, generator=g)]
    for t in range(1, T):
        obs.append(obs[-1] @ M.T + action[:, t] @ N.T)
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True
    return {"state": torch.stack(obs, 1), "action": action, "is_first": is_first}


@pytest.mark.parametrize("discrete, updates", [(0, 120), (4, 200)])  # one-hot z fits this continuous system more slowly
def test_a_few_updates_lower_the_loss_on_a_learnable_system(discrete, updates):
    torch.manual_seed(0)
    model, _ = smoke_model(obs_dim=4, deter=32, stoch=4, hidden=32, units=32, discrete=discrete)
    g = torch.Generator().manual_seed(0)
    held_out = linear_system(16, 12, g)

    def measure():
        torch.manual_seed(1)
        with torch.no_grad():
            metrics = model.loss(held_out)[1]
        return metrics["wm_loss"], metrics["recon"], evaluate.open_loop_error(model, held_out, context=6)

    before = measure()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(updates):
        loss = model.loss(linear_system(16, 12, g))[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = measure()
    assert after[0] < 0.8 * before[0], (before, after)  # Eq. 2's loss (floored by the free nats)
    assert after[1] < 0.3 * before[1], (before, after)  # reconstruction
    assert after[2] < 0.5 * before[2], (before, after)  # open-loop prediction
