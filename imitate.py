"""Phase 2 on one demo folder (Eq. 1, upper level): GIIL-ZS on each demo, and the goal searches flagged (GIIL-FT,
GIIL-online, GIIL-retrieve); the method is goal_inference.py, its harness runner.py, every cell of the tables tables.py.

    python imitate.py --demo stickman_run [--view side|diagonal] [--run runs/<name> | --env walker|stickman] [--preset P] [--finetune] [--online] [--retrieve]
"""
import argparse

import checkpoint
import envs
import rundir
import runner
from goal_inference import FINETUNE_FIELDS, SEARCHES
from runner import config_flags, imitate, parse_config, parse_online


def main():
    parser = argparse.ArgumentParser(description="Phase 2 on one demo folder: GIIL-ZS, and the goal searches flagged (every cell: "
                                     "tables.py).", allow_abbrev=False)
    parser.add_argument("--demo", required=True, help="<demonstrator body>_<task>, e.g. stickman_run")
    parser.add_argument("--view", choices=envs.VIEWS, default="side", help="camera of the demo (default side)")
    parser.add_argument("--run", help="the phase-1 run (train.py) whose agent imitates (default: the --env agent's run of this --preset, "
                        "runs/<env>_<obs>_<preset>_s0, or else the shipped agents/<env>)")
    parser.add_argument("--env", choices=envs.BODIES, help="the agent's body, to pick the default --run (default walker); with --run, checked against its agent")
    for method, s in SEARCHES.items():  # --finetune, --online, --retrieve
        parser.add_argument("--" + s.flag, action="store_true", help=f"also {method}: {s.search.__doc__}")
    rundir.threads_flag(parser)
    config_flags(parser)
    args = parser.parse_args()
    rundir.use_threads(args.threads)
    ic, given = parse_config(args)
    if not args.finetune and any(f in given for f in FINETUNE_FIELDS):
        parser.error(f"--{[f for f in FINETUNE_FIELDS if f in given][0].replace('_', '-')} sets GIIL-FT: add --finetune, or drop it")
    oc, online_given = parse_online(args, ic.preset)
    if online_given and not args.online:
        parser.error(f"--online-{next(iter(online_given)).replace('_', '-')} sets GIIL-online: add --online, or drop it")
    run = args.run or checkpoint.resolve_run(args.env or "walker", ic.preset)
    # before anything runs: the run's agent is the body --env names (with --run) and what its folder's name says
    rundir.run_checkpoint(run, env=args.env)
    run = checkpoint.work_folder(run)
    with runner.running_cell(run, args.demo, args.view):  # as a tables.py cell: one process at a time
        imitate(run, args.demo, args.view, ic, [m for m, s in SEARCHES.items() if getattr(args, s.flag)], oc)


if __name__ == "__main__":
    rundir.run_main(main, "every evaluation finished is in the run's results.jsonl: the same command goes on from there")
