"""Eq. 4: the goal-conditioned actor pi_psi(a | s, g) and critic V_eta(s, g), trained on imagined rollouts with TD(lambda).

One update (policy_losses), following Dreamer V1/V2's actor-critic:
  1. start from N D_body posterior states s_t (sample_starts, detached) with goals g (sample_goals),
  2. imagine H steps with the frozen world model and the actor: s_0 = start, a_k ~ pi(. | s_k, g), s_{k+1} ~ prior,
  3. reward on arrival r_{k+1} = r^goal(s_{k+1}, g) = -d(s_{k+1}, g) (Sec. 4, the distance network),
  4. TD(lambda) returns G_k from r_{k+1} and the slow critic's v_{k+1}, bootstrapped from v_H (lambda_return),
  5. actor loss -G (Eq. 4): its gradient flows back through the frozen dynamics into the actions (Dreamer V1/V2),
  6. critic loss: V(s_k, g) regressed to sg(G_k) for k < H.

Freezing: `freeze` sets requires_grad False on the world model, distance network and slow critic while the
rollout is built, so the actor loss gives their parameters no gradient at all (and no weight-gradient work is
done for them); train.py keeps separate optimisers, so nothing but the actor moves on the actor loss.

Phase 2 (Eq. 5, goal_inference.py) reuses rollout, lambda_return, actor_loss, critic_loss and freeze with the OT reward,
a critic V_ot(s) built with goal_dim = 0 (goal None), and the goal vector g as the only thing optimised by L_GI.
"""
import contextlib
import copy
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from world_model import mlp


def goal_share(linear, goal):
    """W_g g + b of a first layer that reads [feat, goal] (W [f; g] + b = W_f f + W_g g + b): the same at every imagined
    step, so computed once per goal, not once per step. goal (N, G) -> (N, units)."""
    return F.linear(goal, linear.weight[:, linear.in_features - goal.shape[-1] :], linear.bias)


def feat_share(linear, feat):
    """W_f f of that layer: feat (..., F) -> (..., units). As one 2-D matmul: on a 3-D feat with this weight slice
    (not contiguous) F.linear falls back to a batched matmul over a copy of the weight per row (measured slower)."""
    return F.linear(feat.reshape(-1, feat.shape[-1]), linear.weight[:, : feat.shape[-1]]).reshape(*feat.shape[:-1], -1)


def tanh_gaussian_log_prob(u, mean, std):
    """log pi(tanh(u)) of a tanh-squashed diagonal Gaussian, summed over actions: log N(u; mean, std) minus the
    tanh Jacobian log(1 - tanh(u)^2), written stably (SAC, Haarnoja et al. 2018, App. C). (..., A) -> (...)."""
    log_prob = (-0.5 * ((u - mean) / std) ** 2 - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
    return log_prob - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)


class Actor(nn.Module):
    """pi(a | s, g): a tanh-squashed Gaussian (Dreamer V1's tanh-normal) on [feat, goal]."""

    def __init__(self, cfg, feat_dim, goal_dim, action_dim):
        super().__init__()
        self.cfg, self.goal_dim, self.action_dim = cfg, goal_dim, action_dim
        self.net = mlp(feat_dim + goal_dim, cfg.units, 2 * action_dim, cfg.actor_layers)

    def goal_input(self, goal):
        """The goal's share of the first layer, W_g g + b: (N, G) or (1, G) -> (N, units). It is the same at every
        imagined step, so rollout computes it once (the first layer reads [feat, goal]: W [f; g] + b = W_f f + W_g g + b)."""
        assert goal.shape[-1] == self.goal_dim and goal.dim() == 2, goal.shape
        return goal_share(self.net[0], goal)

    def distribution(self, feat, goal, goal_in=None):
        """The Gaussian before the tanh: feat (N, F), goal (N, G) or (1, G) -> mean, std (N, A). goal_in: goal_input(goal)
        when already computed."""
        cfg = self.cfg
        assert feat.dim() == 2, feat.shape
        goal_in = self.goal_input(goal) if goal_in is None else goal_in
        mean, std = self.net[1:](feat_share(self.net[0], feat) + goal_in).chunk(2, -1)
        mean = cfg.mean_scale * torch.tanh(mean / cfg.mean_scale)
        std = (cfg.max_std - cfg.min_std) * torch.sigmoid(std + 2.0) + cfg.min_std  # Dreamer V3's bounded std
        return mean, std

    def log_prob(self, feat, goal, u, goal_in=None):
        """log pi(tanh(u) | s, g) of pre-tanh actions u (N, A) -> (N,)."""
        return tanh_gaussian_log_prob(u, *self.distribution(feat, goal, goal_in))

    def forward(self, feat, goal, deterministic=False, goal_in=None):
        """feat (N, F), goal (N, G) -> action (N, A) in [-1, 1], log pi(action | s, g) (N,) (None if deterministic)."""
        mean, std = self.distribution(feat, goal, goal_in)
        if deterministic:
            return torch.tanh(mean), None
        u = mean + std * torch.randn_like(mean)  # reparameterised: the actor loss differentiates through the sample
        return torch.tanh(u), tanh_gaussian_log_prob(u, mean, std)

    def act(self, feat, goal):
        """How pi acts in the real environment: the tanh of its mean, Dreamer's evaluation (no random numbers drawn).
        (N, F), (N, G) -> (N, A)."""
        return torch.tanh(self.distribution(feat, goal)[0])


