"""Which reading of Eq. 6-7 makes the temporal distance rank steps, on a trained agent's frozen world model?

The distance network alone is trained afresh on D_body's training episodes (the world model, goal VAE and decoder of
`--run` frozen; d reads decoded observations, as the cpu preset's), then measured by fidelity.distance_ranking on the
held-out episodes. Readings, one factor each against Eq. 7 as train.py fits it (`eq7`: pairs i < j drawn uniformly in
a 50-step window, label (j - i) / 50, squared error, negatives regressed to 1 at weight 0.1, posterior and encoder
goals alike):
* `window100`: pairs in 100-step windows, label (j - i) / 100 (the ranking asks for gaps to 100 steps);
* `expectile`: the regression term an expectile at tau = 0.1 instead of the mean: for a pair of states met at several
  gaps (a gait's period, a body at rest) d learns the shortest gap seen, a reachability reading (as IQL's expectile
  value learning, Kostrikov et al. 2022, which HILP uses, Park et al. 2024);
* `hilbert`: d(s, g) = ||phi(s) - phi(g)|| (HILP's Hilbert representation, Park et al. 2024) with Eq. 7's loss:
  d(s, s) = 0 and the triangle inequality by construction;
* `td`: the same Hilbert d learnt as HILP learns it, not from Eq. 6's labels (td_loss; fit in training too until
  measured worse there, docs/ablations.md): Eq. 7 labels every pair of states of two episodes 1, so d towards a demo's
  goal, always another episode's state, can only say "not this episode" unless the network generalises. Here d is a
  metric, d(s, g) = (1 - gamma) ||phi(s) - phi(g)||, and V(s, g) = -d / (1 - gamma), the discounted steps from s to g,
  is fit by temporal differences along the data as a goal-conditioned value: V(s_t, g) <- -(1 + gamma + ... +
  gamma^(n-1)) + gamma^n V'(s_{t+n}, g), an expectile at tau (optimistic: the shortest way the data shows), the sum
  ending where a goal of the same episode is met, V = 0 at s_t's own frame's goal, V' a slow copy. Goals are the
  current frame's, a later frame of the episode at a geometric gap, or any frame (GOAL_SHARES, HILP's), each as the
  posterior's or the goal encoder's; bootstrapping through states that look alike stitches episodes together. Ours
  against HILP's settings: n = 10 steps along the data before bootstrapping and a slow rate of 0.02 where HILP
  bootstraps one step at 0.005: at 20000 updates that reading's d had grown to 2 steps at a gap of 100, this one's to
  8, ranking alike.

Beside the step ranking, each row measures what Eq. 4 needs of d towards the benchmark's stand goals (posture_ranking):
does -d rank a held-out D_body state by the body's posture (envs.observed_posture: 1 upright at stand height)?

    python probes/distance_probe.py --run agents/walker [--readings eq7,expectile] [--updates 3000] [--seed 0] [--out docs/results/distance_probe_walker.jsonl]
    python probes/distance_probe.py --summary docs/results/distance_probe_walker.jsonl
"""
import argparse
import math
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import collect  # noqa: E402
import distance  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import fidelity  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
from world_model import mlp  # noqa: E402

TD = dict(gamma=0.99, tau=0.95, n=10, slow_rate=0.02, lr=3e-4)  # td: discount (HILP), expectile (HILP), steps before bootstrapping, slow copy's EMA rate (ours), Adam
PHI_DIM = 64  # hilbert, td: phi's output (ours; HILP: 32)
GOAL_SHARES = (0.2, 0.5, 0.3)  # td: goals the current frame's, a later one of its episode, any frame of the batch (HILP's)
READINGS = {"eq7": {}, "window100": dict(window=100), "expectile": dict(tau=0.1), "hilbert": dict(hilbert=True), "td": dict(td=True)}


@torch.no_grad()
def embedded_episodes(models, episodes, chunk=50):
    """The frozen models' reading of each frame, what d sees: (decoded posterior state, decoded encoder goal), each (E, L, O)."""
    wm, vae = models["world_model"], models["goal_vae"]
    x, g = [], []
    for i in range(0, len(episodes), chunk):
        part = episodes[i : i + chunk]
        obs, action, is_first, p = (fidelity.stack(part, k, "cpu") for k in (wm.cfg.obs, "action", "is_first", "p"))
        post, _ = wm.observe(obs, action, is_first, sample=False)
        x.append(wm.decoder(wm.feat(post)))
        g.append(wm.decoder(vae.goal(p)))
    return torch.cat(x), torch.cat(g)


