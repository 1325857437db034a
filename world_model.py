"""Eq. 2: the world model, a Recurrent State-Space Model (RSSM, Hafner et al. 2019) trained on the ELBO.

Time alignment of a batch (Dreamer's convention; collect.py writes episodes this way):

    index t          0             1             2                T-1
    is_first         True          False         False     ...   (True again where a new episode starts)
    action[t]        0             a_0           a_1       ...   a_{T-2}    = a_{t-1}, the action that led INTO o_t
    obs[t]           o_0           o_1           o_2       ...   o_{T-1}    (state vector or 64x64x3 pixels)
    reward[t]        r_0           r_1           r_2       ...   r_t arrives with o_t (unused: D_body has no labels)
    p[t]             p_0           p_1           p_2       ...   p_t = f(o_{t-k+1:t}), the video feature
    latent s_t       s_0 --------> s_1 --------> s_2       ...   s_t = (h_t, z_t), h = deter, z = stoch

    h_t = GRU(h_{t-1}, [z_{t-1}, a_{t-1}])            h_{-1} = z_{-1} = 0, and both reset to 0 where is_first
    prior      p_theta(s_t | s_{t-1}, a_{t-1}) = P(z_t; prior_net(h_t))
    posterior  q_phi(s_t | s_{t-1}, a_{t-1}, o_t) = P(z_t; post_net(h_t, e_t)),  e_t = f_phi(o_t) (encoder)
    z's family P (make_latent): Gaussian (discrete = 0, Dreamer V1) or stoch one-hot categoricals of discrete classes (DreamerV2, GenRL)
    decoder    p_theta(o_t | s_t) from feat_t = [h_t, z_t]

Imagination (imagine, policy.py) keeps the convention, with k counting imagined steps from a start state:

    index k          0             1             2                H
    states[:, k]     s_0 = start   s_1           s_2       ...   s_H        s_{k+1} = img_step(s_k, a_k)
    actions[:, k]    a_0 ~ pi(s_0) a_1           a_2       ...   (none)     a_k leads OUT of s_k
    reward[:, k]     r_1           r_2           r_3       ...   (none)     r_{k+1} = -d(s_{k+1}, g), earned on arriving at s_{k+1}
    value[:, k]      v_0           v_1           v_2       ...   v_H        G_k = r_{k+1} + gamma [(1 - lambda) v_{k+1} + lambda G_{k+1}], G_H = v_H
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F


def symlog(x):
    """Dreamer V3: squashes large vector observations while keeping small ones linear."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x):
    return torch.sign(x) * torch.expm1(x.abs())


def gaussian_kl(mean_q, std_q, mean_p, std_p):
    """KL[N(mean_q, std_q) || N(mean_p, std_p)] of diagonal Gaussians, summed over the last axis: (..., Z) -> (...)."""
    kl = torch.log(std_p / std_q) + (std_q**2 + (mean_q - mean_p) ** 2) / (2 * std_p**2) - 0.5
    return kl.sum(-1)


class GaussianLatent:
    """z = stoch diagonal Gaussian units (Dreamer V1): a head's output (..., 2 stoch) -> mean, std = softplus + min_std.
    Every stat tensor, noise and z is (..., width); noise is a standard normal of (..., size) for either family."""

    def __init__(self, stoch, min_std):
        self.stoch, self.min_std = stoch, min_std
        self.stat_keys = ("mean", "std")
        self.size = stoch  # width of z in feat
        self.out_dim = 2 * stoch  # outputs of the prior and posterior heads

    def stats(self, x):
        """(..., out_dim) -> {"mean", "std"} of (..., stoch)."""
        mean, std = x.chunk(2, -1)
        return {"mean": mean, "std": F.softplus(std) + self.min_std}

    def sample(self, stats, noise=None):
        """Reparameterised: z = mean + std * noise (..., stoch)."""
        if noise is None:
            noise = torch.randn_like(stats["std"])
        return stats["mean"] + stats["std"] * noise

    def mode(self, stats):
        """The most likely z: the mean (..., stoch)."""
        return stats["mean"]

    def mean(self, stats):
        """E[z] (..., size)."""
        return stats["mean"]

    def kl(self, q, p):
        """KL[q || p] summed over z: stats dicts -> (...)."""
        return gaussian_kl(q["mean"], q["std"], p["mean"], p["std"])

    def entropy(self, stats):
        """H[z] summed over z: (...)."""
        return (0.5 * math.log(2 * math.pi * math.e) + stats["std"].log()).sum(-1)


