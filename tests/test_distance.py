"""distance.py: Eq. 7 on a hand-made batch against hand-computed values, pair sampling, and a short fit."""
import pytest
import torch

import configs
from configs import DistanceConfig
from distance import DistanceNet, distance_loss, sample_pairs

torch.set_num_threads(1)


class StubDistanceNet:
    """A known 'network': d(s_i, s_j) = s_j[0] - s_i[0], on unembedded states."""

    @staticmethod
    def embed(feat):
        return feat

    def distance(self, x_i, x_j):
        return x_j[..., 0] - x_i[..., 0]

    __call__ = distance


stub_dist_net = StubDistanceNet()


def test_eq7_on_a_hand_made_batch():
    feat = torch.tensor([[[0.0], [0.1], [0.5]], [[0.2], [0.3], [0.9]]])  # (B=2, T=3, F=1)
    pairs = {
        "pos": (torch.tensor([0, 1]), torch.tensor([0, 1]), torch.tensor([2, 2])),  # (b, i, j): (0, 0, 2), (1, 1, 2)
        "neg": (torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([1, 0]), torch.tensor([2, 1])),  # (0,0)-(1,2), (1,0)-(0,1)
    }
    # by hand, T = 3: d = 0.5 vs (2 - 0) / 3 and d = 0.6 vs (2 - 1) / 3; negatives d = 0.9 and d = -0.1 vs 1
    regression = ((0.5 - 2 / 3) ** 2 + (0.6 - 1 / 3) ** 2) / 2
    contrastive = ((0.9 - 1) ** 2 + (-0.1 - 1) ** 2) / 2
    loss, metrics = distance_loss(stub_dist_net, feat, pairs, horizon_T=3)
    assert loss.item() == pytest.approx(regression + contrastive, abs=1e-6)
    assert metrics["dist_regression"] == pytest.approx(regression, abs=1e-6)
    assert metrics["dist_contrastive"] == pytest.approx(contrastive, abs=1e-6)
    weighted, _ = distance_loss(stub_dist_net, feat, pairs, horizon_T=3, contrastive_weight=0.25)
    assert weighted.item() == pytest.approx(regression + 0.25 * contrastive, abs=1e-6)


def test_pairs_stay_inside_a_trajectory_and_negatives_cross_episodes():
    B, T = 4, 10
    episode = torch.tensor([7, 7, 8, 9])  # rows 0 and 1: two segments of one episode
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True
    is_first[2, 5] = True  # row 2 crosses into a new episode at t = 5
    pairs = sample_pairs(episode, is_first, 4000, torch.Generator().manual_seed(0))
    b, i, j = pairs["pos"]
    assert len(b) > 1000 and (i < j).all()
    crosses = (b == 2) & (i < 5) & (j >= 5)
    assert not crosses.any()
    assert set((j - i).tolist()) == set(range(1, T))  # every gap appears
    b1, t1, b2, t2 = pairs["neg"]
    assert len(b1) > 1000 and (episode[b1] != episode[b2]).all()
    assert not ((b1 == 0) & (b2 == 1)).any()


