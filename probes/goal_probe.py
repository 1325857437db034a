"""Eq. 5's probe: does an objective rank a cell's candidate goals as the true task score does, and which factor loses it?

Candidates: the zero-shot goals q(s | p_T) of the cell's 10 demos (GIIL-ZS's goals). Every goal acts in the agent's own
environment from the same `--seeds` start states (one batch per seed, every goal from that seed's start). Each goal is
scored by the true task score (Eq. 8; the target, never shown to any objective) and by objectives that differ from
Eq. 5's imagined J one factor at a time:
  eq5            Eq. 5 as finetune_goal computes it: 64 imagined rollouts of 15 steps from goal-encoder states of
                 demo frames t0, OT against the demo frames after t0 (windowed); the mean reward per step
  demo_h15       the same starts, each segment against whole demos                     (factor: the matching)
  own_h15        64 starts drawn from the agent's own filtered states of these episodes (pooled over every goal,
                 so the same for each), whole-demo OT                                  (factor: the start states)
  own0_h100      from s_0, the filtered state at each seed's reset (the env's start distribution), 100 steps
  own0_h500      the same, the whole episode imagined                                  (factor: the horizon)
  own0_h500_mean the same with the actor's mean action, as the agent acts in the env  (factor: acting noise)
  own0_h500_det  the same with the prior's mean too: imagination without noise        (factor: the prior's samples)
  replay         from s_0, the real episode's own actions replayed open loop through the prior (means)
                                                                                       (factor: closed loop vs the dynamics)
  posterior      the goal decoder's features of the real episode's filtered states     (factor: the world model's error)
  real           the run's video encoder on the real episode's rendered frames: the OT reward of real rollouts
                                                                                       (factor: decoded vs rendered features)
Imagined rollouts share their noise across goals (the same torch seed). Per cell: Spearman's rank correlation over
the 10 goals of each objective against the true score (each goal's mean over the seeds); the world model's error along
the rollout, the cosine between the goal decoder's features of the replayed and of the filtered states at steps 15,
100 and 500 (1 = the imagination sees what the filter sees); rows appended to --out.

    python probes/goal_probe.py agents/walker [--settings SE-SV,SE-CV] [--seeds 3] [--out docs/results/goal_probe_walker.jsonl]
    python probes/goal_probe.py --table docs/results/goal_probe_*.jsonl
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
import online  # noqa: E402
import ot_reward  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
import video_encoder  # noqa: E402

OBJECTIVES = ("eq5", "demo_h15", "own_h15", "own0_h100", "own0_h500", "own0_h500_mean", "own0_h500_det", "replay", "posterior", "real")
ERROR_STEPS = (15, 100, 500)


@torch.no_grad()
def imagined_j(models, start, goal, horizon, demo_p, ot_cfg, offsets=None, mean_action=False, prior_mean=False, seed=0):
    """Mean OT reward per step of rollouts of `horizon` steps from start (dict of (N, .)) given goal (F,), decoded."""
    wm, actor, vae = models["world_model"], models["actor"], models["goal_vae"]
    N = len(start["deter"])
    goals = goal.expand(N, -1)
    torch.manual_seed(seed)  # the same imagination noise for every goal
    if mean_action:  # the actor's tanh(mean), as it acts in the env (policy.Actor.act at temperature 0)
        state, feats = {k: start[k] for k in wm.state_keys}, [wm.feat(start)]
        for _ in range(horizon):
            state = wm.img_step(state, actor.act(feats[-1], goals), sample=not prior_mean)
            feats.append(wm.feat(state))
        feat = torch.stack(feats, 1)
    else:
        feat = policy.rollout(wm, actor, start, goals, horizon)[0]
    reward, _ = ot_reward.ot_reward(vae.decode(feat[:, 1:]), demo_p, ot_cfg, offsets)
    return reward.mean().item()


@torch.no_grad()
def replayed(models, post, goals):
    """The real episodes' actions (the actor's tanh(mean) given each filtered state and goal: how it acted) replayed
    open loop from s_0 through the prior's means: post dict of (G, T + 1, .), goals (G, F) -> feat (G, T + 1, F)."""
    wm, actor = models["world_model"], models["actor"]
    actions = actor.act(wm.feat(post)[:, :-1].flatten(0, 1), goals.repeat_interleave(post["deter"].shape[1] - 1, 0))
    actions = actions.view(len(goals), -1, actions.shape[-1])  # (G, T, A)
    state, feats = {k: post[k][:, 0] for k in wm.state_keys}, [wm.feat({k: v[:, 0] for k, v in post.items()})]
    for t in range(actions.shape[1]):
        state = wm.img_step(state, actions[:, t], sample=False)
        feats.append(wm.feat(state))
    return torch.stack(feats, 1)


