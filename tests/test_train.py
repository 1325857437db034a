"""train.py: end to end with the smoke preset, resume, config mismatch, NaN stop, the paper preset's sizes."""
import dataclasses
import json
import os
import shutil

import numpy as np
import pytest
import torch

import checkpoint
import collect
import configs
import envs
import evaluate
import goal_vae
import rundir
import train
from tests.fixtures import train_args


def test_smoke_run_writes_checkpoint_metrics_and_goal_reaching(smoke_run):
    ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
    assert ckpt["step"] == configs.PRESETS["train"]["smoke"]["steps"] and ckpt["encoder"] == "default-v1"
    assert ckpt["config"]["wm"]["obs"] == "state" and ckpt["config"]["wm"]["deter"] == 16  # the smoke preset, resolved
    lines = [json.loads(l) for l in open(os.path.join(smoke_run, "metrics.jsonl"))]
    assert [l["step"] for l in lines] == [2, 4, 6] and "actor_loss" in lines[-1] and "open_loop" in lines[-1] and -1 <= lines[-1]["open_loop_p_cos"] <= 1
    assert all(len(l["reward_reachable"]) == 3 for l in lines)  # from the fresh actor's row (policy_start 2) on
    record = json.load(open(os.path.join(smoke_run, "goal_reaching.json")))
    scores = record["scores"]
    assert list(scores) == ["stand", "walk", "run", "jump"] and record["agent"] == "walker" and record["preset"] == "smoke"
    assert record["weights"] == rundir.weights_id(torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True))
    assert record["settings"] == {"eval_episodes": 1, "eval_steps": 10, "eval_seed": configs.TrainConfig.eval_seed}
    assert all(len(s["policy"]) == len(s["random"]) == 2 for s in scores.values())  # smoke: 2 demos x 1 episode
    assert os.path.getsize(os.path.join(smoke_run, "learning_curve.png")) > 1000
    imagination = json.load(open(os.path.join(smoke_run, "imagination.json")))
    assert set(imagination) == {"posterior_p_cos", "open_loop_p_cos", "open_loop"}
    assert -1 <= imagination["posterior_p_cos"] <= 1 and -1 <= imagination["open_loop_p_cos"] <= 1
    cfgs, models, _ = checkpoint.load_run(smoke_run)
    held_out = collect.load_folder(os.path.join(cfgs["train"].data, "walker"), ("state", "action", "is_first", "p"))[:: cfgs["train"].holdout_every]
    first = evaluate.evaluate_imagination(models, cfgs, held_out, "cpu")
    assert evaluate.evaluate_imagination(models, cfgs, held_out, "cpu") == first  # a fixed draw: reruns compare
    assert first == pytest.approx(imagination, rel=0.05)


def test_resume_continues_and_refuses_to_overwrite(smoke_run, smoke_data, tmp_path):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    cfgs = train.resolve_configs(train_args(data=smoke_data, steps=8), "smoke")
    with pytest.raises(ValueError, match="pass --resume"):
        train.train(cfgs, run, resume=False)
    train.train(cfgs, run, resume=True)
    assert torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == 8
    assert [json.loads(l)["step"] for l in open(os.path.join(run, "metrics.jsonl"))] == [2, 4, 6, 8]
    other = train.resolve_configs(train_args(data=smoke_data, **{"wm.deter": 32}), "smoke")
    with pytest.raises(ValueError, match=r"other wm\.deter"):
        train.train(other, run, resume=True)
    # a checkpoint written before a field existed resumes as that field's default, and only so
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    del ckpt["config"]["ac"]["goal_near"]
    torch.save(ckpt, os.path.join(run, "checkpoint.pt"))
    with pytest.raises(ValueError, match=r"other ac\.goal_near"):
        train.train(train.resolve_configs(train_args(data=smoke_data, steps=10, **{"ac.goal_near": 0.2}), "smoke"), run, resume=True)
    train.train(train.resolve_configs(train_args(data=smoke_data, steps=10), "smoke"), run, resume=True)
    assert torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == 10


