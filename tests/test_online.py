"""online.py: GIIL-online's search finds the candidate best under the OT reward, spends the stated budget, and never
reads the task reward; end to end through imitate.py (smoke)."""
import os
import subprocess
import sys

import numpy as np
import torch

import checkpoint
import configs
import envs
import fidelity
import online
import rundir
import runner
import tables
import video_encoder

SMOKE = configs.ImitateConfig(**configs.PRESETS["imitate"]["smoke"])


def test_successive_halving_finds_the_best_candidate_under_noise():
    """Ten candidates whose OT scores are their true means plus noise: the schedule (50 episodes) keeps the best."""
    truth = np.array([-0.9, -0.5, -0.8, -0.3, -0.7, -0.6, -0.2, -0.85, -0.4, -0.75])
    cfg = configs.OnlineConfig()
    for seed in range(5):
        rng = np.random.default_rng(seed)
        chosen, log = online.successive_halving(lambda idx, env_seed: truth[idx] + 0.05 * rng.standard_normal(len(idx)), 10, cfg, seed)
        assert chosen == 6
        assert len(log) == online.budget(cfg, 10) == 50
        assert {s for _, s, _ in log} == set(range(cfg.seed_base + 1000 * seed, cfg.seed_base + 1000 * seed + 14))  # 2 + 3 + 9 starts


def test_candidates_of_a_round_share_their_start_state():
    seen = []
    online.successive_halving(lambda idx, env_seed: seen.append((tuple(idx), env_seed)) or -np.asarray(idx, float), 10, configs.OnlineConfig(), 0)
    assert seen[:2] == [(tuple(range(10)), 50_000), (tuple(range(10)), 50_001)]
    assert seen[2:5] == [((0, 1, 2, 3), 50_002 + i) for i in range(3)]  # the 4 best (scores -index) of round 1, from the next starts
    assert [s for _, s in seen[5:]] == list(range(50_005, 50_014)) and all(idx == (0, 1) for idx, _ in seen[5:])


class NoRewardEnv:
    """An env whose task reward is garbage: the refinement must not read it."""

    def __init__(self, env, rng):
        self.env, self.rng = env, rng

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, action):
        obs, reward, *rest = self.env.step(action)
        return (obs, float(self.rng.normal(0, 1e6)), *rest)


def test_refinement_never_reads_the_task_reward(smoke_run):
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    goals = models["goal_vae"].goal(torch.randn(3, models["goal_vae"].feat_dim)).detach()
    demo_p = np.random.default_rng(0).standard_normal((2, 11, models["goal_vae"].feat_dim)).astype(np.float32)
    encoder = video_encoder.load_encoder("default")
    cfg = configs.OnlineConfig(schedule=((3, 1), (2, 1)))
    ot_cfg = configs.OTConfig(iters=5)
    rng = np.random.default_rng(0)
    plain = online.refine_goal(models, cfgs, lambda: envs.make_env("walker", "run"), goals, demo_p, cfg, 0, encoder, 10, ot_cfg)
    poisoned = online.refine_goal(models, cfgs, lambda: NoRewardEnv(envs.make_env("walker", "run"), rng), goals, demo_p, cfg, 0, encoder, 10, ot_cfg)
    assert plain[1] == poisoned[1] and plain[2] == poisoned[2] and torch.equal(plain[0], poisoned[0])  # the same choice from the same OT scores
    assert len(plain[2]) == online.budget(cfg, 3) == 5


