"""Sec. 5 and Eq. 8: the agent in its real environment, phase 1's goal-reaching benchmark, and its imagination checks.

run_episodes acts with the frozen multi-task policy pi(a | s_t, g) in N environments at once (one batched world-model
and actor call per step), s_t filtered online by the world model's posterior; the environments' true task rewards
are summed but never shown to the agent. write_video puts a demo beside the agent's episode (imitate.py's videos).

goal_reaching is how phase 1 is judged on its own (before any imitation): the goals are the agent's OWN body's
side-view expert demos (D_demo, the SE-SV setting of GIIL-ZS): g = q(s | p_T), the goal encoder of the demo's last
video feature, exactly what GIIL-ZS feeds the policy. Each of the 10 demos of stand, walk and run is the goal of
`episodes` episodes of 500 agent steps from the environment's random start; the score is Eq. 8's normalised return
of the demo's task, mean +- standard error over the episodes, beside uniform random actions with the same seeds. Jump
is not in D_body (Sec. 5) and is reported on its own line, outside the average.

    python train.py --evaluate --run-dir runs/walker_state_cpu_s0   # writes runs/<name>/goal_reaching.json
    python evaluate.py runs/walker_state_cpu_s0 runs/walker_state_cpu_s1 runs/walker_state_cpu_s2   # over seeds

evaluate_imagination (run by train.py at its end, imagination.json) measures what phase 2's OT reward rests on: how
well the goal decoder reads posterior and open-loop imagined states of held-out D_body.
"""
import json
import os

import cv2
import numpy as np
import torch
from tqdm import tqdm

import collect
import envs
import policy
import rundir


@torch.no_grad()
def run_episodes(env_list, models, goals, steps, obs_key, seed, render=False, random_actions=False, on_step=None, on_state=None):
    """One episode in each env of env_list (reset with seeds seed, seed + 1, ...), acting with pi(a | s_t, g_i)
    (policy.Actor.act: the tanh of its mean), or uniform random actions. goals (N, F), unused with random_actions.
    on_step(env_list), if given, is called after every step (probes read the physics there); on_state(state), with the
    posterior state dict of (N, .) of every step t = 0 .. steps (not with random_actions).
    seed may also be a list of N env seeds (online.py: several goals from one start state).
    -> returns (N,) float array, frames (N, steps + 1, 64, 64, 3) if render else None."""
    wm, actor = models["world_model"], models["actor"]
    device = next(wm.parameters()).device
    N, A = len(env_list), env_list[0].action_dim
    env_seeds = [seed + i for i in range(N)] if np.isscalar(seed) else list(seed)
    rng = np.random.default_rng(env_seeds[0])
    torch.manual_seed(env_seeds[0])  # the posterior samples z_t: the same seed gives the same episodes
    obs = np.stack([env.reset(seed=s)[0] for s, env in zip(env_seeds, env_list)])
    action = np.zeros((N, A), np.float32)
    state, total, frames = None, np.zeros(N), []
    for t in range(steps + 1):
        if render or (obs_key == "pixels" and not random_actions):
            frames.append(np.stack([env.render() for env in env_list]))
        if not random_actions:  # s_t, filtered by the world model from o_t and a_{t-1}
            o = torch.as_tensor(frames[-1] if obs_key == "pixels" else obs, device=device)[:, None]
            post, _ = wm.observe(o, torch.as_tensor(action, device=device)[:, None], torch.full((N, 1), t == 0, device=device), state)
            state = {k: v[:, -1] for k, v in post.items()}
            if on_state:
                on_state(state)
        if t == steps:
            break
        if random_actions:
            action = rng.uniform(-1, 1, (N, A)).astype(np.float32)
        else:
            action = actor.act(wm.feat(state), goals).cpu().numpy()
        results = [env.step(a) for env, a in zip(env_list, action)]
        obs = np.stack([r[0] for r in results])
        total += [r[1] for r in results]
        if on_step:
            on_step(env_list)
    return total, (np.stack(frames, 1) if render else None)


