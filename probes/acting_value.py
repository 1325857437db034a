"""Does choosing among the policy's own actions by the imagined goal return, at acting time, reach goals better?

A fifth lever on the frozen policy, one that trains nothing (docs/results.md, What limits the policy, measured): at
every real step, K candidate first actions (the actor's mean, as it acts, and K - 1 samples of pi(a | s_t, g)) are
each imagined H steps ahead on the world model's prior (the actor's mean after the first action, z_t the prior's mode)
and scored with Eq. 4's own objective: sum_k gamma^(k-1) r^goal(s_k, g) + gamma^H V(s_H, g), r^goal = -d (Eq. 7) and V
the run's critic. The real body takes the best candidate's first action (model-predictive control with a learned
value, as TD-MPC, Hansen et al. 2022; here the candidates are the clone's, so the choice stays within what the data
shows). K = 1 is the benchmark's own acting, action for action. With --while-down the choice is made only while the
body is down (posture below probes/getting_up.py's UP, read as probes/standing_subgoal.py reads it) and the actor's
mean is taken once up: getting up is where a benchmark episode's luck lies, and d reads a pose, not a speed. Every
variant on the benchmark's own start states and goals; each task's score minus plain acting is paired episode by
episode. With --giil-zs the same variants act in the tables' GIIL-ZS cells instead (every setting x task, each demo's
zero-shot goal on runner.imitate's evaluation seeds; plain acting there reproduces the committed GIIL-ZS rows).

    python probes/acting_value.py agents/walker --while-down [--candidates 8] [--horizon 5 15] [--eval-seed 40000] [--out rows.jsonl]  # ~5 min
    python probes/acting_value.py agents/walker --while-down --giil-zs [--settings SE-SV] [--out rows.jsonl]  # ~40 min
    python probes/acting_value.py --table docs/results/acting_value.jsonl   # or the --giil-zs rows
"""
import argparse
import os
import sys

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import collect  # noqa: E402
import configs  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import rundir  # noqa: E402
import runner  # noqa: E402
from probes.getting_up import LAST, UP  # noqa: E402
from probes.goal_variance import split  # noqa: E402
from probes.standing_subgoal import torso_posture  # noqa: E402


class Chooser:
    """The frozen actor choosing its real action among K candidates by their imagined goal return (module docstring).
    on_state(state) keeps the filtered state s_t that act(feat, goal) then plans from (evaluate.run_episodes calls them
    in that order)."""

    def __init__(self, models, candidates, horizon, gamma, read_posture=None, below=None):
        self.wm, self.actor, self.dist_net, self.critic = (models[k] for k in ("world_model", "actor", "dist_net", "critic"))
        self.K, self.H, self.gamma, self.state = candidates, horizon, gamma, None
        self.read_posture, self.below = read_posture, below  # read_posture() -> (N,); below: choose only at a posture below it (None: always)
        self.posture = []  # (steps, N): the posture each action was chosen at, where read_posture is given

    def on_state(self, state):
        self.state = state

    def scores(self, state, goal, first):
        """Imagined goal return of each first action: state dict of (M, .), goal (M, G), first (M, A) -> (M,)."""
        wm, actor = self.wm, self.actor
        state = wm.img_step(state, first, sample=False)
        total, discount = torch.zeros(first.shape[0]), 1.0
        for k in range(self.H):
            feat = wm.feat(state)
            total = total - discount * self.dist_net(feat, goal)  # r^goal(s_{k+1}, g) = -d on arrival
            discount *= self.gamma
            if k + 1 < self.H:
                state = wm.img_step(state, actor.act(feat, goal), sample=False)
        return total + discount * self.critic(wm.feat(state), goal)

    def act(self, feat, goal):
        if self.read_posture is not None:
            self.posture.append(self.read_posture())
        mean, std = self.actor.distribution(feat, goal)
        if self.K == 1:
            return torch.tanh(mean)
        N, A = mean.shape
        u = mean[:, None] + std[:, None] * torch.randn(N, self.K, A)  # drawn for every episode: the same draws whoever chooses
        u[:, 0] = mean  # candidate 0: the action plain acting takes
        first = torch.tanh(u)
        choose = torch.as_tensor(self.posture[-1] < self.below) if self.below else torch.ones(N, dtype=torch.bool)
        if choose.any():  # only the episodes that choose imagine their candidates
            state = {k: v[choose].repeat_interleave(self.K, 0) for k, v in self.state.items() if k in self.wm.state_keys}
            scores = self.scores(state, goal[choose].repeat_interleave(self.K, 0), first[choose].flatten(0, 1))
            first[choose, 0] = first[choose, scores.reshape(-1, self.K).argmax(1)]
        return first[:, 0]


