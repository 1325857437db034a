"""Phase 1's getting-up probe: where the goal-reaching benchmark's points are lost, read through the body's posture.

The getting-up probe of docs/results.md (Where the points are lost): where the goal-reaching benchmark's points are lost, read
through the body's posture, the stand reward (3 standing + upright) / 4 (envs.posture: 1 upright at stand height;
walk and run multiply their speed term by it). Every episode starts from DMC's random pose and falls first. An episode
is "up at the end" when its mean posture over its last 100 steps is >= 0.8. Per task: the mean posture over all
steps, the share of episodes up at the end, the mean score of those up and of those down, and the mean of all.
Five readings:
* the agent: the benchmark's own episodes (same goals, seeds, threads and matmul route as `python train.py --evaluate`,
  so the last column is the benchmark's number to the digit);
* the D_body task episodes it was trained on (<data>/<body>, from their stored states; --data: another folder than
  the run's), with --data-too, and when those that end up are on the ground (landing);
* with --other-goals, each task also towards the goals of the other tasks' demos (does the goal decide the task,
  and does a stand goal get it up as often as a walk goal), and the posture the world model reads in each goal;
* with --data-goals, does the goal decide whether it gets up: the stand task with goals q(s | p_T) of D_body stand
  episodes that ended up, then of those that ended down (the first 30 of each by name, the benchmark's seeds);
* with --imagined, does the world model imagine getting up: on the fidelity benchmark's D_body episodes (held-out and
  as many training ones), each getting-up event (posture < 0.3 for 10 steps, then >= UP within 60) replayed open loop
  from 15 and from 40 steps before it with the data's own actions (world_model.replay), the decoded posture against
  the real one; what Eq. 4's actor can learn of getting up is what this imagination holds.
Run from the repository root:

    python probes/getting_up.py agents/stickman --data-too --data-goals
    python probes/getting_up.py agents/stickman --other-goals --data-too --data data/late
    python probes/getting_up.py agents/walker --imagined
"""
import argparse
import glob
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import collect  # noqa: E402
import configs  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import fidelity  # noqa: E402
import rundir  # noqa: E402

LAST, UP = 100, 0.8  # "up at the end": mean posture over the last LAST steps >= UP
LYING = 0.3  # on the ground: a getting-up event starts after 10 steps below it


def row(name, posture, scores):
    """One table row from posture (steps, episodes) and scores (episodes,)."""
    up = posture[-LAST:].mean(0) >= UP
    cell = lambda s: f"{s.mean():.1f} +- {evaluate.stderr(s):.1f} ({len(s)})" if len(s) else "-"
    return f"| {name} | {posture.mean():.2f} | {up.mean():.2f} | {cell(scores[up])} | {cell(scores[~up])} | {cell(scores)} |"


def agent_row(name, models, cfgs, body, task, p_goals, repeat=1):
    """The policy's episodes of `task` towards g = q(s | p) of each row of p_goals, each `repeat` times, seeds from the
    benchmark's eval_seed (30000). The goals are encoded before they are repeated, as the benchmark does: the same
    matmul shapes, so the same floats (a stickman's episode drifts apart from a last-digit difference in its goal)."""
    with torch.no_grad():
        goals = models["goal_vae"].goal(torch.as_tensor(p_goals)).repeat_interleave(repeat, 0)
    env_list = [envs.make_env(body, task) for _ in range(len(goals))]
    posture = []  # (steps, episodes)
    torso = lambda env: (env.physics.named.data.xpos["torso", "z"], env.physics.named.data.xmat["torso", "zz"])
    record = lambda env_list: posture.append([envs.posture(body, *torso(env)) for env in env_list])
    returns, _ = evaluate.run_episodes(env_list, models, goals, envs.EPISODE_STEPS, cfgs["wm"].obs, cfgs["train"].eval_seed, on_step=record)
    return row(name, np.array(posture), np.array([evaluate.episode_score(task, r, envs.EPISODE_STEPS) for r in returns]))


