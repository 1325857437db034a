"""world_model.py: the KL against torch.distributions, shapes for both observation modes, the lean observe loop
against img_step, is_first resets, and a few Adam steps that lower Eq. 2's loss on a learnable system."""
import pytest
import torch
import torch.nn.functional as F
from torch.distributions import Independent, Normal, kl_divergence

import presets
import world_model as W

torch.set_num_threads(1)


def smoke_model(obs="state", obs_dim=5, action_dim=2, **overrides):
    cfg = W.WorldModelConfig(**{**presets.PRESETS["wm"]["smoke"], "obs": obs, **overrides})
    obs_shape = obs_dim if obs == "state" else (64, 64, 3)
    return W.WorldModel(cfg, obs_shape, action_dim), obs_shape


def test_gaussian_kl_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    mean_q, mean_p = torch.randn(7, 5, 4, generator=g), torch.randn(7, 5, 4, generator=g)
    std_q, std_p = torch.rand(7, 5, 4, generator=g) + 0.1, torch.rand(7, 5, 4, generator=g) + 0.1
    expected = kl_divergence(Independent(Normal(mean_q, std_q), 1), Independent(Normal(mean_p, std_p), 1))
    assert torch.allclose(W.gaussian_kl(mean_q, std_q, mean_p, std_p), expected, atol=1e-5)


@pytest.mark.parametrize("obs", ["state", "pixels"])
def test_shapes_through_observe_imagine_loss(obs):
    torch.manual_seed(0)
    model, obs_shape = smoke_model(obs)
    cfg, (B, T, A) = model.cfg, (3, 6, 2)
    batch = W.random_batch(obs, obs_shape, A, B, T)
    post, prior = model.observe(batch[obs], batch["action"], batch["is_first"])
    for state in (post, prior):
        assert {k: tuple(v.shape) for k, v in state.items()} == {
            "deter": (B, T, cfg.deter), "stoch": (B, T, cfg.stoch), "mean": (B, T, cfg.stoch), "std": (B, T, cfg.stoch)}
        assert (state["std"] >= cfg.min_std).all()
    feat = model.feat(post)
    assert feat.shape == (B, T, model.feat_dim)
    assert model.decode(feat).shape == (B, T) + model.obs_shape
    loss, metrics, post = model.loss(batch)
    assert loss.shape == () and torch.isfinite(loss) and {"wm_loss", "recon", "kl"} <= metrics.keys()
    start = {k: v[:, -1] for k, v in post.items()}  # (B, .)
    states, actions = model.imagine(start, lambda f: torch.tanh(f[:, :A]), horizon=4)
    assert states["deter"].shape == (B, 5, cfg.deter) and states["stoch"].shape == (B, 5, cfg.stoch)
    assert actions.shape == (B, 4, A) and torch.equal(states["deter"][:, 0], start["deter"])
    error = model.open_loop_error(batch, context=3)
    assert error > 0 and error == error  # finite, not NaN


def test_lean_observe_loop_equals_plain_steps():
    """observe's regrouped loop = the plain definitions: prior via img_step, posterior via post_in on [h_t, e_t]."""
    torch.manual_seed(0)
    model, obs_shape = smoke_model()
    batch = W.random_batch("state", obs_shape, 2, 3, 6, seed=1)
    post, prior = model.observe(batch["state"], batch["action"], batch["is_first"])
    for t in range(1, 6):
        step = model.img_step({k: v[:, t - 1] for k, v in post.items()}, batch["action"][:, t], sample=False)
        for key in ("deter", "mean", "std"):
            assert torch.allclose(step[key], prior[key][:, t], atol=1e-5), (t, key)
    embed = model.encode(batch["state"])
    mean, std = model._gaussian(model.post_out(F.silu(model.post_in(torch.cat([post["deter"], embed], -1)))))
    assert torch.allclose(mean, post["mean"], atol=1e-5) and torch.allclose(std, post["std"], atol=1e-5)
    # continuing from a given state: the suffix's first h is one GRU step from that state
    suffix, _ = model.observe(batch["state"][:, 3:], batch["action"][:, 3:], batch["is_first"][:, 3:], {k: v[:, 2] for k, v in post.items()})
    assert torch.allclose(suffix["deter"][:, 0], post["deter"][:, 3], atol=1e-5)


def test_is_first_resets_the_state():
    torch.manual_seed(0)
    model, obs_shape = smoke_model()
    batch = W.random_batch("state", obs_shape, 2, 3, 8, seed=2)
    k = 4
    batch["is_first"][:, k] = True  # a new episode starts mid-segment; action[:, k] is non-zero and must be ignored
    assert batch["action"][:, k].abs().sum() > 0
    post, _ = model.observe(batch["state"], batch["action"], batch["is_first"])
    fresh, _ = model.observe(batch["state"][:, k:], batch["action"][:, k:], batch["is_first"][:, k:])
    for key in ("deter", "mean", "std"):
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


def test_a_few_updates_lower_the_loss_on_a_learnable_system():
    torch.manual_seed(0)
    model, _ = smoke_model(obs_dim=4, deter=32, stoch=4, hidden=32, units=32)
    g = torch.Generator().manual_seed(0)
    held_out = linear_system(16, 12, g)

    def evaluate():
        torch.manual_seed(1)
        with torch.no_grad():
            metrics = model.loss(held_out)[1]
        return metrics["wm_loss"], metrics["recon"], model.open_loop_error(held_out, context=6)

    before = evaluate()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(120):
        loss = model.loss(linear_system(16, 12, g))[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = evaluate()
    assert after[0] < 0.8 * before[0], (before, after)  # Eq. 2's loss (floored by the free nats)
    assert after[1] < 0.3 * before[1], (before, after)  # reconstruction
    assert after[2] < 0.5 * before[2], (before, after)  # open-loop prediction
