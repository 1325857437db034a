"""Does Eq. 4 alone train a policy that reaches goals, on a trained run's frozen world model, and which guard helps?

A fresh actor and critic learn by Eq. 4 alone (policy.policy_losses, reward -d(s, g), no cloning) on the frozen world
model, goal VAE and distance network of a trained run, as GenRL's actors learn on its frozen world model; starts and
goals drawn as train.py draws them (policy.sample_starts, sample_goals on D_body batches). Guards, one factor each
against this control (`--horizon 15 --starts 256`, the cpu preset's):
* `--horizon 5 --starts 1024`: short rollouts from many real starts (offline DreamerV2's horizon 5, V-D4RL, Lu et al.
  2023; GenRL's starts: every posterior state of a batch): the imagination leaves the data for fewer steps;
* `--critic-real`: the critic also regressed on lambda-returns along the batch's real posterior sequences, each
  towards a goal sampled as the imagined ones are (DreamerV3's "repval", Hafner et al. 2023): its values are tied to
  states the data holds;
* `--distance td`: the reward -d of a distance fit first by temporal differences on the frozen world model's reading
  of D_body (probes/distance_probe.py's `td` reading, HILP's value learning), in place of the run's Eq. 7 network;
  `--distance eq7` its control, Eq. 7 fit afresh the same way (a fresh fit on the final world model, not the reading);
* another run: the frozen world model of another recipe (e.g. runs/walker_wm_os25_s0, latent overshooting).
With `--from-clone` the actor, critic and return scale are the run's own (its cloned, polished actor) instead of fresh
ones, and `--bc-anneal 1.0 0.1` keeps hindsight cloning (cloning.bc_loss) beside Eq. 4's actor loss with a weight
annealed linearly from the first to the second value over the updates (ROT's schedule, Haldar et al. 2023): does Eq. 4
improve on the clone it starts from? The row then keeps the run's own benchmark average (its goal_reaching.json) beside
its own, paired by training seed in --summary.
Every `--log-every` updates it prints Eq. 4's imagined reward towards goals the data reached (evaluate.
reachable_goal_reward: the actor's, with another segment's goal, random actions); at the end the goal-reaching
benchmark (evaluate.goal_reaching) and the imagined minus real -d on the benchmark's episodes (probes/imagination_gap.py),
and appends one row to --out. Run from the repository root:

    python probes/eq4_probe.py agents/walker [--updates 3000] [--horizon 5 --starts 1024] [--critic-real] [--seed 0]
    python probes/eq4_probe.py agents/walker --from-clone --bc-anneal 1.0 0.1 --updates 2000 --horizon 5 --starts 1024 --distance td [--no-eq4]
    python probes/eq4_probe.py --summary docs/results/eq4_probe_walker.jsonl

With `--save-agent DIR` the actor after the stage is kept as an agent (save_agent), for the probes and commands that read
one (e.g. `python probes/acting_value.py DIR --giil-zs`: the tables' GIIL-ZS cells).
"""
import argparse
import dataclasses
import json
import os
import re
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import cloning  # noqa: E402
import collect  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
from probes import distance_probe, imagination_gap  # noqa: E402


def real_critic_loss(critic, slow_critic, dist_net, post_feat, goal, cfg):
    """DreamerV3's repval on D_body: V(s_t, g) along a real segment regressed to TD(lambda) returns of -d(s_{t+1}, g) and
    the slow critic's values. post_feat (B, T, F), goal (B, F) -> loss. Segments that cross an episode start are the
    data's; their returns mix two episodes (as a replay buffer's do)."""
    with torch.no_grad():
        reward = policy.goal_reward(dist_net, post_feat, goal)  # (B, T - 1)
        returns = policy.lambda_return(reward, slow_critic(post_feat, goal), cfg.gamma, cfg.lambda_)
    return policy.critic_loss(critic, post_feat, goal, returns)[0]


def bc_weight(anneal, step, updates):
    """The cloning's weight at `step` of `updates`: linear from anneal[0] to anneal[1] (ROT); 0 without --bc-anneal."""
    return 0.0 if anneal is None else anneal[0] + (anneal[1] - anneal[0]) * step / max(updates - 1, 1)


