"""Speed figures for the README: python bench.py [--only render ...]. Each section measures in one run."""
import argparse
import os
import subprocess
import time

import numpy as np

import configs
import envs


def timed(fn, repeat, warmup=3):
    """Seconds per call of fn, after a few warm-up calls."""
    for _ in range(warmup):
        fn()
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat


def bench_render(repeat=200):
    """dm_control's default physics.render(64, 64) against envs.Env.render(), same state, same run."""
    env = envs.make_env("walker", "walk")
    env.reset(seed=0)
    default = timed(lambda: env.physics.render(64, 64, camera_id="side"), repeat)
    ours = timed(env.render, repeat)
    print(f"render 64x64   dm_control default {1 / default:7.0f} frames/s | ours {1 / ours:7.0f} frames/s | ratio {default / ours:.1f}x")


def features_per_s(frames_per_call=None, repeats=3):
    """Frames/s of the default video encoder (one process, single-threaded numpy) and of rendering, on one walker
    episode; frames_per_call: frames per encoder call, default one episode. -> (encoder frames/s, render frames/s)."""
    import video_encoder

    env = envs.make_env("walker", "walk")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    frames_per_call = frames_per_call or envs.EPISODE_STEPS + 1
    start = time.perf_counter()
    frames = [env.render()]
    while len(frames) < frames_per_call:
        env.step(rng.uniform(-1, 1, env.action_dim))
        frames.append(env.render())
    render_fps = frames_per_call / (time.perf_counter() - start)  # includes the physics steps, as collection does
    env.close()
    encoder, frames = video_encoder.DefaultEncoder(), np.stack(frames)
    return frames_per_call / timed(lambda: encoder(frames), repeats, warmup=1), render_fps


def bench_features():
    """The default video encoder against rendering (+ physics), one thread: features must not hold collection back."""
    encoder_fps, render_fps = features_per_s()
    print(f"features       default encoder {encoder_fps:7.0f} frames/s | render + physics {render_fps:7.0f} frames/s | ratio {encoder_fps / render_fps:.1f}x")


def component_updates(preset="cpu", obs_dim=24, action_dim=6, p_dim=512, device="cpu"):
    """One update of each phase-1 component at a preset's sizes, on a random batch of collect.py's shapes, as
    {name: zero-argument function}: forward, backward, gradient clipping and an Adam step, as train.py does them."""
    import torch

    import cloning
    import distance
    import goal_vae
    import policy
    import world_model as W
    from tests.fixtures import random_batch

    cfg = {name: configs.COMPONENTS[name][0](**configs.PRESETS[name][preset]) for name in ("wm", "goal", "dist", "ac", "cloning")}
    obs_shape = obs_dim if cfg["wm"].obs == "state" else (64, 64, 3)
    wm = W.WorldModel(cfg["wm"], obs_shape, action_dim)
    vae = goal_vae.GoalVAE(cfg["goal"], p_dim, cfg["wm"].deter, wm.latent)
    dist_net = distance.DistanceNet(cfg["dist"], wm.feat_dim, wm.decoder if cfg["dist"].input == "obs" else None)
    actor = policy.Actor(cfg["ac"], wm.feat_dim, wm.feat_dim, action_dim)
    critic, slow_critic = policy.make_critics(cfg["ac"], wm.feat_dim, wm.feat_dim)
    return_norm = policy.ReturnNorm(cfg["ac"].return_norm_decay)
    for m in (wm, vae, dist_net, actor, critic, slow_critic, return_norm):
        m.to(device)
    batch = {k: v.to(device) for k, v in random_batch(cfg["wm"].obs, obs_shape, action_dim, cfg["wm"].batch, cfg["wm"].seq_len, p_dim).items()}
    with torch.no_grad():
        post, _ = wm.observe(batch[cfg["wm"].obs], batch["action"], batch["is_first"])
        post_feat, goal_feat = wm.feat(post), vae.goal(batch["p"])
    modules = {"wm": [wm], "goal": [vae], "dist": [dist_net], "ac": [actor, critic]}
    opts = {k: [torch.optim.Adam(m.parameters(), lr=3e-4) for m in ms] for k, ms in modules.items()}

    def step(name, loss):
        for opt in opts[name]:
            opt.zero_grad(set_to_none=True)
        loss.backward()
        for m, opt in zip(modules[name], opts[name]):
            torch.nn.utils.clip_grad_norm_(m.parameters(), 100.0)
            opt.step()

    def actor_critic():
        start, index = policy.sample_starts(post, cfg["ac"].starts)
        goal = policy.sample_goals(post_feat, goal_feat, index, batch["is_first"], cfg["ac"].goal_mix, cfg["ac"].goal_near)
        a_loss, c_loss, _ = policy.policy_losses(wm, dist_net, actor, critic, slow_critic, return_norm, start, goal, cfg["ac"])
        step("ac", a_loss + c_loss)  # disjoint: the actor loss reaches only the actor, the critic loss only the critic
        policy.ema_update(slow_critic, critic, cfg["ac"].slow_critic_rate)

    pairs = lambda: distance.sample_pairs(batch["episode"], batch["is_first"], cfg["dist"].pairs)
    clone = lambda: step("ac", cloning.bc_loss(actor, post_feat, goal_feat, batch["action"], goal_feat[:, -1], cfg["cloning"].bc_final)[0])
    return {
        "Eq. 2 world model": lambda: step("wm", wm.loss(batch)[0]),
        "Eq. 3 goal VAE": lambda: step("goal", vae.loss(batch["p"], post)[0]),
        "Eq. 7 distance": lambda: step("dist", distance.distance_loss(dist_net, post_feat, pairs(), cfg["wm"].seq_len, cfg["dist"].contrastive_weight,
                                                                       goal_feat if cfg["dist"].encoder_goals else None)[0]),
        f"Eq. 4 actor-critic ({cfg['ac'].starts} starts x {cfg['ac'].horizon} steps)": actor_critic,
        f"ours cloning step (x {cfg['cloning'].bc_steps} per update)": clone,
    }


