"""Tables 1-2 and 4-11 of the paper for one agent: every setting (SE/CE x SV/CV) x task, GIIL-ZS and GIIL-FT, and with
`--methods` the baselines GenRL and AIME-NoB, ours beside the paper's. The rows of runs/<name>/results.jsonl, which of
them count for a cell, and the markdown of runs/<name>/tables.md; `python imitate.py --table [--methods
giil,genrl,aime-nob]` runs the cells missing (imitate.table) and writes it.
"""
import dataclasses
import json
import os

import numpy as np

import envs
import evaluate
import rundir
from envs import SETTINGS


METHODS = ("GIIL-ZS", "GIIL-ZS (demo 0)", "GIIL-FT")  # a cell's columns; GIIL-ZS (demo 0) is the goal GIIL-FT starts from
BASELINES = {"genrl": "GenRL", "aime-nob": "AIME-NoB"}  # --methods name -> method of the rows (genrl.py, aime_nob.py)
ONLINE = "GIIL-online"  # ours, after Sec. 6 (online.py): shown where its rows exist, beside the GIIL-ZS (demo 0) it starts from

# The paper's normalised scores, per setting (SE-SV, SE-CV, CE-SV, CE-CV) the columns PAPER_METHODS: Tables 1-2 ("all")
# and 4-11 (per task), mean only
PAPER_METHODS = ("GenRL", "AIME-NoB", "GIIL-ZS", "GIIL-FT")
PAPER = {
    "walker": {"all": [(86.05, 84.80, 42.52, 68.10), (65.98, 51.46, 32.97, 64.13), (52.12, 64.91, 19.47, 60.76), (65.91, 28.92, 18.09, 45.53)],
               "stand": [(101.89, 101.88, 71.01, 100.57), (92.19, 101.30, 63.79, 97.37), (98.35, 101.27, 47.79, 49.45), (101.09, 96.02, 40.95, 49.90)],
               "walk": [(96.31, 99.36, 16.68, 25.70), (76.90, 16.13, 19.92, 27.31), (22.73, 61.01, 12.68, 92.11), (72.50, 18.74, 10.17, 36.70)],
               "run": [(76.04, 38.45, 55.92, 88.96), (25.85, 19.72, 12.36, 81.61), (39.81, 51.82, 6.40, 76.27), (34.96, 3.84, 4.24, 71.25)],
               "jump": [(69.93, 99.49, 26.48, 57.19), (68.99, 68.68, 35.81, 50.24), (47.60, 45.53, 11.03, 25.21), (55.10, -2.91, 17.01, 24.29)]},
    "stickman": {"all": [(55.30, 83.90, 68.27, 68.56), (63.58, 45.35, 61.26, 72.66), (47.37, 70.64, 54.89, 61.77), (20.44, 49.99, 38.37, 58.99)],
                 "stand": [(97.26, 100.93, 96.96, 98.51), (100.30, 97.50, 97.59, 99.75), (97.88, 101.05, 66.48, 100.83), (6.51, 99.51, 62.68, 100.99)],
                 "walk": [(45.67, 99.33, 59.98, 91.00), (80.11, 23.13, 59.38, 94.33), (12.40, 87.76, 46.77, 22.12), (-0.01, 21.72, 20.79, 17.57)],
                 "run": [(26.11, 47.62, 80.65, 58.65), (35.17, 14.90, 51.70, 59.25), (26.75, 33.58, 69.71, 69.49), (30.10, 19.51, 37.93, 61.68)],
                 "jump": [(52.16, 87.74, 35.50, 26.07), (38.72, 45.87, 36.37, 37.30), (52.43, 60.14, 36.59, 54.64), (45.14, 59.22, 32.07, 55.73)]},
}


def setting(agent_body, demo_body, view):
    """The setting of a demo for an agent: SE or CE (same or cross embodiment), SV or CV (same or cross view)."""
    return ("SE" if demo_body == agent_body else "CE") + "-" + ("SV" if view == "side" else "CV")


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


