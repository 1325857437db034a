"""Ours, after the paper's Sec. 6: GIIL-online, the goal refined on real rollouts scored by the OT reward (psi frozen).

Sec. 6: "During online rollouts, the agent could iteratively refine its inferred goal vector." Here the frozen
policy pi(a | s, g) acts in the agent's own environment; each episode is rendered by the agent's own camera, encoded
by the run's video encoder (Sec. 4, p_t = f(o_{t-k+1:t})) and scored by the OT reward of App. C, whole episode
against every demo, the best-matching demo counting (ROT): J_real(g) = sum_t r^ot_t = -<P, C>. The task reward is
never read (the agent does not have it): `episode_features` drops it.

The search (ours; the paper is silent, precedents: successive halving, Jamieson & Talwalkar 2016; OpTI-BFM's choice
among candidate latents, Rupf et al. 2025): the candidates are the zero-shot goals q(s | p_T) of the cell's demos
(GIIL-ZS's goals). Round r runs every
surviving candidate for `schedule[r][1]` episodes from the same environment seeds (common random numbers: the
candidates are compared on the same start states), then keeps the `schedule[r + 1][0]`
best by their mean OT score over all their episodes so far. The cpu schedule, 10 x 2, 4 x 3, 2 x 9, is 50 episodes
(25,000 agent steps, 50,000 env steps: AIME-NoB's budget). The goal chosen is the best survivor; it is evaluated on
environment seeds never used here.
"""

import numpy as np
import torch
from tqdm import tqdm

import evaluate
import ot_reward
import rundir


def budget(cfg, candidates):
    """Real episodes the schedule spends on `candidates` goals."""
    return sum(min(keep, candidates) * episodes for keep, episodes in cfg.schedule)


@torch.no_grad()
def episode_features(models, env_list, goals, steps, obs_key, seed, encoder):
    """Real episodes with goals (N, F) from env seeds seed, seed + 1, ... (or a list of N seeds) -> video features
    (N, steps + 1, D) of the agent's own rendered frames. The environments' task returns are dropped here: nothing
    downstream can read them."""
    _, frames = evaluate.run_episodes(env_list, models, goals, steps, obs_key, seed, render=True)
    return np.stack([encoder(f) for f in frames])


def ot_score(agent_p, demo_p, ot_cfg):
    """J_real: the OT reward of whole episodes summed over their steps, agent_p (N, T, D), demo_p (K, M, D) -> (N,)."""
    reward, _ = ot_reward.ot_reward(torch.as_tensor(agent_p), torch.as_tensor(demo_p), ot_cfg)
    return reward.sum(-1).numpy()


def successive_halving(score, n_candidates, cfg, seed):
    """Choose among candidates 0 .. n - 1 by score(indices, env_seed) -> (len(indices),) OT scores of one episode each
    from env_seed (every index the same start state). -> (chosen index, log: a list of (index, env_seed, score))."""
    alive, log, next_seed = list(range(n_candidates)), [], cfg.seed_base + 1000 * seed
    for r, (keep, episodes) in enumerate(cfg.schedule):
        if r:  # the best `keep` by their mean score over every episode so far (ties: the lower index)
            mean = {k: np.mean([s for i, _, s in log if i == k]) for k in alive}
            alive = sorted(alive, key=lambda k: (-mean[k], k))[:keep]
        for _ in range(episodes):
            for k, s in zip(alive, score(alive, next_seed)):
                log.append((k, next_seed, float(s)))
            next_seed += 1
    mean = {k: np.mean([s for i, _, s in log if i == k]) for k in alive}
    return min(alive, key=lambda k: (-mean[k], k)), log