def probe_cell(models, cfgs, encoder, task, demo_p, seeds, ot_cfg, steps, n_starts=64):
    """{objective: (G,) scores} and the true scores (G,) of the G zero-shot goals of demo_p (K, M, D)."""
    wm, vae, tc = models["world_model"], models["goal_vae"], cfgs["train"]
    demo_t = torch.as_tensor(demo_p)
    with torch.no_grad():
        goals = vae.goal(demo_t[:, -1])
    G = len(goals)
    true, real, post_ot, replay_ot, error, pool, s0 = [], [], [], [], [], [], []
    for seed in seeds:  # real episodes: every goal from this seed's start state
        states = []
        env_list = [envs.make_env(tc.env, task) for _ in range(G)]
        returns, frames = evaluate.run_episodes(env_list, models, goals, steps, cfgs["wm"].obs, [seed] * G, render=True,
                                                on_state=lambda s: states.append({k: v.clone() for k, v in s.items()}))
        for env in env_list:
            env.close()
        true.append([evaluate.episode_score(task, r, steps) for r in returns])
        real.append(online.ot_score(np.stack([encoder(f) for f in frames]), demo_p, ot_cfg) / (steps + 1))
        post = {k: torch.stack([s[k] for s in states], 1) for k in states[0]}  # (G, T + 1, .)
        with torch.no_grad():
            post_p, replay_p = vae.decode(wm.feat(post)), vae.decode(replayed(models, post, goals))
            post_ot.append(ot_reward.ot_reward(post_p, demo_t, ot_cfg)[0].mean(1).numpy())
            replay_ot.append(ot_reward.ot_reward(replay_p, demo_t, ot_cfg)[0].mean(1).numpy())
            error.append([(post_p[:, min(t, steps)] * replay_p[:, min(t, steps)]).sum(-1).mean().item() for t in ERROR_STEPS])
        pool.append({k: v.flatten(0, 1) for k, v in post.items()})
        s0.append({k: v[:1, 0] for k, v in post.items()})  # the same start for every goal: the reset's filtered state
    pool = {k: torch.cat([p[k] for p in pool]) for k in pool[0]}
    s0 = {k: torch.cat([s[k] for s in s0]).repeat(2, 1) for k in s0[0]}  # each start twice: 2 noise draws
    gen = torch.Generator().manual_seed(0)
    K, M = demo_t.shape[:2]
    t0 = torch.randint(M - cfgs["ac"].horizon - 1, (n_starts,), generator=gen)
    with torch.no_grad():
        demo_start = vae.encode(demo_t[torch.randint(K, (n_starts,), generator=gen), t0])
    demo_start = {k: demo_start[k] for k in wm.state_keys}
    own_start = {k: v[torch.randint(len(pool["deter"]), (n_starts,), generator=gen)] for k, v in pool.items()}
    H = cfgs["ac"].horizon
    out = {obj: [] for obj in OBJECTIVES}
    for g in tqdm(goals, desc="imagined J", leave=False):
        out["eq5"].append(imagined_j(models, demo_start, g, H, demo_t, ot_cfg, t0 + 1))
        out["demo_h15"].append(imagined_j(models, demo_start, g, H, demo_t, ot_cfg))
        out["own_h15"].append(imagined_j(models, own_start, g, H, demo_t, ot_cfg))
        out["own0_h100"].append(imagined_j(models, s0, g, 100, demo_t, ot_cfg))
        out["own0_h500"].append(imagined_j(models, s0, g, steps, demo_t, ot_cfg))
        out["own0_h500_mean"].append(imagined_j(models, s0, g, steps, demo_t, ot_cfg, mean_action=True))
        out["own0_h500_det"].append(imagined_j(models, s0, g, steps, demo_t, ot_cfg, mean_action=True, prior_mean=True))
    out["replay"], out["posterior"], out["real"] = np.mean(replay_ot, 0), np.mean(post_ot, 0), np.mean(real, 0)
    return {k: np.asarray(v, float) for k, v in out.items()}, np.mean(true, 0), np.mean(error, 0)


