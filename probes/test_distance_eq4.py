"""probes/distance_probe.py's readings of d (the td reading's loss among them) and probes/eq4_probe.py, which reads them."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

import checkpoint
from conftest import probe_script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_distance_probe_readings_on_a_body_at_rest_and_one_that_moves():
    """A body at rest for its first half, then moving steadily: every pair in the rest looks alike. Eq. 7's squared
    error gives such a pair its mean gap; the expectile reading the shortest (lower); the Hilbert reading is 0 at
    equal states by construction and rises with the gap where the body moves."""
    probe = probe_script("distance_probe")
    L = 60
    ramp = torch.cat([torch.zeros(L // 2), torch.linspace(0, 3, L // 2)])
    x = ramp[None, :, None].expand(8, L, 2) + torch.arange(8.0)[:, None, None] * 10  # (E, L, 2): an offset per episode
    fitted = {name: probe.fit(x, x, window=20, updates=200, batch=8, pairs=128, units=32, **kw) for name, kw in probe.READINGS.items() if name != "window100"}
    with torch.no_grad():
        rest = {name: d(x[:, 5], x[:, 20]).mean().item() for name, d in fitted.items()}
        moving = [fitted["hilbert"](x[:, 35], x[:, 35 + k]).mean().item() for k in (0, 5, 15)]
    assert rest["expectile"] < rest["eq7"] - 0.05, rest
    assert moving[0] == 0.0 and moving[0] < moving[1] < moving[2], moving


def test_distance_probe_td_reading_ranks_another_episodes_goal_by_the_steps_to_it():
    """Episodes that move along one line from different starting points: a state of one episode is never paired with
    another's by Eq. 6, and Eq. 7 labels every such pair 1. The td reading bootstraps along the transitions, so from
    episode 3 the distance to a frame of episode 0 rises with the steps between their positions, and is 0 at itself."""
    probe = probe_script("distance_probe")
    L = 40
    x = (torch.arange(8.0)[:, None] * 0.5 + torch.linspace(0, 3, L))[..., None]  # (E, L, 1): episode e from 0.5 e
    d = probe.fit_td(x, x, updates=400, batch=256, units=32)
    goal = x[0, 35]  # position 2.69; episode 3 passes it at step 15
    with torch.no_grad():
        rising = [d(x[3, t], goal).item() for t in (13, 9, 5, 1)]
        assert d(goal, goal).item() == 0.0
    assert rising == sorted(rising) and rising[-1] > rising[0] + 0.02, rising


def test_eq4_probe_critic_on_real_sequences_regresses_to_the_lambda_returns():
    """probes/eq4_probe.py's repval: with d = 1 everywhere and a slow critic of 0, a 3-step real segment's returns are
    G_1 = -1, G_0 = -1 - gamma lambda (G_2 = v_2 = 0), and a critic of 0 has the loss 0.5 mean(G^2)."""
    probe = probe_script("eq4_probe")
    cfg = type("Config", (), {"gamma": 0.9, "lambda_": 0.5})
    zero = lambda feat, goal: torch.zeros(feat.shape[:-1])
    dist_net = lambda feat, goal: torch.ones(feat.shape[:-1])
    loss = probe.real_critic_loss(zero, zero, dist_net, torch.randn(2, 3, 4), torch.randn(2, 4), cfg)
    assert loss.item() == pytest.approx(0.5 * ((-1 - 0.45) ** 2 + 1) / 2)


def test_eq4_probe_trains_a_fresh_actor_and_leaves_the_world_model_frozen(smoke_run, smoke_data, tmp_path):
    """On the smoke run, D_body named by --data: a row with the guard's settings, its data, its log and the benchmark;
    the run's checkpoint untouched."""
    before = open(os.path.join(smoke_run, "checkpoint.pt"), "rb").read()
    out = str(tmp_path / "rows.jsonl")
    result = subprocess.run([sys.executable, "probes/eq4_probe.py", smoke_run, "--updates", "2", "--log-every", "1", "--horizon", "3",
                             "--starts", "16", "--critic-real", "--distance", "td", "--distance-updates", "2", "--episodes", "1",
                             "--eval-steps", "10", "--data", smoke_data, "--out", out],
                            cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    row = json.loads(open(out).read())
    assert (row["horizon"], row["starts"], row["critic_real"], row["distance"], row["updates"], row["data"]) == (3, 16, True, "td", 2, smoke_data)
    assert [r["step"] for r in row["log"]] == [1, 2] and len(row["log"][0]["reward_reachable"]) == 3
    assert set(row["scores"]) == {"stand", "walk", "run"} and np.isfinite(row["gap"])
    assert open(os.path.join(smoke_run, "checkpoint.pt"), "rb").read() == before
    summary = subprocess.run([sys.executable, "probes/eq4_probe.py", "--summary", out], cwd=ROOT, capture_output=True, text=True)
    assert f"| {smoke_run} | fresh | td | 3 | 16 | yes | 2 | 1 | {row['average']:.1f} | - | {row['gap']:.3f} |" in summary.stdout


def test_eq4_probe_from_the_clone_without_updates_scores_the_runs_own_benchmark(smoke_run, tmp_path):
    """--from-clone keeps the run's actor: with 0 updates its benchmark on the run's own settings is the run's own,
    episode for episode (the pairing --summary reads); the cloning's weight anneals linearly from FIRST to LAST."""
    probe = probe_script("eq4_probe")
    assert [probe.bc_weight((1.0, 0.1), k, 4) for k in range(4)] == pytest.approx([1.0, 0.7, 0.4, 0.1])
    assert probe.bc_weight(None, 3, 4) == 0.0
    alone = subprocess.run([sys.executable, "probes/eq4_probe.py", smoke_run, "--no-eq4"], cwd=ROOT, capture_output=True, text=True)
    assert alone.returncode == 2 and "--no-eq4 leaves the cloning alone: it goes with --from-clone and --bc-anneal" in alone.stderr
    out = str(tmp_path / "rows.jsonl")
    result = subprocess.run([sys.executable, "probes/eq4_probe.py", smoke_run, "--from-clone", "--bc-anneal", "1", "0.1", "--updates", "0",
                             "--episodes", "1", "--eval-steps", "10", "--out", out],
                            cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    row = json.loads(open(out).read())
    assert row["from_clone"] and row["bc_anneal"] == [1.0, 0.1] and row["average"] == pytest.approx(row["start_average"], abs=1e-9)
    summary = subprocess.run([sys.executable, "probes/eq4_probe.py", "--summary", out], cwd=ROOT, capture_output=True, text=True)
    assert f"| {smoke_run} | clone, bc 1 -> 0.1 | run | " in summary.stdout and "| 0.0 |" in summary.stdout


def test_eq4_probe_saves_the_stage_actor_as_an_agent_and_never_replaces_one(smoke_run, tmp_path):
    """--save-agent DIR: an agent checkpoint.load_run reads, the run's frozen models with the actor the stage moved; a
    folder holding a checkpoint already is refused before anything runs."""
    agent, out = str(tmp_path / "agent"), str(tmp_path / "rows.jsonl")
    command = [sys.executable, "probes/eq4_probe.py", smoke_run, "--from-clone", "--bc-anneal", "1", "0.1", "--updates", "1",
               "--episodes", "1", "--eval-steps", "10", "--out", out, "--save-agent", agent]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr[-2000:]
    _, run, _ = checkpoint.load_run(smoke_run)
    _, saved, _ = checkpoint.load_run(agent)
    same = lambda a, b: all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))  # noqa: E731
    assert same(saved["world_model"], run["world_model"]) and same(saved["dist_net"], run["dist_net"])
    assert not same(saved["actor"], run["actor"])
    again = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert again.returncode == 2 and f"--save-agent {agent}: it holds a checkpoint already; name another folder" in again.stderr
    assert len(open(out).readlines()) == 1