class Critic(nn.Module):
    """V(s, g) on [feat, goal]; goal_dim = 0 gives phase 2's V_ot(s) (goal None)."""

    def __init__(self, cfg, feat_dim, goal_dim):
        super().__init__()
        self.goal_dim = goal_dim
        self.net = mlp(feat_dim + goal_dim, cfg.units, 1, cfg.critic_layers)

    def forward(self, feat, goal):
        """feat (N, ..., F), goal (N, G) or None -> value (N, ...)."""
        assert (goal is None) == (self.goal_dim == 0), "pass a goal exactly when goal_dim > 0"
        if goal is None:
            return self.net(feat).squeeze(-1)
        goal_in = goal_share(self.net[0], goal).reshape(goal.shape[0], *[1] * (feat.dim() - 2), -1)  # over feat's time axes
        return self.net[1:](feat_share(self.net[0], feat) + goal_in).squeeze(-1)


class ReturnNorm(nn.Module):
    """Dreamer V3's return scale max(1, S), S an EMA of the 95th minus the 5th percentile of the lambda-returns."""

    def __init__(self, decay):
        super().__init__()
        self.decay = decay
        self.register_buffer("range", torch.zeros(()))

    def forward(self, returns):
        with torch.no_grad():
            low, high = torch.quantile(returns.detach().flatten(), torch.tensor([0.05, 0.95], device=returns.device))
            self.range.lerp_(high - low, 1 - self.decay)
        return self.range.clamp(min=1.0)


@contextlib.contextmanager
def freeze(*modules):
    """Inside, the parameters of `modules` are constants: what is built there gives them no gradient."""
    params = [p for m in modules for p in m.parameters()]
    flags = [p.requires_grad for p in params]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in zip(params, flags):
            p.requires_grad_(flag)


@torch.no_grad()
def ema_update(slow, fast, rate):
    """slow <- (1 - rate) slow + rate fast, parameter by parameter (the slow critic, Dreamer V3)."""
    for p_slow, p_fast in zip(slow.parameters(), fast.parameters()):
        p_slow.lerp_(p_fast, rate)


def sample_starts(post, n, generator=None):
    """n distinct random posterior states of a batch as imagination starts (all of them if n >= B * T):
    post dict of (B, T, .) -> dict of (n, .), detached, and their flat indices (n,) into B * T."""
    flat = {k: v.detach().flatten(0, 1) for k, v in post.items()}
    index = torch.randperm(len(flat["deter"]), generator=generator)[:n].to(flat["deter"].device)
    return {k: v[index] for k, v in flat.items()}, index


def sample_goals(post_feat, encoded_goal, start_index, is_first, mix, near, generator=None):
    """Goals for pretraining, the choice the paper leaves open (ours). For each start state (flat index into B * T),
    with probability `near` a later frame of its own segment (never across an episode start), the frame it would
    reach by acting as the data did: a goal it can reach and whose -d changes with what it does; otherwise any
    frame of the batch, mostly another episode's (as `near` = 0, our first version, did for all goals). The goal is
    the goal encoder's g = q(s | p_j) with probability `mix` (what phase 2 feeds the frozen policy: GIIL-ZS's
    g = q(s | p_T)), else the world model's posterior feat_j. post_feat, encoded_goal (B, T, F), start_index (n,),
    is_first (B, T) -> (n, F), detached."""
    B, T, _ = post_feat.shape
    assert encoded_goal.shape == post_feat.shape and is_first.shape == (B, T), (post_feat.shape, encoded_goal.shape, is_first.shape)
    n, device = len(start_index), post_feat.device
    rand = lambda *shape: torch.rand(*shape, generator=generator).to(device)
    b, t = start_index // T, start_index % T
    later = t + 1 + (rand(n) * (T - 1 - t)).long()  # uniform in (t, T - 1]; = T where t = T - 1
    part = is_first.long().cumsum(1)  # (B, T): which episode of the segment each step is in
    reachable = (later < T) & (part[b, later.clamp(max=T - 1)] == part[b, t])
    use_near = reachable & (rand(n) < near)
    far = (rand(n) * B * T).long()  # any frame of the batch
    index = torch.where(use_near, b * T + later.clamp(max=T - 1), far)
    from_encoder = rand(n, 1) < mix
    return torch.where(from_encoder, encoded_goal.flatten(0, 1)[index], post_feat.flatten(0, 1)[index]).detach()


