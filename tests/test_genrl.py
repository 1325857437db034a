"""baselines/genrl.py: the sequence-aligned similarity reward on hand-made cases, a frozen world model, the command end to end."""
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
import configs
from baselines import genrl
from tests.fixtures import kill_at_evaluation

SMOKE = configs.GenRLConfig(**configs.PRESETS["genrl"]["smoke"])
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


def test_offsets_are_those_of_the_windows_written_out():
    """t* = argmax_t mean_j sim(s_{t+1+j}, s*_j), each window compared step by step."""
    torch.manual_seed(2)
    agent, target = torch.randn(64, 15, 32), torch.randn(15, 32)
    _, offset = genrl.aligned_reward(agent, target, 8)
    means = torch.stack([torch.stack([genrl.similarity(agent[:, t + j], target[j]) for j in range(8)]).mean(0) for t in range(8)], -1)
    assert torch.equal(offset, means.argmax(-1)) and len(set(offset.tolist())) > 3


def test_reward_is_differentiable_in_the_imagined_states():
    target = torch.randn(6, 5)
    agent = torch.randn(2, 6, 5, requires_grad=True)
    reward, _ = genrl.aligned_reward(agent, target, 3)
    reward.sum().backward()
    assert agent.grad.abs().sum() > 0


def test_bad_windows_name_the_flag():
    with pytest.raises(ValueError, match=r"--align-window 20 is longer than --target-len 15"):
        configs.GenRLConfig(align_window=20)
    with pytest.raises(ValueError, match=r"--align-window 8 is longer than the run's imagination horizon 5"):
        genrl.aligned_reward(torch.randn(1, 5, 3), torch.randn(10, 3), 8)
    with pytest.raises(ValueError, match=r"--seeds 0: must be >= 1"):
        configs.GenRLConfig(seeds=0)


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
    keys = {"agent", "demo", "view", "task", "setting", "method", "seed", "score", "episode_scores", "time", "demo_returns", "config", "weights"}
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
    command = [sys.executable, "baselines/genrl.py", "--preset", "smoke", "--seeds", "1", "--run", run]
    out = subprocess.run(command + ["--demo", "walker_stand"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "GenRL walker imitating walker_stand (side view, SE-SV): normalised score" in out.stdout and "over 1 seeds" in out.stdout
    out = subprocess.run(command + ["--demo", "walker_fly"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.strip().startswith("error: unknown demo 'walker_fly'") and "Traceback" not in out.stderr


def _copy(smoke_run, tmp_path, name):
    run = str(tmp_path / name)
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "baselines"))
    return run


def _state(run, cfg, seed=0):
    return torch.load(genrl.state_path(genrl.load_cell(run, "walker_walk", "side"), "GenRL", cfg, seed), weights_only=True)


def test_a_budget_row_is_the_row_of_a_run_of_that_budget(smoke_run, tmp_path):
    """--steps 4 --eval-at 2: the row at 2 equals a 2-update run's, and the training after the evaluation goes on exactly
    as a 4-update run without one (the evaluation seeds torch; its random state is restored)."""
    curve, two, four = (_copy(smoke_run, tmp_path, n) for n in ("curve", "two", "four"))
    cfg = dataclasses.replace(SMOKE, steps=4, eval_at="2", seeds=1)
    rows = genrl.run_cell(curve, "walker_walk", "side", cfg)
    assert [r["config"]["steps"] for r in rows] == [2, 4] and all("eval_at" not in r["config"] for r in rows)
    alone = genrl.run_cell(two, "walker_walk", "side", dataclasses.replace(cfg, steps=2, eval_at=""))[0]
    assert alone["config"] == rows[0]["config"] and alone["episode_scores"] == rows[0]["episode_scores"]
    genrl.run_cell(four, "walker_walk", "side", dataclasses.replace(cfg, eval_at=""))
    a, b = _state(curve, cfg)["actor"], _state(four, cfg)["actor"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    # the 2-update run's saved state is where a 4-update run goes on from: its row at 4 equals the curve's
    more = genrl.run_cell(two, "walker_walk", "side", dataclasses.replace(cfg, eval_at=""))
    assert [r["config"]["steps"] for r in more] == [4] and more[0]["episode_scores"] == rows[1]["episode_scores"]
    c = _state(two, cfg)["actor"]
    assert all(torch.equal(a[k], c[k]) for k in a)


def test_a_seed_killed_after_a_budget_goes_on_from_it(smoke_run, tmp_path, monkeypatch):
    run, whole = _copy(smoke_run, tmp_path, "run"), _copy(smoke_run, tmp_path, "whole")
    cfg = dataclasses.replace(SMOKE, steps=4, eval_at="1,2", seeds=1)
    evaluate_actor = kill_at_evaluation(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        genrl.run_cell(run, "walker_walk", "side", cfg)
    assert _state(run, cfg)["done"] == 2
    steps = []
    monkeypatch.setattr(genrl.policy, "rollout", lambda *a, _r=genrl.policy.rollout: steps.append(1) or _r(*a))
    rows = genrl.run_cell(run, "walker_walk", "side", cfg)
    assert [r["config"]["steps"] for r in rows] == [4] and len(steps) == 2  # updates 3 and 4 only
    monkeypatch.setattr(genrl, "evaluate_actor", evaluate_actor)
    assert genrl.run_cell(whole, "walker_walk", "side", cfg)[-1]["episode_scores"] == rows[0]["episode_scores"]
    a, b = _state(run, cfg)["actor"], _state(whole, cfg)["actor"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    written = [json.loads(line)["config"]["steps"] for line in open(os.path.join(run, "results.jsonl"))]
    assert written == [1, 2, 4]  # nothing twice


def test_bad_budgets_name_the_flag_and_the_fix():
    with pytest.raises(ValueError, match=r"--eval-at 1000: each budget must be between 0 and --steps 1000"):
        configs.GenRLConfig(eval_at="500,1000")
    with pytest.raises(ValueError, match=r"--eval-at 'a,b': pass budgets as comma-separated integers, e.g. 1000,2000"):
        configs.GenRLConfig(eval_at="a,b")
    assert configs.budgets(configs.GenRLConfig(steps=4000, eval_at="2000, 1000")) == [1000, 2000, 4000]


def test_settings_run_each_of_their_cells_once(smoke_run, tmp_path):
    run = _copy(smoke_run, tmp_path, "run")
    command = [sys.executable, "baselines/genrl.py", "--preset", "smoke", "--seeds", "1", "--steps", "1", "--run", run, "--settings", "SE-SV"]
    out = [subprocess.Popen(command + ["--shard", f"{i}/2"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    for p in out:
        assert p.wait() == 0, p.stderr.read()[-2000:]
    rows = [json.loads(line) for line in open(os.path.join(run, "results.jsonl"))]
    assert sorted(r["demo"] for r in rows) == sorted(f"walker_{t}" for t in genrl.envs.TASKS) and {r["view"] for r in rows} == {"side"}
    bad = subprocess.run(command + ["--demo", "walker_run"], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "pass --demo NAME (one cell) or --settings SE-SV,... (their cells), not both" in bad.stderr
    bad = subprocess.run(command[:-2] + ["--settings", "SE-XX"], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 1 and bad.stderr.strip() == "error: unknown setting(s) SE-XX: choose from SE-SV, SE-CV, CE-SV, CE-CV"
