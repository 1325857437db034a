"""Reliability (smoke preset): weights-only and damaged checkpoints, then issue 67's wrong agents, missing checkpoints, abbreviated or idle flags, cell locks, Ctrl-C and SIGTERM."""
import glob
import os
import runpy
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
import configs
import experts
import imitate
import rundir
import runner
import tables
import train
from tests.reliability_helpers import KILLED_TRAIN, ROOT, SMOKE_IMITATE, TINY, copy_run


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
