"""Reliability (smoke preset): kill -9 and --resume, committed expert weights, partial or mixed data, divergence, numeric flags, run directories, bad episode files."""
import glob
import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
import collect
import configs
import experts
import goal_inference
import goal_vae
import rundir
import runner
import train
from tests.fixtures import train_args
from tests.reliability_helpers import KILLED_TRAIN, ROOT, SMOKE_IMITATE, TINY, copy_run, snapshot


# --- what already held: kill -9, then --resume, is bit-identical to an uninterrupted run ---

def test_kill_then_resume_equals_an_uninterrupted_run(smoke_run, smoke_data, tmp_path):
    run = str(tmp_path / "killed")
    flags = ["--env", "walker", "--preset", "smoke", "--data", smoke_data, "--run-dir", run]
    killed = subprocess.run([sys.executable, "-c", KILLED_TRAIN] + flags, cwd=ROOT, capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    assert torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == 3
    assert os.path.exists(os.path.join(run, "lock")) and glob.glob(os.path.join(run, "checkpoint.pt.*.tmp"))
    resumed = subprocess.run([sys.executable, "train.py", "--resume"] + flags, cwd=ROOT, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resumed" in resumed.stdout and not os.path.exists(os.path.join(run, "lock")) and not glob.glob(os.path.join(run, "*.tmp"))
    a, b = (torch.load(os.path.join(r, "checkpoint.pt"), weights_only=True) for r in (run, smoke_run))
    assert a["step"] == b["step"] == 6 and a["rng"] == b["rng"] and torch.equal(a["torch_rng"], b["torch_rng"])
    for name in b["models"]:
        for key, value in b["models"][name].items():
            assert torch.equal(a["models"][name][key], value), (name, key)
    for name in ("goal_reaching.json", "imagination.json"):
        assert json.load(open(os.path.join(run, name))) == json.load(open(os.path.join(smoke_run, name)))
    rows = [[{k: v for k, v in json.loads(line).items() if k != "updates_per_s"} for line in open(os.path.join(r, "metrics.jsonl"))] for r in (run, smoke_run)]
    assert [r["step"] for r in rows[0]] == [2, 4, 6] and rows[0] == rows[1]  # the killed run's rows past update 3 are not repeated


# --- 1. committed expert weights are overwritten only when a run asks for it by name ---

@pytest.fixture
def committed(tmp_path, monkeypatch):
    """A copy of the committed walker experts as experts/, and its bytes."""
    folder = tmp_path / "experts"
    for path in glob.glob(os.path.join(experts.EXPERT_DIR, "**", "walker_*.pt"), recursive=True):
        target = folder / os.path.relpath(path, experts.EXPERT_DIR)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    monkeypatch.setattr(experts, "EXPERT_DIR", str(folder))
    return str(folder), snapshot(str(folder))


def test_experts_never_overwrite_committed_weights_unasked(committed, tmp_path):
    folder, before = committed
    cfg = experts.ExpertConfig(**TINY)
    with pytest.raises(ValueError, match=r"--resume: no training state at .*missing.*walker.pt .*add --replace-committed"):
        experts.train("walker", list(experts.envs.TASKS), cfg, str(tmp_path / "missing"), resume=True)
    with pytest.raises(ValueError, match=r"walker_stand.pt and \d+ more committed files .* pass --replace-committed"):
        experts.train("walker", list(experts.envs.TASKS), cfg, str(tmp_path / "fresh"), resume=False)
    assert snapshot(folder) == before and not os.path.exists(tmp_path / "missing")
    # asked by name: the compact states resume (walker stand has none committed: named), at their own step
    with pytest.raises(FileNotFoundError, match="resume/walker_stand.pt: leave stand out of --tasks"):
        experts.train("walker", ["stand", "walk"], cfg, str(tmp_path / "missing"), resume=True, replace_committed=True)
    with pytest.raises(ValueError, match=r"--steps 12 is below step \d{6} of the state resumed"):
        experts.train("walker", ["walk", "run"], cfg, str(tmp_path / "missing"), resume=True, replace_committed=True)
    assert snapshot(folder) == before and not os.path.exists(tmp_path / "missing")


# --- 2. partial or mixed data is completed or refused, never used silently ---

def test_killed_collection_is_completed_before_training(smoke_data, tmp_path):
    data = str(tmp_path / "data")
    shutil.copytree(os.path.join(smoke_data, "walker"), os.path.join(data, "walker"))
    os.remove(os.path.join(data, "walker", collect.COMPLETE))  # as a collection killed before its end leaves it
    for name in ("stand_0000.npz", "walk_0000.npz", "run_0000.npz"):
        os.remove(os.path.join(data, "walker", name))
    cfgs = train.resolve_configs(train_args(data=data, preset="smoke"), "smoke")  # the preset whose D_body is completed
    train.train(cfgs, str(tmp_path / "run"), resume=False)
    assert sorted(os.listdir(os.path.join(data, "walker"))) == sorted(os.listdir(os.path.join(smoke_data, "walker")))


def test_episodes_deleted_from_a_complete_collection_are_collected_again(smoke_data, tmp_path):
    data = str(tmp_path / "data")
    shutil.copytree(os.path.join(smoke_data, "walker"), os.path.join(data, "walker"))
    listed = json.load(open(os.path.join(data, "walker", collect.COMPLETE)))["episodes"]
    assert sorted(listed) == sorted(n for n in os.listdir(os.path.join(smoke_data, "walker")) if n.endswith(".npz"))
    for name in ("explore_0001.npz", "walk_0000.npz"):  # collection.json still says complete
        os.remove(os.path.join(data, "walker", name))
    cfgs = train.resolve_configs(train_args(data=data, preset="smoke", steps=2, eval_steps=2), "smoke")
    checkpoint.prepare_data(cfgs)
    assert sorted(os.listdir(os.path.join(data, "walker"))) == sorted(os.listdir(os.path.join(smoke_data, "walker")))


def test_features_are_recomputed_for_the_named_collection_only(smoke_data, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(os.path.join(smoke_data, "walker"), data / "walker")
    shutil.copytree(os.path.join(smoke_data, "demos", "walker_run_side"), data / "demos" / "walker_run_side")
    shutil.copytree(os.path.join(smoke_data, "walker"), data / "smoke" / "walker")  # another collection inside this one

    class Mean(torch.nn.Module):
        def forward(self, x):  # (N, k, 3, S, S) -> (N, 3)
            return x.mean(dim=(1, 3, 4)) + 1

    torch.jit.save(torch.jit.script(Mean()), str(tmp_path / "mean.pt"))
    collect.recompute_features(str(data), str(tmp_path / "mean.pt"))
    encoder_of = lambda folder: {str(np.load(os.path.join(folder, n))["encoder"]) for n in os.listdir(folder) if n.endswith(".npz")}
    assert all(e.startswith("torchscript:mean.pt:") for f in (data / "walker", data / "demos" / "walker_run_side") for e in encoder_of(f))
    assert encoder_of(data / "smoke" / "walker") == encoder_of(os.path.join(smoke_data, "walker")) == {"default-v1"}


def test_a_data_folder_named_by_a_checkpoint_from_elsewhere_is_not_followed(smoke_run, tmp_path):
    elsewhere = tmp_path / "some" / "other" / "place"
    elsewhere.mkdir(parents=True)
    run = copy_run(smoke_run, tmp_path, str(elsewhere))
    with pytest.raises(ValueError, match=r"names the data folder .*/some/other/place, which holds neither D_body nor demos: not followed"):
        runner.imitate(run, "walker_run", "side", SMOKE_IMITATE, [])
    assert os.listdir(elsewhere) == [] and not os.path.exists(os.path.join(run, "results.jsonl"))


def test_demos_of_two_lengths_are_refused(smoke_run, smoke_data, tmp_path):
    data = str(tmp_path / "data")
    for view in ("side", "diagonal"):
        shutil.copytree(os.path.join(smoke_data, "demos", f"walker_run_{view}"), os.path.join(data, "demos", f"walker_run_{view}"))
    path = os.path.join(data, "demos", "walker_run_side", "01.npz")
    episode = dict(np.load(path))
    collect.save_episode(path, {k: v[:11] if v.ndim else v for k, v in episode.items()})
    run = copy_run(smoke_run, tmp_path, data)
    with pytest.raises(ValueError, match=r"walker_run_side mixes episodes of 21 and 11 steps .*00.npz.*01.npz"):
        runner.imitate(run, "walker_run", "side", SMOKE_IMITATE, ["GIIL-FT"])


def test_collection_into_another_presets_folder_is_refused(smoke_data, tmp_path):
    data = str(tmp_path / "data")
    shutil.copytree(os.path.join(smoke_data, "walker"), os.path.join(data, "walker"))
    before = snapshot(data)
    longer = configs.CollectConfig(**dict(configs.PRESETS["collect"]["smoke"], explore_episodes=3, episode_steps=30))
    with pytest.raises(ValueError, match=r"explore_0000.npz is not a 30-step episode .*pass another --data"):
        collect.collect_body("walker", longer, data, workers=1)
    assert snapshot(data) == before
    assert train.resolve_configs(train_args(), "smoke")["train"].data == configs.DATA["smoke"] != configs.DATA["cpu"]  # apart by default


def test_two_processes_writing_one_file_each_write_a_whole_one(tmp_path):
    # two runs side by side on one --data both collect its missing D_demo: another process writes the same episode
    # while this one is half-way through it (one shared temporary file used to lose one writer's rename)
    path, theirs = str(tmp_path / "01.npz"), b"theirs" * 1000
    other = f"import rundir; rundir.atomic_write({path!r}, lambda f: f.write({theirs!r}))"

    def write(f):
        f.write(b"ours, first half ")
        subprocess.run([sys.executable, "-c", other], cwd=ROOT, check=True)
        assert open(path, "rb").read() == theirs
        f.write(b"second half")

    rundir.atomic_write(path, write)
    assert open(path, "rb").read() == b"ours, first half second half" and os.listdir(tmp_path) == ["01.npz"]


# --- 3. divergence stops the run, names what was kept ---

def test_divergence_and_nan_gradient_stop_without_saving(smoke_run, smoke_data, tmp_path, monkeypatch):
    fresh = str(tmp_path / "fresh")
    original = goal_vae.GoalVAE.loss
    monkeypatch.setattr(goal_vae.GoalVAE, "loss", lambda self, p, post: (original(self, p, post)[0] * 1e30, {}))
    cfgs = train.resolve_configs(train_args(data=smoke_data), "smoke")
    with pytest.raises(ValueError, match=r"Eq. 3 goal-VAE loss is [\d.]+e\+3\d at update 0: stopped; no checkpoint was written yet .*--goal-lr is 0.0006"):
        train.train(cfgs, fresh, resume=False)
    assert not os.path.exists(os.path.join(fresh, "checkpoint.pt"))
    # a finite loss whose gradient is NaN (sqrt at 0): the resumed checkpoint is named and left as it was
    run = copy_run(smoke_run, tmp_path)
    before = snapshot(run)
    nan_grad = lambda self, p, post: (original(self, p, post)[0] + (next(self.parameters()) * 0).sqrt().sum(), {})
    monkeypatch.setattr(goal_vae.GoalVAE, "loss", nan_grad)
    with pytest.raises(ValueError, match=r"goal-VAE loss has a non-finite gradient \(norm nan\) at update 6: stopped; the last good checkpoint is .*checkpoint.pt \(update 6\)"):
        train.train(train.resolve_configs(train_args(data=smoke_data, steps=9), "smoke"), run, resume=True)
    assert snapshot(run)["checkpoint.pt"] == before["checkpoint.pt"]


def test_phase_2_divergence_stops_before_writing_a_result(smoke_run, tmp_path, monkeypatch):
    run = copy_run(smoke_run, tmp_path)
    original = goal_inference.goal_inference_loss

    def nan_loss(*args, **kwargs):
        loss, critic_loss, metrics = original(*args, **kwargs)
        return loss * float("nan"), critic_loss, metrics

    monkeypatch.setattr(goal_inference, "goal_inference_loss", nan_loss)
    with pytest.raises(ValueError, match=r"GIIL-FT seed 0: Eq. 5 L_GI is nan at update 0: stopped"):
        runner.imitate(run, "walker_run", "side", SMOKE_IMITATE, ["GIIL-FT"], zero_shot=False)
    rows = rundir.read_jsonl(os.path.join(run, "results.jsonl"))
    assert [r["method"] for r in rows] == ["GIIL-ZS (demo 0)"]  # its zero-shot evaluation, written before; no GIIL-FT row


# --- 4. every numeric flag is checked at start-up, naming the flag ---

@pytest.mark.parametrize("given, message", [
    (dict(steps=0), "--steps 0: must be >= 1"), (dict(checkpoint_every=0), "--checkpoint-every 0: must be >= 1"),
    (dict(holdout_every=1), "--holdout-every 1: must be >= 2"), (dict(holdout_every=0), "--holdout-every 0: must be >= 2"),
    (dict(threads=0), "--threads 0: must be >= 1"), (dict(eval_steps=-5), "--eval-steps -5: must be >= 1"),
    ({"goal.lr": 1e3}, r"--goal-lr 1000.0: must be a learning rate in \(0, 1\)"), ({"ac.critic_lr": 1e3}, "--ac-critic-lr 1000.0"),
    ({"dist.lr": float("nan")}, "--dist-lr nan"), ({"ac.gamma": 1.5}, r"--ac-gamma 1.5: must be in \[0, 1\]"),
])
def test_train_flags_out_of_range(given, message, smoke_data, tmp_path):
    with pytest.raises(ValueError, match=message):
        train.train(train.resolve_configs(train_args(data=smoke_data, **given), "smoke"), str(tmp_path / "run"), resume=False)
    assert not os.path.exists(tmp_path / "run")


@pytest.mark.parametrize("given, message", [
    (dict(steps=0), "--steps 0: must be >= 1"), (dict(seeds=0), "--seeds 0: must be >= 1"),
    (dict(eval_episodes=0), "--eval-episodes 0: must be >= 1"), (dict(eval_steps=0), "--eval-steps 0: must be >= 1"),
    (dict(starts=0), "--starts 0: must be >= 1"),
])
def test_imitate_flags_out_of_range(given, message, smoke_run, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    ic = configs.ImitateConfig(**{**configs.PRESETS["imitate"]["smoke"], **given})
    with pytest.raises(ValueError, match=message):
        runner.imitate(run, "walker_run", "side", ic, ["GIIL-FT"])
    assert not os.path.exists(os.path.join(run, "results.jsonl"))


def test_every_preset_passes_the_checks_and_the_command_line_prints_one_line():
    for preset in ("smoke", "cpu", "paper"):
        for name, (cls, prefix) in configs.COMPONENTS.items():
            rundir.check_flags(cls(**configs.PRESETS[name][preset]), prefix)
        rundir.check_flags(configs.ImitateConfig(**configs.PRESETS["imitate"][preset]))
    rundir.check_flags(experts.ExpertConfig())
    with pytest.raises(ValueError, match="--snapshot-every 0: must be >= 1"):
        rundir.check_flags(experts.ExpertConfig(snapshot_every=0))
    out = subprocess.run([sys.executable, "train.py", "--preset", "smoke", "--eval-steps", "0"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr == "error: --eval-steps 0: must be >= 1\n"


def test_phase_2_threads_are_the_command_lines_not_the_runs(smoke_run, tmp_path):
    """A run trained with --threads 2 must not put 2 threads in each table shard (rundir.threads_flag)."""
    run = copy_run(smoke_run, tmp_path)
    path = os.path.join(run, "checkpoint.pt")
    ckpt = torch.load(path, weights_only=True)
    ckpt["config"]["train"]["threads"] = 2
    torch.save(ckpt, path)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        runner.imitate(run, "walker_run", "side", SMOKE_IMITATE)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    out = subprocess.run([sys.executable, "tables.py", "--run", run, "--threads", "0"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr == "error: --threads 0: must be >= 1\n"


# --- 5. run directories: one writer, --resume needs a checkpoint, logs without duplicates or cut rows ---

def test_a_live_trainer_locks_its_run_directory(smoke_run, smoke_data, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    other = subprocess.Popen(["sleep", "60"])
    try:
        with open(os.path.join(run, "lock"), "w") as f:
            f.write(str(other.pid))
        before = snapshot(run)
        cfgs = train.resolve_configs(train_args(data=smoke_data, steps=8), "smoke")
        with pytest.raises(ValueError, match=rf"run is in use by process {other.pid} \(its lock file .*lock\)"):
            train.train(cfgs, run, resume=True)
        assert snapshot(run) == before
    finally:
        other.kill()
        other.wait()
    with pytest.raises(ValueError, match=r"--resume: no checkpoint at .*nothing.checkpoint.pt; drop --resume"):
        train.train(cfgs, str(tmp_path / "nothing"), resume=True)
    assert not os.path.exists(tmp_path / "nothing")


def test_resume_drops_metrics_rows_past_the_checkpoint(smoke_run, smoke_data, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    with open(os.path.join(run, "metrics.jsonl"), "a") as f:
        f.write(json.dumps({"step": 8, "wm_loss": 1.0}) + "\n" + '{"step": 10, "wm_lo')  # logged by a run killed after update 6
    train.train(train.resolve_configs(train_args(data=smoke_data, steps=8), "smoke"), run, resume=True)
    rows = [json.loads(line) for line in open(os.path.join(run, "metrics.jsonl"))]
    assert [r["step"] for r in rows] == [2, 4, 6, 8] and rows[-1]["wm_loss"] != 1.0


def test_results_with_a_cut_last_line_still_table(tmp_path):
    path = str(tmp_path / "results.jsonl")
    row = {"demo": "walker_run", "view": "side", "method": "GIIL-ZS", "seed": 0, "score": 1.0}
    with open(path, "w") as f:
        f.write(json.dumps(row) + "\n" + json.dumps(row)[:20])  # a kill while appending
    assert runner.load_results(str(tmp_path)) == [row]
    rundir.append_jsonl(path, dict(row, seed=1))
    assert [r["seed"] for r in rundir.read_jsonl(path)] == [0, 1] and open(path).read().count("\n") == 2
    with open(path, "a") as f:
        f.write(json.dumps(dict(row, seed=2)))  # whole, but cut before its newline: kept, like read_jsonl keeps it
    rundir.append_jsonl(path, dict(row, seed=3))
    assert [r["seed"] for r in rundir.read_jsonl(path)] == [0, 1, 2, 3]
    with open(path, "a") as f:
        f.write("not json\n" + json.dumps(row) + "\n")
    with pytest.raises(ValueError, match=r"results.jsonl: line 5 is not a JSON row"):
        runner.load_results(str(tmp_path))


# --- 6. a bad episode file is named ---

def test_bad_episodes_are_named(smoke_data, tmp_path):
    data = str(tmp_path / "data")
    folder = os.path.join(data, "walker")
    shutil.copytree(os.path.join(smoke_data, "walker"), folder)
    keys = ("state", "action", "is_first", "p")
    with open(os.path.join(folder, "text.npz"), "w") as f:
        f.write("not an archive\n")
    with pytest.raises(ValueError, match=r"text.npz: not a readable .npz episode"):
        collect.load_folder(folder, keys)
    with open(os.path.join(folder, "text.npz"), "wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(ValueError, match=r"text.npz: not a readable .npz episode \(no zip archive"):
        collect.load_folder(folder, keys)
    os.remove(os.path.join(folder, "text.npz"))
    path = os.path.join(folder, "walk_0000.npz")
    episode = dict(np.load(path))
    collect.save_episode(path, dict(episode, action=episode["action"][:, :5]))
    with pytest.raises(ValueError, match=r"walk_0000.npz: key 'action' has shape \(5,\) per step, .*explore_0000.npz has \(6,\)"):
        collect.load_folder(folder, keys)
    episode["state"][7, 2] = np.nan
    collect.save_episode(path, episode)
    cfgs = train.resolve_configs(train_args(data=data), "smoke")
    with pytest.raises(ValueError, match=r"walk_0000.npz: key 'state' must be a finite array, has nan at step 7"):
        train.train(cfgs, str(tmp_path / "run"), resume=False)
