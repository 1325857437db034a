"""Eq. 3 and App. A: the goal VAE, goal encoder q_{phi^g}(s | p_t) into the world model's latent space, decoder p_{theta^g}(p_t | s).

    p_t (..., D) --encoder--> q(h | p_t) = N(h; mean_h, std_h)     App. A: NLL of the world model's h_t under it
                              q(z | p_t) = P(z; stats_z)           Eq. 3: KL[q(z | p_t) || sg(q_phi(z_t | ...))]
                 s^g = (h, z) sampled --decoder--> p_hat (..., D) on the unit sphere

q(z | p_t) has the family P of the world model's z (world_model.make_latent: Gaussian, or categorical logits per
variable), and Eq. 3's KL is the world model's latent.kl. The prior of Eq. 3 is the world model's posterior with a
stop-gradient: this module reads `post` detached, so no gradient reaches the world model (App. A). The goal is
g = feat(encode(p)) = [mean_h, E[z]], the encoder's means (a categorical z's: its probabilities, a continuous vector
phase 2 can optimise): it lives in the world model's feature space, so the distance network and the policy take it
like a state.

The decoder likelihood p(p_t | s) is a von Mises-Fisher distribution on the unit sphere with mean direction
p_hat = normalise(decoder(s)) and a fixed concentration kappa: -log p = kappa * (1 - cos(p_hat, p_t)) + const.
The video features are unit vectors compared by cosine (App. C's OT cost), so the decoder is fit in that geometry.
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from world_model import mlp


def gaussian_nll(x, mean, std):
    """-log N(x; mean, std) of a diagonal Gaussian, summed over the last axis: (..., K) -> (...)."""
    return (0.5 * ((x - mean) / std) ** 2 + torch.log(std) + 0.5 * math.log(2 * math.pi)).sum(-1)


class GoalVAE(nn.Module):
    """Goal encoder q_{phi^g}(s | p_t) and goal decoder p_{theta^g}(p_t | s); `loss` is Eq. 3 with App. A's h term."""

    def __init__(self, cfg, feat_dim, deter, latent):
        """feat_dim: D of the video features p_t; deter: the world model's h size; latent: its z's family
        (WorldModel.latent)."""
        super().__init__()
        # stoch: the width of z in feat (the world model's stoch, times discrete for a categorical z)
        self.cfg, self.feat_dim, self.deter, self.stoch, self.latent = cfg, feat_dim, deter, latent.size, latent
        assert latent.out_dim % 2 == 0, f"the encoder's output splits z's head in halves: {latent.out_dim} outputs"
        self.encoder = mlp(feat_dim, cfg.units, 2 * deter + latent.out_dim, cfg.layers)  # mean_h, std_h and z's head
        self.decoder = mlp(deter + self.stoch, cfg.units, feat_dim, cfg.layers)

    def distribution(self, p):
        """q(s | p_t): p (..., D) -> mean_h, std_h (..., deter) and q(z | p_t)'s stats (latent.stat_keys)."""
        assert p.shape[-1] == self.feat_dim, (p.shape, self.feat_dim)
        # outputs [mean_h, z's head's first half, std_h, its second half]: a Gaussian z's [mean_h, mean_z, std_h, std_z], as saved
        (mean_h, z_a), (std_h, z_b) = (x.split([self.deter, self.latent.out_dim // 2], -1) for x in self.encoder(p).chunk(2, -1))
        return mean_h, F.softplus(std_h) + self.cfg.min_std, self.latent.stats(torch.cat([z_a, z_b], -1))

    def encode(self, p):
        """p (..., D) -> a latent state dict with the world model's state_keys (deterministic: stoch = E[z]), plus deter_std."""
        mean_h, std_h, stats = self.distribution(p)
        return {"deter": mean_h, "stoch": self.latent.mean(stats), **stats, "deter_std": std_h}

    def goal(self, p):
        """The goal vector g = feat(encode(p)) = [mean_h, E[z]]: (..., D) -> (..., deter + stoch)."""
        mean_h, _, stats = self.distribution(p)
        return torch.cat([mean_h, self.latent.mean(stats)], -1)

    def _sample(self, mean_h, std_h, stats, noise):
        """s^g = [h, z] ~ q(s | p_t) from a standard normal noise (..., deter + stoch): h = mean_h + std_h * eps, z = latent.sample."""
        eps, noise_z = noise.split([self.deter, self.stoch], -1)
        return torch.cat([mean_h + std_h * eps, self.latent.sample(stats, noise_z)], -1)

    def decode(self, feat):
        """p_hat, the mean direction of p(p_t | s): feat (..., deter + stoch) -> unit vectors (..., D)."""
        assert feat.shape[-1] == self.deter + self.stoch, feat.shape
        return F.normalize(self.decoder(feat), dim=-1)

    def loss(self, p, post):  # Eq. 3
        """p (B, T, D) video features, post the world model's posterior (dict of (B, T, .)) -> (loss, metrics)."""
        assert p.shape[:-1] == post["deter"].shape[:-1] and post["stoch"].shape[-1] == self.stoch, (p.shape, post["deter"].shape)
        # sg(q_phi): the world model's posterior is a fixed target (App. A)
        h, post_stats = post["deter"].detach(), {k: post[k].detach() for k in self.latent.stat_keys}
        mean_h, std_h, stats = self.distribution(p)  # (B, T, deter) twice, q(z | p_t)'s stats
        kl = self.latent.kl(stats, post_stats)  # (B, T): KL[q_{phi^g}(z | p_t) || sg(q_phi)], z only (App. A)
        deter_nll = gaussian_nll(h, mean_h, std_h)  # (B, T): -log q_{phi^s}(h_t | p_t) replaces the KL on h (App. A)
        s_g = self._sample(mean_h, std_h, stats, torch.randn(*p.shape[:-1], self.deter + self.stoch, device=p.device))  # s^g ~ q_{phi^g}(s | p_t)
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
