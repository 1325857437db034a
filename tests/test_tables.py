"""tables.py: the table keeps finished cells and reruns only what changed (other demos, other settings)."""
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import numpy as np

import configs
import runner
import tables

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SMOKE = configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"])


def test_table_keeps_finished_cells(smoke_run, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    tables.run_table(run, SMOKE, demos_per_cell=2)
    lines = open(os.path.join(run, "results.jsonl")).read().splitlines()
    text = open(os.path.join(run, "tables.md")).read()
    assert text.count("| SE-SV |") == 5 and "| CE-CV |" in text  # Table 1/2 shape, then one per task
    tables.run_table(run, SMOKE, demos_per_cell=2)  # nothing missing: nothing runs again
    assert open(os.path.join(run, "results.jsonl")).read().splitlines() == lines
    # cells cut off after their first demo / seed: only the missing evaluations run, each once
    cut = {("walker_walk", "side", "GIIL-ZS", 1), ("stickman_run", "diagonal", "GIIL-FT", 1)}
    kept = [line for line in lines if tuple(json.loads(line)[k] for k in ("demo", "view", "method", "seed")) not in cut]
    assert len(kept) == len(lines) - 2
    with open(os.path.join(run, "results.jsonl"), "w") as f:
        f.write("".join(line + "\n" for line in kept))
    tables.run_table(run, SMOKE, demos_per_cell=2)
    lines = open(os.path.join(run, "results.jsonl")).read().splitlines()
    assert {tuple(json.loads(line)[k] for k in ("demo", "view", "method", "seed")) for line in lines[len(kept):]} == cut
    assert len(lines) == len(kept) + 2
    # rows made with other demos (D_demo regenerated since) do not count: only that cell runs again
    rows = [json.loads(line) for line in lines]
    for r in rows:
        if r["demo"] == "walker_stand" and r["view"] == "side":
            r["demo_returns"] = [0.0] * len(r["demo_returns"])
    with open(os.path.join(run, "results.jsonl"), "w") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows))
    tables.run_table(run, SMOKE, demos_per_cell=2)
    new = [json.loads(line) for line in open(os.path.join(run, "results.jsonl")).read().splitlines()[len(lines):]]
    assert {(r["demo"], r["view"]) for r in new} == {("walker_stand", "side")} and len(new) == 2 + 2 * SMOKE.seeds
    # other finetuning settings: the GIIL-FT cells run again, no zero-shot cell does; only in the settings asked for
    before = len(open(os.path.join(run, "results.jsonl")).read().splitlines())
    tables.run_table(run, dataclasses.replace(SMOKE, goal_lr=1e-4), settings=("CE-CV",), demos_per_cell=2)
    new = [json.loads(line) for line in open(os.path.join(run, "results.jsonl")).read().splitlines()[before:]]
    assert {(r["method"], r["setting"]) for r in new} == {("GIIL-FT", "CE-CV")} and len(new) == 4 * SMOKE.seeds
    text = open(os.path.join(run, "tables.md")).read()
    assert "| SE-SV | " in text and "| SE-SV | - |" not in text  # the zero-shot cells still fill the other settings


def test_the_zero_shot_columns_depend_on_the_evaluation_alone():
    """A GIIL-ZS row's config is the evaluation's (episodes and steps); GIIL-FT's adds the finetuning's, not the seeds."""
    oc = configs.OnlineConfig()
    assert runner.result_config(SMOKE, "GIIL-ZS", oc) == {"eval_episodes": SMOKE.eval_episodes, "eval_steps": SMOKE.eval_steps}
    assert "seeds" not in runner.result_config(SMOKE, "GIIL-FT", oc) and runner.result_config(SMOKE, "GIIL-FT", oc)["goal_lr"] == SMOKE.goal_lr


