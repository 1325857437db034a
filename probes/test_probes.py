"""probes/: each research script's reading on a toy or the smoke run (the product's tests, tests/, never load a probe)."""
import glob
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
import configs
import evaluate
import rundir
import video_encoder
from baselines import aime_nob, genrl
from conftest import probe_script

GENRL_SMOKE = configs.GenRLConfig(**configs.PRESETS["genrl"]["smoke"])
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _copy(smoke_run, tmp_path, name):
    run = str(tmp_path / name)
    shutil.copytree(smoke_run, run, ignore=shutil.ignore_patterns("results.jsonl", "baselines"))
    return run


def test_aime_reward_ranks_each_seeds_episodes(smoke_run, tmp_path):
    """probes/aime_reward.py reads each AIME-NoB seed's log: Spearman of its episodes' OT sums against their task returns."""
    run = _copy(smoke_run, tmp_path, "run")
    aime_nob.run_cell(run, "stickman_stand", "side", configs.AIMENoBConfig(**configs.PRESETS["aime_nob"]["smoke"]))
    probe = [sys.executable, "probes/aime_reward.py", run]
    out = subprocess.run(probe + ["stickman_stand", "side", "--body"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    log = torch.load(glob.glob(os.path.join(run, "baselines", "AIME-NoB_stickman_stand_side_s0_*.pt"))[0], weights_only=True)["log"]
    rho = evaluate.spearman([e["ot_sum"] for e in log], [e["task_return"] for e in log])
    assert f"seed 0 | 20 | {len(log)} | {rho:+.2f} |" in out.stdout and "\nall | " in out.stdout
    out = subprocess.run(probe + ["walker_walk", "side"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and "no AIME-NoB training state of walker_walk (side view)" in out.stderr
    out = subprocess.run(probe + ["stickman_walk", "side", "--body"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 2 and "--body needs a stand cell" in out.stderr


def test_getting_up_row_classes_episodes_by_their_last_steps():
    """probes/getting_up.py: an episode is up when its mean posture over the last 100 steps is >= 0.8, whatever came before."""
    getting_up = probe_script("getting_up")
    posture = np.zeros((500, 3))
    posture[-100:, 0] = 0.85  # up only at the end
    posture[:400, 1] = 1.0  # up, then fell for the last 100 steps
    posture[-100:, 2] = [0.9] * 50 + [0.6] * 50  # mean 0.75: down
    line = getting_up.row("stand", posture, np.array([90.0, 10.0, 30.0]))
    assert line == f"| stand | {posture.mean():.2f} | 0.33 | 90.0 +- 0.0 (1) | 20.0 +- 10.0 (2) | 43.3 +- 24.0 (3) |"


def test_getting_up_landing_times_the_fall_of_episodes_that_end_up():
    """probes/getting_up.py's landing: of the episodes up at the end, the median step of the lowest posture (first 150
    steps) and of the first step back up after it; an episode that stays down is left out."""
    getting_up = probe_script("getting_up")
    fall = lambda low, again: np.concatenate([np.ones(low), np.full(again - low, 0.1), np.ones(500 - again)])
    down = np.concatenate([np.ones(5), np.zeros(495)])
    assert getting_up.landing([fall(5, 15), fall(9, 30), fall(11, 40), down]) == (3, 9.0, 30.0)


def test_getting_up_events_are_a_lying_spell_then_up_within_60_steps():
    """probes/getting_up.py --imagined: an event is the first step at posture >= 0.8 after 10 steps below 0.3, within
    60 of them, with `before` steps before it and 20 after it in the episode; a body that rises too slowly, or too near
    the episode's end, makes none."""
    getting_up = probe_script("getting_up")
    rise = lambda down: np.concatenate([np.full(down, 0.1), np.ones(200 - down)])  # noqa: E731
    slow = np.concatenate([np.full(50, 0.1), np.full(80, 0.5), np.ones(70)])  # 80 steps half up: over 60
    posture = np.stack([rise(50), rise(190), slow, np.full(200, 0.1)])  # up at 190: 20 steps after it are not there
    assert getting_up.getting_up_events(posture, before=15) == [(0, 50)]
    assert getting_up.getting_up_events(posture, before=60) == []  # 50 steps down is less than 60 before


def test_imagination_gap_is_zero_when_reality_follows_imagination(smoke_run):
    """probes/imagination_gap.py: read as real steps, the imagined states give the imagined reading (both -d(s_k, g) on
    arrival, k = 1 .. H); run_episodes hands over one posterior state per step, t = 0 .. steps."""
    import torch

    import envs

    gap = probe_script("imagination_gap")
    cfgs, models, ckpt = checkpoint.load_run(smoke_run)
    wm, actor = models["world_model"], models["actor"]
    with torch.no_grad():
        goals = models["goal_vae"].goal(torch.randn(2, ckpt["p_dim"]))
    states = []
    evaluate.run_episodes([envs.make_env("walker", "walk") for _ in range(2)], models, goals, 6, "state", 0, on_state=states.append)
    assert len(states) == 7 and states[3]["deter"].shape == (2, cfgs["wm"].deter)
    imagined = gap.imagined_reward(models, states[3], goals, 4, seed=1)
    torch.manual_seed(1)
    with torch.no_grad():
        path, _ = wm.imagine(states[3], lambda feat: actor(feat, goals, deterministic=True)[0], 4)
        real = gap.real_reward(models["dist_net"], wm.feat(path), goals, 0, 4)
        assert imagined.shape == (2,) and torch.allclose(imagined, real)
        assert not torch.allclose(imagined, gap.real_reward(models["dist_net"], wm.feat(path), goals, 1, 3))  # indexing matters


def test_imagination_gap_reads_the_unpolished_actor_where_the_checkpoint_keeps_it(smoke_run, tmp_path):
    """--unpolished loads the checkpoint's actor_unpolished in place of the polished actor, and says so where there is none."""
    import torch

    gap = probe_script("imagination_gap")
    ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
    assert "actor_unpolished" in ckpt  # the smoke preset polishes, as the cpu one does
    torch.save({k: v for k, v in ckpt.items() if k != "actor_unpolished"}, tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match="keeps no unpolished actor: only a run trained with --ac-bc-polish"):
        gap.load(str(tmp_path), unpolished=True)
    polished, unpolished = gap.load(smoke_run)[1]["actor"], gap.load(smoke_run, unpolished=True)[1]["actor"]
    for name, value in unpolished.state_dict().items():
        assert torch.equal(value, ckpt["actor_unpolished"][name]) and torch.equal(polished.state_dict()[name], ckpt["models"]["actor"][name])


def test_filter_probe_reproduces_the_benchmark_and_its_window_changes_the_state(smoke_run):
    """probes/filter_probe.py: carried over the episode (window 0) the probe's filter is the benchmark's, return for return;
    a window shorter than the episode or z's mean gives other states, so other returns."""
    import torch

    import envs

    probe = probe_script("filter_probe")
    cfgs, models, ckpt = checkpoint.load_run(smoke_run)
    with torch.no_grad():
        goals = models["goal_vae"].goal(torch.randn(2, ckpt["p_dim"]))
    make = lambda: [envs.make_env("walker", "walk") for _ in range(2)]
    plain, _ = evaluate.run_episodes(make(), models, goals, 12, "state", 3)
    assert np.array_equal(probe.run_filtered(make(), models, goals, 12, 3), plain)
    assert not np.allclose(probe.run_filtered(make(), models, goals, 12, 3, window=4), plain)
    assert not np.allclose(probe.run_filtered(make(), models, goals, 12, 3, mean=True), plain)


def test_ensemble_probe_acts_with_the_mean_of_its_clones_actions():
    """probes/ensemble_probe.py: K actors act with the mean of their policy.Actor.act."""
    import torch

    import policy

    ensemble = probe_script("ensemble_probe")
    torch.manual_seed(0)
    cfg = configs.ActorCriticConfig(**configs.PRESETS["ac"]["smoke"])
    actors = [policy.Actor(cfg, 5, 5, 3) for _ in range(3)]
    feat, goal = torch.randn(4, 5), torch.randn(4, 5)
    with torch.no_grad():
        expected = sum(a.act(feat, goal) for a in actors) / 3
        assert torch.allclose(ensemble.Ensemble(actors).act(feat, goal), expected, atol=1e-6)
        assert not torch.allclose(actors[0].act(feat, goal), expected)



def test_ot_probe_scores_goals_alike_for_alike_goals(smoke_run):
    """probes/ot_probe.py: J(g) is a mean OT reward (<= 0), the same for the same goal (every goal meets the same starts and
    imagination noise), and the script prints one line per cell and the summary."""
    import subprocess
    import sys

    probe = probe_script("ot_probe")
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    feat_dim = models["world_model"].feat_dim
    demo_p = torch.nn.functional.normalize(torch.randn(2, 20, models["goal_vae"].feat_dim), dim=-1)
    g = torch.randn(feat_dim)
    J = probe.imagined_ot(models, cfgs, torch.stack([g, torch.randn(feat_dim), g]), demo_p, starts=6)
    assert J.shape == (3,) and (J <= 0).all() and J[0] == J[2] and J[0] != J[1]
    spearman = evaluate.spearman  # the probes' rank correlation
    assert spearman([1, 2, 3], [10, 20, 30]) == pytest.approx(1) and spearman([1, 2, 3], [3, 2, 1]) == pytest.approx(-1)
    out = subprocess.run([sys.executable, probe.__file__, smoke_run, "--settings", "SE-SV", "--starts", "4"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    assert [l.split(" |")[0] for l in lines[1:-1]] == [f"SE-SV {t}" for t in ("stand", "walk", "run", "jump")]
    assert lines[-1].startswith("own task's goals ranked first in ") and " of 4 cells" in lines[-1]


def test_goal_candidates_probe_sets_and_pairing(smoke_run):
    """probes/goal_candidates.py: four sets of 10 goals, 'zs' the demos' zero-shot goals; --paired differences by cell and seed."""
    probe = probe_script("goal_candidates")
    _, models, _ = checkpoint.load_run(smoke_run)
    demo_p = list(np.random.default_rng(0).standard_normal((10, 5, models["goal_vae"].feat_dim)).astype(np.float32))
    sets = probe.candidate_sets(models["goal_vae"], demo_p)
    assert list(sets) == ["zs", "q x1", "q x2", "mix"] and all(g.shape == (10, models["goal_vae"].deter + models["goal_vae"].stoch) for g in sets.values())
    assert torch.equal(sets["zs"], models["goal_vae"].goal(torch.as_tensor(np.stack([p[-1] for p in demo_p]))).detach())
    row = lambda method, seed, score, **config: dict(agent="walker", setting="SE-SV", task="run", seed=seed, method=method, score=score, config=config)
    rows = [row("GIIL-ZS (demo 0)", 0, 40.0), row("GIIL-ZS (demo 0)", 1, 50.0), row("GIIL-online", 0, 45.0), row("GIIL-online", 1, 45.0),
            row("GIIL-online", 0, 50.0, candidates="posterior"), row("GIIL-online", 1, 44.0, candidates="posterior")]
    assert probe.paired(rows).splitlines()[-1] == "| walker | SE-SV run (2 pairs) | 47.0 +- 3.0 | +2.0 +- 8.0 | +2.0 +- 3.0 |"


def test_scorers_rank_the_demo_first_and_the_table_reads_held_out_ranks():
    """probes/scorers.py: an agent episode equal to a demo scores above random features under every scorer, above its
    own frames shuffled only where the order counts (same step; whole-episode OT is blind to it); the table ranks a
    scorer ordered as the true score at +1 held out (A against B and back), its reverse at -1."""
    scorers = probe_script("scorers")
    rng = np.random.default_rng(0)
    demo = rng.standard_normal((2, 12, 16)).astype(np.float32)
    agent = np.stack([demo[1], demo[1][rng.permutation(12)], rng.standard_normal((12, 16)).astype(np.float32)])
    for name, scorer in scorers.SCORERS.items():
        s = np.asarray(scorer(agent, demo))
        assert s.shape == (3,) and s[0] > s[2], name
    same_step = scorers.SCORERS["same step"](agent, demo)
    whole = scorers.SCORERS["OT"](agent, demo)
    assert same_step[0] > same_step[1] + 0.5 and abs(whole[0] - whole[1]) < 1e-4
    true = [[[float(g)] * 3 for g in range(10)]] * 2  # (A/B, goal, episode)
    row = dict(agent="walker", view="side", true=true, scores={"good": true, "bad": [[[-float(g)] * 3 for g in range(10)]] * 2})
    lines = scorers.table([row]).splitlines()
    assert lines[2] == "| walker | side | 1 | good | +1.00 +- 0.00 | +1.00 | +1.00 |" and lines[3].startswith("| walker | side | 1 | bad | -1.00")
    assert lines[4].startswith("| walker | side | 1 | true score (ceiling) | +1.00")


def test_retrieval_scorers_rank_a_noisy_copy_of_a_demo_first():
    """probes/retrieval.py: among body episodes of random features, a noisy copy of one demo is the best match under
    every scorer."""
    retrieval = probe_script("retrieval")
    rng = np.random.default_rng(0)
    demo = rng.standard_normal((2, 12, 16)).astype(np.float32)
    body = rng.standard_normal((5, 12, 16)).astype(np.float32)
    body[3] = demo[1] + 0.1 * rng.standard_normal((12, 16))
    for name, scorer in retrieval.SCORERS.items():
        assert int(np.argmax(scorer(body, body[:, -1], demo, demo[:, -1]))) == 3, name


def test_neighbour_objective_scores_a_goal_by_the_episodes_that_ended_nearest_it():
    """probes/neighbour_objective.py: a goal reads the mean score of the k D_body episodes whose final goals lie
    nearest it, so the goal beside the best episode's end ranks first."""
    neighbour = probe_script("neighbour_objective")
    final_goals = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    score = np.array([1.0, 5.0, 2.0, 3.0])
    goals = torch.tensor([[9.0, 2.0], [1.0, 2.0], [2.0, 9.0]])
    assert neighbour.neighbour_objective(goals, final_goals, score, 1).tolist() == [5.0, 1.0, 2.0]
    assert neighbour.neighbour_objective(goals, final_goals, score, 2).tolist() == [4.0, 1.5, 2.5]


def test_standing_subgoal_feeds_the_up_goal_by_its_rule():
    """probes/standing_subgoal.py: g_up while the posture is below 0.8 (while), until it first reached 0.8 (until), or
    below 0.3 (lying); the task's goal otherwise."""
    subgoal = probe_script("standing_subgoal")

    class Echo:
        def act(self, feat, goal):
            return goal

    chosen = {}
    for rule in ("while", "until", "lying"):
        postures = iter([0.1, 0.5, 0.9, 0.5, 0.2])
        switch = subgoal.Subgoal(Echo(), lambda: np.array([next(postures)]), torch.ones(1, 2), rule)
        chosen[rule] = [switch.act(None, torch.zeros(1, 2))[0, 0].item() for _ in range(5)]
    assert chosen == {"while": [1, 1, 0, 1, 1], "until": [1, 1, 0, 0, 0], "lying": [1, 0, 0, 0, 1]}
    assert np.stack(switch.posture)[:, 0].tolist() == [0.1, 0.5, 0.9, 0.5, 0.2]


def test_goal_variance_splits_goal_from_episode_noise():
    """Goals that differ only by their episodes' noise have no goal variance; a fixed offset per goal is all goal."""
    goal_variance = probe_script("goal_variance")
    g, e, rel = goal_variance.split([[10.0, 20.0, 30.0]] * 10)
    assert (g, rel) == (0.0, 0.0) and abs(e - 10.0) < 1e-9
    g, e, rel = goal_variance.split([[k, k, k] for k in range(10)])
    assert e == 0.0 and rel == 1.0 and abs(g - np.std(range(10), ddof=1)) < 1e-9


def test_goal_variance_reads_the_benchmark_by_demo(smoke_run, tmp_path):
    """--benchmark: goal_reaching.json's scores, eval_episodes per demo goal in a row, split as the GIIL-ZS rows are."""
    goal_variance = probe_script("goal_variance")
    run = _copy(smoke_run, tmp_path, "run")
    record = json.load(open(os.path.join(run, "goal_reaching.json")))
    record["settings"]["eval_episodes"] = 2
    record["scores"]["walk"]["policy"] = [10.0, 30.0, 50.0, 70.0]  # two demos' goals, 2 episodes each
    with open(os.path.join(run, "goal_reaching.json"), "w") as f:
        json.dump(record, f)
    g, e, rel, mean, _ = goal_variance.benchmark_rows([run])[(run, "benchmark", "walk")]
    assert mean == 40.0 and (g, e, rel) == goal_variance.split([[10.0, 30.0], [50.0, 70.0]])
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "goal_variance.py")
    out = subprocess.run([sys.executable, script, run], capture_output=True, text=True)  # a folder without --benchmark
    assert out.returncode == 2 and out.stderr.strip().endswith(f"error: {run}: pass results.jsonl files, or run folders with --benchmark")


def test_goal_probe_scores_every_goal_by_every_objective(smoke_run):
    """On the smoke agent: each objective gives one finite score per goal; `real` is online.ot_score of the same
    episodes per step, and the replayed features start at the filtered ones (the same s_0)."""
    goal_probe = probe_script("goal_probe")
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    demo_p = np.random.default_rng(0).standard_normal((3, 40, models["goal_vae"].feat_dim)).astype(np.float32)
    demo_p /= np.linalg.norm(demo_p, axis=-1, keepdims=True)
    scores, true, error = goal_probe.probe_cell(models, cfgs, video_encoder.load_encoder("default"), "run", demo_p, [7],
                                                configs.OTConfig(iters=5), steps=12, n_starts=4)
    assert set(scores) == set(goal_probe.OBJECTIVES) and all(v.shape == (3,) and np.isfinite(v).all() for v in scores.values())
    assert true.shape == (3,) and error.shape == (len(goal_probe.ERROR_STEPS),)


def test_ft_pairs_pairs_seeds_of_two_variants(tmp_path):
    """probes/ft_pairs.py: A's last GIIL-FT row of a (demo, view, seed) against B's, both against A's GIIL-ZS (demo 0);
    a row of A with B's settings (copied, its variant not run yet) is no pair."""
    ft_pairs = probe_script("ft_pairs")
    row = lambda method, seed, score, demo="walker_walk", **config: dict(demo=demo, view="side", task="walk", setting="SE-SV",
                                                                          method=method, seed=seed, score=score, config=config)
    frozen = [row("GIIL-FT", s, 50.0 + s) for s in range(2)] + [row("GIIL-FT", 0, 10.0, demo="walker_run")]
    runs = {"a": [row("GIIL-ZS (demo 0)", s, 40.0) for s in range(2)] + frozen + [row("GIIL-ZS (demo 0)", 0, 5.0, demo="walker_run")]
            + [row("GIIL-FT", 0, 30.0, goal_lr=1e-4), row("GIIL-FT", 0, 45.0, goal_lr=1e-4), row("GIIL-FT", 1, 60.0, goal_lr=1e-4)],
            "b": frozen}
    for name, rows in runs.items():
        os.makedirs(tmp_path / name)
        with open(tmp_path / name / "results.jsonl", "w") as f:
            f.write("".join(json.dumps(r) + "\n" for r in rows))
    got = [(r["seed"], r["score"], b, zs0) for r, b, zs0 in ft_pairs.pairs(str(tmp_path / "a"), str(tmp_path / "b"))]
    assert got == [(0, 45.0, 50.0, 40.0), (1, 60.0, 51.0, 40.0)]  # walker_run's copied row is no pair
    # GIIL-online's rows, from .jsonl files as committed
    for name, rows in runs.items():
        online = ({**r, "method": "GIIL-online"} if r["method"] == "GIIL-FT" else r for r in rows)
        (tmp_path / f"{name}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in online))
    got = [(r["seed"], r["score"], b, zs0) for r, b, zs0 in ft_pairs.pairs(str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl"), "GIIL-online")]
    assert got == [(0, 45.0, 50.0, 40.0), (1, 60.0, 51.0, 40.0)]


def test_reward_probe_scores_saved_actors_in_the_real_body_and_in_imagination(smoke_run, tmp_path):
    run = _copy(smoke_run, tmp_path, "run")
    out = subprocess.run([sys.executable, "probes/genrl_reward.py", run, "walker_walk", "side"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 1 and "no GenRL training state of walker_walk (side view)" in out.stderr
    genrl.run_cell(run, "walker_walk", "side", GENRL_SMOKE)
    out = subprocess.run([sys.executable, "probes/genrl_reward.py", run, "walker_walk", "side", "--preset", "smoke"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line.split("|") for line in out.stdout.splitlines() if "|" in line][1:]
    assert [line[0].strip() for line in lines] == ["phase-1 policy, demo 0's zero-shot goal"] + [f"GenRL seed {s} after {GENRL_SMOKE.steps} updates" for s in (0, 1)]
    assert all(-1 <= float(x) <= 1 for line in lines for x in line[2:])  # max-cosine rewards


def test_data_lever_rows_read_the_records_of_each_demos_and_the_table_averages_seeds(smoke_run, smoke_data, tmp_path):
    """probes/data_lever.py: a run's own benchmark and its record on other demos (train.py --evaluate --data's file) as
    rows that name the demos' scores; the table lists each seed's per-task means, then their mean +- s.e."""
    probe = probe_script("data_lever")
    run, other = _copy(smoke_run, tmp_path, "run"), tmp_path / "other"
    own = probe.row(run, "recipe")
    assert own["scores"]["walk"] == evaluate.read_goal_reaching(run)["scores"]["walk"]["policy"] and own["seed"] == 0
    with pytest.raises(FileNotFoundError, match=r"0 records of .* run `python train.py --evaluate --run-dir .* --data .*other`"):
        probe.row(run, "recipe", str(other))
    shutil.copytree(os.path.join(smoke_data, "demos"), other / "demos")
    record = json.load(open(os.path.join(run, "goal_reaching.json")))
    named = os.path.join(run, "goal_reaching_x_data-" + str(other).strip(os.sep).replace(os.sep, "-") + ".json")
    json.dump(dict(record, data=str(other)), open(named, "w"))
    assert probe.row(run, "recipe", str(other))["demos"] == str(other)
    json.dump(dict(record, data=str(other), weights="1:0"), open(named, "w"))
    with pytest.raises(ValueError, match="scores another agent than"):
        probe.row(run, "recipe", str(other))
    twin = dict(own, seed=1, scores={t: [x + 2 for x in s] for t, s in own["scores"].items()})
    walk = float(np.mean(own["scores"]["walk"]))
    lines = probe.table([own, twin])
    name = f"recipe, {own['demos']} ({own['demo_scores']['run']:.0f})"
    assert f"| {name} | 0 | " in lines[2] and f"| {name} | 1 | " in lines[3]
    assert lines[4].split(" | ")[3] == f"{walk + 1:.1f} +- 1.0"  # two seeds 2 apart: s.e. 1
    other = dict(twin, recipe="other", scores={t: [x + 3 for x in s] for t, s in own["scores"].items()})
    lines = probe.table([own, twin, other])
    assert lines[6].startswith(f"| other, {own['demos']}") and lines[6].split(" | ")[1:3] == ["1 paired", "+1.0"]  # seed 1: +3 - 2


def test_data_lever_groups_task_episodes_by_the_snapshot_they_replay(tmp_path):
    probe = probe_script("data_lever")
    for k, (source, ret) in enumerate([("run@100000", 100.0), ("run@50000", 300.0), ("run@100000", 200.0)]):
        np.savez(tmp_path / f"run_{k:04d}.npz", source=source, **{"return": ret})
    np.savez(tmp_path / "walk_0000.npz", source="walk@50000", **{"return": 0.0})
    score = lambda r: float(probe.envs.normalized_score("run", r))
    assert probe.episodes_by_snapshot(str(tmp_path), "run") == [(50000, 1, score(300.0)), (100000, 2, (score(100.0) + score(200.0)) / 2)]


def test_acting_value_is_plain_acting_at_one_candidate_and_picks_the_best_imagined_return(smoke_run):
    """probes/acting_value.py: K = 1 acts as the benchmark, return for return; with K = 4 the action taken scores at
    least the actor's mean by the imagined goal return, and differs from it somewhere; while down only, the mean where up."""
    import envs

    probe = probe_script("acting_value")
    cfgs, models, ckpt = checkpoint.load_run(smoke_run)
    with torch.no_grad():
        goals = models["goal_vae"].goal(torch.randn(3, ckpt["p_dim"]))
        make = lambda: [envs.make_env("walker", "walk") for _ in range(3)]
        plain, _ = evaluate.run_episodes(make(), models, goals, 10, "state", 3)
        one = probe.Chooser(models, 1, 3, 0.99)
        assert np.array_equal(evaluate.run_episodes(make(), {**models, "actor": one}, goals, 10, "state", 3, on_state=one.on_state)[0], plain)
        chooser, states = probe.Chooser(models, 4, 3, 0.99), []
        evaluate.run_episodes(make(), models, goals, 5, "state", 3, on_state=states.append)
        chooser.on_state(states[-1])
        feat = models["world_model"].feat(states[-1])
        taken, mean = chooser.act(feat, goals), models["actor"].act(feat, goals)
        keep = {k: states[-1][k] for k in models["world_model"].state_keys}
        assert (chooser.scores(keep, goals, taken) >= chooser.scores(keep, goals, mean) - 1e-5).all()
        assert not torch.allclose(taken, mean)
        chooser.read_posture, chooser.below = lambda: np.array([0.9, 0.1, 0.9]), 0.8  # up in episodes 0, 2: the mean there
        taken = chooser.act(feat, goals)
        assert torch.equal(taken[[0, 2]], mean[[0, 2]])


def test_acting_value_giil_zs_cell_at_one_candidate_is_the_runners_giil_zs(smoke_run, tmp_path):
    """probes/acting_value.py --giil-zs: K = 1 in a cell scores each demo's goal episode for episode as runner.imitate's
    GIIL-ZS rows do (the tables' column), on the preset's evaluation settings and seeds."""
    import runner

    probe = probe_script("acting_value")
    run = shutil.copytree(smoke_run, tmp_path / "run")  # runner appends to its results.jsonl
    rows = runner.imitate(str(run), "walker_walk", "side", configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"]))
    cfgs, models, _ = checkpoint.load_run(str(run))
    with torch.no_grad():
        scores, _ = probe.zero_shot_cell(models, cfgs, "walk", "SE-SV", 1, 1, None, runner.EVAL_SEED)
    expected = [s for r in sorted(rows, key=lambda r: r["seed"]) for s in r["episode_scores"]]
    assert len(expected) == len(rows) > 1 and np.array_equal(scores, expected)


def test_acting_value_at_one_candidate_acts_plainly_only_and_refuses_no_candidate(smoke_run, tmp_path):
    """--candidates 1: one row per task, plain acting's (no choice variant); --candidates 0 is refused before anything runs."""
    out = tmp_path / "rows.jsonl"
    command = [sys.executable, "probes/acting_value.py", smoke_run, "--tasks", "stand", "--out", str(out)]
    result = subprocess.run(command + ["--candidates", "1"], cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    assert [(r["variant"], r["task"], r["minus_plain"]) for r in rundir.read_jsonl(str(out))] == [("K 1", "stand", 0.0)]
    refused = subprocess.run(command + ["--candidates", "0"], cwd=ROOT, capture_output=True, text=True)
    assert refused.returncode == 2 and "--candidates 0 --horizon [15]: give K >= 1 and H >= 1" in refused.stderr


def test_acting_value_table_averages_the_tasks_and_marks_an_unfinished_variant():
    """probes/acting_value.py --table: plain acting's scores, a variant's paired differences and their average with
    the s.e. of independent tasks, the share up at the end and the episode s.d. where a row has them; a variant
    missing a task is incomplete."""
    probe = probe_script("acting_value")
    row = lambda variant, task, score, minus, se: {"run": "a", "variant": variant, "task": task, "score": score,
                                                   "minus_plain": minus, "minus_plain_se": se, "up_at_end": 0.5}
    rows = [row("K 1", t, s, 0, 0) for t, s in zip(("stand", "walk", "run"), (60, 90, 30))]
    rows += [row("K 8, H 15", t, 0, m, 3) for t, m in zip(("stand", "walk", "run"), (9, 0, -3))]
    rows += [row("K 8, H 5", "stand", 0, 1, 1)]
    rows[3]["episode_sd"] = 12.25
    lines = probe.table(rows).splitlines()
    assert lines[2] == "| a | K 1 | 60.0 | 90.0 | 30.0 | 60.0 | 0.50 / 0.50 / 0.50 | - / - / - |"
    assert lines[3] == "| a | K 8, H 15 | +9.0 +- 3.0 | +0.0 +- 3.0 | -3.0 +- 3.0 | **+2.0 +- 1.7** | 0.50 / 0.50 / 0.50 | 12.2 / - / - |"
    assert lines[4] == "| a | K 8, H 5 | - | - | - | incomplete | - | - |"


def test_acting_value_zero_shot_table_averages_settings_cross_settings_and_tasks():
    """probes/acting_value.py --table on --giil-zs rows: each setting over its tasks, w/o SE-SV over the 12 cross
    cells, each task over the four settings; a missing cell leaves its groups '-'."""
    import envs

    probe = probe_script("acting_value")
    row = lambda variant, task, where, score, minus: {"run": "a", "variant": variant, "task": task, "setting": where,
                                                      "score": score, "minus_plain": minus, "minus_plain_se": 2.0}
    rows = [row("K 1", t, w, 10 * i, 0) for i, w in enumerate(envs.SETTINGS) for t in envs.TASKS]
    rows += [row("K 8", t, w, 0, 4 if w == "CE-SV" else 0) for w in envs.SETTINGS for t in envs.TASKS if (t, w) != ("jump", "SE-SV")]
    lines = probe.zero_shot_table(rows).splitlines()
    assert lines[0] == "| agent | variant | SE-SV | SE-CV | CE-SV | CE-CV | w/o SE-SV | stand | walk | run | jump |"
    assert lines[2] == "| a | K 1 | 0.0 | 10.0 | 20.0 | 30.0 | 20.0 | 15.0 | 15.0 | 15.0 | 15.0 |"
    assert lines[3] == "| a | K 8 | - | +0.0 +- 1.0 | +4.0 +- 1.0 | +0.0 +- 1.0 | +1.3 +- 0.6 | +1.0 +- 1.0 | +1.0 +- 1.0 | +1.0 +- 1.0 | - |"