class Reading(torch.nn.Module):
    """d on embedded observations: an MLP of the pair (Eq. 7's), or ||phi(a) - phi(b)|| (hilbert)."""

    def __init__(self, dim, hilbert=False, units=128, layers=4):
        super().__init__()
        self.hilbert = hilbert
        self.net = mlp(dim, units, PHI_DIM, layers) if hilbert else mlp(2 * dim, units, 1, layers)

    def forward(self, a, b):
        a, b = torch.broadcast_tensors(a, b)
        return (self.net(a) - self.net(b)).norm(dim=-1) if self.hilbert else self.net(torch.cat([a, b], -1)).squeeze(-1)


class DecodedDistance(torch.nn.Module):
    """A reading as a run's dist_net is called: d(feat_i, feat_j) on the decoded observations."""

    def __init__(self, reading, decoder):
        super().__init__()
        self.reading, self.embed = reading, decoder.forward  # the decoder stays the world model's, not a parameter here

    def forward(self, feat_i, feat_j):
        return self.reading(self.embed(feat_i), self.embed(feat_j))


def fit(x, g, window=50, tau=0.5, hilbert=False, td=False, updates=3000, batch=16, pairs=1024, weight=0.1, units=128, seed=0):
    """Eq. 7 (one reading) on windows of `window` steps of (x, g) (E, L, O); tau 0.5 is the squared error."""
    if td:
        return fit_td(x, g, updates, pairs, units=units, seed=seed)
    torch.manual_seed(seed)
    rng = torch.Generator().manual_seed(seed)
    d = Reading(x.shape[-1], hilbert, units)
    opt = torch.optim.Adam(d.parameters(), 3e-4)
    E, L, _ = x.shape
    is_first = torch.zeros(batch, window, dtype=torch.bool)
    for _ in range(updates):
        episode = torch.randint(E, (batch,), generator=rng)
        rows = torch.randint(L - window + 1, (batch,), generator=rng)[:, None] + torch.arange(window)
        xb, gb = x[episode[:, None], rows], g[episode[:, None], rows]
        drawn = distance.sample_pairs(episode, is_first, pairs, rng)
        (b, i, j), (b1, t1, b2, t2) = drawn["pos"], drawn["neg"]
        loss = 0
        for goal in (xb, gb):  # the later state as the posterior's and as the goal encoder's, as train.py
            u = (j - i).float() / window - d(xb[b, i], goal[b, j])
            regression = (2 * torch.where(u < 0, 1 - tau, tau) * u**2).mean()  # tau 0.5: (u)^2, Eq. 7's
            contrastive = ((d(xb[b1, t1], goal[b2, t2]) - 1) ** 2).mean()
            loss = loss + (regression + weight * contrastive) / 2
        opt.zero_grad()
        loss.backward()
        opt.step()
    return d


class TDReading(Reading):
    """The td reading's d on embedded observations: (1 - gamma) ||phi(a) - phi(b)||, V = -d / (1 - gamma) in steps;
    phi is the hilbert reading's network."""

    def __init__(self, dim, units=128, layers=4):
        super().__init__(dim, hilbert=True, units=units, layers=layers)
        self.dim = dim

    def distance(self, a, b):
        return (self.net(a) - self.net(b)).norm(dim=-1) * (1 - TD["gamma"])

    def forward(self, a, b):
        a, b = torch.broadcast_tensors(a, b)
        return self.distance(a.reshape(-1, self.dim), b.reshape(-1, self.dim)).reshape(a.shape[:-1])


