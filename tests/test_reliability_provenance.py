"""Reliability (smoke preset): a result names the agent that made it (issue 83), and nothing kept is replaced without asking (issue 96)."""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
import collect
import configs
import envs
import evaluate
import experts
import rundir
import runner
import tables
from tests.reliability_helpers import ROOT, SMOKE_IMITATE, copy_run, snapshot


# --- 9. a result names the agent that made it (issue 83): a changed agent is evaluated again, never credited ---

def test_rows_of_other_weights_are_not_credited_to_the_agent(smoke_run, tmp_path):
    """imitate's rows carry rundir.weights_id; after the weights change the same command runs again, and the
    tables count the new agent's rows only."""
    run = copy_run(smoke_run, tmp_path)
    first = runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
    path = os.path.join(run, "checkpoint.pt")
    ckpt = torch.load(path, weights_only=True)
    assert {r["weights"] for r in first} == {rundir.weights_id(ckpt)} and first[0]["weights"].startswith("6:")
    assert runner.imitate(run, "walker_run", "side", SMOKE_IMITATE) == []  # the same agent: nothing runs again
    ckpt["models"]["actor"] = {k: v + 1e-3 for k, v in ckpt["models"]["actor"].items()}  # as a resumed training would
    torch.save(ckpt, path)
    second = runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
    assert len(second) == len(first) and {r["weights"] for r in second} == {rundir.weights_id(ckpt)} != {first[0]["weights"]}


def test_a_baseline_never_resumes_a_state_of_other_weights(smoke_run, tmp_path):
    from baselines import genrl

    cell = genrl.load_cell(copy_run(smoke_run, tmp_path), "walker_run", "side")
    cfg = configs.GenRLConfig(**configs.PRESETS["genrl"]["smoke"])
    other = dict(cell, weights="6:0000000000000000")
    assert genrl.state_path(cell, "GenRL", cfg, 0) != genrl.state_path(other, "GenRL", cfg, 0)
    row = genrl.append_row(cell, "GenRL", 0, [1.0], 1.0, genrl.result_config(cfg))
    assert row["weights"] == cell["weights"] and genrl.cell_rows(cell, "GenRL", row["config"]) == [row]
    assert genrl.cell_rows(other, "GenRL", row["config"]) == []


def test_a_run_in_training_is_not_imitated_nor_exported(smoke_run, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    trainer = subprocess.Popen(["sleep", "60"])
    try:
        with open(os.path.join(run, "lock"), "w") as f:
            f.write(str(trainer.pid))
        with pytest.raises(ValueError, match=rf"is being trained now by process {trainer.pid} .*: its checkpoint is not the final agent"):
            runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
        with pytest.raises(ValueError, match="is being trained now"):
            tables.run_table(run, SMOKE_IMITATE)
        with pytest.raises(ValueError, match="is being trained now"):  # its update-k checkpoint is no agent to ship
            checkpoint.export_agent(run, str(tmp_path / "agents" / "walker"))
        assert not os.path.exists(tmp_path / "agents")
        out = subprocess.run([sys.executable, "train.py", "--evaluate", "--run-dir", run, "--preset", "smoke"], cwd=ROOT, capture_output=True, text=True)
        assert out.returncode == 1 and "is being trained now" in out.stderr
    finally:
        trainer.kill()
        trainer.wait()
    assert len(runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)) == 2  # the trainer gone: its stale lock is no obstacle


def test_two_files_scoring_one_evaluation_differently_are_named(tmp_path):
    row = dict(agent="walker", demo="walker_run", view="side", task="run", setting="SE-SV", method="GIIL-ZS", seed=0, score=70.0,
               time=1.0, demo_returns=[1.0], config={}, weights="6:ab")
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text(json.dumps(row) + "\n")
    b.write_text(json.dumps(dict(row, score=20.0)) + "\n" + json.dumps(dict(row, seed=1)) + "\n")
    with pytest.raises(ValueError, match=r"a.jsonl and .*b.jsonl score GIIL-ZS seed 0 on walker_run \(side view\) differently \(70.00 against 20.00\)"):
        tables.merge_files([str(a), str(b)])
    b.write_text(json.dumps(row) + "\n" + json.dumps(dict(row, seed=1)) + "\n")
    assert len(tables.merge_files([str(a), str(b)])) == 2  # the same row in both counts once
    # rows of two weights of one body in one cell (a retrained agent's beside the old one's), in two files or in one
    b.write_text(json.dumps(dict(row, seed=1, weights="6:cd")) + "\n")
    with pytest.raises(ValueError, match=r"a.jsonl and .*b.jsonl hold rows of two agents \(6:ab and 6:cd\) for walker imitating walker_run "
                                         r"\(side view\): pass the rows of one agent's weights"):
        tables.merge_files([str(a), str(b)])
    a.write_text(json.dumps(row) + "\n" + json.dumps(dict(row, seed=1, weights="6:cd")) + "\n")
    with pytest.raises(ValueError, match="hold rows of two agents"):
        tables.merge_files([str(a)])


