"""Does AIME-NoB's OT reward rank its own episodes as the task does? baselines/aime_nob.py keeps, in each seed's training state
(runs/<name>/baselines/AIME-NoB_<demo>_<view>_s<seed>_*.pt), a log of every episode it collected: the sum of its OT
labels (what the agent is trained to raise) and its task return (never shown to the agent). Per seed: Spearman's rank
correlation of the two over the seed's episodes, and the task return of its first and last 10 episodes. A reward that
identifies the task ranks them alike (correlation near 1); near 0 or below, more interaction cannot help.
--body (stand cells): the same OT sum (unscaled) of the run's D_body episodes against the cell's demos, by the policy
that collected them, beside their stand return (read off the torso's posture, envs.observed_posture): does the reward
rank far apart behaviour right where it ranks the agent's own episodes wrong?

    python probes/aime_reward.py runs/<name> walker_stand side [--body]
"""
import argparse
import glob
import os
import re
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import collect  # noqa: E402
import configs  # noqa: E402
import envs  # noqa: E402
from baselines import genrl  # noqa: E402
import ot_reward  # noqa: E402
import rundir  # noqa: E402
from evaluate import spearman  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("run")
    parser.add_argument("demo")
    parser.add_argument("view", choices=envs.VIEWS)
    parser.add_argument("--body", action="store_true", help="also D_body's episodes by source (stand cells only; ~7 CPU-minutes)")
    args = parser.parse_args()
    if args.body and not args.demo.endswith("_stand"):
        parser.error("--body needs a stand cell: only the stand return is read off a state")
    paths = sorted(glob.glob(os.path.join(args.run, "baselines", f"AIME-NoB_{args.demo}_{args.view}_s*_*.pt")))
    if not paths:
        raise ValueError(f"no AIME-NoB training state of {args.demo} ({args.view} view) in {args.run}/baselines: run baselines/aime_nob.py on that cell first")
    print(f"{args.demo} ({args.view} view) | env steps | episodes | Spearman(OT sum, task return) | task return: first 10 / last 10")
    for path in paths:
        state = rundir.load_checkpoint(path)
        ot, task = (np.array([e[k] for e in state["log"]]) for k in ("ot_sum", "task_return"))
        seed = re.search(r"_s(\d+)_[0-9a-f]+\.pt$", path).group(1)
        print(f"seed {seed} | {state['done']} | {len(task)} | {spearman(ot, task):+.2f} | {task[:10].mean():.0f} / {task[-10:].mean():.0f}")
    if args.body:
        cell = genrl.load_cell(args.run, args.demo, args.view)
        demo_p = torch.as_tensor(np.stack([d["p"] for d in cell["demos"]]))
        tc = cell["cfgs"]["train"]
        body = collect.load_folder(os.path.join(tc.data, tc.env), ("p", "state"))
        ot = np.concatenate([ot_reward.ot_reward(torch.as_tensor(np.stack([e["p"] for e in body[i:i + 40]])), demo_p, configs.OTConfig())[0].sum(1).numpy()
                             for i in range(0, len(body), 40)])
        stand = np.array([envs.observed_posture(tc.env, e["state"]).sum() for e in body])
        source = np.array([str(e["task"]) for e in body])
        print("D_body by source | episodes | stand return | OT sum | Spearman within")
        for name in sorted(set(source)):
            m = source == name
            print(f"{name} | {m.sum()} | {stand[m].mean():.0f} | {ot[m].mean():.3f} +- {ot[m].std():.3f} | {spearman(ot[m], stand[m]):+.2f}")
        print(f"all | {len(body)} | {stand.mean():.0f} | {ot.mean():.3f} | {spearman(ot, stand):+.2f}")


if __name__ == "__main__":
    rundir.run_main(main, "nothing is written")
