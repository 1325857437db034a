"""Eq. 6-7 and App. B: the temporal distance network d(s_i, s_j), its regression + contrastive loss.

Eq. 6, D^dis(s_i, s_j) = (j - i) / T for j > i in one trajectory. T is "the maximum trajectory horizon"; pairs
are drawn inside a training segment, so the longest horizon a pair spans is the segment length, and that is the
T we use (train.py passes seq_len). LEXA (Mendonca et al. 2021) labels (j - i) / H over its sampled sequences the
same way. With the 500-step episode length instead, every same-trajectory label would sit below 0.1 and the
goal reward -d would barely change over an imagined horizon of 15 steps.

Eq. 7's sign. As printed, Eq. 7 subtracts the contrastive term, -E_{i != j} ||d(s^(i), s^(j)) - 1||^2. Minimised
literally, it rewards predictions far from 1 without bound (d -> +-inf for states of different trajectories),
which contradicts the text ("penalizes small predicted distances between states from different trajectories").
We read the minus as a typo and add the term, regressing cross-trajectory pairs to 1, LEXA's label for negatives.

Pair sampling (the paper does not say; ours): positives are uniform pairs i < j inside one segment that do not
cross an episode start; negatives are uniform pairs of steps from two segments of different episode ids (a
segment that runs into the next episode keeps its first episode's id: rare, and label noise only if that next
episode is the other segment's). Eq. 7 is a sum of two expectations, so each term is a mean over its own pairs
and the two are weighted equally (contrastive_weight = 1); LEXA instead mixes ~10% negatives into one mean,
i.e. a weight of about 0.11.

Which goals d is trained on (ours; the paper trains d on pairs of posterior states only). The policy is given
goals from the goal encoder, g = q(s | p_j) (GIIL-ZS feeds it q(s | p_T) of a demo), which a d trained on posterior
pairs alone does not rank (docs/ablations.md, Phase 1). With `encoder_goals` (default) every pair is scored twice,
with the later state as the world model's posterior feat_j and as the goal encoder's g_j of the same frame, against
the same Eq. 6 target: the posterior's h_t carries the episode's history, which lets d answer "same trajectory?"
instead of "how far?"; g_j is read from an 8-frame video window and has no such shortcut. contrastive_weight 0.1 in
the cpu preset follows LEXA's share of negatives.

What d reads (ours, `input`). LEXA reads an embedding of the observation; `input = "obs"` does the same with the
world model's own decoder: d reads the decoded observation (symlog of the state vector) of s and of g, which holds the
body's pose and velocities and no history (in imagination, h continues the start state's history; docs/ablations.md,
Phase 1, has what each input measured). `input = "feat"` is Eq. 7 as written.

d fit by temporal differences instead (HILP's value learning, Park et al. 2024) was measured in training and not kept
(docs/ablations.md, Phase 1); it lives in probes/distance_probe.py, the lead of Eq. 4 started from the clone.
"""
import torch
import torch.nn as nn

from world_model import mlp


class DistanceNet(nn.Module):
    """d_{theta^dis}(s_i, s_j): an MLP on [embed(feat_i), embed(feat_j)] -> predicted temporal distance in units of T.
    embed is the identity (cfg.input 'feat') or the world model's observation decoder ('obs'), held as a plain function:
    it stays the world model's, trained by Eq. 2 only, and is not among this network's parameters or state."""

    def __init__(self, cfg, feat_dim, decoder=None):
        super().__init__()
        self.cfg, self.feat_dim = cfg, feat_dim
        assert cfg.input in ("feat", "obs") and (cfg.input == "feat" or decoder is not None), (cfg.input, decoder)
        self.embed = decoder.forward if cfg.input == "obs" else (lambda feat: feat)
        in_dim = decoder[-1].out_features if cfg.input == "obs" else feat_dim
        self.net = mlp(2 * in_dim, cfg.units, 1, cfg.layers)

    def distance(self, x_i, x_j):
        """d on embedded inputs: x_i, x_j (..., E) -> (...)."""
        return self.net(torch.cat([x_i, x_j], -1)).squeeze(-1)

    def forward(self, feat_i, feat_j):
        """feat_i, feat_j (..., F) -> (...)."""
        assert feat_i.shape[-1] == feat_j.shape[-1] == self.feat_dim, (feat_i.shape, feat_j.shape)
        feat_i, feat_j = torch.broadcast_tensors(feat_i, feat_j)
        flat = lambda feat: feat.reshape(-1, self.feat_dim)  # 2-D: a sliced 3-D input made the decoder a batched matmul
        return self.distance(self.embed(flat(feat_i)), self.embed(flat(feat_j))).reshape(feat_i.shape[:-1])