def demo_goals(cfgs, body):
    """{task: (10, D)}: the last video feature of each own-body side-view demo, the benchmark's goals before encoding."""
    folder = lambda task: os.path.join(cfgs["train"].data, "demos", f"{body}_{task}_side")
    return {task: np.stack([d["p"][-1] for d in collect.load_folder(folder(task), ("p",))]) for task in envs.BODY_TASKS}


def decoded_posture(models, body, p_goals):
    """The posture the world model's decoder reads in the goals q(s | p): is a stand goal a body standing?"""
    with torch.no_grad():
        obs = models["world_model"].decode(models["goal_vae"].goal(torch.as_tensor(p_goals))[:, None])[:, 0].numpy()
    return envs.observed_posture(body, obs).mean()


def agent_rows(models, cfgs, body, goals, other_goals=False):
    """As evaluate.goal_reaching: each demo's last feature (goals, demo_goals), the goal of 3 episodes; with
    other_goals, each task also towards the other tasks' demo goals."""
    for task in envs.BODY_TASKS:
        for goal_task in envs.BODY_TASKS if other_goals else (task,):
            name = task if goal_task == task else f"{task}, goals of {goal_task} demos"
            yield agent_row(name, models, cfgs, body, task, goals[goal_task], repeat=3)


def data_episodes(folder, body, task, keys=("state",)):
    """D_body's episodes of `task` and each one's posture (steps,) from its stored states."""
    episodes = [collect.load_episode(path, keys) for path in sorted(glob.glob(os.path.join(folder, f"{task}_*.npz")))]
    if not episodes:
        raise FileNotFoundError(f"no {task} episodes in {folder}: collect them with `python collect.py --env {body}`")
    return episodes, [envs.observed_posture(body, e["state"]) for e in episodes]


def data_rows(folder, body):
    for task in envs.BODY_TASKS:
        episodes, posture = data_episodes(folder, body, task)
        yield row(task, np.stack(posture, 1), np.array([float(envs.normalized_score(task, e["return"])) for e in episodes]))


def landing(posture):
    """When episodes that end up are on the ground: of posture, a list of (steps,) per episode, those up at the end,
    -> (their count, the median step of their lowest posture in the first 150 steps, the median first step after it
    back at posture >= UP)."""
    up = [p for p in posture if p[-LAST:].mean() >= UP]
    low = np.array([np.argmin(p[:150]) for p in up])
    again = np.array([k + np.argmax(p[k:] >= UP) for k, p in zip(low, up)])
    return len(up), float(np.median(low)), float(np.median(again))


def data_goal_rows(models, cfgs, folder, body):
    episodes, posture = data_episodes(folder, body, "stand", ("state", "p"))
    up = np.array([p[-LAST:].mean() >= UP for p in posture])
    for name, chosen in (("stand, goals of D_body episodes that ended up", up), ("stand, goals of those that ended down", ~up)):
        p_goals = np.stack([episodes[i]["p"][-1] for i in np.flatnonzero(chosen)[:30]])
        yield agent_row(name, models, cfgs, body, "stand", p_goals)


def getting_up_events(posture, before, after=20):
    """(episode, step) of each getting-up event (--imagined) in posture (E, L) with `before` steps before it and
    `after` after it in the episode; one per 100 steps at most."""
    events = []
    for e, p in enumerate(posture):
        t = max(10, before)
        while t < len(p) - after:
            up = np.flatnonzero(p[t : t + 60] >= UP) if (p[t - 10 : t] < LYING).all() else []
            if len(up) and t + up[0] + after < len(p):
                events.append((e, t + up[0]))
                t += up[0] + 100
            else:
                t += 1
    return events


