"""Does better data move the benchmark? Phase-1 runs trained on D_body collected by run experts trained on further,
benchmarked on the old and the new demos, against the recipe's runs: each run's benchmark record as a row, then
the table by training seed.

python probes/data_lever.py --add docs/results/data_lever.jsonl --recipe NAME [--demos DATA] RUN ...  # RUN's rows
python probes/data_lever.py --summary docs/results/data_lever.jsonl
python probes/data_lever.py --by-snapshot data/walker run   # D_body's run episodes by the expert snapshot they replay

A run's own benchmark (goal_reaching.json) scores the demos under the data it trained on; `train.py --evaluate --data
DATA` writes another demos' scores beside it (goal_reaching_<settings>_data-<DATA>.json, naming DATA), which --demos
DATA reads.
A row names its recipe (a label), run, training seed, D_body folder, demos folder with each task's demo score (the
mean normalised return of its side-view demos: which experts made them) and weights; a record of weights the run no
longer holds is refused (the run was trained since). The table groups rows by (recipe, demos), a column per task.
"""
import argparse
import glob
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import envs  # noqa: E402
import rundir  # noqa: E402
from evaluate import read_goal_reaching, stderr  # noqa: E402


def demo_scores(data, body):
    """{task: mean normalised return of the body's side-view demos under data/demos}."""
    out = {}
    for task in envs.BODY_TASKS:
        returns = [float(np.load(f)["return"]) for f in sorted(glob.glob(os.path.join(data, "demos", f"{body}_{task}_side", "*.npz")))]
        out[task] = float(envs.normalized_score(task, np.mean(returns)))
    return out


def episodes_by_snapshot(folder, task):
    """[(snapshot step, episodes, mean normalised score)] of a D_body folder's `task` episodes (collect.py: each replays
    one snapshot of the expert's history with action noise), ascending by step."""
    by = {}
    for path in sorted(glob.glob(os.path.join(folder, f"{task}_*.npz"))):
        episode = np.load(path)
        by.setdefault(int(str(episode["source"]).rsplit("@", 1)[1]), []).append(float(envs.normalized_score(task, float(episode["return"]))))
    return [(step, len(v), float(np.mean(v))) for step, v in sorted(by.items())]


def row(run_dir, recipe, demos=None):
    """The row of run_dir's benchmark on the demos under `demos` (default: its own training data's)."""
    ckpt = rundir.run_checkpoint(run_dir)
    config, own = ckpt["config"]["train"], ckpt["config"]["train"]["data"]
    if demos is None or os.path.normpath(demos) == os.path.normpath(own):
        record, demos = read_goal_reaching(run_dir), own
    else:
        records = [json.load(open(p)) for p in glob.glob(os.path.join(rundir.work_path(run_dir), "goal_reaching_*.json"))]
        found = [r for r in records if os.path.normpath(r.get("data", "")) == os.path.normpath(demos)]  # the demos it scored
        if len(found) != 1:
            raise FileNotFoundError(f"{len(found)} records of {run_dir} on the demos under {demos}: run `python train.py --evaluate "
                                    f"--run-dir {run_dir} --data {demos}` (once per benchmark setting)")
        record = found[0]
        if record["weights"] != read_goal_reaching(run_dir)["weights"]:
            raise ValueError(f"the record on {demos} scores another agent than {run_dir} holds: evaluate it again")
    return {"recipe": recipe, "run": run_dir, "agent": record["agent"], "seed": config["seed"], "d_body": os.path.normpath(ckpt.get("trained_data", own)),
            "demos": os.path.normpath(demos), "demo_scores": demo_scores(demos, record["agent"]), "weights": record["weights"], "settings": record["settings"],
            "scores": {t: s["policy"] for t, s in record["scores"].items()}}


def table(rows):
    """Per body and (recipe, demos): each seed's per-task means, their mean +- s.e. over seeds, and the difference to
    the body's first group paired by seed."""
    lines = []
    for body in sorted({r["agent"] for r in rows}):
        lines += [f"| {body}: recipe, demos (their run score) | seed | " + " | ".join(envs.BODY_TASKS) + " | average |", "|---|---|" + "---|" * (len(envs.BODY_TASKS) + 1)]
        groups = {}
        for r in rows:
            if r["agent"] == body:
                groups.setdefault(f"{r['recipe']}, {r['demos']} ({r['demo_scores']['run']:.0f})", []).append(r)
        first = None  # {seed: its means} of the body's first group, which the others are paired with by seed
        for name, members in groups.items():
            means = np.array([[np.mean(m["scores"][t]) for t in envs.BODY_TASKS] for m in members])
            means = {m["seed"]: np.append(v, v.mean()) for m, v in zip(members, means)}
            for seed, v in means.items():
                lines.append(f"| {name} | {seed} | " + " | ".join(f"{x:.1f}" for x in v) + " |")
            if len(means) > 1:
                lines.append(f"| {name} | {len(means)} seeds | " + " | ".join(
                    f"{c.mean():.1f} +- {stderr(c):.1f}" for c in np.array(list(means.values())).T) + " |")
            if first is None:
                first = means
            elif set(means) & set(first):
                paired = np.array([means[s] - first[s] for s in sorted(set(means) & set(first))])
                lines.append(f"| {name} minus the first | {len(paired)} paired | " + " | ".join(
                    f"{c.mean():+.1f}" + (f" +- {stderr(c):.1f}" if len(c) > 1 else "") for c in paired.T) + " |")
        lines.append("")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("--add", metavar="ROWS", help="append the rows of RUN ... to this JSONL file")
    parser.add_argument("--recipe", help="with --add: the label of these runs' recipe (the table groups by it)")
    parser.add_argument("--demos", default=None, help="with --add: the data folder whose demos were scored (default: each run's own)")
    parser.add_argument("--summary", metavar="ROWS", help="print the table of a rows file")
    parser.add_argument("--by-snapshot", nargs=2, metavar=("FOLDER", "TASK"), help="the D_body folder's TASK episodes' mean score by "
                        "the expert snapshot each replays, e.g. data/walker run")
    parser.add_argument("runs", nargs="*")
    args = parser.parse_args()
    if args.by_snapshot:
        print("| snapshot (training step) | episodes | mean normalised score |\n|---|---|---|")
        print("\n".join(f"| {step // 1000}k | {n} | {score:.1f} |" for step, n, score in episodes_by_snapshot(*args.by_snapshot)))
        return
    if bool(args.add) == bool(args.summary) or not (bool(args.runs) == bool(args.add) == bool(args.recipe)):
        parser.error("pass --add ROWS --recipe NAME with run folders, or --summary ROWS alone")
    if args.add:
        new = [row(run, args.recipe, args.demos) for run in args.runs]
        with open(args.add, "a") as f:
            f.writelines(json.dumps(r) + "\n" for r in new)
        print(f"appended {len(new)} rows to {args.add}")
    else:
        print("\n".join(table([json.loads(line) for line in open(args.summary)])))


if __name__ == "__main__":
    main()
