"""The imagination-gap probe of docs/experiments.md (Phase 1, "Eq. 4 beside the cloning, and alone"): does the world
model keep what it promises the actor? The agent runs the benchmark's episodes (its own side-view demos as goals,
g = q(s | p_T), the benchmark's seeds) for the first 115 steps; from its posterior states at t0 = 10, 40, 70, 100 the
same actor is imagined 15 steps towards g (Eq. 4's rollout), and Eq. 4's reward -d(s_k, g), k = 1 .. 15, is averaged
twice: over the imagined states, and over the posterior states of the 15 real steps that followed. Per task and over
all: imagined, real and imagined minus real, mean +- s.e. over episodes. An actor trained on imagination that the
environment does not follow earns more imagined than real reward.
With --uncertainty N, also the disagreement u of world_model.Disagreement (--ac-uncertainty's penalty) on the same imagined
steps, per episode, in units of its mean on D_body's transitions, and the rank correlation over episodes of u with
the gap: does the ensemble see where the world model is wrong? The run's own ensemble where it has one, else one
trained for N updates on the run's frozen world model and D_body.
Run from the repository root:

    python docs/imagination_gap.py runs/stickman_late_s0 runs/stickman_distrl_s0 [--uncertainty 2000]
"""
import argparse
import os
import sys

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402
import train  # noqa: E402
import world_model  # noqa: E402

STARTS, HORIZON = (10, 40, 70, 100), 15


def real_reward(dist_net, feats, goals, t0, horizon):
    """-d(s_k, g) of the real steps k = t0 + 1 .. t0 + horizon, each episode's mean: feats (N, T, F) -> (N,)."""
    return policy.goal_reward(dist_net, feats[:, t0 : t0 + horizon + 1], goals).mean(1)


def imagined_path(models, start, goals, horizon, seed=0):
    """`horizon` steps imagined from `start` (state dict of (N, .)) with the actor's mean action given g, as Eq. 4's
    rollout, the prior's samples z seeded: states (N, H + 1, .), actions (N, H, A)."""
    wm, actor = models["world_model"], models["actor"]
    goal_in = actor.goal_input(goals)
    torch.manual_seed(seed)
    return wm.imagine(start, lambda feat: actor(feat, goals, deterministic=True, goal_in=goal_in)[0], horizon)


@torch.no_grad()
def imagined_reward(models, start, goals, horizon, seed=0):
    """-d(s_k, g) on imagined_path: each episode's mean (N,)."""
    states, _ = imagined_path(models, start, goals, horizon, seed)
    return policy.goal_reward(models["dist_net"], models["world_model"].feat(states), goals).mean(1)


@torch.no_grad()
def imagined_uncertainty(models, ensemble, start, goals, horizon, seed=0):
    """u of world_model.Disagreement on the steps imagined_reward imagines (the same seed, the same path): each episode's
    mean over s_k, a_k, k = 0 .. horizon - 1 (N,)."""
    states, actions = imagined_path(models, start, goals, horizon, seed)
    return ensemble.disagreement(models["world_model"].feat(states)[:, :-1], actions).mean(1)


