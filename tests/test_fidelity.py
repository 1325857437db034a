"""fidelity.py: the benchmark on a toy where the world model is exact (cosine 1, error 0, no KL), its table and PNG."""
import numpy as np
import pytest
import torch

import configs
import fidelity
import goal_vae
import world_model as W

torch.set_num_threads(1)


def exact_toy(E=3, L=40, obs_dim=5, action_dim=2, p_dim=8, discrete=0):
    """A smoke world model whose posterior ignores the observation (post_in, post_out copied from the prior head), and
    episodes it generates itself: o_t and p_t decoded from its own prior-mean states. Filtering and imagination then
    follow the same states, so the model is exact on its episodes."""
    torch.manual_seed(0)
    wm = W.WorldModel(configs.WorldModelConfig(**configs.PRESETS["wm"]["smoke"]), obs_dim, action_dim)
    vae = goal_vae.GoalVAE(configs.GoalVAEConfig(**configs.PRESETS["goal"]["smoke"]), p_dim, wm.cfg.deter, wm.latent)
    with torch.no_grad():
        first, last = wm.prior_net[0], wm.prior_net[-1]
        wm.post_in.weight.zero_()
        wm.post_in.weight[:, : wm.cfg.deter] = first.weight
        wm.post_in.bias.copy_(first.bias)
        wm.post_out.load_state_dict(last.state_dict())
        wm.img_in.weight.mul_(10)  # actions that move the state: holding o_t0 is then far from the episode
        action = torch.rand(E, L, action_dim) * 2 - 1
        action[:, 0] = 0
        state, feats = wm.initial_state(E), []
        for t in range(L):
            state = wm.img_step(state, action[:, t], sample=False)
            feats.append(wm.feat(state))
        feat = torch.stack(feats, 1)
        obs, p = wm.decode(feat), vae.decode(feat)
    is_first = np.zeros(L, bool)
    is_first[0] = True
    episodes = [{"state": obs[e].numpy(), "action": action[e].numpy(), "is_first": is_first, "p": p[e].numpy()} for e in range(E)]
    return wm, vae, episodes


@pytest.mark.parametrize("discrete", [0, 4])  # a Gaussian z, a categorical z
def test_an_exact_model_scores_cosine_one_and_error_zero(discrete):
    wm, vae, episodes = exact_toy(discrete=discrete)
    m = fidelity.measure(wm, vae, episodes, starts=(10, 20), ahead=15)
    assert len(m["cos"]) == 15 and m["starts"] == 2 and m["episodes"] == 3
    assert np.allclose(m["cos"], 1, atol=1e-5) and np.allclose(m["filtered"], 1, atol=1e-5)
    assert max(m["error"]) < 1e-10 < 1e-5 < min(m["hold"])  # holding o_t0 is not the episode
    assert m["kl"] < 1e-6


def test_a_perturbed_model_loses_the_episode_and_short_episodes_shorten_the_horizon():
    wm, vae, episodes = exact_toy()
    with torch.no_grad():
        wm.prior_net[-1].weight.add_(torch.randn_like(wm.prior_net[-1].weight))  # the prior no longer the data's, the filter still exact
    m = fidelity.measure(wm, vae, episodes, starts=(10, 20), ahead=100)
    assert len(m["cos"]) == 40 - 1 - 10  # as far as the first start can imagine
    assert m["error"][-1] > 1e-8 and m["cos"][-1] < 0.999 and np.allclose(m["filtered"], 1, atol=1e-5)


def test_table_and_png(tmp_path):
    wm, vae, episodes = exact_toy(L=70)  # 59 steps ahead of t0 = 10: no column at 100
    row = fidelity.benchmark({"world_model": wm, "goal_vae": vae}, {"walk": episodes}, 7, "toy")
    table = fidelity.markdown([row])
    assert "| toy | 7 | walk | 1.00 / 1.00 / - | 1.00 / 1.00 / - | 0.000 / 0.000 / - |" in table
    assert fidelity.plot([row], str(tmp_path / "f.png")).endswith("f.png") and (tmp_path / "f.png").stat().st_size > 1000


