"""Ours, for Eq. 2: the world model's fidelity benchmark. Does imagination keep the episode?

Eq. 4 trains the policy and Eq. 5 infers the goal in the world model's imagination, so both are only as good as its
open-loop rollouts. On held-out episodes of the agent's own body (its side-view demos of the four tasks, expert episodes
never in D_body, and every `holdout_every`-th D_body episode, held out of training; beside them as many D_body
training episodes), each episode is filtered with the posterior's mode; from the filtered state at steps t0 = 10, 110,
210, 310 (at least 10 filtered steps of context) the prior imagines 100 steps open loop with the recorded actions (the
latent's mode, no sampling). At k steps ahead:

    error     the decoder's squared error per element of the imagined state (symlog space, world_model.open_loop_error)
    hold      the same for holding the last filtered observation o_t0: what imagining nothing earns
    cos       cosine of the goal decoder's p_hat of the imagined state and the recorded p_{t0 + k}: what Eq. 5's OT
              reward reads of imagination (1 = exact)
    filtered  the same for the filtered state at t0 + k: what the goal decoder reads of a true state (the ceiling)
and the held-out ELBO terms of Eq. 2 (recon, KL per step) on those episodes, of a run's checkpoint.

--ranking is the functional test, for a trained agent (world model and policy): on a same-body cell, does Eq. 5's
imagined objective rank goals as reality does? Candidates: the zero-shot goals q(s | p_T) of the cell's 10 demos and
10 draws of q(s | p_T) of its first demo (posterior_goals), whose outcomes differ. Each goal acts in the real
environment from the same `--episodes` start states (env seeds 60000 + i); its real score is Eq. 8's, averaged. Eq. 5's
J of a goal is the mean OT reward of the frozen policy's imagined rollouts, as GIIL-FT computes it (goal_inference.py): 256
starts from goal-encoder states of demo frames t0, `horizon` steps, matched against the demo frames after t0; every goal
from the same starts and imagination noise. Reported: Spearman (J, real score) over the 20 goals; the same for the
task reward of the same rollouts' decoded states (a probe of the imagination alone, without the OT reward); and the
cap the real score's own noise puts on both: sqrt of its split-half reliability (even against odd episodes,
Spearman-Brown).

    python fidelity.py agents/walker [--out docs/results/fidelity_walker.jsonl]
    python fidelity.py --table docs/results/fidelity_walker.jsonl [--png docs/fidelity_walker.png]
    python fidelity.py agents/walker --ranking [--settings SE-SV] [--episodes 10] [--out docs/results/ranking_walker.jsonl]
    python fidelity.py agents/walker --distance [--out docs/results/distance_walker.jsonl]

--distance asks Eq. 6-7's question of the same held-out episodes: does the temporal distance d(s_t, goal of frame
t + k) rise with k (distance_ranking)? Beside d it measures the observations' own distance: a walking or running body
returns to the same state every ~15 / ~10 steps (a gait's period) and a standing one hardly moves, so no function of
two states without their history can rank k along one episode, whatever Eq. 7 trains.
"""
import argparse
import os

import numpy as np
import torch

import checkpoint
import collect
import configs
import envs
import evaluate
import ot_reward
import policy
import rundir

STARTS = (10, 110, 210, 310)  # t0: where imagination leaves the filter (ours: 4 per 500-step episode, >= 10 steps of context)
AHEAD = 100  # steps imagined from each start
HORIZONS = (16, 50, 100)  # the reported k: GenRL's imagination horizon (16), and further
GAPS = (1, 5, 15, 50, 100)  # --distance: steps from a state to its goal


def sample_goals(vae, p, n, generator=None, scale=1.0):
    """Ours, for the ranking and the probes: n draws s^g ~ q(s | p) of the goal VAE `vae` as goal vectors, from
    `generator`'s standard normal noise multiplied by `scale` (a Gaussian's std times scale; a categorical z's draws
    flatter for scale > 1): p (1, D) -> (n, deter + stoch)."""
    assert p.shape == (1, vae.feat_dim), p.shape
    mean_h, std_h, stats = vae.distribution(p)
    noise = torch.randn(n, vae.deter + vae.stoch, generator=generator).to(mean_h.device)
    return vae._sample(mean_h, std_h, stats, scale * noise)


