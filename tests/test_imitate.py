"""goal_inference.py and imitate.py: GIIL-ZS / GIIL-FT end to end (smoke), Eq. 5's gradient (g only, through V_ot), bad input."""
import dataclasses
import json
import os
import shutil

import numpy as np
import pytest
import torch

import checkpoint
import configs
import goal_inference
import runner

SMOKE = configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"])


def test_zero_shot_and_finetune_end_to_end(smoke_run):
    rows = runner.imitate(smoke_run, "stickman_run", "diagonal", SMOKE, ["GIIL-FT"])
    zs = [r for r in rows if r["method"] == "GIIL-ZS"]
    ft = [r for r in rows if r["method"] == "GIIL-FT"]
    zs0 = [r for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    assert len(zs) == 2 and len(ft) == len(zs0) == SMOKE.seeds  # smoke: 2 demos per folder, 2 seeds
    assert all(r["setting"] == "CE-CV" and r["task"] == "run" and np.isfinite(r["score"]) for r in rows)
    assert all(r["goal_shift"] > 0 for r in ft)  # finetuning moved g
    videos = sorted(n for n in os.listdir(os.path.join(smoke_run, "imitate")) if n.startswith("stickman_run_diagonal"))
    assert videos == sorted(r["video"] for r in rows if "video" in r)  # ZS (demo 0)'s is ZS's demo 0
    assert [v[:-len("_01234567.mp4")] for v in videos] == ["stickman_run_diagonal_GIIL-FT_s0", "stickman_run_diagonal_GIIL-ZS_s0"]
    assert os.path.getsize(os.path.join(smoke_run, "imitate", videos[0])) > 0
    filmed = [r for r in rows if "video_episode" in r]  # seed 0 of GIIL-ZS's first demo and of GIIL-FT: the median episode
    assert len(filmed) == 2 and all(r["video_episode"] == np.argsort(r["episode_scores"])[len(r["episode_scores"]) // 2] for r in filmed)
    logged = [json.loads(l) for l in open(os.path.join(smoke_run, "results.jsonl"))]
    assert logged[-len(rows):] == rows


def posterior_starts(models, cfgs, n=2):
    """Imagination starts: the world model's posterior states of n D_body segments, flattened."""
    batch = checkpoint.body_segments(cfgs).sample(n, np.random.default_rng(0), "cpu")
    with torch.no_grad():
        post, _ = models["world_model"].observe(batch[cfgs["wm"].obs], batch["action"], batch["is_first"])
    return {k: v.flatten(0, 1)[:6] for k, v in post.items()}


def test_goal_gets_L_GI_and_psi_nothing(smoke_run):
    """Eq. 5 moves g and never psi, the world model or the goal decoder."""
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    critic_ot, slow_ot = goal_inference.policy.make_critics(cfgs["ac"], feat_dim, 0)
    goal = torch.nn.Parameter(torch.randn(feat_dim))
    demo_p = torch.nn.functional.normalize(torch.randn(2, 12, models["goal_vae"].feat_dim), dim=-1)
    gi, ot_loss, _ = goal_inference.goal_inference_loss(models, critic_ot, slow_ot, goal, posterior_starts(models, cfgs), demo_p, cfgs,
                                                 configs.OTConfig(iters=5))
    gi.backward()
    assert goal.grad is not None and goal.grad.abs().sum() > 0
    assert all(p.grad is None for name in ("actor", "critic", "world_model", "goal_vae") for p in models[name].parameters())


def test_a_new_goal_search_is_one_function_and_one_entry(smoke_run, tmp_path, monkeypatch):
    """A search registered in SEARCHES runs beside GIIL-ZS (demo 0) with its own seeds, its rows carry its config, the
    same call again finds them finished, and the tables show its column paired with GIIL-ZS (demo 0)."""
    import tables

    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    last_demo = lambda cell, seed: (cell.goals[-1], len(cell.goals) - 1, {"picked": seed})
    entry = goal_inference.GoalSearch(last_demo, lambda ic, oc: 2, lambda ic, oc: {"eval_steps": ic.eval_steps, "last": True}, "last")
    monkeypatch.setitem(goal_inference.SEARCHES, "last demo", entry)
    monkeypatch.setattr(goal_inference, "METHODS", goal_inference.METHODS + ("last demo",))
    rows = runner.imitate(run, "walker_walk", "side", SMOKE, ["last demo"], zero_shot=False)
    assert [(r["method"], r["seed"]) for r in rows] == [("GIIL-ZS (demo 0)", 0), ("last demo", 0), ("GIIL-ZS (demo 0)", 1), ("last demo", 1)]
    assert rows[1]["config"] == {"eval_steps": SMOKE.eval_steps, "last": True} and rows[3]["picked"] == 1
    assert runner.imitate(run, "walker_walk", "side", SMOKE, ["last demo"], zero_shot=False) == []
    assert "last demo (ours)" in tables.markdown_tables("walker", rows) and "last demo - ZS (demo 0), paired" in tables.markdown_tables("walker", rows)


def test_unknown_demo_lists_the_valid_names(smoke_run):
    with pytest.raises(ValueError, match=r"unknown demo 'stickman_fly': valid demos are walker_stand, .*, stickman_jump$"):
        runner.imitate(smoke_run, "stickman_fly", "side", SMOKE)


def test_missing_demos_are_collected_first(smoke_run, smoke_data, tmp_path):
    """From a fresh clone's state (D_body only): imitate collects the demos it needs, both views of one body x task."""
    data = str(tmp_path / "data")
    shutil.copytree(os.path.join(smoke_data, "walker"), os.path.join(data, "walker"))
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "imitate"))
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    ckpt["config"]["train"].update(data=data, preset="smoke")
    torch.save(ckpt, os.path.join(run, "checkpoint.pt"))
    rows = runner.imitate(run, "stickman_run", "side", SMOKE, ["GIIL-FT"])
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
        runner.imitate(str(tmp_path), "walker_run", "side", SMOKE)


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
        runner.imitate(run, "walker_walk", "side", SMOKE)
    episode["p"][3] = np.nan
    np.savez(path, **episode)
    with pytest.raises(ValueError, match=r"01.npz: key 'p' must be a finite"):
        runner.imitate(run, "walker_walk", "side", SMOKE)


def test_command_line(smoke_run, tmp_path):
    """`python imitate.py --demo walker_stand --finetune --preset smoke --run ...` prints both scores."""
    import subprocess
    import sys

    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))  # whatever other tests ran on the shared run
    cwd = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run([sys.executable, "imitate.py", "--demo", "walker_stand", "--finetune", "--preset", "smoke", "--run", run],
                         cwd=cwd, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "GIIL-ZS walker imitating walker_stand (side view, SE-SV): normalised score" in out.stdout
    assert "GIIL-FT walker imitating walker_stand" in out.stdout


def test_goal_searches_leave_the_policy_as_pretrained(smoke_run, tmp_path, monkeypatch):
    """psi stays psi*: after GIIL-FT's seeds every weight of the agent is the checkpoint's."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    before = {k: {n: t.clone() for n, t in m.state_dict().items()} for k, m in checkpoint.load_run(run)[1].items()}
    loaded, load_run = [], checkpoint.load_run
    monkeypatch.setattr(checkpoint, "load_run", lambda *args: loaded.append(load_run(*args)) or loaded[-1])
    runner.imitate(run, "walker_run", "side", SMOKE, ["GIIL-FT"], zero_shot=False)
    assert all(torch.equal(before[k][n], t) for k, m in loaded[0][1].items() for n, t in m.state_dict().items())


def test_goal_gradient_flows_through_v_ot_only(smoke_run):
    """Eq. 5 differentiates the values alone: with V_ot constant g gets no gradient (not through the OT rewards), and
    with a V_ot that reads the state it does."""
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    start = posterior_starts(models, cfgs)
    demo_p = torch.nn.functional.normalize(torch.randn(2, 12, models["goal_vae"].feat_dim), dim=-1)
    grads = []
    for constant in (True, False):
        critic_ot, slow_ot = goal_inference.policy.make_critics(cfgs["ac"], feat_dim, 0)
        if constant:
            for p in slow_ot.parameters():
                p.data.zero_()  # V_ot(s) = 0 everywhere
        goal = torch.nn.Parameter(torch.randn(feat_dim))
        torch.manual_seed(0)
        gi = goal_inference.goal_inference_loss(models, critic_ot, slow_ot, goal, start, demo_p, cfgs, configs.OTConfig(iters=5))[0]
        gi.backward()
        grads.append(goal.grad.abs().sum().item())
    assert grads[0] == 0 and grads[1] > 0


def test_zero_shot_demo_0_is_finetuning_that_never_moves_the_goal(smoke_run, tmp_path):
    """GIIL-ZS (demo 0) is evaluated with GIIL-FT's seeds: when the goal does not move and psi is frozen, GIIL-FT's
    episodes are exactly GIIL-ZS (demo 0)'s."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    ic = dataclasses.replace(SMOKE, eval_episodes=2, goal_lr=1e-12)  # each Adam update moves g by ~1e-12: nothing
    rows = runner.imitate(run, "walker_walk", "side", ic, ["GIIL-FT"], zero_shot=False)
    zs0 = [r["episode_scores"] for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    ft = [r["episode_scores"] for r in rows if r["method"] == "GIIL-FT"]
    assert len(zs0) == SMOKE.seeds and np.allclose(zs0, ft, atol=1e-6)
    assert all(r["goal_shift"] < 1e-6 for r in rows if r["method"] == "GIIL-FT")  # ||g - g0||, logged with each GIIL-FT row


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
    cfgs = {"train": configs.TrainConfig(data=str(tmp_path))}
    os.makedirs(tmp_path / "demos")  # a data folder of ours (checkpoint.demo_folder follows no other)
    shards = [threading.Thread(target=checkpoint.demo_folder, args=(cfgs, "walker_run", "side")) for _ in range(2)]
    for shard in shards:
        shard.start()
    for shard in shards:
        shard.join()
    assert overlaps == [1, 1]


def test_retrieve_takes_the_goal_of_the_body_episode_closest_to_the_demos():
    """GIIL-retrieve on a toy D_body of 4 episodes, one of them a noisy copy of a demo: with a zero-shot goal outside
    the support of D_body's final goals, the goal of that episode's last frame is returned, whatever the order; the goal
    encoder is a stub (g = 2 p)."""
    rng = np.random.default_rng(0)
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)
    demos = [{"p": unit(rng.normal(size=(41, 8))).astype(np.float32)} for _ in range(2)]
    body = unit(rng.normal(size=(4, 41, 8))).astype(np.float32)
    body[2] = unit(demos[1]["p"] + 0.1 * rng.normal(size=(41, 8))).astype(np.float32)
    stride = goal_inference.RETRIEVE_STRIDE
    names = [f"e{i}.npz" for i in range(4)]
    vae = type("Stub", (), {"goal": staticmethod(lambda p: 2 * p)})()
    far = torch.full((8,), 10.0)  # beyond every final goal (norm 2)
    cell = goal_inference.Cell({"goal_vae": vae}, None, SMOKE, None, configs.OTConfig(), "run", demos, [far], "cpu",
                               lambda: (names, body[:, ::stride], body[:, -1]))
    goal, k, extra = goal_inference.giil_retrieve(cell, seed=0)
    assert extra["retrieved"] == "e2.npz" and torch.allclose(goal, 2 * torch.as_tensor(body[2, -1]))
    order = [3, 2, 0, 1]
    cell = dataclasses.replace(cell, body=lambda: ([names[i] for i in order], body[order, ::stride], body[order, -1]))
    assert goal_inference.giil_retrieve(cell, seed=1)[2]["retrieved"] == "e2.npz"


def test_retrieve_keeps_a_zero_shot_goal_the_body_holds():
    """The acceptance test: a zero-shot goal next to one of D_body's final goals is kept (nothing retrieved); the
    support's radius is the largest distance of a final goal to its nearest other one (here 3: points 0, 1, 4)."""
    final = torch.tensor([[0.0], [1.0], [4.0]])
    assert goal_inference.support(torch.tensor([4.5]), final) == (0.5, 3.0)
    assert goal_inference.support(torch.tensor([-3.5]), final) == (3.5, 3.0)
    body = np.zeros((3, 11, 1), np.float32)
    body[:, -1, 0] = [0.0, 0.5, 2.0]  # the stub encoder doubles them: the final goals of the toy above
    vae = type("Stub", (), {"goal": staticmethod(lambda p: 2 * p)})()
    start = torch.tensor([3.9])
    cell = goal_inference.Cell({"goal_vae": vae}, None, SMOKE, None, configs.OTConfig(), "run", [], [start], "cpu",
                               lambda: (["a", "b", "c"], body, body[:, -1]))
    goal, _, extra = goal_inference.giil_retrieve(cell, seed=0)
    assert goal is start and extra == {"retrieved": None, "support_distance": 0.1, "support_radius": 3.0}


def test_retrieve_end_to_end_names_a_d_body_episode(smoke_run, tmp_path):
    run = str(tmp_path / "run")  # a copy: the shared smoke run's rows stay as the other tests expect them
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "imitate"))
    rows = runner.imitate(run, "stickman_walk", "side", SMOKE, ["GIIL-retrieve"], zero_shot=False)
    found = [r for r in rows if r["method"] == "GIIL-retrieve"]
    cfgs = checkpoint.load_run(run)[0]
    assert len(found) == SMOKE.seeds and len({r["retrieved"] for r in found}) == 1  # one goal, every seed's starts
    retrieved = found[0]["retrieved"]  # None where demo 0's goal lies inside D_body's final goals
    assert retrieved is None or os.path.exists(os.path.join(cfgs["train"].data, "walker", retrieved))
    assert found[0]["support_distance"] >= 0 and (retrieved is None) == (found[0]["support_distance"] <= found[0]["support_radius"])
    assert found[0]["config"] == {"eval_episodes": SMOKE.eval_episodes, "eval_steps": SMOKE.eval_steps, "preset": SMOKE.preset,
                                  "stride": 10, "accept": "support"}
