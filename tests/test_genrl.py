"""genrl.py: the sequence-aligned similarity reward on hand-made cases, a frozen world model, the command end to end."""
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
import genrl
import presets

SMOKE = genrl.GenRLConfig(**presets.PRESETS["genrl"]["smoke"])
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_copy_of_the_target_earns_the_most():
    torch.manual_seed(0)
    target = torch.randn(6, 5)
    reward, offset = genrl.aligned_reward(target[None], target, 3)
    assert offset.tolist() == [0] and torch.allclose(reward, torch.ones(1, 6))
    others, _ = genrl.aligned_reward(torch.randn(50, 6, 5), target, 3)
    assert others.max() < 1 and others.mean() < 0.5
    # max-cosine, not cosine: a copy twice as long points the same way but earns 1/2
    scaled, _ = genrl.aligned_reward(2 * target[None], target, 3)
    assert torch.allclose(scaled, torch.full((1, 6), 0.5))


def test_time_shifted_copy_is_matched_by_the_alignment():
    """The imagined trajectory reaches the target's start 3 steps in: offset 3, then every step matches its target state."""
    torch.manual_seed(1)
    target = torch.randn(10, 8)
    late = target[(torch.arange(10) - 3).clamp(min=0)][None]  # s_1..s_3 = s*_0, then s_{j} = s*_{j-1-3}
    reward, offset = genrl.aligned_reward(late, target, 4)
    assert offset.tolist() == [3] and torch.allclose(reward, torch.ones(1, 10))
    assert genrl.similarity(late[0], target).mean() < 0.9  # compared step by step without the alignment it would not match
    # two trajectories, two offsets: the alignment is per trajectory
    both, offsets = genrl.aligned_reward(torch.cat([target[None], late]), target, 4)
    assert offsets.tolist() == [0, 3] and torch.allclose(both, torch.ones(2, 10))


def test_reward_is_differentiable_in_the_imagined_states():
    target = torch.randn(6, 5)
    agent = torch.randn(2, 6, 5, requires_grad=True)
    reward, _ = genrl.aligned_reward(agent, target, 3)
    reward.sum().backward()
    assert agent.grad.abs().sum() > 0


def test_bad_windows_name_the_flag():
    with pytest.raises(ValueError, match=r"--align-window 20 is longer than --target-len 15"):
        genrl.GenRLConfig(align_window=20)
    with pytest.raises(ValueError, match=r"--align-window 8 is longer than the run's imagination horizon 5"):
        genrl.aligned_reward(torch.randn(1, 5, 3), torch.randn(10, 3), 8)
    with pytest.raises(ValueError, match=r"--seeds 0: must be >= 1"):
        genrl.GenRLConfig(seeds=0)


def test_world_model_stays_frozen_and_the_actor_learns(smoke_run):
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    before = {k: v.clone() for k, v in models["world_model"].state_dict().items()}
    target = genrl.target_states(models, torch.nn.functional.normalize(torch.randn(12, models["goal_vae"].feat_dim), dim=-1), SMOKE.target_len)
    assert target.shape == (SMOKE.target_len, cfgs["wm"].units)  # the state decoder's first layer
    actor = genrl.train_policy(models, cfgs, SMOKE, target, checkpoint.body_segments(cfgs), 0, "cpu")
    torch.manual_seed(0)
    fresh = genrl.policy.Actor(cfgs["ac"], models["world_model"].feat_dim, 1, models["world_model"].action_dim)  # train_policy's initial actor
    assert any(not torch.equal(a, b) for a, b in zip(actor.state_dict().values(), fresh.state_dict().values()))
    assert all(torch.equal(v, before[k]) for k, v in models["world_model"].state_dict().items())


def test_target_longer_than_the_demo_is_an_error(smoke_run):
    _, models, _ = checkpoint.load_run(smoke_run)
    with pytest.raises(ValueError, match=r"the first demo has 4 features, fewer than --target-len 5"):
        genrl.target_states(models, torch.randn(4, models["goal_vae"].feat_dim), 5)


def test_cell_end_to_end_and_resumable(smoke_run, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))  # other tests' rows of the shared run
    rows = genrl.run_cell(run, "stickman_run", "diagonal", SMOKE)
    assert [r["seed"] for r in rows] == [0, 1]
    keys = {"agent", "demo", "view", "task", "setting", "method", "seed", "score", "episode_scores", "time", "demo_returns", "config"}
    for r in rows:
        assert set(r) == keys and r["method"] == "GenRL" and r["setting"] == "CE-CV" and r["task"] == "run" and r["agent"] == "walker"
        assert len(r["episode_scores"]) == SMOKE.eval_episodes == 2 and np.isfinite(r["score"]) and r["score"] == np.mean(r["episode_scores"])
        assert r["config"]["steps"] == SMOKE.steps and "seeds" not in r["config"] and len(r["demo_returns"]) == 2
    path = os.path.join(run, "results.jsonl")
    assert [json.loads(line) for line in open(path)] == rows
    assert genrl.run_cell(run, "stickman_run", "diagonal", SMOKE) == []  # finished: nothing runs again
    assert [r["seed"] for r in genrl.run_cell(run, "stickman_run", "diagonal", dataclasses.replace(SMOKE, seeds=3))] == [2]
    assert [r["seed"] for r in genrl.run_cell(run, "stickman_run", "diagonal", dataclasses.replace(SMOKE, steps=2))] == [0, 1]  # other settings
    assert len(open(path).readlines()) == 5


def test_command_line(smoke_run, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    command = [sys.executable, "genrl.py", "--preset", "smoke", "--seeds", "1", "--run", run]
    out = subprocess.run(command + ["--demo", "walker_stand"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "GenRL walker imitating walker_stand (side view, SE-SV): normalised score" in out.stdout and "over 1 seeds" in out.stdout
    out = subprocess.run(command + ["--demo", "walker_fly"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.strip().startswith("error: unknown demo 'walker_fly'") and "Traceback" not in out.stderr