def sample_pairs(episode, is_first, num, generator=None):
    """Draw `num` candidate pairs of each kind and keep the valid ones (module docstring).
    episode (B,) long, is_first (B, T) bool -> {'pos': (b, i, j), 'neg': (b1, t1, b2, t2)}, tuples of (P,) / (Q,) long."""
    B, T = is_first.shape
    assert episode.shape == (B,) and T >= 2, (episode.shape, is_first.shape)
    draw = lambda high: torch.randint(high, (num,), generator=generator).to(is_first.device)
    b, t1, t2 = draw(B), draw(T), draw(T)
    i, j = torch.minimum(t1, t2), torch.maximum(t1, t2)
    part = is_first.long().cumsum(1)  # (B, T): which episode of the segment each step belongs to
    valid = (i < j) & (part[b, i] == part[b, j])
    pos = (b[valid], i[valid], j[valid])
    b1, b2, t1, t2 = draw(B), draw(B), draw(T), draw(T)
    valid = episode[b1] != episode[b2]
    neg = (b1[valid], t1[valid], b2[valid], t2[valid])
    return {"pos": pos, "neg": neg}


def distance_loss(dist_net, feat, pairs, horizon_T, contrastive_weight=1.0, goal_feat=None):  # Eq. 7
    """feat (B, T, F) posterior features, pairs from sample_pairs, horizon_T = T of Eq. 6, goal_feat (B, T, F) the goal
    encoder's goals of the same frames or None -> (loss, metrics). With goal_feat, each pair's later state is also
    given as its encoder goal (module docstring) and the loss is the mean of both. Inputs are detached: the distance
    network learns on the world model's states and goals, never shapes them."""
    with torch.no_grad():  # embedded once per frame, not per pair; no gradient reaches the world model
        x = dist_net.embed(feat)  # (B, T, E)
        goals = {"": x} if goal_feat is None else {"": x, "_enc": dist_net.embed(goal_feat)}
    b, i, j = pairs["pos"]
    b1, t1, b2, t2 = pairs["neg"]
    target = (j - i).to(x.dtype) / horizon_T  # Eq. 6: D^dis(s_i, s_j) = (j - i) / T
    loss, metrics = 0.0, {}
    for name, goal in goals.items():
        d_pos = dist_net.distance(x[b, i], goal[b, j])  # (P,)
        regression = ((d_pos - target) ** 2).mean()
        d_neg = dist_net.distance(x[b1, t1], goal[b2, t2])  # (Q,)
        contrastive = ((d_neg - 1) ** 2).sum() / max(len(d_neg), 1)  # + E ||d - 1||^2: Eq. 7 with its sign read as + (module docstring)
        loss = loss + (regression + contrastive_weight * contrastive) / len(goals)
        metrics.update({f"dist_regression{name}": regression.item(), f"dist_contrastive{name}": contrastive.item(),
                        f"dist_pos{name}": d_pos.mean().item(), f"dist_neg{name}": d_neg.mean().item() if len(d_neg) else float("nan")})
    metrics["dist_loss"] = loss.item()
    return loss, metrics