def test_td_loss_bootstraps_inside_an_episode_and_targets_the_discounted_steps():
    """distance_probe.td_loss on segments that cross an episode start: every target reads a state of the same episode part
    1 to n steps later; and with d = 0 everywhere but the slow copy at d (1 - gamma) = 1, i.e. V' = -1 / (1 - gamma)
    (100 steps), a value of 0 meets its targets -(1 - gamma^m) / (1 - gamma) - gamma^m 100 (or 0) with the expectile."""
    probe = probe_script("distance_probe")
    B, T = 4, 30
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = is_first[1, 12] = is_first[2, 20] = True
    part, t = is_first.long().cumsum(1).float(), torch.arange(T).float().expand(B, T)
    x = torch.stack([part + 10 * torch.arange(B)[:, None], t], -1)  # (B, T, 2): which episode part, which step
    seen = []

    class Zero:  # V = 0: d = 0, differentiable
        def __init__(self):
            self.w = torch.zeros((), requires_grad=True)

        def distance(self, a, g):
            seen.append(a)
            return self.w * a[..., 0]

    class Slow:
        def distance(self, a, g):
            seen.append(a)
            return torch.full(a.shape[:-1], 1.0)

    loss, metrics = probe.td_loss(Zero(), Slow(), x, [x], is_first, 2000, torch.Generator().manual_seed(0), n=5)
    later, now = seen  # the slow copy reads s_{t+m} first, then d reads s_t
    assert torch.equal(later[:, 0], now[:, 0])  # the same episode part
    steps = later[:, 1] - now[:, 1]
    assert steps.min() >= 1 and steps.max() <= 5 and metrics["dist_value"] == 0.0
    # targets below the value weigh 1 - tau = 0.05; a goal not met within the m steps: -(1 - g^m) / (1 - g) - g^m 100 =
    # -100 exactly (the any-frame 30 %, most of the later-frame 50 %), the current frame's 0, one met within them ~ -m
    assert 0.05 * 100**2 * 0.6 < loss.item() < 0.05 * 100**2 * 0.85


def test_td_loss_survives_a_uniform_draw_of_exactly_zero(monkeypatch):
    """torch.rand draws from [0, 1): a 0 once made the geometric gap log(0) / log(gamma) = inf, an index of -2^63 (a
    phase-1 run stopped on it). Here every goal is a later frame (the first draw 0.5) at the gap of a draw of 0."""
    probe = probe_script("distance_probe")
    x = torch.randn(2, 10, 3)
    draws = iter([0.5, 0.0])
    monkeypatch.setattr(torch, "rand", lambda n, generator=None: torch.full((n,), next(draws)))
    net = probe.TDReading(3, units=8, layers=2)
    loss, _ = probe.td_loss(net, net, x, [x], torch.zeros(2, 10, dtype=torch.bool), 16)
    assert torch.isfinite(loss)
