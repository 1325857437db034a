"""Ours, for Eq. 2: the world model's fidelity benchmark. Does imagination keep the episode?

Eq. 4 trains the policy and Eq. 5 infers the goal in the world model's imagination, so both are only as good as its
open-loop rollouts. On held-out episodes of the agent's own body (its side-view demos of the four tasks, expert episodes
never in D_body, and every `holdout_every`-th D_body episode, held out of training), each episode is filtered with the
posterior's means; from the filtered state at steps t0 = 10, 110, 210, 310 (at least 10 filtered steps of context) the
prior imagines 100 steps open loop with the recorded actions (the latent's mode, no sampling). At k steps ahead:

    error     the decoder's squared error per element of the imagined state (symlog space, world_model.open_loop_error)
    hold      the same for holding the last filtered observation o_t0: what imagining nothing earns
    cos       cosine of the goal decoder's p_hat of the imagined state and the recorded p_{t0 + k}: what Eq. 5's OT
              reward reads of imagination (1 = exact)
    filtered  the same for the filtered state at t0 + k: what the goal decoder reads of a true state (the ceiling)
and the held-out ELBO terms of Eq. 2 (recon, KL per step) on those episodes. train.py runs it every `fidelity_every`
updates into runs/<name>/fidelity.jsonl (a curve against updates); this command benchmarks a run's checkpoint.

    python fidelity.py agents/walker [--out docs/results/fidelity_walker.jsonl]
    python fidelity.py --table docs/results/fidelity_walker.jsonl [--png docs/fidelity_walker.png]
"""
import argparse
import os

import numpy as np
import torch

import checkpoint
import collect
import envs
import rundir

STARTS = (10, 110, 210, 310)  # t0: where imagination leaves the filter (ours: 4 per 500-step episode, >= 10 steps of context)
AHEAD = 100  # steps imagined from each start
HORIZONS = (16, 50, 100)  # the reported k: GenRL's imagination horizon (16), and further


def held_out_episodes(cfgs):
    """{source: episodes}: the body's own side-view demos per task, and D_body's held-out episodes ('body')."""
    tc, wc = cfgs["train"], cfgs["wm"]
    keys = (wc.obs, "action", "is_first", "p")
    out = {task: collect.load_folder(os.path.join(tc.data, "demos", f"{tc.env}_{task}_side"), keys) for task in envs.TASKS}
    out["body"] = collect.load_folder(os.path.join(tc.data, tc.env), keys)[:: tc.holdout_every]
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
    feats = []
    for k in range(ahead):
        state = wm.img_step(state, action[row[:, 0], index[:, k]], sample=False)
        feats.append(wm.feat(state))
    imagined = torch.stack(feats, 1)  # (E * S, ahead, F)
    target = wm._target(obs)[row, index]  # (E * S, ahead, ...) in the decoder's space
    last = wm._target(obs)[row[:, 0], index[:, 0] - 1][:, None]  # (E * S, 1, ...): o_t0, held
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
    out = [f"| run | update | source | cos imagined at {h} | cos filtered at {h} | error at {h} | hold at {h} | held-out recon / KL |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for name, m in r["sources"].items():
            cells = [" / ".join(at(m[key], k, 2) for k in HORIZONS) for key in ("cos", "filtered")]
            cells += [" / ".join(at(m[key], k, 3) for k in HORIZONS) for key in ("error", "hold")]
            out.append(f"| {r['run']} | {r['step']} | {name} | " + " | ".join(cells) + f" | {m['recon']:.2f} / {m['kl']:.2f} |")
    return "\n".join(out)


def plot(rows, path):
    """The picture to look at first: cosine against steps ahead per source, imagined (solid) beside filtered (dashed),
    the last row of each run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    last = {r["run"]: r for r in rows}
    sources = list(next(iter(last.values()))["sources"])
    fig, axes = plt.subplots(1, len(sources), figsize=(3.2 * len(sources), 3), sharey=True)
    for ax, name in zip(np.atleast_1d(axes), sources):
        for i, (run, r) in enumerate(last.items()):
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
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("run", nargs="?", help="the run whose world model is benchmarked (none with --table)")
    parser.add_argument("--out", help="append the row to this JSONL (default: docs/results/fidelity_<body>.jsonl)")
    parser.add_argument("--table", nargs="+", metavar="JSONL", help="print the markdown table of these rows and stop")
    parser.add_argument("--png", help="with --table: also plot the last row of each run to this PNG")
    args = parser.parse_args()
    if args.table:
        rows = [r for path in args.table for r in rundir.read_jsonl(path)]
        print(markdown(rows))
        if args.png:
            print("wrote", plot(rows, args.png))
        return
    if not args.run:
        parser.error("pass a run folder (e.g. agents/walker) or --table JSONL ...")
    torch.set_num_threads(1)
    cfgs, models, ckpt = checkpoint.load_run(args.run)
    row = benchmark(models, held_out_episodes(cfgs), ckpt["step"], args.run)
    out = args.out or f"docs/results/fidelity_{cfgs['train'].env}.jsonl"
    rundir.append_jsonl(out, row)
    print(markdown([row]))
    print("appended to", out)


if __name__ == "__main__":
    rundir.run_main(main, "nothing was written")
