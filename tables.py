"""Tables 1-2 and 4-11 of the paper for one agent: every setting (SE/CE x SV/CV) x task, GIIL-ZS and GIIL-FT, and with
`--methods` the baselines GenRL and AIME-NoB, ours beside the paper's. The rows of runs/<name>/results.jsonl, which of
them count for a cell, and the markdown of runs/<name>/tables.md; `python imitate.py --table [--methods
giil,genrl,aime-nob]` runs the cells missing (imitate.table) and writes it.

From committed rows alone (no checkpoint, no demos), as docs/tables_<agent>.md: `python tables.py --table
docs/results/{online,curves,table}_<agent>.jsonl --budgets genrl=1000,aime-nob=5000` (the presets' budgets; each page
names the budgets it shows).

Score against compute (ours): every method's score against the minutes one seed took, the baselines at each budget
they were run at (genrl.py / aime_nob.py --eval-at), from rows of any results.jsonl:

    python tables.py --curves runs/<name>/results.jsonl [docs/results/*.jsonl] --png docs/curves_<agent>.png
"""
import argparse
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
    return latest(rundir.read_jsonl(os.path.join(run_dir, "results.jsonl")))


def latest(rows_in):
    """The last of the rows with the same (demo, view, method, seed, demos' returns, settings) (load_results)."""
    rows = {}
    for r in rows_in:
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


def parse_shard(text):
    """--shard I/N -> (I, N); None: (0, 1), the whole."""
    try:
        shard = tuple(int(x) for x in (text or "0/1").split("/"))
        assert len(shard) == 2 and 0 <= shard[0] < shard[1]
    except (ValueError, AssertionError):
        raise ValueError(f"--shard {text}: pass I/N with 0 <= I < N, e.g. 0/4") from None
    return shard


def parse_settings(text):
    """--settings SE-SV,CE-CV -> the list; an unknown one names the valid ones."""
    settings = text.split(",")
    unknown = [w for w in settings if w not in SETTINGS]
    if unknown:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)}: choose from {', '.join(SETTINGS)}")
    return settings


def parse_budgets(text):
    """--budgets genrl=2000,aime-nob=15000 -> {name: budget}."""
    try:
        budgets = {name: int(value) for name, value in (item.split("=") for item in text.split(","))}
    except ValueError:
        raise ValueError(f"--budgets {text}: pass NAME=BUDGET pairs, e.g. genrl=2000,aime-nob=15000") from None
    unknown = [name for name in budgets if name not in BASELINES]
    if unknown:
        raise ValueError(f"--budgets {unknown[0]}=...: choose from {', '.join(BASELINES)}")
    return budgets


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


def table_rows(rows, budgets=None):
    """The rows of one table (markdown_tables) out of rows of any runs: a baseline's at budgets[its --methods name] or at
    its only budget, of every method the rows of one config, of every cell those of one set of demos; where that is
    not one, the error says what to pass."""
    budgets, out = budgets or {}, []
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method]
        if method in BUDGET:
            (name,), (field, unit) = [n for n, m in BASELINES.items() if m == method], BUDGET[method]
            have = sorted({r["config"][field] for r in mine})
            if name in budgets and budgets[name] not in have:
                raise ValueError(f"--budgets {name}={budgets[name]}: no {method} rows at {budgets[name]} {unit} (they are at {', '.join(map(str, have))})")
            if name not in budgets and len(have) > 1:
                raise ValueError(f"{method} rows at {', '.join(map(str, have))} {unit}: pick one with --budgets {name}=N")
            mine = [r for r in mine if r["config"][field] == budgets.get(name, have[0])]
        if len({json.dumps(r["config"], sort_keys=True) for r in mine}) > 1:
            raise ValueError(f"{method} rows made with different settings (their config): pass the rows of one table")
        out += mine
    demos = {}
    for r in out:
        demos.setdefault((r["demo"], r["view"]), set()).add(json.dumps(r.get("demo_returns")))
    mixed = [cell for cell, sets in demos.items() if len(sets) > 1]
    if mixed:
        raise ValueError(f"{mixed[0][0]} ({mixed[0][1]} view): rows made with {len(demos[mixed[0]])} sets of demos: pass the rows of one table")
    return out


BUDGET = {"GenRL": ("steps", "updates"), "AIME-NoB": ("env_steps", "env steps")}  # a baseline's budget: its config field, its unit


def curve_points(rows, settings):
    """{method: {budget: [(cell, seed, score, seconds)]}} of the rows of `settings`; GIIL's methods have one budget,
    None. A baseline's rows at a budget are those whose config has that budget (a run of it, or an --eval-at point)."""
    out = {}
    for r in rows:
        if r["setting"] not in settings or r["method"] not in METHODS + (ONLINE, *BASELINES.values()):
            continue
        budget = r["config"][BUDGET[r["method"]][0]] if r["method"] in BUDGET else None
        out.setdefault(r["method"], {}).setdefault(budget, []).append(((r["demo"], r["view"]), r["seed"], r["score"], r["time"]))
    return out


