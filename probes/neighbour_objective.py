"""Does an objective read from the body's own real D_body episodes rank a cell's candidate goals as their real score does?

Eq. 5's J (the OT reward of imagined rollouts) ranks goals at -0.14 / 0.22 (docs/goal_inference.md); the OT reward of
real rollouts at 0.62 / 0.66, but it needs episodes in the environment. This probe asks whether the agent's own
recorded experience can stand in for those rollouts, with no imagination and no episode run. The policy is a
hindsight clone of D_body: given a goal g, it acts as the D_body episodes that ended near g did. So a goal's objective
is the OT reward (App. C, the demos' features against the episode's, every goal_inference.RETRIEVE_STRIDE-th frame,
online.ot_score: GIIL-online's score) of the k D_body episodes whose final goal q(s | p_T) lies nearest g, averaged.

The candidates and their real scores are those of committed rows, regenerated from their cell's demos:
  ranking rows (fidelity.py --ranking): the 10 demos' zero-shot goals and 10 draws of demo 0's q(s | p_T), 10 episodes
  goal_probe rows (probes/goal_probe.py): the 10 demos' zero-shot goals, 3 episodes
A number is Spearman's rank correlation over a cell's goals between the objective and the real score (the rows' own
ceiling: a ranking row's `cap`). Same-body cells only: the cross-domain cells are the test set.

    python probes/neighbour_objective.py agents/walker docs/results/ranking_walker.jsonl docs/results/goal_probe_walker.jsonl
    python probes/neighbour_objective.py agents/stickman docs/results/goal_probe_stickman.jsonl
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
import fidelity  # noqa: E402
import online  # noqa: E402
import rundir  # noqa: E402
from evaluate import spearman  # noqa: E402
from goal_inference import RETRIEVE_STRIDE  # noqa: E402

KS = (1, 5, 20)  # neighbours averaged


def neighbour_objective(goals, final_goals, episode_score, k):
    """The mean episode_score (N,) of the k D_body episodes whose final goals (N, F) lie nearest each goal (G, F) -> (G,)."""
    nearest = torch.cdist(goals, final_goals).topk(k, largest=False).indices  # (G, k)
    return episode_score[nearest.numpy()].mean(1)


def candidates(vae, demo_p, row):
    """The goals a committed row scored, in its order: (G, F)."""
    zs = vae.goal(torch.as_tensor(demo_p[:, -1]))
    if "spearman" in row:  # fidelity.rank_goals: the demos' goals, then draws of demo 0's posterior
        return torch.cat([zs, fidelity.posterior_goals(vae, demo_p[0, -1], len(row["real"]) - len(zs) + 1, seed=0)[1:]])
    return zs  # probes/goal_probe.py: the demos' goals


def probe(run, rows):
    cfgs, models, _ = checkpoint.load_run(run)
    vae, agent = models["goal_vae"], cfgs["train"].env
    _, body_p, body_last = checkpoint.body_features(cfgs, RETRIEVE_STRIDE)
    with torch.no_grad():
        final_goals = vae.goal(torch.as_tensor(body_last))
    out = []
    for row in rows:
        if row.get("agent", agent) != agent or row["setting"] not in ("SE-SV", "SE-CV"):
            continue
        demo, view = envs.demo_of(agent, row["task"], row["setting"])
        demo_p = np.stack([d["p"] for d in collect.load_folder(checkpoint.demo_folder(cfgs, demo, view), ("p",))])
        with torch.no_grad():
            goals = candidates(vae, demo_p, row)
        real = np.array(row.get("real", row.get("true")))
        assert len(goals) == len(real), (len(goals), len(real))
        score = online.ot_score(body_p, demo_p[:, ::RETRIEVE_STRIDE], configs.OTConfig())  # (N,)
        out.append({"cell": f"{row['setting']} {row['task']}", "goals": len(goals), "cap": row.get("cap"),
                    **{f"k{k}": round(spearman(neighbour_objective(goals, final_goals, score, k), real), 3) for k in KS}})
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("run", help="the agent the rows measured, e.g. agents/walker (its D_body is read)")
    parser.add_argument("rows", nargs="+", help="committed rows of fidelity.py --ranking or probes/goal_probe.py")
    args = parser.parse_args()
    for path in args.rows:
        rows = [r for r in rundir.read_jsonl(path) if r["run"] == args.run]
        found = probe(args.run, rows)
        print(f"\n{path}: Spearman(objective, real score) over each cell's goals, the k nearest D_body episodes' OT reward")
        print("| cell | goals | " + " | ".join(f"k = {k}" for k in KS) + " | cap |\n|---|---|" + "---|" * (len(KS) + 1))
        for r in found:
            print(f"| {r['cell']} | {r['goals']} | " + " | ".join(f"{r[f'k{k}']:.2f}" for k in KS) + f" | {r['cap'] or '-'} |")
        print("| mean | | " + " | ".join(f"**{np.mean([r[f'k{k}'] for r in found]):.2f}**" for k in KS) + " | |")