def test_shards_together_make_the_whole_table_once(smoke_run, tmp_path, monkeypatch):
    """Shards 1/3 and 2/3 finish while shard 0/3 works on its last cell (15: jump, CE-CV): shard 0's tables.md, the
    last written, shows their cells too."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))
    real, others_ran = runner.imitate, []

    def others_finish_meanwhile(run_dir, demo, view, *args, **kwargs):
        if (demo, view) == ("stickman_jump", "diagonal") and not others_ran:
            others_ran.append(len({(r["demo"], r["view"]) for r in runner.load_results(run)}))
            for i in (1, 2):
                tables.run_table(run, SMOKE, demos_per_cell=2, shard=(i, 3))
        return real(run_dir, demo, view, *args, **kwargs)

    monkeypatch.setattr(runner, "imitate", others_finish_meanwhile)
    tables.run_table(run, SMOKE, demos_per_cell=2, shard=(0, 3))
    assert others_ran == [5]  # cells 0, 3, ..., 12 of shard 0 were done when the others ran
    rows = [json.loads(line) for line in open(os.path.join(run, "results.jsonl"))]
    keys = [(r["demo"], r["view"], r["method"], r["seed"]) for r in rows]
    assert len(keys) == len(set(keys)) == 16 * (2 + 2 * SMOKE.seeds)  # every cell once, nothing twice
    assert "| - |" not in open(os.path.join(run, "tables.md")).read()  # every cell of every table filled


def test_shards_split_the_settings_asked_for(smoke_run, tmp_path, monkeypatch):
    """--settings SE-CV,CE-CV --shard i/2: each shard runs half of those 8 cells, none of another setting."""
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))
    first, second = [], []
    for i, ran in enumerate((first, second)):
        monkeypatch.setattr(runner, "imitate", lambda run_dir, demo, view, *args, **kwargs: ran.append((demo, view)))
        tables.run_table(run, SMOKE, settings=("SE-CV", "CE-CV"), demos_per_cell=2, shard=(i, 2))
    assert len(first) == len(second) == 4 and len(set(first + second)) == 8
    assert {view for _, view in first + second} == {"diagonal"}  # SE-CV and CE-CV are the diagonal view's settings


def test_baselines_join_the_table_as_columns_and_are_not_rerun(smoke_run, tmp_path):
    """--methods finetune,genrl,aime-nob: each cell asked for gets the baselines' seeds, the tables show
    their columns beside the paper's, and a second call runs nothing; an unknown method is a one-line error."""
    import pytest

    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl"))
    smoke = dataclasses.replace(SMOKE, preset="smoke")  # the baselines' smoke presets too
    one_cell = dict(demos_per_cell=2, shard=(0, 16))  # cell 0: stand, SE-SV
    tables.run_table(run, smoke, methods=("genrl", "aime-nob"), **one_cell)
    rows = runner.load_results(run)
    seeds = {m: configs.PRESETS["genrl"]["smoke"]["seeds"] if m == "GenRL" else configs.PRESETS["aime_nob"]["smoke"]["seeds"] for m in ("GenRL", "AIME-NoB")}
    assert {r["method"] for r in rows} == {"GenRL", "AIME-NoB"} and {(r["task"], r["setting"]) for r in rows} == {("stand", "SE-SV")}
    assert len(rows) == sum(seeds.values())  # each baseline's seeds, no GIIL (not asked for)
    text = open(os.path.join(run, "tables.md")).read()
    assert "| GenRL (ours) | AIME-NoB (ours) | FT - ZS (demo 0), paired | GIIL-ZS (paper) | GIIL-FT (paper) | GenRL (paper) | AIME-NoB (paper) |" in text
    assert "| SE-SV | - | - | - | " in text and "| - | 42.52 | 68.10 | 86.05 | 84.80 |" in text  # GIIL not run; the paper's walker Table 1
    tables.run_table(run, smoke, methods=("genrl", "aime-nob"), **one_cell)
    assert len(runner.load_results(run)) == len(rows)  # nothing missing: nothing runs again
    tables.run_table(run, smoke, methods=("finetune",), **one_cell)
    assert {r["method"] for r in runner.load_results(run)[len(rows):]} == {"GIIL-ZS", "GIIL-ZS (demo 0)", "GIIL-FT"}
    assert "| GenRL (ours) | AIME-NoB (ours) |" in open(os.path.join(run, "tables.md")).read()  # the baselines' cells stay
    with pytest.raises(ValueError, match="--methods dreamer: choose from finetune, online, retrieve, genrl, aime-nob"):
        tables.run_table(run, SMOKE, methods=("finetune", "dreamer"))
    # --budgets: GenRL's column at 2 updates, its 3-update rows (the preset's) no longer shown, then run again at 2
    genrl_rows = len([r for r in runner.load_results(run) if r["method"] == "GenRL"])
    tables.run_table(run, smoke, methods=("genrl",), budgets=tables.parse_budgets("genrl=2"), **one_cell)
    at_two = [r for r in runner.load_results(run) if r["method"] == "GenRL"][genrl_rows:]
    assert [r["config"]["steps"] for r in at_two] == [2] * seeds["GenRL"]
    with pytest.raises(ValueError, match=r"--budgets dreamer=\.\.\.: choose from genrl, aime-nob"):
        tables.parse_budgets("dreamer=5")
    with pytest.raises(ValueError, match=r"--budgets genrl=5,genrl=7: genrl is given twice; pass one budget per baseline"):
        tables.parse_budgets("genrl=5,genrl=7")