def td_loss(d, slow, x, goals, is_first, num, generator=None, n=TD["n"]):
    """The td reading's loss (module docstring; HILP's value learning): x (B, T, E) embedded states, goals a list of
    (B, T, E) embedded goals of the same frames (the posterior's, the goal encoder's), is_first (B, T), num steps drawn
    -> (loss, metrics); slow the slow copy for the targets."""
    (B, T, _), gamma, tau = x.shape, TD["gamma"], TD["tau"]
    draw = lambda high: torch.randint(high, (num,), generator=generator).to(x.device)  # noqa: E731
    index = torch.arange(T, device=x.device).expand(B, T)
    start_after = torch.where(is_first, index, T).flip(1).cummin(1).values.flip(1)  # (B, T): the first episode start at or after t
    end = torch.cat([start_after[:, 1:], torch.full_like(start_after[:, :1], T)], 1) - 1  # the last step of t's episode in its segment
    b, t = draw(B), draw(T)
    keep = t < end[b, t]  # a step after t to bootstrap from
    b, t, end = b[keep], t[keep], end[b[keep], t[keep]]
    k = len(b)
    kind = torch.bucketize(torch.rand(k, generator=generator), torch.tensor(GOAL_SHARES).cumsum(0)[:-1]).to(x.device)  # 0 current, 1 later, 2 any
    uniform = torch.rand(k, generator=generator).clamp_min(torch.finfo(torch.float32).tiny)  # rand's 0: an infinite gap
    gap = (torch.log(uniform) / math.log(gamma)).floor().long().to(x.device) + 1  # geometric, mean 1 / (1 - gamma)
    later = torch.minimum(t + gap, end)
    goal_b, goal_t = torch.where(kind == 2, draw(B)[:k], b), torch.where(kind == 0, t, torch.where(kind == 1, later, draw(T)[:k]))
    which = torch.randint(len(goals), (k,), generator=generator).to(x.device)
    goal = torch.stack([g[goal_b, goal_t] for g in goals])[which, torch.arange(k, device=x.device)]
    steps = torch.minimum(torch.full_like(t, n), end - t)  # along the data, then the slow value
    reached = (kind == 1) & (later - t <= steps)  # a goal of the same episode met within them ends the sum
    steps = torch.where(reached, later - t, steps)
    scale = 1 - gamma
    with torch.no_grad():
        tail = torch.where(reached, 0.0, slow.distance(x[b, t + steps], goal) / scale)
        target = torch.where(kind == 0, 0.0, -(1 - gamma**steps) / scale - gamma**steps * tail)
    value = -d.distance(x[b, t], goal) / scale
    u = target - value
    loss = (torch.where(u < 0, 1 - tau, tau) * u**2).mean()
    return loss, {"dist_loss": loss.item(), "dist_value": value.mean().item()}


def fit_td(x, g, updates, batch, units=128, seed=0):
    """The `td` reading (module docstring) on whole episodes (x, g) (E, L, O), the frozen models' reading of D_body.
    Returns the TDReading."""
    torch.manual_seed(seed)
    rng = torch.Generator().manual_seed(seed)
    d, slow = (TDReading(x.shape[-1], units) for _ in range(2))
    slow.load_state_dict(d.state_dict())
    opt = torch.optim.Adam(d.parameters(), TD["lr"])
    is_first = torch.zeros(x.shape[:2], dtype=torch.bool)
    for _ in range(updates):
        loss, _ = td_loss(d, slow, x, [g, x], is_first, batch, rng)
        opt.zero_grad()
        loss.backward()
        opt.step()
        policy.ema_update(slow, d, TD["slow_rate"])
    return d


@torch.no_grad()
def posture_ranking(wm, dist, episodes, goals, body):
    """Does -d towards `goals` (G, F) rank held-out states by the body's posture? On episodes (E of length L): the mean
    over goals of d(s_t, g) per step, then Spearman(-d, posture) over all steps, and d where the body lies (posture
    < 0.4) and where it stands (>= 0.8)."""
    obs, action, is_first = (fidelity.stack(episodes, k, "cpu") for k in (wm.cfg.obs, "action", "is_first"))
    post, _ = wm.observe(obs, action, is_first, sample=False)
    feat = wm.feat(post)
    d = torch.stack([dist(feat, goal.expand_as(feat)) for goal in goals]).mean(0).flatten().numpy()
    posture = envs.observed_posture(body, obs.numpy()).ravel()
    return {"rho": round(evaluate.spearman(-d, posture), 3), "lying": round(float(d[posture < 0.4].mean()), 4),
            "standing": round(float(d[posture >= 0.8].mean()), 4)}