def train_eq4(models, cfgs, data, updates, critic_real, log_every, seed, from_clone=False, anneal=None, eq4=True):
    """An actor and critic trained `updates` steps by Eq. 4 (with cloning weighted bc_weight(anneal, ...) beside it); the
    world model, goal VAE and distance frozen. Fresh ones seeded from `seed`, or with from_clone the run's own. eq4
    False: the actor steps on the cloning alone (the control of Eq. 4's share). Returns the log rows."""
    wc, ac, cc = cfgs["wm"], cfgs["ac"], cfgs["cloning"]
    wm, vae, dist_net = models["world_model"], models["goal_vae"], models["dist_net"]
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    if not from_clone:
        models["actor"] = policy.Actor(ac, wm.feat_dim, wm.feat_dim, wm.action_dim)
        models["critic"], models["slow_critic"] = policy.make_critics(ac, wm.feat_dim, wm.feat_dim)
        models["return_norm"] = policy.ReturnNorm(ac.return_norm_decay)
    actor, critic, slow_critic, return_norm = (models[k] for k in ("actor", "critic", "slow_critic", "return_norm"))
    opt_actor, opt_critic = torch.optim.Adam(actor.parameters(), lr=ac.actor_lr), torch.optim.Adam(critic.parameters(), lr=ac.critic_lr)
    stop = lambda: "a smaller --ac-actor-lr or --ac-critic-lr in the run"
    log, t0 = [], time.time()
    for step in range(updates):
        batch = data.sample(wc.batch, rng, "cpu")
        with torch.no_grad():
            post, _ = wm.observe(batch[wc.obs], batch["action"], batch["is_first"])
            post_feat, goal_feat, final_goal = wm.feat(post), vae.goal(batch["p"]), vae.goal(batch["p_last"])
        start, index = policy.sample_starts(post, ac.starts)
        goals = policy.sample_goals(post_feat, goal_feat, index, batch["is_first"], ac.goal_mix, ac.goal_near)
        a_loss, c_loss, m = policy.policy_losses(wm, dist_net, actor, critic, slow_critic, return_norm, start, goals, ac)
        if critic_real:  # one goal per segment, drawn for its first state as the imagined ones are
            first = torch.arange(wc.batch) * wc.seq_len
            real_goals = policy.sample_goals(post_feat, goal_feat, first, batch["is_first"], ac.goal_mix, ac.goal_near)
            c_loss = c_loss + real_critic_loss(critic, slow_critic, dist_net, post_feat, real_goals, ac)
        if (weight := bc_weight(anneal, step, updates)) > 0:
            bc, m_bc = cloning.bc_loss(actor, post_feat, goal_feat, batch["action"], final_goal, cc.bc_final)
            a_loss, m = (a_loss if eq4 else 0.0) + weight * bc, m | m_bc
        rundir.checked_step(opt_actor, a_loss, "Eq. 4 actor loss", step, stop, ac.grad_clip)
        rundir.checked_step(opt_critic, c_loss, "Eq. 4 critic loss", step, stop, ac.grad_clip)
        policy.ema_update(slow_critic, critic, ac.slow_critic_rate)
        if (step + 1) % log_every == 0:
            reach = evaluate.reachable_goal_reward(wm, dist_net, actor, post, goal_feat, batch["is_first"], ac.horizon, seed=step)
            log.append({"step": step + 1, "reward": m["reward"], "value": m["value"], **reach} | ({"bc_loss": m["bc_loss"]} if "bc_loss" in m else {}))
            print(f"{step + 1}: reward {m['reward']:.3f} value {m['value']:.2f}" + (f" bc {m['bc_loss']:.2f}" if "bc_loss" in m else "") + " | reachable goals -d own / other goal / random: "
                  + " ".join(f"{r:.3f}" for r in reach["reward_reachable"]) + f" | {log_every / (time.time() - t0):.1f} upd/s", flush=True)
            t0 = time.time()
    return log


def save_agent(ckpt, models, out_dir):
    """DIR/checkpoint.pt: the run's checkpoint (its config and frozen models) with the actor, critic and return scale the
    stage trained, no optimisers or RNGs, as checkpoint.export_agent writes an agent; the distance network stays the
    run's own (a td reading fit here is the probe's). main refuses a DIR that holds a checkpoint before the stage runs."""
    path = os.path.join(out_dir, "checkpoint.pt")
    trained = {k: models[k].state_dict() for k in ("actor", "critic", "slow_critic", "return_norm")}
    agent = {k: ckpt[k] for k in ("config", "step", "encoder", "obs_shape", "action_dim", "p_dim")} | {"models": ckpt["models"] | trained}
    os.makedirs(out_dir, exist_ok=True)
    rundir.atomic_write(path, lambda f: torch.save(agent, f))
    return path