def bench_components():
    """Each phase-1 component's update at the cpu preset, one thread, with fp32 matmuls in MKL and through oneDNN
    (rundir.fast_matmul, what train.py uses where it stays fp32), alternating in this one run; with the matmul FLOPs of
    each (forward and backward, torch.utils.flop_counter) and the rate they run at, against this core's peak (a
    1024 x 1024 fp32 matmul on the same route): how far one thread could go without fewer FLOPs or less precision."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    import rundir

    torch.set_num_threads(1)
    fast = rundir.fast_matmul()
    routes = ("none", "bf16") if fast else ("none",)
    updates, times, flops = component_updates(), {}, {}
    for name, update in updates.items():
        with FlopCounterMode(display=False) as counter:
            update()
        flops[name] = counter.get_total_flops()
    for _ in range(2):
        for route in routes:
            torch.backends.mkldnn.matmul.fp32_precision = route
            for name, update in updates.items():
                times.setdefault((name, route), []).append(timed(update, repeat=5, warmup=2))
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    peak = 2 * 1024**3 / timed(lambda: a @ b, repeat=10)  # on the last route, oneDNN's where fast
    used = routes[-1]
    for name in updates:
        line = f"phase 1        {name}: {1000 * np.mean(times[name, 'none']):.0f} ms"
        if fast:
            line += f" | oneDNN {1000 * np.mean(times[name, 'bf16']):.0f} ms | ratio {np.mean(times[name, 'none']) / np.mean(times[name, 'bf16']):.2f}x"
        print(line + f" | {flops[name] / 1e9:.2f} GFLOP at {flops[name] / np.mean(times[name, used]) / 1e9:.0f} GFLOP/s")
    if not fast:
        print("phase 1        (oneDNN fp32 matmuls not used: on this CPU they would not compute in fp32, rundir.fast_matmul)")
    bc_steps = configs.COMPONENTS["cloning"][0]().bc_steps
    count = {name: bc_steps if name.startswith("ours cloning") else 1 for name in updates}  # the first cloning step rides on Eq. 4's
    total_flops = sum(count[n] * flops[n] for n in updates)
    total_s = sum(count[n] * np.mean(times[n, used]) for n in updates)
    print(f"phase 1        one update: {total_flops / 1e9:.1f} GFLOP in {1000 * total_s:.0f} ms ({total_flops / total_s / 1e9:.0f} GFLOP/s); "
          f"this core's fp32 peak {peak / 1e9:.0f} GFLOP/s: at most {total_s * peak / total_flops:.2f}x on one thread with the same FLOPs")


def bench_gpu():
    """Each phase-1 component's update on the GPU, at the cpu preset's sizes and at the paper preset's (pixels)."""
    import torch

    if not torch.cuda.is_available():
        raise SystemExit("bench.py --only gpu needs a CUDA GPU (torch.cuda.is_available() is False)")

    def on_gpu(update):
        def run():
            update()
            torch.cuda.synchronize()
        return run

    for preset in ("cpu", "paper"):
        updates = component_updates(preset, device="cuda")
        times = {name: timed(on_gpu(update), repeat=10) for name, update in updates.items()}
        for name, t in times.items():
            print(f"phase 1 GPU    {preset} preset, {name}: {1000 * t:.0f} ms")
        print(f"phase 1 GPU    {preset} preset, one update of all four: {1000 * sum(times.values()):.0f} ms ({torch.cuda.get_device_name()})")