def write_video(path, demo_frames, agent_frames):
    """demo | agent side by side, 4x upscaled, 20 frames/s (one frame per agent step = 0.05 s); a whole file, reopened
    with all its frames, or none (rundir.atomic_write: cv2 writes the temporary file by its name)."""
    n = min(len(demo_frames), len(agent_frames))
    both = np.concatenate([demo_frames[:n], agent_frames[:n]], axis=2)  # (n, 64, 128, 3)

    def write(name):
        writer = cv2.VideoWriter(name, cv2.VideoWriter_fourcc(*"mp4v"), 20, (both.shape[2] * 4, both.shape[1] * 4))
        if not writer.isOpened():
            raise ValueError(f"{path}: this OpenCV cannot write mp4 videos (no FFmpeg?); pass --video 0")
        for frame in both:
            writer.write(cv2.resize(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST))
        writer.release()
        # verified whole before it replaces an older file: cv2 reports no full disk, and a cut mp4 lacks its index
        video = cv2.VideoCapture(name)
        frames = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video.isOpened() else 0
        video.release()
        if frames != n:
            raise OSError(f"{path}: the video reopened with {frames} of its {n} frames (disk full?); any older video there is kept")

    rundir.atomic_write(path, write, by_name=True)


@torch.no_grad()
def open_loop(wm, batch, context):
    """Ours, for Eq. 2: observe steps [0, context), imagine [context, T) with the recorded actions from the last posterior
    state (prior modes) -> imagined feats (B, T - context, F), keep (B,): False where an episode starts in that part."""
    obs, action, is_first = batch[wm.cfg.obs], batch["action"], batch["is_first"]
    assert 0 < context < action.shape[1]
    post, _ = wm.observe(obs[:, :context], action[:, :context], is_first[:, :context])
    return replay(wm, {k: v[:, -1] for k, v in post.items()}, action[:, context:]), ~is_first[:, context:].any(1)


def replay(wm, state, actions, sample=False):
    """The prior rolled open loop from `state` (N, .) with recorded actions (N, H, A) -> imagined feats (N, H, F)
    (prior modes unless sample)."""
    feats = []
    for a in actions.unbind(1):
        state = wm.img_step(state, a, sample=sample)
        feats.append(wm.feat(state))
    return torch.stack(feats, 1)


def open_loop_error(wm, batch, context, imagined=None):
    """The decoder's mean squared error per observation element on the open-loop imagined steps (open_loop, or `imagined`,
    its output for this batch when already computed), in the decoder's target space (symlog for states, [-0.5, 0.5]
    for pixels); NaN if no segment is kept."""
    feats, keep = imagined or open_loop(wm, batch, context)
    err = wm._decode_raw(feats) - wm._target(batch[wm.cfg.obs][:, context:])
    return err[keep].pow(2).mean().item() if keep.any() else float("nan")


@torch.no_grad()
def open_loop_metrics(wm, vae, batch, context):
    """Imagination quality: the world model's open-loop error (Eq. 2's decoder) and the cosine between the goal decoder's
    features of the open-loop imagined states and the true p_t, what phase 2's OT reward reads (0 to 1, 1 = exact)."""
    feats, keep = imagined = open_loop(wm, batch, context)  # imagined once, read by both decoders
    cos = (vae.decode(feats) * batch["p"][:, context:]).sum(-1)[keep]
    return {"open_loop": open_loop_error(wm, batch, context, imagined), "open_loop_p_cos": cos.mean().item() if len(cos) else float("nan")}


