"""The behaviour-cloning probe of docs/experiments.md (Phase 1): how far hindsight goal-conditioned behaviour cloning
alone (policy.bc_loss, no Eq. 4) takes a fresh actor on the frozen world model and goal VAE of a trained run, scored
by the goal-reaching benchmark (evaluate.goal_reaching, 1 episode per demo goal). It first prints what the data allow:
the mean normalised score of D_body's expert episodes per task, and for each own side-view demo's last feature p_T
the share of its 200 nearest D_body frames (cosine of p) that come from the same task. Run from the repository root:

    python docs/bc_probe.py runs/walker_bc1_s0 --steps 20000 [--batches 1000] [--final-share 0.5] [--units 256 --layers 2]
"""
import argparse
import dataclasses
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import collect  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402
import train  # noqa: E402


def what_the_data_allow(cfgs):
    tc = cfgs["train"]
    episodes = collect.load_folder(os.path.join(tc.data, tc.env), ("p",))
    p = np.concatenate([e["p"][1:] for e in episodes])
    labels = np.concatenate([[e["task"]] * (len(e["p"]) - 1) for e in episodes])
    for task in evaluate.BODY_TASKS:
        score = np.mean([envs.normalized_score(task, e["return"]) for e in episodes if e["task"] == task])
        demos = collect.load_folder(os.path.join(tc.data, "demos", f"{tc.env}_{task}_side"), ("p",))
        same = np.mean([np.mean(labels[np.argsort(-(p @ d["p"][-1]))[:200]] == task) for d in demos])
        print(f"{task}: D_body expert episodes {score:.1f}; nearest 200 D_body frames of a demo's p_T: {100 * same:.0f}% {task}")

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--steps", type=int, default=20000, help="behaviour-cloning steps (Adam, the actor's lr)")
    parser.add_argument("--batches", type=int, default=1000, help="D_body batches of posterior states, computed once and cycled")
    parser.add_argument("--final-share", type=float, default=0.5, help="bc_loss's share of goals from the episode's last frame")
    parser.add_argument("--units", type=int, default=None)
    parser.add_argument("--layers", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfgs, models, _ = train.load_run(args.run)
    what_the_data_allow(cfgs)
    _, data, _, _ = train.prepare_data(cfgs)
    wm, vae, wc = models["world_model"], models["goal_vae"], cfgs["wm"]
    rng, cache, t0 = np.random.default_rng(0), [], time.time()
    with torch.no_grad():
        for _ in range(args.batches):
            b = data.sample(wc.batch, rng, "cpu")
            post, _ = wm.observe(b[wc.obs], b["action"], b["is_first"])
            cache.append((wm.feat(post), vae.goal(b["p"]), b["action"], vae.goal(b["p_last"])))
    ac = dataclasses.replace(cfgs["ac"], units=args.units or cfgs["ac"].units, actor_layers=args.layers or cfgs["ac"].actor_layers)
    actor = policy.Actor(ac, wm.feat_dim, wm.feat_dim, cache[0][2].shape[-1])
    opt = torch.optim.Adam(actor.parameters(), lr=ac.actor_lr)
    for k in range(args.steps):
        loss, m = policy.bc_loss(actor, *cache[k % len(cache)], args.final_share)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(actor.parameters(), ac.grad_clip)
        opt.step()
        if k % 1000 == 0:
            print(f"step {k}: bc_loss {m['bc_loss']:.3f} ({time.time() - t0:.0f} s)", flush=True)
    models["actor"] = actor
    print("\n".join(evaluate.summary(evaluate.goal_reaching(models, cfgs, 1, 500))))