def train_updates_per_s(tree, data, threads, logs=4, every=10):
    """Updates/s of the real train.py loop of the source tree `tree` (walker, cpu preset, the actor-critic from the
    first update), read from its metrics.jsonl: the mean over `logs` log intervals after the first (warm-up)."""
    import json
    import subprocess
    import sys
    import tempfile

    run = tempfile.mkdtemp()
    cmd = [sys.executable, "train.py", "--env", "walker", "--steps", "100000", "--policy-start", "0", "--log-every", str(every),
           "--checkpoint-every", "100000", "--threads", str(threads), "--run-dir", run, "--data", data]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    proc = subprocess.Popen(cmd, cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    path = os.path.join(run, "metrics.jsonl")
    try:
        while proc.poll() is None:
            rows = [json.loads(line) for line in open(path)] if os.path.exists(path) else []
            if len(rows) > logs:
                return logs * every / sum(every / r["updates_per_s"] for r in rows[1 : logs + 1])
            time.sleep(1)
        raise RuntimeError(f"train.py in {tree} stopped: {proc.stderr.read().decode()[-500:]}")
    finally:
        proc.kill()
        proc.wait()


# GIIL-FT's update (goal_inference.finetune_goal) of the shipped walker on the stickman's side-view walk demos, timed in a
# source tree of its own (this one, or a commit's since goal_inference.py): seconds per update after 3 warm-up updates
FT_UPDATE = """
import dataclasses, sys, time
import torch
import collect, goal_inference, rundir
from checkpoint import load_run
try:  # every config in configs.py, or a commit's from before it
    from configs import ImitateConfig, OTConfig
except ImportError:
    from ot_reward import OTConfig
    ImitateConfig = goal_inference.ImitateConfig
torch.set_num_threads(1)
rundir.fast_matmul()
cfgs, models, _ = load_run(sys.argv[1], "cpu")
demo_p = [d["p"] for d in collect.load_folder(sys.argv[2], ("p",))]
run = lambda n: goal_inference.finetune_goal(models, cfgs, dataclasses.replace(ImitateConfig(), steps=n), OTConfig(),
                                     torch.as_tensor(demo_p[0][-1]), demo_p, 0, "cpu")
run(3)
start = time.perf_counter()
run(int(sys.argv[3]))
print((time.perf_counter() - start) / int(sys.argv[3]))
"""

# D_body episodes as a collection worker runs them (collect._worker: simulate, render, features, compressed write), timed
# in a source tree: seconds per episode over 2 exploration and 2 expert-snapshot episodes, after one untimed of each
# (a worker runs ~280 episodes of 4 kinds: what it does once per process is not the rate)
COLLECT_EPISODE = """
import sys, tempfile, time
import collect
try:  # every config in configs.py, or a commit's from before it
    from configs import CollectConfig
except ImportError:
    from collect import CollectConfig
cfg = CollectConfig(explore_episodes=3, task_episodes=3)
jobs = collect.episode_jobs("walker", cfg, tempfile.mkdtemp())
explore, walk = [j for j in jobs if j[1]["kind"] == "explore"], [j for j in jobs if j[1]["kind"] == "walk"]
for paths, job in (explore[0], walk[0]):
    collect._worker((paths, job, "default"))
start = time.perf_counter()
for paths, job in explore[1:] + walk[1:]:
    collect._worker((paths, job, "default"))
print((time.perf_counter() - start) / 4)
"""


# The baselines' cost, timed in a source tree: seconds per GenRL update (genrl.train_policy) and per AIME-NoB round (one
# episode collected, encoded and OT-labelled, then its 50 updates: aime_nob.train_seed), the shipped walker on its own
# side-view walk demos, one thread, after a warm-up (this tree, or a commit's since baselines/)
BASELINE_UPDATE = """
import dataclasses, sys, time
import numpy as np, torch
import checkpoint
from baselines import aime_nob, genrl
try:  # every config in configs.py, or a commit's from before it
    from configs import AIMENoBConfig, GenRLConfig
except ImportError:
    AIMENoBConfig, GenRLConfig = aime_nob.AIMENoBConfig, genrl.GenRLConfig
torch.set_num_threads(1)
cell = genrl.load_cell(sys.argv[1], "walker_walk", "side", sys.argv[4])
models, cfgs, n = cell["models"], cell["cfgs"], int(sys.argv[3])
if sys.argv[2] == "genrl":
    gc = GenRLConfig()
    target = genrl.target_states(models, torch.as_tensor(cell["demos"][0]["p"]), gc.target_len)
    segments = checkpoint.body_segments(cfgs)
    run = lambda k: genrl.train_policy(models, cfgs, dataclasses.replace(gc, steps=k), target, segments, 0, "cpu")
else:
    demo_p = torch.as_tensor(np.stack([d["p"] for d in cell["demos"]]))
    body, encoder = checkpoint.body_segments(cfgs), aime_nob.load_encoder("default")
    run = lambda k: aime_nob.train_seed(cell, dataclasses.replace(AIMENoBConfig(), env_steps=k * 500), body, encoder, demo_p, 0)
run(max(1, n // 4))
start = time.perf_counter()
run(n)
print((time.perf_counter() - start) / n)
"""


def in_tree(tree, code, *args):
    """Runs `code` (a script that prints one number) with the source tree `tree` as its working directory -> that number."""
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=tree, env=env, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"bench.py in {tree}: {out.stderr.strip().splitlines()[-1]}")
    return float(out.stdout.split()[-1])


