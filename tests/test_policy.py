"""policy.py: TD(lambda) against the n-step definition, the tanh-Gaussian log-probability against torch.distributions,
no gradient from the actor loss into the world model, goal sampling, and phase 2's gradient to the goal only."""
import numpy as np
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

import configs
import policy as P
import world_model as W
from tests.fixtures import random_batch
from configs import DistanceConfig
from distance import DistanceNet

torch.set_num_threads(1)


def plain_lambda_return(reward, value, gamma, lambda_):
    """The TD(lambda) return by its definition, in plain Python: a lambda-weighted mix of n-step returns
    G^(n)_k = r_{k+1} + ... + gamma^(n-1) r_{k+n} + gamma^n v_{k+n}, the last one carrying the remaining weight."""
    H = len(reward)
    out = []
    for k in range(H):
        n_max = H - k
        n_step = [sum(gamma**m * reward[k + m] for m in range(n)) + gamma**n * value[k + n] for n in range(1, n_max + 1)]
        out.append(sum((1 - lambda_) * lambda_ ** (n - 1) * n_step[n - 1] for n in range(1, n_max)) + lambda_ ** (n_max - 1) * n_step[-1])
    return out


def test_lambda_return_matches_the_plain_definition():
    g = torch.Generator().manual_seed(0)
    reward, value = torch.randn(3, 6, generator=g, dtype=torch.float64), torch.randn(3, 7, generator=g, dtype=torch.float64)
    returns = P.lambda_return(reward, value, 0.9, 0.8)
    assert returns.shape == (3, 6)
    for n in range(3):
        assert returns[n].tolist() == pytest.approx(plain_lambda_return(reward[n].tolist(), value[n].tolist(), 0.9, 0.8), abs=1e-10)


def test_tanh_gaussian_log_prob_matches_torch_distributions():
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    actor = P.Actor(cfg, 6, 3, 2).double()
    feat, goal = torch.randn(50, 6, dtype=torch.float64), torch.randn(50, 3, dtype=torch.float64)
    action, log_prob = actor(feat, goal)
    mean, std = actor.distribution(feat, goal)
    expected = TransformedDistribution(Normal(mean, std), [TanhTransform()]).log_prob(action).sum(-1)
    assert action.shape == (50, 2) and action.abs().max() <= 1
    assert torch.allclose(log_prob, expected, atol=1e-6)


def make_agents(goal_dim=None):
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    world_model = W.WorldModel(configs.WorldModelConfig(**configs.PRESETS["wm"]["smoke"]), 5, 2)
    F = world_model.feat_dim
    dist_net = DistanceNet(DistanceConfig(**configs.PRESETS["dist"]["smoke"], input="feat"), F)
    actor = P.Actor(cfg, F, F, 2)
    critic, slow_critic = P.make_critics(cfg, F, F if goal_dim is None else goal_dim)
    return cfg, world_model, dist_net, actor, critic, slow_critic


def test_actor_loss_passes_no_gradient_to_the_world_model():
    torch.manual_seed(0)
    cfg, world_model, dist_net, actor, critic, slow_critic = make_agents()
    batch = random_batch("state", 5, 2, 4, 6)
    _, _, post = world_model.loss(batch)  # post carries the world model's graph: the start states must cut it
    start, index = P.sample_starts(post, 16)
    post_feat = world_model.feat(post)
    goal = P.sample_goals(post_feat, post_feat.flip(0), index, batch["is_first"], cfg.goal_mix, 0.5)
    a_loss, c_loss, metrics = P.policy_losses(world_model, dist_net, actor, critic, slow_critic, P.ReturnNorm(0.99), start, goal, cfg)
    assert {"actor_loss", "critic_loss", "reward", "return", "value", "entropy"} <= metrics.keys()
    a_loss.backward()
    for module in (world_model, dist_net, critic, slow_critic):
        assert all(p.grad is None for p in module.parameters()), type(module).__name__
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    assert all(p.requires_grad for p in world_model.parameters()) and all(p.requires_grad for p in dist_net.parameters())
    c_loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in critic.parameters())
    assert all(p.grad is None for p in world_model.parameters())


