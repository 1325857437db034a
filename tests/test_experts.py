"""experts/: stopping experts on resume keeps their latest policy; --warm-start copies one expert into another."""
import os

import pytest
import torch

import experts
from experts import sac

TINY = dict(steps=12, seed_steps=4, batch=8, hidden=8, snapshot_every=12, eval_every=10_000, checkpoint_minutes=0.0, final_episodes=1)


@pytest.fixture
def expert_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(experts, "EXPERT_DIR", str(tmp_path / "experts"))
    return tmp_path


def test_dropped_task_keeps_latest_policy_and_warm_start_copies(expert_dir):
    ckpt_dir = str(expert_dir / "ckpt")
    experts.train("walker", ["stand", "walk", "run"], experts.ExpertConfig(**TINY), ckpt_dir, resume=False)
    state = torch.load(os.path.join(ckpt_dir, "walker.pt"), weights_only=True)
    assert state["step"] == 12 and state["tasks"] == ["stand", "walk", "run"]

    # resume without stand: its final file is its step-12 actor
    experts.train("walker", ["walk", "run"], experts.ExpertConfig(**TINY), ckpt_dir, resume=True, replace_committed=True)
    stand = torch.load(experts.expert_path("walker", "stand"))
    assert stand["step"] == 12
    for key, value in stand["actor"].items():
        assert torch.equal(value, state["actor"][key][0:1].half())


def test_warm_start_copies_networks_temperature_and_moments():
    torch.manual_seed(0)
    tasks, n = ["stand", "walk", "run"], 3
    actor, critic, target = experts.Actor(n, 5, 2, 8), experts.Critic(n, 5, 2, 8), experts.Critic(n, 5, 2, 8)
    log_alpha = torch.randn(n, requires_grad=True)
    optims = {"actor": torch.optim.Adam(actor.parameters()), "critic": torch.optim.Adam(critic.parameters())}
    (actor(torch.randn(n, 4, 5))[0].sum() + critic(torch.randn(n, 4, 5), torch.randn(n, 4, 2)).sum()).backward()
    for opt in optims.values():
        opt.step()  # Adam moments differ per member
    before = {name: {k: v.clone() for k, v in m.state_dict().items()} for name, m in (("actor", actor), ("critic", critic))}
    experts.copy_member(["run=walk"], tasks, actor, critic, target, log_alpha, optims)
    for name, module, heads in (("actor", actor, 1), ("critic", critic, 2), ("target", target, 2)):
        for key, value in module.state_dict().items():
            rows = value.unflatten(0, (heads, n))  # the twin critics stack Q1 members, then Q2 members
            assert torch.equal(rows[:, 2], rows[:, 1]), (name, key)
            if name in before:
                assert torch.equal(rows[:, :2], before[name][key].unflatten(0, (heads, n))[:, :2]), (name, key)
    for p in list(actor.parameters()) + list(critic.parameters()):
        heads = len(p) // n
        moment = optims["actor" if heads == 1 else "critic"].state[p]["exp_avg"].unflatten(0, (heads, n))
        assert torch.equal(moment[:, 2], moment[:, 1])
    assert log_alpha[2] == log_alpha[1]


def test_warm_start_rejects_unknown_task(expert_dir):
    with pytest.raises(ValueError, match="--warm-start stand=jump: both tasks must be among --tasks"):
        experts.train("walker", ["stand", "walk"], experts.ExpertConfig(**TINY), str(expert_dir / "c"), resume=False, warm_start=["stand=jump"])


def test_compact_state_resumes_tasks_in_any_order(expert_dir):
    experts.train("walker", ["stand", "walk"], experts.ExpertConfig(**TINY), str(expert_dir / "a"), resume=False)
    full = torch.load(str(expert_dir / "a" / "walker.pt"), weights_only=True)
    state = experts.load_compact("walker", ["walk", "stand"])  # per-task files, stacked in the order asked
    assert state["step"] == 12
    for key, value in full["actor"].items():
        assert torch.equal(state["actor"][key], value[[1, 0]].half())
    for key, value in full["critic"].items():  # Q1 of walk, stand, then Q2 of walk, stand
        assert torch.equal(state["critic"][key], value[[1, 0, 3, 2]].half())
    with pytest.raises(FileNotFoundError, match="walker_run.pt"):
        experts.load_compact("walker", ["walk", "run"])


def test_a_run_stopped_after_a_snapshot_resumes_from_it_not_before(expert_dir, monkeypatch):
    """Killed between timed checkpoints: the compact state (what --resume --replace-committed starts from) is the last
    snapshot's step, so a resume never writes a snapshot already written."""
    calls = []

    def stop_at_step_9(*args):
        calls.append(1)
        if len(calls) == 5:  # updates run from step seed_steps = 4 on: the fifth is step 9
            raise KeyboardInterrupt
        return update(*args)

    update = experts.sac_update
    monkeypatch.setattr(experts, "sac_update", stop_at_step_9)
    with pytest.raises(KeyboardInterrupt):
        experts.train("walker", ["stand"], experts.ExpertConfig(**{**TINY, "snapshot_every": 6, "checkpoint_minutes": 1e9}), str(expert_dir / "c"), resume=False)
    assert experts.history_steps("walker", "stand") == [6] and experts.load_compact("walker", ["stand"])["step"] == 6


def test_final_expert_is_the_best_snapshot(expert_dir):
    torch.manual_seed(0)
    actor = experts.Actor(1, 24, 6, 8)
    experts.save_actor_member(actor, 0, "walker", "stand", experts.expert_path("walker", "stand"), 100, score=1e9)
    experts.keep_best(actor, "walker", ["stand"], 200, episodes=1)  # worse than the saved one: kept
    assert torch.load(experts.expert_path("walker", "stand"))["step"] == 100
    experts.save_actor_member(actor, 0, "walker", "stand", experts.expert_path("walker", "stand"), 100, score=-1e9)
    experts.keep_best(actor, "walker", ["stand"], 200, episodes=1)  # better: replaced, with its --eval score
    saved = torch.load(experts.expert_path("walker", "stand"))
    assert saved["step"] == 200
    evaluated = experts.envs.normalized_score("stand", experts.evaluate("walker", "stand", 1).mean())  # of the float16 copy
    assert saved["score"] == pytest.approx(float(evaluated), abs=0.1)


def test_sac_log_prob_matches_torch_distributions():
    torch.manual_seed(0)
    mean, std = torch.randn(5, 3), torch.rand(5, 3) + 0.1
    u = mean + std * torch.randn(5, 3)
    squashed = torch.distributions.TransformedDistribution(torch.distributions.Normal(mean, std), torch.distributions.TanhTransform())
    expected = squashed.log_prob(torch.tanh(u)).sum(-1)
    assert torch.allclose(sac.tanh_gaussian_log_prob(u, mean, std), expected, atol=1e-4)


def test_data_and_expert_code_never_imports_method_files():
    import subprocess
    import sys

    code = ("import sys, collect, envs, experts, experts.sac, video_encoder, rundir; "
            "print(sorted({'policy', 'distance', 'world_model', 'goal_vae', 'ot_reward', 'train', 'imitate'} & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))), capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr[-2000:]