def posterior_goals(vae, p_last, n, seed):
    """q(s | p_T)'s mean (GIIL-ZS's goal) and n - 1 draws s^g ~ q(s | p_T) of the goal
    encoder's distribution (a Gaussian's mean + std * eps), their noise from `seed`. p_last (D,) -> (n, F)."""
    p = torch.as_tensor(p_last)[None]
    return torch.cat([vae.goal(p), sample_goals(vae, p, n - 1, torch.Generator().manual_seed(seed))])


def held_out_episodes(cfgs):
    """{source: episodes}: the body's own side-view demos per task, D_body's held-out episodes ('body') and as many of
    its training episodes ('body_train': the model keeps those it trained on, and not the held-out ones, where it is
    data-bound)."""
    tc, wc = cfgs["train"], cfgs["wm"]
    keys = (wc.obs, "action", "is_first", "p")
    out = {task: collect.load_folder(os.path.join(tc.data, "demos", f"{tc.env}_{task}_side"), keys) for task in envs.TASKS}
    body = checkpoint.body_episodes(cfgs, keys)
    out["body"], out["body_train"] = body[:: tc.holdout_every], body[1 :: tc.holdout_every]
    return out


def stack(episodes, key, device):
    """One key of episodes of equal length as a (E, L, ...) tensor."""
    return torch.as_tensor(np.stack([e[key] for e in episodes]), device=device)


@torch.no_grad()
def measure(wm, vae, episodes, starts=STARTS, ahead=AHEAD, seed=0):
    """The benchmark of one source's episodes (E of length L; module docstring): {'error', 'hold', 'cos', 'filtered'}
    each (ahead,) for k = 1..ahead, averaged over episodes x starts, and the held-out ELBO terms 'recon', 'kl'."""
    device = next(wm.parameters()).device
    obs, action, is_first, p = (stack(episodes, k, device) for k in (wm.cfg.obs, "action", "is_first", "p"))
    L = action.shape[1]
    ahead = min(ahead, L - 1 - starts[0])  # short episodes (the smoke preset's): fewer steps ahead
    starts = [t0 for t0 in starts if t0 + ahead < L]
    assert ahead > 0 and not is_first[:, 1:].any(), f"whole episodes of more than {starts[0] + 1} steps"
    with torch.random.fork_rng(devices=[]):  # the random numbers drawn here: seeded, the training RNG untouched
        torch.manual_seed(seed)
        _, elbo, _ = wm.loss({wm.cfg.obs: obs, "action": action, "is_first": is_first})  # the ELBO's posterior samples
        post, _ = wm.observe(obs, action, is_first, sample=False)  # (E, L, .)
    state = {k: torch.cat([v[:, t0] for t0 in starts]) for k, v in post.items()}  # (E * S, .), start-major
    index = torch.tensor(starts, device=device).repeat_interleave(len(obs))[:, None] + torch.arange(1, ahead + 1, device=device)
    row = torch.arange(len(obs), device=device).repeat(len(starts))[:, None]  # (E * S, 1): each start's episode
    imagined = evaluate.replay(wm, state, action[row, index])  # (E * S, ahead, F)
    space = wm._target(obs)  # (E, L, ...): observations in the decoder's space
    target = space[row, index]  # (E * S, ahead, ...)
    last = space[row[:, 0], index[:, 0] - 1][:, None]  # (E * S, 1, ...): o_t0, held
    per_step = lambda err: err.pow(2).flatten(2).mean(-1).mean(0)  # (ahead,)
    cos = lambda f: (vae.decode(f) * p[row, index]).sum(-1).mean(0)  # (ahead,)
    return {"error": per_step(wm._decode_raw(imagined) - target).tolist(), "hold": per_step(last - target).tolist(),
            "cos": cos(imagined).tolist(), "filtered": cos(wm.feat(post)[row, index]).tolist(),
            "recon": elbo["recon"], "kl": elbo["kl"], "episodes": len(obs), "starts": len(starts)}