def test_ranking_rows_on_a_smoke_agent(smoke_run, tmp_path):
    """The functional test end to end: one row per same-body cell with 20 goals' real scores and Eq. 5's J, a cell
    already in the file is skipped, and the cross-domain cells are refused (the test set)."""
    import checkpoint

    cfgs, models, ckpt = checkpoint.load_run(smoke_run)
    out = str(tmp_path / "ranking.jsonl")
    fidelity.ranking(smoke_run, ckpt["step"], cfgs, models, ["SE-SV"], 2, out)
    rows = fidelity.rundir.read_jsonl(out)
    assert [(r["task"], r["setting"]) for r in rows] == [(t, "SE-SV") for t in ("stand", "walk", "run", "jump")]
    # the 2 smoke demos' goals and 10 draws
    assert all(len(r["real"]) == len(r["eq5"]) == 2 + 10 and -1 <= r["spearman"] <= 1 and 0 <= r["cap"] <= 1 for r in rows)
    fidelity.ranking(smoke_run, ckpt["step"], cfgs, models, ["SE-SV"], 2, out)
    assert len(fidelity.rundir.read_jsonl(out)) == 4
    assert all(-1 <= r["spearman_reward"] <= 1 for r in rows) and "mean of 4 cells" in fidelity.ranking_markdown(rows)
    with pytest.raises(ValueError, match="--settings SE-SV,CE-SV: the ranking is measured on same-body cells"):
        fidelity.ranking(smoke_run, ckpt["step"], cfgs, models, ["SE-SV", "CE-SV"], 2, out)


def test_distance_ranking_reads_d_at_each_gap_and_the_observations_own_distance():
    """States that move steadily away: the observations' distance rises with k (Spearman 1 per episode and per start),
    another episode's frame is farther; d is read from posterior states and from goal-encoder goals alike."""
    wm, vae, episodes = exact_toy(E=2, L=130)
    for e, episode in enumerate(episodes):
        episode["state"] = np.repeat(np.arange(130, dtype=np.float32)[:, None] / 100 + 5 * e, 5, 1)  # a ramp per episode
    seen = []
    dist_net = lambda a, b: seen.append(b.shape) or (a - b).norm(dim=-1)  # a stand-in d: the features' own distance
    out = fidelity.distance_ranking(wm, vae, dist_net, episodes)
    assert set(out) == {"post", "enc", "obs"} and len(seen) == 2 * (len(fidelity.GAPS) + 1)
    obs = out["obs"]
    assert obs["rho_episode"] == obs["rho_start"] == 1.0 and np.all(np.diff(obs["d"]) > 0) and obs["other"] > obs["d"][-1]
    table = fidelity.distance_markdown([{"run": "toy", "step": 3, "distance": {"walk": out}}])
    assert "| toy | 3 | walk | obs | " in table and "| 1.00 / 1.00 |" in table


def test_the_command_writes_into_the_run_and_docs_only_when_asked(smoke_run, tmp_path):
    """python fidelity.py <run>: the row goes to the run's fidelity.jsonl, never by default into the committed
    docs/results files (a smoke run's row there would join the shipped agents' rows); --out names another file."""
    import os
    import shutil
    import subprocess
    import sys

    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "fidelity.py")
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    done = subprocess.run([sys.executable, script, str(run)], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-500:]
    assert len(fidelity.rundir.read_jsonl(str(run / "fidelity.jsonl"))) == 1 and not (tmp_path / "docs").exists()
    done = subprocess.run([sys.executable, script, str(run), "--out", str(tmp_path / "rows.jsonl")], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0 and len(fidelity.rundir.read_jsonl(str(tmp_path / "rows.jsonl"))) == 1
