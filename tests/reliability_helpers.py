"""Helpers shared by tests/test_reliability*.py: the repository root, tiny configs, a self-killing train.py, folder snapshots and run copies."""
import glob
import os
import shutil

import torch

import configs

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