@torch.no_grad()
def distance_profile(dist_net, feat, goal_feat, is_first, t0=10, ahead=(1, 5, 15, 30)):
    """Ours, a diagnostic of Eq. 7's d (distance.py): mean d(s_t0, goal) for goals `ahead` steps later in the same segment, as
    posterior feats and as encoder goals, and for another segment's frame (the last value). feat, goal_feat (B, T, F),
    is_first (B, T) -> {'d_post': [...], 'd_enc': [...]}, each len(ahead) + 1 floats (NaN where no segment qualifies)."""
    B, T, _ = feat.shape
    assert t0 + max(ahead) < T, (t0, ahead, T)
    whole = ~is_first[:, t0 + 1 :].any(1)  # segments with no episode start after t0
    out = {}
    for name, goal in (("d_post", feat), ("d_enc", goal_feat)):
        d = [dist_net(feat[whole, t0], goal[whole, t0 + k]).mean().item() for k in ahead]
        d.append(dist_net(feat[:, t0], goal.roll(1, 0)[:, t0 + ahead[0]]).mean().item())  # another segment's frame
        out[name] = d
    return out


@torch.no_grad()
def reachable_goal_reward(wm, dist_net, actor, post, goal_feat, is_first, horizon, seed=0):
    """Eq. 4's imagined goal reward -d(s_k, g) on goals the agent can reach (ours, a diagnostic): from s_t0 (t0 = 10,
    less in short segments) of each batch segment with no episode start after t0, imagine `horizon` steps towards
    g = q(s | p_{t0 + horizon}), the goal encoder's state of the frame the data reached; mean -d(s_k, g) over the
    imagined steps, for the actor's mean action given g, the actor given another segment's goal instead (what
    ignoring g would earn), and uniform random actions (seeded apart: the training RNG is untouched). The reward of
    training (`reward`) averages over goals half out of reach and hardly moves; this one starts at the random
    actions' level with a fresh actor.
    post dict of (B, T, .), goal_feat (B, T, F), is_first (B, T) -> {'reward_reachable': [own, other goal, random]}."""
    t0 = min(10, is_first.shape[1] - 1 - horizon)
    whole = ~is_first[:, t0 + 1 : t0 + horizon + 1].any(1)
    start = {k: v[whole, t0] for k, v in post.items()}
    goal = goal_feat[whole, t0 + horizon]
    random_action = lambda feat: torch.rand(len(feat), actor.action_dim, device=feat.device) * 2 - 1
    out = []
    with torch.random.fork_rng(devices=[goal.device] if goal.is_cuda else []):  # the prior's samples and random actions
        torch.manual_seed(seed)
        for given, act in ((goal, None), (goal.roll(1, 0), None), (None, random_action)):  # always scored against goal
            goal_in = None if given is None else actor.goal_input(given)
            act = act or (lambda feat: actor(feat, given, deterministic=True, goal_in=goal_in)[0])
            states, _ = wm.imagine(start, act, horizon)
            out.append(policy.goal_reward(dist_net, wm.feat(states), goal).mean().item())
    return {"reward_reachable": out}


