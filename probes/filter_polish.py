"""Does the polish improve when it clones only the actions that a value fit on real D_body calls better than expected?

The hindsight clone imitates the average of D_body's actions towards a goal; the field's gains on learning-history
data come from cloning the better ones (CRR's binary filter, Wang et al. 2020; filtered BC in OGBench's and WGCSL's
terms). The value is the td reading of a run trained with `--dist-reading td` (distance.py: V(s, g) = -||phi(s) -
phi(g)|| steps to g, an expectile fit by temporal differences along real D_body sequences). For every relabelled step
(cloning.relabel) the advantage is

    A(s_t, a_t, g) = -1 + gamma V(s_{t+1}, g) - V(s_t, g)        (r = -1 per step; > 0: a_t brought g nearer than V expects)

and the polish (cloning.polish: the same batches, goals, steps and seeds) clones only the steps whose A lies in the
top `--keep` share of its batch (1.0: the plain polish). It starts from the run's actor before its polish (the
checkpoint keeps it), runs the benchmark on the run's own start states, and pairs it with the run's own polished
benchmark (goal_reaching.json) by training seed.

    python probes/filter_polish.py runs/walker_td_s0 --keep 0.5 [--out rows.jsonl]
    python probes/filter_polish.py --summary rows.jsonl
"""
import argparse
import json
import re
import sys
import os
from unittest import mock

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import cloning  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import rundir  # noqa: E402


def filtered_bc_loss(dist_net, keep, kept):
    """cloning.bc_loss with each batch's steps of the top `keep` share of A kept (module docstring); appends the
    batch's mean A to `kept`."""
    gamma = dist_net.cfg.gamma

    def loss_fn(actor, post_feat, goal_feat, action, final_goal=None, final_share=0.0):
        (rows, t), goal, a = cloning.relabel(post_feat, goal_feat, action, final_goal, final_share)
        with torch.no_grad():
            phi_goal = dist_net.phi(goal)
            value = lambda s: -(dist_net.phi(post_feat[rows, s]) - phi_goal).norm(dim=-1)  # noqa: E731
            adv = (-1.0 + gamma * value(t + 1) - value(t)).flatten()
            mask = adv >= torch.quantile(adv, 1 - keep)
        feat, goal = post_feat[rows, t].flatten(0, 1)[mask], goal.flatten(0, 1)[mask]
        a = a.flatten(0, 1)[mask].clamp(-0.999, 0.999)
        loss = -actor.log_prob(feat, goal, torch.atanh(a)).mean()
        kept.append(adv.mean().item())
        return loss, {"bc_loss": loss.item()}

    return loss_fn


def summary(rows):
    groups = {}
    for r in rows:
        groups.setdefault((re.sub(r"_s\d+$", "_s*", r["run"]), r["keep"]), []).append(r)
    out = ["| runs | keep | seeds | goal reaching | minus the run's own polish (paired) | per task, minus |", "|---|---|---|---|---|---|"]
    cell = lambda x, sign="": f"{np.mean(x):{sign}.1f}" + (f" +- {evaluate.stderr(x):.1f}" if len(x) > 1 else "")  # noqa: E731
    for (run, keep), g in groups.items():
        tasks = " / ".join(f"{t} {np.mean([r['scores'][t] - r['start_scores'][t] for r in g]):+.1f}" for t in g[0]["scores"])
        out.append(f"| {run} | {keep:g} | {len(g)} | {cell([r['average'] for r in g])} | {cell([r['average'] - r['start_average'] for r in g], '+')} | {tasks} |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="a run trained with --dist-reading td (its checkpoint keeps the actor before the polish)")
    parser.add_argument("--keep", type=float, default=0.5, help="share of each batch's steps cloned, those of the highest A")
    parser.add_argument("--out", help="append the row here (default docs/results/filter_polish_<body>.jsonl)")
    parser.add_argument("--summary", nargs="+", help="print the rows of these files, paired by run, and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary([r for path in args.summary for r in rundir.read_jsonl(path)]))
        return
    if not args.run or not 0 < args.keep <= 1:
        parser.error("give a run, and --keep in (0, 1]")
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as train.py's benchmark computes, so that the run's own scores pair episode for episode
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    if cfgs["dist"].reading != "td" or "actor_unpolished" not in ckpt:
        raise SystemExit(f"{args.run}: needs a run trained with --dist-reading td and a polish (its value and the actor before the polish)")
    models["actor"].load_state_dict(ckpt["actor_unpolished"])
    _, data, _, _ = checkpoint.prepare_data(cfgs)
    mean_adv = []
    with mock.patch.object(cloning, "bc_loss", filtered_bc_loss(models["dist_net"], args.keep, mean_adv)):
        cloning.polish(models, cfgs, data, "cpu")
    tc = cfgs["train"]
    scores = evaluate.goal_reaching(models, cfgs, tc.eval_episodes, tc.eval_steps, envs.BODY_TASKS)
    print("\n".join(evaluate.summary(scores)))
    start = {t: float(np.mean(s["policy"])) for t, s in evaluate.read_goal_reaching(args.run)["scores"].items() if t in envs.BODY_TASKS}
    row = {"run": args.run.rstrip("/"), "weights_id": rundir.weights_id(ckpt), "keep": args.keep, "mean_advantage": float(np.mean(mean_adv)),
           "scores": {t: float(np.mean(s["policy"])) for t, s in scores.items()}, "start_scores": start,
           "average": float(np.mean([np.mean(s["policy"]) for s in scores.values()])), "start_average": float(np.mean(list(start.values())))}
    print(f"goal reaching {row['average']:.1f} against the run's own polish {row['start_average']:.1f}")
    rundir.append_jsonl(args.out or os.path.join("docs", "results", f"filter_polish_{tc.env}.jsonl"), row)


if __name__ == "__main__":
    main()
