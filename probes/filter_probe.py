"""Phase 1's filter probe: does the agent lose goal-reaching points to how the world model filters the real episode?

The filter probe of docs/ablations.md (The actor and how it acts): does the agent lose goal-reaching points to how the
world model filters the real episode? The goal-reaching benchmark's episodes (own side-view demos as goals, 3 episodes per demo,
the benchmark's seeds) with the state the actor reads computed three ways:
  plain    the benchmark's own: one filter over the whole 500-step episode, z_t sampled (evaluate.run_episodes)
  window   the filter restarted at every step over the last W steps only, as training's W-step segments see it: a
           state the actor has been trained on, whatever a long filter drifts to
  mean     one filter over the whole episode with z_t the posterior's mode (a Gaussian's mean) instead of a sample
Run from the repository root:

    python probes/filter_probe.py agents/stickman --data data/late [--window 50] [--mean]
"""
import argparse
import dataclasses
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import rundir  # noqa: E402


@torch.no_grad()
def run_filtered(env_list, models, goals, steps, seed, window=0, mean=False):
    """evaluate.run_episodes' policy episodes, the state filtered over the last `window` steps afresh at every step
    (0: carried over the whole episode), with z_t the posterior's mode if `mean` -> returns (N,)."""
    wm, actor = models["world_model"], models["actor"]
    N = len(env_list)
    torch.manual_seed(seed)
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(env_list)])
    action = np.zeros((N, env_list[0].action_dim), np.float32)
    seen, state, total = [], None, np.zeros(N)
    for t in range(steps + 1):
        seen.append((obs, action))
        if window:  # a segment of the last `window` steps that starts cold, as a training segment does
            o, a = (torch.as_tensor(np.stack(x, 1)) for x in zip(*seen[-window:]))  # (N, <= window, .)
            first = torch.zeros(o.shape[:2], dtype=torch.bool)
            first[:, 0] = True
            post, _ = wm.observe(o, a, first)
        else:
            post, _ = wm.observe(torch.as_tensor(obs)[:, None], torch.as_tensor(action)[:, None], torch.full((N, 1), t == 0), state)
        state = {k: v[:, -1] for k, v in post.items()}
        if mean:
            state["stoch"] = wm.latent.mode(state)
        if t == steps:
            break
        action = actor.act(wm.feat(state), goals).numpy()
        results = [env.step(a) for env, a in zip(env_list, action)]
        obs = np.stack([r[0] for r in results])
        total += [r[1] for r in results]
    return total


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--data", default=None, help="the demos' folder (default: the run's)")
    parser.add_argument("--window", type=int, default=0, help="filter over the last W steps afresh at every step (0: the whole episode)")
    parser.add_argument("--mean", action="store_true", help="z_t the posterior's mode (a Gaussian's mean) instead of a sample")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as the benchmark: the plain reading then gives train.py --evaluate's number
    cfgs, models, _ = checkpoint.load_run(args.run)
    tc = dataclasses.replace(cfgs["train"], data=args.data or cfgs["train"].data)
    if cfgs["wm"].obs != "state":
        raise SystemExit("error: the filter probe reads state observations; this run's world model reads pixels")
    scores = []
    for task in envs.BODY_TASKS:
        goals = evaluate.demo_goals(models, tc.env, task, tc.data, tc.eval_episodes)
        env_list = [envs.make_env(tc.env, task) for _ in range(len(goals))]
        if args.window or args.mean:
            returns = run_filtered(env_list, models, goals, tc.eval_steps, tc.eval_seed, args.window, args.mean)
        else:
            returns, _ = evaluate.run_episodes(env_list, models, goals, tc.eval_steps, "state", tc.eval_seed)
        scores.append([evaluate.episode_score(task, r, tc.eval_steps) for r in returns])
        print(f"{tc.env} {task}: {np.mean(scores[-1]):.1f} +- {evaluate.stderr(scores[-1]):.1f}", flush=True)
    se = np.sqrt(sum(evaluate.stderr(s) ** 2 for s in scores)) / len(scores)  # as evaluate.summary
    print(f"average {np.mean(scores):.1f} +- {se:.1f} (window {args.window}, mean z {args.mean})")