def test_distance_net_learns_temporal_order():
    """Features that drift along a trajectory: after a short fit, later states are predicted further away."""
    torch.manual_seed(0)
    cfg = DistanceConfig(units=64, layers=2, contrastive_weight=1.0, input="feat")  # Eq. 7 as written
    B, T, F = 8, 10, 4
    dist_net = DistanceNet(cfg, F)
    opt = torch.optim.Adam(dist_net.parameters(), lr=3e-3)
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True

    def batch():
        start = torch.randn(B, 1, F)
        return start + torch.linspace(0, 1, T)[None, :, None] * torch.ones(F)  # (B, T, F)

    for _ in range(300):
        loss, _ = distance_loss(dist_net, batch(), sample_pairs(torch.arange(B), is_first, 256), T, cfg.contrastive_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
    feat = batch()
    with torch.no_grad():
        d = dist_net(feat[:, :1].expand(-1, T, -1), feat)  # (B, T): from step 0 to every step
    assert d.shape == (B, T)
    assert (d[:, -1] - d[:, 1]).mean() > 0.3  # (9 - 1) / 10 = 0.8 by Eq. 6


def test_encoder_goals_score_each_pair_with_the_frame_s_encoder_goal_too():
    feat = torch.tensor([[[0.0], [0.1], [0.5]], [[0.2], [0.3], [0.9]]])  # (B=2, T=3, F=1)
    goal_feat = feat + 0.25  # the encoder's goals of the same frames, offset
    pairs = {"pos": (torch.tensor([0]), torch.tensor([0]), torch.tensor([2])), "neg": (torch.tensor([1]), torch.tensor([0]), torch.tensor([0]), torch.tensor([1]))}
    same, _ = distance_loss(stub_dist_net, feat, pairs, horizon_T=3, goal_feat=feat)
    alone, _ = distance_loss(stub_dist_net, feat, pairs, horizon_T=3)
    assert same.item() == pytest.approx(alone.item())  # identical goals: the mean of two equal terms
    loss, metrics = distance_loss(stub_dist_net, feat, pairs, horizon_T=3, contrastive_weight=0.1, goal_feat=goal_feat)
    # by hand: posterior goal d = 0.5 vs 2/3, negative d = 0.1 - 0.2 = -0.1 vs 1; encoder goal d = 0.75 vs 2/3, negative d = 0.15 vs 1
    post = (0.5 - 2 / 3) ** 2 + 0.1 * (-0.1 - 1) ** 2
    enc = (0.75 - 2 / 3) ** 2 + 0.1 * (0.15 - 1) ** 2
    assert loss.item() == pytest.approx((post + enc) / 2, abs=1e-6)
    assert metrics["dist_pos_enc"] == pytest.approx(0.75) and metrics["dist_neg_enc"] == pytest.approx(0.15)


def test_distance_profile_reads_d_at_each_gap():
    from evaluate import distance_profile

    B, T = 3, 45
    feat = torch.arange(T, dtype=torch.float)[None, :, None].expand(B, T, 1)  # feature = time step
    is_first = torch.zeros(B, T, dtype=torch.bool)
    profile = distance_profile(stub_dist_net, feat, feat + 1, is_first)
    assert profile["d_post"][:4] == [1.0, 5.0, 15.0, 30.0] and profile["d_enc"][:4] == [2.0, 6.0, 16.0, 31.0]
    assert len(profile["d_post"]) == 5


def test_encoder_goals_a_few_steps_ahead_score_better_than_another_trajectory_s():
    """Synthetic trajectories: the state is (position, a per-trajectory tag); the encoder goal of a frame sees only
    the position (a video window has no history). Trained with encoder goals, -d ranks a goal k steps ahead of the
    same trajectory above the goal of another trajectory's frame, and nearer goals above farther ones."""
    torch.manual_seed(0)
    cfg = DistanceConfig(units=64, layers=2, contrastive_weight=1.0, input="feat")  # Eq. 7 as written
    B, T = 16, 12
    dist_net = DistanceNet(cfg, 2)
    opt = torch.optim.Adam(dist_net.parameters(), lr=3e-3)
    is_first = torch.zeros(B, T, dtype=torch.bool)
    is_first[:, 0] = True

    def batch():
        position = torch.rand(B, 1) * 4 + torch.linspace(0, 1, T)  # (B, T): each trajectory moves 1 in T steps
        tag = torch.randn(B, 1).expand(B, T)
        feat = torch.stack([position, tag], -1)
        goal = torch.stack([position, torch.zeros(B, T)], -1)  # the encoder's goal: the position only
        return feat, goal

    for _ in range(400):
        feat, goal = batch()
        loss, _ = distance_loss(dist_net, feat, sample_pairs(torch.arange(B), is_first, 256), T, 0.1, goal)
        opt.zero_grad()
        loss.backward()
        opt.step()
    feat, goal = batch()
    with torch.no_grad():
        near, far = dist_net(feat[:, 0], goal[:, 2]), dist_net(feat[:, 0], goal[:, 10])
        other = dist_net(feat[:, 0], goal.roll(1, 0)[:, 2])
    assert near.mean() < far.mean() - 0.3 and near.mean() < other.mean() - 0.2, (near.mean(), far.mean(), other.mean())


def test_obs_input_reads_the_decoded_observation_and_leaves_the_decoder_to_the_world_model():
    import world_model as W

    wm = W.WorldModel(configs.WorldModelConfig(**configs.PRESETS["wm"]["smoke"]), 5, 2)
    dist_net = DistanceNet(DistanceConfig(units=8, layers=1, input="obs"), wm.feat_dim, wm.decoder)
    assert not any(n.startswith("embed") for n, _ in dist_net.named_parameters()) and len(list(dist_net.parameters())) == 4
    feat_i, feat_j = torch.randn(3, wm.feat_dim), torch.randn(3, wm.feat_dim)
    assert torch.allclose(dist_net(feat_i, feat_j), dist_net.net(torch.cat([wm.decoder(feat_i), wm.decoder(feat_j)], -1)).squeeze(-1))
    feat = torch.randn(2, 4, wm.feat_dim)
    pairs = sample_pairs(torch.arange(2), torch.zeros(2, 4, dtype=torch.bool), 16)
    distance_loss(dist_net, feat, pairs, 4, 0.1, feat.flip(0))[0].backward()
    assert all(p.grad is None for p in wm.parameters())  # Eq. 7 never trains the world model's decoder

