"""baselines/aime_nob.py: the episode's OT reward on hand-made cases, one seed's online loop, the command end to end."""
import dataclasses
import glob
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import checkpoint
import configs
from baselines import aime_nob, genrl
from tests.fixtures import kill_at_evaluation

SMOKE = configs.AIMENoBConfig(**configs.PRESETS["aime_nob"]["smoke"])
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_copy_of_a_demo_earns_the_most_and_is_matched_to_it():
    torch.manual_seed(0)
    demo_p = F.normalize(torch.randn(3, 12, 16, dtype=torch.float64), dim=-1)  # 3 demos of 12 frames
    cfg = configs.OTConfig()
    copy, best = aime_nob.episode_rewards(demo_p[1].numpy(), demo_p, cfg)
    assert best == 1 and copy.shape == (12,) and copy.dtype == np.float32
    assert -1e-3 < copy.sum() <= 0  # each frame transported onto itself: cost ~0
    others = [aime_nob.episode_rewards(F.normalize(torch.randn(12, 16), dim=-1).numpy(), demo_p, cfg)[0].sum() for _ in range(5)]
    assert max(others) < copy.sum() - 0.5
    # whole-episode OT matches the distribution of frames (ROT): the same frames in reverse order earn the same
    reverse, best = aime_nob.episode_rewards(demo_p[1].flip(0).numpy(), demo_p, cfg)
    assert best == 1 and np.isclose(reverse.sum(), copy.sum(), atol=1e-6)


def test_bad_budgets_name_the_flag():
    with pytest.raises(ValueError, match=r"--env-steps 1200 is not a multiple of --episode-steps 500"):
        configs.AIMENoBConfig(env_steps=1200)
    with pytest.raises(ValueError, match=r"--body-ratio 1: must be below 1"):
        configs.AIMENoBConfig(body_ratio=1.0)


def test_one_seed_interacts_for_its_budget_and_the_world_model_learns(smoke_run):
    cell = genrl.load_cell(smoke_run, "walker_walk", "side")
    start = {k: v.clone() for k, v in cell["ckpt"]["models"]["world_model"].items()}
    demo_p = torch.as_tensor(np.stack([d["p"] for d in cell["demos"]]))
    encoder = aime_nob.load_encoder("default")
    nc = dataclasses.replace(SMOKE, env_steps=30)
    actor, wm, log = aime_nob.train_seed(cell, nc, checkpoint.body_segments(cell["cfgs"]), encoder, demo_p, 0)
    wm = {k: v.clone() for k, v in wm.state_dict().items()}
    assert [e["episode"] for e in log] == [0, 1, 2]  # 30 agent steps = 3 episodes of 10
    assert log[0]["ot_sum"] == -nc.reward_sum  # ROT's scale: the first episode's labels sum to -10
    assert all(e["ot_sum"] < 0 and e["best_demo"] in (0, 1) for e in log)
    assert any(not torch.equal(v, start[k]) for k, v in wm.items())  # Eq. 2 went on
    assert all(torch.equal(v, cell["ckpt"]["models"]["world_model"][k]) for k, v in start.items())  # the checkpoint's copy untouched
    # every seed starts again from the phase-1 world model: the same seed run again gives the same world model
    _, again, _ = aime_nob.train_seed(cell, nc, checkpoint.body_segments(cell["cfgs"]), encoder, demo_p, 0)
    assert all(torch.equal(v, wm[k]) for k, v in again.state_dict().items())


def test_cell_end_to_end_and_resumable(smoke_run, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))  # other tests' rows of the shared run
    rows = aime_nob.run_cell(run, "stickman_stand", "side", SMOKE)
    assert [r["seed"] for r in rows] == [0, 1]
    keys = {"agent", "demo", "view", "task", "setting", "method", "seed", "score", "episode_scores", "time", "demo_returns", "config", "weights", "env_steps"}
    for r in rows:
        assert set(r) == keys and r["method"] == "AIME-NoB" and r["setting"] == "CE-SV" and r["task"] == "stand"
        assert r["env_steps"] == r["config"]["env_steps"] == SMOKE.env_steps and len(r["episode_scores"]) == 2 and np.isfinite(r["score"])
    path = os.path.join(run, "results.jsonl")
    assert [json.loads(line) for line in open(path)] == rows
    assert aime_nob.run_cell(run, "stickman_stand", "side", SMOKE) == []  # finished: nothing runs again
    assert [r["seed"] for r in aime_nob.run_cell(run, "stickman_stand", "side", dataclasses.replace(SMOKE, env_steps=10))] == [0, 1]
    assert len(open(path).readlines()) == 4


def test_command_line(smoke_run, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    command = [sys.executable, "baselines/aime_nob.py", "--preset", "smoke", "--seeds", "1", "--run", run, "--demo", "walker_run"]
    out = subprocess.run(command + ["--view", "diagonal"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "AIME-NoB walker imitating walker_run (diagonal view, SE-CV): normalised score" in out.stdout
    out = subprocess.run(command + ["--env-steps", "25"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.strip() == "error: --env-steps 25 is not a multiple of --episode-steps 10: the budget is whole episodes"


def test_budget_rows_and_a_killed_seed_going_on(smoke_run, tmp_path, monkeypatch):
    """--env-steps 30 --eval-at 10: the row at 10 is a 10-step run's; a seed killed after 20 goes on from its saved
    state (episodes, scale, world model) to the same row at 30 as a seed never killed."""
    runs = {}
    for name in ("curve", "ten", "killed"):
        runs[name] = str(tmp_path / name)
        shutil.copytree(smoke_run, runs[name], ignore=shutil.ignore_patterns("results.jsonl", "baselines"))
    cfg = dataclasses.replace(SMOKE, env_steps=30, eval_at="10,20", seeds=1)
    rows = aime_nob.run_cell(runs["curve"], "walker_stand", "side", cfg)
    assert [(r["env_steps"], r["config"]["env_steps"]) for r in rows] == [(10, 10), (20, 20), (30, 30)]
    alone = aime_nob.run_cell(runs["ten"], "walker_stand", "side", dataclasses.replace(cfg, env_steps=10, eval_at=""))[0]
    assert alone["config"] == rows[0]["config"] and alone["episode_scores"] == rows[0]["episode_scores"]
    kill_at_evaluation(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        aime_nob.run_cell(runs["killed"], "walker_stand", "side", cfg)
    episodes = []
    monkeypatch.setattr(aime_nob, "collect_episode", lambda *a, _c=aime_nob.collect_episode: episodes.append(1) or _c(*a))
    last = aime_nob.run_cell(runs["killed"], "walker_stand", "side", cfg)
    assert len(episodes) == 1 and [r["env_steps"] for r in last] == [30]  # the third episode only
    assert last[0]["episode_scores"] == rows[2]["episode_scores"]
    states = [torch.load(glob.glob(os.path.join(runs[n], "baselines", "*.pt"))[0], weights_only=True) for n in ("curve", "killed")]
    assert all(torch.equal(v, states[1]["world_model"][k]) for k, v in states[0]["world_model"].items())
    assert states[0]["log"] == states[1]["log"] and states[0]["done"] == 30
    with pytest.raises(ValueError, match=r"--eval-at 15: each budget must be between 0 and --env-steps 30, whole episodes of --episode-steps 10"):
        dataclasses.replace(cfg, eval_at="15")
