"""Beside Eq. 4 (L_MG), ours: hindsight goal-conditioned behaviour cloning of D_body's actions (GCSL, Ghosh et al. 2021).

Not in the paper: on a CPU budget Eq. 4 alone did not learn to reach goals (README, "Deviations from the paper";
docs/ablations.md, Phase 1), so the actor's loss also clones D_body's own actions towards hindsight goals:
  bc_loss            -log pi(a_t | s_t, g), g the goal encoder's state of a later frame of
                     the same segment or of the episode's last frame
  advantage_weights  optional per-action weights exp(beta A) under Eq. 4's critic (AWR; --ac-bc-awr, not kept)
  polish             cloning steps on the frozen final world model after training (--ac-bc-polish)
train.py adds ac.bc * bc_loss to Eq. 4's actor loss (policy.policy_losses) and takes ac.bc_steps - 1 more cloning
steps per update; imitate.py does the same while the policy is finetuned jointly (Sec. 4).
"""
import copy

import numpy as np
import torch
from tqdm import tqdm

import policy


AWR_MAX = 20.0  # the largest weight advantage_weights gives, before normalising (AWR, Peng et al. 2019)


def advantage_weights(critic, dist_net, feat, next_feat, goal, gamma, beta):
    """Weights of advantage-weighted cloning (ours, --ac-bc-awr; AWR, Peng et al. 2019; for hindsight goals WGCSL,
    Yang et al. 2022): D_body's action a_t from s_t is scored by its one-step advantage under the actor's own value,
    A = r^goal(s_{t+1}, g) + gamma V(s_{t+1}, g) - V(s_t, g), with r^goal = -d (Sec. 4) and V the critic of Eq. 4, so
    actions that bring the goal nearer than the actor would are cloned more: a step of policy improvement beyond the
    data's average. A is standardised over the batch (its scale, ~1/(1 - gamma) times d's, moves during training), the
    weights exp(beta * A) are clipped at AWR_MAX and divided by their mean, so the loss keeps its scale.
    feat, next_feat (N, F) s_t and s_{t+1}, goal (N, F) -> (N,), no gradient."""
    with torch.no_grad():
        adv = -dist_net(next_feat, goal) + gamma * critic(next_feat, goal) - critic(feat, goal)
        adv = (adv - adv.mean()) / (adv.std() + 1e-6)
        weight = torch.exp(beta * adv).clamp(max=AWR_MAX)
        return weight / weight.mean()


def bc_loss(actor, post_feat, goal_feat, action, final_goal=None, final_share=0.0, weigh=None):
    """Hindsight goal-conditioned behaviour cloning (ours, a deviation; GCSL, Ghosh et al. 2021): D_body has no task
    labels, but each of its actions a_t reaches what its own episode shows later, so -log pi(a_t | s_t, g) with g the
    goal encoder's state of a later frame of the same segment, for every step t of every segment (each with its own
    random later frame); with probability final_share, g is instead final_goal, the goal of the episode's last frame
    (what evaluation and GIIL-ZS feed the policy: a standing expert's last frame is then the goal of its getting up).
    post_feat (B, T, F) posterior feats, goal_feat (B, T, F) goal-encoder goals of every frame, final_goal (B, F),
    action (B, T, A) with action[:, t] = a_{t-1} (world_model.py's alignment). weigh: None (every action counts the
    same), or (s_t, s_{t+1}, g) (N, F) each -> per-action weights (N,), e.g. advantage_weights."""
    B, T, _ = post_feat.shape
    device = post_feat.device
    t = torch.arange(T - 1, device=device).expand(B, -1)  # (B, T - 1): s_t, acted on with a_t = action[:, t + 1]
    later = t + 1 + (torch.rand(B, T - 1, device=device) * (T - 1 - t)).long()  # a frame in (t, T - 1]
    rows = torch.arange(B, device=device)[:, None].expand(-1, T - 1)
    goal = goal_feat[rows, later]  # (B, T - 1, F)
    if final_share > 0:
        final = torch.rand(B, T - 1, 1, device=device) < final_share
        goal = torch.where(final, final_goal[:, None].expand_as(goal), goal)
    feat, goal = post_feat[rows, t].flatten(0, 1).detach(), goal.flatten(0, 1).detach()
    a = action[rows, t + 1].flatten(0, 1).clamp(-0.999, 0.999)  # tanh is never exactly +-1
    log_prob = actor.log_prob(feat, goal, torch.atanh(a))
    if weigh is None:
        loss = -log_prob.mean()
        return loss, {"bc_loss": loss.item()}
    weight = weigh(feat, post_feat[rows, t + 1].flatten(0, 1).detach(), goal)
    loss = -(weight * log_prob).mean()
    return loss, {"bc_loss": -log_prob.mean().item(), "bc_weight_max": weight.max().item()}


