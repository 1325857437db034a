"""bench.py's comparison against a git commit: both source trees measured in one run, the ratio the right way up."""
import os

import pytest

import bench

HERE = os.path.dirname(os.path.abspath(bench.__file__))


def test_against_a_commit_measures_both_trees(capsys):
    """Each measure runs once per tree and round; 'speed-up' is old / new for seconds and new / old for rates; the
    commit's tree (git archive, no .git) is removed afterwards."""
    seen = []

    def seconds(tree):
        seen.append(tree)
        return 2.0 if tree == HERE else 4.0

    bench.against("HEAD", {"update": ("s", False, seconds), "rate": ("updates/s", True, lambda tree: 3.0 if tree == HERE else 1.5)}, rounds=2)
    assert capsys.readouterr().out.splitlines() == ["update: HEAD 4 s | this tree 2 s | speed-up 2.00x",
                                                    "rate: HEAD 1.5 updates/s | this tree 3 updates/s | speed-up 2.00x"]
    old = {t for t in seen if t != HERE}
    assert len(seen) == 4 and len(old) == 1 and not os.path.exists(old.pop())


def test_a_script_that_fails_names_its_tree():
    with pytest.raises(RuntimeError, match=r"bench.py in /: ValueError: no such run"):
        bench.in_tree("/", "raise ValueError('no such run')")
