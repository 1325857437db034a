"""Reliability (smoke preset): kill -9 and --resume, committed expert weights, partial or mixed data, divergence,
numeric flags, run directories, corrupt files, weights-only checkpoints, and commands that exited 0 doing the wrong
thing (issue 67: another body's agent, abbreviated or idle flags, two table processes, Ctrl-C, SIGTERM, empty files)."""
import glob
import json
import os
import runpy
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
import envs
import evaluate
import experts
import goal_inference
import goal_vae
import imitate
import rundir
import runner
import tables
import train
from tests.fixtures import train_args

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = dict(steps=12, seed_steps=4, batch=8, hidden=8, snapshot_every=6, eval_every=10_000, checkpoint_minutes=0.0, final_episodes=1)
SMOKE_IMITATE = configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"])
# train.py run as a script that SIGKILLs itself while writing its second checkpoint (update 6 of the smoke preset),
# leaving a half-written temporary file, metrics rows past its checkpoint and its lock behind
KILLED_TRAIN = """
import os, runpy, signal, sys
import rundir
saves = []
def dying_write(path, write, original=rundir.atomic_write):
    if path.endswith("checkpoint.pt"):
        saves.append(path)
        if len(saves) == 2:
            with open(f"{path}.{os.getpid()}.tmp", "wb") as f:
                f.write(b"half a checkpoint")
            os.kill(os.getpid(), signal.SIGKILL)
    original(path, write)
rundir.atomic_write = dying_write
sys.argv = ["train.py"] + sys.argv[1:]
runpy.run_path("train.py", run_name="__main__")
"""


def snapshot(folder):
    """{relative path: bytes} of every file under folder."""
    out = {}
    for path in glob.glob(os.path.join(folder, "**", "*"), recursive=True):
        if os.path.isfile(path):
            with open(path, "rb") as f:
                out[os.path.relpath(path, folder)] = f.read()
    return out


