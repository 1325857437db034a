"""The tests' shared fixtures and helpers (the smoke data and phase-1 run, config namespaces, a killed baseline seed),
loaded for tests/ and probes/ alike by the root conftest.py (pytest_plugins)."""
import argparse
import dataclasses

import pytest
import torch
import torch.nn.functional as F

import collect
import configs
import train
from baselines import genrl


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory):
    """D_body of the walker and D_demo, smoke preset (a few 20-step episodes), in a temporary data folder."""
    root = str(tmp_path_factory.mktemp("data"))
    cfg = configs.CollectConfig(**configs.PRESETS["collect"]["smoke"])
    collect.collect_body("walker", cfg, root, workers=2)
    collect.collect_demos(cfg, root, workers=2)
    return root


@pytest.fixture(scope="session")
def smoke_run(smoke_data, tmp_path_factory):
    """A phase-1 run of the walker with the smoke preset; returns its folder."""
    cfgs = train.resolve_configs(train_args(data=smoke_data), "smoke")
    run_dir = str(tmp_path_factory.mktemp("runs") / "walker_smoke")
    train.train(cfgs, run_dir, resume=False)
    return run_dir


def train_args(**given):
    """An argparse-like namespace for train.resolve_configs: 'component.field' -> value (None = not given)."""
    ns = argparse.Namespace()
    for name, (cls, _) in configs.COMPONENTS.items():
        for field in dataclasses.fields(cls):
            setattr(ns, f"{name}.{field.name}", given.pop(field.name if name == "train" else f"{name}.{field.name}", None))
    assert not given, f"no such config field: {sorted(given)}"  # a typo would test the default
    return ns


def kill_at_evaluation(monkeypatch, n):
    """A baseline's n-th seed evaluation (genrl.evaluate_actor) raises KeyboardInterrupt, as a kill there would;
    returns the real function (to put back with monkeypatch.setattr)."""
    evaluate_actor, calls = genrl.evaluate_actor, []

    def killed(*args):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return evaluate_actor(*args)

    monkeypatch.setattr(genrl, "evaluate_actor", killed)
    return evaluate_actor


def random_batch(obs, obs_shape, action_dim, batch, seq_len, p_dim=64, seed=0):
    """A batch with collect.py's keys and shapes, filled with noise: for benchmarks and shape tests."""
    g = torch.Generator().manual_seed(seed)
    B, T = batch, seq_len
    if obs == "state":
        data = {"state": torch.randn(B, T, obs_shape, generator=g)}
    else:
        data = {"pixels": torch.randint(0, 256, (B, T, *obs_shape), generator=g, dtype=torch.uint8)}
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True
    action = torch.rand(B, T, action_dim, generator=g) * 2 - 1
    action[:, 0] = 0
    p = F.normalize(torch.randn(B, T, p_dim, generator=g), dim=-1)
    return {**data, "action": action, "reward": torch.zeros(B, T), "is_first": is_first, "p": p, "episode": torch.arange(B)}