def result_config(ic, method, oc=None):
    """The ImitateConfig fields a result depends on: evaluation for the zero-shot columns, finetuning too for GIIL-FT,
    the OnlineConfig oc's too for GIIL-online."""
    fields, evaluation = dataclasses.asdict(ic), ("eval_episodes", "eval_steps")
    if method == ONLINE:  # as a row stores it: JSON has no tuples (the schedule reads back as lists); `candidates` only
        # where it is not 'demos', what every GIIL-online row had before the field existed
        online = {k: v for k, v in dataclasses.asdict(oc).items() if k != "seeds" and not (k == "candidates" and v == "demos")}
        return json.loads(json.dumps({**{k: fields[k] for k in evaluation}, **online}))
    keep = evaluation if method.startswith("GIIL-ZS") else tuple(k for k in fields if k not in ("seeds", "video"))
    return {k: fields[k] for k in keep}


def finished(rows, demo, view, returns, configs):
    """A cell's rows that count: made with the demos now on disk (their returns) and, for a method of `configs`, with
    the settings configs[method] (result_config)."""
    return [r for r in rows if r["demo"] == demo and r["view"] == view and r.get("demo_returns") == returns
            and r["method"] in configs and r.get("config") == configs[r["method"]]]


def cell_lock(run_dir, demo, view):
    """The lock file of a cell while a process runs it (rundir.claim; imitate.table, imitate.py --demo)."""
    return os.path.join(run_dir, "imitate", f"{demo}_{view}.lock")


def cells(agent):
    """Every (task, setting) of an agent's table, in a fixed order (what --shard splits)."""
    return [(task, where) for task in envs.TASKS for where in SETTINGS]


def markdown_tables(agent, rows):
    """Tables 1/2 (all tasks) and 4-11 (per task) for this agent: ours next to the paper's, mean +- s.e., and GIIL-FT
    minus GIIL-ZS (demo 0) paired by cell and seed (both are scored on the same evaluation seeds)."""
    def cell(scores):
        return f"{np.mean(scores):.1f} +- {evaluate.stderr(scores):.1f}" if scores else "-"

    methods = METHODS + tuple(m for m in (ONLINE, *BASELINES.values()) if any(r["method"] == m for r in rows))
    paired = ("GIIL-FT",) + ((ONLINE,) if ONLINE in methods else ())  # each minus GIIL-ZS (demo 0), seed by seed
    paper_methods = [m for m in methods if m in PAPER_METHODS]  # the paper's columns of the methods shown
    out = []
    for task in ("all",) + envs.TASKS:
        title = f"{agent} agent, {'all tasks (as Table 1/2)' if task == 'all' else task}: normalised score, mean +- s.e."
        out += [f"### {title}", "", "| setting | " + " | ".join(f"{m} (ours)" for m in methods) + " | "
                + " | ".join(f"{m.removeprefix('GIIL-')} - ZS (demo 0), paired" for m in paired) + " | "
                + " | ".join(f"{m} (paper)" for m in paper_methods) + " |", "|---|" + "---|" * (len(methods) + len(paired) + len(paper_methods))]
        mine = lambda m, ws: {(r["demo"], r["view"], r["seed"]): r["score"] for r in rows
                              if r["method"] == m and r["setting"] in ws and (task == "all" or r["task"] == task)}
        # "w/o SE-SV" the paper's way: the mean over the other three settings' results
        for name, ws in [(w, [w]) for w in SETTINGS] + [("Average", SETTINGS), ("Average w/o SE-SV", SETTINGS[1:])]:
            paper = [np.mean([PAPER[agent][task][SETTINGS.index(w)][PAPER_METHODS.index(m)] for w in ws]) for m in paper_methods]
            zs0 = mine("GIIL-ZS (demo 0)", ws)
            # what finetuning (or online refinement) adds: the same evaluation seeds, seed by seed
            gains = [[v - zs0[k] for k, v in mine(m, ws).items() if k in zs0] for m in paired]
            out.append(f"| {name} | " + " | ".join(cell(list(mine(m, ws).values())) for m in methods) + " | "
                       + " | ".join(cell(g) for g in gains) + " | " + " | ".join(f"{p:.2f}" for p in paper) + " |")
        out.append("")
    return "\n".join(out)
