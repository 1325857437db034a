"""Sec. 5, baseline GenRL (Mazzaglia et al. 2024): a task policy trained from scratch in the frozen world model's
imagination, rewarded for following the demo's video features mapped into the latent space.

GenRL's recipe, written with this project's models (world_model.py, goal_vae.py, policy.py):
  connector  GenRL learns a sequence model that unrolls one video-language embedding into a short sequence of
             latent states. Ours is phase 1's goal encoder q(s | p) (goal_vae.py) applied to each of the first
             demo's last L features p_{T-L+1..T}: the target sequence s*_0..s*_{L-1}, [mean_h, mean_z] each, which
             ends at the prompt p_T, "the last embedding of the first demonstration trajectory" (Sec. 5).
             Deviation: the sequence comes from the demo's own last features, not from a learnt unroll of p_T alone
             (there is no sequence connector here).
  reward     on each imagined arrival state s_j (j = 1..H, world_model.py's alignment) r_j = sim(s_j, s*_i(j)), with
             GenRL's choices: sim(x, y) = x.y / max(|x|, |y|)^2 ("max_cosine", 1 only for x = y), taken between the
             states' images under the first layer of the world model's decoder (GenRL compares states in its
             decoder's input layer too; its decoder reads z alone, ours [h, z]); and sequence alignment ("align_sequence"): every window of k imagined
             steps, offset t = 0..H-k, is scored by its mean sim to the target's first k states; with t* the best
             offset of each trajectory, i(j) = clamp(j - 1 - t*, 0, L - 1): the target starts where the imagined
             trajectory matches its beginning best, the steps before it are compared with the target's first
             state. The alignment is a constant (argmax, no gradient); the reward is differentiable in s_j.
  policy     a fresh actor pi(a | s) and critic V(s), the run's ActorCriticConfig (sizes, rates, horizon),
             trained by Dreamer's actor-critic (policy.rollout, lambda_return, actor_loss, critic_loss) in the
             frozen world model's imagination from D_body posterior states. The multi-task policy of phase 1 and
             the distance network are not used. The actor takes a constant zero goal of size 1 (no_goal): with
             the goal's weights multiplied by 0 it is pi(a | s).
Evaluation: the trained actor in the agent's own environment with the task's true reward, Eq. 8's normalised
score, eval_episodes episodes per seed; one row per seed appended to runs/<name>/results.jsonl (imitate.py's format).
A rerun skips the seeds that already have a row for the same demos and settings. The plumbing of a per-cell
baseline run (load_cell, run_seeds, evaluate_actor, cell_rows, append_row, the config flags) lives here and
aime_nob.py uses it.

Score against budget (ours, for the baselines' curves): --eval-at 1000,2000 also evaluates each seed after 1000 and
2000 of its --steps updates. Such a row is the row a run of that budget writes, bit for bit (the evaluation leaves
the training's random state as it was; tests/test_genrl.py), and counts as one. After each budget the seed's training
state is saved (runs/<name>/baselines/), so a killed seed goes on from its last budget, and a longer --steps later goes
on from the longest one instead of from update 0.

    python baselines/genrl.py --demo stickman_run --view side --run runs/<name> [--seeds 3] [--preset smoke|cpu]
    python baselines/genrl.py --settings SE-SV,SE-CV --run runs/<name> --steps 4000 --eval-at 1000,2000 [--shard 0/2]
"""
import argparse
import dataclasses
import hashlib
import json
import os
import sys
import time

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the project's modules, run as a script too
import checkpoint  # noqa: E402
import collect  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
import runner  # noqa: E402
from configs import PRESETS, GenRLConfig, budgets, config_flags  # noqa: E402
from video_encoder import check_same_encoder  # noqa: E402

METHOD = "GenRL"


def decoder_input(world_model, feat):
    """The world model decoder's first (linear) layer on feat (..., F) -> (..., U): where GenRL compares states."""
    layer = world_model.decoder[0] if world_model.cfg.obs == "state" else world_model.decoder.net[0]
    return layer(feat)


def similarity(x, y):
    """GenRL's "max_cosine" x.y / max(|x|, |y|)^2: (..., D), (..., D) -> (...). It is the cosine when |x| = |y| and
    1 only for x = y; the cosine would also give 1 to any positive multiple of y."""
    norm = torch.maximum(x.norm(dim=-1), y.norm(dim=-1)).clamp(min=1e-8)
    return (x * y).sum(-1) / norm**2


