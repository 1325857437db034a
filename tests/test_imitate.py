"""imitate.py: GIIL-ZS / GIIL-FT end to end (smoke), the stop-gradients of Eq. 5 vs Eq. 4, bad input, tables."""
import dataclasses
import json
import os
import shutil

import numpy as np
import pytest
import torch

import checkpoint
import evaluate
import imitate
import ot_reward
import presets
from conftest import probe_script

SMOKE = imitate.ImitateConfig(**presets.PRESETS["imitate"]["smoke"])


def test_zero_shot_and_finetune_end_to_end(smoke_run):
    rows = imitate.imitate(smoke_run, "stickman_run", "diagonal", True, SMOKE)
    zs = [r for r in rows if r["method"] == "GIIL-ZS"]
    ft = [r for r in rows if r["method"] == "GIIL-FT"]
    zs0 = [r for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    assert len(zs) == 2 and len(ft) == len(zs0) == SMOKE.seeds  # smoke: 2 demos per folder, 2 seeds
    assert all(r["setting"] == "CE-CV" and r["task"] == "run" and np.isfinite(r["score"]) for r in rows)
    assert all(r["goal_shift"] > 0 for r in ft)  # finetuning moved g
    assert os.path.getsize(os.path.join(smoke_run, "imitate", "stickman_run_diagonal_GIIL-FT_s0.mp4")) > 0
    logged = [json.loads(l) for l in open(os.path.join(smoke_run, "results.jsonl"))]
    assert logged[-len(rows):] == rows


def test_goal_gets_only_L_GI_and_policy_only_L_MG(smoke_run):
    """Eq. 5 moves g and never psi; Eq. 4 (joint finetuning) moves psi and never g."""
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    critic_ot, slow_ot = imitate.policy.make_critics(cfgs["ac"], feat_dim, 0)
    goal = torch.nn.Parameter(torch.randn(feat_dim))
    cfgs["ac"].bc = 1.0  # the cpu preset's behaviour-cloning term is part of L_MG too
    pool, bc = imitate.body_pool(models, cfgs, checkpoint.body_segments(cfgs), np.random.default_rng(0), "cpu", n=2)
    start = {k: v[:6] for k, v in pool.items()}
    demo_p = torch.nn.functional.normalize(torch.randn(2, 12, models["goal_vae"].feat_dim), dim=-1)
    gi, ot_loss, _ = imitate.goal_inference_loss(models, critic_ot, slow_ot, goal, start, demo_p, cfgs, ot_reward.OTConfig(iters=5))
    gi.backward()
    assert goal.grad is not None and goal.grad.abs().sum() > 0
    assert all(p.grad is None for name in ("actor", "world_model", "goal_vae") for p in models[name].parameters())
    a_loss, c_loss, _ = imitate.multi_goal_loss(models, start, goal, models["world_model"].feat(pool), bc, cfgs)
    goal.grad = None
    (a_loss + c_loss).backward()
    assert goal.grad is None
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in models["actor"].parameters())
    assert all(p.grad is None for p in models["world_model"].parameters())


def test_unknown_demo_lists_the_valid_names(smoke_run):
    with pytest.raises(ValueError, match=r"unknown demo 'stickman_fly': valid demos are walker_stand, .*, stickman_jump$"):
        imitate.imitate(smoke_run, "stickman_fly", "side", False, SMOKE)


def test_missing_demos_are_collected_first(smoke_run, smoke_data, tmp_path):
    """From a fresh clone's state (D_body only): imitate collects the demos it needs, both views of one body x task."""
    data = str(tmp_path / "data")
    shutil.copytree(os.path.join(smoke_data, "walker"), os.path.join(data, "walker"))
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "imitate"))
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    ckpt["config"]["train"].update(data=data, preset="smoke")
    torch.save(ckpt, os.path.join(run, "checkpoint.pt"))
    rows = imitate.imitate(run, "stickman_run", "side", True, SMOKE)
    assert [r["method"] for r in rows] == ["GIIL-ZS"] * 2 + ["GIIL-ZS (demo 0)", "GIIL-FT"] * SMOKE.seeds
    assert sorted(os.listdir(os.path.join(data, "demos"))) == ["stickman_run_diagonal", "stickman_run_side"]
    assert sorted(os.listdir(os.path.join(data, "demos", "stickman_run_side"))) == ["00.npz", "01.npz"]


