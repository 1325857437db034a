"""evaluate.py: the benchmark's tables by hand, over runs, and the batched episodes against the environment's own returns."""
import json
import os

import numpy as np
import pytest

import checkpoint
import evaluate
import rundir


def test_summary_and_across_runs_by_hand(smoke_run, tmp_path):
    import torch

    runs, tc = [], checkpoint.load_run(smoke_run)[0]["train"]
    for k, (stand, walk, run) in enumerate([([10, 20], [50, 70], [0, 10]), ([30, 30], [40, 40], [20, 20])]):
        folder = tmp_path / f"r{k}"
        folder.mkdir()
        ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
        ckpt["models"]["actor"] = {n: v + k for n, v in ckpt["models"]["actor"].items()}  # two training seeds: two agents
        torch.save(ckpt, folder / "checkpoint.pt")
        weights = rundir.weights_id(ckpt)
        scores = {"stand": {"policy": stand, "random": [0, 0]}, "walk": {"policy": walk, "random": [1, 3]},
                  "run": {"policy": run, "random": [0, 0]}, "jump": {"policy": [99, 99], "random": [0, 0]}}
        evaluate.write_goal_reaching(str(folder), scores, tc, weights)
        runs.append(str(folder))
    lines = evaluate.summary(scores)
    assert lines[-1].split()[:2] == ["average", "stand/walk/run"] and "30.0 +-  0.0" in lines[-1]  # (30 + 40 + 20) / 3, jump left out
    assert "(not in D_body)" in lines[4]
    table = evaluate.across_runs(runs)
    # run 0: stand 15, walk 60, run 5, average 26.67; run 1: 30, 40, 20, average 30 -> mean 28.33, s.e. 1.67
    assert table[-1].startswith("| mean +- s.e. over 2 runs | 22.5 +- 7.5 | 50.0 +- 10.0 | 12.5 +- 7.5 | 99.0 +- 0.0 | 28.3 +- 1.7 |")
    with pytest.raises(FileNotFoundError, match="train.py --evaluate --run-dir"):
        evaluate.across_runs([str(tmp_path)])


def test_across_runs_refuses_what_is_not_one_comparison(smoke_run, tmp_path):
    """The same run twice, a copy of a run, runs benchmarked with other settings, a benchmark of weights since trained on,
    and a file that names no agent: each a one-line error."""
    import dataclasses
    import shutil

    import torch

    tc = checkpoint.load_run(smoke_run)[0]["train"]
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    for run in (a, b):
        shutil.copytree(smoke_run, run)
    with pytest.raises(ValueError, match=r"/a and .*/b/\.\./a are the same run: pass each training seed once"):
        evaluate.across_runs([a, os.path.join(b, "..", "a")])
    with pytest.raises(ValueError, match=r"/a and .*/b hold the same agent \(6:\w+\): pass each training seed once"):
        evaluate.across_runs([a, b])  # a copy of a run (cp -a) is one agent, not a second seed
    ckpt = torch.load(os.path.join(b, "checkpoint.pt"), weights_only=True)
    ckpt["models"]["actor"] = {k: v + 1 for k, v in ckpt["models"]["actor"].items()}
    torch.save(ckpt, os.path.join(b, "checkpoint.pt"))
    weights = rundir.weights_id(ckpt)
    evaluate.write_goal_reaching(b, json.load(open(os.path.join(b, "goal_reaching.json")))["scores"], dataclasses.replace(tc, eval_steps=2), weights)
    with pytest.raises(ValueError, match=r"differ in settings .*'eval_steps': 10.* against .*'eval_steps': 2"):
        evaluate.across_runs([a, b])
    ckpt = torch.load(os.path.join(b, "checkpoint.pt"), weights_only=True)
    ckpt["models"]["actor"] = {k: v + 1e-3 for k, v in ckpt["models"]["actor"].items()}
    torch.save(ckpt, os.path.join(b, "checkpoint.pt"))
    with pytest.raises(ValueError, match=r"scores the agent 6:\w+, but .*b now holds 6:\w+ \(trained since\): run `python train.py --evaluate"):
        evaluate.across_runs([a, b])
    with open(os.path.join(b, "goal_reaching.json"), "w") as f:
        json.dump(json.load(open(os.path.join(a, "goal_reaching.json")))["scores"], f)  # the format before the agent was named
    with pytest.raises(ValueError, match="was written before results named their agent"):
        evaluate.across_runs([a, b])
    for damaged, says in (("null", r"is damaged \(it holds null, not a benchmark record\)"),
                          ('{"weights": "6:ab", "scores": {"stand": {"random": [0]}}}', r"is damaged \(its scores are not per-task lists")):
        with open(os.path.join(b, "goal_reaching.json"), "w") as f:
            f.write(damaged)
        with pytest.raises(ValueError, match=says + r".*: run `python train.py --evaluate --run-dir .*b` again"):
            evaluate.across_runs([a, b])