def aligned_reward(agent, target, window):
    """GenRL's sequence-aligned reward (module docstring): agent (N, H, D) imagined arrival states s_1..s_H, target
    (L, D) -> reward (N, H), differentiable in agent, and offset (N,) the best offset t* of each trajectory."""
    N, H, D = agent.shape
    L = len(target)
    if window > H:
        raise ValueError(f"--align-window {window} is longer than the run's imagination horizon {H}: pass a window <= {H}")
    assert target.shape == (L, D) and window <= L, (agent.shape, target.shape, window)
    with torch.no_grad():  # sim(s_{t+j}, s*_j) of every window t and step j, read off one (N, H, k) matrix of all pairs
        # (one matmul, not a gather of the (N, H - k + 1, k, D) windows: bench.py --only baselines)
        first = target[:window]
        pairs = (agent @ first.T) / torch.maximum(agent.norm(dim=-1)[..., None], first.norm(dim=-1)).clamp(min=1e-8) ** 2  # (N, H, k)
        t, j = torch.arange(H - window + 1, device=agent.device)[:, None], torch.arange(window, device=agent.device)
        offset = pairs[:, t + j, j].mean(-1).argmax(-1)  # (N,) t*
    index = (torch.arange(H, device=agent.device) - offset[:, None]).clamp(0, L - 1)  # (N, H) i(j)
    return similarity(agent, target[index]), offset


def target_states(models, demo_p, target_len):
    """The connector (module docstring): q(s | p) of the demo's last L features -> decoder-layer images (L, U)."""
    if len(demo_p) < target_len:
        raise ValueError(f"the first demo has {len(demo_p)} features, fewer than --target-len {target_len}: pass a shorter target")
    with torch.no_grad():
        goals = models["goal_vae"].goal(demo_p[-target_len:])  # (L, F) = [mean_h, mean_z] of each feature
        return decoder_input(models["world_model"], goals)


def no_goal(n, device):
    """The actor's constant goal, zeros (n, 1): policy.Actor with goal_dim 0 fails (its goal slice weight[:, -0:] is
    the whole matrix), so the task actors take one input fixed at 0, which makes them pi(a | s)."""
    return torch.zeros(n, 1, device=device)


