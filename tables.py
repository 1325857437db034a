"""Tables 1-2 and 4-11 of the paper for one agent: every setting (SE/CE x SV/CV) x task, GIIL-ZS and the goal searches
(goal_inference.SEARCHES: GIIL-FT, GIIL-online, GIIL-retrieve), and with `--methods` the baselines GenRL and AIME-NoB,
ours beside the paper's. The table harness: it runs the cells missing from runs/<name>/results.jsonl (sharded over
processes, a lock per cell, resumed from the rows), and writes their markdown to runs/<name>/tables.md:

    python tables.py --run runs/<name> [--methods finetune,online,genrl,aime-nob] [--settings SE-SV,CE-CV] [--shard I/N]

From committed rows alone (no checkpoint, no demos), as docs/tables_<agent>.md: `python tables.py --table
docs/results/{online,curves,table}_<agent>.jsonl --budgets genrl=1000,aime-nob=5000` (the presets' budgets; each page
names the budgets it shows).

Score against compute (ours): every method's score against the minutes one seed took, the baselines at each budget
they were run at (baselines/genrl.py / baselines/aime_nob.py --eval-at), from rows of any results.jsonl:

    python tables.py --curves runs/<name>/results.jsonl [docs/results/*.jsonl] --png docs/curves_<agent>.png
"""
import argparse
import contextlib
import json
import os

import numpy as np

import checkpoint
import collect
import envs
import evaluate
import goal_inference
import rundir
import runner
from baselines import aime_nob, genrl
from envs import SETTINGS
from configs import PRESETS, AIMENoBConfig, GenRLConfig, OnlineConfig


BASELINES = {"genrl": "GenRL", "aime-nob": "AIME-NoB"}  # --methods name -> method of the rows (baselines/genrl.py, baselines/aime_nob.py)
SHOWN = ("GIIL-ZS", "GIIL-ZS (demo 0)", "GIIL-FT")  # the columns of every table; the other methods where they have rows

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


def parse_budgets(text):
    """--budgets genrl=2000,aime-nob=15000 -> {name: budget}."""
    try:
        pairs = [(name, int(value)) for name, value in (item.split("=") for item in text.split(","))]
    except ValueError:
        raise ValueError(f"--budgets {text}: pass NAME=BUDGET pairs, e.g. genrl=2000,aime-nob=15000") from None
    budgets = dict(pairs)
    if len(budgets) < len(pairs):
        twice = next(name for name, _ in pairs if sum(n == name for n, _ in pairs) > 1)
        raise ValueError(f"--budgets {text}: {twice} is given twice; pass one budget per baseline")
    unknown = [name for name in budgets if name not in BASELINES]
    if unknown:
        raise ValueError(f"--budgets {unknown[0]}=...: choose from {', '.join(BASELINES)}")
    return budgets


def markdown_tables(agent, rows):
    """Tables 1/2 (all tasks) and 4-11 (per task) for this agent: ours next to the paper's, mean +- s.e., and GIIL-FT
    minus GIIL-ZS (demo 0) paired by cell and seed (both are scored on the same evaluation seeds)."""
    def cell(scores):
        return f"{np.mean(scores):.1f} +- {evaluate.stderr(scores):.1f}" if scores else "-"

    methods = SHOWN + tuple(m for m in goal_inference.METHODS + tuple(BASELINES.values()) if m not in SHOWN and any(r["method"] == m for r in rows))
    paired = [m for m in methods if m in goal_inference.SEARCHES]  # each minus GIIL-ZS (demo 0), seed by seed
    paper_methods = [m for m in methods if m in PAPER_METHODS and agent in PAPER]  # the paper's columns of the methods shown
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
        if r["setting"] not in settings or r["method"] not in goal_inference.METHODS + tuple(BASELINES.values()):
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
                 if method in PAPER_METHODS and agent in PAPER else "-")
        line, cells = curve(points, 1 if method.startswith("GIIL") else seeds)
        for budget, scores, seconds in line:
            kept = [(envs.parse_demo(c[0])[1], score) for c, _, score, _ in points[budget] if c in cells]
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
        if method in PAPER_METHODS and agent in PAPER:
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


def baseline_configs(preset, budgets=None):
    """{method: (module, its config, the config its rows carry)} of each baseline, with its own preset of that name (cpu's
    where it has none); budgets {name: budget} replaces a preset's (GenRL's updates, AIME-NoB's env steps: --budgets)."""
    out, budgets = {}, budgets or {}
    for name, method in BASELINES.items():
        module, cls, key = {"genrl": (genrl, GenRLConfig, "genrl"), "aime-nob": (aime_nob, AIMENoBConfig, "aime_nob")}[name]
        given = {cls.budget_field: budgets[name]} if name in budgets else {}
        cfg = cls(**{**PRESETS[key].get(preset, {}), **given})  # a preset the baseline has not (paper): its defaults
        out[method] = (module, cfg, genrl.result_config(cfg))
    return out