def benchmark(models, sources, step, run):
    """measure() of every source -> one row: {run, step (the update), sources: {source: measure()}}."""
    wm, vae = models["world_model"], models["goal_vae"]
    rounded = lambda m: {k: np.round(v, 4).tolist() if isinstance(v, list) else round(v, 4) for k, v in m.items()}
    return {"run": run, "step": step, "sources": {name: rounded(measure(wm, vae, eps)) for name, eps in sources.items()}}


def at(curve, k, digits):
    """The value k steps ahead, '-' where the episodes were too short."""
    return f"{curve[k - 1]:.{digits}f}" if k <= len(curve) else "-"


def markdown(rows):
    """Per row and source: cos imagined (filtered) at each horizon, error against hold at each horizon, recon / KL."""
    h = " / ".join(map(str, HORIZONS))
    out = [f"| run | update | source | cos imagined at {h} | cos filtered at {h} | error at {h} | hold at {h} | recon / KL |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for name, m in r["sources"].items():
            cells = [" / ".join(at(m[key], k, 2) for k in HORIZONS) for key in ("cos", "filtered")]
            cells += [" / ".join(at(m[key], k, 3) for k in HORIZONS) for key in ("error", "hold")]
            out.append(f"| {r['run']} | {r['step']} | {name} | " + " | ".join(cells) + f" | {m['recon']:.2f} / {m['kl']:.2f} |")
    return "\n".join(out)


def distance_markdown(rows):
    """Per row, source and kind of goal: d at each gap, d to another episode's frame, both Spearman means."""
    g = " / ".join(map(str, GAPS))
    out = [f"| run | update | source | goal | d at k = {g} | another episode's | Spearman(k, d): per episode / per start |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        for name, kinds in r["distance"].items():
            for kind, m in kinds.items():
                out.append(f"| {r['run']} | {r['step']} | {name} | {kind} | {' / '.join(f'{v:.2f}' for v in m['d'])} | {m['other']:.2f} "
                           f"| {m['rho_episode']:.2f} / {m['rho_start']:.2f} |")
    return "\n".join(out)


def curve_markdown(rows):
    """One line per row (a run at an update), for a learning curve: the cosine imagined at each horizon averaged over the
    four tasks' demos, at 50 steps per source, and the held-out recon of D_body."""
    h = " / ".join(map(str, HORIZONS))
    sources = list(dict.fromkeys(name for r in rows for name in r["sources"]))
    out = [f"| run | update | demos' cos at {h} | cos at 50: " + " / ".join(sources) + " | held-out D_body recon / KL |", "|---|---|---|---|---|"]
    for r in rows:
        m = r["sources"]
        demos = [np.mean([m[t]["cos"][k - 1] for t in envs.TASKS]) if all(k <= len(m[t]["cos"]) for t in envs.TASKS) else None for k in HORIZONS]
        out.append(f"| {r['run']} | {r['step']} | " + " / ".join("-" if v is None else f"{v:.2f}" for v in demos) + " | "
                   + " / ".join(at(m[name]["cos"], 50, 2) if name in m else "-" for name in sources) + f" | {m['body']['recon']:.2f} / {m['body']['kl']:.2f} |")
    return "\n".join(out)


def plot(rows, path):
    """The picture to look at first: cosine against steps ahead per source, imagined (solid) beside filtered (dashed),
    the last row of each run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    last = {r["run"]: r for r in rows}
    sources = list(dict.fromkeys(name for r in last.values() for name in r["sources"]))
    fig, axes = plt.subplots(1, len(sources), figsize=(3.2 * len(sources), 3), sharey=True)
    for ax, name in zip(np.atleast_1d(axes), sources):
        for i, (run, r) in enumerate(last.items()):
            if name not in r["sources"]:
                continue
            m, color = r["sources"][name], f"C{i}"
            steps = np.arange(1, len(m["cos"]) + 1)
            ax.plot(steps, m["cos"], color=color, label=f"{run} ({r['step']})")
            ax.plot(steps, m["filtered"], color=color, linestyle="--")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("steps imagined")
        ax.set_ylim(-0.2, 1)
    np.atleast_1d(axes)[0].set_ylabel("cos(p_hat, p_t): imagined, filtered --")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.tight_layout()
    rundir.atomic_write(path, lambda name: fig.savefig(name, dpi=80), by_name=True)  # never through a link
    plt.close(fig)
    return path


@torch.no_grad()
def distance_ranking(wm, vae, dist_net, episodes, gaps=GAPS, every=10):
    """Eq. 6-7's promise on whole episodes (E of length L): d(s_t, goal of frame t + k) for t = 10, 20, ... and k in
    `gaps`, the goal as the filtered posterior state ('post') and as the goal encoder's q(s | p_{t+k}) ('enc'), and the
    same distance for the observations themselves ('obs': |symlog o_t - symlog o_{t+k}|, what a state without history
    tells apart; state observations only). Per kind: 'd' (len(gaps),) means, 'other' d to another episode's frame
    t + 1, 'rho_episode' the mean over episodes of Spearman(k, d averaged over t), 'rho_start' the mean over (episode,
    t) of Spearman(k, d)."""
    device = next(wm.parameters()).device
    obs, action, is_first, p = (stack(episodes, k, device) for k in (wm.cfg.obs, "action", "is_first", "p"))
    t = torch.arange(10, obs.shape[1] - max(gaps), every, device=device)
    post, _ = wm.observe(obs, action, is_first, sample=False)
    feat, x = wm.feat(post), wm._target(obs)
    kinds = {"post": (dist_net, feat, feat), "enc": (dist_net, feat, vae.goal(p))}  # d, from, to
    if wm.cfg.obs == "state":
        kinds["obs"] = (lambda a, b: (a - b).norm(dim=-1), x, x)
    out = {}
    for kind, (d, start, goal) in kinds.items():
        ahead = torch.stack([d(start[:, t], goal[:, t + k]) for k in gaps]).cpu().numpy()  # (K, E, starts)
        other = d(start[:, t], goal.roll(1, 0)[:, t + 1])
        rank = lambda d_k: evaluate.spearman(np.arange(len(gaps)), d_k)
        out[kind] = {"d": ahead.mean((1, 2)).round(4).tolist(), "other": round(other.mean().item(), 4),
                     "rho_episode": round(float(np.mean([rank(ahead[:, e].mean(1)) for e in range(len(obs))])), 3),
                     "rho_start": round(float(np.nanmean([rank(ahead[:, e, i]) for e in range(len(obs)) for i in range(len(t))])), 3)}
    return out


@torch.no_grad()
def imagined_objective(models, cfgs, task, goals, demo_p, ot_cfg, starts=256, seed=0):
    """Eq. 5's J of each goal: the mean OT reward r^ot of the frozen policy's imagined rollouts (the quantity L_GI's
    lambda-returns estimate), from goal-encoder states of demo frames t0 matched against the frames after t0, as
    goal_inference.finetune_goal; every goal from the same starts and noise. Beside it, a probe of the imagination alone: the
    mean task reward of the same rollouts' decoded states (envs.observed_reward; state observations only).
    goals (G, F), demo_p (K, M, D) -> J (G,), task reward (G,) (NaN with pixel observations)."""
    wm, vae, actor, H = models["world_model"], models["goal_vae"], models["actor"], cfgs["ac"].horizon
    demo_p = torch.as_tensor(demo_p, dtype=torch.float64)
    K, M = demo_p.shape[:2]
    gen = torch.Generator().manual_seed(seed)
    t0 = torch.randint(M - H - 1, (starts,), generator=gen)
    start = vae.encode(demo_p[torch.randint(K, (starts,), generator=gen), t0].float())
    start = {k: start[k] for k in wm.state_keys}
    j, reward = [], []
    with torch.random.fork_rng(devices=[]):
        for goal in goals:
            torch.manual_seed(seed)  # the same imagination noise for every goal
            feat = policy.rollout(wm, actor, start, goal.expand(starts, -1), H)[0][:, 1:]  # (N, H, F)
            j.append(ot_reward.ot_reward(vae.decode(feat), demo_p, ot_cfg, t0 + 1)[0].mean().item())
            state = wm.cfg.obs == "state"
            reward.append(envs.observed_reward(cfgs["train"].env, task, wm.decode(feat).numpy()).mean() if state else np.nan)
    return np.array(j), np.array(reward)


def real_scores(models, cfgs, task, goals, episodes, first_seed=60_000):
    """Eq. 8's score of each goal (G, F) in the real environment, every goal from the same start states (env seeds
    first_seed + i) -> (episodes, G)."""
    tc = cfgs["train"]
    steps = tc.eval_steps  # the goal-reaching benchmark's episode: 500 agent steps, the whole episode, at the cpu preset
    env_list = [envs.make_env(tc.env, task) for _ in range(len(goals))]
    out = []
    for i in range(episodes):
        returns, _ = evaluate.run_episodes(env_list, models, goals, steps, cfgs["wm"].obs, [first_seed + i] * len(goals))
        out.append([evaluate.episode_score(task, r, steps) for r in returns])
    for env in env_list:
        env.close()
    return np.array(out)


def rank_goals(models, cfgs, task, demo_p, episodes, ot_cfg, draws=10):
    """The functional test of one cell (module docstring) -> a row without its run and cell."""
    vae = models["goal_vae"]
    with torch.no_grad():
        goals = torch.cat([vae.goal(torch.as_tensor(demo_p[:, -1])), posterior_goals(vae, demo_p[0, -1], draws + 1, seed=0)[1:]])
    real = real_scores(models, cfgs, task, goals, episodes)  # (episodes, G)
    j, reward = imagined_objective(models, cfgs, task, goals, demo_p, ot_cfg)
    half = evaluate.spearman(real[0::2].mean(0), real[1::2].mean(0))
    reliability = 2 * half / (1 + half)  # Spearman-Brown: the reliability of the mean over all episodes
    return {"episodes": episodes, "real": real.mean(0).round(2).tolist(), "eq5": j.round(5).tolist(),
            "imagined_reward": reward.round(5).tolist(), "spearman": round(evaluate.spearman(j, real.mean(0)), 3),
            "spearman_reward": round(evaluate.spearman(reward, real.mean(0)), 3), "reliability": round(reliability, 3),
            "cap": round(float(np.sqrt(max(reliability, 0))), 3)}


def ranking(run, step, cfgs, models, settings, episodes, out):
    """rank_goals on each same-body cell of `settings` not yet in `out` for this run at this update, a row appended per cell."""
    if any(w not in ("SE-SV", "SE-CV") for w in settings):
        raise ValueError(f"--settings {','.join(settings)}: the ranking is measured on same-body cells (SE-SV, SE-CV); the "
                         "cross-domain cells are the test set, never used to choose")
    if episodes < 2:
        raise ValueError(f"--episodes {episodes}: must be >= 2 (the cap splits them in halves)")
    agent, data = cfgs["train"].env, cfgs["train"].data
    done = {(r["run"], r["step"], r["task"], r["setting"]) for r in rundir.read_jsonl(out)}
    for task, where in envs.cells(agent):
        if where not in settings or (run, step, task, where) in done:
            continue
        demo, view = envs.demo_of(agent, task, where)
        demo_p = np.stack([d["p"] for d in collect.load_folder(os.path.join(data, "demos", f"{demo}_{view}"), ("p",))])
        row = {"run": run, "step": step, "task": task, "setting": where, **rank_goals(models, cfgs, task, demo_p, episodes, configs.OTConfig())}
        rundir.append_jsonl(out, row)
        print(f"{where} {task}: Spearman(Eq. 5's J, real score) {row['spearman']:.2f} (cap {row['cap']:.2f}), real scores "
              f"{min(row['real']):.1f}..{max(row['real']):.1f}", flush=True)


def ranking_markdown(rows):
    reward = lambda r: f"{r['spearman_reward']:.2f}" if "spearman_reward" in r else "-"
    out = ["| run | update | cell | real score: mean (min..max) | Spearman(J, real) | Spearman(imagined task reward, real) | cap |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['run']} | {r['step']} | {r['setting']} {r['task']} | {np.mean(r['real']):.1f} ({min(r['real']):.1f}..{max(r['real']):.1f}) "
                   f"| {r['spearman']:.2f} | {reward(r)} | {r['cap']:.2f} |")
    for run in dict.fromkeys(r["run"] for r in rows):
        sel = [r for r in rows if r["run"] == run]
        mean_reward = np.mean([r["spearman_reward"] for r in sel]) if all("spearman_reward" in r for r in sel) else None
        out.append(f"| {run} | | mean of {len(sel)} cells | | **{np.mean([r['spearman'] for r in sel]):.2f}** | "
                   + ("-" if mean_reward is None else f"{mean_reward:.2f}") + f" | {np.mean([r['cap'] for r in sel]):.2f} |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="the run whose world model is benchmarked (none with --table)")
    parser.add_argument("--out", help="append the row to this JSONL (default: the run's fidelity.jsonl, ranking.jsonl or distance.jsonl; "
                        "the committed docs/results files only when named here)")
    parser.add_argument("--table", nargs="+", metavar="JSONL", help="print the markdown table of these rows and stop")
    parser.add_argument("--png", help="with --table: also plot the last row of each run to this PNG")
    parser.add_argument("--curve", action="store_true", help="with --table: one line per row (a learning curve), not one per source")
    parser.add_argument("--ranking", action="store_true", help="the functional test: Eq. 5's J against real scores (cells already in "
                        "--out are skipped)")
    parser.add_argument("--distance", action="store_true", help="Eq. 6-7: does d(s_t, goal of frame t + k) rise with k on held-out "
                        "episodes")
    parser.add_argument("--settings", default="SE-SV,SE-CV", help="with --ranking: the same-body cells (never the cross-domain ones)")
    parser.add_argument("--episodes", type=int, default=10, help="with --ranking: real episodes per goal, shared start states")
    args = parser.parse_args()
    if args.table:
        if missing := [path for path in args.table if not os.path.isfile(path)]:
            parser.error(f"{missing[0]}: no such file; pass rows this command wrote (docs/results/<fidelity|ranking|distance>_<body>.jsonl)")
        rows = [r for path in args.table for r in rundir.read_jsonl(path)]
        if rows and ("spearman" in rows[0] or "distance" in rows[0]):
            print(ranking_markdown(rows) if "spearman" in rows[0] else distance_markdown(rows))
            return
        print(curve_markdown(rows) if args.curve else markdown(rows))
        if args.png:
            print("wrote", plot(rows, args.png))
        return
    if not args.run:
        parser.error("pass a run folder (e.g. agents/walker) or --table JSONL ...")
    torch.set_num_threads(1)
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    kind = "ranking" if args.ranking else "distance" if args.distance else "fidelity"
    out = args.out or os.path.join(checkpoint.work_folder(args.run), f"{kind}.jsonl")  # committed rows only when --out names them
    if args.ranking:
        ranking(args.run, ckpt["step"], cfgs, models, args.settings.split(","), args.episodes, out)
        return
    if args.distance:
        row = {"run": args.run, "step": ckpt["step"], "distance": {name: distance_ranking(models["world_model"], models["goal_vae"],
               models["dist_net"], eps) for name, eps in held_out_episodes(cfgs).items()}}
    else:
        row = benchmark(models, held_out_episodes(cfgs), ckpt["step"], args.run)
    rundir.append_jsonl(out, row)
    print(distance_markdown([row]) if args.distance else markdown([row]))
    print("appended to", out)


if __name__ == "__main__":
    rundir.run_main(main, "nothing was written")
