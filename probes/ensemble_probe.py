"""Phase 1's ensemble probe: do K hindsight clones acting with their mean action reach goals better than one?

The ensemble probe of docs/ablations.md (The actor and how it acts): do K hindsight clones acting together reach goals
better than one? K fresh actors are cloned (cloning.polish from a fresh actor, --steps each, --batches D_body batches of posterior
states) on the frozen world model and goal VAE of a trained run, clone k with the cloning seed 100 * seed + k; the
goal-reaching benchmark (3 episodes per own side-view demo goal, the benchmark's seeds) then scores clone 0 alone and,
for K > 1, the K clones acting with the mean of their actions. Clone 0 of a longer --steps starts as clone 0 of a
shorter one (same seeds): K = 1 with K times the steps is the equal-compute single clone. With --keep-actor, clone 0 is
the run's own actor and clones 1 .. K - 1 go on cloning from it. Run from the repository root:

    python probes/ensemble_probe.py agents/stickman --data data/s560 --seed 0 --clones 3 --steps 20000
    python probes/ensemble_probe.py agents/stickman --data data/s560 --seed 0 --clones 1 --steps 60000
    python probes/ensemble_probe.py agents/stickman --data data/late --seed 1 --clones 3 --steps 20000 --keep-actor
"""
import argparse
import copy
import dataclasses
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import cloning  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402


class Ensemble(torch.nn.Module):
    """K actors acting together: the mean of their actions (policy.Actor.act each)."""

    def __init__(self, actors):
        super().__init__()
        self.actors = torch.nn.ModuleList(actors)

    def act(self, feat, goal):
        return torch.stack([actor.act(feat, goal) for actor in self.actors]).mean(0)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--data", default=None, help="D_body and demos from this folder instead of the run's (same world model)")
    parser.add_argument("--seed", type=int, default=0, help="clone k's cloning seed is 100 * seed + k")
    parser.add_argument("--clones", type=int, default=3, help="K fresh clones")
    parser.add_argument("--steps", type=int, default=20000, help="cloning steps of each clone")
    parser.add_argument("--batches", type=int, default=1000, help="D_body batches of posterior states, computed once per clone and cycled")
    parser.add_argument("--keep-actor", action="store_true", help="clone 0 is the run's actor, the others go on cloning from it")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as train.py and its benchmark
    cfgs, models, _ = checkpoint.load_run(args.run)
    cfgs["train"] = dataclasses.replace(cfgs["train"], data=args.data or cfgs["train"].data)
    _, data, _, _ = checkpoint.prepare_data(cfgs)
    trained = copy.deepcopy(models["actor"])
    actors = [trained] if args.keep_actor else []
    for k in range(len(actors), args.clones):
        clone_cfgs = {**cfgs, "train": dataclasses.replace(cfgs["train"], seed=100 * args.seed + k),
                      "cloning": dataclasses.replace(cfgs["cloning"], bc_polish=args.steps, bc_polish_batches=args.batches)}
        models["actor"] = copy.deepcopy(trained)
        if not args.keep_actor:  # a fresh actor, seeded from clone k's cloning seed
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(clone_cfgs["train"].seed + 1)
                feat_dim = models["world_model"].feat_dim
                models["actor"] = policy.Actor(cfgs["ac"], feat_dim, feat_dim, models["world_model"].action_dim)
        cloning.polish(models, clone_cfgs, data, "cpu")
        actors.append(copy.deepcopy(models["actor"]))
    arms = [("clone 0", actors[0])] + ([(f"{args.clones} clones", Ensemble(actors))] if args.clones > 1 else [])
    for name, actor in arms:
        models["actor"] = actor
        scores = evaluate.goal_reaching(models, cfgs, 3, 500, tasks=envs.BODY_TASKS)
        means = [np.mean(scores[task]["policy"]) for task in envs.BODY_TASKS]
        print(f"seed {args.seed}, {name}, {args.steps} steps each: " + " / ".join(f"{m:.1f}" for m in means) + f", average {np.mean(means):.1f}")
