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


SECTIONS = {"render": bench_render}

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    for name in parser.parse_args().only:
        SECTIONS[name]()
