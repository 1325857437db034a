"""ot_reward.py: Sinkhorn against POT, the small-eps limit against exact OT (ot.emd), costs near 2 in
float32, the best-matching demo, windowed matching, chunking, bad input."""
import math

import ot
import pytest
import torch
import torch.nn.functional as F

import bench
import ot_reward
from configs import OTConfig
from ot_reward import cosine_cost, sinkhorn

torch.set_num_threads(1)


def unit(*shape, seed, dtype=torch.float64):
    return F.normalize(torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype), dim=-1)


def uniform(n):
    return torch.full((n,), 1 / n, dtype=torch.float64)


def test_cosine_cost_values_and_range():
    x = torch.tensor([[1.0, 0.0], [0.0, 3.0], [-2.0, 0.0]], dtype=torch.float64)  # norms 1, 3, 2: normalised inside
    y = torch.tensor([[5.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(cosine_cost(x, y), torch.tensor([[0.0], [1.0], [2.0]], dtype=torch.float64))
    cost = cosine_cost(unit(2, 7, 16, seed=0), unit(2, 9, 16, seed=1))  # batched (..., N, D) x (..., M, D)
    assert cost.shape == (2, 7, 9) and 0 <= cost.min() and cost.max() <= 2


def test_sinkhorn_equals_pot_iteration_for_iteration():
    """Same iteration as ot.sinkhorn: equal plans after 30 iterations, far from converged."""
    cost = 2 * torch.rand(3, 5, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    plan = sinkhorn(cost, eps=0.01, iters=30)
    for c, p in zip(cost, plan):
        expected = ot.sinkhorn(uniform(5), uniform(7), c, 0.01, method="sinkhorn_log", numItermax=30, stopThr=0, warn=False)
        assert torch.allclose(p, expected, rtol=0, atol=1e-12)
    assert torch.allclose(plan.sum(-1), torch.full((3, 5), 1 / 5, dtype=torch.float64))  # u's update is last: rows exact


def test_reward_equals_exact_ot_in_small_eps_limit():
    """N = M = 5, agent = permuted noisy demo: the exact plan is a permutation; ROT's reward equals ot.emd's."""
    demo_p = unit(5, 8, seed=0)
    agent_p = F.normalize(demo_p[[3, 0, 4, 1, 2]] + 0.05 * unit(5, 8, seed=1), dim=-1)[None]  # (1, 5, 8)
    reward, _ = ot_reward.ot_reward(agent_p, demo_p, OTConfig(eps=0.004, iters=2000))
    cost = cosine_cost(agent_p[0], demo_p)
    plan = ot.emd(uniform(5), uniform(5), cost)
    assert torch.allclose(reward[0], -(plan * cost).sum(1), rtol=0, atol=1e-9)
    assert reward[0].sum().item() == pytest.approx(-ot.emd2(uniform(5), uniform(5), cost).item(), abs=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_transport_cost_within_entropic_bound_of_exact_ot(seed):
    """Generic random costs, 5 x 7: 0 <= <P_eps, C> - W_emd <= eps * log(min(N, M)) (entropy of the plans)."""
    agent_p, demo_p = unit(1, 5, 3, seed=2 * seed), unit(7, 3, seed=2 * seed + 1)
    cfg = OTConfig(eps=0.004, iters=3000)
    reward, _ = ot_reward.ot_reward(agent_p, demo_p, cfg)
    exact = ot.emd2(uniform(5), uniform(7), cosine_cost(agent_p[0], demo_p)).item()
    assert -1e-9 <= -reward.sum().item() - exact <= cfg.eps * math.log(5)


def test_costs_near_2_in_float32():
    """Agent nearly antipodal to the demo, float32 features: the worst reward (~ -2/T per step), not 0."""
    T, M = 6, 20
    mu = unit(16, seed=0, dtype=torch.float32)
    demo_p = F.normalize(mu + 0.1 * unit(M, 16, seed=1, dtype=torch.float32), dim=-1)  # (M, 16) around mu
    agent_p = F.normalize(-mu + 0.1 * unit(1, T, 16, seed=2, dtype=torch.float32), dim=-1)  # (1, T, 16) around -mu
    cost = cosine_cost(agent_p[0].double(), demo_p.double())
    assert cost.min() > 1.9 and (torch.exp(-cost.float() / 0.01) == 0).all()  # the float32 pitfall is live here
    reward, _ = ot_reward.ot_reward(agent_p, demo_p, OTConfig())
    assert reward.dtype == torch.float32 and (reward < -1.9 / T).all()
    plan = ot.sinkhorn(uniform(T), uniform(M), cost, 0.01, method="sinkhorn_log", numItermax=100, stopThr=0, warn=False)
    assert torch.allclose(reward[0].double(), -(plan * cost).sum(1), rtol=1e-6, atol=0)


def test_best_matching_demo_is_chosen():
    """Each trajectory is one of the demos (plus noise): that demo is chosen, with its own rewards."""
    T, K = 8, 4
    demos = unit(K, T, 16, seed=0)
    agent_p = F.normalize(demos[[2, 0, 3]] + 0.05 * unit(3, T, 16, seed=1), dim=-1)  # (3, T, 16)
    reward, best = ot_reward.ot_reward(agent_p, demos, OTConfig())
    assert best.tolist() == [2, 0, 3]
    for b, k in enumerate(best.tolist()):
        alone, _ = ot_reward.ot_reward(agent_p[b : b + 1], demos[k], OTConfig())
        assert torch.allclose(reward[b], alone[0], rtol=0, atol=1e-12)
    assert (reward > -0.05).all()  # a near-copy costs little


def test_windowed_matching_uses_the_aligned_window():
    """demo_offsets: the reward equals whole-demo matching against the window; past the end, the last T frames."""
    T, M = 5, 30
    demos = unit(2, M, 16, seed=0)
    agent_p = unit(3, T, 16, seed=1)
    offsets = torch.tensor([0, 12, M - 2])
    reward, best = ot_reward.ot_reward(agent_p, demos, OTConfig(), demo_offsets=offsets)
    for b, start in enumerate([0, 12, M - T]):
        alone, k = ot_reward.ot_reward(agent_p[b : b + 1], demos[:, start : start + T], OTConfig())
        assert best[b] == k[0] and torch.allclose(reward[b], alone[0], rtol=0, atol=1e-12)


def reference_reward(agent_p, demo_p, cfg, offsets=None):
    """App. C written out one trajectory and one demo at a time (the windows gathered, as ot_reward computed them before
    it normalised the demos once per call): r_t = -scale sum_j P_tj C_tj against the demo of least <P, C>."""
    rewards, bests = [], []
    for b in range(len(agent_p)):
        x = agent_p[b].double()
        targets = [d.double() if offsets is None else d.double()[min(offsets[b].item(), d.shape[0] - len(x)) :][: len(x)] for d in demo_p]
        plans = [sinkhorn(cosine_cost(x, y).detach(), cfg.eps, cfg.iters) for y in targets]
        k = min(range(len(targets)), key=lambda i: (plans[i] * cosine_cost(x, targets[i])).sum().item())
        rewards.append(-cfg.scale * (plans[k] * cosine_cost(x, targets[k])).sum(-1))
        bests.append(k)
    return torch.stack(rewards).float(), torch.tensor(bests)


@pytest.mark.parametrize("windowed", [False, True])
def test_reward_and_gradient_equal_the_definition(windowed):
    """The batched reward (demos normalised once, each window a view) and its gradient equal App. C trajectory by trajectory."""
    gen = torch.Generator().manual_seed(0)
    demo_p = 3 * torch.rand(4, 40, 16, generator=gen)  # not unit norm, float32: normalised inside
    agent_p = torch.randn(9, 6, 16, generator=gen, requires_grad=True)
    offsets = torch.randint(0, 40, (9,), generator=gen) if windowed else None
    reward, best = ot_reward.ot_reward(agent_p, demo_p, OTConfig(scale=2.0), offsets)
    grad, = torch.autograd.grad(reward.sum(), agent_p)
    expected, expected_best = reference_reward(agent_p, demo_p, OTConfig(scale=2.0), offsets)
    expected_grad, = torch.autograd.grad(expected.sum(), agent_p)
    assert torch.equal(best, expected_best)
    assert torch.allclose(reward, expected, rtol=0, atol=1e-6) and torch.allclose(grad, expected_grad, rtol=1e-5, atol=1e-7)


def test_chunks_do_not_change_the_reward():
    agent_p, demos = unit(7, 6, 16, seed=0), unit(3, 40, 16, seed=1)
    one_batch = ot_reward.ot_reward(agent_p, demos, OTConfig(cpu_chunk_bytes=2**40))
    one_by_one = ot_reward.ot_reward(agent_p, demos, OTConfig(cpu_chunk_bytes=1))
    assert torch.equal(one_batch[1], one_by_one[1]) and torch.allclose(one_batch[0], one_by_one[0], rtol=0, atol=1e-14)


def test_shapes_and_dtype():
    agent_p = torch.randn(4, 6, 16)  # float32, not unit norm
    reward, best = ot_reward.ot_reward(agent_p, unit(30, 16, seed=0), OTConfig())  # one demo (M, D)
    assert reward.shape == (4, 6) and reward.dtype == torch.float32 and not reward.requires_grad
    assert best.tolist() == [0, 0, 0, 0]
    reward, best = ot_reward.ot_reward(agent_p, unit(3, 30, 16, seed=0), OTConfig(scale=10))  # K demos
    assert reward.shape == (4, 6) and best.shape == (4,) and (reward <= 0).all()


def test_gradient_is_that_of_the_entropic_ot_cost():
    """With the plan held constant, d(sum_t r_t)/dx equals minus the gradient of the entropic OT cost
    min_P <P, C(x)> + eps sum P (log P - 1), here differentiated through a fully converged, unrolled Sinkhorn."""
    eps, iters = 0.05, 500
    agent_p = torch.randn(2, 6, 16, dtype=torch.float64, requires_grad=True)
    demo = unit(9, 16, seed=1).double()
    reward, _ = ot_reward.ot_reward(agent_p, demo, OTConfig(eps=eps, iters=iters))
    (ours,) = torch.autograd.grad(reward.sum(), agent_p)
    cost = ot_reward.cosine_cost(agent_p, demo.expand(2, 9, 16))
    plan = ot_reward.sinkhorn(cost, eps, iters)  # differentiable in agent_p through every iteration
    value = (plan * cost).sum() + eps * (plan * (plan.log() - 1)).sum()
    (reference,) = torch.autograd.grad(value, agent_p)
    assert ours.abs().max() > 1e-3
    assert torch.allclose(ours, -reference, atol=1e-6)


nan_demo = unit(30, 16, seed=0).clone()
nan_demo[3, 5] = float("nan")


@pytest.mark.parametrize(
    "agent_p, demo_p, offsets, match",
    [
        (torch.randn(4, 6, 16), torch.zeros(0, 16), None, "demo_p must be a non-empty"),
        (torch.randn(4, 6, 16), torch.zeros(3, 0, 16), None, "demo_p must be a non-empty"),
        (torch.randn(6, 16), unit(30, 16, seed=0), None, r"agent_p must be a non-empty \(B, T, D\)"),
        (torch.randn(4, 6, 16), nan_demo, None, "demo_p contains NaN"),
        (torch.randn(4, 6, 16), torch.full((30, 16), float("inf")), None, "demo_p contains NaN or inf"),
        (torch.full((4, 6, 16), float("nan")), unit(30, 16, seed=0), None, "agent_p contains NaN"),
        (torch.randn(4, 6, 8), unit(30, 16, seed=0), None, "feature sizes differ"),
        (torch.randn(4, 6, 16), unit(30, 16, seed=0), torch.tensor([0, 1]), r"demo_offsets must be a \(B,\)"),
        (torch.randn(4, 6, 16), unit(30, 16, seed=0), torch.tensor([0, -1, 2, 3]), "demo_offsets must be >= 0"),
        (torch.randn(4, 6, 16), unit(5, 16, seed=0), torch.tensor([0, 1, 2, 3]), "at least T=6 frames"),
    ],
)
def test_bad_input(agent_p, demo_p, offsets, match):
    with pytest.raises(ValueError, match=match):
        ot_reward.ot_reward(agent_p, demo_p, OTConfig(), demo_offsets=offsets)


def test_bad_config():
    with pytest.raises(ValueError, match="underflows float64"):
        OTConfig(eps=0.001)
    with pytest.raises(ValueError, match="at least one iteration"):
        OTConfig(iters=0)


def test_bench_runs_and_restores_threads():
    threads = torch.get_num_threads()
    result = bench.ot_seconds(B=2, T=4, M=8, K=2, D=8, repeat=1)
    assert result["whole_demo_s"] > 0 and result["window_s"] > 0 and torch.get_num_threads() == threads
