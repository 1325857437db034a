"""App. C and Eq. 5: the optimal-transport reward r^ot(s_t) of imagined trajectories against demonstrations.

ROT (Haldar et al., 2022), which the paper cites for r^ot: the cost between an agent frame and a demo
frame is the cosine distance of their video features p (App. C: the features lie on the unit sphere,
so the cost lives there, not in the world model's latent space); the entropic OT plan P between the
two sets of frames, with uniform marginals, comes from Sinkhorn; agent step i earns
    r_i = -scale * sum_j P_ij C_ij.
Against several demos, each trajectory takes its rewards from the demo with the smallest total
transport cost <P, C> (ROT, AIME-NoB). Nothing is differentiated through Sinkhorn: the plan is a constant,
and the reward is differentiable in the agent's features through the cost alone (ot_reward).

Which demo frames an imagined segment (T ~ 16 steps) is matched against, the paper leaves open:
* whole demo (default): the segment's T frames against all M frames of a demo. Each agent step
  carries mass 1/T, spread over ~M/T demo frames, so a segment is rewarded for reproducing the demo's
  distribution of frames (App. C's "distributional similarity"); no time alignment is needed, so it
  works from any imagined start state, and a periodic gait is matched phase by phase (the features
  are of frame windows, so they carry the direction of motion). Demo frames that no T-step segment
  can cover (e.g. the first frames of standing up) add a cost common to all segments.
* window (`demo_offsets`): when imagination starts from the goal-encoder state of demo frame t0
  (Eq. 5 draws start states from D_demo), the T imagined steps are matched against the T demo
  frames that follow it, offset .. offset + T - 1 (OT still lets steps swap within the window):
  a sharper, time-aligned reward at T/M of the cost. With K demos, each demo's window at that
  offset is a candidate and the best-matching one counts, as for whole demos.

eps is absolute, as in ROT: the cosine cost is bounded in [0, 2] for any demo, so eps = 0.01 means
the same sharpness on every demo (a relative eps, eps x mean cost, would change with how alike a
demo's frames are). Costs near 2 make the kernel exp(-C/eps) as small as exp(-200) at eps 0.01.

Sinkhorn is solved here, batched over trajectories and demos, in torch: the scaling-domain iteration
of POT's ot.sinkhorn, in float64 (IEEE 754: exp(-C/eps) is 0 in float32 for C > 1.03 at eps 0.01,
which makes the worst frames earn the best reward, 0). POT is the reference the tests check against:
ot.sinkhorn(method='sinkhorn_log') iteration for iteration, and ot.emd in the small-eps limit. POT
in the main path (per-pair ot.sinkhorn, ot.batch.solve_batch) was several times slower at bench.py's
size, and so was the log-domain form of this loop against the scaling form (docs/results.md, Speed).
"""

import torch
import torch.nn.functional as F

EPS_MIN = 0.004  # float64: exp(-2/eps) = exp(-500) ~ 7e-218 stays above the smallest normal 2e-308, with room for u, v


def cosine_cost(x, y):
    """C = 1 - cos(x, y) in [0, 2]: x (..., N, D), y (..., M, D) -> (..., N, M); rows need not be unit norm."""
    cos = F.normalize(x, dim=-1) @ F.normalize(y, dim=-1).mT  # (..., N, M)
    return (1 - cos).clamp(0, 2)  # rounding can step just outside [0, 2]


def sinkhorn(cost, eps, iters):
    """Entropic OT plans with uniform marginals for a batch of costs (..., N, M), float64 -> (..., N, M).

    POT's ot.sinkhorn iteration (u = 1; then v = b / K^T u, u = a / K v), so after `iters` iterations
    the plan equals ot.sinkhorn(a, b, C, eps, method='sinkhorn_log', numItermax=iters, stopThr=0).
    The last update is u's: every row of the plan sums exactly to a = 1/N.
    """
    N, M = cost.shape[-2:]
    kernel = torch.exp(-cost / eps)  # (..., N, M) K = exp(-C/eps) >= exp(-2/eps), a normal float64 for eps >= EPS_MIN
    u = torch.ones_like(cost[..., :1])  # (..., N, 1)
    for _ in range(iters):
        v = (1 / M) / (u.mT @ kernel)  # (..., 1, M) b = 1/M
        u = (1 / N) / (kernel @ v.mT)  # (..., N, 1) a = 1/N
    return u * kernel * v  # (..., N, M) P = diag(u) K diag(v)


