"""Sec. 5: per-task expert policies that generate the demonstrations D_demo and the task part of D_body.

The paper trains its experts with Dreamer from pixels (GPU-days). Here each expert is Soft
Actor-Critic (Haarnoja et al. 2018) on proprioceptive state with the true task reward: the expert
only has to produce good behaviour, and state-based SAC reaches it in hours on a CPU.

All tasks of one body train in lockstep in one process as an ensemble (experts/sac.py): each task has its
own env, replay buffer, networks, temperature and optimiser state; nothing is shared but the matrix
multiply.

Outputs (committed, small, actor only, float16):
  experts/<body>_<task>.pt                 the final policy
  experts/history/<body>_<task>_<step>.pt  snapshots along training: the learning history D_body replays
Training state (networks, optimisers, replay; not committed) lives in --ckpt-dir and --resume continues.
A compact copy of each task (networks and temperature, float16, no replay; committed) goes to
experts/resume/<body>_<task>.pt: on a machine without --ckpt-dir's state, --resume --replace-committed starts
from them with an empty replay, which it refills with the current policy (seed_steps transitions) before
updating again. One file per task, so experts of one body may train in separate processes.
The committed files are never overwritten by a run that was not given --replace-committed (committed_files).
The expert stack is this folder, code and weights: `python -m experts --body walker` trains (experts/__main__.py).
"""
import argparse
import csv
import math
import os
import time
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import torch
from tqdm import tqdm

import envs
import rundir
from experts.sac import Actor, Critic, Replay, copy_member, sac_update, select_tasks

EXPERT_DIR = os.path.dirname(os.path.abspath(__file__))  # this folder: the expert stack's code and its committed weights


@dataclass
class ExpertConfig:
    # rundir.check_flags: the values a field may take where not a count (>= 1), a learning rate in (0, 1) or a float >= 0
    ranges: ClassVar[dict] = {"seed": (0, None), "seed_steps": (0, None), "gamma": (0, 1), "tau": (0, 1), "init_alpha": "> 0"}
    steps: int = 500_000  # agent steps per task (action repeat 2); run needs ~0.5M, stand far fewer
    seed_steps: int = 5_000  # uniform random actions before the first update (Yarats & Kostrikov pytorch_sac)
    batch: int = 256  # SAC paper
    hidden: int = 256  # SAC paper: 2 x 256
    lr: float = 3e-4  # SAC paper
    gamma: float = 0.99  # SAC paper
    tau: float = 0.005  # target critic EMA, SAC paper
    init_alpha: float = 0.1  # pytorch_sac on DMC
    snapshot_every: int = 50_000  # agent steps between history snapshots (100 episodes)
    eval_every: int = 10_000  # agent steps between 1-episode deterministic evaluations
    checkpoint_minutes: float = 15.0  # wall-clock between full checkpoints (replay included); one at every snapshot too
    final_episodes: int = 10  # episodes that score each snapshot; the best becomes the final expert (keep_best)
    seed: int = 0


# Fields that change what is learned: a resumed run must keep them (steps and logging may change).
LEARNING_FIELDS = ("seed_steps", "batch", "hidden", "lr", "gamma", "tau", "init_alpha", "seed")


def expert_path(body, task, step=None):
    if step is None:
        return os.path.join(EXPERT_DIR, f"{body}_{task}.pt")
    return os.path.join(EXPERT_DIR, "history", f"{body}_{task}_{step:07d}.pt")


def save_actor_member(actor, member, body, task, path, step, score=None):
    """Write one task's actor, float16, as a 1-member Actor state dict (with its --eval score if known)."""
    state = {k: v[member : member + 1].detach().half() for k, v in actor.state_dict().items()}
    meta = {"body": body, "task": task, "step": step, "hidden": actor.net[0].w.shape[2], "score": score}
    rundir.atomic_write(path, lambda f: torch.save({"actor": state, **meta}, f))


