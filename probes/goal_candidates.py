"""Which candidate goals could a search on real rollouts choose among: their spread and their best, by the true score.

GIIL-online (online.py) chooses among the 10 demos' zero-shot goals, whose scores hardly differ (goal_variance.py: a
goal s.d. of 3-5 points against an episode's 24-26): even the truly best of them adds little. This probe measures, on
a cell, candidate sets a search could draw instead, each of 10 goals, all run with the frozen policy from the same
start states and scored by the environment's task return (the true score, Eq. 8; a probe may read it, GIIL-online
never does):
  zs       the 10 demos' zero-shot goals q(s | p_T) (what GIIL-online searches now)
  q x1     10 samples of demo 0's goal distribution: mean + std * eps (the goal encoder's own uncertainty)
  q x2     the same at twice the std (a categorical z: its noise doubled, flatter draws)
  mix      10 random convex combinations of the 10 zero-shot goals (Dirichlet(1) weights)
Each candidate runs `episodes` episodes from shared start states (seeds A). The best of each set on A is then run
again from fresh start states (seeds B) beside demo 0's zero-shot goal (GIIL-ZS (demo 0), GIIL-online's start):
their paired difference on B is what a search that ranked this set perfectly would gain, free of the winner's curse.

    python probes/goal_candidates.py --run agents/walker --demo walker_walk --view side --out rows.jsonl
    python probes/goal_candidates.py --table rows.jsonl [more.jsonl ...]
    python probes/goal_candidates.py --paired docs/results/online_*.jsonl   # GIIL-online: posterior vs demos candidates

Which scorer of real episodes ranks these goals: probes/scorers.py.
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # goal_variance.py beside it, also when imported from elsewhere
import checkpoint  # noqa: E402
import collect  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import fidelity  # noqa: E402
import rundir  # noqa: E402
from goal_variance import split  # noqa: E402

SEEDS_A, SEEDS_B = 70_000, 80_000  # start states of the sets' runs and of the re-runs (neither GIIL-FT's nor online.py's)


@torch.no_grad()
def candidate_sets(vae, demo_p, n=10, seed=0):
    """{name: (n, F) goals} of the module docstring; demo_p (K, M, D) the cell's demos."""
    gen = torch.Generator().manual_seed(seed)
    last = torch.as_tensor(np.stack([p[-1] for p in demo_p]))
    zs = vae.goal(last)
    weights = torch.from_numpy(np.random.default_rng(seed).dirichlet(np.ones(len(zs)), n)).float()
    return {"zs": zs[:n], "q x1": fidelity.sample_goals(vae, last[:1], n, gen),
            "q x2": fidelity.sample_goals(vae, last[:1], n, gen, scale=2.0), "mix": weights @ zs}


@torch.no_grad()
def scores(models, cfgs, task, goals, episodes, seed_base):
    """(len(goals), episodes) true scores: episode e of every goal from env seed seed_base + e."""
    out = []
    for e in range(episodes):
        env_list = [envs.make_env(cfgs["train"].env, task) for _ in goals]
        returns, _ = evaluate.run_episodes(env_list, models, goals, envs.EPISODE_STEPS, cfgs["wm"].obs, [seed_base + e] * len(goals))
        out.append([evaluate.episode_score(task, r, envs.EPISODE_STEPS) for r in returns])
        for env in env_list:
            env.close()
    return np.array(out).T


def probe(run, demo, view, episodes, out):
    cfgs, models, _ = checkpoint.load_run(run, "cpu")
    torch.set_num_threads(1)
    rundir.fast_matmul()
    task = envs.parse_demo(demo)[1]
    demo_p = [d["p"] for d in collect.load_folder(checkpoint.demo_folder(cfgs, demo, view), ("p",))]
    sets = candidate_sets(models["goal_vae"], demo_p)
    rows = []
    for name, goals in sets.items():
        a = scores(models, cfgs, task, goals, episodes, SEEDS_A)
        best = int(np.argmax(a.mean(1)))
        b = scores(models, cfgs, task, torch.stack([goals[best], sets["zs"][0]]), episodes, SEEDS_B)
        g, e, rel = split(a.tolist())
        row = dict(agent=cfgs["train"].env, demo=demo, view=view, set=name, episodes=episodes, scores_a=a.tolist(), best=best,
                   best_b=b[0].tolist(), zs0_b=b[1].tolist(), goal_sd=g, episode_sd=e, reliability=rel)
        rundir.append_jsonl(out, row)
        rows.append(row)
        print(f"{demo} {view} {name:5s}: mean {a.mean():5.1f} goal sd {g:4.1f} | best on A {a[best].mean():5.1f} -> on B "
              f"{b[0].mean():5.1f} against ZS (demo 0) {b[1].mean():5.1f}")
    return rows


