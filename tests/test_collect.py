"""collect.py: D_body / D_demo contents, the episode reader's errors, resume (smoke preset)."""
import os

import numpy as np
import pytest
import torch

import collect
import configs
import envs
import experts

SMOKE = configs.CollectConfig(**configs.PRESETS["collect"]["smoke"])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("data"))
    collect.collect_body("walker", SMOKE, root, workers=1)
    return root


def test_body_dataset_is_unlabelled_mix_without_jump(data):
    episodes = collect.load_folder(os.path.join(data, "walker"))
    assert len(episodes) == SMOKE.explore_episodes + len(envs.BODY_TASKS) * SMOKE.task_episodes
    assert {e["task"] for e in episodes} == {"explore", "stand", "walk", "run"}
    assert not any("jump" in e["source"] for e in episodes)
    e = episodes[-1]
    length = SMOKE.episode_steps + 1
    assert e["state"].shape == (length, 24) and e["pixels"].shape == (length, 64, 64, 3) and e["action"].shape == (length, 6)
    assert e["is_first"][0] and not e["is_first"][1:].any() and not e["action"][0].any() and e["reward"][0] == 0
    assert np.allclose(np.linalg.norm(e["p"], axis=1), 1, atol=1e-5)


def test_resume_skips_existing_episodes(data):
    folder = os.path.join(data, "walker")
    before = {n: os.path.getmtime(os.path.join(folder, n)) for n in os.listdir(folder)}
    os.remove(os.path.join(folder, "walk_0000.npz"))
    collect.collect_body("walker", SMOKE, data, workers=1)
    after = {n: os.path.getmtime(os.path.join(folder, n)) for n in os.listdir(folder)}
    assert sorted(after) == sorted(before)  # same files, no duplicates, no temporaries
    assert sorted(n for n in after if after[n] != before[n]) == [collect.COMPLETE, "walk_0000.npz"]


def test_episodes_are_reproducible(data, tmp_path):
    collect.collect_body("walker", SMOKE, str(tmp_path), workers=2)
    for name in ("explore_0001.npz", "run_0000.npz"):
        a = collect.load_episode(os.path.join(data, "walker", name))
        b = collect.load_episode(os.path.join(tmp_path, "walker", name))
        assert np.array_equal(a["state"], b["state"]) and np.array_equal(a["p"], b["p"])


def test_episodes_do_not_depend_on_the_callers_matmul_route():
    """A process that routed fp32 matmuls through oneDNN (train.py, imitate.py: rundir.fast_matmul) simulates the same
    expert episode as a fresh one, and keeps its route."""
    job = dict(kind="run", body="walker", task="run", index=0, snapshot=None, steps=SMOKE.episode_steps, noise=0.3,
               seed=[0, 1, 2], views=("side",))
    plain = collect.simulate(job)[0]
    matmul = torch.backends.mkldnn.matmul
    try:
        matmul.fp32_precision = "bf16"
        routed = collect.simulate(job)[0]
        assert matmul.fp32_precision == "bf16"
    finally:
        matmul.fp32_precision = "none"
    assert np.array_equal(plain["state"], routed["state"]) and np.array_equal(plain["action"], routed["action"])


def test_an_episode_in_a_reused_env_is_that_of_a_fresh_one():
    """A worker keeps one env per (body, task) across its episodes (collect._worker_env): an episode after another in
    the same env has the states, actions and frames it has in a fresh process."""
    job = lambda seed: dict(kind="explore", body="walker", task="stand", index=0, snapshot=None, steps=SMOKE.episode_steps,
                            noise=0.3, seed=[0, 0, seed], views=("side",))
    collect._ENVS.clear()
    fresh = collect.simulate(job(1))[0]
    collect.simulate(job(2))  # the env now holds another episode's last state
    reused = collect.simulate(job(1))[0]
    assert len(collect._ENVS) == 1
    assert all(np.array_equal(fresh[k], reused[k]) for k in ("state", "action", "pixels"))


def test_demo_return_is_sum_of_rewards_and_views_share_motion(tmp_path):
    cfg = configs.CollectConfig(**dict(configs.PRESETS["collect"]["smoke"], demo_episodes=1))
    collect.collect_demos(cfg, str(tmp_path), workers=2)
    folders = sorted(os.listdir(tmp_path / "demos"))
    assert len(folders) == 2 * 4 * 2  # body x task x view
    side = collect.load_episode(str(tmp_path / "demos" / "stickman_jump_side" / "00.npz"))
    diagonal = collect.load_episode(str(tmp_path / "demos" / "stickman_jump_diagonal" / "00.npz"))
    assert side["return"] == pytest.approx(side["reward"].sum(), rel=1e-5)
    assert np.array_equal(side["state"], diagonal["state"]) and not np.array_equal(side["pixels"], diagonal["pixels"])
    assert side["source"] == "jump@final" and side["view"] == "side"