def test_default_run_follows_preset_and_agent(tmp_path):
    """Without --run, imitate reads the run train.py writes for that --preset and agent body."""
    import subprocess
    import sys

    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "imitate.py")
    for flags, run in (([], "runs/walker_state_smoke_s0"), (["--env", "stickman"], "runs/stickman_state_smoke_s0")):
        out = subprocess.run([sys.executable, script, "--demo", "walker_run", "--preset", "smoke"] + flags, cwd=tmp_path, capture_output=True, text=True)
        assert out.returncode == 1 and out.stderr.startswith(f"error: no checkpoint at {run}/checkpoint.pt"), out.stderr[-2000:]
    assert checkpoint.default_run_dir("walker", "cpu") == os.path.join("runs", "walker_state_cpu_s0")


def test_no_checkpoint_names_the_train_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="python train.py"):
        imitate.imitate(str(tmp_path), "walker_run", "side", False, SMOKE)


def test_demo_features_from_another_encoder_or_nan_are_errors(smoke_run, smoke_data, tmp_path):
    data = str(tmp_path / "data")
    shutil.copytree(smoke_data, data)
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    ckpt["config"]["train"]["data"] = data
    torch.save(ckpt, os.path.join(run, "checkpoint.pt"))
    path = os.path.join(data, "demos", "walker_walk_side", "01.npz")
    episode = dict(np.load(path))
    np.savez(path, **dict(episode, encoder="torchscript:other.pt:0123456789ab"))
    with pytest.raises(ValueError, match="other.pt"):
        imitate.imitate(run, "walker_walk", "side", False, SMOKE)
    episode["p"][3] = np.nan
    np.savez(path, **episode)
    with pytest.raises(ValueError, match=r"01.npz: key 'p' must be a finite"):
        imitate.imitate(run, "walker_walk", "side", False, SMOKE)


