"""Phase 1's cloning probe: how far hindsight behaviour cloning alone takes a fresh actor on a trained world model.

The behaviour-cloning probe of docs/results.md (What the actors are): how far hindsight goal-conditioned behaviour
cloning alone (cloning.bc_loss, no Eq. 4) takes a fresh actor on the frozen world model and goal VAE of a trained run, scored
by the goal-reaching benchmark (evaluate.goal_reaching, --episodes per demo goal). It first prints what the data
allow: the mean normalised score of D_body's expert episodes per task, and for each own side-view demo's last feature
p_T the share of its 200 nearest D_body frames (cosine of p) that come from the same task. Run from the repository root:

    python probes/bc_probe.py runs/walker_bc1_s0 --steps 20000 [--batches 1000] [--final-share 0.5] [--units 256 --layers 2]
        [--keep-actor] [--data DIR] [--episodes 3] [--seed N]
"""
import argparse
import dataclasses
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import cloning  # noqa: E402
import collect  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402


def what_the_data_allow(cfgs):
    tc = cfgs["train"]
    episodes = collect.load_folder(os.path.join(tc.data, tc.env), ("p",))
    p = np.concatenate([e["p"][1:] for e in episodes])
    labels = np.concatenate([[e["task"]] * (len(e["p"]) - 1) for e in episodes])
    for task in envs.BODY_TASKS:
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
    parser.add_argument("--data", default=None, help="D_body and demos from this folder instead of the run's (same world model)")
    parser.add_argument("--episodes", type=int, default=1, help="benchmark episodes per demo goal (the benchmark's own: 3)")
    parser.add_argument("--seed", type=int, default=None, help="the cloning's seeds (fresh actor, batches; default: the run's)")
    parser.add_argument("--keep-actor", action="store_true", help="go on from the run's trained actor instead of a fresh one")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfgs, models, _ = checkpoint.load_run(args.run)
    cfgs["train"] = dataclasses.replace(cfgs["train"], data=args.data or cfgs["train"].data,
                                        seed=cfgs["train"].seed if args.seed is None else args.seed)
    what_the_data_allow(cfgs)
    _, data, _, _ = checkpoint.prepare_data(cfgs)
    ac = dataclasses.replace(cfgs["ac"], units=args.units or cfgs["ac"].units, actor_layers=args.layers or cfgs["ac"].actor_layers)
    cc = dataclasses.replace(cfgs["cloning"], bc_polish=args.steps, bc_polish_batches=args.batches, bc_final=args.final_share)
    if not args.keep_actor:  # a fresh actor, seeded from the cloning's seed
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfgs["train"].seed + 1)
            models["actor"] = policy.Actor(ac, models["world_model"].feat_dim, models["world_model"].feat_dim, models["world_model"].action_dim)
    cloning.polish(models, {**cfgs, "ac": ac, "cloning": cc}, data, "cpu")  # the cloning steps, as train.py's polish runs them
    print("\n".join(evaluate.summary(evaluate.goal_reaching(models, cfgs, args.episodes, 500))))
