"""How much of a cell's score is the goal's, and how much the episode's: the ceiling of any goal inference.

From the GIIL-ZS rows of a run's results (each of a cell's 10 demos' zero-shot goals, 3 episodes from its own start
states, `episode_scores`), a one-way random-effects split of the score's variance (Snedecor & Cochran): the episode
variance e^2 is the mean within-goal variance; the goal variance g^2 = var(goal means) - e^2 / n, floored at 0. Then
* reliability r = g^2 / (g^2 + e^2 / n): the share of the spread of n-episode goal means that is the goal's; an
  objective that knows each goal's true quality exactly correlates with n-episode scores at most sqrt(r);
* the gain of choosing the best of the 10 goals, were it known: ~1.54 g (the mean of the largest of 10 normals).
With GIIL-online rows, also the rank correlation of their first round's OT scores (one episode per goal, online.py)
with the goals' GIIL-ZS scores, which come from other start states: how well one real episode ranks the goals.

    python probes/goal_variance.py runs/walker_online/results.jsonl [more.jsonl ...]
    python probes/goal_variance.py --benchmark runs/<run> [...]     the same of phase 1's goal-reaching benchmark
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import evaluate  # noqa: E402
import rundir  # noqa: E402

BEST_OF_10 = 1.539  # E[max of 10 standard normals]


def split(episode_scores):
    """[[scores of goal 1], [scores of goal 2], ...] (equal counts n) -> (goal sd g, episode sd e, reliability r)."""
    n = len(episode_scores[0])
    e2 = float(np.mean([np.var(s, ddof=1) for s in episode_scores]))
    g2 = max(float(np.var([np.mean(s) for s in episode_scores], ddof=1)) - e2 / n, 0.0)
    return g2**0.5, e2**0.5, g2 / (g2 + e2 / n) if g2 + e2 else 0.0


def cell_rows(rows):
    """{(agent, setting, task): (g, e, r, ZS mean, first-round Spearmans of GIIL-online)}"""
    out = {}
    for key in sorted({(r["agent"], r["setting"], r["task"], r["demo"], r["view"]) for r in rows if r["method"] == "GIIL-ZS"}):
        zs = {r["seed"]: r for r in rows if r["method"] == "GIIL-ZS" and (r["agent"], r["setting"], r["task"], r["demo"], r["view"]) == key}
        g, e, rel = split([zs[k]["episode_scores"] for k in sorted(zs)])
        online = [r for r in rows if r["method"] == "GIIL-online" and (r["agent"], r["setting"], r["task"], r["demo"], r["view"]) == key]
        first = [evaluate.spearman([s for _, _, s in r["ot_log"][:len(zs)]], [zs[i]["score"] for i, _, _ in r["ot_log"][:len(zs)]]) for r in online]
        out[key[:3]] = (g, e, rel, np.mean([z["score"] for z in zs.values()]), first)
    return out


def benchmark_rows(run_dirs, tasks=("stand", "walk", "run")):
    """The same split of phase 1's goal-reaching benchmark (goal_reaching.json: each own demo's zero-shot goal, its
    episodes from their own start states) -> {(run, 'benchmark', task): (g, e, r, mean, [])}."""
    out = {}
    for run in run_dirs:
        record = evaluate.read_goal_reaching(run)
        n = record["settings"]["eval_episodes"]
        for task in tasks:
            scores = record["scores"][task]["policy"]
            out[(run, "benchmark", task)] = (*split([scores[i : i + n] for i in range(0, len(scores), n)]), float(np.mean(scores)), [])
    return out


def markdown(cells):
    lines = ["| agent | cell | GIIL-ZS mean | goal sd g | episode sd e | reliability of a 3-episode score | best of 10 known: + 1.54 g | "
             "one real episode's OT vs held-out score, Spearman |", "|---|---|---|---|---|---|---|---|"]
    for (agent, where, task), (g, e, rel, mean, first) in cells.items():
        lines.append(f"| {agent} | {where} {task} | {mean:.1f} | {g:.1f} | {e:.1f} | {rel:.2f} | +{BEST_OF_10 * g:.1f} | "
                     + (f"{np.mean(first):.2f} ({len(first)} seeds)" if first else "-") + " |")
    for agent in sorted({k[0] for k in cells}):
        sel = [v for k, v in cells.items() if k[0] == agent]
        first = [x for v in sel for x in v[4]]
        lines.append(f"| {agent} | mean of {len(sel)} cells | {np.mean([v[3] for v in sel]):.1f} | {np.mean([v[0] for v in sel]):.1f} | "
                     f"{np.mean([v[1] for v in sel]):.1f} | {np.mean([v[2] for v in sel]):.2f} | +{BEST_OF_10 * np.mean([v[0] for v in sel]):.1f} | "
                     + (f"{np.mean(first):.2f}" if first else "-") + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("results", nargs="+", help="results.jsonl files (imitate.py) with GIIL-ZS rows, or with --benchmark run folders")
    parser.add_argument("--benchmark", action="store_true", help="the runs' goal-reaching benchmark (goal_reaching.json) instead")
    args = parser.parse_args()
    if folders := [p for p in args.results if os.path.isdir(p) != args.benchmark]:
        parser.error(f"{folders[0]}: pass results.jsonl files, or run folders with --benchmark" if not args.benchmark else
                     f"{folders[0]}: --benchmark reads run folders (their goal_reaching.json); drop it for results.jsonl files")
    if args.benchmark:
        print(markdown(benchmark_rows(args.results)))
    else:
        print(markdown(cell_rows([r for path in args.results for r in rundir.read_jsonl(path)])))
