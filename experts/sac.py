"""Soft Actor-Critic (Haarnoja et al. 2018) for several tasks at once: the algorithm of the experts (experts/__init__.py).

Every network is an *ensemble*: a stack of per-task weights applied with batched matrix products
(torch.baddbmm), so n tasks cost little more than one in a small-MLP regime dominated by per-call
overhead (fused critics). Each task has its own replay buffer, networks, temperature and
optimiser state; nothing is shared but the matrix multiply. select_tasks and copy_member edit a
training state member by member (stopping experts that are done, restarting one from another).
"""
import math

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


def tanh_gaussian_log_prob(u, mean, std):
    """log pi(tanh(u)) of a tanh-squashed diagonal Gaussian, summed over actions: log N(u; mean, std) minus the tanh
    Jacobian log(1 - tanh(u)^2), written stably (SAC, Haarnoja et al. 2018, App. C). (..., A) -> (...). The expert
    stack keeps its own copy: it never imports GIIL's method files (policy.py has the same function)."""
    log_prob = (-0.5 * ((u - mean) / std) ** 2 - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
    return log_prob - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)


class EnsembleLinear(nn.Module):
    """n independent linear layers applied at once: (n, B, i) -> (n, B, o)."""

    def __init__(self, n, i, o):
        super().__init__()
        bound = 1 / math.sqrt(i)  # nn.Linear's default initialisation, per member
        self.w = nn.Parameter(torch.empty(n, i, o).uniform_(-bound, bound))
        self.b = nn.Parameter(torch.empty(n, 1, o).uniform_(-bound, bound))

    def forward(self, x):
        return torch.baddbmm(self.b, x, self.w)


def ensemble_mlp(n, i, hidden, o):
    return nn.Sequential(EnsembleLinear(n, i, hidden), nn.ReLU(), EnsembleLinear(n, hidden, hidden), nn.ReLU(), EnsembleLinear(n, hidden, o))


class Actor(nn.Module):
    """tanh-squashed Gaussian policy, one member per task."""

    def __init__(self, n, obs_dim, action_dim, hidden):
        super().__init__()
        self.net = ensemble_mlp(n, obs_dim, hidden, 2 * action_dim)

    def forward(self, obs, deterministic=False):
        """obs (n, B, obs_dim) -> action (n, B, A) in [-1, 1] and its log-probability (n, B)."""
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        if deterministic:
            return torch.tanh(mean), None
        std = log_std.clamp(-5, 2).exp()
        u = mean + std * torch.randn_like(mean)
        action = torch.tanh(u)
        return action, tanh_gaussian_log_prob(u, mean, std)


class Critic(nn.Module):
    """Twin Q-functions for n tasks, fused into one ensemble of 2n members."""

    def __init__(self, n, obs_dim, action_dim, hidden):
        super().__init__()
        self.net = ensemble_mlp(2 * n, obs_dim + action_dim, hidden, 1)

    def forward(self, obs, action):
        """(n, B, .) -> (2, n, B): Q1 and Q2."""
        x = torch.cat([obs, action], -1).repeat(2, 1, 1)
        return self.net(x).squeeze(-1).unflatten(0, (2, -1))


class Replay:
    """One fixed-size buffer per task, stored as (n, capacity, .) arrays."""

    def __init__(self, n, capacity, obs_dim, action_dim):
        self.obs = np.zeros((n, capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((n, capacity, obs_dim), np.float32)
        self.action = np.zeros((n, capacity, action_dim), np.float32)
        self.reward = np.zeros((n, capacity), np.float32)
        self.size = 0

    def add(self, obs, action, reward, next_obs):
        i = self.size
        self.obs[:, i], self.action[:, i], self.reward[:, i], self.next_obs[:, i] = obs, action, reward, next_obs
        self.size += 1

    def sample(self, batch, rng):
        idx = rng.integers(0, self.size, size=(len(self.obs), batch))
        take = lambda a: torch.as_tensor(np.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - 2)), axis=1))
        return take(self.obs), take(self.action), take(self.reward), take(self.next_obs)


