"""Reliability (smoke preset), issue 67 continued: empty, cut, linked, unwritable or mislabelled files and unusable command lines end right or in one line naming them."""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import checkpoint
import collect
import configs
import evaluate
import experts
import rundir
import runner
import tables
from tests.reliability_helpers import ROOT, SMOKE_IMITATE, copy_run


# --- 8. (continued from test_reliability_checkpoints.py) runs that exited 0 and did the wrong thing (issue 67): each ends right or in one line naming the fix ---

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