def train_ensemble(cfgs, models, updates, seed=0):
    """A world_model.Disagreement trained for `updates` updates on the run's frozen world model: its posterior states of
    D_body batches, as train.py trains one beside the world model."""
    wc, wm = cfgs["wm"], models["world_model"]
    data = train.prepare_data(cfgs)[1]
    ensemble = world_model.Disagreement.of(wm)
    opt, rng = torch.optim.Adam(ensemble.parameters(), lr=wc.lr), np.random.default_rng(seed)
    torch.manual_seed(seed)
    for _ in tqdm(range(updates), desc="train the ensemble"):
        batch = data.sample(wc.batch, rng, "cpu")
        with torch.no_grad():
            post, _ = wm.observe(batch[wc.obs], batch["action"], batch["is_first"])
        loss, _ = ensemble.loss(wm.feat(post), batch["action"], world_model.Disagreement.target(wm, batch[wc.obs]), batch["is_first"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(ensemble.parameters(), wc.grad_clip)
        opt.step()
    return ensemble


@torch.no_grad()
def task_gap(models, cfgs, task, episodes=1, ensemble=None):
    """(imagined, real, u) (N,) arrays for the demos of `task`, each the goal of `episodes` episodes, averaged over
    STARTS; u None without an ensemble."""
    body = cfgs["train"].env
    goals = evaluate.demo_goals(models, body, task, cfgs["train"].data, episodes)
    states = []
    env_list = [envs.make_env(body, task) for _ in range(len(goals))]
    evaluate.run_episodes(env_list, models, goals, STARTS[-1] + HORIZON, cfgs["wm"].obs, 30_000, on_state=states.append)
    post = {k: torch.stack([s[k] for s in states], 1) for k in states[0]}  # (N, T, .), t = 0 .. 115
    feats = models["world_model"].feat(post)
    starts = [{k: v[:, t0] for k, v in post.items()} for t0 in STARTS]
    imagined = [imagined_reward(models, start, goals, HORIZON) for start in starts]
    real = [real_reward(models["dist_net"], feats, goals, t0, HORIZON) for t0 in STARTS]
    u = None if ensemble is None else torch.stack([imagined_uncertainty(models, ensemble, start, goals, HORIZON) for start in starts]).mean(0).numpy()
    return torch.stack(imagined).mean(0).numpy(), torch.stack(real).mean(0).numpy(), u


def load(run_dir, unpolished=False):
    """checkpoint.load_run's configs and models; with `unpolished`, the actor as training left it, before cloning.polish's
    cloning steps (the checkpoint keeps it)."""
    cfgs, models, ckpt = checkpoint.load_run(run_dir)
    if unpolished:
        if "actor_unpolished" not in ckpt:
            raise ValueError(f"{run_dir}/checkpoint.pt keeps no unpolished actor: only a run trained with --ac-bc-polish has one (shipped agents do not)")
        models["actor"].load_state_dict(ckpt["actor_unpolished"])
    return cfgs, models


def rank_correlation(x, y):
    """Spearman's rho of two (N,) arrays without ties: Pearson's correlation of their ranks."""
    return float(np.corrcoef(np.argsort(np.argsort(x)), np.argsort(np.argsort(y)))[0, 1])


def rows(run_dir, episodes=1, unpolished=False, uncertainty=0):
    cfgs, models = load(run_dir, unpolished)
    ensemble = None
    if uncertainty:
        ensemble = models["ensemble"] if "ensemble" in models else train_ensemble(cfgs, models, uncertainty)
    cell = lambda x: f"{x.mean():.3f} +- {evaluate.stderr(x):.3f}"
    out, every = [], []
    for task in envs.BODY_TASKS:
        every.append(task_gap(models, cfgs, task, episodes, ensemble))
        imagined, real, u = every[-1]
        out.append(f"| {run_dir} | {task} | {cell(imagined)} | {cell(real)} | {cell(imagined - real)} |" + (f" {cell(u)} |" if ensemble is not None else ""))
    imagined, real = np.concatenate([e[0] for e in every]), np.concatenate([e[1] for e in every])
    out.append(f"| {run_dir} | **all** | {cell(imagined)} | {cell(real)} | **{cell(imagined - real)}** |")
    if ensemble is not None:
        u = np.concatenate([e[2] for e in every])
        out[-1] += f" **{cell(u)}**, rank correlation with the gap {rank_correlation(u, imagined - real):.2f} |"
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="phase-1 run folders (or agents/<body>)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per demo goal")
    parser.add_argument("--unpolished", action="store_true", help="the actor before the cloning polish after training (cloning.polish)")
    parser.add_argument("--uncertainty", type=int, default=0, metavar="N", help="also the ensemble's disagreement u (the run's, "
                        "else one trained for N updates on its frozen world model)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"| run | task | imagined -d, {HORIZON} steps | real -d, the next {HORIZON} steps | imagined minus real |" + (" u |" if args.uncertainty else ""))
    print("|---|---|---|---|---|" + ("---|" if args.uncertainty else ""))
    try:
        for run_dir in args.runs:
            print("\n".join(rows(run_dir, args.episodes, args.unpolished, args.uncertainty)), flush=True)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"error: {error}")
