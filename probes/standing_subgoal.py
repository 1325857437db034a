"""Does a standing subgoal until the body is up make the goal-reaching benchmark's episodes depend less on luck?

Every benchmark episode starts from DMC's random pose, on the ground; whether the body gets up decides a stand episode
(within-goal episode s.d. 41 on the shipped walker's stand, probes/goal_variance.py) and a share of the walk and run
ones (probes/getting_up.py). The frozen policy is the same; only the goal it is fed changes, as a two-level policy
would (HIQL's subgoal, Park et al. 2023): while the body is down, the goal of another task's demo with the same
index (g_up), and the task's own goal once it is up. Down / up reads envs.posture (the stand reward without its
speed, 1 upright at stand height) against getting_up.py's UP = 0.8; the agent has it in its own state observation
(envs.observed_posture: torso zz and height are entries of o_t); the probe reads the same numbers from the physics.
Two rules:
  while   g_up at every step whose posture is below UP
  until   g_up until the first step at or above UP, the task's goal after it
  lying   g_up at every step whose posture is below LYING (on the ground; rising and a low gait keep the task's goal)
g_up is a task's own demo goals (labelled: what the benchmark gives), or with `data` the label-free choice: the final
goals q(s | p_T) of the 10 D_body episodes whose body is up the longest (highest mean posture over the episode).
Per task: the benchmark's mean score, its within-goal episode s.d. (each demo's goal has `eval_episodes` episodes)
and the share of episodes up at the end (getting_up.py's rule), every variant on the benchmark's own start states
(its first row equals the run's goal_reaching.json, episode for episode).

    python probes/standing_subgoal.py agents/walker [--up-goals stand walk] [--out rows.jsonl]   # ~1 min per variant and task
    python probes/standing_subgoal.py agents/walker --up-goals data --rules while until lying --episodes 10 --out rows.jsonl
    python probes/standing_subgoal.py --table docs/results/subgoal_walker.jsonl docs/results/subgoal_stickman.jsonl
"""
import argparse
import os
import sys

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import rundir  # noqa: E402
from probes.getting_up import LAST, LYING, UP  # noqa: E402


def torso_posture(body, env):
    data = env.physics.named.data
    return envs.posture(body, data.xpos["torso", "z"], data.xmat["torso", "zz"])


class Subgoal:
    """The frozen actor fed g_up instead of the task's goal while `rule` says the body is down (module docstring)."""

    def __init__(self, actor, read_posture, g_up, rule):
        self.actor, self.read_posture, self.g_up, self.rule = actor, read_posture, g_up, rule  # read_posture() -> (N,)
        self.been_up = None
        self.posture = []  # (steps, episodes): the posture each action was chosen at

    def act(self, feat, goals):
        posture = self.read_posture()
        self.posture.append(posture)
        self.been_up = (posture >= UP) | (False if self.been_up is None else self.been_up)
        if self.g_up is None:
            return self.actor.act(feat, goals)
        down = {"while": posture < UP, "until": ~self.been_up, "lying": posture < LYING}[self.rule]
        return self.actor.act(feat, torch.where(torch.as_tensor(down, device=goals.device)[:, None], self.g_up, goals))


def data_up_goals(models, cfgs, n=10):
    """The label-free g_up: q(s | p_T) of the n D_body episodes with the highest mean posture -> (n, F)."""
    body_ep = checkpoint.body_episodes(cfgs, ("state", "p"))
    posture = np.array([envs.observed_posture(cfgs["train"].env, e["state"]).mean() for e in body_ep])
    best = np.argsort(-posture, kind="stable")[:n]
    return models["goal_vae"].goal(torch.as_tensor(np.stack([body_ep[i]["p"][-1] for i in best])))


def episodes(models, cfgs, task, g_up, rule, per_goal):
    """The benchmark's episodes of `task` (per_goal per demo) with the subgoal -> (scores (E,), up at the end (E,))."""
    tc, body = cfgs["train"], cfgs["train"].env
    goals = evaluate.demo_goals(models, body, task, tc.data, per_goal)
    env_list = [envs.make_env(body, task) for _ in range(len(goals))]
    switch = Subgoal(models["actor"], lambda: np.array([torso_posture(body, env) for env in env_list]), g_up, rule)
    returns, _ = evaluate.run_episodes(env_list, {**models, "actor": switch}, goals, tc.eval_steps, cfgs["wm"].obs, tc.eval_seed)
    for env in env_list:
        env.close()
    return np.array([evaluate.episode_score(task, r, tc.eval_steps) for r in returns]), np.stack(switch.posture)[-LAST:].mean(0) >= UP