def test_finetuning_gain_is_paired_by_cell_and_seed():
    """FT - ZS (demo 0) pairs the rows of one cell and seed; a seed without its partner, or another cell's, is left out."""
    row = lambda method, seed, score, task="walk", setting="CE-SV": dict(method=method, seed=seed, score=score, task=task, setting=setting,
                                                                         demo=f"stickman_{task}", view="side")
    rows = [row("GIIL-FT", 0, 50.0), row("GIIL-ZS (demo 0)", 0, 40.0), row("GIIL-FT", 1, 60.0), row("GIIL-ZS (demo 0)", 1, 40.0),
            row("GIIL-FT", 2, 90.0),  # no ZS (demo 0) partner
            row("GIIL-FT", 0, 10.0, task="run"), row("GIIL-ZS (demo 0)", 0, 30.0, task="run")]
    text = tables.markdown_tables("walker", rows)
    walk = text.split("### walker agent, walk")[1].split("###")[0]
    assert "| CE-SV | - | 40.0 +- 0.0 | 66.7 +- 12.0 | 15.0 +- 5.0 | 12.68 | 92.11 |" in walk
    assert "| CE-SV | - | 36.7 +- 3.3 | 52.5 +- 16.5 | 3.3 +- 12.0 | " in text.split("###")[1]  # all tasks: +10, +20, -20


def _row(method, demo, seed, score, seconds, setting="SE-SV", **config):
    return {"agent": "walker", "demo": demo, "view": "side", "task": demo.split("_")[1], "setting": setting, "method": method, "seed": seed,
            "score": score, "time": seconds, "demo_returns": [1.0], "config": config}