def run_table(run_dir, ic, oc=None, settings=SETTINGS, shard=(0, 1), methods=("finetune",), budgets=None, demos_per_cell=10):
    """Every setting x task for this agent: GIIL-ZS and the goal searches whose flag is in `methods` (goal_inference.SEARCHES),
    and the baselines named there (BASELINES' keys, each with its preset of ic.preset, or at `budgets`); runs only what
    is missing from results.jsonl, then writes the tables of every finished cell. `settings` limits which settings run
    now; shard (i, N) runs only the cells i, i + N, ... of those (tables' order: N processes share one table, rows
    appended under a lock and told apart by method and seed). A row counts only if it was made with the demos now on
    disk (their returns), with the settings asked for (runner.result_config) and by this checkpoint's weights:
    regenerating D_demo, changing a setting or retraining the agent runs the cells again instead of mixing results."""
    known = [s.flag for s in goal_inference.SEARCHES.values()] + list(BASELINES)
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ValueError(f"--methods {','.join(unknown)}: choose from {', '.join(known)}")
    oc = oc or OnlineConfig(**PRESETS["online"][ic.preset])
    rundir.check_flags(ic)
    baselines = baseline_configs(ic.preset, budgets)  # their finished cells are shown whichever methods run now
    cfgs, _, ckpt = checkpoint.load_run(run_dir)  # a run in training refused (rundir.run_checkpoint)
    agent, shown, weights = cfgs["train"].env, [], rundir.weights_id(ckpt)
    configs = {**{m: runner.result_config(ic, m, oc) for m in goal_inference.METHODS}, **{m: b[2] for m, b in baselines.items()}}
    searches = [m for m, s in goal_inference.SEARCHES.items() if s.flag in methods]
    # the shards split the cells of `settings`, so that none is left idle; a cell left out runs nothing, its finished rows still count
    runs_here = [cell for cell in envs.cells(agent) if cell[1] in settings][shard[0]::shard[1]]
    for task, where in envs.cells(agent):
        demo, view = envs.demo_of(agent, task, where)
        run_now = (task, where) in runs_here
        # one process at a time runs a cell (its lock file, rundir.claim): a second table process without --shard, or
        # with shards that overlap, skips the cells another one is running; their rows count once written
        with rundir.claim(runner.cell_lock(run_dir, demo, view)) if run_now else contextlib.nullcontext() as other:
            if other:
                print(f"{demo} ({view} view): process {other} is running this cell now ({runner.cell_lock(run_dir, demo, view)}): skipped here")
            run_now = run_now and not other
            folder = checkpoint.demo_folder(cfgs, demo, view) if run_now else os.path.join(cfgs["train"].data, "demos", f"{demo}_{view}")
            if not os.path.isdir(folder):
                continue
            returns = [round(e["return"], 3) for e in collect.load_folder(folder, ())]
            done = {(r["method"], r["seed"]) for r in runner.finished(runner.load_results(run_dir), demo, view, returns, configs, weights)}
            count = lambda m: sum(method == m for method, _ in done)
            # only the seeds missing (a cell cut off goes on where it was); GIIL-online's candidates are GIIL-ZS's goals
            missing = [m for m in searches if min(count(m), count("GIIL-ZS (demo 0)")) < goal_inference.SEARCHES[m].seeds(ic, oc)]
            zero_shot = bool(searches) and count("GIIL-ZS") < demos_per_cell
            if (zero_shot or missing) and run_now:
                runner.imitate(run_dir, demo, view, ic, missing, oc, zero_shot, done)
            for name, method in BASELINES.items():
                module, cfg, _ = baselines[method]
                if count(method) < cfg.seeds and run_now and name in methods:
                    module.run_cell(run_dir, demo, view, cfg)
            shown.append((demo, view, returns, configs, weights))
    rows = runner.load_results(run_dir)  # read once all cells ran: the rows other shards appended meanwhile count too
    text = markdown_tables(agent, [r for cell in shown for r in runner.finished(rows, *cell)])
    path = os.path.join(run_dir, "tables.md")
    rundir.atomic_write(path, lambda f: f.write(text.encode()))
    print(text)
    print(f"wrote {path}")


def merge_files(paths):
    """The rows of several results files, each file's latest (runner.latest); a row in two files counts once, and two files
    that score the same evaluation (runner.row_key) differently are a one-line error naming both."""
    merged, keys = {}, ("agent", "demo", "view", "method", "seed", "score")
    for path in paths:
        rows = rundir.read_jsonl(path)
        if bad := [n for n, r in enumerate(rows, 1) if not isinstance(r, dict) or any(k not in r for k in keys)]:
            raise ValueError(f"{path}: row {bad[0]} is not a result row (a dict with {', '.join(keys)}); pass files imitate.py or tables.py wrote")
        for r in runner.latest(rows):
            have = merged.setdefault(runner.row_key(r), (path, r))
            if have[1]["score"] != r["score"]:
                raise ValueError(f"{have[0]} and {path} score {r['method']} seed {r['seed']} on {r['demo']} ({r['view']} view) differently "
                                 f"({have[1]['score']:.2f} against {r['score']:.2f}), made alike: pass one of them")
    agents = {}  # a cell's columns read one agent: rows of two weights of one body are not averaged together
    for path, r in merged.values():
        if r.get("weights"):
            other = agents.setdefault((r["agent"], r["demo"], r["view"]), (path, r["weights"]))
            if other[1] != r["weights"]:
                raise ValueError(f"{other[0]} and {path} hold rows of two agents ({other[1]} and {r['weights']}) for {r['agent']} imitating "
                                 f"{r['demo']} ({r['view']} view): pass the rows of one agent's weights")
    return [r for _, r in merged.values()]