def against(rev, measures, rounds=2):
    """Each of `measures` ({label: (unit, higher_is_better, fn(tree))}) for this tree and, with rev, for that git commit's
    source, alternating old and new `rounds` times in this one run so that both see the same load; one line each."""
    import shutil
    import tempfile

    trees = {"this tree": os.path.dirname(os.path.abspath(__file__))}
    if rev:
        trees = {rev: tempfile.mkdtemp(), **trees}
    try:
        if rev:
            archive = subprocess.run(["git", "archive", rev], capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", trees[rev]], input=archive, check=True)
        for label, (unit, higher, measure) in measures.items():
            values = {name: [] for name in trees}
            for _ in range(rounds):
                for name, tree in trees.items():
                    values[name].append(measure(tree))
            line = " | ".join(f"{name} {np.mean(v):.3g} {unit}" for name, v in values.items())
            if rev:
                ratio = np.mean(values["this tree"]) / np.mean(values[rev])
                line += f" | speed-up {ratio if higher else 1 / ratio:.2f}x"
            print(f"{label}: {line}")
    finally:
        if rev:
            shutil.rmtree(trees[rev])


def bench_phase1(rev=None, data="data"):
    """Updates/s of the real train.py loop (cpu preset, walker's D_body) at 1 and 2 threads, with --against REV beside
    that commit's code in the same run."""
    if not os.path.isdir(os.path.join(data, "walker")):
        raise SystemExit(f"bench.py --only phase1 trains on {data}/walker: collect it with `python collect.py --env walker`")
    data = os.path.abspath(data)
    against(rev, {f"phase 1        train.py loop, {n} thread{'s' if n > 1 else ''}": ("updates/s", True, lambda tree, n=n: train_updates_per_s(tree, data, n))
                  for n in (1, 2)})


def bench_finetune(rev=None, run="agents/walker", demos="data/demos/stickman_walk_side", updates=10):
    """Seconds per GIIL-FT update (goal_inference.finetune_goal, one thread), with --against REV beside that commit's code."""
    if not os.path.isdir(demos):
        raise SystemExit(f"bench.py --only finetune reads {demos}: collect it with `python collect.py --demos`")
    run, demos = os.path.abspath(run), os.path.abspath(demos)
    against(rev, {"GIIL-FT        update (64 starts x 15 steps, windowed OT)": ("s", False, lambda tree: in_tree(tree, FT_UPDATE, run, demos, updates))})


def bench_collect(rev=None):
    """Seconds per D_body episode on one core (simulate, render, features, compressed write), with --against REV
    beside that commit's code."""
    against(rev, {"collect        D_body episode (500 steps), one core": ("s", False, lambda tree: in_tree(tree, COLLECT_EPISODE))})


def bench_baselines(rev=None, run="agents/walker"):
    """Seconds per GenRL update and per AIME-NoB round (one thread), with --against REV beside that commit's code."""
    if not os.path.isdir("data/demos/walker_walk_side") or not os.path.isdir("data/walker"):
        raise SystemExit("bench.py --only baselines reads data/walker and data/demos/walker_walk_side: `python collect.py --env walker --demos`")
    run, data = os.path.abspath(run), os.path.abspath("data")
    against(rev, {"GenRL          update (128 starts x 15 steps, aligned reward)": ("s", False, lambda tree: in_tree(tree, BASELINE_UPDATE, run, "genrl", 100, data)),
                  "AIME-NoB       round (1 episode, its OT labels, 50 updates)": ("s", False, lambda tree: in_tree(tree, BASELINE_UPDATE, run, "aime", 2, data))})


def ot_seconds(B=256, T=16, M=500, K=10, D=64, repeat=3):
    """Seconds per ot_reward.ot_reward call on one thread, whole-demo and windowed matching (torch's threads restored)."""
    import torch
    import torch.nn.functional as F

    import ot_reward

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    agent_p = torch.randn(B, T, D, generator=gen)
    demo_p = F.normalize(torch.randn(K, M, D, generator=gen), dim=-1)
    demo_offsets = torch.randint(0, M, (B,), generator=gen)
    cfg = configs.OTConfig()
    seconds = lambda **kwargs: timed(lambda: ot_reward.ot_reward(agent_p, demo_p, cfg, **kwargs), repeat, warmup=1)
    try:
        return {"B": B, "T": T, "M": M, "K": K, "D": D, "whole_demo_s": seconds(), "window_s": seconds(demo_offsets=demo_offsets)}
    finally:
        torch.set_num_threads(threads)


def bench_ot():
    """The OT reward (App. C): one call at GIIL-FT's cpu size and at a paper-like size, one thread."""
    cpu = configs.ImitateConfig()
    for B, M in ((cpu.starts, envs.EPISODE_STEPS), (256, envs.EPISODE_STEPS)):
        r = ot_seconds(B=B, T=15, M=M, K=10, D=512, repeat=2)
        print(f"OT reward      B={B} trajectories x T=15 against K=10 demos of M={M} frames (D=512): {1000 * r['whole_demo_s']:.0f} ms (windowed: {1000 * r['window_s']:.0f} ms)")


AGAINST = ("phase1", "finetune", "collect", "baselines")  # the sections that take --against
SECTIONS = {"render": bench_render, "features": bench_features, "collect": bench_collect, "components": bench_components, "phase1": bench_phase1, "finetune": bench_finetune,
            "baselines": bench_baselines, "ot": bench_ot, "gpu": bench_gpu}

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, allow_abbrev=False)
    parser.add_argument("--only", nargs="+", choices=SECTIONS, default=[s for s in SECTIONS if s != "gpu"], help="default: all but gpu")
    parser.add_argument("--against", metavar="REV", help="phase1, finetune, collect, baselines: also time this git commit's code, in the same run "
                        "(e.g. 3e0cd69)")
    args = parser.parse_args()
    if args.against and not set(args.only) & set(AGAINST):
        parser.error(f"--against times {', '.join(AGAINST)} only: add one of them to --only, or drop --against")
    if args.against and subprocess.run(["git", "rev-parse", "--verify", "--quiet", args.against + "^{commit}"], capture_output=True).returncode:
        parser.error(f"--against {args.against}: not a commit of this repository (git log --oneline lists them)")
    for name in args.only:
        SECTIONS[name](args.against) if name in AGAINST else SECTIONS[name]()