def curve(points, seeds):
    """A method's curve: [(budget, scores, seconds)] over the cells with >= `seeds` seeds at its smallest budget, at
    each budget where all of them have >= `seeds` (so every point is a mean over the same cells), and those cells."""
    complete = lambda p: {c for c, _, _, _ in p if sum(c == d for d, _, _, _ in p) >= seeds}
    budgets = sorted(points, key=lambda b: b or 0)
    cells, out = complete(points[budgets[0]]), []
    for budget in budgets:
        if cells and cells <= complete(points[budget]):
            out.append((budget, *zip(*[(score, seconds) for c, _, score, seconds in points[budget] if c in cells])))
    return out, cells


def markdown_curves(agent, rows, settings, seeds=3):
    """One line per method and budget: the score over the complete cells (mean +- s.e. over cells x seeds), the cells,
    the minutes per seed, and the paper's score of the method over the same settings."""
    out = [f"### {agent}: score against budget, {' + '.join(settings)} cells", "",
           "| method | budget | score | " + " / ".join(envs.TASKS) + " | cells x seeds | minutes per seed | paper |", "|---|---|---|---|---|---|---|"]
    for method, points in sorted(curve_points(rows, settings).items()):
        paper = (f"{np.mean([PAPER[agent]['all'][SETTINGS.index(w)][PAPER_METHODS.index(method)] for w in settings]):.1f}"
                 if method in PAPER_METHODS else "-")
        line, cells = curve(points, 1 if method.startswith("GIIL") else seeds)
        for budget, scores, seconds in line:
            kept = [(c[0].rsplit("_", 1)[1], score) for c, _, score, _ in points[budget] if c in cells]
            tasks = " / ".join(f"{np.mean([v for t, v in kept if t == task]):.1f}" if any(t == task for t, _ in kept) else "-" for task in envs.TASKS)
            out.append(f"| {method} | {f'{budget} {BUDGET[method][1]}' if budget else '-'} | {np.mean(scores):.1f} +- "
                       f"{evaluate.stderr(scores):.1f} | {tasks} | {len(cells)} x {len(scores) / len(cells):.0f} | {np.mean(seconds) / 60:.1f} | {paper} |")
    return "\n".join(out) + "\n"


def plot_curves(agent, rows, settings, path, seeds=3):
    """The PNG of markdown_curves: score against minutes per seed (log scale), one line per method, the paper's scores
    dashed in the method's colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for method, points in sorted(curve_points(rows, settings).items()):
        line, cells = curve(points, 1 if method.startswith("GIIL") else seeds)
        if not line:
            continue
        xy = [(np.mean(seconds) / 60, np.mean(scores), evaluate.stderr(scores)) for _, scores, seconds in line]
        x, y, e = zip(*xy)
        line = ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=f"{method} ({len(cells)} cells)")
        if method in PAPER_METHODS:
            paper = np.mean([PAPER[agent]["all"][SETTINGS.index(w)][PAPER_METHODS.index(method)] for w in settings])
            ax.axhline(paper, ls="--", lw=1, color=line[0].get_color())
    ax.set_xscale("log")
    ax.set_xlabel("minutes per seed (one process per core, 2-core CPU)")
    ax.set_ylabel("normalised score (Eq. 8)")
    ax.set_title(f"{agent}, {' + '.join(settings)} cells; dashed: the paper's", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    rundir.atomic_write(path, lambda name: fig.savefig(name, dpi=90), by_name=True)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description="Tables 1-2 and 4-11, or score against compute, from result rows (docs/results.md).", allow_abbrev=False)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--table", nargs="+", metavar="ROWS", help="results.jsonl files of one agent: its tables (as imitate.py --table)")
    mode.add_argument("--curves", nargs="+", metavar="ROWS", help="results.jsonl files of one agent: score against compute")
    parser.add_argument("--budgets", help="with --table: the baselines' columns at these budgets, e.g. genrl=2000,aime-nob=15000")
    parser.add_argument("--settings", default="SE-SV,SE-CV", help="with --curves: the settings averaged (default the same-body ones)")
    parser.add_argument("--seeds", type=int, default=3, help="with --curves: a baseline's cell counts with this many seeds at each budget")
    parser.add_argument("--png", help="with --curves: also draw the figure here")
    args = parser.parse_args()
    curves_only = [f for f in ("png", "settings", "seeds") if getattr(args, f) != parser.get_default(f)]
    if args.table and curves_only:
        parser.error(f"--{curves_only[0]} works with --curves only: drop it")
    if args.curves and args.budgets:
        parser.error("--budgets works with --table only: drop it")
    paths = args.table or args.curves
    missing = [path for path in paths if not os.path.isfile(path)]
    if missing:
        raise ValueError(f"{missing[0]}: no such file; pass results.jsonl files (runs/<name>/results.jsonl, docs/results/*.jsonl)")
    rows = latest(r for path in paths for r in rundir.read_jsonl(path))  # a row in two files counts once
    agents = {r["agent"] for r in rows}
    if len(agents) != 1:
        raise ValueError(f"the rows are of agents {sorted(agents)}: pass one agent's files")
    agent = agents.pop()
    if args.table:
        print(markdown_tables(agent, table_rows(rows, parse_budgets(args.budgets) if args.budgets else None)))
        return
    settings = parse_settings(args.settings)
    print(markdown_curves(agent, rows, settings, args.seeds))
    if args.png:
        plot_curves(agent, rows, settings, args.png, args.seeds)
        print(f"wrote {args.png}")


if __name__ == "__main__":
    rundir.run_main(main, "nothing is written but the figure")