def summary(rows, sources=("body", "stand", "walk", "run", "jump")):
    """Per reading, the held-out sources' mean of Spearman(k, d) per episode and per start and of the contrast (d to
    another episode's frame minus d one step ahead), as mean +- s.e. over the fit seeds' rows; and posture_ranking's
    Spearman where the rows have it."""
    by = {}
    for r in rows:
        by.setdefault(r["run"].rsplit(" s", 1)[0], []).append(r["distance"])
    out = ["| reading | seeds | goal | Spearman per episode | per start | contrast | Spearman(-d to stand goals, posture) |",
           "|---|---|---|---|---|---|---|"]
    first = next(iter(by.values()))
    lines = [(name, fits, kind) for name, fits in by.items() for kind in ("post", "enc")]
    if "obs" in first[0][sources[0]]:  # the observations' own distance, the same for every reading
        lines.append(("the observations themselves", first, "obs"))
    cell = lambda x: f"{np.mean(x):.2f}" + (f" +- {evaluate.stderr(x):.2f}" if len(x) > 1 else "")  # noqa: E731
    for name, fits, kind in lines:
        cells = []
        for read in (lambda m: m["rho_episode"], lambda m: m["rho_start"], lambda m: m["other"] - m["d"][0]):
            cells.append(cell([np.mean([read(f[source][kind]) for source in sources]) for f in fits]))
        posture = [r["posture"]["rho"] for r in rows if r["run"].rsplit(" s", 1)[0] == name and "posture" in r]
        cells.append(cell(posture) if posture and kind == "enc" else "")
        out.append(f"| {name} | {len(fits)} | {kind} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--run", help="a trained agent, e.g. agents/walker")
    parser.add_argument("--summary", metavar="JSONL", help="instead: each reading over its fit seeds, from this probe's rows")
    parser.add_argument("--readings", default=",".join(READINGS), help=f"comma-separated, of {', '.join(READINGS)}")
    parser.add_argument("--updates", type=int, default=3000)
    parser.add_argument("--td-updates", type=int, default=20000, help="the td reading's (its values grow by bootstrapping)")
    parser.add_argument("--seed", type=int, default=0, help="of d's initialisation and pairs (the frozen models stay the run's)")
    parser.add_argument("--out", help="append one row per reading (default docs/results/distance_probe_<body>.jsonl)")
    args = parser.parse_args()
    if args.summary:
        print(summary(rundir.read_jsonl(args.summary)))
        return
    if not args.run:
        parser.error("pass --run (a trained agent) or --summary JSONL")
    readings = args.readings.split(",")
    if unknown := [r for r in readings if r not in READINGS]:
        parser.error(f"--readings {unknown[0]}: not one of {', '.join(READINGS)}")
    torch.set_num_threads(1)
    cfgs, models, _ = checkpoint.load_run(args.run)
    tc, wm = cfgs["train"], models["world_model"]
    body = collect.load_folder(os.path.join(tc.data, tc.env), (wm.cfg.obs, "action", "is_first", "p"))
    x, g = embedded_episodes(models, [e for k, e in enumerate(body) if k % tc.holdout_every])  # the training episodes
    out = args.out or f"docs/results/distance_probe_{tc.env}.jsonl"
    held_out, stand_goals = fidelity.held_out_episodes(cfgs), evaluate.demo_goals(models, tc.env, "stand", tc.data, 1)
    print("the run's own d towards the stand goals:", posture_ranking(wm, models["dist_net"], held_out["body"], stand_goals, tc.env), flush=True)
    for name in readings:
        updates = args.td_updates if name == "td" else args.updates
        d = fit(x, g, updates=updates, seed=args.seed, **READINGS[name])
        dist = DecodedDistance(d, wm.decoder)  # fidelity.distance_ranking gives posterior features
        with torch.no_grad():
            row = {"run": f"{args.run} d:{name} s{args.seed}", "step": updates, "distance": {
                source: fidelity.distance_ranking(wm, models["goal_vae"], dist, eps) for source, eps in held_out.items()},
                "posture": posture_ranking(wm, dist, held_out["body"], stand_goals, tc.env)}
        rundir.append_jsonl(out, row)
        print(fidelity.distance_markdown([row]), flush=True)


if __name__ == "__main__":
    main()