def within_goal_sd(scores, per_goal):
    """The mean over goals of the s.d. of each goal's episodes (scores ordered goal by goal, per_goal each)."""
    return float(np.mean(np.std(np.reshape(scores, (-1, per_goal)), axis=1, ddof=1)))


def table(rows):
    """Markdown: a line per agent, episodes per task and variant; each task's score, and minus no subgoal (paired)."""
    out = ["| agent | episodes | g_up, rule | " + " | ".join(envs.BODY_TASKS) + " | up at the end (" + " / ".join(envs.BODY_TASKS) + ") |",
           "|---|---|---|" + "---|" * len(envs.BODY_TASKS) + "---|"]
    for key in dict.fromkeys((r["run"], r["episodes"], r["variant"]) for r in rows):
        sel = {r["task"]: r for r in rows if (r["run"], r["episodes"], r["variant"]) == key}
        cell = lambda r: "-" if r is None else (f"{r['score']:.1f}" if key[2] == "none" else f"{r['minus_none']:+.1f} +- {r['minus_none_se']:.1f}")
        up = " / ".join("-" if t not in sel else f"{sel[t]['up_at_end']:.2f}" for t in envs.BODY_TASKS)
        out.append(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cell(sel.get(t)) for t in envs.BODY_TASKS) + f" | {up} |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="a trained run or shipped agent, e.g. agents/walker")
    parser.add_argument("--table", nargs="+", help="print the table of these rows and stop")
    parser.add_argument("--up-goals", nargs="+", default=["stand", "walk"], choices=envs.BODY_TASKS + ("data",),
                        help="g_up: this task's demo goals, or data: the label-free choice (module docstring)")
    parser.add_argument("--rules", nargs="+", default=["while", "until"], choices=["while", "until", "lying"])
    parser.add_argument("--tasks", nargs="+", default=list(envs.BODY_TASKS), choices=envs.BODY_TASKS)
    parser.add_argument("--episodes", type=int, help="episodes per demo goal (default: the run's benchmark's, eval_episodes)")
    parser.add_argument("--out", help="append a row per variant and task to this JSONL")
    args = parser.parse_args()
    if args.table:
        print(table([r for path in args.table for r in rundir.read_jsonl(path)]))
        return
    if not args.run:
        parser.error("give a run, e.g. agents/walker, or --table rows.jsonl")
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as train.py's benchmark computes, so that the first row is the run's own, episode for episode
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    tc = cfgs["train"]
    per_goal = args.episodes or tc.eval_episodes
    variants = [("none", None, None)] + [(f"{rule} {up}", up, rule) for up in args.up_goals for rule in args.rules]
    with torch.no_grad():  # D_body's label-free g_up, read once
        data_goals = data_up_goals(models, cfgs).repeat_interleave(per_goal, 0) if "data" in args.up_goals else None
    base = {}
    for name, up, rule in tqdm(variants, desc="variants"):
        for task in args.tasks:
            with torch.no_grad():
                if up == "data":
                    g_up = data_goals
                else:
                    g_up = evaluate.demo_goals(models, tc.env, up, tc.data, per_goal) if up else None
                scores, up_end = episodes(models, cfgs, task, g_up, rule, per_goal)
            base.setdefault(task, scores)
            row = {"run": args.run, "weights": rundir.weights_id(ckpt), "variant": name, "task": task, "episodes": len(scores), "score": round(float(scores.mean()), 2),
                   "se": round(float(evaluate.stderr(scores)), 2), "minus_none": round(float((scores - base[task]).mean()), 2),
                   "minus_none_se": round(float(evaluate.stderr(scores - base[task])), 2),
                   "within_goal_sd": round(within_goal_sd(scores, per_goal), 1), "up_at_end": round(float(up_end.mean()), 3)}
            print(row, flush=True)
            if args.out:
                rundir.append_jsonl(args.out, row)


if __name__ == "__main__":
    main()