def act_through(models, cfgs, task, goals, seed, steps, K, H, below):
    """One episode of `steps` per goal of `task` from env seeds seed, seed + 1, ..., acting through a Chooser -> scores
    (N,), up at the end (N,) (getting_up.py's rule)."""
    body = cfgs["train"].env
    env_list = [envs.make_env(body, task) for _ in range(len(goals))]
    read = lambda: np.array([torso_posture(body, env) for env in env_list])
    chooser = Chooser(models, K, H, cfgs["ac"].gamma, read, below)
    returns, _ = evaluate.run_episodes(env_list, {**models, "actor": chooser}, goals, steps, cfgs["wm"].obs, seed,
                                       on_state=chooser.on_state)
    for env in env_list:
        env.close()
    return np.array([evaluate.episode_score(task, r, steps) for r in returns]), np.stack(chooser.posture)[-LAST:].mean(0) >= UP


def episodes(models, cfgs, task, K, H, below, seed):
    """The benchmark's episodes of `task` -> scores (E,), up at the end (E,)."""
    tc = cfgs["train"]
    goals = evaluate.demo_goals(models, tc.env, task, tc.data, tc.eval_episodes)
    return act_through(models, cfgs, task, goals, seed, tc.eval_steps, K, H, below)


def imitate_config(cfgs):
    """The ImitateConfig of the run's preset, as `python imitate.py` or `tables.py` evaluates it without flags."""
    return configs.ImitateConfig(**configs.PRESETS["imitate"][cfgs["train"].preset])


def zero_shot_cell(models, cfgs, task, where, K, H, below, seed):
    """The tables' GIIL-ZS cell `where` of `task` as runner.imitate evaluates it: g = q(s | p_T) of each demo k,
    eval_episodes each from env seeds seed + 100 k + e (runner.EVAL_SEED: the tables' own), the ImitateConfig of the run's
    preset -> scores, up at the end (demos x episodes,). With K = 1 and the tables' seed they are the GIIL-ZS rows'
    episode_scores."""
    demo, view = envs.demo_of(cfgs["train"].env, task, where)
    demos = collect.load_folder(checkpoint.demo_folder(cfgs, demo, view), ("p",))
    ic = imitate_config(cfgs)
    out = [act_through(models, cfgs, task, models["goal_vae"].goal(torch.as_tensor(d["p"][-1]))[None].expand(ic.eval_episodes, -1),
                       seed + 100 * k, ic.eval_steps, K, H, below) for k, d in enumerate(demos)]
    return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])


def table(rows):
    """Markdown: a line per agent and variant; each task's score (plain acting) or minus plain acting, paired by episode,
    their average (its s.e. from the tasks' independent episodes), each task's share of episodes up at the end and its
    episode s.d. within a goal (the issue's luck, goal_variance.split)."""
    tasks = " / ".join(envs.BODY_TASKS)
    out = ["| agent | variant | " + " | ".join(envs.BODY_TASKS) + f" | average | up at the end ({tasks}) | episode s.d. ({tasks}) |",
           "|---|---|" + "---|" * (len(envs.BODY_TASKS) + 3)]
    for key in dict.fromkeys((r["run"], r["variant"]) for r in rows):
        sel = {r["task"]: r for r in rows if (r["run"], r["variant"]) == key}  # a rerun's row replaces the earlier
        if len(sel) < len(envs.BODY_TASKS):
            out.append(f"| {key[0]} | {key[1]} | " + " | ".join("-" for _ in envs.BODY_TASKS) + " | incomplete | - | - |")
            continue
        sel = [sel[t] for t in envs.BODY_TASKS]
        plain = key[1].split(",")[0] == "K 1"  # plain acting
        cells = [average([r], plain) for r in sel] + [average(sel, plain) if plain else f"**{average(sel, plain)}**"]
        up = " / ".join(f"{r['up_at_end']:.2f}" if "up_at_end" in r else "-" for r in sel)  # rows before it was read: -
        sd = " / ".join(f"{r['episode_sd']:.1f}" if "episode_sd" in r else "-" for r in sel)
        out.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + f" | {up} | {sd} |")
    return "\n".join(out)


def average(sel, plain):
    """One cell of a table over the rows `sel`: plain acting's mean score, or the mean of the rows' differences to
    plain acting with the s.e. of their independent episodes; '-' where a row is missing."""
    if any(r is None for r in sel):
        return "-"
    if plain:
        return f"{np.mean([r['score'] for r in sel]):.1f}"
    return f"{np.mean([r['minus_plain'] for r in sel]):+.1f} +- {np.sqrt(sum(r['minus_plain_se'] ** 2 for r in sel)) / len(sel):.1f}"