def test_reader_names_corrupt_file(data, tmp_path):
    good = os.path.join(data, "walker", "explore_0000.npz")
    truncated = str(tmp_path / "truncated.npz")
    with open(good, "rb") as f, open(truncated, "wb") as g:
        g.write(f.read()[:2000])
    with pytest.raises(ValueError, match="truncated.npz"):
        collect.load_episode(truncated)
    episode = dict(np.load(good))
    episode["p"] = episode["p"][:-3]
    bad = str(tmp_path / "short_p.npz")
    np.savez(bad, **episode)
    with pytest.raises(ValueError, match=r"short_p.npz: key 'p' has 18 steps, expected 21"):
        collect.load_episode(bad)
    del episode["action"]
    np.savez(bad, **episode)
    with pytest.raises(ValueError, match="short_p.npz: missing key.*action"):
        collect.load_episode(bad)
    episode = dict(np.load(good), **{"return": np.float64("nan")})  # a demo's return names its demos in every result row
    np.savez(bad, **episode)
    with pytest.raises(ValueError, match=r"short_p.npz: its return nan is not a finite number; delete the file and rerun collect.py"):
        collect.load_episode(bad)


def test_missing_expert_names_the_command(tmp_path, monkeypatch):
    monkeypatch.setattr(experts, "EXPERT_DIR", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="python -m experts --body stickman"):
        collect.collect_body("stickman", SMOKE, str(tmp_path), workers=1)
    with pytest.raises(ValueError, match="valid body names are walker, stickman"):
        collect.collect_body("humanoid", SMOKE, str(tmp_path), workers=1)


def test_collection_never_replaces_a_written_view(data, tmp_path):
    """A demo whose side view is on disk and diagonal view is not: only the diagonal file is written."""
    cfg = configs.CollectConfig(**dict(configs.PRESETS["collect"]["smoke"], demo_episodes=1))
    side = tmp_path / "demos" / "walker_run_side" / "00.npz"
    side.parent.mkdir(parents=True)
    episode = dict(np.load(os.path.join(data, "walker", "run_0000.npz")))  # any 20-step episode stands in for it
    collect.save_episode(str(side), episode)
    before = side.read_bytes()
    collect.collect_demos(cfg, str(tmp_path), workers=1, demos=[("walker", "run")])
    assert side.read_bytes() == before
    assert collect.load_episode(str(tmp_path / "demos" / "walker_run_diagonal" / "00.npz"))["view"] == "diagonal"
    assert sorted(os.listdir(tmp_path / "demos")) == ["walker_run_diagonal", "walker_run_side"]


def test_task_episodes_flag_grows_d_body_and_keeps_what_exists(data, tmp_path):
    """`python collect.py --task-episodes N` collects N episodes per task (the preset's others unchanged) on top of a
    smaller D_body, rewriting none of it; 0 is refused in one line."""
    import json
    import shutil
    import subprocess
    import sys

    root = str(tmp_path / "data")
    shutil.copytree(data, root)
    folder = os.path.join(root, "walker")
    before = {n: os.path.getmtime(os.path.join(folder, n)) for n in os.listdir(folder) if n.endswith(".npz")}
    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "collect.py")
    run = lambda n: subprocess.run([sys.executable, script, "--env", "walker", "--preset", "smoke", "--data", root, "--workers", "1",
                                    "--task-episodes", str(n)], capture_output=True, text=True)
    out = run(0)
    assert out.returncode == 2 and out.stderr.strip().endswith("--task-episodes 0: must be >= 1")
    out = subprocess.run([sys.executable, script, "--env", "walker", "--preset", "smoke", "--data", root, "--history-from", "1.5"],
                         capture_output=True, text=True)
    assert out.returncode == 2 and out.stderr.strip().endswith("--history-from 1.5: must be in [0, 1]")
    out = run(2)
    assert out.returncode == 0, out.stderr[-2000:]
    names = sorted(n for n in os.listdir(folder) if n.endswith(".npz"))
    assert len(names) == SMOKE.explore_episodes + 2 * len(envs.BODY_TASKS) and "walk_0001.npz" in names
    assert all(os.path.getmtime(os.path.join(folder, n)) == t for n, t in before.items())
    assert json.load(open(os.path.join(folder, collect.COMPLETE)))["task_episodes"] == 2


def test_task_episodes_replay_the_chosen_part_of_each_learning_history(tmp_path):
    cfg = configs.CollectConfig(explore_episodes=0, task_episodes=40, history_from=0.5)
    steps = {task: experts.history_steps("stickman", task) for task in envs.BODY_TASKS}
    chosen = {}
    for _, job in collect.episode_jobs("stickman", cfg, str(tmp_path)):
        chosen.setdefault(job["task"], set()).add(job["snapshot"])
    for task, history in steps.items():  # e.g. stand 50k..300k: only 150k..300k, each of them drawn
        assert chosen[task] == {s for s in history if s >= history[-1] / 2}
    whole = collect.episode_jobs("stickman", configs.CollectConfig(explore_episodes=0, task_episodes=40), str(tmp_path))  # the default
    assert {job["snapshot"] for _, job in whole if job["task"] == "stand"} == set(steps["stand"])


def test_the_cpu_preset_collects_160_task_episodes_per_task_for_both_bodies(tmp_path):
    """The cpu preset's D_body: 80 exploration episodes and 160 per task in BODY_TASKS (560), each with its own seed;
    D_demo's config is the same preset's."""
    cpu = collect.preset_config("cpu")
    assert cpu == configs.CollectConfig() and cpu.demo_episodes == 10
    for body in ("walker", "stickman"):
        jobs = [job for _, job in collect.episode_jobs(body, cpu, str(tmp_path))]
        assert len(jobs) == 560 and [j["kind"] for j in jobs].count("explore") == 80
        assert all([j["kind"] for j in jobs].count(task) == 160 for task in envs.BODY_TASKS)
        assert len({tuple(j["seed"]) for j in jobs}) == 560
    assert collect.preset_config("smoke") == SMOKE