def refine_goal(models, cfgs, make_env, goals, demo_p, cfg, seed, encoder, steps, ot_cfg):
    """GIIL-online for one seed: goals (G, F) the candidates (the demos' zero-shot goals), demo_p (K, M, D) ->
    (the chosen goal (F,), its index, the log of (index, env seed, OT score))."""
    bar = tqdm(total=budget(cfg, len(goals)), desc=f"GIIL-online seed {seed}: real episodes", leave=False)

    def score(indices, env_seed):  # one batch: every candidate from the same start state
        env_list = [make_env() for _ in indices]
        p = episode_features(models, env_list, goals[indices], steps, cfgs["wm"].obs, [env_seed] * len(indices), encoder)
        for env in env_list:
            env.close()
        bar.update(len(indices))
        return ot_score(p, demo_p, ot_cfg)

    chosen, log = successive_halving(score, len(goals), cfg, seed)
    bar.close()
    return goals[chosen], chosen, log


def choice_curve(log, n_candidates):
    """The goal GIIL-online would choose after each of its episodes: [index after 0, 1, ..., len(log) episodes], 0 (the
    first demo's zero-shot goal, GIIL-FT's start) before any; then the best mean OT score so far (ties: lower index)."""
    curve, scores = [0], {}
    for index, _, score in log:
        scores.setdefault(index, []).append(score)
        curve.append(min(scores, key=lambda k: (-np.mean(scores[k]), k)))
    return curve


def plot_curves(rows, path):
    """Score against environment steps, one line per cell: the true score (its GIIL-ZS row, evaluated on seeds the search
    never used) of the goal chosen after each episode, mean over GIIL-online's seeds; the final evaluations as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    cells = sorted({(r["demo"], r["view"]) for r in rows if r["method"] == "GIIL-online"})
    for demo, view in cells:
        zs = {r["seed"]: r["score"] for r in rows if r["method"] == "GIIL-ZS" and (r["demo"], r["view"]) == (demo, view)}
        runs = [r for r in rows if r["method"] == "GIIL-online" and (r["demo"], r["view"]) == (demo, view)]
        curves = np.array([[zs[k] for k in choice_curve(r["ot_log"], len(zs))] for r in runs])  # (seeds, episodes + 1)
        steps = np.arange(curves.shape[1]) * runs[0]["env_steps"] / (curves.shape[1] - 1)
        line, = ax.plot(steps, curves.mean(0), label=f"{runs[0]['setting']} {runs[0]['task']} ({demo}, {view})")
        ax.plot([steps[-1]] * len(runs), [r["score"] for r in runs], "o", color=line.get_color(), alpha=0.5)
        ax.axhline(np.mean(list(zs.values())), color=line.get_color(), ls=":", lw=1)
    ax.set_xlabel("environment steps (agent steps) of the search")
    ax.set_ylabel("normalised score of the chosen goal")
    ax.set_title(f"GIIL-online, {rows[0]['agent']} (dotted: GIIL-ZS, the mean over the demos' goals)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    rundir.atomic_write(path, lambda name: fig.savefig(name, dpi=90), by_name=True)  # never through a link
    plt.close(fig)
    return path


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="GIIL-online's curve: score of the chosen goal against environment steps, from a "
                                     "run's results.jsonl (python imitate.py --demo D --online, or tables.py --methods online)", allow_abbrev=False)
    parser.add_argument("run")
    parser.add_argument("--demo", help="only this demo's cells, e.g. stickman_run (default: every cell with GIIL-online rows)")
    parser.add_argument("--view", help="only this camera's cells")
    parser.add_argument("--out", help="the PNG (default: <run>/online_curve.png)")
    args = parser.parse_args()
    rows = [r for r in rundir.read_jsonl(f"{args.run}/results.jsonl") if r["demo"] == (args.demo or r["demo"]) and r["view"] == (args.view or r["view"])]
    if not any(r["method"] == "GIIL-online" for r in rows):
        raise SystemExit(f"error: no GIIL-online rows in {args.run}/results.jsonl for those cells: run `python imitate.py --demo "
                         f"{args.demo or 'stickman_run'} --online --run {args.run}` first")
    print(f"wrote {plot_curves(rows, args.out or f'{args.run}/online_curve.png')}")