def test_command_line(smoke_run, tmp_path):
    """`python imitate.py --demo walker_stand --finetune --preset smoke --run ...` prints both scores."""
    import subprocess
    import sys

    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    cwd = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run([sys.executable, "imitate.py", "--demo", "walker_stand", "--finetune", "--preset", "smoke", "--run", run],
                         cwd=cwd, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "GIIL-ZS walker imitating walker_stand (side view, SE-SV): normalised score" in out.stdout
    assert "GIIL-FT walker imitating walker_stand" in out.stdout


def test_every_finetuning_seed_starts_from_the_pretrained_policy(smoke_run, tmp_path, monkeypatch):
    """With psi finetuned too, each seed's finetuning and its GIIL-ZS (demo 0) evaluation see psi*, not the policy
    that the previous seed finetuned."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    seen, evaluated, finetune, run_episodes = [], [], imitate.finetune_goal, imitate.evaluate.run_episodes
    actor_sum = lambda models: sum(p.sum().item() for p in models["actor"].parameters())

    def recording(models, *args):
        seen.append(actor_sum(models))
        return finetune(models, *args)

    def recording_eval(env_list, models, *args, **kwargs):
        evaluated.append(actor_sum(models))
        return run_episodes(env_list, models, *args, **kwargs)

    monkeypatch.setattr(imitate, "finetune_goal", recording)
    monkeypatch.setattr(imitate.evaluate, "run_episodes", recording_eval)
    imitate.imitate(run, "walker_run", "side", True, dataclasses.replace(SMOKE, finetune_policy=1), zero_shot=False)
    pretrained = actor_sum(checkpoint.load_run(run)[1])
    assert len(seen) == SMOKE.seeds and all(s == pytest.approx(pretrained, abs=1e-6) for s in seen)
    zs0 = evaluated[0::2]  # GIIL-ZS (demo 0), GIIL-FT, GIIL-ZS (demo 0), ...
    assert len(zs0) == SMOKE.seeds and all(s == pytest.approx(pretrained, abs=1e-6) for s in zs0)
    assert evaluated[1] != pytest.approx(pretrained, abs=1e-6)  # GIIL-FT's evaluation: psi moved


def test_finetuning_continues_phase_1_optimisers_without_changing_them(smoke_run):
    """L_MG's Adam starts from the checkpoint's states (deep copies: every seed starts from the same ones)."""
    cfgs, models, ckpt = checkpoint.load_run(smoke_run)
    states = ckpt["optims"]
    before = [t.clone() for s in states["actor"]["state"].values() for t in s.values()]
    assert before, "the smoke checkpoint must hold Adam moments for the actor"
    demo_p = [np.random.default_rng(k).standard_normal((12, models["goal_vae"].feat_dim)).astype(np.float32) for k in range(2)]
    p0 = torch.nn.functional.normalize(torch.as_tensor(demo_p[0][-1]), dim=-1)
    imitate.finetune_goal(models, cfgs, dataclasses.replace(SMOKE, finetune_policy=1), ot_reward.OTConfig(iters=5), p0, demo_p, 0, "cpu", states)
    after = [t for s in states["actor"]["state"].values() for t in s.values()]
    assert all(torch.equal(a, b) for a, b in zip(before, after))


def test_goal_gradient_flows_through_v_ot_only(smoke_run):
    """Eq. 5 differentiates the values alone: with V_ot constant g gets no gradient (not through the OT rewards), and
    with a V_ot that reads the state it does."""
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    pool, _ = imitate.body_pool(models, cfgs, checkpoint.body_segments(cfgs), np.random.default_rng(0), "cpu", n=2)
    start = {k: v[:6] for k, v in pool.items()}
    demo_p = torch.nn.functional.normalize(torch.randn(2, 12, models["goal_vae"].feat_dim), dim=-1)
    grads = []
    for constant in (True, False):
        critic_ot, slow_ot = imitate.policy.make_critics(cfgs["ac"], feat_dim, 0)
        if constant:
            for p in slow_ot.parameters():
                p.data.zero_()  # V_ot(s) = 0 everywhere
        goal = torch.nn.Parameter(torch.randn(feat_dim))
        torch.manual_seed(0)
        gi = imitate.goal_inference_loss(models, critic_ot, slow_ot, goal, start, demo_p, cfgs, ot_reward.OTConfig(iters=5))[0]
        gi.backward()
        grads.append(goal.grad.abs().sum().item())
    assert grads[0] == 0 and grads[1] > 0


def test_zero_shot_demo_0_is_finetuning_that_never_moves_the_goal(smoke_run, tmp_path):
    """GIIL-ZS (demo 0) is evaluated with GIIL-FT's seeds: when the goal does not move and psi is frozen, GIIL-FT's
    episodes are exactly GIIL-ZS (demo 0)'s."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    ic = dataclasses.replace(SMOKE, eval_episodes=2, goal_lr=1e-12)  # each Adam update moves g by ~1e-12: nothing
    rows = imitate.imitate(run, "walker_walk", "side", True, ic, zero_shot=False)
    zs0 = [r["episode_scores"] for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    ft = [r["episode_scores"] for r in rows if r["method"] == "GIIL-FT"]
    assert len(zs0) == SMOKE.seeds and np.allclose(zs0, ft, atol=1e-6)
    assert all(r["goal_shift"] < 1e-6 for r in rows if r["method"] == "GIIL-FT")  # ||g - g0||, logged with each GIIL-FT row


def test_ot_probe_scores_goals_alike_for_alike_goals(smoke_run):
    """probes/ot_probe.py: J(g) is a mean OT reward (<= 0), the same for the same goal (every goal meets the same starts and
    imagination noise), and the script prints one line per cell and the summary."""
    import subprocess
    import sys

    probe = probe_script("ot_probe")
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    demo_p = torch.nn.functional.normalize(torch.randn(2, 20, models["goal_vae"].feat_dim), dim=-1)
    g = torch.randn(feat_dim)
    J = probe.imagined_ot(models, cfgs, torch.stack([g, torch.randn(feat_dim), g]), demo_p, starts=6)
    assert J.shape == (3,) and (J <= 0).all() and J[0] == J[2] and J[0] != J[1]
    spearman = evaluate.spearman  # the probes' rank correlation
    assert spearman([1, 2, 3], [10, 20, 30]) == pytest.approx(1) and spearman([1, 2, 3], [3, 2, 1]) == pytest.approx(-1)
    out = subprocess.run([sys.executable, probe.__file__, smoke_run, "--settings", "SE-SV", "--starts", "4"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    assert [l.split(" |")[0] for l in lines[1:-1]] == [f"SE-SV {t}" for t in ("stand", "walk", "run", "jump")]
    assert lines[-1].startswith("own task's goals ranked first in ") and " of 4 cells" in lines[-1]


def test_parallel_shards_collect_demos_one_at_a_time(tmp_path, monkeypatch):
    """Two table shards needing the same demos: the second waits for the first's collection (no clashing writes)."""
    import threading
    import time

    import collect

    active, overlaps = [], []

    def slow_collect(*args):
        active.append(1)
        overlaps.append(len(active))
        time.sleep(0.3)
        active.pop()

    monkeypatch.setattr(collect, "collect_demos", slow_collect)
    cfgs = {"train": checkpoint.TrainConfig(data=str(tmp_path))}
    shards = [threading.Thread(target=checkpoint.demo_folder, args=(cfgs, "walker_run", "side")) for _ in range(2)]
    for shard in shards:
        shard.start()
    for shard in shards:
        shard.join()
    assert overlaps == [1, 1]