def test_nan_loss_stops_and_keeps_last_checkpoint(smoke_run, smoke_data, tmp_path, monkeypatch):
    run = str(tmp_path / "run")
    shutil.copytree(smoke_run, run)
    before = open(os.path.join(run, "checkpoint.pt"), "rb").read()
    original = goal_vae.GoalVAE.loss
    monkeypatch.setattr(goal_vae.GoalVAE, "loss", lambda self, p, post: (original(self, p, post)[0] * float("nan"), {}))
    cfgs = train.resolve_configs(train_args(data=smoke_data, steps=12), "smoke")
    with pytest.raises(ValueError, match=r"Eq. 3 goal-VAE loss is nan at update 6.*checkpoint.pt \(update 6\), untouched"):
        train.train(cfgs, run, resume=True)
    assert open(os.path.join(run, "checkpoint.pt"), "rb").read() == before


def test_segments_stay_inside_episodes(smoke_data):
    episodes = collect.load_folder(os.path.join(smoke_data, "walker"), ("state", "action", "is_first", "p"))
    batch = collect.Segments(episodes, ("state", "is_first"), 8).sample(200, np.random.default_rng(0), "cpu")
    assert batch["state"].shape == (200, 8, 24)
    assert not batch["is_first"][:, 1:].any()  # an episode start can only open a segment
    for b in range(0, 200, 17):  # every segment is a slice of its own episode
        states = episodes[batch["episode"][b]]["state"]
        first = np.flatnonzero((states == batch["state"][b, 0].numpy()).all(1))[0]
        assert np.array_equal(states[first : first + 8], batch["state"][b].numpy())


def test_a_smaller_older_d_body_grows_to_the_preset_before_training(smoke_data, tmp_path, monkeypatch):
    """A D_body collected when the preset asked for fewer episodes per task, by code older than a CollectConfig field,
    is completed, not trained on as it is; what exists is kept."""
    root = str(tmp_path / "data")
    shutil.copytree(smoke_data, root)
    folder = os.path.join(root, "walker")
    complete = os.path.join(folder, collect.COMPLETE)
    older = {k: v for k, v in json.load(open(complete)).items() if k != "history_from"}  # written before history_from existed
    open(complete, "w").write(json.dumps(older))
    before = {n: os.path.getmtime(os.path.join(folder, n)) for n in os.listdir(folder) if n.endswith(".npz")}
    monkeypatch.setitem(configs.PRESETS["collect"], "smoke", {**configs.PRESETS["collect"]["smoke"], "task_episodes": 2})
    cfgs = train.resolve_configs(train_args(data=root), "smoke")
    _, data, held_out, _ = checkpoint.prepare_data(cfgs)
    names = [n for n in os.listdir(folder) if n.endswith(".npz")]
    assert len(names) == len(before) + len(envs.BODY_TASKS) and len(data.lengths) + len(held_out) == len(names)
    assert all(os.path.getmtime(os.path.join(folder, n)) == t for n, t in before.items())
    assert json.load(open(os.path.join(folder, collect.COMPLETE)))["task_episodes"] == 2


def test_paper_preset_builds_pixel_dreamer_sizes_and_updates(smoke_data, tmp_path):
    """The paper's sizes (pixels, GRU 1024, CNN depth 48) run a couple of updates on CPU with a tiny batch."""
    small = {"steps": 2, "policy_start": 1, "eval_episodes": 1, "eval_steps": 3, "holdout_every": 3, "log_every": 1,
             "checkpoint_every": 2, "wm.batch": 2, "wm.seq_len": 8, "ac.starts": 4, "ac.horizon": 3, "data": smoke_data}
    cfgs = train.resolve_configs(train_args(**small), "paper")
    assert (cfgs["wm"].obs, cfgs["wm"].deter, cfgs["wm"].cnn_depth) == ("pixels", 1024, 48)
    train.train(cfgs, str(tmp_path / "paper"), resume=False)
    ckpt = torch.load(tmp_path / "paper" / "checkpoint.pt", weights_only=True)
    assert ckpt["step"] == 2 and ckpt["obs_shape"] == (64, 64, 3)


def test_missing_checkpoint_names_the_train_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="python train.py --env walker"):
        checkpoint.load_run(str(tmp_path))


