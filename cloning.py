"""Beside Eq. 4 (L_MG), ours: hindsight goal-conditioned behaviour cloning of D_body's actions (GCSL, Ghosh et al. 2021).

Not in the paper: on a CPU budget Eq. 4 alone did not learn to reach goals (README, "Deviations from the paper";
docs/ablations.md, Phase 1), so the actor's loss also clones D_body's own actions towards hindsight goals:
  bc_loss  -log pi(a_t | s_t, g), g the goal encoder's state of a later frame of the same segment or of the
           episode's last frame
  polish   cloning steps on the frozen final world model after training (--ac-bc-polish)
train.py adds bc * bc_loss to Eq. 4's actor loss (policy.policy_losses) and takes bc_steps - 1 more cloning steps per
update (configs.CloningConfig; its flags are --ac-bc...: a term of the actor's loss).
"""

import numpy as np
import torch
from tqdm import tqdm

import rundir


def relabel(post_feat, goal_feat, action, final_goal=None, final_share=0.0):
    """GCSL's hindsight relabelling (Ghosh et al. 2021) of D_body segments: D_body has no task labels, but each of its
    actions a_t reaches what its own episode shows later, so each step t of every segment is paired with the goal
    encoder's state of a random later frame of the same segment; with probability final_share with final_goal instead,
    the goal of the episode's last frame (what evaluation and GIIL-ZS feed the policy: a standing expert's last frame is
    then the goal of its getting up). post_feat (B, T, F) posterior feats, goal_feat (B, T, F) goal-encoder goals of
    every frame, final_goal (B, F), action (B, T, A) with action[:, t] = a_{t-1} (world_model.py's alignment)
    -> (rows, t) indices (B, T - 1) of the states s_t, their goals (B, T - 1, F), their actions a_t (B, T - 1, A)."""
    B, T, _ = post_feat.shape
    device = post_feat.device
    t = torch.arange(T - 1, device=device).expand(B, -1)  # (B, T - 1): s_t, acted on with a_t = action[:, t + 1]
    later = t + 1 + (torch.rand(B, T - 1, device=device) * (T - 1 - t)).long()  # a frame in (t, T - 1]
    rows = torch.arange(B, device=device)[:, None].expand(-1, T - 1)
    final = torch.rand(B, T - 1, 1, device=device) < final_share if final_share > 0 else None
    goal = goal_feat[rows, later] if final is None else torch.where(final, final_goal[:, None], goal_feat[rows, later])
    return (rows, t), goal, action[rows, t + 1]


def bc_loss(actor, post_feat, goal_feat, action, final_goal=None, final_share=0.0):
    """Hindsight goal-conditioned behaviour cloning (ours, a deviation; GCSL, Ghosh et al. 2021): -log pi(a_t | s_t, g)
    for every step of every segment, g relabelled (relabel's arguments)."""
    (rows, t), goal, a = relabel(post_feat, goal_feat, action, final_goal, final_share)
    feat, goal = post_feat[rows, t].flatten(0, 1).detach(), goal.flatten(0, 1).detach()
    a = a.flatten(0, 1).clamp(-0.999, 0.999)  # tanh is never exactly +-1
    loss = -actor.log_prob(feat, goal, torch.atanh(a)).mean()
    return loss, {"bc_loss": loss.item()}


def polish(models, cfgs, data, device):
    """After the last update, bc_polish steps of hindsight behaviour cloning (bc_loss) of the actor alone on
    the frozen final world model and goal VAE (ours): during training the actor clones from posterior states that the
    world model still moves, and cloning on the final ones raised goal reaching (docs/ablations.md, Phase 1). The
    posterior states of bc_polish_batches D_body batches are computed once and cycled, each step with fresh
    hindsight goals; a fresh Adam at the actor's lr, and RNGs of its own, so that the training's (in the checkpoint)
    are untouched."""
    wc, ac, cc, tc = cfgs["wm"], cfgs["ac"], cfgs["cloning"], cfgs["train"]
    wm, vae, actor = models["world_model"], models["goal_vae"], models["actor"]
    rng, cache = np.random.default_rng([tc.seed, 1]), []
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        torch.manual_seed(tc.seed + 1)
        for _ in range(min(cc.bc_polish_batches, cc.bc_polish)):
            b = data.sample(wc.batch, rng, device)
            post, _ = wm.observe(b[wc.obs], b["action"], b["is_first"])
            feat, goal, final = wm.feat(post), vae.goal(b["p"]), vae.goal(b["p_last"])
            cache.append((feat, goal, b["action"], final))
    opt = torch.optim.Adam(actor.parameters(), lr=ac.actor_lr)
    stop = lambda: f"the checkpoint keeps the actor before the polish (a learning rate too high? --ac-actor-lr is {ac.actor_lr})"
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(tc.seed + 2)
        for k in tqdm(range(cc.bc_polish), desc="polish the actor (behaviour cloning on the final world model)"):
            feat, goal, action, final = cache[k % len(cache)]
            loss, m = bc_loss(actor, feat, goal, action, final, cc.bc_final)
            rundir.checked_step(opt, loss, "the polish's behaviour-cloning loss", k, stop, ac.grad_clip)
    print(f"polished the actor: {cc.bc_polish} cloning steps on the final world model, bc_loss {m['bc_loss']:.3f}")
