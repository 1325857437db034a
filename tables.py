"""Tables 1-2 and 4-11 of the paper for one agent: every setting (SE/CE x SV/CV) x task, GIIL-ZS and GIIL-FT, ours
beside the paper's. `python imitate.py --table` runs the cells missing from runs/<name>/results.jsonl (imitate.py) and
writes runs/<name>/tables.md.
"""
import dataclasses
import json
import os

import numpy as np

import collect
import envs
import evaluate
import rundir
import train
from envs import SETTINGS


METHODS = ("GIIL-ZS", "GIIL-ZS (demo 0)", "GIIL-FT")  # a cell's columns; GIIL-ZS (demo 0) is the goal GIIL-FT starts from

# The paper's normalised scores (GIIL-ZS, GIIL-FT) for comparison: Tables 1-2 ("all") and 4-11 (per task)
PAPER = {
    "walker": {"all": [(42.52, 68.10), (32.97, 64.13), (19.47, 60.76), (18.09, 45.53)],
               "stand": [(71.01, 100.57), (63.79, 97.37), (47.79, 49.45), (40.95, 49.90)],
               "walk": [(16.68, 25.70), (19.92, 27.31), (12.68, 92.11), (10.17, 36.70)],
               "run": [(55.92, 88.96), (12.36, 81.61), (6.40, 76.27), (4.24, 71.25)],
               "jump": [(26.48, 57.19), (35.81, 50.24), (11.03, 25.21), (17.01, 24.29)]},
    "stickman": {"all": [(68.27, 68.56), (61.26, 72.66), (54.89, 61.77), (38.37, 58.99)],
                 "stand": [(96.96, 98.51), (97.59, 99.75), (66.48, 100.83), (62.68, 100.99)],
                 "walk": [(59.98, 91.00), (59.38, 94.33), (46.77, 22.12), (20.79, 17.57)],
                 "run": [(80.65, 58.65), (51.70, 59.25), (69.71, 69.49), (37.93, 61.68)],
                 "jump": [(35.50, 26.07), (36.37, 37.30), (36.59, 54.64), (32.07, 55.73)]},
}


def demo_of(agent, task, where):
    """(demo name, view) of a setting: SE/CE picks the demonstrator's body, SV/CV its camera."""
    other = [b for b in envs.BODIES if b != agent][0]
    return f"{agent if where.startswith('SE') else other}_{task}", "side" if where.endswith("SV") else "diagonal"


def load_results(run_dir):
    """The latest row per (demo, view, method, seed, demos' returns, settings) of runs/<name>/results.jsonl: a rerun
    replaces its own earlier result, never one made with other demos or settings."""
    rows = {}
    for r in rundir.read_jsonl(os.path.join(run_dir, "results.jsonl")):
        rows[(r["demo"], r["view"], r["method"], r["seed"], json.dumps(r.get("demo_returns")), json.dumps(r.get("config")))] = r
    return list(rows.values())


def result_config(ic, method):
    """The ImitateConfig fields a result depends on: evaluation for the zero-shot columns, finetuning too for GIIL-FT."""
    fields = dataclasses.asdict(ic)
    keep = ("eval_episodes", "eval_steps") if method.startswith("GIIL-ZS") else tuple(k for k in fields if k not in ("seeds", "video"))
    return {k: fields[k] for k in keep}


def cells(agent):
    """Every (task, setting) of an agent's table, in a fixed order (what --shard splits)."""
    return [(task, where) for task in envs.TASKS for where in SETTINGS]


def table(run_dir, ic, settings=SETTINGS, demos_per_cell=10, shard=(0, 1)):
    """Every setting x task for this agent, GIIL-ZS, GIIL-ZS (demo 0) and GIIL-FT; runs only what is missing from
    results.jsonl. `settings` limits which settings run now, shard (i, N) runs only the cells i, i + N, i + 2N, ... of
    `cells` (N processes or machines share one table: rows are appended under a lock, one row per evaluation, and a
    cell's rows are told apart by method and seed, so shards merge without loss or duplicates); the tables show every
    finished cell. A row counts only if it was made with the demos now on disk (their returns match) and with the
    settings asked for (result_config): regenerating D_demo or changing a setting makes the cells run again instead
    of mixing old and new results."""
    import imitate  # the cells it runs (imitate.py imports this module)

    rundir.check_flags(ic)
    cfgs = train.load_run(run_dir)[0]
    agent, current = cfgs["train"].env, []
    for k, (task, where) in enumerate(cells(agent)):
        demo, view = demo_of(agent, task, where)
        run_now = where in settings and k % shard[1] == shard[0]  # a cell left out runs nothing; its finished rows still count
        folder = imitate.demo_folder(cfgs, demo, view) if run_now else os.path.join(cfgs["train"].data, "demos", f"{demo}_{view}")
        if not os.path.isdir(folder):
            continue
        returns = [round(e["return"], 3) for e in collect.load_folder(folder, ())]
        cell = lambda: [r for r in load_results(run_dir) if r["demo"] == demo and r["view"] == view and r.get("demo_returns") == returns
                        and r.get("config") == result_config(ic, r["method"])]
        count = lambda m: len({r["seed"] for r in cell() if r["method"] == m})
        zs, ft = count("GIIL-ZS") < demos_per_cell, min(count("GIIL-FT"), count("GIIL-ZS (demo 0)")) < ic.seeds
        if (zs or ft) and run_now:
            imitate.imitate(run_dir, demo, view, ft, ic, zero_shot=zs)
        current += cell()
    text = markdown_tables(agent, current)
    path = os.path.join(run_dir, "tables.md")
    collect.atomic_write(path, lambda f: f.write(text.encode()))
    print(text)
    print(f"wrote {path}")


def markdown_tables(agent, rows):
    """Tables 1/2 (all tasks) and 4-11 (per task) for this agent: ours next to the paper's, mean +- s.e."""
    def cell(scores):
        return f"{np.mean(scores):.1f} +- {evaluate.stderr(scores):.1f}" if scores else "-"

    methods = METHODS
    out = []
    for task in ("all",) + envs.TASKS:
        title = f"{agent} agent, {'all tasks (as Table 1/2)' if task == 'all' else task}: normalised score, mean +- s.e."
        out += [f"### {title}", "", "| setting | " + " | ".join(f"{m} (ours)" for m in methods) + " | GIIL-ZS (paper) | GIIL-FT (paper) |",
                "|---|" + "---|" * (len(methods) + 2)]
        pick = lambda m, ws: [r["score"] for r in rows if r["method"] == m and r["setting"] in ws and (task == "all" or r["task"] == task)]
        # "w/o SE-SV" the paper's way: the mean over the other three settings' results
        for name, ws in [(w, [w]) for w in SETTINGS] + [("Average", SETTINGS), ("Average w/o SE-SV", SETTINGS[1:])]:
            paper = [np.mean([PAPER[agent][task][SETTINGS.index(w)][m] for w in ws]) for m in (0, 1)]
            out.append(f"| {name} | " + " | ".join(cell(pick(m, ws)) for m in methods) + f" | {paper[0]:.2f} | {paper[1]:.2f} |")
        out.append("")
    return "\n".join(out)