def copy_run(smoke_run, tmp_path, data=None):
    """A copy of the smoke run's phase 1 (without the results other tests may have added), reading D_body from `data` if given."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "imitate", "tables.md"))
    if data:
        path = os.path.join(run, "checkpoint.pt")
        ckpt = torch.load(path, weights_only=True)
        ckpt["config"]["train"]["data"] = data
        torch.save(ckpt, path)
    return run


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


# --- 7. every checkpoint loads weights-only; older pickled ones are named and converted ---

def test_every_kind_of_checkpoint_loads_weights_only(smoke_run, tmp_path, monkeypatch):
    committed = glob.glob(os.path.join(experts.EXPERT_DIR, "**", "*.pt"), recursive=True)
    assert len(committed) >= 56
    for path in committed:
        torch.load(path, weights_only=True)
    torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
    monkeypatch.setattr(experts, "EXPERT_DIR", str(tmp_path / "experts"))
    experts.train("walker", ["stand", "walk"], experts.ExpertConfig(**TINY), str(tmp_path / "ckpt"), resume=False)
    written = [str(tmp_path / "ckpt" / "walker.pt"), experts.expert_path("walker", "walk"), experts.expert_path("walker", "walk", 6),
               experts.compact_path("walker", "walk")]
    for path in written:
        torch.load(path, weights_only=True)
    assert isinstance(torch.load(written[0], weights_only=True)["replay"]["obs"], torch.Tensor)


def test_older_pickled_checkpoint_is_named_and_never_unpickled(smoke_run, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    path = os.path.join(run, "checkpoint.pt")
    new = torch.load(path, weights_only=True)
    torch.save(dict(new, rng=rundir.generator(new["rng"]), obs_shape=np.int64(new["obs_shape"])), path)  # the format before
    with pytest.raises(ValueError, match=r"checkpoint.pt holds pickled Python objects .*not loaded: train it again$"):
        checkpoint.load_run(run)
    out = subprocess.run([sys.executable, "train.py", "--upgrade-checkpoint", path], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 2 and "unrecognized arguments: --upgrade-checkpoint" in out.stderr  # gone: nothing unpickles a file
    with open(path, "wb") as f:
        f.write(b"PK\x03\x04 half a zip")
    with pytest.raises(ValueError, match=r"checkpoint.pt: not a readable checkpoint"):
        checkpoint.load_run(run)


@pytest.mark.parametrize("damage, says", [
    (lambda c: c["config"]["wm"].update(deter=32), r"world_model\.cell\.bias_hh is \(48,\) where its config makes \(96,\)"),
    (lambda c: c["config"]["wm"].update(deter=10**6), r"world_model\.cell\.bias_hh is \(48,\) where its config makes \(3000000,\)"),  # checked on the meta device: no 12 TB
    (lambda c: c["models"]["world_model"].update({"encoder.0.weight": torch.zeros(3, 3)}), r"world_model\.encoder\.0\.weight is \(3, 3\)"),
    (lambda c: c["models"].pop("critic"), r"it has no weights of the critic$"),
    (lambda c: c["config"].update(foo={}), r"its config names \['ac', 'cloning', 'dist', 'foo', 'goal', 'train', 'wm'\]"),
    (lambda c: c["config"]["train"].update(preset="huge"), r"its preset 'huge' is not one of smoke, cpu, paper$"),
    (lambda c: c["config"]["wm"].update(deter="x"), r"its config wm\.deter is 'x', not of type int$"),
    (lambda c: c["config"]["wm"].update(deter=-1), r"its config holds --wm-deter -1: must be >= 1$"),
    (lambda c: c["config"]["ac"].update(horizon=0), r"its config holds --ac-horizon 0: must be >= 1$"),
    (lambda c: c["config"]["dist"].update(input="bogus"), r"its config dist\.input is 'bogus', not one of obs, feat$"),
    (lambda c: c["config"]["wm"].update(obs="bogus"), r"its config wm\.obs is 'bogus', not one of state, pixels$"),
    (lambda c: c.update(p_dim=-5), r"its step \d+ or shapes \(observation \d+, action \d+, p -5\) are not counts"),
    (lambda c: c.update(obs_shape="x"), r"its step \d+ or shapes \(observation 'x', action"),
    (lambda c: c.update(step="abc"), r"its step 'abc' or shapes"),
    (lambda c: c.pop("models"), r"it holds no run config and models; delete it or restore it from a copy$"),
    (lambda c: c.update(config=[1, 2]), r"it holds no run config and models"),
])
def test_a_damaged_checkpoint_is_named_before_any_model_is_built(smoke_run, tmp_path, damage, says):
    run = copy_run(smoke_run, tmp_path)
    path = os.path.join(run, "checkpoint.pt")
    ckpt = torch.load(path, weights_only=True)
    damage(ckpt)
    torch.save(ckpt, path)
    with pytest.raises(ValueError, match=r"checkpoint.pt is damaged or not this project's checkpoint: " + says):
        checkpoint.load_run(run)


def test_a_checkpoint_that_is_a_list_is_named(smoke_run, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    torch.save([1, 2, 3], os.path.join(run, "checkpoint.pt"))
    with pytest.raises(ValueError, match=r"checkpoint.pt is damaged or not this project's checkpoint: it holds no run config and models"):
        checkpoint.load_run(run)


def test_fast_matmul_keeps_fp32_results():
    """Whether or not oneDNN takes the fp32 matmuls on this CPU, a layer and its backward stay at fp32's error (a bf16
    route would be ~1e-3)."""
    try:
        rundir.fast_matmul()
        g = torch.Generator().manual_seed(1)
        x, w = torch.randn(16, 50, 230, generator=g, requires_grad=True), torch.randn(256, 230, generator=g)
        out = torch.nn.functional.linear(x[:, 1:], w)  # a sliced 3-D input, as the critic's
        out.sum().backward()
        exact = x.double()[:, 1:] @ w.double().t()
        assert ((out.double() - exact).abs().max() / exact.abs().max()).item() < 1e-5
        assert torch.allclose(x.grad[:, 1:].double(), w.double().sum(0).expand(16, 49, -1), rtol=1e-5, atol=1e-4)
    finally:
        torch.backends.mkldnn.matmul.fp32_precision = "none"


# --- 8. runs that exited 0 and did the wrong thing (issue 67): each ends right or in one line naming the fix ---

def test_a_run_folder_holding_another_agent_is_refused(smoke_run, tmp_path, monkeypatch):
    """agents/<body> and runs/<env>_<obs>_<preset>_s<seed> hold what their names say, an explicit --run the --env given."""
    ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)  # walker, state, smoke preset, seed 0
    os.makedirs(tmp_path / "agents" / "walker")
    torch.save(dict(ckpt, config={**ckpt["config"], "train": {**ckpt["config"]["train"], "env": "stickman"}}), tmp_path / "agents" / "walker" / "checkpoint.pt")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(rundir, "use_threads", lambda threads: None)  # imitate.main would set this process's torch threads
    small = ["--steps", "1", "--seeds", "1", "--eval-episodes", "1", "--eval-steps", "2"]  # should it run
    monkeypatch.setattr(sys, "argv", ["imitate.py", "--demo", "stickman_run", "--finetune"] + small)
    with pytest.raises(ValueError, match=r"^agents/walker/checkpoint.pt holds a stickman agent, but agents/walker is the shipped walker agent's "
                                         r"folder: put the walker agent back \(`git checkout agents/walker/checkpoint.pt`\)"):
        imitate.main()
    os.makedirs(tmp_path / "runs" / "walker_state_cpu_s0")
    shutil.copy(os.path.join(smoke_run, "checkpoint.pt"), tmp_path / "runs" / "walker_state_cpu_s0")
    with pytest.raises(ValueError, match=r"holds the run walker_state_smoke_s0 \(body, observations, preset, seed\), not the walker_state_cpu_s0 "
                                         r"that its folder is named: move the folder to runs/walker_state_smoke_s0$"):
        imitate.main()
    monkeypatch.setattr(sys, "argv", ["imitate.py", "--demo", "stickman_run", "--run", smoke_run, "--env", "stickman", "--eval-steps", "2"])
    with pytest.raises(ValueError, match=r"^--env stickman, but .*checkpoint.pt holds a walker agent: pass --env walker, or a --run of a stickman agent$"):
        imitate.main()
    assert sorted(os.listdir(tmp_path / "agents" / "walker")) == ["checkpoint.pt"] and not glob.glob(str(tmp_path / "runs" / "*" / "*.jsonl"))
    with pytest.raises(ValueError, match="holds a stickman agent"):
        tables.run_table(os.path.join("agents", "walker"), SMOKE_IMITATE)
    with pytest.raises(ValueError, match=r"^--export agents/stickman: .* trained a walker agent; export it to agents/walker$"):
        checkpoint.export_agent(smoke_run, os.path.join("agents", "stickman"))  # how such a folder comes about
    assert not os.path.exists(os.path.join("agents", "stickman"))


def test_a_missing_checkpoint_names_the_command_for_its_body_and_preset(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(rundir, "use_threads", lambda threads: None)
    for run, command in ((os.path.join("runs", "stickman_state_smoke_s0"), "python train.py --env stickman --obs state --preset smoke"),
                         (os.path.join("runs", "walker_pixels_cpu_s2"), "python train.py --env walker --obs pixels --seed 2"),
                         ("elsewhere", "python train.py --env walker --run-dir elsewhere")):
        with pytest.raises(FileNotFoundError, match=rf"^no checkpoint at {run}/checkpoint.pt: train one with `{command}`$"):
            checkpoint.load_run(run)
    monkeypatch.setattr(sys, "argv", ["imitate.py", "--demo", "walker_run", "--preset", "smoke", "--env", "stickman"])
    with pytest.raises(FileNotFoundError, match=r"train one with `python train.py --env stickman --obs state --preset smoke`$"):
        imitate.main()
    assert not os.path.exists("runs/stickman_state_smoke_s0")


PROG = {"experts": "python -m experts"}  # a package's command names itself (its argparse prog)


@pytest.mark.parametrize("script, argv, message", [
    # abbreviations (argparse's prefix matching) are refused by every entry point: today's --he(lp) printed the help
    *[(script, argv + ["--hel"], "unrecognized arguments: --hel") for script, argv in (
        ("train.py", []), ("imitate.py", ["--demo", "walker_run"]), ("collect.py", []), ("experts", []), ("baselines/genrl.py", ["--demo", "walker_run"]),
        ("baselines/aime_nob.py", ["--demo", "walker_run"]), ("evaluate.py", ["runs/x"]), ("tables.py", ["--table", "x"]), ("bench.py", []), ("video_encoder.py", []), ("envs.py", []))],
    ("imitate.py", ["--demo", "walker_run", "--finetune", "--seed", "3", "--threads", "0"], "unrecognized arguments: --seed 3"),
    ("train.py", ["--pres", "smoke", "--steps", "0"], "unrecognized arguments: --pres smoke"),
    # a flag that does nothing in the mode chosen
    ("imitate.py", ["--demo", "stickman_run", "--methods", "genrl"], "unrecognized arguments: --methods genrl"),
    ("tables.py", ["--table", "rows.jsonl", "--shard", "0/2"], "--shard does nothing with --table: drop it"),
    ("tables.py", ["--table", "rows.jsonl", "--steps", "3"], "--steps does nothing with --table: drop it"),
    ("tables.py", ["--run", "runs/x", "--min-seeds", "2"], "--min-seeds does nothing with --run: drop it"),
    ("tables.py", ["--curves", "rows.jsonl", "--budgets", "genrl=1000"], "--budgets does nothing with --curves: drop it"),
    ("imitate.py", ["--demo", "stickman_run", "--seeds", "3"], "--seeds sets GIIL-FT: add --finetune, or drop it"),
    ("train.py", ["--evaluate", "--resume"], "--resume is for training: it does nothing with --export or --evaluate"),
    ("collect.py", ["--features", "--data", "no_data", "--history-from", "0.5"], "--task-episodes and --history-from shape D_body: add --env BODY"),
    ("experts", ["--history"], "--history works with --eval only"),
])
def test_flags_act_by_their_whole_name_and_only_where_they_act(script, argv, message, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [script] + argv)
    with pytest.raises(SystemExit) as exit:
        runpy.run_path(os.path.join(ROOT, script), run_name="__main__")
    assert exit.value.code == 2 and capsys.readouterr().err.splitlines()[-1].startswith(f"{PROG.get(script, os.path.basename(script))}: error: {message}")


def test_a_cell_runs_in_one_process_at_a_time(smoke_run, tmp_path, monkeypatch):
    """Two --table processes without --shard: the second skips the cells the first is running; a --demo run of such a
    cell stops with one line."""
    run = copy_run(smoke_run, tmp_path)
    lock = runner.cell_lock(run, "walker_stand", "side")
    other = subprocess.Popen(["sleep", "60"])
    try:
        os.makedirs(os.path.dirname(lock))
        with open(lock, "w") as f:
            f.write(str(other.pid))
        tables.run_table(run, SMOKE_IMITATE, settings=("SE-SV",), demos_per_cell=2, shard=(0, 4))  # that cell alone
        assert not os.path.exists(os.path.join(run, "results.jsonl")) and open(lock).read() == str(other.pid)
        monkeypatch.setattr(rundir, "use_threads", lambda threads: None)
        monkeypatch.setattr(sys, "argv", ["imitate.py", "--demo", "walker_stand", "--run", run, "--preset", "smoke"])
        with pytest.raises(ValueError, match=rf"^process {other.pid} is running walker_stand \(side view\) on .*run now .*walker_stand_side.lock\): "
                                             r"wait for it to end; the same command then goes on from its rows$"):
            imitate.main()
    finally:
        other.kill()
        other.wait()
    tables.run_table(run, SMOKE_IMITATE, settings=("SE-SV",), demos_per_cell=2, shard=(0, 4))  # its process gone: the lock is stale
    assert len(rundir.read_jsonl(os.path.join(run, "results.jsonl"))) == 2 + 2 * SMOKE_IMITATE.seeds and not os.path.exists(lock)


@pytest.mark.parametrize("name", ["genrl", "aime_nob"])
def test_a_baseline_runs_a_cell_in_one_process_at_a_time(name, smoke_run, tmp_path, monkeypatch, capsys):
    """Two baseline processes on one cell (or a baseline beside imitate.py or a table on it) take the cell's lock that
    imitate.py does: --demo stops in one line, --settings skips the cell; neither trains a seed nor appends a row."""
    from baselines import aime_nob, genrl

    baseline, script = {"genrl": genrl, "aime_nob": aime_nob}[name], f"baselines/{name}.py"
    run = copy_run(smoke_run, tmp_path)
    lock = runner.cell_lock(run, "walker_stand", "side")
    other = subprocess.Popen(["sleep", "60"])
    monkeypatch.setattr(rundir, "use_threads", lambda threads: None)
    try:
        os.makedirs(os.path.dirname(lock))
        with open(lock, "w") as f:
            f.write(str(other.pid))
        monkeypatch.setattr(sys, "argv", [script, "--demo", "walker_stand", "--run", run, "--preset", "smoke"])
        with pytest.raises(ValueError, match=rf"^process {other.pid} is running walker_stand \(side view\) on .*run now .*walker_stand_side.lock\): "
                                             r"wait for it to end; the same command then goes on from its rows$"):
            baseline.main()
        monkeypatch.setattr(sys, "argv", [script, "--settings", "SE-SV", "--shard", "0/4", "--run", run, "--preset", "smoke"])  # that cell alone
        baseline.main()
        assert f"walker_stand (side view): process {other.pid} is running this cell now" in capsys.readouterr().out
        assert not os.path.exists(os.path.join(run, "results.jsonl")) and not os.path.exists(os.path.join(run, "baselines"))
        assert open(lock).read() == str(other.pid)
    finally:
        other.kill()
        other.wait()
    monkeypatch.setattr(sys, "argv", [script, "--demo", "walker_stand", "--run", run, "--preset", "smoke"])
    baseline.main()  # its process gone: the lock is stale, the cell runs and its lock goes
    assert len(rundir.read_jsonl(os.path.join(run, "results.jsonl"))) == configs.PRESETS[name]["smoke"]["seeds"] and not os.path.exists(lock)


def test_paper_preset_needs_a_gpu_or_allow_cpu_and_sigterm_releases_the_lock(smoke_data, tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    flags = ["train.py", "--preset", "paper", "--data", smoke_data, "--run-dir", str(tmp_path / "paper")]
    monkeypatch.setattr(sys, "argv", flags)
    with pytest.raises(ValueError, match=r"^--preset paper is sized for a GPU and this machine has none: .*~6 h on one.*; pass --preset cpu, or --allow-cpu"):
        train.main()
    monkeypatch.setattr(sys, "argv", flags + ["--allow-cpu", "--steps", "0"])
    with pytest.raises(ValueError, match="--steps 0: must be >= 1"):  # past the check
        train.main()
    assert not os.path.exists(tmp_path / "paper")
    # `timeout` sends SIGTERM: the run's finally blocks run (its lock goes), its last checkpoint stays whole
    run = str(tmp_path / "term")
    script = KILLED_TRAIN.replace('''            with open(f"{path}.{os.getpid()}.tmp", "wb") as f:
                f.write(b"half a checkpoint")
            os.kill(os.getpid(), signal.SIGKILL)''', "            os.kill(os.getpid(), signal.SIGTERM)")
    assert script != KILLED_TRAIN
    out = subprocess.run([sys.executable, "-c", script, "--preset", "smoke", "--data", smoke_data, "--run-dir", run], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 130 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert out.stderr.splitlines()[-1] == "interrupted: the run folder keeps its last checkpoint: the same command with --resume goes on from it"
    assert sorted(os.listdir(run)) == ["checkpoint.pt", "metrics.jsonl"] and torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == 3


def test_ctrl_c_then_the_same_imitate_command_goes_on_without_duplicates(smoke_run, tmp_path):
    run = copy_run(smoke_run, tmp_path)
    # Ctrl-C in GIIL-FT seed 0's first update; the sleep holds the call until Python runs the SIGINT handler, which it
    # may otherwise do only after the call returned None and its caller failed on it
    # (Python's own SIGINT handler put back: a shell starts background jobs with SIGINT ignored, and Python keeps that)
    interrupted = ("import os, runpy, signal, sys, time, ot_reward\n"
                   "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
                   "ot_reward.ot_reward = lambda *a, **k: (os.kill(os.getpid(), signal.SIGINT), time.sleep(60))\n"
                   "sys.argv = ['imitate.py'] + sys.argv[1:]\nrunpy.run_path('imitate.py', run_name='__main__')\n")
    flags = ["--demo", "walker_run", "--finetune", "--preset", "smoke", "--run", run]
    out = subprocess.run([sys.executable, "-c", interrupted] + flags, cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 130 and "Traceback" not in out.stderr and "Exception ignored" not in out.stderr, out.stderr[-2000:]
    assert out.stderr.splitlines()[-1] == "interrupted: every evaluation finished is in the run's results.jsonl: the same command goes on from there"
    path = os.path.join(run, "results.jsonl")
    assert [(r["method"], r["seed"]) for r in rundir.read_jsonl(path)] == [("GIIL-ZS", 0), ("GIIL-ZS", 1), ("GIIL-ZS (demo 0)", 0)]
    ic = configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"], preset="smoke")  # what --preset smoke makes
    rows = runner.imitate(run, "walker_run", "side", ic, ["GIIL-FT"])
    assert [(r["method"], r["seed"]) for r in rows] == [("GIIL-FT", 0), ("GIIL-ZS (demo 0)", 1), ("GIIL-FT", 1)]
    assert runner.imitate(run, "walker_run", "side", ic, ["GIIL-FT"]) == [] and len(rundir.read_jsonl(path)) == 6


def test_an_empty_episode_file_is_collected_again(smoke_data, tmp_path):
    data = str(tmp_path / "data")
    for view in ("side", "diagonal"):
        shutil.copytree(os.path.join(smoke_data, "demos", f"walker_run_{view}"), os.path.join(data, "demos", f"walker_run_{view}"))
    path = os.path.join(data, "demos", "walker_run_side", "01.npz")
    before = dict(np.load(path))
    open(path, "wb").close()  # zero bytes: a disk that was full, a copy cut off
    collect.collect_demos(configs.CollectConfig(**configs.PRESETS["collect"]["smoke"]), data, workers=1, demos=[("walker", "run")])
    after = dict(np.load(path))
    assert all(np.array_equal(after[k], before[k]) for k in ("state", "action", "pixels")) and np.allclose(after["p"], before["p"], atol=1e-5)
    assert sorted(os.listdir(os.path.dirname(path))) == ["00.npz", "01.npz"]


def cut_writer(writer, frames, killed):
    """cv2.VideoWriter that writes `frames` frames, then raises (a kill) or writes nothing more (a full disk, unreported)."""

    class Cut:
        def __init__(self, *args):
            self.writer, self.frames = writer(*args), 0

        def __getattr__(self, name):
            return getattr(self.writer, name)

        def write(self, frame):
            self.frames += 1
            if self.frames > frames and killed:
                raise RuntimeError("killed")
            if self.frames <= frames:
                self.writer.write(frame)

    return Cut


def test_a_video_cut_off_half_way_leaves_the_old_file(tmp_path, monkeypatch):
    path = str(tmp_path / "walker_run_side_GIIL-FT_s0.mp4")
    with open(path, "wb") as f:
        f.write(b"the video of an earlier run")
    frames = np.zeros((6, 64, 64, 3), np.uint8)
    writer = evaluate.cv2.VideoWriter
    monkeypatch.setattr(evaluate.cv2, "VideoWriter", cut_writer(writer, 2, killed=True))  # killed after its second frame
    with pytest.raises(RuntimeError, match="killed"):
        evaluate.write_video(path, frames, frames)
    assert open(path, "rb").read() == b"the video of an earlier run" and os.listdir(tmp_path) == [os.path.basename(path)]
    monkeypatch.setattr(evaluate.cv2, "VideoWriter", writer)
    evaluate.write_video(path, frames, frames)
    assert open(path, "rb").read(12)[4:8] == b"ftyp" and os.listdir(tmp_path) == [os.path.basename(path)]


def test_a_video_that_does_not_reopen_whole_keeps_the_old_file(tmp_path, monkeypatch):
    """A full disk: cv2 drops frames without a word; the video is reopened and counted before it replaces anything."""
    path = str(tmp_path / "walker_run_side_GIIL-FT_s0.mp4")
    with open(path, "wb") as f:
        f.write(b"the video of an earlier run")
    monkeypatch.setattr(evaluate.cv2, "VideoWriter", cut_writer(evaluate.cv2.VideoWriter, 2, killed=False))  # then silent
    with pytest.raises(OSError, match=r"walker_run_side_GIIL-FT_s0.mp4: the video reopened with 2 of its 6 frames \(disk full\?\)"):
        evaluate.write_video(path, np.zeros((6, 64, 64, 3), np.uint8), np.zeros((6, 64, 64, 3), np.uint8))
    assert open(path, "rb").read() == b"the video of an earlier run" and os.listdir(tmp_path) == [os.path.basename(path)]


def test_nothing_is_written_through_a_link_in_a_run_folder(tmp_path):
    """A run folder from elsewhere whose results.jsonl or imitate/ is a link: refused before anything is written."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "rows.jsonl").write_text('{"a": 1}\n{"cut')
    run = tmp_path / "run"
    run.mkdir()
    os.symlink(outside / "rows.jsonl", run / "results.jsonl")
    os.symlink(outside, run / "imitate")
    with pytest.raises(ValueError, match=r"results.jsonl is a symbolic link \(to .*rows.jsonl\): nothing is written through a link; remove it"):
        rundir.append_jsonl(str(run / "results.jsonl"), {"b": 2})
    with pytest.raises(ValueError, match=r"imitate is a symbolic link"):
        runner.cell_lock(str(run), "walker_run", "side")
    with pytest.raises(ValueError, match=r"results.jsonl is a symbolic link"):
        rundir.atomic_write(str(run / "results.jsonl"), lambda f: f.write(b"{}"))
    assert (outside / "rows.jsonl").read_text() == '{"a": 1}\n{"cut' and os.listdir(outside) == ["rows.jsonl"]
    # a folder a file is written into that is a link: a run's baselines/ states, a demo folder of the data
    os.symlink(outside, run / "baselines")
    with pytest.raises(ValueError, match=r"run/baselines is a symbolic link \(to .*outside\): nothing is written through a link"):
        rundir.atomic_write(str(run / "baselines" / "state.pt"), lambda f: f.write(b"{}"))
    os.makedirs(tmp_path / "data" / "demos")
    os.symlink(outside, tmp_path / "data" / "demos" / "stickman_walk_side")
    with pytest.raises(ValueError, match=r"stickman_walk_side is a symbolic link"):
        rundir.atomic_write(str(tmp_path / "data" / "demos" / "stickman_walk_side" / "00.npz"), lambda f: f.write(b"x"))
    assert os.listdir(outside) == ["rows.jsonl"]