def train_policy(models, cfgs, gc, target, segments, seed, device, on_budget=None, resume=None):
    """GenRL's task behaviour for one seed: gc.steps actor-critic updates in imagination from D_body segments
    (collect.Segments) -> the actor. on_budget(updates, actor, world_model, state) after each budget of budgets(gc),
    state() the seed's training state; resume: such a state, to go on from its updates."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    ac, wc, wm = cfgs["ac"], cfgs["wm"], models["world_model"]
    actor = policy.Actor(ac, wm.feat_dim, 1, wm.action_dim).to(device)  # the baseline's own actor, the run's sizes
    critic, slow_critic = (m.to(device) for m in policy.make_critics(ac, wm.feat_dim, 0))
    return_norm = policy.ReturnNorm(ac.return_norm_decay).to(device)
    optims = [torch.optim.Adam(actor.parameters(), lr=ac.actor_lr), torch.optim.Adam(critic.parameters(), lr=ac.critic_lr)]
    parts = {"actor": actor, "critic": critic, "slow_critic": slow_critic, "return_norm": return_norm, "optim_actor": optims[0],
             "optim_critic": optims[1]}
    first = 0
    if resume:
        first, rng = load_state(parts, resume)
    state = lambda: save_state(parts, step + 1, rng)
    stop = lambda: f"no row is written for seed {seed} (the run's --ac-actor-lr {ac.actor_lr}, --ac-critic-lr {ac.critic_lr} too high here?)"
    goal = no_goal(1, device)
    marks = budgets(gc)
    bar = tqdm(range(first, gc.steps), desc=f"{METHOD} seed {seed}", leave=False, initial=first, total=gc.steps)
    for step in bar:
        batch = segments.sample(wc.batch, rng, device)
        with torch.no_grad():
            post, _ = wm.observe(batch[wc.obs], batch["action"], batch["is_first"])
        start, _ = policy.sample_starts(post, gc.starts)
        with policy.freeze(wm, slow_critic):  # the world model is frozen (GenRL), the slow critic a constant
            feat, _, log_prob = policy.rollout(wm, actor, start, goal, ac.horizon)  # (N, H + 1, F)
            reward, _ = aligned_reward(decoder_input(wm, feat[:, 1:]), target, gc.align_window)  # (N, H)
            value = slow_critic(feat, None)  # (N, H + 1)
            returns = policy.lambda_return(reward, value, ac.gamma, ac.lambda_)  # (N, H)
        a_loss, metrics = policy.actor_loss(returns, log_prob, return_norm, ac.entropy)
        c_loss, _ = policy.critic_loss(critic, feat, None, returns)
        for opt, loss, what in zip(optims, (a_loss, c_loss), ("actor loss", "critic loss")):
            rundir.checked_step(opt, loss, f"{METHOD} seed {seed}: the {what}", step, stop, ac.grad_clip)
        policy.ema_update(slow_critic, critic, ac.slow_critic_rate)
        bar.set_postfix(sim=f"{reward.mean().item():.3f}", ret=f"{metrics['return']:.2f}")
        if on_budget and step + 1 in marks:
            on_budget(step + 1, actor, wm, state)
    return actor


def run_cell(run_dir, demo, view, gc, data=None):
    """GenRL on one demo folder for seeds 0..gc.seeds-1, at each budget of budgets(gc), skipping what has a row already
    -> the new rows."""
    cell = load_cell(run_dir, demo, view, data)
    models, cfgs, device = cell["models"], cell["cfgs"], cell["device"]
    inputs = {}

    def train(seed, on_budget, resume):
        if not inputs:  # once per cell, and only when a seed runs
            inputs["target"] = target_states(models, torch.as_tensor(cell["demos"][0]["p"], device=device), gc.target_len)
            inputs["segments"] = checkpoint.body_segments(cfgs)
        train_policy(models, cfgs, gc, inputs["target"], inputs["segments"], seed, device, on_budget, resume)

    return run_seeds(cell, METHOD, gc, train)


# --- per-cell plumbing of the baselines (also used by aime_nob.py) ---


def load_cell(run_dir, demo, view, data=None):
    """A phase-1 run and one demo folder (data/demos/<demo>_<view>): configs, models, the demos' features, task and
    setting. data: the data folder, default the run's."""
    device = "cuda" if torch.cuda.is_available() else "cpu"
    cfgs, models, ckpt = checkpoint.load_run(run_dir, device)  # a run in training refused (rundir.run_checkpoint)
    if data is not None:
        cfgs["train"] = dataclasses.replace(cfgs["train"], data=data)
    tc = cfgs["train"]
    rundir.fast_matmul()  # oneDNN where it is faster and still fp32 (rundir.py)
    folder = checkpoint.demo_folder(cfgs, demo, view)
    demos = collect.load_folder(folder, ("p",))
    for d in demos:
        check_same_encoder(ckpt["encoder"], d["encoder"], d["path"])
    demo_body, task = envs.parse_demo(demo)
    envs._check_name("task", task, envs.TASKS)
    return {"run_dir": run_dir, "cfgs": cfgs, "models": models, "ckpt": ckpt, "device": device, "demo": demo, "view": view,
            "demos": demos, "demo_returns": [round(d["return"], 3) for d in demos], "task": task,
            "setting": envs.setting(tc.env, demo_body, view), "weights": rundir.weights_id(ckpt)}


def evaluate_actor(cell, world_model, actor, episodes, steps, seed):
    """The actor pi(a | s) in `episodes` episodes of the agent's own env with the task's true reward (deterministic,
    s_t filtered by the world model, evaluate.run_episodes) -> Eq. 8's normalised scores."""
    body, task = cell["cfgs"]["train"].env, cell["task"]
    env_list = [envs.make_env(body, task) for _ in range(episodes)]
    returns, _ = evaluate.run_episodes(env_list, {"world_model": world_model, "actor": actor}, no_goal(episodes, cell["device"]),
                                       steps, cell["cfgs"]["wm"].obs, runner.EVAL_SEED + 100 * seed)  # GIIL's evaluation seeds
    for env in env_list:
        env.close()
    return [evaluate.episode_score(task, r, steps) for r in returns]