def summary(rows):
    """One line per (run, guard): the benchmark average over seeds, mean +- s.e., the gap and the reachable rewards; from
    the clone, also the average minus the run's own benchmark, paired by run. Runs that differ only in their training
    seed (runs/<name>_s<seed>) share a line, as runs/<name>_s*."""
    groups = {}
    for row in rows:
        start = "clone, bc {:g} -> {:g}".format(*row["bc_anneal"]) if row.get("bc_anneal") else "clone" if row.get("from_clone") else "fresh"
        start += "" if row.get("eq4", True) else ", no Eq. 4"
        groups.setdefault((re.sub(r"_s\d+$", "_s*", row["run"].rstrip("/")), start, row.get("distance", "run"), row["horizon"], row["starts"], row["critic_real"], row["updates"]), []).append(row)
    out = ["| run | actor | d | horizon | starts | critic on real | updates | seeds | goal reaching | minus its start (paired) | imagined minus real -d | -d own / other / random |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    cell = lambda x, digits: f"{np.mean(x):.{digits}f}" + (f" +- {evaluate.stderr(x):.{digits}f}" if len(x) > 1 else "")  # noqa: E731
    for (run, start, distance, horizon, starts, real, updates), group in groups.items():
        score, gap = [r["average"] for r in group], [r["gap"] for r in group]
        paired = [r["average"] - r["start_average"] for r in group if "start_average" in r]
        reach = np.mean([r["log"][-1]["reward_reachable"] for r in group if r["log"]] or [[np.nan] * 3], 0)
        out.append(f"| {run} | {start} | {distance} | {horizon} | {starts} | {'yes' if real else 'no'} | {updates} | {len(group)} | {cell(score, 1)} | "
                   f"{cell(paired, 1) if paired else '-'} | {cell(gap, 3)} | " + " / ".join(f"{r:.3f}" for r in reach) + " |")
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", nargs="?", help="a trained run whose world model, goal VAE and distance stay frozen, e.g. agents/walker")
    parser.add_argument("--summary", metavar="JSONL", help="instead: the rows of this probe, grouped by run and guard")
    parser.add_argument("--updates", type=int, default=3000)
    parser.add_argument("--horizon", type=int, default=None, help="imagined steps H (default: the run's)")
    parser.add_argument("--starts", type=int, default=None, help="imagination starts per update (default: the run's)")
    parser.add_argument("--critic-real", action="store_true", help="the critic also fit on real D_body sequences (repval)")
    parser.add_argument("--distance", choices=("run", "eq7", "td"), default="run", help="the run's Eq. 7 network, or one fit "
                        "first on the frozen world model: Eq. 7 as train.py fits it, or by temporal differences (distance_probe's readings)")
    parser.add_argument("--distance-updates", type=int, help="with --distance eq7 / td: its fit's updates (default 3000 / 20000, "
                        "distance_probe's)")
    parser.add_argument("--from-clone", action="store_true", help="start from the run's own actor, critic and return scale "
                        "(its cloned, polished actor) instead of fresh ones")
    parser.add_argument("--bc-anneal", type=float, nargs=2, metavar=("FIRST", "LAST"), help="hindsight cloning beside Eq. 4's "
                        "actor loss, its weight linear from FIRST to LAST over the updates (ROT: 1.0 0.1)")
    parser.add_argument("--no-eq4", action="store_true", help="with --from-clone --bc-anneal: the actor steps on the cloning "
                        "alone, the control of what Eq. 4's actor loss adds")
    parser.add_argument("--seed", type=int, default=0, help="of the fresh actor, critic and batches")
    parser.add_argument("--episodes", type=int, default=3, help="benchmark episodes per demo goal (the benchmark's own: 3)")
    parser.add_argument("--eval-steps", type=int, default=envs.EPISODE_STEPS, help="steps of each benchmark episode")
    parser.add_argument("--log-every", type=int, default=250)
    parser.add_argument("--data", help="D_body's folder for the starts, batches and fits (default the run's; an exported agent "
                        "stores data/, e.g. agents/stickman was trained on data/late)")
    parser.add_argument("--out", help="append the row here (default docs/results/eq4_probe_<body>.jsonl)")
    parser.add_argument("--save-agent", metavar="DIR", help="keep the actor after the stage as an agent in DIR (save_agent)")
    args = parser.parse_args()
    if args.summary:
        print("\n".join(summary([json.loads(line) for line in open(args.summary)])))
        return
    if not args.run:
        parser.error("name a trained run, or --summary JSONL")
    if args.no_eq4 and not (args.from_clone and args.bc_anneal):
        parser.error("--no-eq4 leaves the cloning alone: it goes with --from-clone and --bc-anneal")
    if args.save_agent and os.path.exists(os.path.join(args.save_agent, "checkpoint.pt")):
        parser.error(f"--save-agent {args.save_agent}: it holds a checkpoint already; name another folder")
    if args.bc_anneal and min(args.bc_anneal) < 0:
        parser.error(f"--bc-anneal {args.bc_anneal[0]:g} {args.bc_anneal[1]:g}: cloning weights are >= 0 (ROT's: 1.0 0.1)")
    torch.set_num_threads(1)
    rundir.fast_matmul()  # as train.py's benchmark computes, so that the run's own scores pair episode for episode
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    # the run's own benchmark on the same start states, to pair with (its averaged tasks those scored here)
    start = {t: float(np.mean(s["policy"])) for t, s in evaluate.read_goal_reaching(args.run)["scores"].items()} if args.from_clone else None
    ac = cfgs["ac"] = dataclasses.replace(cfgs["ac"], horizon=args.horizon or cfgs["ac"].horizon, starts=args.starts or cfgs["ac"].starts)
    tc = dataclasses.replace(cfgs["train"], data=args.data or cfgs["train"].data)  # D_body's; the benchmark's demos stay the run's
    _, data, _, _ = checkpoint.prepare_data({**cfgs, "train": tc})
    if args.distance != "run":
        wm = models["world_model"]
        body = collect.load_folder(os.path.join(tc.data, tc.env), (wm.cfg.obs, "action", "is_first", "p"))
        x, g = distance_probe.embedded_episodes(models, [e for k, e in enumerate(body) if k % tc.holdout_every])
        updates = args.distance_updates or (20000 if args.distance == "td" else 3000)
        reading = distance_probe.fit(x, g, updates=updates, seed=args.seed, **distance_probe.READINGS[args.distance]).requires_grad_(False)
        models["dist_net"] = distance_probe.DecodedDistance(reading, wm.decoder)
    log = train_eq4(models, cfgs, data, args.updates, args.critic_real, args.log_every, args.seed, args.from_clone, args.bc_anneal, not args.no_eq4)
    if args.save_agent:
        print("the agent after the stage:", save_agent(ckpt, models, args.save_agent))
    scores = evaluate.goal_reaching(models, cfgs, args.episodes, args.eval_steps, envs.BODY_TASKS)
    print("\n".join(evaluate.summary(scores)))
    gaps = [np.subtract(*imagination_gap.task_gap(models, cfgs, task)) for task in envs.BODY_TASKS]
    gap = float(np.concatenate(gaps).mean())
    print(f"imagined minus real -d on the benchmark's episodes: {gap:.3f}")
    row = {"run": args.run, "weights_id": rundir.weights_id(ckpt), "horizon": ac.horizon, "starts": ac.starts, "critic_real": args.critic_real,
           "distance": args.distance, "from_clone": args.from_clone, "bc_anneal": args.bc_anneal, "eq4": not args.no_eq4,
           "updates": args.updates, "seed": args.seed, "data": tc.data, "episodes": args.episodes, "gap": gap, "log": log,
           "scores": {t: float(np.mean(s["policy"])) for t, s in scores.items()},
           "average": float(np.mean([np.mean(s["policy"]) for s in scores.values()]))}
    if start:
        row["start_average"] = float(np.mean([start[t] for t in scores]))
        print(f"goal reaching {row['average']:.1f} against the run's own {row['start_average']:.1f}")
    out = args.out or os.path.join("docs", "results", f"eq4_probe_{cfgs['train'].env}.jsonl")
    rundir.append_jsonl(out, row)
    print("appended to", out)


if __name__ == "__main__":
    main()