def test_every_config_field_says_what_it_is_in_the_help():
    """--help shows each field's source comment (rundir.config_flags): every field of every config has one."""
    import dataclasses

    classes = [cls for cls, _ in configs.COMPONENTS.values()] + [configs.ImitateConfig, configs.GenRLConfig, configs.AIMENoBConfig,
                                                                     configs.OnlineConfig, configs.OTConfig, configs.CollectConfig]
    for cls in classes:
        comments = configs.field_comments(cls)
        assert [f.name for f in dataclasses.fields(cls) if not comments.get(f.name)] == [], cls.__name__
    out = subprocess.run([sys.executable, "imitate.py", "--help"], cwd=ROOT, capture_output=True, text=True).stdout
    assert "Adam on g (ours; chosen on same-body cells," in out and "(default 0.0003, or the preset's)" in out


def test_an_episode_that_is_not_what_its_folder_says_is_named(smoke_data, tmp_path):
    """A stickman episode or a D_body episode among walker run demos, and actions outside [-1, 1]: one line each."""
    data = str(tmp_path / "data")
    shutil.copytree(smoke_data, data)
    folder = os.path.join(data, "demos", "walker_run_side")
    shutil.copy(os.path.join(data, "demos", "stickman_run_side", "00.npz"), os.path.join(folder, "07.npz"))
    with pytest.raises(ValueError, match=r"07.npz: an episode of body 'stickman' in .*walker_run_side, which holds body 'walker', task 'run', view 'side': move or delete it"):
        collect.load_folder(folder, ("p",))
    body = sorted(n for n in os.listdir(os.path.join(data, "walker")) if n.startswith("walk_"))[0]
    shutil.copy(os.path.join(data, "walker", body), os.path.join(folder, "07.npz"))
    with pytest.raises(ValueError, match=r"07.npz: an episode of task 'walk'"):
        collect.load_folder(folder, ("p",))
    os.remove(os.path.join(folder, "07.npz"))
    assert len(collect.load_folder(folder, ("p",))) == 2
    path = os.path.join(data, "walker", body)
    episode = dict(np.load(path))
    episode["action"][3, 1] = 1e6
    np.savez(path, **episode)
    with pytest.raises(ValueError, match=r"key 'action' must lie in \[-1, 1\], has 1e\+06 at step 3"):
        collect.load_folder(os.path.join(data, "walker"), ("action",))


# --- 10. nothing kept is replaced without asking (issue 96) ---

def test_a_rerun_with_other_settings_or_weights_keeps_the_kept_rows_videos(smoke_run, tmp_path):
    """A video's name carries its cell, method and seed readably and a tag of the rest of its row's identity (demos,
    settings, weights): a rerun with other --eval-episodes, or by a retrained agent, writes videos of its own."""
    run = copy_run(smoke_run, tmp_path)
    folder = os.path.join(run, "imitate")
    first = runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
    kept = snapshot(folder)
    assert list(kept) == [r["video"] for r in first if "video" in r] and list(kept)[0].startswith("walker_run_side_GIIL-ZS_s0_")
    other = runner.imitate(run, "walker_run", "side", configs.ImitateConfig(**{**configs.PRESETS["imitate"]["smoke"], "eval_episodes": 2}))
    path = os.path.join(run, "checkpoint.pt")
    ckpt = torch.load(path, weights_only=True)
    ckpt["models"]["actor"] = {k: v + 1e-3 for k, v in ckpt["models"]["actor"].items()}  # as a resumed training would
    torch.save(ckpt, path)
    retrained = runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
    now = snapshot(folder)
    assert {k: now[k] for k in kept} == kept  # the kept rows' videos untouched
    videos = [r["video"] for r in first + other + retrained if "video" in r]
    assert len(set(videos)) == len(videos) == 3 and sorted(now) == sorted(videos)


