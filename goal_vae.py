"""Eq. 3 and App. A: the goal VAE, goal encoder q_{phi^g}(s | p_t) into the world model's latent space, decoder p_{theta^g}(p_t | s).

    p_t (..., D) --encoder--> q(h | p_t) = N(h; mean_h, std_h)     App. A: NLL of the world model's h_t under it
                              q(z | p_t) = N(z; mean_z, std_z)     Eq. 3: KL[q(z | p_t) || sg(q_phi(z_t | ...))]
                 s^g = (h, z) sampled --decoder--> p_hat (..., D) on the unit sphere

The prior of Eq. 3 is the world model's posterior with a stop-gradient: this module reads `post` detached, so no
gradient reaches the world model (App. A). The goal is g = feat(encode(p)) = [mean_h, mean_z], the encoder's
means: it lives in the world model's feature space, so the distance network and the policy take it like a state.

The decoder likelihood p(p_t | s) is a von Mises-Fisher distribution on the unit sphere with mean direction
p_hat = normalise(decoder(s)) and a fixed concentration kappa: -log p = kappa * (1 - cos(p_hat, p_t)) + const.
The video features are unit vectors compared by cosine (App. C's OT cost), so the decoder is fit in that geometry.
"""
import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from world_model import gaussian_kl, mlp


@dataclass
class GoalVAEConfig:
    units: int = 256  # MLP width, the world model's (ours; Dreamer V1's MLP size: 400)
    layers: int = 2  # hidden layers of the encoder and of the decoder (ours)
    min_std: float = 0.1  # std = softplus(x) + 0.1, as the world model (Dreamer V1)
    kappa: float = 10.0  # vMF concentration of p(p_t | s) (ours: recon kappa * (1 - cos) on the scale of the z KL)
    posterior_recon: float = 1.0  # weight of the decoder's fit on world-model posterior states (ours, `loss`; 0 = Eq. 3 alone)
    lr: float = 6e-4  # Adam, the world model's rate (Dreamer V1)
    grad_clip: float = 100.0  # global gradient norm, Dreamer V1


def gaussian_nll(x, mean, std):
    """-log N(x; mean, std) of a diagonal Gaussian, summed over the last axis: (..., K) -> (...)."""
    return (0.5 * ((x - mean) / std) ** 2 + torch.log(std) + 0.5 * math.log(2 * math.pi)).sum(-1)


class GoalVAE(nn.Module):
    """Goal encoder q_{phi^g}(s | p_t) and goal decoder p_{theta^g}(p_t | s); `loss` is Eq. 3 with App. A's h term."""

    def __init__(self, cfg, feat_dim, deter, stoch):
        """feat_dim: D of the video features p_t; deter, stoch: the world model's h and z sizes."""
        super().__init__()
        self.cfg, self.feat_dim, self.deter, self.stoch = cfg, feat_dim, deter, stoch
        self.encoder = mlp(feat_dim, cfg.units, 2 * (deter + stoch), cfg.layers)  # mean and std of [h, z]
        self.decoder = mlp(deter + stoch, cfg.units, feat_dim, cfg.layers)

    def distribution(self, p):
        """q(s | p_t): p (..., D) -> mean, std (..., deter + stoch), ordered [h, z] like world_model.feat."""
        assert p.shape[-1] == self.feat_dim, (p.shape, self.feat_dim)
        mean, std = self.encoder(p).chunk(2, -1)
        return mean, F.softplus(std) + self.cfg.min_std

    def encode(self, p):
        """p (..., D) -> a latent state dict like the world model's (deterministic: the means), plus deter_std."""
        mean, std = self.distribution(p)
        deter, stoch = mean.split([self.deter, self.stoch], -1)
        deter_std, stoch_std = std.split([self.deter, self.stoch], -1)
        return {"deter": deter, "stoch": stoch, "mean": stoch, "std": stoch_std, "deter_std": deter_std}

    def goal(self, p):
        """The goal vector g = feat(encode(p)) = [mean_h, mean_z]: (..., D) -> (..., deter + stoch)."""
        return self.distribution(p)[0]

    def decode(self, feat):
        """p_hat, the mean direction of p(p_t | s): feat (..., deter + stoch) -> unit vectors (..., D)."""
        assert feat.shape[-1] == self.deter + self.stoch, feat.shape
        return F.normalize(self.decoder(feat), dim=-1)

    def loss(self, p, post):  # Eq. 3
        """p (B, T, D) video features, post the world model's posterior (dict of (B, T, .)) -> (loss, metrics)."""
        assert p.shape[:-1] == post["deter"].shape[:-1] and post["mean"].shape[-1] == self.stoch, (p.shape, post["deter"].shape)
        # sg(q_phi): the world model's posterior is a fixed target (App. A)
        h, z_mean, z_std = post["deter"].detach(), post["mean"].detach(), post["std"].detach()
        mean, std = self.distribution(p)  # (B, T, deter + stoch)
        (mean_h, mean_z), (std_h, std_z) = mean.split([self.deter, self.stoch], -1), std.split([self.deter, self.stoch], -1)
        kl = gaussian_kl(mean_z, std_z, z_mean, z_std)  # (B, T): KL[q_{phi^g}(z | p_t) || sg(q_phi)], z only (App. A)
        deter_nll = gaussian_nll(h, mean_h, std_h)  # (B, T): -log q_{phi^s}(h_t | p_t) replaces the KL on h (App. A)
        s_g = mean + std * torch.randn_like(std)  # s^g ~ q_{phi^g}(s | p_t), reparameterised
        cos = (self.decode(s_g) * p).sum(-1)  # (B, T)
        recon = self.cfg.kappa * (1 - cos)  # -log vMF(p_t; p_hat, kappa) + const
        # Ours: the decoder also reads sg(posterior) states, the states phase 2 decodes (Eq. 5's imagined rollouts).
        # Fit on encoder samples alone it read held-out posterior states far worse (train.py's imagination.json;
        # docs/ablations.md, Phase 1).
        post_cos = (self.decode(torch.cat([h, post["stoch"].detach()], -1)) * p).sum(-1)  # (B, T)
        loss = kl.mean() + deter_nll.mean() + recon.mean() + self.cfg.posterior_recon * self.cfg.kappa * (1 - post_cos).mean()
        metrics = {"goal_loss": loss.item(), "goal_kl": kl.mean().item(), "goal_deter_nll": deter_nll.mean().item(),
                   "goal_recon": recon.mean().item(), "goal_cos": cos.mean().item(), "goal_post_cos": post_cos.mean().item()}
        return loss, metrics