def test_command_line_runs_and_resumes(smoke_data, tmp_path):
    """`python train.py --preset smoke`, then `--resume --steps 8`, as a user types them."""
    import subprocess
    import sys

    run = str(tmp_path / "cli")
    base = [sys.executable, "train.py", "--env", "walker", "--preset", "smoke", "--data", smoke_data, "--run-dir", run]
    cwd = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    first = subprocess.run(base, cwd=cwd, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-2000:]
    assert "average stand/walk/run" in first.stdout
    evaluated = subprocess.run(base + ["--evaluate", "--eval-episodes", "2"], cwd=cwd, capture_output=True, text=True)
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    # other settings than the run's: written beside its goal_reaching.json, named by them; the kept one stays
    record = json.load(open(os.path.join(run, "goal_reaching_episodes2_steps10_seed30000.json")))
    assert all(len(s["policy"]) == 4 for s in record["scores"].values()) and record["settings"]["eval_episodes"] == 2  # 2 demos x 2
    assert json.load(open(os.path.join(run, "goal_reaching.json")))["settings"]["eval_episodes"] == 1
    other = tmp_path / "other"  # other demos (--data): scored beside the run's own benchmark, named by their folder
    shutil.copytree(os.path.join(smoke_data, "demos"), other / "demos")
    kept = open(os.path.join(run, "goal_reaching.json")).read()
    moved = subprocess.run(base + ["--evaluate", "--data", str(other)], cwd=cwd, capture_output=True, text=True)
    assert moved.returncode == 0, moved.stderr[-2000:]
    named = "goal_reaching_episodes1_steps10_seed30000_data-" + str(other).strip(os.sep).replace(os.sep, "-") + ".json"
    assert os.path.exists(os.path.join(run, named)) and open(os.path.join(run, "goal_reaching.json")).read() == kept
    again = subprocess.run(base + ["--resume", "--steps", "8"], cwd=cwd, capture_output=True, text=True)
    assert again.returncode == 0 and "resumed" in again.stdout
    assert torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == 8
    bad = subprocess.run(base[:3] + ["humanoid"], cwd=cwd, capture_output=True, text=True)
    assert bad.returncode != 0 and "valid body names are walker, stickman" in bad.stderr
    bad = subprocess.run(base + ["--preset", "big"], cwd=cwd, capture_output=True, text=True)  # refused before any work
    assert bad.returncode != 0 and "invalid choice: 'big' (choose from 'smoke', 'cpu', 'paper')" in bad.stderr
    gone = subprocess.run(base + ["--ac-mixture", "3"], cwd=cwd, capture_output=True, text=True)  # a deleted variant
    assert gone.returncode == 2 and "unrecognized arguments: --ac-mixture 3" in gone.stderr


def test_exported_agent_loads_weights_only_and_acts_like_its_run(smoke_run, tmp_path, monkeypatch, capsys):
    path = checkpoint.export_agent(smoke_run, str(tmp_path / "agents" / "walker"))
    agent = torch.load(path, weights_only=True)
    assert "optims" not in agent and "rng" not in agent
    # D_body is not shipped: the agent reads demos from its preset's default folder; where it trained is kept
    assert agent["config"]["train"]["data"] == configs.DATA["smoke"] and agent["trained_data"] == checkpoint.load_run(smoke_run)[0]["train"].data
    _, run_models, _ = checkpoint.load_run(smoke_run)
    _, agent_models, _ = checkpoint.load_run(os.path.dirname(path))
    for name, model in run_models.items():
        for (k, a), b in zip(model.state_dict().items(), agent_models[name].state_dict().values()):
            assert b.dtype == a.dtype and torch.equal(a, b), (name, k)
    # exporting over an agent needs force, and moves the old agent and what was measured on it aside (no table mixes the two)
    with open(os.path.join(os.path.dirname(path), "results.jsonl"), "w") as f:
        f.write('{"method": "GIIL-ZS"}\n')
    before = open(path, "rb").read()
    with pytest.raises(ValueError, match=r"walker/checkpoint.pt holds an agent already: pass --force to replace it"):
        checkpoint.export_agent(smoke_run, os.path.dirname(path))
    assert sorted(os.listdir(os.path.dirname(path))) == ["checkpoint.pt", "results.jsonl"]
    checkpoint.export_agent(smoke_run, os.path.dirname(path), force=True)
    assert not os.path.exists(os.path.join(os.path.dirname(path), "results.jsonl"))
    assert open(os.path.join(os.path.dirname(path), "previous_0", "results.jsonl")).read() == '{"method": "GIIL-ZS"}\n'
    assert open(os.path.join(os.path.dirname(path), "previous_0", "checkpoint.pt"), "rb").read() == before
    shutil.rmtree(os.path.join(os.path.dirname(path), "previous_0"))
    os.makedirs(os.path.join(os.path.dirname(path), "previous_1"))  # a gap: the next export takes the first free name
    with open(os.path.join(os.path.dirname(path), "results.jsonl"), "w") as f:
        f.write('{"method": "GIIL-FT"}\n')
    checkpoint.export_agent(smoke_run, os.path.dirname(path), force=True)
    assert open(os.path.join(os.path.dirname(path), "previous_0", "results.jsonl")).read() == '{"method": "GIIL-FT"}\n'
    # phase 2's default: the user's own run when there is one, else the shipped agent, saying which
    monkeypatch.chdir(tmp_path)
    assert checkpoint.resolve_run("walker", "cpu") == os.path.join("agents", "walker")
    assert "using the shipped walker agent agents/walker" in capsys.readouterr().out
    os.makedirs(checkpoint.default_run_dir("walker", "cpu"))
    shutil.copy(os.path.join(smoke_run, "checkpoint.pt"), checkpoint.default_run_dir("walker", "cpu"))
    assert checkpoint.resolve_run("walker", "cpu") == checkpoint.default_run_dir("walker", "cpu")