def result_config(cfg, budget=None):
    """The config fields a result depends on: all but the number of seeds and eval_at; with `budget`, those of a run
    of that budget (what its row at that budget carries)."""
    out = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("seeds", "eval_at")}
    return out if budget is None else {**out, cfg.budget_field: budget}


def save_state(parts, done, rng):
    """A seed's training state after `done` updates (or episodes): the state dicts of `parts` (modules, optimisers),
    the random states, as torch.load(weights_only=True) reads them."""
    return {"done": done, **{k: v.state_dict() for k, v in parts.items()}, "torch_rng": torch.get_rng_state(),
            "rng": rng.bit_generator.state}


def load_state(parts, state):
    """save_state's state into `parts` and the torch random state -> (done, the numpy generator)."""
    for k, v in parts.items():
        v.load_state_dict(state[k])
    torch.set_rng_state(state["torch_rng"])
    return state["done"], rundir.generator(state["rng"])


def state_path(cell, method, cfg, seed):
    """Where a seed's training state goes after each budget: one file per cell, seed and settings but the budget, so
    that a longer budget goes on from it."""
    key = hashlib.sha1(json.dumps({**result_config(cfg, 0), "demo_returns": cell["demo_returns"], "weights": cell["weights"]},
                                  sort_keys=True).encode()).hexdigest()[:10]  # never a state trained on another agent's world model
    return os.path.join(cell["run_dir"], "baselines", f"{method}_{cell['demo']}_{cell['view']}_s{seed}_{key}.pt")


def run_seeds(cell, method, cfg, train, **extra):
    """Seeds 0..cfg.seeds-1 of a baseline on one cell, each evaluated at budgets(cfg) -> the new rows.
    train(seed, on_budget, resume) trains one seed and calls on_budget(budget, actor, world_model, state) at each
    budget; resume is the state saved at the seed's longest budget, when every missing row is beyond it. A row's time
    is that of a run of its budget alone: training up to it and its own evaluation (not the earlier evaluations)."""
    marks = budgets(cfg)
    configs = {b: result_config(cfg, b) for b in marks}
    have = {b: {r["seed"] for r in cell_rows(cell, method, configs[b])} for b in marks}
    rows = []
    for seed in range(cfg.seeds):
        missing = [b for b in marks if seed not in have[b]]
        if not missing:
            continue
        path = state_path(cell, method, cfg, seed)
        resume = rundir.load_checkpoint(path, cell["device"]) if os.path.exists(path) else None
        if resume and resume["done"] >= min(missing):  # a row is missing at or below it: the seed runs from the start
            resume = None
        clock = {"start": time.time() - (resume["seconds"] if resume else 0.0), "evaluating": 0.0}

        def on_budget(budget, actor, world_model, state):
            seconds = time.time() - clock["start"] - clock["evaluating"]  # training so far
            if seed not in have[budget]:
                t0 = time.time()
                with torch.random.fork_rng(devices=[]):  # run_episodes seeds torch: the training's draws go on as without it
                    scores = evaluate_actor(cell, world_model, actor, cfg.eval_episodes, cfg.eval_steps, seed)
                clock["evaluating"] += time.time() - t0
                extras = {k: budget if v == "budget" else v for k, v in extra.items()}
                rows.append(append_row(cell, method, seed, scores, seconds + time.time() - t0, configs[budget], **extras))
            rundir.atomic_write(path, lambda f: torch.save({**state(), "seconds": seconds}, f))

        train(seed, on_budget, resume)
    report(cell, method, configs[marks[-1]], len(rows))
    return rows


def cell_rows(cell, method, config):
    """This cell's rows of `method` made by the same agent's weights with the same demos (their returns) and config."""
    return runner.finished(runner.load_results(cell["run_dir"]), cell["demo"], cell["view"], cell["demo_returns"], {method: config}, cell["weights"])


