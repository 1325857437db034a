"""Phase 2's harness, under imitate.py (one demo folder) and tables.py (every cell): a demo folder's rows in
runs/<name>/results.jsonl (each naming the agent's weights and the settings it depends on), resumed from them, its
videos and plots, and the flags of ImitateConfig and OnlineConfig; a cell's lock (cell_lock), which rows count for it
(load_results, finished, row_key) and the --shard / --settings of tables.py and the baselines. The method it runs is
goal_inference.py (Eq. 5 and the goal searches' registry, SEARCHES); missing demos of the body x task imitated are
collected first (collect.py).
"""
import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import re
import time

import numpy as np
import torch
from tqdm import tqdm

import checkpoint
import collect
import configs
import envs
import evaluate
import goal_inference
import online
import rundir
from video_encoder import check_same_encoder


def result_config(ic, method, oc):
    """The settings a row of `method` depends on: evaluation alone for the zero-shot columns, the search's own too."""
    return {k: getattr(ic, k) for k in goal_inference.EVALUATION_FIELDS} if method in goal_inference.ZERO_SHOT else goal_inference.SEARCHES[method].config(ic, oc)


def done_here(rows, demo, view, returns, ic, oc, weights):
    """The (method, seed) pairs of a cell's rows that count (finished) under these settings and weights."""
    configs = {m: result_config(ic, m, oc) for m in goal_inference.METHODS}
    return {(r["method"], r["seed"]) for r in finished(rows, demo, view, returns, configs, weights)}


EVAL_SEED = 20_000  # a cell's evaluation episodes start from environment seeds EVAL_SEED + 100 seed + e (ours)


def check_online_seeds(ic, oc, demos=10):
    """GIIL-online's goal-choosing episodes (env seeds seed_base + 1000 seed + i) never start where an evaluation's do
    (EVAL_SEED + 100 seed + e, for the demos' GIIL-ZS and every search's seeds): a one-line error otherwise."""
    last = EVAL_SEED + 100 * (max(ic.seeds, oc.seeds, demos) - 1) + ic.eval_episodes  # one past the evaluations' last seed
    if any(oc.seed_base + 1000 * s < last and EVAL_SEED < oc.seed_base + 1000 * (s + 1) for s in range(oc.seeds)):
        raise ValueError(f"--online-seed-base {oc.seed_base}: GIIL-online's episodes would start where the evaluation's do (environment "
                         f"seeds {EVAL_SEED} to {last - 1}): pass {last} or more (default {configs.OnlineConfig.seed_base})")