def test_a_copy_of_an_exported_agent_trains_on_from_its_weights(smoke_run, smoke_data, tmp_path):
    """--resume in a folder holding a shipped agent (no optimiser state): training goes on from its weights, its step
    count, with fresh Adam moments (their step counters restart), and the result resumes like any run."""
    run = str(tmp_path / "longer")
    checkpoint.export_agent(smoke_run, run)
    shipped = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    steps = configs.PRESETS["train"]["smoke"]["steps"]
    train.train(train.resolve_configs(train_args(data=smoke_data, steps=steps + 2), "smoke"), run, resume=True)
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    assert ckpt["step"] == steps + 2 and "optims" in ckpt
    assert {int(s["step"]) for s in ckpt["optims"]["world_model"]["state"].values()} == {2}  # fresh Adam, 2 updates
    change = [(ckpt["models"]["world_model"][k] - a).abs().max().item() for k, a in shipped["models"]["world_model"].items()]
    lr = train.resolve_configs(train_args(), "smoke")["wm"].lr
    assert 0 < max(change) <= 2 * 2 * lr  # trained on from the shipped weights: two Adam steps (each <~ lr) away, not re-initialised
    assert [json.loads(l)["step"] for l in open(os.path.join(run, "metrics.jsonl"))] == [steps + 2]
    train.train(train.resolve_configs(train_args(data=smoke_data, steps=steps + 4), "smoke"), run, resume=True)
    assert torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)["step"] == steps + 4


def test_bc_steps_are_extra_actor_steps(smoke_data, tmp_path):
    """--ac-bc-steps 3: each Eq. 4 update of the actor is followed by 2 steps on bc_loss alone (Adam counts 3 per update);
    the log has the gradient norm of each term."""
    cfgs = train.resolve_configs(train_args(data=smoke_data, **{"cloning.bc": 1.0, "cloning.bc_steps": 3}), "smoke")
    run = train.train(cfgs, str(tmp_path / "bc_steps"), resume=False)
    ckpt = torch.load(os.path.join(run, "checkpoint.pt"), weights_only=True)
    tc = cfgs["train"]
    actor_steps = {int(s["step"]) for s in ckpt["optims"]["actor"]["state"].values()}
    assert actor_steps == {3 * (tc.steps - tc.policy_start)}
    assert {int(s["step"]) for s in ckpt["optims"]["critic"]["state"].values()} == {tc.steps - tc.policy_start}
    last = [json.loads(l) for l in open(os.path.join(run, "metrics.jsonl"))][-1]
    assert np.isfinite(last["reward"]) and "bc_loss" in last
    assert last["grad_eq4"] > 0 and last["grad_bc"] > 0  # each term's share of the actor's step, logged


def test_polish_clones_on_the_final_models_and_leaves_training_untouched(smoke_data, tmp_path):
    """--ac-bc-polish N: after the last update, N cloning steps of the actor alone. The checkpoint's actor is the polished
    one; the world model, the training actor (kept as actor_unpolished) and the RNG are those of the same run without
    polish, and a resumed run trains on from the unpolished actor, as if no polish had been."""
    def run(name, steps, polish, resume=False):
        cfgs = train.resolve_configs(train_args(data=smoke_data, steps=steps, **{"cloning.bc": 1.0, "cloning.bc_polish": polish}), "smoke")
        train.train(cfgs, str(tmp_path / name), resume=resume)
        return torch.load(os.path.join(tmp_path, name, "checkpoint.pt"), weights_only=True)

    plain, polished = run("plain", 6, 0), run("polished", 6, 20)
    assert "actor_unpolished" not in plain and polished["config"]["cloning"]["bc_polish"] == 20
    same = lambda a, b: a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert same(polished["actor_unpolished"], plain["models"]["actor"])
    assert not same(polished["models"]["actor"], plain["models"]["actor"])
    assert same(polished["models"]["world_model"], plain["models"]["world_model"])
    assert torch.equal(polished["torch_rng"], plain["torch_rng"]) and polished["rng"] == plain["rng"]
    assert same(run("plain", 8, 0, resume=True)["models"]["actor"], run("polished", 8, 0, resume=True)["models"]["actor"])