def _check_inputs(agent_p, demo_p, demo_offsets):
    """One-line ValueErrors for what would otherwise fail deep inside, or silently give a wrong reward."""
    if agent_p.ndim != 3 or 0 in agent_p.shape:
        raise ValueError(f"agent_p must be a non-empty (B, T, D) tensor of imagined features, got shape {tuple(agent_p.shape)}")
    if demo_p.ndim not in (2, 3) or 0 in demo_p.shape:
        raise ValueError(f"demo_p must be a non-empty (M, D) or (K, M, D) tensor of demo features, got shape {tuple(demo_p.shape)}")
    if demo_p.shape[-1] != agent_p.shape[-1]:
        raise ValueError(f"feature sizes differ: agent_p has D={agent_p.shape[-1]}, demo_p has D={demo_p.shape[-1]}")
    for name, p in (("agent_p", agent_p), ("demo_p", demo_p)):
        # NaN and inf reach a float64 sum, which float32 values cannot overflow: one pass, cheaper than isfinite(p).all()
        if not torch.isfinite(p.sum(dtype=torch.float64)):
            raise ValueError(f"{name} contains NaN or inf")
    if demo_offsets is None:
        return
    B, T, _ = agent_p.shape
    if demo_offsets.shape != (B,) or demo_offsets.is_floating_point():
        raise ValueError(f"demo_offsets must be a (B,) = ({B},) integer tensor, got {demo_offsets.dtype} of shape {tuple(demo_offsets.shape)}")
    if (demo_offsets < 0).any():
        raise ValueError(f"demo_offsets must be >= 0, got min {demo_offsets.min().item()}")
    if demo_p.shape[-2] < T:
        raise ValueError(f"windowed matching needs demos of at least T={T} frames, got M={demo_p.shape[-2]}")


def ot_reward(agent_p, demo_p, cfg, demo_offsets=None):
    """Per-step OT reward of B imagined trajectories against the best-matching of K demos (App. C).

    agent_p (B, T, D): video features decoded from imagined states (any norm: normalised here).
    demo_p (M, D) or (K, M, D): the demos' video features.
    demo_offsets (B,) integer, optional: windowed matching; agent step t of trajectory b is matched
      within demo frames demo_offsets[b] + 0..T-1, the window moved back to end at the demo's last
      frame where it would run past it. Without it, whole-demo matching.
    Returns reward (B, T) in agent_p's dtype and on its device, and best (B,) the index of the demo
    each trajectory was matched to. The plans and the choice of demo carry no gradient; where agent_p
    requires grad, the reward is differentiable through the cost with the plan held constant (for the
    entropic OT cost <P, C> - eps H(P) this is its exact gradient: the envelope theorem), so the
    imagined lambda-returns of Eq. 5 reach g through the OT cost as Dreamer's returns do through a reward model.
    """
    _check_inputs(agent_p, demo_p, demo_offsets)
    p = F.normalize(agent_p.to(torch.float64), dim=-1)  # float64 throughout: exp(-C/eps) underflows in float32 (docs/sources.md)
    raw = demo_p.to(p.device, torch.float64).reshape(-1, *demo_p.shape[-2:])  # (K, M, D)
    # unit demo frames, once per call: normalising each trajectory's gathered copy of them cost more than Sinkhorn (bench.py --only ot)
    demo = F.normalize(raw, dim=-1)
    (B, T, D), (K, M, _) = p.shape, demo.shape
    if demo_offsets is None:
        start = None
        cos_of = lambda b: p[b, None] @ demo.mT  # (b, 1, T, D) @ (K, D, M) -> (b, K, T, M): every trajectory against every whole demo
    else:
        start = demo_offsets.to(p.device).clamp(max=M - T).tolist()  # B ints
        # each trajectory against its window in every demo, a view of the demo's frames: (K, T, D) @ (D, T) -> (K, T_demo, T)
        cos_of = lambda b: torch.stack([(demo[:, start[i] : start[i] + T] @ p[i].T).mT for i in b.tolist()])
    width = M if start is None else T
    chunk = max(1, cfg.cpu_chunk_bytes // (8 * K * T * width)) if p.device.type == "cpu" else B  # one trajectory's float64 kernels
    best, plans = [], []
    with torch.no_grad():  # nothing is differentiated through Sinkhorn
        for b in torch.arange(B, device=p.device).split(chunk):
            cost = (1 - cos_of(b)).clamp(0, 2)  # (b, K, T, M or T), cosine_cost of the unit rows
            plan = sinkhorn(cost, cfg.eps, cfg.iters)  # (b, K, T, M or T)
            k = (plan * cost).sum((-2, -1)).argmin(-1)  # (b,) smallest total transport cost <P, C> (ROT)
            best.append(k)
            plans.append(plan[torch.arange(len(k), device=p.device), k])  # (b, T, M or T)
    best, plan = torch.cat(best), torch.cat(plans)  # (B,), (B, T, M or T)
    if start is None:
        matched = raw[best]  # (B, M, D)
    else:
        matched = torch.stack([raw[k, s : s + T] for k, s in zip(best.tolist(), start)])  # (B, T, D)
    cost = cosine_cost(agent_p.to(torch.float64), matched)  # (B, T, M or T), differentiable in agent_p
    reward = -cfg.scale * (plan * cost).sum(-1)  # (B, T)
    return reward.to(agent_p.dtype), best