def test_run_episodes_sums_each_environment_s_true_reward(smoke_run):
    """Random actions in two envs at once: each return equals the env's reward summed over the same actions."""
    import envs

    cfgs, models, _ = checkpoint.load_run(smoke_run)
    env_list = [envs.make_env("walker", "walk") for _ in range(2)]
    heights = []  # on_step reads the physics after every step
    on_step = lambda env_list: heights.append([env.physics.named.data.xpos["torso", "z"] for env in env_list])
    returns, frames = evaluate.run_episodes(env_list, models, None, 5, "state", seed=3, render=True, random_actions=True, on_step=on_step)
    assert returns.shape == (2,) and frames.shape == (2, 6, 64, 64, 3) and np.array(heights).shape == (5, 2)
    rng = np.random.default_rng(3)
    for env, seed in zip(env_list, (3, 4)):
        env.reset(seed=seed)
    total = np.zeros(2)
    for _ in range(5):
        actions = rng.uniform(-1, 1, (2, env_list[0].action_dim)).astype(np.float32)
        total += [env.step(a)[1] for env, a in zip(env_list, actions)]
    assert np.allclose(returns, total) and heights[-1] == [env.physics.named.data.xpos["torso", "z"] for env in env_list]
    scores = json.load(open(os.path.join(smoke_run, "goal_reaching.json")))["scores"]
    assert set(scores) == {"stand", "walk", "run", "jump"}


def test_run_episodes_acts_with_the_actors_mean_action(smoke_run):
    """The agent acts with the tanh of pi's mean on each posterior state (Dreamer's evaluation), the same for the same seed."""
    import torch

    import envs

    _, models, ckpt = checkpoint.load_run(smoke_run)
    wm, actor = models["world_model"], models["actor"]
    with torch.no_grad():
        goals = models["goal_vae"].goal(torch.randn(2, ckpt["p_dim"]))

    def episode():
        states, actions, act = [], [], actor.act
        actor.act = lambda feat, goal: actions.append(act(feat, goal)) or actions[-1]  # what run_episodes acts with
        try:
            evaluate.run_episodes([envs.make_env("walker", "walk") for _ in range(2)], models, goals, 4, "state", 0, on_state=states.append)
        finally:
            del actor.act
        return states, torch.stack(actions)

    states, mean = episode()
    with torch.no_grad():
        assert torch.equal(mean, torch.stack([actor(wm.feat(s), goals, deterministic=True)[0] for s in states[:-1]]))
    assert torch.equal(episode()[1], mean)


def test_reachable_reward_across_runs_by_hand(tmp_path):
    """First row against the mean of the last rows, over runs: rows without reward_reachable (before the actor) skipped."""
    runs = []
    for k, rows in enumerate([[[-0.4, -0.4, -0.4], [-0.3, -0.35, -0.5], [-0.1, -0.35, -0.5]], [[-0.5, -0.5, -0.5], [-0.4, -0.4, -0.6]]]):
        folder = tmp_path / f"r{k}"
        folder.mkdir()
        with open(folder / "metrics.jsonl", "w") as f:
            f.write(json.dumps({"step": 100}) + "\n")
            f.writelines(json.dumps({"reward_reachable": r}) + "\n" for r in rows)
        runs.append(str(folder))
    table = evaluate.reachable_across_runs(runs, last=2)
    # run 0: first -0.4, last two -0.2 / -0.35 / -0.5; run 1: first -0.5, last two -0.45 / -0.45 / -0.55
    assert table[2] == "| first row (a fresh actor), 2 runs | -0.450 +- 0.050 | -0.450 +- 0.050 | -0.450 +- 0.050 |"
    assert table[3] == "| last 2 rows | -0.325 +- 0.125 | -0.400 +- 0.050 | -0.525 +- 0.025 |"
    assert table[4].startswith("| last minus first, paired | 0.125 +- 0.075 |")  # (0.2 + 0.05) / 2
    (tmp_path / "old").mkdir()  # a run from before the diagnostic
    (tmp_path / "old" / "metrics.jsonl").write_text(json.dumps({"step": 100}) + "\n")
    assert evaluate.reachable_across_runs([str(tmp_path / "old")]) == []


def test_gradient_share_across_runs_by_hand(tmp_path):
    """The last rows' mean grad_eq4 and grad_bc per run, then over runs; runs without them (no cloning) are left out."""
    runs = []
    for k, rows in enumerate([[(9.0, 9.0), (0.1, 2.0), (0.3, 4.0)], [(0.2, 1.0), (0.2, 3.0)], []]):
        folder = tmp_path / f"r{k}"
        folder.mkdir()
        with open(folder / "metrics.jsonl", "w") as f:
            f.write(json.dumps({"step": 100}) + "\n")
            f.writelines(json.dumps({"grad_eq4": eq4, "grad_bc": bc}) + "\n" for eq4, bc in rows)
        runs.append(str(folder))
    table = evaluate.gradient_share(runs, last=2)
    # run 0: 0.2 and 3.0 (ratio 15); run 1: 0.2 and 2.0 (ratio 10); run 2 logged none
    assert table[0].startswith("| actor's gradient norm, last 2 rows, 2 runs |")
    assert table[2] == "| mean +- s.e. | 0.200 +- 0.000 | 2.500 +- 0.500 | 12.5 +- 2.5 |"
    assert evaluate.gradient_share(runs[2:]) == []