def weigh(models, ac):
    """bc_loss's per-action weights: advantage-weighted cloning when --ac-bc-awr > 0 (advantage_weights, with
    the slow critic, the one Eq. 4's targets come from), else None (plain cloning)."""
    if not ac.bc_awr:
        return None
    return lambda feat, next_feat, goal: advantage_weights(models["slow_critic"], models["dist_net"], feat, next_feat, goal, ac.gamma, ac.bc_awr)


def polish(models, cfgs, data, device):
    """After the last update, ac.bc_polish steps of hindsight behaviour cloning (bc_loss) of the actor alone on
    the frozen final world model and goal VAE (ours): during training the actor clones from posterior states that the
    world model still moves, and cloning on the final ones raised goal reaching (docs/ablations.md, Phase 1). With
    ac.bc_polish_fresh the actor is first initialised afresh (models["actor"] is replaced). The posterior states of
    ac.bc_polish_batches D_body batches are computed once and cycled, each step with fresh hindsight goals; a fresh
    Adam at the actor's lr, and RNGs of its own, so that the training's (in the checkpoint) are untouched. With
    ac.bc_polish_ema the actor kept is the moving average of the steps' weights; returns the last step's state_dict
    then (None otherwise)."""
    wc, ac, tc = cfgs["wm"], cfgs["ac"], cfgs["train"]
    wm, vae = models["world_model"], models["goal_vae"]
    rng, cache = np.random.default_rng([tc.seed, 1]), []
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        torch.manual_seed(tc.seed + 1)
        if ac.bc_polish_fresh:
            models["actor"] = policy.Actor(ac, wm.feat_dim, wm.feat_dim, data.data["action"].shape[-1], wm.decoder).to(device)
        for _ in range(min(ac.bc_polish_batches, ac.bc_polish)):
            b = data.sample(wc.batch, rng, device)
            post, _ = wm.observe(b[wc.obs], b["action"], b["is_first"])
            cache.append((wm.feat(post), vae.goal(b["p"]), b["action"], vae.goal(b["p_last"])))
    actor = models["actor"]
    opt = torch.optim.Adam(actor.parameters(), lr=ac.actor_lr)
    average = copy.deepcopy(actor).requires_grad_(False) if ac.bc_polish_ema else None
    weights = weigh(models, ac)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(tc.seed + 2)
        for k in tqdm(range(ac.bc_polish), desc="polish the actor (behaviour cloning on the final world model)"):
            loss, m = bc_loss(actor, *cache[k % len(cache)], ac.bc_final, weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(actor.parameters(), ac.grad_clip)
            opt.step()
            if average is not None:
                policy.ema_update(average, actor, 1 - ac.bc_polish_ema)
    print(f"polished the actor: {ac.bc_polish} cloning steps on the final world model, bc_loss {m['bc_loss']:.3f}")
    if average is None:
        return None
    last = copy.deepcopy(actor.state_dict())
    actor.load_state_dict(average.state_dict())
    return last