def test_curves_average_the_same_cells_at_every_budget(tmp_path):
    """A budget is shown only where every cell of the smallest budget has its seeds: the walk cell's 4000 (2 seeds) is
    left out rather than averaging another set of cells."""
    rows = [_row("GenRL", d, s, score, 60 * b / 1000, steps=b) for d, base in (("walker_walk", 10), ("walker_run", 30))
            for b, score in ((1000, base), (2000, base + 10)) for s in range(3)]
    rows += [_row("GenRL", "walker_run", s, 0.0, 240, steps=4000) for s in range(3)] + [_row("GenRL", "walker_walk", s, 0.0, 240, steps=4000) for s in range(2)]
    rows += [_row("GIIL-ZS", "walker_walk", k, 50.0 + k, 6) for k in range(10)] + [_row("GenRL", "walker_stand", 0, 99.0, 60, steps=1000)]
    line, cells = tables.curve(tables.curve_points(rows, ["SE-SV"])["GenRL"], 3)
    assert cells == {("walker_walk", "side"), ("walker_run", "side")}
    assert [(b, np.mean(s), np.mean(t)) for b, s, t in line] == [(1000, 20.0, 60.0), (2000, 30.0, 120.0)]
    text = tables.markdown_curves("walker", rows, ["SE-SV"])
    assert "| GenRL | 2000 updates | 30.0 +- 4.5 | - / 20.0 / 40.0 / - | 2 x 3 | 2.0 | 86.0 |" in text and "4000" not in text
    assert "| GIIL-ZS | - | 54.5 +- 1.0 | - / 54.5 / - / - | 1 x 10 | 0.1 | 42.5 |" in text
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    png = tmp_path / "curves.png"
    out = subprocess.run([sys.executable, "tables.py", "--curves", str(path), str(path), "--settings", "SE-SV", "--png", str(png)],
                         cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0 and "| GenRL | 1000 updates | 20.0 +- 4.5 | - / 10.0 / 30.0 / - | 2 x 3 |" in out.stdout and png.stat().st_size > 1000  # the file twice: once
    out = subprocess.run([sys.executable, "tables.py", "--curves", str(tmp_path / "none.jsonl")], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.strip().startswith(f"error: {tmp_path / 'none.jsonl'}: no such file")


def test_a_table_from_rows_alone_picks_one_budget_and_refuses_mixed_rows(tmp_path):
    """tables.py --table ROWS: a baseline at several budgets needs --budgets, the chosen budget's rows alone are shown;
    rows of two configs of a method, or of two demo sets in a cell, are an error rather than one column."""
    import pytest

    rows = [_row("GenRL", "walker_walk", s, 10.0 * b / 1000 + s, 60, steps=b) for b in (1000, 2000) for s in range(3)]
    rows += [_row("GIIL-FT", "walker_walk", s, 50.0 + s, 30, steps=300) for s in range(3)]
    with pytest.raises(ValueError, match=r"^GenRL rows at 1000, 2000 updates: pick one with --budgets genrl=N$"):
        tables.table_rows(rows)
    with pytest.raises(ValueError, match=r"--budgets genrl=4000: no GenRL rows at 4000 updates \(they are at 1000, 2000\)"):
        tables.table_rows(rows, {"genrl": 4000})
    kept = tables.table_rows(rows, tables.parse_budgets("genrl=2000"))
    assert sorted((r["method"], r["score"]) for r in kept) == [("GIIL-FT", 50.0), ("GIIL-FT", 51.0), ("GIIL-FT", 52.0),
                                                               ("GenRL", 20.0), ("GenRL", 21.0), ("GenRL", 22.0)]
    assert "| SE-SV | - | - | 51.0 +- 0.6 | 21.0 +- 0.6 | - |" in tables.markdown_tables("walker", kept)
    with pytest.raises(ValueError, match="GIIL-FT rows made with different settings"):
        tables.table_rows(rows + [_row("GIIL-FT", "walker_walk", 3, 0.0, 30, steps=100)], {"genrl": 1000})
    other_demos = {**_row("GIIL-FT", "walker_walk", 4, 0.0, 30, steps=300), "demo_returns": [2.0]}
    with pytest.raises(ValueError, match=r"walker_walk \(side view\): rows made with 2 sets of demos"):
        tables.table_rows(rows + [other_demos], {"genrl": 1000})
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = subprocess.run([sys.executable, "tables.py", "--table", str(path), "--budgets", "genrl=1000"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0 and "| SE-SV | - | - | 51.0 +- 0.6 | 11.0 +- 0.6 | - |" in out.stdout
    out = subprocess.run([sys.executable, "tables.py", "--curves", str(path), "--budgets", "genrl=1000"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 2 and "--budgets does nothing with --curves: drop it" in out.stderr
    out = subprocess.run([sys.executable, "tables.py", "--table", str(path), "--min-seeds", "5"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 2 and "--min-seeds does nothing with --table: drop it" in out.stderr


def test_a_third_body_needs_no_edit_of_the_tables(monkeypatch):
    """With a body the paper has no numbers for: CE demos come from the next body in envs.BODIES, and the tables show
    ours without the paper's columns."""
    import envs

    monkeypatch.setattr(envs, "BODIES", ("walker", "stickman", "hopper"))
    assert [envs.cross_body(b) for b in envs.BODIES] == ["stickman", "hopper", "walker"]
    assert envs.demo_of("hopper", "run", "CE-CV") == ("walker_run", "diagonal") and envs.demo_of("hopper", "run", "SE-SV") == ("hopper_run", "side")
    rows = [_row("GIIL-ZS", "walker_run", 0, 40.0, 1.0, setting="CE-SV"), _row("GIIL-FT", "walker_run", 0, 50.0, 1.0, setting="CE-SV")]
    text = tables.markdown_tables("hopper", [dict(r, agent="hopper") for r in rows])
    assert "| CE-SV | 40.0 +- 0.0 | - | 50.0 +- 0.0 | - |" in text and "(paper)" not in text
    assert "| GIIL-ZS | - | 40.0 +- 0.0 | - / - / 40.0 / - | 1 x 1 | 0.0 | - |" in tables.markdown_curves("hopper", rows, ["CE-SV"])