def markdown(rows):
    """The probe's table: per run and cell, Spearman (objective, true score) over its goals; means over same-body and cross cells."""
    head = "| run | cell | true score: mean (best) | " + " | ".join(OBJECTIVES) + " | replay cos at 15 / 100 / 500 |"
    out = [head, "|---" * (head.count("|") - 1) + "|"]
    for r in rows:
        out.append(f"| {r['run']} | {r['setting']} {r['task']} | {np.mean(r['true']):.1f} ({max(r['true']):.1f}) | "
                   + " | ".join(f"{r['spearman'][k]:.2f}" for k in OBJECTIVES) + " | " + " / ".join(f"{v:.2f}" for v in r["replay_cos"].values()) + " |")
    for name, keep in (("same body (SE-SV, SE-CV)", "SE"), ("cross body (CE-SV, CE-CV)", "CE")):
        for run in sorted({r["run"] for r in rows}):
            sel = [r for r in rows if r["run"] == run and r["setting"].startswith(keep)]
            if sel:
                out.append(f"| {run} | mean of {len(sel)}, {name} | | " + " | ".join(
                    f"**{np.nanmean([r['spearman'][k] for r in sel]):.2f}**" for k in OBJECTIVES) + " | " + " / ".join(
                    f"{np.mean([list(r['replay_cos'].values())[i] for r in sel]):.2f}" for i in range(len(ERROR_STEPS))) + " |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="the phase-1 run whose agent is probed (none with --table)")
    parser.add_argument("--table", nargs="+", metavar="JSONL", help="print the markdown table of these probe rows and stop")
    parser.add_argument("--settings", default=",".join(envs.SETTINGS))
    parser.add_argument("--tasks", default=",".join(envs.TASKS))
    parser.add_argument("--seeds", type=int, default=3, help="shared start states (env seeds 60000 + i)")
    parser.add_argument("--out", help="the rows' JSONL (default docs/results/goal_probe_<agent>.jsonl); cells in it are skipped")
    args = parser.parse_args()
    if args.table:
        print(markdown([r for path in args.table for r in rundir.read_jsonl(path)]))
        return
    if not args.run:
        parser.error("pass a run folder (e.g. agents/walker) or --table JSONL ...")
    torch.set_num_threads(1)
    cfgs, models, _ = checkpoint.load_run(args.run)
    agent, data = cfgs["train"].env, cfgs["train"].data
    encoder = video_encoder.load_encoder(cfgs["train"].encoder)
    ot_cfg = configs.OTConfig()
    args.out = args.out or f"docs/results/goal_probe_{agent}.jsonl"
    done = {(r["run"], r["task"], r["setting"]) for r in rundir.read_jsonl(args.out)}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    for task, where in envs.cells(agent):
        if where not in args.settings.split(",") or task not in args.tasks.split(",") or (args.run, task, where) in done:
            continue
        demo, view = envs.demo_of(agent, task, where)
        demo_p = np.stack([d["p"] for d in collect.load_folder(os.path.join(data, "demos", f"{demo}_{view}"), ("p",))])
        scores, true, error = probe_cell(models, cfgs, encoder, task, demo_p, [60_000 + i for i in range(args.seeds)], ot_cfg, envs.EPISODE_STEPS)
        row = {"agent": agent, "run": args.run, "task": task, "setting": where, "seeds": args.seeds, "true": true.round(2).tolist(),
               **{k: v.tolist() for k, v in scores.items()},
               "replay_cos": dict(zip(map(str, ERROR_STEPS), error.round(3).tolist())), "spearman": {k: round(evaluate.spearman(v, true), 3) for k, v in scores.items()}}
        rundir.append_jsonl(args.out, row)
        print(f"{agent} {where} {task}: true {true.mean():.1f} (best {true.max():.1f}) | " + " ".join(f"{k} {v:.2f}" for k, v in row["spearman"].items()) + f" | replay cos {row['replay_cos']}", flush=True)


if __name__ == "__main__":
    main()