def test_a_count_has_an_upper_bound_that_every_preset_keeps(smoke_run, tmp_path):
    """--seeds 99999999999999999999 ran for hours: an int flag whose range has no top is at most rundir.MAX_COUNT, named
    in one line; every preset and default of every config keeps to it."""
    import dataclasses

    huge = 99999999999999999999
    with pytest.raises(ValueError, match=rf"^--seeds {huge}: must be <= 1000000$"):
        rundir.check_flags(dataclasses.replace(SMOKE_IMITATE, seeds=huge))
    with pytest.raises(ValueError, match=r"^--ac-horizon 1000001: must be <= 1000000$"):
        rundir.check_flags(configs.ActorCriticConfig(horizon=10**6 + 1), "ac-")
    with pytest.raises(ValueError, match=rf"^--seed {huge}: must be <= 1000000$"):  # a range (0, None) too
        rundir.check_flags(configs.TrainConfig(seed=huge))
    with pytest.raises(ValueError, match=rf"^--seeds {huge}: must be <= 1000000$"):
        configs.GenRLConfig(seeds=huge)
    with pytest.raises(ValueError, match=rf"^--threads {huge}: must be <= 1000000$"):
        rundir.use_threads(huge)
    rundir.check_flags(configs.TrainConfig(seed=10**6))  # the bound itself is allowed
    out = subprocess.run([sys.executable, "tables.py", "--run", copy_run(smoke_run, tmp_path), "--seeds", str(huge)], cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr == f"error: --seeds {huge}: must be <= 1000000\n"
    for preset in ("smoke", "cpu", "paper"):
        for name, (cls, prefix) in {**configs.COMPONENTS, "imitate": (configs.ImitateConfig, ""), "online": (configs.OnlineConfig, "online-"),
                                    "collect": (configs.CollectConfig, "")}.items():
            rundir.check_flags(cls(**configs.PRESETS[name][preset]), prefix)
    for name, cls in (("genrl", configs.GenRLConfig), ("aime_nob", configs.AIMENoBConfig)):
        for preset in configs.PRESETS[name]:
            cls(**configs.PRESETS[name][preset])  # checked as it is made
    rundir.check_flags(experts.ExpertConfig())


@pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")
def test_an_encoder_window_longer_than_an_episode_is_refused_before_any_memory_is_taken(tmp_path):
    """A TorchScript video model saying window 10**6 (its probe input alone would take terabytes): one line naming the fix."""
    import video_encoder

    class Model(torch.nn.Module):
        def __init__(self, window):
            super().__init__()
            self.window, self.input_size = window, 8

        def forward(self, x):  # (N, k, 3, S, S) -> (N, 2)
            return torch.stack([x.mean(dim=(1, 2, 3, 4)), torch.ones(len(x))], 1)

    for window in (10**6, envs.EPISODE_STEPS + 2):
        path = str(tmp_path / "long_window.pt")
        torch.jit.save(torch.jit.script(Model(window)), path)
        with pytest.raises(ValueError, match=rf"^{path} says window {window}, more than the 501 frames of an episode \(envs.EPISODE_STEPS steps\): "
                                             r"set the module's window to at most 501$"):
            video_encoder.load_encoder(path)
    torch.jit.save(torch.jit.script(Model(envs.EPISODE_STEPS + 1)), path)
    assert video_encoder.load_encoder(path).window == 501  # a whole episode's frames: allowed


def test_a_run_in_training_is_refused_by_every_reader_of_its_checkpoint(smoke_run, tmp_path):
    """The probes, evaluate.py and every command read a run through rundir.run_checkpoint (checkpoint.load_run,
    evaluate.read_goal_reaching): a run still in training is refused there, before anything is measured."""
    run = copy_run(smoke_run, tmp_path)
    trainer = subprocess.Popen(["sleep", "60"])
    try:
        with open(os.path.join(run, "lock"), "w") as f:
            f.write(str(trainer.pid))
        message = rf"^{run} is being trained now by process {trainer.pid} \(.*lock\): its checkpoint is not the final agent; wait for the training to end"
        with pytest.raises(ValueError, match=message):
            checkpoint.load_run(run)  # what the probes load a run with
        with pytest.raises(ValueError, match=message):
            evaluate.read_goal_reaching(run)  # evaluate.py's and probes/goal_variance.py --benchmark's
        for probe in (["probes/imagination_gap.py", run], ["probes/goal_variance.py", "--benchmark", run]):
            out = subprocess.run([sys.executable] + probe, cwd=ROOT, capture_output=True, text=True)
            assert out.returncode == 1 and f"is being trained now by process {trainer.pid}" in out.stderr.splitlines()[-1], out.stderr[-2000:]
    finally:
        trainer.kill()
        trainer.wait()
    assert checkpoint.load_run(run)[2]["step"] == 6 and evaluate.read_goal_reaching(run)["weights"]  # the trainer gone: read as before