def table(rows):
    """Markdown: per agent and set, the mean over cells of the set's mean, goal s.d., and the paired gain on B."""
    lines = ["| agent | candidates | cells | mean score | goal s.d. | best on A, re-run on B | ZS (demo 0) on B | paired gain +- s.e. |",
             "|---|---|---|---|---|---|---|---|"]
    for agent in sorted({r["agent"] for r in rows}):
        for name in dict.fromkeys(r["set"] for r in rows):
            sel = [r for r in rows if r["agent"] == agent and r["set"] == name]
            if not sel:
                continue
            gain = [np.mean(r["best_b"]) - np.mean(r["zs0_b"]) for r in sel]
            lines.append(f"| {agent} | {name} | {len(sel)} | {np.mean([np.mean(r['scores_a']) for r in sel]):.1f} | "
                         f"{np.mean([r['goal_sd'] for r in sel]):.1f} | {np.mean([np.mean(r['best_b']) for r in sel]):.1f} | "
                         f"{np.mean([np.mean(r['zs0_b']) for r in sel]):.1f} | {np.mean(gain):+.1f} +- {evaluate.stderr(gain):.1f} |")
    return "\n".join(lines)


def paired(rows):
    """Markdown: GIIL-online with each kind of candidates on the cells the 'posterior' rows cover, paired by cell and
    seed with GIIL-ZS (demo 0) and with GIIL-online on the demos' goals (rows of imitate.py --online)."""
    key = lambda r: (r["agent"], r["setting"], r["task"], r["seed"])
    zs0 = {key(r): r["score"] for r in rows if r["method"] == "GIIL-ZS (demo 0)"}
    online = [r for r in rows if r["method"] == "GIIL-online"]
    kind = lambda r: r["config"].get("candidates", "demos")
    demos = {key(r): r["score"] for r in online if kind(r) == "demos"}
    lines = ["| agent | cells | posterior candidates | - ZS (demo 0), paired | - GIIL-online on the demos' goals, paired |", "|---|---|---|---|---|"]
    for agent in sorted({r["agent"] for r in online if kind(r) == "posterior"}):
        post = [r for r in online if kind(r) == "posterior" and r["agent"] == agent]
        d0 = [r["score"] - zs0[key(r)] for r in post]
        dd = [r["score"] - demos[key(r)] for r in post]
        cells = sorted({f"{r['setting']} {r['task']}" for r in post})
        lines.append(f"| {agent} | {', '.join(cells)} ({len(post)} pairs) | {np.mean([r['score'] for r in post]):.1f} +- "
                     f"{evaluate.stderr([r['score'] for r in post]):.1f} | {np.mean(d0):+.1f} +- {evaluate.stderr(d0):.1f} | "
                     f"{np.mean(dd):+.1f} +- {evaluate.stderr(dd):.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("--run")
    parser.add_argument("--demo", nargs="+", help="e.g. walker_walk walker_run")
    parser.add_argument("--view", default="side", choices=envs.VIEWS)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--out", help="JSONL the rows are appended to")
    parser.add_argument("--table", nargs="+", metavar="JSONL", help="print the markdown table of these rows, then exit")
    parser.add_argument("--paired", nargs="+", metavar="JSONL", help="GIIL-online rows (imitate.py): posterior against demos candidates")
    args = parser.parse_args()
    if args.table:
        print(table([row for path in args.table for row in rundir.read_jsonl(path)]))
    elif args.paired:
        print(paired([row for path in args.paired for row in rundir.read_jsonl(path)]))
    elif not (args.run and args.demo and args.out):
        parser.error("pass --run, --demo and --out (or --table)")
    else:
        for demo in args.demo:
            probe(args.run, demo, args.view, args.episodes, args.out)