def imitate(run_dir, demo, view, ic, searches=(), oc=None, zero_shot=True, done=None):
    """For one demo folder: GIIL-ZS on every demo (unless not zero_shot), then each goal search named (SEARCHES' keys) for
    its seeds, each seed beside GIIL-ZS (demo 0) on the same evaluation seeds. Appends each evaluation to
    runs/<name>/results.jsonl, each row with the agent's weights (weights_id), and returns the rows. done:
    (method, seed) pairs not run again (tables.py); None: those results.jsonl has for these demos, settings and weights
    (a rerun after Ctrl-C goes on, appending no duplicates; a retrained agent runs again)."""
    rundir.check_flags(ic)
    oc = oc or configs.OnlineConfig(**configs.PRESETS["online"][ic.preset])
    if "GIIL-online" in searches:
        check_online_seeds(ic, oc)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    cfgs, models, ckpt = checkpoint.load_run(run_dir, device)  # a run in training refused (rundir.run_checkpoint)
    tc, weights = cfgs["train"], rundir.weights_id(ckpt)
    rundir.fast_matmul()  # oneDNN where it is faster and still fp32 (rundir.py)
    folder = checkpoint.demo_folder(cfgs, demo, view)
    demo_body, task = envs.parse_demo(demo)
    demos = collect.load_folder(folder, ("pixels", "p"))  # one collection: every demo of one length
    if "GIIL-FT" in searches and len(demos[0]["p"]) < cfgs["ac"].horizon + 2:
        raise ValueError(f"{folder}: demos of {len(demos[0]['p'])} steps are too short for imagined segments of {cfgs['ac'].horizon}; collect longer ones")
    for d in demos:
        check_same_encoder(ckpt["encoder"], d["encoder"], d["path"])
    demo_returns = [round(d["return"], 3) for d in demos]  # identifies this D_demo: rows of older demos do not count
    where = envs.setting(tc.env, demo_body, view)
    out_dir, results_path = rundir.no_link(os.path.join(run_dir, "imitate")), os.path.join(run_dir, "results.jsonl")
    os.makedirs(out_dir, exist_ok=True)
    if done is None:
        done = done_here(load_results(run_dir), demo, view, demo_returns, ic, oc, weights)
        if done:
            print(f"{results_path} has {len(done)} of these evaluations (these demos and settings): kept, not run again")
    done, rows = set(done), []  # done grows as this call evaluates: the searches share their GIIL-ZS (demo 0) seeds

    def evaluate_goal(method, seed, goal, k, t0, **extra):
        """eval_episodes episodes at once with goal (F,), environment seeds EVAL_SEED + 100 seed + e: a search's seed s and
        GIIL-ZS (demo 0) seed s meet the same start states. Seed 0's median-scoring episode (a representative one, its
        index in the row's video_episode) is written as a video (video_name) beside demo k, but for GIIL-ZS (demo 0): its
        seed 0 is GIIL-ZS's demo 0, goal and start alike, already written."""
        render = bool(ic.video) and seed == 0 and method != "GIIL-ZS (demo 0)"
        env_list = [envs.make_env(tc.env, task) for _ in range(ic.eval_episodes)]
        returns, frames = evaluate.run_episodes(env_list, models, goal[None].expand(ic.eval_episodes, -1), ic.eval_steps,
                                                cfgs["wm"].obs, EVAL_SEED + 100 * seed, render)
        scores = [evaluate.episode_score(task, r, ic.eval_steps) for r in returns]
        row = {"agent": tc.env, "demo": demo, "view": view, "task": task, "setting": where, "method": method, "seed": seed,
               "score": float(np.mean(scores)), "episode_scores": scores, "time": None, "demo_returns": demo_returns,
               "config": result_config(ic, method, oc), "weights": weights, **extra}
        if render:
            row["video_episode"] = int(np.argsort(scores)[len(scores) // 2])
            row["video"] = video_name(row)
            evaluate.write_video(os.path.join(out_dir, row["video"]), demos[k]["pixels"], frames[row["video_episode"]])
        row["time"] = round(time.time() - t0, 1)  # the video's writing included
        rundir.append_jsonl(results_path, row)
        rows.append(row)
        done.add((method, seed))

    with torch.no_grad():
        goals = [models["goal_vae"].goal(torch.as_tensor(d["p"][-1], device=device)) for d in demos]  # GIIL-ZS: g = q(s | p_T)
    for k, goal in enumerate(tqdm(goals if zero_shot else [], desc=f"GIIL-ZS {demo} {view}")):
        if ("GIIL-ZS", k) not in done:
            evaluate_goal("GIIL-ZS", k, goal, k, time.time())  # each row its own time: a table's cost is the sum
    cell = goal_inference.Cell(models, cfgs, ic, oc, configs.OTConfig(**configs.PRESETS["ot"][ic.preset]), task, demos, goals, device,
                               functools.cache(lambda: checkpoint.body_features(cfgs, goal_inference.RETRIEVE_STRIDE)))
    for method in searches:
        for seed in range(goal_inference.SEARCHES[method].seeds(ic, oc)):  # each seed independent of the others: its own RNG seeds
            if ("GIIL-ZS (demo 0)", seed) not in done:
                evaluate_goal("GIIL-ZS (demo 0)", seed, goals[0], 0, time.time())
            if (method, seed) not in done:
                t0 = time.time()  # the search's time: the search and its evaluation
                goal, k, extra = goal_inference.SEARCHES[method].search(cell, seed)
                evaluate_goal(method, seed, goal, k, t0, **extra)
    if "GIIL-online" in searches and zero_shot:  # the curve of the goal chosen after each real episode (its GIIL-ZS score)
        counted = finished(load_results(run_dir), demo, view, demo_returns, {m: result_config(ic, m, oc) for m in goal_inference.METHODS}, weights)
        print(f"wrote {online.plot_curves(counted, os.path.join(out_dir, f'{demo}_{view}_online_curve.png'))}")
    for method in goal_inference.METHODS:
        scores = [r["score"] for r in rows if r["method"] == method]
        if scores:
            print(f"{method} {tc.env} imitating {demo} ({view} view, {where}): normalised score {np.mean(scores):.1f} +- "
                  f"{evaluate.stderr(scores):.1f} over {len(scores)} {'demos' if method == 'GIIL-ZS' else 'seeds'} x {ic.eval_episodes} episodes")
    print(f"appended to {results_path}; videos in {out_dir}")
    return rows


def config_flags(parser):
    """--<field> of every configs.ImitateConfig field and --online-<field> of OnlineConfig's (the preset's value unless given);
    parse_config and parse_online read them back."""
    configs.config_flags(parser, configs.ImitateConfig, choices=goal_inference.CHOICES)
    configs.config_flags(parser, configs.OnlineConfig, "online-", "online_")


def parse_config(args):
    """-> (the configs.ImitateConfig of the preset and the flags given, the fields given)."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(configs.ImitateConfig) if getattr(args, f.name) is not None}
    return configs.ImitateConfig(**{**configs.PRESETS["imitate"][given.get("preset", "cpu")], **given}), given


def parse_online(args, preset):
    """-> (GIIL-online's OnlineConfig of the preset and the --online-* flags given, the fields given)."""
    given = {f.name: getattr(args, "online_" + f.name) for f in dataclasses.fields(configs.OnlineConfig)
             if getattr(args, "online_" + f.name, None) is not None}
    oc = configs.OnlineConfig(**{**configs.PRESETS["online"][preset], **given})
    rundir.check_flags(oc, "online-")
    return oc, given


def load_results(run_dir):
    """The latest row per row_key of runs/<name>/results.jsonl: a rerun replaces its own earlier result, never one made
    with other demos, settings or weights. A line that is no result row ({}, [1, 2], NaN) is a one-line error."""
    path = os.path.join(run_dir, "results.jsonl")
    rows = rundir.read_jsonl(path)
    for number, row in enumerate(rows, 1):
        if not isinstance(row, dict) or not {"demo", "view", "method", "seed"} <= set(row):
            raise ValueError(f"{path}: line {number} is not a result row ({json.dumps(row)[:60]}): remove that line, or move the file aside")
    return latest(rows)


def row_key(r):
    """What tells two result rows apart: cell, method, seed, demos (their returns), settings and the agent's weights."""
    return (r["demo"], r["view"], r["method"], r["seed"], json.dumps(r.get("demo_returns")), json.dumps(r.get("config")), r.get("weights"))


def video_name(row):
    """A row's video, named readably by its cell, method and seed, and by 8 hex digits of the rest of its row_key (the demos'
    returns, settings and weights): a rerun with other settings or another agent's weights keeps the kept rows' videos.
    The row names its video ("video"), e.g. walker_run_side_GIIL-FT_s0_1f2e3d4c.mp4."""
    method = re.sub(r"[^A-Za-z0-9-]+", "_", row["method"])  # GIIL-ZS, GIIL-FT, GIIL-online: no shell quoting needed
    tag = hashlib.sha256(json.dumps(row_key(row)[4:]).encode()).hexdigest()[:8]
    return f"{row['demo']}_{row['view']}_{method}_s{row['seed']}_{tag}.mp4"


def latest(rows_in):
    """The last of the rows with the same row_key (load_results)."""
    return list({row_key(r): r for r in rows_in}.values())


def finished(rows, demo, view, returns, configs, weights):
    """A cell's rows that count: made by the agent `weights` (weights_id) with the demos now on disk (their
    returns) and, for a method of `configs`, with the settings configs[method] (result_config)."""
    return [r for r in rows if r["demo"] == demo and r["view"] == view and r.get("demo_returns") == returns
            and r.get("weights") == weights and r["method"] in configs and r.get("config") == configs[r["method"]]]


def cell_lock(run_dir, demo, view):
    """The lock file of a cell while a process runs it, any of its methods (claim; tables.py's cells, imitate.py --demo,
    the baselines' cells)."""
    return os.path.join(rundir.no_link(os.path.join(run_dir, "imitate")), f"{demo}_{view}.lock")


@contextlib.contextmanager
def running_cell(run_dir, demo, view):
    """Holds the cell's lock (cell_lock) while the block runs it (imitate.py, the baselines' --demo): a second process
    on the cell stops in one line naming the one that runs it (tables.py and the baselines' --settings skip it instead)."""
    lock = cell_lock(run_dir, demo, view)
    with rundir.claim(lock) as other:
        if other:
            raise ValueError(f"process {other} is running {demo} ({view} view) on {run_dir} now ({lock}): wait for it to end; "
                             f"the same command then goes on from its rows")
        yield


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
    if unknown := [w for w in settings if w not in envs.SETTINGS]:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)}: choose from {', '.join(envs.SETTINGS)}")
    return settings