def main():
    parser = argparse.ArgumentParser(description="Tables 1-2 and 4-11: run an agent's missing cells (--run, --env), or from result "
                                     "rows (--table, --curves: score against compute; docs/results.md).", allow_abbrev=False)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--run", help="the phase-1 run (train.py) whose agent imitates: run its missing cells, write <run>/tables.md")
    mode.add_argument("--env", choices=envs.BODIES, help="as --run, the run train.py writes for this body and --preset "
                      "(runs/<env>_<obs>_<preset>_s0, or else the shipped agents/<env>)")
    mode.add_argument("--table", nargs="+", metavar="ROWS", help="results.jsonl files of one agent: its tables")
    mode.add_argument("--curves", nargs="+", metavar="ROWS", help="results.jsonl files of one agent: score against compute")
    parser.add_argument("--methods", help="with --run: comma-separated, of finetune (GIIL-FT; the default), online (GIIL-online), retrieve (GIIL-retrieve), genrl, "
                        "aime-nob (the baselines, baselines/genrl.py and baselines/aime_nob.py with their --preset); GIIL-ZS comes with any goal search")
    parser.add_argument("--settings", help="with --run: the settings to run now (default all); with --curves: the settings averaged "
                        "(default the same-body ones), comma-separated")
    parser.add_argument("--shard", metavar="I/N", help="with --run: run only cells I, I + N, ... of those of --settings (N processes, one table)")
    parser.add_argument("--budgets", help="with --run or --table: the baselines' columns at these budgets instead of their presets', "
                        "e.g. genrl=2000,aime-nob=15000 (GenRL updates, AIME-NoB env steps)")
    parser.add_argument("--min-seeds", type=int, default=3, help="with --curves: a baseline's cell counts with this many seeds at each budget")
    parser.add_argument("--png", help="with --curves: also draw the figure here")
    rundir.threads_flag(parser)
    runner.config_flags(parser)
    args = parser.parse_args()
    ic, given = runner.parse_config(args)
    oc, online_given = runner.parse_online(args, ic.preset)
    mode = "--run" if args.run or args.env else "--table" if args.table else "--curves"
    allowed = {"--run": ("methods", "settings", "shard", "budgets", "threads"), "--table": ("budgets",), "--curves": ("settings", "min_seeds", "png")}
    extra = [f for f in ("methods", "settings", "shard", "budgets", "min_seeds", "png", "threads")
             if getattr(args, f) != parser.get_default(f) and f not in allowed[mode]]
    extra += [] if mode == "--run" else list(given) + ["online_" + f for f in online_given]
    if extra:
        parser.error(f"--{extra[0].replace('_', '-')} does nothing with {mode}: drop it")
    if args.min_seeds < 1:
        parser.error(f"--min-seeds {args.min_seeds}: must be >= 1")
    try:
        budgets = parse_budgets(args.budgets) if args.budgets else None
        settings = runner.parse_settings(args.settings or (",".join(SETTINGS) if mode == "--run" else "SE-SV,SE-CV"))
        shard = runner.parse_shard(args.shard)
    except ValueError as error:
        parser.error(str(error))
    if mode == "--run":
        rundir.use_threads(args.threads)
        run = args.run or checkpoint.resolve_run(args.env, ic.preset)
        rundir.run_checkpoint(run, env=args.env)  # before anything runs: the run's agent is what its folder's name says
        run_table(checkpoint.work_folder(run), ic, oc, settings, shard, (args.methods or "finetune").split(","), budgets)
        return
    paths = args.table or args.curves
    missing = [path for path in paths if not os.path.isfile(path)]
    if missing:
        raise ValueError(f"{missing[0]}: no such file; pass results.jsonl files (runs/<name>/results.jsonl, docs/results/*.jsonl)")
    rows = merge_files(paths)
    agents = {r["agent"] for r in rows}
    if len(agents) != 1:
        raise ValueError(f"the rows are of agents {sorted(agents)}: pass one agent's files")
    agent = agents.pop()
    if args.table:
        print(markdown_tables(agent, table_rows(rows, budgets)))
        return
    print(markdown_curves(agent, rows, settings, args.min_seeds))
    if args.png:
        plot_curves(agent, rows, settings, args.png, args.min_seeds)
        print(f"wrote {args.png}")


if __name__ == "__main__":
    rundir.run_main(main, "every evaluation finished is in the run's results.jsonl: the same command goes on from there")