def rollout(world_model, actor, start, goal, horizon):
    """Imagine `horizon` steps from start states (dict of (N, .), detached here) with pi(a | s, g)
    -> feat (N, H + 1, F) (index 0 = start), action (N, H, A), log_prob (N, H) of a_k at s_k."""
    start = {k: v.detach() for k, v in start.items()}
    log_probs = []
    goal_in = actor.goal_input(goal)  # once for all steps

    def policy_fn(feat):
        action, log_prob = actor(feat.detach(), goal, goal_in=goal_in)  # the actor reads sg(feat), as Dreamer V1/V2
        log_probs.append(log_prob)
        return action

    states, actions = world_model.imagine(start, policy_fn, horizon)
    return world_model.feat(states), actions, torch.stack(log_probs, 1)


def goal_reward(dist_net, feat, goal):
    """r^goal(s_{k+1}, g) = -d(s_{k+1}, g) on arrival (Sec. 4): feat (N, H + 1, F), goal (N, F) -> (N, H)."""
    goal = goal[:, None].expand(-1, feat.shape[1] - 1, -1)
    return -dist_net(feat[:, 1:], goal)


def lambda_return(reward, value, gamma, lambda_):
    """TD(lambda) targets: reward (N, H) with reward[:, k] = r_{k+1} (on arriving at s_{k+1}), value (N, H + 1)
    with value[:, k] = v_k -> G (N, H), G_k = r_{k+1} + gamma [(1 - lambda) v_{k+1} + lambda G_{k+1}], G_H = v_H."""
    N, H = reward.shape
    assert value.shape == (N, H + 1), (reward.shape, value.shape)
    G, returns = value[:, H], []
    for k in reversed(range(H)):
        G = reward[:, k] + gamma * ((1 - lambda_) * value[:, k + 1] + lambda_ * G)
        returns.append(G)
    return torch.stack(returns[::-1], 1)


def actor_loss(returns, log_prob, return_norm, entropy_scale):  # Eq. 4
    """-E[V_lambda(s_k, g)] over the imagined steps, the lambda-returns (N, H) standing for Eq. 4's values as in
    Dreamer V1, scaled by 1 / max(1, S) (Dreamer V3), minus an entropy bonus estimated by -log pi (N, H)."""
    scale = return_norm(returns)
    objective = (returns / scale).mean()
    entropy = -log_prob.mean()
    loss = -objective - entropy_scale * entropy
    return loss, {"actor_loss": loss.item(), "return": returns.mean().item(), "return_scale": scale.item(), "entropy": entropy.item()}


def critic_loss(critic, feat, goal, returns):  # Eq. 4: V_eta trained with TD(lambda) targets
    """V(s_k, g) for k < H regressed to sg(G_k) (Dreamer V1: a unit Gaussian, 0.5 squared error):
    feat (N, H + 1, F), goal (N, G) or None, returns (N, H) -> (loss, metrics)."""
    goal = None if goal is None else goal.detach()
    value = critic(feat[:, :-1].detach(), goal)  # (N, H)
    loss = 0.5 * ((value - returns.detach()) ** 2).mean()
    return loss, {"critic_loss": loss.item(), "value": value.mean().item()}


def policy_losses(world_model, dist_net, actor, critic, slow_critic, return_norm, start, goal, cfg):  # Eq. 4
    """One update of L_MG (module docstring): start dict of (N, .), goal (N, F) -> actor loss, critic loss, metrics.
    Call ema_update(slow_critic, critic, cfg.slow_critic_rate) after the critic's optimiser step."""
    with freeze(world_model, dist_net, slow_critic):
        feat, _, log_prob = rollout(world_model, actor, start, goal, cfg.horizon)
        reward = goal_reward(dist_net, feat, goal)  # (N, H)
        value = slow_critic(feat, goal)  # (N, H + 1): differentiable in feat, so -G reaches the actions
        returns = lambda_return(reward, value, cfg.gamma, cfg.lambda_)  # (N, H)
    a_loss, a_metrics = actor_loss(returns, log_prob, return_norm, cfg.entropy)
    c_loss, c_metrics = critic_loss(critic, feat, goal, returns)
    return a_loss, c_loss, {**a_metrics, **c_metrics, "reward": reward.mean().item()}


def make_critics(cfg, feat_dim, goal_dim):
    """The critic and its slow copy (a constant: requires_grad False, moved only by ema_update)."""
    critic = Critic(cfg, feat_dim, goal_dim)
    return critic, copy.deepcopy(critic).requires_grad_(False)