class CategoricalLatent:
    """z = stoch one-hot categoricals of `discrete` classes each, flattened to (..., stoch * discrete) (DreamerV2;
    GenRL: 32 x 32). The stat is "logits" (..., stoch * discrete): log-probabilities after DreamerV3's unimix."""

    def __init__(self, stoch, discrete, unimix):
        self.stoch, self.discrete, self.unimix = stoch, discrete, unimix
        self.stat_keys = ("logits",)
        self.size = stoch * discrete  # width of z in feat
        self.out_dim = stoch * discrete  # outputs of the prior and posterior heads

    def _probs(self, stats):
        return stats["logits"].unflatten(-1, (self.stoch, self.discrete)).softmax(-1)  # (..., stoch, discrete)

    def stats(self, x):
        """(..., out_dim) -> {"logits"}: DreamerV3's unimix, probs = (1 - unimix) softmax(x) + unimix / discrete, so
        that no class's probability (and no KL term) collapses."""
        probs = x.unflatten(-1, (self.stoch, self.discrete)).softmax(-1)
        probs = (1 - self.unimix) * probs + self.unimix / self.discrete
        return {"logits": probs.log().flatten(-2)}

    def sample(self, stats, noise=None):
        """A one-hot draw per variable with DreamerV2's straight-through gradient (the probabilities'). Gumbel-max
        (Maddison et al. 2014): argmax(logits + G) ~ Categorical for G = -log(-log u), u uniform; here u = Phi(noise) of
        a standard normal noise (..., size), so that both families draw from the same noise (observe's, the goal VAE's)."""
        logits = stats["logits"].unflatten(-1, (self.stoch, self.discrete))  # (..., stoch, discrete)
        if noise is None:
            noise = torch.randn_like(stats["logits"])
        # u = Phi(noise) through ndtr, clamped (1e-12: noise below -7; 1 - 1e-7: Gumbel values above 16, each about 1e-7
        # likely): several times cheaper than log_ndtr, and this runs at every step of observe's loop
        u = torch.special.ndtr(noise.unflatten(-1, (self.stoch, self.discrete))).clamp(1e-12, 1 - 1e-7)
        gumbel = -torch.log(-torch.log(u))
        return self._straight_through(F.one_hot((logits + gumbel).argmax(-1), self.discrete), logits.softmax(-1))

    def mode(self, stats):
        """The one-hot of each variable's most likely class, straight-through as `sample`."""
        probs = self._probs(stats)
        return self._straight_through(F.one_hot(probs.argmax(-1), self.discrete), probs)

    @staticmethod
    def _straight_through(one_hot, probs):
        """Forward the exact one-hot, backward the probabilities' gradient (DreamerV2): (..., stoch, discrete) -> (..., size)."""
        return (one_hot.to(probs.dtype) + (probs - probs.detach())).flatten(-2)

    def mean(self, stats):
        """E[z] = the probabilities, flattened (..., size)."""
        return self._probs(stats).flatten(-2)

    def kl(self, q, p):
        """KL[q || p] of each variable, summed over the variables: stats dicts -> (...)."""
        return (q["logits"].exp() * (q["logits"] - p["logits"])).sum(-1)

    def entropy(self, stats):
        """H[z] summed over the variables: (...)."""
        return -(stats["logits"].exp() * stats["logits"]).sum(-1)


def make_latent(cfg):
    """z's family from a WorldModelConfig: categorical when cfg.discrete > 0 (DreamerV2), else Gaussian (Dreamer V1)."""
    if cfg.discrete:
        return CategoricalLatent(cfg.stoch, cfg.discrete, cfg.unimix)
    return GaussianLatent(cfg.stoch, cfg.min_std)