def test_slow_critic_follows_by_ema():
    cfg, *_, critic, slow_critic = make_agents()
    assert all(not p.requires_grad for p in slow_critic.parameters())
    with torch.no_grad():
        for p in critic.parameters():
            p.add_(1.0)  # the critic moved by 1 everywhere
    before = [p.clone() for p in slow_critic.parameters()]
    P.ema_update(slow_critic, critic, cfg.slow_critic_rate)
    assert all(torch.allclose(p, b + cfg.slow_critic_rate) for p, b in zip(slow_critic.parameters(), before))


def test_rollout_shapes_and_alignment():
    torch.manual_seed(0)
    cfg, world_model, dist_net, actor, *_ = make_agents()
    N, H, F = 5, 4, world_model.feat_dim
    start = world_model.initial_state(N)
    goal = torch.randn(N, F)
    feat, action, log_prob = P.rollout(world_model, actor, start, goal, H)
    assert feat.shape == (N, H + 1, F) and action.shape == (N, H, 2) and log_prob.shape == (N, H)
    assert torch.equal(feat[:, 0], world_model.feat(start))
    reward = P.goal_reward(dist_net, feat, goal)
    assert reward.shape == (N, H)
    assert torch.allclose(reward[:, 0], -dist_net(feat[:, 1], goal))  # r_1 is earned on arriving at s_1


def test_sample_goals_mixes_posterior_states_and_encoder_goals():
    B, T = 5, 2
    post_feat, encoded = torch.zeros(B, T, 3), torch.ones(B, T, 3)
    is_first, index = torch.zeros(B, T, dtype=torch.bool), torch.zeros(2000, dtype=torch.long)
    g = torch.Generator().manual_seed(0)
    assert (P.sample_goals(post_feat, encoded, index[:200], is_first, 0.0, 0.5, g) == 0).all()
    assert (P.sample_goals(post_feat, encoded, index[:200], is_first, 1.0, 0.5, g) == 1).all()
    share = P.sample_goals(post_feat, encoded, index, is_first, 0.5, 0.5, g)[:, 0].mean().item()
    assert 0.45 < share < 0.55


def test_near_goals_are_later_frames_of_the_start_segment():
    """Each frame's feature is its flat index b * T + t, so a goal tells which frame it came from."""
    B, T = 3, 6
    frame = torch.arange(B * T, dtype=torch.float).reshape(B, T, 1)
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[1, 3] = True  # row 1: a new episode starts at t = 3
    g = torch.Generator().manual_seed(0)
    index = torch.tensor([0 * T + 1, 1 * T + 0, 2 * T + 5] * 400)  # starts (0, 1), (1, 0), (2, 5)
    goal = P.sample_goals(frame, frame, index, is_first, 1.0, 1.0, g)[:, 0].long()
    first, second, last = goal[0::3], goal[1::3], goal[2::3]
    assert set(first.tolist()) == set(range(2, 6))  # every later frame of row 0, none earlier
    # row 1 from t = 0: frames 7, 8 are reachable; a draw past the episode start at t = 3 (frames 9-11) falls back
    # to a frame anywhere in the batch, so 9-11 appear only at that rate (3 / 5 of draws x 3 / 18 frames = 0.1)
    assert ((second == 7) | (second == 8)).float().mean() > 0.35
    assert ((second >= 9) & (second <= 11)).float().mean() < 0.16
    assert len(set(last.tolist())) > 5  # the last frame has no later one: any frame of the batch
    far = P.sample_goals(frame, frame, index, is_first, 1.0, 0.0, g)[:, 0].long()
    assert len(set(far[0::3].tolist())) == B * T  # near = 0: goals anywhere in the batch


def test_sample_starts_are_distinct_detached_posterior_states():
    post = {"deter": torch.arange(12.0, requires_grad=True).reshape(3, 4, 1) * 1, "stoch": torch.zeros(3, 4, 2)}
    start, index = P.sample_starts(post, 5, torch.Generator().manual_seed(0))
    assert start["deter"].shape == (5, 1) and start["stoch"].shape == (5, 2) and not start["deter"].requires_grad
    assert len(set(start["deter"].flatten().tolist())) == 5
    assert torch.equal(start["deter"][:, 0], index.float())  # deter of flat index i is i
    assert P.sample_starts(post, 100)[0]["deter"].shape == (12, 1)