def test_a_config_stored_before_the_cloning_had_its_own_reads_the_actor_critics_cloning_fields(smoke_run, tmp_path):
    """The shipped agents keep the cloning's fields (bc, bc_final, ...) in the actor-critic's config: they load into
    configs.CloningConfig, with the same values, and the run resumes as if stored today."""
    ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
    old = {k: v for k, v in ckpt["config"].items() if k != "cloning"}
    old["ac"] = {**ckpt["config"]["ac"], **ckpt["config"]["cloning"], "bc_final": 0.25}
    torch.save(dict(ckpt, config=old), tmp_path / "checkpoint.pt")
    cfgs = checkpoint.load_run(str(tmp_path))[0]
    assert cfgs["cloning"] == dataclasses.replace(checkpoint.load_run(smoke_run)[0]["cloning"], bc_final=0.25)
    assert cfgs["ac"] == checkpoint.load_run(smoke_run)[0]["ac"]


def test_a_stored_config_with_a_deleted_switch_loads_at_its_off_value_and_is_refused_on(smoke_run, tmp_path):
    """The shipped agents store fields of switches since deleted (checkpoint.REMOVED): at their off value they are
    dropped and the run loads and resumes as before; switched on, a one-line error names the flag and where its commit is."""
    ckpt = torch.load(os.path.join(smoke_run, "checkpoint.pt"), weights_only=True)
    off = dict(ckpt["config"], train={**ckpt["config"]["train"], "act_temperature": 0.0, "cover_edges": 0},
               ac={**ckpt["config"]["ac"], "reward": "distance", "mixture": 1, "uncertainty": 0.0},
               cloning={**ckpt["config"]["cloning"], "bc_polish_fresh": 0})
    torch.save(dict(ckpt, config=off), tmp_path / "checkpoint.pt")
    cfgs, models, _ = checkpoint.load_run(str(tmp_path))
    assert cfgs == checkpoint.load_run(smoke_run)[0]
    torch.save(dict(ckpt, config=dict(off, ac={**off["ac"], "mixture": 3})), tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"trained with --ac-mixture 3, a variant measured worse and deleted \(docs/ablations.md names the commit that had it\)"):
        checkpoint.load_run(str(tmp_path))
    pixels = train.resolve_configs(train_args(**{"wm.obs": "pixels"}), "smoke")  # the cpu recipe's d reads decoded state vectors
    with pytest.raises(ValueError, match="--dist-input obs reads decoded state vectors: with --obs pixels pass --dist-input feat"):
        checkpoint.build_models(pixels, (64, 64, 3), 6, 64, "cpu")


def test_gradient_norms_are_each_losss_own_and_leave_grad_untouched():
    """train.gradient_norms: the L2 norm over all parameters of each loss's gradient, computed apart (the sum's is not the sum
    of the norms), with .grad left as it was for the optimiser step that follows."""
    lin = torch.nn.Linear(3, 2)
    x = torch.randn(4, 3)
    first, second = lin(x).sum(), (lin(x) ** 2).sum()
    norms = train.gradient_norms(lin, first=first, second=second)
    # d first / dW = 1 x (sum over rows of x) for each output, d first / db = (4, 4)
    expected = torch.sqrt(2 * (x.sum(0) ** 2).sum() + 2 * 4.0**2)
    assert norms["grad_first"] == pytest.approx(expected.item(), rel=1e-5)
    y = lin(x).detach()
    expected = torch.sqrt(((2 * y.T @ x) ** 2).sum() + ((2 * y.sum(0)) ** 2).sum())
    assert norms["grad_second"] == pytest.approx(expected.item(), rel=1e-5)
    assert lin.weight.grad is None and lin.bias.grad is None
    (first + second).backward()  # the graphs were kept for the step itself
    assert lin.weight.grad is not None