def feat(state):
    """The feature vector of a latent state, feat = [h, z]: what decoder, actor, critic, distance and goals see."""
    return torch.cat([state["deter"], state["stoch"]], -1)


def mlp(inp, units, out, layers):
    """`layers` hidden layers of `units` with SiLU, then a linear output layer. SiLU is Dreamer V3's activation
    (Dreamer V1 used ELU, which costs more on a CPU); no LayerNorm, unlike Dreamer V3."""
    modules = []
    for _ in range(layers):
        modules += [nn.Linear(inp, units), nn.SiLU()]
        inp = units
    return nn.Sequential(*modules, nn.Linear(inp, out))


class ConvEncoder(nn.Module):
    """Dreamer V1: four 4x4 stride-2 convolutions, (N, 3, 64, 64) -> (N, 32 * depth)."""

    def __init__(self, depth):
        super().__init__()
        d = depth
        self.net = nn.Sequential(
            nn.Conv2d(3, d, 4, 2), nn.ReLU(), nn.Conv2d(d, 2 * d, 4, 2), nn.ReLU(),
            nn.Conv2d(2 * d, 4 * d, 4, 2), nn.ReLU(), nn.Conv2d(4 * d, 8 * d, 4, 2), nn.ReLU(), nn.Flatten(),
        )

    def forward(self, x):
        return self.net(x)


class ConvDecoder(nn.Module):
    """Dreamer V1: a dense layer to (32 * depth, 1, 1), then transposed convolutions 5, 5, 6, 6 (stride 2) to 64x64."""

    def __init__(self, feat_dim, depth):
        super().__init__()
        d = depth
        self.net = nn.Sequential(
            nn.Linear(feat_dim, 32 * d), nn.Unflatten(1, (32 * d, 1, 1)),
            nn.ConvTranspose2d(32 * d, 4 * d, 5, 2), nn.ReLU(), nn.ConvTranspose2d(4 * d, 2 * d, 5, 2), nn.ReLU(),
            nn.ConvTranspose2d(2 * d, d, 6, 2), nn.ReLU(), nn.ConvTranspose2d(d, 3, 6, 2),
        )

    def forward(self, x):
        return self.net(x)


