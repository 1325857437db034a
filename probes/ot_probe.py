"""Phase 2's OT-reward probe: does the imagined OT reward GIIL-FT climbs (Eq. 5) rank goals as the true reward does?

The OT-reward probe of docs/results.md (What limits GIIL-FT): does the imagined OT reward that GIIL-FT climbs (Eq. 5)
rank goals the way the task's true reward does? For each cell of an agent's table it scores candidate goals g by J(g), the
mean per-step OT reward (ot_reward.py) of the frozen policy's imagined rollouts from the cell's demo start states, the
quantity L_GI's returns are made of (same starts and windows for every g):
* task discrimination: the candidates are the zero-shot goals q(s | p_T) of the 10 demos of each of the 4 tasks
  (the cell's demonstrator body and camera); the share of cells whose own task's goals have the highest mean J;
* within a task: Spearman's rank correlation, over the cell's 10 zero-shot goals, between J(g_k) and the real score of
  g_k (the GIIL-ZS rows of the run's results.jsonl, so run the table first).
Run from the repository root:

    python probes/ot_probe.py agents/walker [--starts 64] [--settings SE-SV,SE-CV]
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import collect  # noqa: E402
import configs  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import ot_reward  # noqa: E402
import policy  # noqa: E402
import runner  # noqa: E402


def imagined_ot(models, cfgs, goals, demo_p, starts, seed=0):
    """J(g) for each row of goals (G, F): the mean OT reward of `starts` imagined rollouts per goal from goal-encoder
    states of random demo frames t0, matched against the frames after t0 (as finetune_goal draws them)."""
    ac, vae = cfgs["ac"], models["goal_vae"]
    g = torch.Generator().manual_seed(seed)
    K, M = demo_p.shape[:2]
    t0 = torch.randint(M - ac.horizon - 1, (starts,), generator=g)
    with torch.no_grad():
        start = vae.encode(demo_p[torch.randint(K, (starts,), generator=g), t0])
        start = {k: start[k] for k in models["world_model"].state_keys}
        out = []
        for goal in goals:
            torch.manual_seed(seed)  # the same imagination noise for every goal
            feat, _, _ = policy.rollout(models["world_model"], models["actor"], start, goal.expand(starts, -1), ac.horizon)
            reward, _ = ot_reward.ot_reward(vae.decode(feat[:, 1:]), demo_p, configs.OTConfig(), t0 + 1)
            out.append(reward.mean().item())
    return np.array(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--starts", type=int, default=64, help="imagined rollouts per goal (as each GIIL-FT update)")
    parser.add_argument("--settings", default=",".join(envs.SETTINGS))
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfgs, models, _ = checkpoint.load_run(args.run)
    agent, data = cfgs["train"].env, cfgs["train"].data
    zs = {}
    for r in runner.load_results(args.run):
        if r["method"] == "GIIL-ZS":
            zs[(r["demo"], r["view"], r["seed"])] = r["score"]
    hits, rhos = [], []
    print("cell | J(g) of the goals of each task's demos, mean over 10 (x 1e3) | own task first | Spearman J vs real score (10 ZS goals)")
    for task, where in envs.cells(agent):
        if where not in args.settings.split(","):
            continue
        demo, view = envs.demo_of(agent, task, where)
        body = envs.parse_demo(demo)[0]
        load = lambda t: collect.load_folder(os.path.join(data, "demos", f"{body}_{t}_{view}"), ("p",))
        demo_p = torch.as_tensor(np.stack([d["p"] for d in load(task)]))
        J = {}
        for t in envs.TASKS:
            with torch.no_grad():
                goals = models["goal_vae"].goal(torch.as_tensor(np.stack([d["p"][-1] for d in load(t)])))
            J[t] = imagined_ot(models, cfgs, goals, demo_p, args.starts)
        means = {t: J[t].mean() for t in envs.TASKS}
        hit = max(means, key=means.get) == task
        real = [zs.get((demo, view, k)) for k in range(len(J[task]))]
        rho = evaluate.spearman(J[task], real) if None not in real else float("nan")
        hits.append(hit)
        rhos.append(rho)
        print(f"{where} {task} | " + " ".join(f"{t} {1e3 * means[t]:.2f}" for t in envs.TASKS) + f" | {'yes' if hit else 'no'} | {rho:.2f}")
    print(f"own task's goals ranked first in {sum(hits)} of {len(hits)} cells; mean Spearman {np.nanmean(rhos):.2f} over {np.isfinite(rhos).sum()} cells")


if __name__ == "__main__":
    main()