def keep_best(actor, body, tasks, step, episodes):
    """The final expert of each task is its best snapshot: member k of `actor` replaces experts/<body>_<task>.pt
    when its mean normalised score over `episodes` deterministic episodes (the seeds of `evaluate`, so the same
    figure as --eval) beats the saved one's. SAC's return can drop after a peak (stickman stand's did); the latest
    snapshot is not always the best."""
    env_list = [envs.make_env(body, task) for task in tasks]
    returns = np.mean([episode_returns(actor, env_list, 1000 + k) for k in range(episodes)], 0)
    for k, task in enumerate(tasks):
        score, final = float(envs.normalized_score(task, returns[k])), expert_path(body, task)
        saved = rundir.load_checkpoint(final) if os.path.exists(final) else {"score": -np.inf}
        best = saved.get("score")
        if best is None:  # a final written before scores were stored: score it once, and store the score
            best = float(envs.normalized_score(task, evaluate(body, task, episodes).mean()))
            rundir.atomic_write(final, lambda f: torch.save({**saved, "score": best}, f))
        if score > best:
            save_actor_member(actor, k, body, task, final, step, score)


def history_steps(body, task):
    """The training steps at which snapshots of this expert exist, ascending."""
    folder = os.path.join(EXPERT_DIR, "history")
    prefix = f"{body}_{task}_"
    names = os.listdir(folder) if os.path.isdir(folder) else []
    return sorted(int(n[len(prefix) : -3]) for n in names if n.startswith(prefix) and n.endswith(".pt"))


