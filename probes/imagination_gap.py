"""Phase 1's imagination-gap probe: does the world model keep what it promises the actor (Eq. 4's reward, imagined vs real)?

The imagination-gap probe of docs/ablations.md (Eq. 4 beside the cloning): does the world model keep what it promises
the actor? The agent runs the benchmark's episodes (its own side-view demos as goals,
g = q(s | p_T), the benchmark's seeds) for the first 115 steps; from its posterior states at t0 = 10, 40, 70, 100 the
same actor is imagined 15 steps towards g (Eq. 4's rollout), and Eq. 4's reward -d(s_k, g), k = 1 .. 15, is averaged
twice: over the imagined states, and over the posterior states of the 15 real steps that followed. Per task and over
all: imagined, real and imagined minus real, mean +- s.e. over episodes. An actor trained on imagination that the
environment does not follow earns more imagined than real reward. (Its --uncertainty, the disagreement of the deleted
--ac-uncertainty's ensemble on the same steps, is in the code of commit 5fb4022.) Run from the repository root:

    python probes/imagination_gap.py runs/stickman_late_s0 runs/stickman_distrl_s0
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402

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
def task_gap(models, cfgs, task, episodes=1):
    """(imagined, real) (N,) arrays for the demos of `task`, each the goal of `episodes` episodes, averaged over STARTS."""
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
    return torch.stack(imagined).mean(0).numpy(), torch.stack(real).mean(0).numpy()


def load(run_dir, unpolished=False):
    """checkpoint.load_run's configs and models; with `unpolished`, the actor as training left it, before cloning.polish's
    cloning steps (the checkpoint keeps it)."""
    cfgs, models, ckpt = checkpoint.load_run(run_dir)
    if unpolished:
        if "actor_unpolished" not in ckpt:
            raise ValueError(f"{run_dir}/checkpoint.pt keeps no unpolished actor: only a run trained with --ac-bc-polish has one (shipped agents do not)")
        models["actor"].load_state_dict(ckpt["actor_unpolished"])
    return cfgs, models


def rows(run_dir, episodes=1, unpolished=False):
    cfgs, models = load(run_dir, unpolished)
    cell = lambda x: f"{x.mean():.3f} +- {evaluate.stderr(x):.3f}"
    out, every = [], []
    for task in envs.BODY_TASKS:
        every.append(task_gap(models, cfgs, task, episodes))
        imagined, real = every[-1]
        out.append(f"| {run_dir} | {task} | {cell(imagined)} | {cell(real)} | {cell(imagined - real)} |")
    imagined, real = np.concatenate([e[0] for e in every]), np.concatenate([e[1] for e in every])
    out.append(f"| {run_dir} | **all** | {cell(imagined)} | {cell(real)} | **{cell(imagined - real)}** |")
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="phase-1 run folders (or agents/<body>)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per demo goal")
    parser.add_argument("--unpolished", action="store_true", help="the actor before the cloning polish after training (cloning.polish)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"| run | task | imagined -d, {HORIZON} steps | real -d, the next {HORIZON} steps | imagined minus real |")
    print("|---|---|---|---|---|")
    try:
        for run_dir in args.runs:
            print("\n".join(rows(run_dir, args.episodes, args.unpolished)), flush=True)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"error: {error}")
