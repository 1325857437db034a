"""python -m experts --body walker [--tasks ...] [--resume] | --eval: the per-task SAC experts (experts/__init__.py)."""
import rundir
from experts import main

rundir.run_main(main, "the last training state is in --ckpt-dir: the same command with --resume goes on from it")
