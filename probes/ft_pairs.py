"""Phase 2's pairing: two GIIL-FT (or GIIL-online) variants of one agent, cell by cell and seed by seed, each against GIIL-ZS (demo 0).

Two GIIL-FT variants of one agent, paired cell by cell and seed by seed (docs/ablations.md, Phase 2): run A's
GIIL-FT rows against run B's, and each against run A's GIIL-ZS (demo 0), the goal both start from. GIIL-FT seed s is
evaluated on the same environment seeds in every run of an agent, so the differences are paired. Each (demo, view,
seed) takes the run's last GIIL-FT row (a folder that holds rows of earlier settings too reads its latest). Run from
the repository root, e.g. joint finetuning of psi (run A) against psi frozen (run B):

    python probes/ft_pairs.py runs/walker_psi agents/walker
    python probes/ft_pairs.py docs/results/online50_cem_walker.jsonl docs/results/online50_walker.jsonl --method GIIL-online

A run folder stands for its results.jsonl; a .jsonl file is read as it is.
"""
import argparse
import collections
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import evaluate  # noqa: E402
import rundir  # noqa: E402


def last_rows(run_dir, method):
    """{(demo, view, seed): row} of `method`, the last row of each."""
    rows = rundir.read_jsonl(run_dir if run_dir.endswith(".jsonl") else os.path.join(run_dir, "results.jsonl"))
    return {(r["demo"], r["view"], r["seed"]): r for r in rows if r["method"] == method}


def pairs(run_a, run_b, method="GIIL-FT"):
    """[(row of A, score of B, score of A's GIIL-ZS (demo 0))] over the (demo, view, seed) both runs have with other
    settings (a row A copied from B, its variant not run yet, is no pair)."""
    a, b, zs0 = last_rows(run_a, method), last_rows(run_b, method), last_rows(run_a, "GIIL-ZS (demo 0)")
    return [(a[k], b[k]["score"], zs0[k]["score"]) for k in sorted(a) if k in b and k in zs0 and a[k]["config"] != b[k]["config"]]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_a")
    parser.add_argument("run_b")
    parser.add_argument("--method", default="GIIL-FT", choices=("GIIL-FT", "GIIL-online"))
    args = parser.parse_args()
    groups = collections.defaultdict(list)
    for row, b, zs0 in pairs(args.run_a, args.run_b, args.method):
        same_body = row["setting"].startswith("SE")
        for key in (row["setting"], f"{row['task']}, {'SE' if same_body else 'CE'}", "SE-SV + SE-CV" if same_body else "CE-SV + CE-CV"):
            groups[key].append((row["score"], b, zs0))
    cell = lambda x: f"{np.mean(x):.1f} +- {evaluate.stderr(x):.1f}"
    print(f"| A: {args.run_a}, B: {args.run_b} | pairs | A | B | A - B | A - ZS (demo 0) |\n|---|---|---|---|---|---|")
    for key in sorted(groups, key=lambda k: (len(k.split()) != 1, "," in k, k)):
        a, b, zs0 = np.array(groups[key]).T
        print(f"| {key} | {len(a)} | {cell(a)} | {cell(b)} | {cell(a - b)} | {cell(a - zs0)} |")


if __name__ == "__main__":
    main()