def load_expert(body, task, step=None):
    """A policy function obs (obs_dim,) -> (mean action (A,), Actor); step None = the final expert."""
    envs._check_name("body", body, envs.BODIES)
    envs._check_name("task", task, envs.TASKS)
    path = expert_path(body, task, step)
    if not os.path.exists(path):
        raise FileNotFoundError(f"no expert weights at {path}: train them with `python -m experts --body {body} --tasks {task}`")
    saved = rundir.load_checkpoint(path)
    if (saved.get("body"), saved.get("task")) != (body, task) or (step is not None and saved.get("step") != step):
        raise ValueError(f"{path} holds the expert of {saved.get('body')} {saved.get('task')} at step {saved.get('step')}, not {body} {task}"
                         f"{'' if step is None else f' at step {step}'}: put the right file back (git checkout {path}) or retrain it")
    w0, w_last = saved["actor"]["net.0.w"], saved["actor"]["net.4.w"]
    actor = Actor(1, w0.shape[1], w_last.shape[2] // 2, saved["hidden"])
    actor.load_state_dict({k: v.float() for k, v in saved["actor"].items()})
    return actor


@torch.no_grad()
def episode_returns(actor, env_list, seed):
    """Deterministic return of member k of `actor` in env_list[k], all in lockstep; (n,) array."""
    obs = np.stack([env.reset(seed=seed)[0] for env in env_list])
    totals, done = np.zeros(len(env_list)), False
    while not done:
        action = actor(torch.as_tensor(obs)[:, None], deterministic=True)[0][:, 0].double().numpy()
        results = [env.step(a) for env, a in zip(env_list, action)]
        obs = np.stack([r[0] for r in results])
        totals += [r[1] for r in results]
        done = results[0][3]
    return totals


def random_returns(body, task, episodes=10, seed=2000):
    """Returns of the uniform random policy: the lower bound of Eq. 8 for our jump."""
    env, rng, returns = envs.make_env(body, task), np.random.default_rng(seed), []
    for k in range(episodes):
        env.reset(seed=seed + k)
        returns.append(sum(env.step(rng.uniform(-1, 1, env.action_dim))[1] for _ in range(envs.EPISODE_STEPS)))
    return np.array(returns)


def evaluate(body, task, episodes=10, seed=1000, step=None):
    """Returns of the deterministic expert over `episodes` episodes (seeds seed, seed+1, ...)."""
    actor, env = load_expert(body, task, step), envs.make_env(body, task)
    return np.array([episode_returns(actor, [env], seed + k)[0] for k in range(episodes)])


@torch.no_grad()
def jump_stats(body, episodes=10, seed=1000, step=None):
    """What the jump expert does ("visibly jumps": the torso well above standing height, repeatedly), measured on
    the physics at every control step of its deterministic episodes, averaged over episodes:
    (share of steps with no body geom touching the floor, take-offs per episode = ground-to-air transitions
    that stay airborne >= 2 steps, highest torso rise above the standing height in metres, mean torso
    uprightness cos(pitch) over the airborne steps: 1 = vertical, 0 = horizontal)."""
    actor, env = load_expert(body, "jump", step), envs.make_env(body, "jump")
    airborne, takeoffs, peaks, upright = [], [], [], []
    for k in range(episodes):
        obs, flying, heights, zz = env.reset(seed=seed + k)[0], [], [], []
        for _ in range(envs.EPISODE_STEPS):
            action = actor(torch.as_tensor(obs)[None, None], deterministic=True)[0][0, 0].double().numpy()
            obs = env.step(action)[0]
            flying.append(envs.airborne(env.physics))
            heights.append(env.physics.named.data.xpos["torso", "z"])
            zz.append(env.physics.named.data.xmat["torso", "zz"])
        f = np.array(flying)
        upright.append(np.mean(np.array(zz)[f]) if f.any() else np.nan)
        airborne.append(f.mean())
        takeoffs.append(int(np.sum(~f[:-2] & f[1:-1] & f[2:])))
        peaks.append(max(heights) - envs.STAND_HEIGHT[body])
    return float(np.mean(airborne)), float(np.mean(takeoffs)), float(np.mean(peaks)), float(np.nanmean(upright))


def compact_path(body, task):
    return os.path.join(EXPERT_DIR, "resume", f"{body}_{task}.pt")


def committed_files(body, tasks):
    """The files under experts/ that training `tasks` of `body` may overwrite and that exist already."""
    paths = [p for task in tasks for p in (expert_path(body, task), compact_path(body, task))]
    paths += [expert_path(body, task, step) for task in tasks for step in history_steps(body, task)]
    return [p for p in paths if os.path.exists(p)]


def load_compact(body, tasks):
    """The compact states of `tasks` stacked into one ensemble's state dicts (module docstring)."""
    parts = []
    for task in tasks:
        if not os.path.exists(compact_path(body, task)):
            raise FileNotFoundError(f"no compact state at {compact_path(body, task)}: leave {task} out of --tasks, or train it from scratch without --resume")
        parts.append(rundir.load_checkpoint(compact_path(body, task)))
    state = {"step": min(p["step"] for p in parts), "log_alpha": torch.stack([p["log_alpha"] for p in parts]),
             "actor": {k: torch.cat([p["actor"][k] for p in parts]) for k in parts[0]["actor"]}}
    for name in ("critic", "critic_target"):  # each file holds [Q1, Q2] of its task; the ensemble wants Q1s, then Q2s
        state[name] = {k: torch.cat([p[name][k][q : q + 1] for q in (0, 1) for p in parts]) for k in parts[0][name]}
    return state


def train(body, tasks, cfg, ckpt_dir, resume, warm_start=(), replace_committed=False):
    """SAC for all `tasks` of `body` in lockstep (module docstring). Refuses, before anything is written, to overwrite
    committed files under experts/ unless replace_committed."""
    rundir.check_flags(cfg)
    ckpt = os.path.join(ckpt_dir, f"{body}.pt")
    if resume and not os.path.exists(ckpt) and not replace_committed:
        raise ValueError(f"--resume: no training state at {ckpt} (--ckpt-dir); to go on from the committed {compact_path(body, '<task>')} "
                         f"instead, add --replace-committed: the run then replaces the committed {body} experts")
    existing = committed_files(body, tasks)
    if existing and not replace_committed:
        raise ValueError(f"{existing[0]} and {len(existing) - 1} more committed files of the {body} {'/'.join(tasks)} experts exist: "
                         f"this run would overwrite them; pass --replace-committed to let it")
    torch.set_num_threads(1)
    n = len(tasks)
    env_list = [envs.make_env(body, task, seed=cfg.seed + 100 * k) for k, task in enumerate(tasks)]
    eval_envs = [envs.make_env(body, task) for task in tasks]
    obs_dim, action_dim = env_list[0].obs_dim, env_list[0].action_dim
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    actor = Actor(n, obs_dim, action_dim, cfg.hidden)
    critic = Critic(n, obs_dim, action_dim, cfg.hidden)
    critic_target = Critic(n, obs_dim, action_dim, cfg.hidden)
    critic_target.load_state_dict(critic.state_dict())
    log_alpha = torch.full((n,), math.log(cfg.init_alpha), requires_grad=True)
    optims = {
        "actor": torch.optim.Adam(actor.parameters(), lr=cfg.lr),
        "critic": torch.optim.Adam(critic.parameters(), lr=cfg.lr),
        "alpha": torch.optim.Adam([log_alpha], lr=cfg.lr),
    }
    target_entropy = -float(action_dim)  # SAC: -|A|
    replay = Replay(n, cfg.steps, obs_dim, action_dim)
    step, learn_from = 0, cfg.seed_steps
    compact = resume and not os.path.exists(ckpt)  # allowed above only with replace_committed
    if resume:
        state = load_compact(body, tasks) if compact else rundir.load_checkpoint(ckpt)
        if state["step"] > cfg.steps:
            raise ValueError(f"--steps {cfg.steps} is below step {state['step']} of the state resumed: pass --steps {state['step']} or more")
    if compact:
        for name, module in (("actor", actor), ("critic", critic), ("critic_target", critic_target)):
            module.load_state_dict({k: v.float() for k, v in state[name].items()})
        with torch.no_grad():
            log_alpha.copy_(state["log_alpha"].float())
        step = state["step"]
        learn_from = step + cfg.seed_steps  # refill the replay with the current policy first
        print(f"resumed the compact experts/resume/{body}_<task>.pt at step {step}: replay and optimisers start empty")
    elif resume:
        changed = [k for k in LEARNING_FIELDS if state["config"][k] != getattr(cfg, k)]
        if changed or not set(tasks) <= set(state["tasks"]):
            raise ValueError(f"{ckpt} was trained with other {', '.join(changed) or 'tasks: ' + ' '.join(state['tasks'])}; pass the same flags or delete it")
        if state["tasks"] != list(tasks):
            dropped = [k for k, task in enumerate(state["tasks"]) if task not in tasks]
            stopped = Actor(len(dropped), obs_dim, action_dim, cfg.hidden)
            stopped.load_state_dict({k: v[dropped] for k, v in state["actor"].items()})
            keep_best(stopped, body, [state["tasks"][k] for k in dropped], state["step"], cfg.final_episodes)  # a stopped expert's latest policy may be its best
            state = select_tasks(state, [state["tasks"].index(t) for t in tasks])
        for name, module in (("actor", actor), ("critic", critic), ("critic_target", critic_target)):
            module.load_state_dict(state[name])
        for name, opt in optims.items():
            opt.load_state_dict(state["optim_" + name])
        with torch.no_grad():
            log_alpha.copy_(state["log_alpha"])
        replay.size = state["replay_size"]
        for key in ("obs", "next_obs", "action", "reward"):
            getattr(replay, key)[:, : replay.size] = state["replay"][key].numpy()
        step, rng = state["step"], rundir.generator(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        print(f"resumed {ckpt} at step {step}")
    if warm_start:
        copy_member(warm_start, tasks, actor, critic, critic_target, log_alpha, optims)

    def save_checkpoint():  # what torch.load(weights_only=True) reads: tensors and plain values (the generator as its state)
        state = {
            "config": asdict(cfg), "tasks": list(tasks), "step": step, "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
            "actor": actor.state_dict(), "critic": critic.state_dict(), "critic_target": critic_target.state_dict(),
            "log_alpha": log_alpha.detach(), "replay_size": replay.size,
            "replay": {k: torch.from_numpy(getattr(replay, k)[:, : replay.size].copy()) for k in ("obs", "next_obs", "action", "reward")},
            **{"optim_" + k: opt.state_dict() for k, opt in optims.items()},
        }
        rundir.atomic_write(ckpt, lambda f: torch.save(state, f))
        member = lambda module, rows: {key: v[rows].half() for key, v in module.state_dict().items()}
        for k, task in enumerate(tasks):
            compact = {"task": task, "step": step, "actor": member(actor, [k]), "critic": member(critic, [k, k + n]),
                       "critic_target": member(critic_target, [k, k + n]), "log_alpha": log_alpha.detach()[k].clone()}
            rundir.atomic_write(compact_path(body, task), lambda f: torch.save(compact, f))

    os.makedirs(ckpt_dir, exist_ok=True)
    log_path = os.path.join(ckpt_dir, f"{body}_{'-'.join(tasks)}_log.csv")
    obs = np.stack([env.reset()[0] for env in env_list])
    last_ckpt, t0, losses = time.time(), time.time(), (float("nan"), float("nan"))
    bar = tqdm(total=cfg.steps, initial=step, desc=f"SAC {body} {'/'.join(tasks)}", mininterval=30)
    while step < cfg.steps:
        if step < cfg.seed_steps:  # the first run's random phase (a compact resume acts with its policy instead)
            action = rng.uniform(-1, 1, (n, action_dim)).astype(np.float32)
        else:
            with torch.no_grad():
                action = actor(torch.as_tensor(obs)[:, None])[0][:, 0].numpy()
        results = [env.step(a) for env, a in zip(env_list, action)]
        next_obs = np.stack([r[0] for r in results])
        replay.add(obs, action, [r[1] for r in results], next_obs)
        obs = next_obs
        if results[0][3]:  # all envs time out together (500 steps)
            obs = np.stack([env.reset()[0] for env in env_list])
        if step >= learn_from:
            losses = sac_update(actor, critic, critic_target, log_alpha, optims, replay.sample(cfg.batch, rng), cfg, target_entropy)
        step += 1
        bar.update(1)
        if step % cfg.snapshot_every == 0 or step == cfg.steps:
            for k, task in enumerate(tasks):
                save_actor_member(actor, k, body, task, expert_path(body, task, step), step)
            keep_best(actor, body, tasks, step, cfg.final_episodes)
            save_checkpoint()  # a resume never starts before a written snapshot (it would write that step again, differently)
            last_ckpt = time.time()
        if step % cfg.eval_every == 0:
            scores = [float(envs.normalized_score(t, r)) for t, r in zip(tasks, episode_returns(actor, eval_envs, 10_000 + step))]
            new = not os.path.exists(log_path)
            with open(log_path, "a", newline="") as f:
                w = csv.writer(f)
                if new:
                    w.writerow(["step", "minutes", "critic_loss", "actor_loss"] + [f"score_{t}" for t in tasks] + [f"alpha_{t}" for t in tasks])
                w.writerow([step, round((time.time() - t0) / 60, 1), round(losses[0], 4), round(losses[1], 4)] + [round(s, 1) for s in scores] + [round(a, 4) for a in log_alpha.exp().tolist()])
            bar.write(f"step {step}: score " + " ".join(f"{t} {s:.1f}" for t, s in zip(tasks, scores)))
        if time.time() - last_ckpt > 60 * cfg.checkpoint_minutes:
            save_checkpoint()
            last_ckpt = time.time()
    bar.close()
    print(f"done: {body} {tasks}; final policies in {EXPERT_DIR}")


def main():
    parser = argparse.ArgumentParser(prog="python -m experts", description="Train (or --eval) the per-task SAC experts of one body.", allow_abbrev=False)
    parser.add_argument("--body", choices=envs.BODIES)
    parser.add_argument("--tasks", nargs="+", default=list(envs.TASKS), choices=envs.TASKS)
    parser.add_argument("--ckpt-dir", default="runs/experts", help="training state (not committed)")
    parser.add_argument("--resume", action="store_true", help="continue from --ckpt-dir")
    parser.add_argument("--replace-committed", action="store_true",
                        help="let this run overwrite the committed files of its experts under experts/ (without --ckpt-dir's state, --resume then starts from experts/resume/)")
    parser.add_argument("--warm-start", nargs="+", default=[], metavar="DST=SRC",
                        help="restart expert DST from expert SRC's networks (copy_member); pass it once, later --resume runs without it")
    parser.add_argument("--eval", action="store_true", help="score the committed final experts: 10 episodes each")
    parser.add_argument("--history", action="store_true", help="with --eval: score every snapshot of experts/history instead (what D_body replays)")
    parser.add_argument("--pick-best", action="store_true", help="make the best snapshot of experts/history each task's final expert (keep_best)")
    parser.add_argument("--bounds", action="store_true", help="random-policy returns (Eq. 8's R_min) per body and task")
    for field, value in asdict(ExpertConfig()).items():
        parser.add_argument("--" + field.replace("_", "-"), type=type(value), default=value)
    args = parser.parse_args()
    if args.history and not args.eval:
        parser.error("--history works with --eval only: add --eval, or drop it")
    cfg = ExpertConfig(**{f: getattr(args, f) for f in asdict(ExpertConfig())})
    rundir.check_flags(cfg)
    torch.set_num_threads(1)  # small MLPs: one thread is fastest, and far faster when the cores are shared (train.py)
    if args.bounds:
        print("| body | task | random return (mean +- std of 10) |\n|---|---|---|")
        for body in [args.body] if args.body else envs.BODIES:
            for task in args.tasks:
                returns = random_returns(body, task)
                print(f"| {body} | {task} | {returns.mean():.1f} +- {returns.std():.1f} |")
        return
    if args.pick_best:
        for body in [args.body] if args.body else envs.BODIES:
            for task in args.tasks:
                for step in tqdm(history_steps(body, task), desc=f"{body} {task} snapshots"):
                    keep_best(load_expert(body, task, step), body, [task], step, cfg.final_episodes)
                saved = rundir.load_checkpoint(expert_path(body, task))
                print(f"{body} {task}: final = step {saved['step']}, score {saved['score']:.1f}")
        return
    if args.eval and args.history:
        print("| body | task | normalised score of each snapshot (training step: mean of 10 episodes) |\n|---|---|---|")
        for body in [args.body] if args.body else envs.BODIES:
            for task in [t for t in args.tasks if t in envs.BODY_TASKS]:
                scores = [f"{step // 1000}k: {envs.normalized_score(task, evaluate(body, task, step=step).mean()):.0f}" for step in history_steps(body, task)]
                print(f"| {body} | {task} | {', '.join(scores)} |")
        return
    if args.eval:
        bodies = [args.body] if args.body else envs.BODIES
        print("| body | task | return (mean of 10) | normalised score | training steps | jump: airborne steps, take-offs/episode, peak rise, upright in the air |\n|---|---|---|---|---|---|")
        for body in bodies:
            for task in args.tasks:
                returns = evaluate(body, task)
                step = rundir.load_checkpoint(expert_path(body, task))["step"]
                jump = ""
                if task == "jump":
                    airborne, takeoffs, peak, upright = jump_stats(body)
                    jump = f"{100 * airborne:.0f}%, {takeoffs:.1f}, {peak:.2f} m, {upright:.2f}"
                print(f"| {body} | {task} | {returns.mean():.1f} | {envs.normalized_score(task, returns.mean()):.1f} | {step} | {jump} |")
        return
    if args.body is None:
        parser.error("--body is required to train (or pass --eval)")
    train(args.body, args.tasks, cfg, args.ckpt_dir, args.resume, args.warm_start, args.replace_committed)