def append_row(cell, method, seed, scores, seconds, config, **extra):
    """One result row in imitate.py's format, appended to runs/<name>/results.jsonl -> the row."""
    row = {"agent": cell["cfgs"]["train"].env, "demo": cell["demo"], "view": cell["view"], "task": cell["task"], "setting": cell["setting"],
           "method": method, "seed": seed, "score": float(np.mean(scores)), "episode_scores": scores, "time": round(seconds, 1),
           "demo_returns": cell["demo_returns"], "config": config, "weights": cell["weights"], **extra}
    rundir.append_jsonl(os.path.join(cell["run_dir"], "results.jsonl"), row)
    return row


def report(cell, method, config, ran):
    """Prints the cell's score over all its finished seeds."""
    scores = [r["score"] for r in cell_rows(cell, method, config)]
    print(f"{method} {cell['cfgs']['train'].env} imitating {cell['demo']} ({cell['view']} view, {cell['setting']}): normalised score "
          f"{np.mean(scores):.1f} +- {evaluate.stderr(scores):.1f} over {len(scores)} seeds ({ran} run now); "
          f"rows in {os.path.join(cell['run_dir'], 'results.jsonl')}")


def config_from_args(cls, presets, args):
    """dataclass defaults < the preset's overrides < explicit flags."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if getattr(args, f.name) is not None}
    return cls(**{**presets[given.get("preset", "cpu")], **given})


def cell_parser(description, cls, presets):
    parser = argparse.ArgumentParser(description=description, allow_abbrev=False)
    parser.add_argument("--demo", help="<demonstrator body>_<task>, e.g. stickman_run (or --settings)")
    parser.add_argument("--view", choices=envs.VIEWS, help="camera of the demo (default side)")
    parser.add_argument("--settings", help="instead of --demo: every cell of these settings for the run's agent (4 tasks each), "
                        "comma-separated, e.g. SE-SV,SE-CV")
    parser.add_argument("--shard", metavar="I/N", help="with --settings: only its cells I, I + N, ... (N processes on one run)")
    parser.add_argument("--run", default=checkpoint.default_run_dir("walker", "cpu"), help="the phase-1 run (train.py) whose world model is used")
    parser.add_argument("--data", default=None, help="data folder with demos/ and D_body (default: the run's)")
    rundir.threads_flag(parser)
    config_flags(parser, cls, choices={"preset": tuple(presets)})
    return parser


def run_cells(parser, run_cell, method, cls, presets):
    """A baseline's command: --demo (one cell) or --settings (each of their cells). One process at a time runs a cell,
    any of its methods (runner.cell_lock, imitate.py's and tables.py's lock): --demo stops in one line while another runs
    it (runner.running_cell), --settings skips it."""
    args = parser.parse_args()
    rundir.use_threads(args.threads)
    if bool(args.demo) == bool(args.settings):
        parser.error("pass --demo NAME (one cell) or --settings SE-SV,... (their cells), not both")
    if args.settings and args.view:
        parser.error("--view does nothing with --settings (a setting names the view): drop it")
    if args.shard and not args.settings:
        parser.error("--shard works with --settings only: add --settings, or drop it")
    cfg = config_from_args(cls, presets, args)  # a bad value: ValueError, one line (rundir.run_main)
    rundir.run_checkpoint(args.run)
    args.run = checkpoint.work_folder(args.run)
    if args.demo:
        with runner.running_cell(args.run, args.demo, args.view or "side"):
            return run_cell(args.run, args.demo, args.view or "side", cfg, args.data)
    settings, shard = runner.parse_settings(args.settings), runner.parse_shard(args.shard)
    agent = checkpoint.load_run(args.run)[0]["train"].env
    for task, where in [c for c in envs.cells(agent) if c[1] in settings][shard[0]::shard[1]]:
        demo, view = envs.demo_of(agent, task, where)
        lock = runner.cell_lock(args.run, demo, view)
        with rundir.claim(lock) as other:
            if other:
                print(f"{demo} ({view} view): process {other} is running this cell now ({lock}): {method} skipped here")
            else:
                run_cell(args.run, demo, view, cfg, args.data)


def main():
    run_cells(cell_parser("Baseline GenRL: a task policy in the frozen world model's imagination, rewarded by latent similarity to a demo.",
                          GenRLConfig, PRESETS["genrl"]), run_cell, METHOD, GenRLConfig, PRESETS["genrl"])


if __name__ == "__main__":
    rundir.run_main(main, "the finished seeds are in the run's results.jsonl: the same command runs the others")