class WorldModel(nn.Module):
    """Encoder, RSSM (GRU, prior, posterior) and decoder; `loss` is Eq. 2's negative ELBO."""

    def __init__(self, cfg, obs_shape, action_dim):
        """obs_shape: obs_dim (int) for cfg.obs == 'state', (64, 64, 3) for 'pixels'."""
        super().__init__()
        self.cfg, self.action_dim = cfg, action_dim
        self.obs_shape = (obs_shape,) if cfg.obs == "state" else tuple(obs_shape)
        assert cfg.obs in ("state", "pixels") and (cfg.obs == "state" or self.obs_shape == (64, 64, 3)), (cfg.obs, obs_shape)
        self.latent = make_latent(cfg)  # z's family: every use of z goes through it
        self.state_keys = ("deter", "stoch") + self.latent.stat_keys  # a latent state: h_t, z_t and the stats z_t came from
        self.feat_dim = cfg.deter + self.latent.size
        if cfg.obs == "state":
            self.encoder = mlp(obs_shape, cfg.units, cfg.units, cfg.layers - 1)  # e_t: (N, units)
            self.decoder = mlp(self.feat_dim, cfg.units, obs_shape, cfg.layers)  # mean of symlog(o_t)
            embed_dim = cfg.units
        else:
            self.encoder = ConvEncoder(cfg.cnn_depth)
            self.decoder = ConvDecoder(self.feat_dim, cfg.cnn_depth)
            embed_dim = 32 * cfg.cnn_depth
        self.img_in = nn.Linear(self.latent.size + action_dim, cfg.hidden)  # [z_{t-1}, a_{t-1}] -> GRU input
        self.cell = nn.GRUCell(cfg.hidden, cfg.deter)
        self.prior_net = nn.Sequential(nn.Linear(cfg.deter, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, self.latent.out_dim))
        self.post_in = nn.Linear(cfg.deter + embed_dim, cfg.hidden)  # [h_t, e_t] -> posterior hidden layer
        self.post_out = nn.Linear(cfg.hidden, self.latent.out_dim)

    feat = staticmethod(feat)  # WorldModel.feat(state), the module-level function

    def _target(self, obs):
        """What the decoder predicts: symlog(o) (B, T, obs_dim), or pixels in [-0.5, 0.5] (B, T, 3, 64, 64) (Dreamer V1)."""
        if self.cfg.obs == "state":
            return symlog(obs)
        return obs.permute(0, 1, 4, 2, 3).float() / 255 - 0.5

    def encode(self, obs):
        """e_t = f_phi(o_t) for all (B, T) at once: (B, T, *obs_shape) -> (B, T, E)."""
        x = self._target(obs)
        return self.encoder(x.flatten(0, 1)).unflatten(0, x.shape[:2])

    def _decode_raw(self, feat):
        """(B, T, F) -> the decoder mean in the space of _target."""
        return self.decoder(feat.flatten(0, 1)).unflatten(0, feat.shape[:2])

    def decode(self, feat):
        """Predicted observation in its own units: state (B, T, obs_dim), or pixels (B, T, 64, 64, 3) in [0, 1]."""
        out = self._decode_raw(feat)
        if self.cfg.obs == "state":
            return symexp(out)
        return (out.permute(0, 1, 3, 4, 2) + 0.5).clamp(0, 1)

    def initial_state(self, batch_size):
        """Every entry of the state zero: (batch_size, .)."""
        zeros = torch.zeros(batch_size, self.latent.out_dim, device=self.img_in.weight.device)
        stats = {k: torch.zeros_like(v) for k, v in self.latent.stats(zeros).items()}
        return {"deter": zeros.new_zeros(batch_size, self.cfg.deter), "stoch": zeros.new_zeros(batch_size, self.latent.size), **stats}

    def observe(self, obs, action, is_first, state=None, sample=True):
        """Filter a sequence: obs (B, T, *obs_shape), action (B, T, A) = a_{t-1}, is_first (B, T) bool,
        state (B, .) the latent before index 0 (zeros if None) -> post, prior: dicts of (B, T, .) tensors.
        sample=False: the posterior's modes instead of samples (a deterministic filter, for the fidelity benchmark).

        The time loop is the cost of an RSSM, so it holds only what depends on the previous step: the encoder,
        the action's and the embedding's share of the layers that read them, the noise and the prior head all
        run once for the whole (B, T) batch outside it (the same math as img_step, regrouped)."""
        B, T = action.shape[:2]
        cfg, latent = self.cfg, self.latent
        assert obs.shape == (B, T) + self.obs_shape and action.shape == (B, T, self.action_dim) and is_first.shape == (B, T)
        embed = self.encode(obs)  # (B, T, E)
        keep = (~is_first).to(embed.dtype).unsqueeze(-1)  # (B, T, 1): 0 where an episode starts
        w_z, w_a = self.img_in.weight.split([latent.size, self.action_dim], 1)
        w_h, w_e = self.post_in.weight.split([cfg.deter, embed.shape[-1]], 1)
        # per-step slices by unbind, not [:, t]: indexing a tensor that needs grad costs a full-size zero gradient
        # per step in backward; unbind's backward is one stack
        action_in = F.linear(action * keep, w_a, self.img_in.bias).unbind(1)  # T x (B, hidden): W_a a_{t-1} + b, a = 0 at a start
        embed_in = F.linear(embed, w_e, self.post_in.bias).unbind(1)  # T x (B, hidden): W_e e_t + b
        # drawn whatever `sample`, so that the prior's samples below read the same random numbers either way
        noise = torch.randn(B, T, latent.size, device=embed.device).unbind(1)  # T x (B, Z)
        keep = keep.unbind(1)  # T x (B, 1)
        w_z, w_h = w_z.t(), w_h.t()
        resets = is_first.any(0).tolist()
        state = state or self.initial_state(B)
        h, z = state["deter"], state["stoch"]
        deters, stochs, outs = [], [], []
        for t in range(T):
            if resets[t]:
                h, z = h * keep[t], z * keep[t]
            h = self.cell(F.silu(torch.addmm(action_in[t], z, w_z)), h)  # h_t = GRU(h_{t-1}, [z_{t-1}, a_{t-1}])
            out = self.post_out(F.silu(torch.addmm(embed_in[t], h, w_h)))  # q(z_t | h_t, e_t)
            stats = latent.stats(out)
            z = latent.sample(stats, noise[t]) if sample else latent.mode(stats)
            deters.append(h)
            stochs.append(z)
            outs.append(out)
        deter = torch.stack(deters, 1)  # (B, T, H)
        post = {"deter": deter, "stoch": torch.stack(stochs, 1), **latent.stats(torch.stack(outs, 1))}
        prior_stats = latent.stats(self.prior_net(deter))  # p(z_t | h_t) for all (B, T) at once
        prior = {"deter": deter, "stoch": latent.sample(prior_stats), **prior_stats}
        return post, prior

    def img_step(self, state, action, sample=True):
        """One prior step p_theta(s_t | s_{t-1}, a_{t-1}): state dict of (N, .), action (N, A) -> state dict of (N, .)."""
        x = F.silu(self.img_in(torch.cat([state["stoch"], action], -1)))
        h = self.cell(x, state["deter"])
        stats = self.latent.stats(self.prior_net(h))
        z = self.latent.sample(stats) if sample else self.latent.mode(stats)
        return {"deter": h, "stoch": z, **stats}

    def imagine(self, start, policy_fn, horizon):
        """Roll the prior forward with actions from policy_fn(feat (N, F)) -> (N, A).
        start: state dict of (N, .) -> states dict of (N, horizon + 1, .) (index 0 = start), actions (N, horizon, A)."""
        state = {k: start[k] for k in self.state_keys}
        assert state["deter"].dim() == 2, "flatten start states to (N, .)"
        states, actions = [state], []
        for _ in range(horizon):
            action = policy_fn(feat(state))
            state = self.img_step(state, action)
            states.append(state)
            actions.append(action)
        return {k: torch.stack([s[k] for s in states], 1) for k in self.state_keys}, torch.stack(actions, 1)

    def loss(self, batch):  # Eq. 2
        """Negative ELBO of a batch (module docstring) -> (loss, metrics of floats, post dict of (B, T, .))."""
        cfg, latent = self.cfg, self.latent
        obs = batch[cfg.obs]
        post, prior = self.observe(obs, batch["action"], batch["is_first"])
        # -log p(o_t | s_t) as Dreamer V3: squared error summed over dimensions (a Gaussian with variance 1/2, constant
        # dropped), on symlog(o) for vectors; V3's scale, so that its KL weights below keep their meaning
        err = self._decode_raw(feat(post)) - self._target(obs)
        recon = err.pow(2).flatten(2).sum(-1)  # (B, T)
        # KL[q_phi || p_theta] with Dreamer V3's balancing: the same KL, once with the posterior fixed (trains the prior)
        # and once with the prior fixed (trains the posterior), each clipped below free_nats per step
        sg = lambda state: {k: state[k].detach() for k in latent.stat_keys}
        kl_dyn = latent.kl(sg(post), prior)  # (B, T)
        kl_rep = latent.kl(post, sg(prior))  # (B, T)
        dyn = kl_dyn.clamp(min=cfg.free_nats).mean()
        rep = kl_rep.clamp(min=cfg.free_nats).mean()
        loss = recon.mean() + cfg.kl_dyn * dyn + cfg.kl_rep * rep
        metrics = {"wm_loss": loss.item(), "recon": recon.mean().item(), "kl": kl_dyn.mean().item(),
                   "post_ent": latent.entropy(post).mean().item(), "prior_ent": latent.entropy(prior).mean().item()}
        return loss, metrics, post