def sac_update(actor, critic, critic_target, log_alpha, optims, batch, cfg, target_entropy):
    """One SAC step for every task of the ensemble; returns the mean losses."""
    obs, action, reward, next_obs = batch
    alpha = log_alpha.exp().detach()[:, None]  # (n, 1)
    with torch.no_grad():
        next_action, next_log_prob = actor(next_obs)
        target_q = critic_target(next_obs, next_action).min(0).values - alpha * next_log_prob
        target_q = reward + cfg.gamma * target_q  # no terminal states: DMC episodes only time out
    critic_loss = ((critic(obs, action) - target_q) ** 2).mean(dim=(1, 2)).sum()  # sum over members: per-task gradients
    optims["critic"].zero_grad(set_to_none=True)
    critic_loss.backward()
    optims["critic"].step()

    new_action, log_prob = actor(obs)
    q = critic(obs, new_action).min(0).values
    actor_loss = (alpha * log_prob - q).mean(1).sum()
    optims["actor"].zero_grad(set_to_none=True)
    actor_loss.backward()
    optims["actor"].step()

    alpha_loss = (-log_alpha[:, None] * (log_prob.detach() + target_entropy)).mean(1).sum()
    optims["alpha"].zero_grad(set_to_none=True)
    alpha_loss.backward()
    optims["alpha"].step()

    with torch.no_grad():
        for p, p_target in zip(critic.parameters(), critic_target.parameters()):
            p_target.lerp_(p, cfg.tau)
    n = len(log_alpha)
    return critic_loss.item() / n, actor_loss.item() / n


def select_tasks(state, keep):
    """A training checkpoint restricted to the tasks at positions `keep`: resuming with fewer --tasks stops
    the experts that are done, and the others go on faster (every ensemble tensor is sliced per member)."""
    n, rows = len(state["tasks"]), torch.tensor(keep)
    critic_rows = torch.cat([rows, rows + n])  # the fused twin critics: Q1 members, then Q2 members
    for name, r in (("actor", rows), ("critic", critic_rows), ("critic_target", critic_rows)):
        state[name] = {k: v[r] for k, v in state[name].items()}
    state["log_alpha"] = state["log_alpha"][rows]
    for name, r in (("actor", rows), ("critic", critic_rows), ("alpha", rows)):
        for adam in state["optim_" + name]["state"].values():
            adam["exp_avg"], adam["exp_avg_sq"] = adam["exp_avg"][r], adam["exp_avg_sq"][r]
    state["replay"] = {k: v[keep] for k, v in state["replay"].items()}
    state["tasks"] = [state["tasks"][i] for i in keep]
    return state


def copy_member(pairs, tasks, actor, critic, critic_target, log_alpha, optims):
    """Restart experts from others: for each "dst=src", task dst takes task src's networks, temperature
    and Adam moments, and goes on learning with its own reward and replay. Used for stickman stand,
    whose SAC settled on kneeling upright: the walk expert already stands (dm_control's stand
    reward does not penalise moving), so it is a better start than a fresh network."""
    n = len(tasks)
    with torch.no_grad():
        for pair in pairs:
            dst, _, src = pair.partition("=")
            if dst not in tasks or src not in tasks:
                raise ValueError(f"--warm-start {pair}: both tasks must be among --tasks ({' '.join(tasks)})")
            d, s = tasks.index(dst), tasks.index(src)
            twin = [(d, s), (d + n, s + n)]  # critics stack the Q1 members, then the Q2 members
            for module, rows, optim in ((actor, [(d, s)], optims["actor"]), (critic, twin, optims["critic"]), (critic_target, twin, None)):
                for p in module.parameters():
                    moments = optim.state.get(p, {}) if optim else {}
                    for to, frm in rows:
                        p[to] = p[frm]
                        for key in ("exp_avg", "exp_avg_sq"):
                            if key in moments:
                                moments[key][to] = moments[key][frm]
            log_alpha[d] = log_alpha[s]
            print(f"warm start: {dst} restarts from {src}")