def test_a_temporary_file_is_never_a_link_planted_at_a_predictable_name(tmp_path):
    """Links planted at the names a writer's pid would give its temporary files (<file>.<pid>.tmp and the like): the
    write makes its own file (O_EXCL, a name no one can guess), the link's target is untouched, and the file written is
    a plain file with the permissions open() gives."""
    outside = tmp_path / "outside.txt"
    outside.write_text("kept")
    run = tmp_path / "run"
    run.mkdir()
    for pid in range(os.getpid(), os.getpid() + 50):
        for name in (f"goal_reaching.json.{pid}.tmp", f"goal_reaching.json.{pid}.tmp.json"):
            os.symlink(outside, run / name)
    for by_name in (False, True):
        write = (lambda name: open(name, "w").write("{}")) if by_name else (lambda f: f.write(b"{}"))
        rundir.atomic_write(str(run / "goal_reaching.json"), write, by_name=by_name)
        assert outside.read_text() == "kept" and not os.path.islink(run / "goal_reaching.json")
        assert (run / "goal_reaching.json").read_text() == "{}"
    assert oct(os.stat(run / "goal_reaching.json").st_mode & 0o777) == oct(0o666 & ~rundir.UMASK)
    left = [n for n in os.listdir(run) if n != "goal_reaching.json"]  # planted links (those of dead pids cleared as leftovers)
    assert all(os.path.islink(run / n) for n in left)  # no temporary file of ours left


