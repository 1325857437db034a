"""Speed figures for the README: python bench.py [--only render ...]. Each section measures in one run."""
import argparse
import time

import numpy as np

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


def bench_features():
    """The default video encoder against rendering (+ physics), one thread: features must not hold collection back."""
    import video_encoder

    encoder_fps, render_fps = video_encoder.bench()
    print(f"features       default encoder {encoder_fps:7.0f} frames/s | render + physics {render_fps:7.0f} frames/s | ratio {encoder_fps / render_fps:.1f}x")


def bench_collect(episodes=2):
    """D_body episodes per second on one core: simulate, render, features, compressed write (collect._worker)."""
    import tempfile

    import collect

    cfg = collect.CollectConfig(explore_episodes=episodes, task_episodes=1)
    jobs = collect.episode_jobs("walker", cfg, tempfile.mkdtemp())
    explore, task = [j for j in jobs if j[1]["kind"] == "explore"], [j for j in jobs if j[1]["kind"] == "walk"]
    for name, chosen in (("exploration", explore), ("expert snapshot", task)):
        start = time.perf_counter()
        for paths, job in chosen:
            collect._worker((paths, job, "default"))
        per = (time.perf_counter() - start) / len(chosen)
        print(f"collect        {name} episode ({job['steps']} steps) {per:5.1f} s | {3600 / per:5.0f} episodes/h per core")


def bench_phase1():
    """Updates/s of each phase-1 component at the cpu preset, one thread (train.py runs them in sequence)."""
    import torch

    import distance
    import goal_vae
    import policy
    import video_encoder
    import world_model

    torch.set_num_threads(1)
    total = 0.0
    for module in (world_model, goal_vae, distance, policy):
        kwargs = {"feat_dim": video_encoder.DEFAULT_DIM} if module is goal_vae else {}
        update, what = module.bench_update("cpu", **kwargs)
        seconds = timed(update, repeat=10, warmup=2)
        total += seconds
        print(f"phase 1        {what}: {1 / seconds:6.1f} updates/s ({1000 * seconds:.0f} ms)")
    print(f"phase 1        one full train.py update (all four): {1000 * total:.0f} ms, {1 / total:.1f} updates/s")


def bench_ot():
    """The OT reward (App. C): one call at imitate.py's cpu size and at a paper-like size, one thread."""
    import imitate
    import ot_reward

    cpu = imitate.ImitateConfig()
    for B, M in ((cpu.starts, envs.EPISODE_STEPS // cpu.demo_stride), (256, envs.EPISODE_STEPS)):
        r = ot_reward.bench(B=B, T=15, M=M, K=10, D=512, repeat=2)
        print(f"OT reward      B={B} trajectories x T=15 against K=10 demos of M={M} frames (D=512): {1000 * r['whole_demo_s']:.0f} ms (windowed: {1000 * r['window_s']:.0f} ms)")


SECTIONS = {"render": bench_render, "features": bench_features, "collect": bench_collect, "phase1": bench_phase1, "ot": bench_ot}

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    for name in parser.parse_args().only:
        SECTIONS[name]()