def test_actor_with_its_goal_input_computed_once_equals_the_concatenated_layer():
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    actor = P.Actor(cfg, 6, 4, 3)
    feat, goal = torch.randn(7, 6), torch.randn(7, 4)
    mean, std = actor.distribution(feat, goal)
    x = actor.net(torch.cat([feat, goal], -1))  # the plain MLP on [feat, goal]
    raw_mean, raw_std = x.chunk(2, -1)
    assert torch.allclose(mean, cfg.mean_scale * torch.tanh(raw_mean / cfg.mean_scale), atol=1e-6)
    assert torch.allclose(std, (cfg.max_std - cfg.min_std) * torch.sigmoid(raw_std + 2.0) + cfg.min_std, atol=1e-6)
    assert torch.allclose(actor.distribution(feat, goal, actor.goal_input(goal))[0], mean)
    other = actor.distribution(feat, torch.randn(7, 4))[0]
    assert (other - mean).abs().max() > 1e-3  # the action depends on the goal


def test_act_is_the_tanh_of_the_mean_and_draws_no_random_numbers():
    """How pi acts in the real environment: forward's deterministic action, the RNG untouched."""
    torch.manual_seed(0)
    actor = P.Actor(configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"]), 6, 4, 3)
    feat, goal = torch.randn(50, 6), torch.randn(50, 4)
    with torch.no_grad():
        state = torch.get_rng_state()
        assert torch.equal(actor.act(feat, goal), actor(feat, goal, deterministic=True)[0])
        assert torch.equal(actor.act(feat, goal), torch.tanh(actor.distribution(feat, goal)[0]))
        assert torch.equal(torch.get_rng_state(), state)


def test_phase2_reuse_sends_gradient_to_the_goal_only():
    """Eq. 5's pattern: frozen world model and actor, a critic V(s) without goal, a reward of the states only."""
    torch.manual_seed(0)
    cfg, world_model, _, actor, critic, _ = make_agents(goal_dim=0)
    N, F = 6, world_model.feat_dim
    goal = torch.randn(1, F, requires_grad=True)  # one goal vector shared by every start
    with P.freeze(world_model, actor, critic):
        feat, _, log_prob = P.rollout(world_model, actor, world_model.initial_state(N), goal, cfg.horizon)
        reward = -feat[:, 1:].pow(2).sum(-1)  # any differentiable reward of the states (the OT reward in imitate.py)
        returns = P.lambda_return(reward, critic(feat, None), cfg.gamma, cfg.lambda_)
    loss, _ = P.actor_loss(returns, log_prob, P.ReturnNorm(cfg.return_norm_decay), cfg.entropy)
    loss.backward()
    assert goal.grad is not None and goal.grad.abs().sum() > 0
    for module in (world_model, actor, critic):
        assert all(p.grad is None for p in module.parameters())
    with pytest.raises(AssertionError):
        critic(feat, goal)  # goal_dim = 0: V_ot(s) takes no goal


def test_return_norm_scale():
    norm = P.ReturnNorm(0.0)  # decay 0: the scale is the current batch's 5-95 percentile range
    assert norm(torch.linspace(0, 0.5, 101)).item() == 1.0  # ranges below 1 are not scaled up
    assert norm(torch.linspace(0, 10, 101)).item() == pytest.approx(9.0, abs=1e-4)


class ToyWorld(torch.nn.Module):
    """A world whose latent state is a point in the plane that each action moves by 0.2 a: what imagine needs."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(0.2))

    @staticmethod
    def feat(state):
        return state["deter"]

    def imagine(self, start, policy_fn, horizon):
        states, actions = [start["deter"]], []
        for _ in range(horizon):
            actions.append(policy_fn(states[-1]))
            states.append(states[-1] + self.scale * actions[-1])
        return {"deter": torch.stack(states, 1)}, torch.stack(actions, 1)


def test_eq4_updates_on_a_toy_world_raise_the_goal_reward_beyond_what_ignoring_the_goal_earns():
    """Starts at the origin, goals on the unit circle, d = distance to the goal. A policy that ignores g can do no
    better than staying put (reward -1 at every step); a few hundred Eq. 4 updates must reach the goals."""
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(units=64, actor_layers=2, critic_layers=2, horizon=8, actor_lr=1e-3, critic_lr=1e-3)
    world = ToyWorld()
    dist_net = lambda feat, goal: (feat - goal).norm(dim=-1)  # a stub with no parameters
    dist_module = torch.nn.Module()
    actor = P.Actor(cfg, 2, 2, 2)
    critic, slow_critic = P.make_critics(cfg, 2, 2)
    return_norm = P.ReturnNorm(cfg.return_norm_decay)
    opts = [torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr), torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr)]

    def losses():
        angle = torch.rand(128) * 2 * torch.pi
        goal = torch.stack([angle.cos(), angle.sin()], -1)
        start = {"deter": torch.zeros(128, 2)}
        with P.freeze(world, dist_module, slow_critic):
            feat, _, log_prob = P.rollout(world, actor, start, goal, cfg.horizon)
            reward = P.goal_reward(dist_net, feat, goal)
            returns = P.lambda_return(reward, slow_critic(feat, goal), cfg.gamma, cfg.lambda_)
        return P.actor_loss(returns, log_prob, return_norm, cfg.entropy)[0], P.critic_loss(critic, feat, goal, returns)[0], reward.mean().item()

    first = losses()[2]
    for _ in range(120):
        a_loss, c_loss, reward = losses()
        for opt in opts:
            opt.zero_grad()
        (a_loss + c_loss).backward()
        for opt in opts:
            opt.step()
        P.ema_update(slow_critic, critic, cfg.slow_critic_rate)
    assert first > -1.3 and reward > -0.6, (first, reward)  # ignoring g: -1 at best


def test_critic_with_the_goal_share_computed_once_equals_the_mlp_on_feat_and_goal():
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    critic = P.Critic(cfg, 6, 4)
    feat, goal = torch.randn(5, 3, 6), torch.randn(5, 4)  # (N, H + 1, F), (N, G)
    expected = critic.net(torch.cat([feat, goal[:, None].expand(-1, 3, -1)], -1)).squeeze(-1)
    assert torch.allclose(critic(feat, goal), expected, atol=1e-6)


class OracleActor:
    """Steps straight towards the goal it is given: what reachable_goal_reward needs of an actor."""

    action_dim = 2

    def goal_input(self, goal):
        return goal

    def __call__(self, feat, goal, deterministic=False, goal_in=None):
        step = (goal_in - feat) / 0.2  # ToyWorld moves 0.2 a: a step of at most 0.2
        return step / step.norm(dim=-1, keepdim=True).clamp(min=1), None


def test_reachable_goal_reward_scores_the_goal_of_the_data_against_ignoring_it_and_random_actions():
    """Segments that move 0.1 per step in their own direction: the goal 15 steps ahead is 1.5 away and an actor
    steering to it arrives; the same actor given another segment's goal, or random actions, score lower. The training
    RNG is left where it was."""
    import evaluate

    torch.manual_seed(0)
    B, T, H = 16, 30, 15
    angle = torch.rand(B) * 2 * torch.pi
    pos = 0.1 * torch.arange(T)[None, :, None] * torch.stack([angle.cos(), angle.sin()], -1)[:, None]  # (B, T, 2)
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True
    dist = lambda feat, goal: (feat - goal).norm(dim=-1)
    state = torch.get_rng_state()
    own, other, random = evaluate.reachable_goal_reward(ToyWorld(), dist, OracleActor(), {"deter": pos}, pos, is_first, H)["reward_reachable"]
    assert torch.equal(torch.get_rng_state(), state)
    steps = torch.arange(1, H + 1).float()
    assert own == pytest.approx(-(1.5 - 0.2 * steps).clamp(min=0).mean().item(), abs=1e-5)  # arrives at step 8
    assert own > random + 0.5 and own > other + 0.5, (own, other, random)
    is_first[:, 20] = True  # an episode starts inside every segment's window: no segment qualifies
    assert np.isnan(evaluate.reachable_goal_reward(ToyWorld(), dist, OracleActor(), {"deter": pos}, pos, is_first, H)["reward_reachable"][0])