def zero_shot_table(rows):
    """Markdown for --giil-zs rows: a line per agent and variant; each setting's average over its tasks, the cross
    settings' (w/o SE-SV, as the tables show it) and each task's over the settings."""
    groups = [(w, [(t, w) for t in envs.TASKS]) for w in envs.SETTINGS]
    groups += [("w/o SE-SV", [(t, w) for w in envs.SETTINGS if w != "SE-SV" for t in envs.TASKS])]
    groups += [(t, [(t, w) for w in envs.SETTINGS]) for t in envs.TASKS]
    out = ["| agent | variant | " + " | ".join(name for name, _ in groups) + " |", "|---|---|" + "---|" * len(groups)]
    for key in dict.fromkeys((r["run"], r["variant"]) for r in rows):
        sel = {(r["task"], r["setting"]): r for r in rows if (r["run"], r["variant"]) == key}  # a rerun's row replaces the earlier
        cells = [average([sel.get(c) for c in members], key[1].split(",")[0] == "K 1") for _, members in groups]
        out.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="a trained run or shipped agent, e.g. agents/walker")
    parser.add_argument("--table", nargs="+", help="print the table of these rows and stop")
    parser.add_argument("--candidates", type=int, default=8, help="K: first actions scored per real step (1: plain acting only)")
    parser.add_argument("--horizon", type=int, nargs="+", default=[15], help="H: imagined steps per candidate (15: Eq. 4's horizon, chosen over 5)")
    parser.add_argument("--while-down", dest="below", action="store_const", const=UP, help="choose only while the body is down (module docstring)")
    parser.add_argument("--eval-seed", type=int, help="the episodes' first env seed (default: the run's benchmark's, 30000, or with --giil-zs the tables' 20000; "
                        "40000: fresh start poses, to confirm a choice made on the benchmark's)")
    parser.add_argument("--giil-zs", action="store_true", help="the tables' GIIL-ZS cells instead of the benchmark (zero_shot_cell)")
    parser.add_argument("--settings", nargs="+", default=list(envs.SETTINGS), choices=envs.SETTINGS, help="with --giil-zs")
    parser.add_argument("--tasks", nargs="+", choices=envs.TASKS, help="default: the benchmark's (stand, walk, run); with --giil-zs all four")
    parser.add_argument("--out", help="append a row per variant and task to this JSONL")
    args = parser.parse_args()
    if args.table:
        rows = [r for path in args.table for r in rundir.read_jsonl(path)]
        print(zero_shot_table(rows) if rows and "setting" in rows[0] else table(rows))
        return
    if not args.run:
        parser.error("give a run, e.g. agents/walker, or --table rows.jsonl")
    if args.candidates < 1 or min(args.horizon) < 1:
        parser.error(f"--candidates {args.candidates} --horizon {args.horizon}: give K >= 1 and H >= 1 (K = 1: plain acting only)")
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as train.py's benchmark computes, so that plain acting is the run's own, episode for episode
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    default_seed = runner.EVAL_SEED if args.giil_zs else cfgs["train"].eval_seed  # the tables' or the benchmark's
    seed = default_seed if args.eval_seed is None else args.eval_seed
    down = ", while down" if args.below else ""
    fresh = "" if args.eval_seed is None else f", seed {seed}"
    variants = [(f"K 1{fresh}", 1, 1)] + [(f"K {args.candidates}, H {h}{down}{fresh}", args.candidates, h) for h in args.horizon if args.candidates > 1]
    if args.giil_zs:
        cells = [c for c in envs.cells(cfgs["train"].env) if c[0] in (args.tasks or envs.TASKS) and c[1] in args.settings]
    else:
        cells = [(task, None) for task in args.tasks or envs.BODY_TASKS]
    plain = {}
    for name, K, H in tqdm(variants, desc="variants"):
        for task, where in cells:
            with torch.no_grad():
                if where:
                    scores, up_end = zero_shot_cell(models, cfgs, task, where, K, H, args.below, seed)
                else:
                    scores, up_end = episodes(models, cfgs, task, K, H, args.below, seed)
            plain.setdefault((task, where), scores)
            minus = scores - plain[task, where]
            per_goal = (imitate_config(cfgs) if where else cfgs["train"]).eval_episodes  # episodes of a goal lie side by side
            row = {"run": args.run, "weights": rundir.weights_id(ckpt), "variant": name, **({"setting": where} if where else {}),
                   "task": task, "episodes": len(scores), "eval_seed": seed, "score": round(float(scores.mean()), 2),
                   "se": round(float(evaluate.stderr(scores)), 2), "minus_plain": round(float(minus.mean()), 2),
                   "minus_plain_se": round(float(evaluate.stderr(minus)), 2), "up_at_end": round(float(up_end.mean()), 3),
                   "episode_sd": round(split(scores.reshape(-1, per_goal))[1], 2)}  # within a goal (goal_variance.split)
            print(row, flush=True)
            if args.out:
                rundir.append_jsonl(args.out, row)


if __name__ == "__main__":
    main()