def test_a_plot_is_never_written_through_a_link(smoke_run, tmp_path):
    """learning_curve.png planted as a link in a run folder (train.py --resume redraws it): refused in one line, the
    link's target untouched; GIIL-online's and the fidelity plots go through the same atomic write."""
    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    outside = tmp_path / "outside.png"
    outside.write_bytes(b"kept")
    os.remove(run / "learning_curve.png")
    os.symlink(outside, run / "learning_curve.png")
    with pytest.raises(ValueError, match=r"learning_curve.png is a symbolic link \(to .*outside.png\): nothing is written through a link"):
        evaluate.learning_curve(str(run))
    assert outside.read_bytes() == b"kept"
    os.remove(run / "learning_curve.png")
    assert evaluate.learning_curve(str(run)) == str(run / "learning_curve.png") and (run / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"


def test_a_results_line_that_is_no_row_is_named(tmp_path):
    """results.jsonl lines {}, [1, 2], "x" or NaN: one line naming the file and the line, not a KeyError under imitate."""
    good = json.dumps(dict(demo="walker_run", view="side", method="GIIL-ZS", seed=0, score=1.0)) + "\n"
    for bad in ("{}", "[1, 2]", '"x"', "NaN"):
        (tmp_path / "results.jsonl").write_text(good + bad + "\n" + good)
        with pytest.raises(ValueError, match=r"results.jsonl: line 2 is not a result row \(.*\): remove that line, or move the file aside"):
            runner.load_results(str(tmp_path))
    (tmp_path / "results.jsonl").write_text(good + good)
    assert len(runner.load_results(str(tmp_path))) == 1


def test_a_d_body_with_deleted_episodes_is_named_where_it_is_read_without_collecting(smoke_run, smoke_data, tmp_path):
    """2 D_body episodes deleted: the baselines' segments (checkpoint.body_segments) and fidelity.py's held-out episodes
    are refused in one line naming the collect command, instead of training or measuring on what is left."""
    import fidelity

    data = tmp_path / "data"
    shutil.copytree(smoke_data, data)
    cfgs = checkpoint.load_run(copy_run(smoke_run, tmp_path, str(data)))[0]
    gone = sorted(n for n in os.listdir(data / "walker") if n.endswith(".npz"))[:2]
    for name in gone:
        os.remove(data / "walker" / name)
    listed = len(json.load(open(data / "walker" / collect.COMPLETE))["episodes"])
    match = rf"D_body at .*walker lacks 2 of the {listed} episodes its collection.json lists \({gone[0]}, ...\): collect them again \(python collect.py --env walker --data .*data --preset smoke\)"
    with pytest.raises(ValueError, match=match):
        checkpoint.body_segments(cfgs)
    with pytest.raises(ValueError, match=match):
        fidelity.held_out_episodes(cfgs)


def test_a_full_disk_names_the_file_it_was_writing(tmp_path):
    """A write that fails inside the file object (torch.save, json on a full disk: an OSError without a file name) ends in
    one line naming the file and what is kept, and leaves no temporary file."""
    import errno

    path = str(tmp_path / "goal_reaching.json")

    def full(f):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(SystemExit, match=rf"^error: No space left on device: {path} \(the old file is kept\)$"):
        rundir.run_main(lambda: rundir.atomic_write(path, full), "the old file is kept")
    assert os.listdir(tmp_path) == []


def test_the_shipped_agents_results_go_to_runs_not_into_its_folder(smoke_run, tmp_path, monkeypatch):
    """Phase 2 on agents/<body> writes to runs/agent_<body> (its checkpoint a link to the agent's); agents/ keeps the weights only."""
    monkeypatch.chdir(tmp_path)
    os.makedirs("agents/walker")
    shutil.copy(os.path.join(smoke_run, "checkpoint.pt"), "agents/walker/checkpoint.pt")
    work = checkpoint.work_folder("agents/walker")
    assert work == os.path.join("runs", "agent_walker") and os.path.realpath(os.path.join(work, "checkpoint.pt")) == str(tmp_path / "agents/walker/checkpoint.pt")
    rows = runner.imitate(work, "walker_run", "side", SMOKE_IMITATE, [])
    assert rows and all(r["weights"] == rundir.weights_id(rundir.run_checkpoint("agents/walker")) for r in rows)
    assert os.listdir("agents/walker") == ["checkpoint.pt"] and sorted(os.listdir(work)) == ["checkpoint.pt", "imitate", "results.jsonl"]
    assert checkpoint.work_folder("agents/walker") == work and checkpoint.work_folder(smoke_run) == smoke_run  # again; a run of one's own
    assert rundir.work_path("agents/walker/") == work  # where evaluate.py reads the agent's goal_reaching.json
    os.remove(os.path.join(work, "checkpoint.pt"))
    shutil.copy("agents/walker/checkpoint.pt", os.path.join(work, "checkpoint.pt"))
    with pytest.raises(ValueError, match=r"runs/agent_walker/checkpoint.pt is a checkpoint of its own: move that run elsewhere"):
        checkpoint.work_folder("agents/walker")


def test_an_expert_file_of_another_task_is_refused(tmp_path, monkeypatch):
    """experts/walker_run.pt replaced by the walk expert: demos labelled run are not collected from it."""
    os.makedirs(tmp_path / "experts")
    shutil.copy(experts.expert_path("walker", "walk"), tmp_path / "experts" / "walker_run.pt")
    monkeypatch.setattr(experts, "expert_path", lambda body, task, step=None: str(tmp_path / "experts" / f"{body}_{task}.pt"))
    with pytest.raises(ValueError, match=r"walker_run.pt holds the expert of walker walk at step .*, not walker run: put the right file back"):
        experts.load_expert("walker", "run")


def test_a_full_disk_or_a_path_that_cannot_be_written_ends_in_one_line_naming_it(tmp_path):
    def full():
        raise OSError(28, "No space left on device", "runs/x/checkpoint.pt.123.tmp")

    with pytest.raises(SystemExit, match=r"^error: No space left on device: runs/x/checkpoint.pt.123.tmp \(the older checkpoint is kept\)$"):
        rundir.run_main(full, "the older checkpoint is kept")
    (tmp_path / "a_file").write_text("")
    out = subprocess.run([sys.executable, "train.py", "--preset", "smoke", "--run-dir", str(tmp_path / "a_file")], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.strip().startswith(f"error: File exists: {tmp_path / 'a_file'}"), out.stderr[-500:]


def test_rows_and_records_that_are_not_what_they_should_be_are_named(smoke_run, smoke_data, tmp_path):
    for text in ("[1, 2]\n", '{"demo": "walker_run"}\n'):
        (tmp_path / "rows.jsonl").write_text(text)
        with pytest.raises(ValueError, match=r"rows.jsonl: row 1 is not a result row \(a dict with agent, demo, view, method, seed, score\)"):
            tables.merge_files([str(tmp_path / "rows.jsonl")])
    run = copy_run(smoke_run, tmp_path)
    out = subprocess.run([sys.executable, "train.py", "--evaluate", "--run-dir", run, "--data", smoke_data, "--eval-steps", "5", "--eval-episodes", "1"],
                         cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    path = os.path.join(run, "goal_reaching.json")
    with open(path, "r+") as f:
        f.truncate(40)
    with pytest.raises(ValueError, match=r"goal_reaching.json is cut or damaged \(not JSON\): run `python train.py --evaluate --run-dir .*` again$"):
        evaluate.read_goal_reaching(run)
    metrics = os.path.join(run, "metrics.jsonl")
    lines = open(metrics).read().split("\n")
    with open(metrics, "w") as f:
        f.write("\n".join([lines[0][:30]] + lines[1:]))  # a cut row before the last
    with pytest.raises(ValueError, match=r"metrics.jsonl: line 1 is not a JSON row .*; delete that line$"):
        evaluate.learning_curve(run)


def test_unusable_command_lines_stop_before_any_work():
    cases = [(["bench.py", "--only", "components", "--against", "HEAD"], "--against times phase1, finetune, collect, baselines only"),
             (["bench.py", "--only", "phase1", "--against", "nosuchrev"], "--against nosuchrev: not a commit of this repository"),
             (["tables.py", "--curves", "docs/results/curves_walker.jsonl", "--min-seeds", "-3"], "--min-seeds -3: must be >= 1")]
    for argv, says in cases:
        out = subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and says in out.stderr, (argv, out.stderr[-500:])
    # a GL backend MuJoCo cannot load (OSMesa, not installed here, fails the same way; glx is no backend anywhere)
    out = subprocess.run([sys.executable, "-c", "import envs"], cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "glx"})
    assert out.returncode == 1 and out.stderr.startswith("error: MuJoCo does not load with MUJOCO_GL=glx") and "Traceback" not in out.stderr


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