def test_online_end_to_end_pairs_with_its_zero_shot_start(smoke_run):
    oc = configs.OnlineConfig(**configs.PRESETS["online"]["smoke"])
    rows = runner.imitate(smoke_run, "stickman_walk", "side", SMOKE, ["GIIL-online"], oc, zero_shot=False)
    on = [r for r in rows if r["method"] == "GIIL-online"]
    zs0 = [r for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    assert len(on) == len(zs0) == oc.seeds
    assert on[0]["env_steps"] == online.budget(oc, 2) * SMOKE.eval_steps and on[0]["chosen_demo"] in (0, 1)
    stored = [r for r in rundir.read_jsonl(os.path.join(smoke_run, "results.jsonl")) if r["method"] == "GIIL-online"]
    assert stored[-1]["config"] == runner.result_config(SMOKE, "GIIL-online", oc) and "schedule" in stored[-1]["config"]
    text = tables.markdown_tables("walker", rows)
    assert "GIIL-online (ours)" in text and "online - ZS (demo 0), paired" in text
    # the same command again finds its rows finished (as read back from JSON) and runs nothing
    assert runner.imitate(smoke_run, "stickman_walk", "side", SMOKE, ["GIIL-online"], oc, zero_shot=False) == []


def test_posterior_goals_start_at_the_zero_shot_goal(smoke_run):
    """q(s | p_T)'s mean first (GIIL-ZS's goal), then seeded draws around it (fidelity.py's ranking goals)."""
    _, models, _ = checkpoint.load_run(smoke_run)
    vae, p_last = models["goal_vae"], np.random.default_rng(0).standard_normal(models["goal_vae"].feat_dim).astype(np.float32)
    goals = fidelity.posterior_goals(vae, p_last, 10, seed=3)
    assert goals.shape == (10, vae.deter + vae.stoch) and torch.equal(goals[0], vae.goal(torch.as_tensor(p_last)).detach())
    assert torch.equal(goals, fidelity.posterior_goals(vae, p_last, 10, seed=3)) and not torch.equal(goals, fidelity.posterior_goals(vae, p_last, 10, seed=4))
    assert len(torch.unique(goals, dim=0)) == 10


def test_online_with_its_zero_shot_column_writes_the_curve(smoke_run):
    """imitate.py --online's cell: GIIL-ZS of every demo, then GIIL-online, and the curve of the goal it would choose
    after each real episode, a PNG beside the cell's videos."""
    oc = configs.OnlineConfig(**configs.PRESETS["online"]["smoke"])
    runner.imitate(smoke_run, "walker_stand", "side", SMOKE, ["GIIL-online"], oc)
    path = os.path.join(checkpoint.work_folder(smoke_run), "imitate", "walker_stand_side_online_curve.png")
    assert os.path.getsize(path) > 1000 and open(path, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_finetune_and_online_share_their_zero_shot_start(smoke_run):
    """One command with both: GIIL-ZS (demo 0) once per seed, not once per method."""
    oc = configs.OnlineConfig(**configs.PRESETS["online"]["smoke"])
    rows = runner.imitate(smoke_run, "walker_jump", "diagonal", SMOKE, ["GIIL-FT", "GIIL-online"], oc, zero_shot=False)
    zs0 = [r["seed"] for r in rows if r["method"] == "GIIL-ZS (demo 0)"]
    assert sorted(zs0) == list(range(max(SMOKE.seeds, oc.seeds)))
    assert sum(r["method"] == "GIIL-online" for r in rows) == oc.seeds


def test_online_flags_are_checked_and_need_online():
    for flags, message in ((["--online-seeds", "2"], "--online-seeds sets GIIL-online: add --online, or drop it"),
                           (["--online", "--online-seeds", "0"], "--online-seeds 0: must be >= 1")):
        out = subprocess.run([sys.executable, "imitate.py", "--demo", "walker_run", *flags], capture_output=True, text=True,
                             cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        assert out.returncode != 0 and message in out.stderr, out.stderr


def test_the_goal_choosing_episodes_never_start_where_the_evaluation_does(smoke_run):
    """--online-seed-base 20000 would replay the evaluation's start states (seeds 20000 + 100 seed + e) while choosing the
    goal: refused in one line before anything runs; the default and a base past the evaluations' seeds pass."""
    import dataclasses

    import pytest

    cpu = configs.ImitateConfig()
    runner.check_online_seeds(cpu, configs.OnlineConfig())
    with pytest.raises(ValueError, match=r"--online-seed-base 20000: GIIL-online's episodes would start where the evaluation's do "
                                         r"\(environment seeds 20000 to 20902\): pass 20903 or more \(default 50000\)"):
        runner.check_online_seeds(cpu, configs.OnlineConfig(seed_base=20_000))
    runner.check_online_seeds(cpu, configs.OnlineConfig(seed_base=20_903))
    runner.check_online_seeds(cpu, configs.OnlineConfig(seed_base=16_000))  # its 3 seeds' episodes end below 20000
    oc = dataclasses.replace(configs.OnlineConfig(**configs.PRESETS["online"]["smoke"]), seed_base=19_500)
    with pytest.raises(ValueError, match="--online-seed-base 19500"):
        runner.imitate(smoke_run, "walker_walk", "side", SMOKE, ["GIIL-online"], oc)