@torch.no_grad()
def imagined_rows(models, cfgs, body, befores=(15, 40), after=20):
    """--imagined (module docstring): per `before`, the mean real, filtered and imagined posture at the event's start,
    at the event, `after` steps after it, and the share of events whose posture reaches UP from 10 steps before it."""
    wm, sources = models["world_model"], fidelity.held_out_episodes(cfgs)
    obs, action, is_first = (fidelity.stack(sources["body"] + sources["body_train"], k, "cpu") for k in (wm.cfg.obs, "action", "is_first"))
    posture, post = envs.observed_posture(body, obs.numpy()), wm.observe(obs, action, is_first, sample=False)[0]
    filtered = envs.observed_posture(body, wm.decode(wm.feat(post)).numpy())
    for before in befores:
        events = getting_up_events(posture, before, after)
        if not events:
            yield f"| {before} steps before | no getting-up event in these episodes | 0 | | | | |"
            continue
        e, t = (torch.tensor(v) for v in zip(*events))
        index = (t - before)[:, None] + torch.arange(1, before + after + 1)  # (N, before + after): the steps replayed
        imagined = evaluate.replay(wm, {k: v[e, t - before] for k, v in post.items()}, action[e[:, None], index])
        kinds = {"real": posture[e[:, None], index], "filtered posterior": filtered[e[:, None], index],
                 "imagined, open loop": envs.observed_posture(body, wm.decode(imagined).numpy())}
        for name, p in kinds.items():
            gets_up = (p[:, before - 10 :] >= UP).any(1).mean()
            yield (f"| {before} steps before | {name} | {len(e)} | {p[:, 0].mean():.2f} | {p[:, before - 1].mean():.2f} | "
                   f"{p[:, -1].mean():.2f} | {gets_up:.2f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run or agent folder, e.g. agents/stickman")
    parser.add_argument("--data-too", action="store_true", help="also the D_body task episodes of the run's data folder")
    parser.add_argument("--data-goals", action="store_true", help="also stand towards goals of D_body episodes that ended up / down")
    parser.add_argument("--other-goals", action="store_true", help="also each task towards the other tasks' demo goals")
    parser.add_argument("--imagined", action="store_true", help="instead: does the world model imagine D_body's getting-up events")
    parser.add_argument("--data", help="the data folder of D_body and the demos (default: the run's)")
    args = parser.parse_args()
    torch.set_num_threads(configs.TrainConfig.threads)  # the benchmark's threads and matmul route (train.py --evaluate):
    rundir.fast_matmul()  # other float sums change a stickman's episodes after a few steps
    cfgs, models, _ = checkpoint.load_run(args.run)
    cfgs["train"].data = args.data or cfgs["train"].data
    body = cfgs["train"].env
    if args.imagined:
        print(f"| {args.run}: replayed from | posture | events | at the start | at the event | 20 steps after | share up |\n|---|---|---|---|---|---|---|")
        print("\n".join(imagined_rows(models, cfgs, body)))
        return
    goals = demo_goals(cfgs, body)
    header = "| posture | up at the end | score of those up | score of those down | all |\n|---|---|---|---|---|---|"
    print(f"| {args.run} (benchmark episodes) {header}")
    print("\n".join(agent_rows(models, cfgs, body, goals, args.other_goals)))
    if args.other_goals and cfgs["wm"].obs == "state":  # the posture is read off a decoded state observation
        print("the demo goals q(s | p_T), read by the world model's decoder: posture",
              ", ".join(f"{task} {decoded_posture(models, body, p):.2f}" for task, p in goals.items()))
    folder = os.path.join(cfgs["train"].data, body)
    if args.data_too:
        print(f"\n| {folder} (D_body task episodes) {header}")
        print("\n".join(data_rows(folder, body)))
        for task in envs.BODY_TASKS:
            print("{}: {} episodes up at the end, lowest at step {:.0f}, up again at step {:.0f} (medians)".format(task, *landing(data_episodes(folder, body, task)[1])))
    if args.data_goals:
        print(f"\n| {args.run} (goals from {folder}) {header}")
        print("\n".join(data_goal_rows(models, cfgs, folder, body)))


if __name__ == "__main__":
    main()