@torch.no_grad()
def evaluate_imagination(models, cfgs, held_out, device, segments=64):
    """What phase 2's OT reward rests on, on held-out D_body segments (a fixed draw, so reruns compare): the goal
    decoder's cosine to the true p_t on world-model posterior states, and open_loop_metrics."""
    wc, wm, vae = cfgs["wm"], models["world_model"], models["goal_vae"]
    seed = cfgs["train"].seed + 1
    batch = collect.Segments(held_out, (wc.obs, "action", "is_first", "p"), wc.seq_len).sample(segments, np.random.default_rng(seed), device)
    with torch.random.fork_rng(devices=[]):  # the posterior samples z: seeded here, the training RNG untouched
        torch.manual_seed(seed)
        post, _ = wm.observe(batch[wc.obs], batch["action"], batch["is_first"])
        cos = (vae.decode(wm.feat(post)) * batch["p"]).sum(-1).mean().item()
        return {"posterior_p_cos": cos, **open_loop_metrics(wm, vae, batch, wc.seq_len // 2)}


def episode_score(task, episode_return, steps):
    """Eq. 8 on a return of `steps` agent steps, scaled to the full episode when shorter."""
    return float(envs.normalized_score(task, episode_return * envs.EPISODE_STEPS / steps))


def stderr(values):
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0


def spearman(a, b):
    """Spearman's rank correlation of two 1-d sequences (no ties expected: real-valued scores)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


@torch.no_grad()
def demo_goals(models, body, task, data, episodes, device="cpu"):
    """The benchmark's goals: g = q(s | p_T) of each own side-view demo of `task` under data/demos, each repeated for
    its `episodes` episodes -> (demos x episodes, F)."""
    folder = os.path.join(data, "demos", f"{body}_{task}_side")
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"no own-body demos at {folder}: collect them with `python collect.py --demos --data {data}`")
    demos = collect.load_folder(folder, ("p",))
    goals = models["goal_vae"].goal(torch.as_tensor(np.stack([d["p"][-1] for d in demos]), device=device))
    return goals.repeat_interleave(episodes, 0)


def goal_reaching(models, cfgs, episodes=3, steps=envs.EPISODE_STEPS, tasks=envs.TASKS, device="cpu"):
    """The benchmark (module docstring): {task: {'policy': [scores], 'random': [scores]}} over demos x episodes."""
    body, data = cfgs["train"].env, cfgs["train"].data
    out = {}
    for task in tasks:
        goals = demo_goals(models, body, task, data, episodes, device)
        env_list = [envs.make_env(body, task) for _ in range(len(goals))]
        out[task] = {}
        for name in tqdm(("policy", "random"), desc=f"goal reaching {body} {task}", leave=False):
            returns, _ = run_episodes(env_list, models, goals, steps, cfgs["wm"].obs, cfgs["train"].eval_seed, random_actions=name == "random")
            out[task][name] = [episode_score(task, r, steps) for r in returns]
    return out


def summary(scores):
    """Lines of the benchmark's table: each task, then the stand/walk/run average (jump apart)."""
    lines = [f"{'task':<22}{'policy':>16}{'random':>16}"]
    cell = lambda v: f"{np.mean(v):6.1f} +- {stderr(v):4.1f}"
    for task, s in scores.items():
        lines.append(f"{task + (' (not in D_body)' if task not in envs.BODY_TASKS else ''):<22}{cell(s['policy']):>16}{cell(s['random']):>16}")
    inside = [t for t in envs.BODY_TASKS if t in scores]
    if inside:
        # the average of the task means; its s.e. from the per-task standard errors (independent episodes)
        mean = lambda k: np.mean([np.mean(scores[t][k]) for t in inside])
        se = lambda k: np.sqrt(sum(stderr(scores[t][k]) ** 2 for t in inside)) / len(inside)
        average = {k: f"{mean(k):6.1f} +- {se(k):4.1f}" for k in ("policy", "random")}
        lines.append(f"{'average ' + '/'.join(inside):<22}{average['policy']:>16}{average['random']:>16}")
    return lines


BENCHMARK = ("eval_episodes", "eval_steps", "eval_seed")  # the TrainConfig fields a benchmark's scores depend on


def write_goal_reaching(run_dir, scores, tc, weights, name="goal_reaching.json"):
    """runs/<name>/goal_reaching.json: the scores, with the agent that made them (body, preset, rundir.weights_id)
    and the benchmark's settings, and the data folder whose demos were its goals."""
    record = {"agent": tc.env, "preset": tc.preset, "weights": weights, "settings": {k: getattr(tc, k) for k in BENCHMARK}, "data": tc.data, "scores": scores}
    path = os.path.join(run_dir, name)
    rundir.atomic_write(path, lambda f: f.write(json.dumps(record).encode()))
    return path


def read_goal_reaching(run_dir):
    """A run's goal_reaching.json, refused unless it scores the agent the run's checkpoint holds now."""
    path = os.path.join(rundir.work_path(run_dir), "goal_reaching.json")  # a shipped agent's in runs/agent_<body>
    again = f"run `python train.py --evaluate --run-dir {run_dir}`"
    if not os.path.exists(path):
        raise FileNotFoundError(f"no {path}: {again} first")
    try:
        record = json.load(open(path))
    except json.JSONDecodeError:
        raise ValueError(f"{path} is cut or damaged (not JSON): {again} again") from None
    if not isinstance(record, dict):
        raise ValueError(f"{path} is damaged (it holds {json.dumps(record)[:40]}, not a benchmark record): {again} again")
    if "weights" not in record:
        raise ValueError(f"{path} was written before results named their agent: {again} again")
    scores = record.get("scores")
    if not isinstance(scores, dict) or not all(isinstance(s, dict) and isinstance(s.get("policy"), list) and s["policy"] for s in scores.values()):
        raise ValueError(f"{path} is damaged (its scores are not per-task lists of the policy's episode scores): {again} again")
    now = rundir.weights_id(rundir.run_checkpoint(run_dir))
    if record["weights"] != now:
        raise ValueError(f"{path} scores the agent {record['weights']}, but {run_dir} now holds {now} (trained since): {again} again")
    return record


def learning_curve(run_dir):
    """runs/<name>/learning_curve.png from metrics.jsonl: Eq. 4's imagined goal reward (policy.policy_losses, and
    on reachable goals, reachable_goal_reward), Eq. 7's distances of encoder
    goals 1 and 15 steps ahead, and the world model's and goal VAE's losses, against updates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = rundir.read_jsonl(os.path.join(run_dir, "metrics.jsonl"))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.2))
    series = [("Eq. 4 imagined goal reward -d(s, g)", [("reward", "training goals"), ("reward_reachable", "reachable g", 0),
                                                       ("reward_reachable", "reachable g, pi given another g", 1),
                                                       ("reward_reachable", "reachable g, random actions", 2)]),
              ("Eq. 7: d(s_t, q(s | p_t+k))", [("d_enc", "k = 1", 0), ("d_enc", "k = 15", 2), ("d_enc", "other episode", 4)]),
              ("losses", [("wm_loss", "Eq. 2 world model"), ("goal_loss", "Eq. 3 goal VAE"), ("bc_loss", "hindsight BC")])]
    for ax, (title, keys) in zip(axes, series):
        for key, label, *index in keys:
            points = [(r["step"], r[key][index[0]] if index else r[key]) for r in rows if key in r]
            if points:
                ax.plot(*zip(*points), label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("update")
        if title == "losses":
            ax.set_yscale("symlog")  # losses of different scales (the goal VAE's KL is in the hundreds)
        if ax.lines:
            ax.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(run_dir, "learning_curve.png")
    rundir.atomic_write(path, lambda name: fig.savefig(name, dpi=80), by_name=True)  # never through a link
    plt.close(fig)
    return path


def across_runs(run_dirs):
    """Training seeds compared: each run's goal_reaching.json reduced to its per-task means, then mean +- s.e. over the
    runs (the s.e. of a claim about the method, not about one agent's episodes)."""
    seen = {}
    for run_dir in run_dirs:
        other = seen.setdefault(os.path.realpath(run_dir), run_dir)
        if other != run_dir:
            raise ValueError(f"{other} and {run_dir} are the same run: pass each training seed once")
    records = {run_dir: read_goal_reaching(run_dir) for run_dir in run_dirs}
    agents = {}
    for run_dir, record in records.items():  # a copy of a run (cp -a) is the same agent: one seed, not two
        other = agents.setdefault(record["weights"], run_dir)
        if other != run_dir:
            raise ValueError(f"{other} and {run_dir} hold the same agent ({record['weights']}): pass each training seed once")
    first = run_dirs[0]
    for run_dir, record in records.items():
        for key in ("agent", "preset", "settings"):
            if record[key] != records[first][key]:
                raise ValueError(f"{first} and {run_dir} differ in {key} ({records[first][key]} against {record[key]}): compare runs of "
                                 f"one body and preset, benchmarked alike")
    per_run = {}
    for run_dir, record in records.items():
        scores = record["scores"]
        per_run[run_dir] = {t: float(np.mean(s["policy"])) for t, s in scores.items()}
        per_run[run_dir]["average"] = float(np.mean([per_run[run_dir][t] for t in envs.BODY_TASKS if t in scores]))
    columns = list(next(iter(per_run.values())))
    lines = ["| run | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    lines += [f"| {r} | " + " | ".join(f"{v[c]:.1f}" for c in columns) + " |" for r, v in per_run.items()]
    lines.append(f"| mean +- s.e. over {len(per_run)} runs | " + " | ".join(
        f"{np.mean([v[c] for v in per_run.values()]):.1f} +- {stderr([v[c] for v in per_run.values()]):.1f}" for c in columns) + " |")
    return lines


def reachable_across_runs(run_dirs, last=5):
    """reward_reachable (reachable_goal_reward) of each run's metrics.jsonl: its first row (the fresh actor's, unless the
    run was resumed from one that did not log it) and the mean of its last `last` rows, mean +- s.e. over the runs; []
    when no run logged it."""
    first, end = [], []
    for run_dir in run_dirs:
        rows = rundir.read_jsonl(os.path.join(run_dir, "metrics.jsonl"))
        rows = [r["reward_reachable"] for r in rows if "reward_reachable" in r]
        if rows:
            first.append(rows[0])
            end.append(np.mean(rows[-last:], 0))
    if not first:
        return []
    first, end = np.array(first), np.array(end)
    cell = lambda x: f"{x.mean():.3f} +- {stderr(x):.3f}"
    return ["| imagined -d on reachable goals | actor given g | actor given another g | random actions |", "|---|---|---|---|",
            f"| first row (a fresh actor), {len(first)} runs | " + " | ".join(cell(first[:, k]) for k in range(3)) + " |",
            f"| last {last} rows | " + " | ".join(cell(end[:, k]) for k in range(3)) + " |",
            f"| last minus first, paired | {cell(end[:, 0] - first[:, 0])} | given g minus given another g, last: "
            f"{cell(end[:, 0] - end[:, 1])} | given g minus random, last: {cell(end[:, 0] - end[:, 2])} |"]


def gradient_share(run_dirs, last=5):
    """grad_eq4 and grad_bc of each run's metrics.jsonl (train.py logs them where cloning is on: the L2 norms of the
    gradients on the actor's parameters of Eq. 4's actor loss and of the weighted cloning loss, train.gradient_norms),
    the mean of its last `last` rows, then mean +- s.e. over the runs; [] when no run logged them."""
    norms = []
    for run_dir in run_dirs:
        rows = rundir.read_jsonl(os.path.join(run_dir, "metrics.jsonl"))
        rows = [(r["grad_eq4"], r["grad_bc"]) for r in rows if "grad_eq4" in r][-last:]
        if rows:
            norms.append(np.mean(rows, 0))
    if not norms:
        return []
    norms = np.array(norms)
    cell = lambda x, digits: f"{x.mean():.{digits}f} +- {stderr(x):.{digits}f}"
    return [f"| actor's gradient norm, last {last} rows, {len(norms)} runs | Eq. 4 | cloning | cloning / Eq. 4 |", "|---|---|---|---|",
            f"| mean +- s.e. | {cell(norms[:, 0], 3)} | {cell(norms[:, 1], 3)} | {cell(norms[:, 1] / norms[:, 0], 1)} |"]


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="Goal reaching of several phase-1 runs (e.g. training seeds), their imagined goal "
                                     "reward on reachable goals and the actor's gradient norms, mean +- s.e. over runs.", allow_abbrev=False)
    parser.add_argument("runs", nargs="+", help="run folders with goal_reaching.json (train.py writes it)")
    try:
        runs = parser.parse_args().runs
        print("\n".join(across_runs(runs) + [""] + reachable_across_runs(runs) + [""] + gradient_share(runs)))
    except (FileNotFoundError, ValueError) as error:
        raise SystemExit(f"error: {error}")
