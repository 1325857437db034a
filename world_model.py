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
    prior      p_theta(s_t | s_{t-1}, a_{t-1}) = N(z_t; prior_net(h_t))
    posterior  q_phi(s_t | s_{t-1}, a_{t-1}, o_t) = N(z_t; post_net(h_t, e_t)),  e_t = f_phi(o_t) (encoder)
    decoder    p_theta(o_t | s_t) from feat_t = [h_t, z_t]

Imagination (imagine, policy.py) keeps the convention, with k counting imagined steps from a start state:

    index k          0             1             2                H
    states[:, k]     s_0 = start   s_1           s_2       ...   s_H        s_{k+1} = img_step(s_k, a_k)
    actions[:, k]    a_0 ~ pi(s_0) a_1           a_2       ...   (none)     a_k leads OUT of s_k
    reward[:, k]     r_1           r_2           r_3       ...   (none)     r_{k+1} = -d(s_{k+1}, g), earned on arriving at s_{k+1}
    value[:, k]      v_0           v_1           v_2       ...   v_H        G_k = r_{k+1} + gamma [(1 - lambda) v_{k+1} + lambda G_{k+1}], G_H = v_H
"""
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F


@dataclass
class WorldModelConfig:
    obs: str = "state"  # 'state': proprioception (ours, a CPU budget; deviation) or 'pixels': 64x64x3 (the paper)
    deter: int = 200  # GRU state h_t, Dreamer V1
    stoch: int = 30  # Gaussian z_t, Dreamer V1
    hidden: int = 256  # width of the RSSM's input and head layers (ours; Dreamer V1: 200)
    units: int = 256  # width of the state encoder/decoder MLPs (ours; Dreamer V1's MLP size: 400)
    layers: int = 2  # hidden layers of the state encoder/decoder MLPs (ours: a 24-36-d vector needs little)
    cnn_depth: int = 32  # Dreamer V1 (channels 32, 64, 128, 256)
    min_std: float = 0.1  # Dreamer V1: std = softplus(x) + 0.1
    free_nats: float = 1.0  # Dreamer V3: each KL term is clipped below 1 nat per step
    kl_dyn: float = 0.5  # Dreamer V3 KL balancing: weight of KL(sg(post) || prior), trains the prior
    kl_rep: float = 0.1  # Dreamer V3 KL balancing: weight of KL(post || sg(prior)), trains the posterior
    batch: int = 16  # sequences per batch (ours, a CPU budget; Dreamer V1: 50)
    seq_len: int = 50  # steps per sequence, Dreamer V1
    lr: float = 6e-4  # Adam, Dreamer V1
    grad_clip: float = 100.0  # global gradient norm, Dreamer V1


STATE_KEYS = ("deter", "stoch", "mean", "std")  # a latent state: h_t, z_t and the Gaussian (mean, std) z_t came from


def symlog(x):
    """Dreamer V3: squashes large vector observations while keeping small ones linear."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x):
    return torch.sign(x) * torch.expm1(x.abs())


def gaussian_kl(mean_q, std_q, mean_p, std_p):
    """KL[N(mean_q, std_q) || N(mean_p, std_p)] of diagonal Gaussians, summed over the last axis: (..., Z) -> (...)."""
    kl = torch.log(std_p / std_q) + (std_q**2 + (mean_q - mean_p) ** 2) / (2 * std_p**2) - 0.5
    return kl.sum(-1)


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
        self.feat_dim = cfg.deter + cfg.stoch
        if cfg.obs == "state":
            self.encoder = mlp(obs_shape, cfg.units, cfg.units, cfg.layers - 1)  # e_t: (N, units)
            self.decoder = mlp(self.feat_dim, cfg.units, obs_shape, cfg.layers)  # mean of symlog(o_t)
            embed_dim = cfg.units
        else:
            self.encoder = ConvEncoder(cfg.cnn_depth)
            self.decoder = ConvDecoder(self.feat_dim, cfg.cnn_depth)
            embed_dim = 32 * cfg.cnn_depth
        self.img_in = nn.Linear(cfg.stoch + action_dim, cfg.hidden)  # [z_{t-1}, a_{t-1}] -> GRU input
        self.cell = nn.GRUCell(cfg.hidden, cfg.deter)
        self.prior_net = nn.Sequential(nn.Linear(cfg.deter, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, 2 * cfg.stoch))
        self.post_in = nn.Linear(cfg.deter + embed_dim, cfg.hidden)  # [h_t, e_t] -> posterior hidden layer
        self.post_out = nn.Linear(cfg.hidden, 2 * cfg.stoch)

    feat = staticmethod(feat)  # WorldModel.feat(state), the module-level function

    def _gaussian(self, stats):
        mean, std = stats.chunk(2, -1)
        return mean, F.softplus(std) + self.cfg.min_std

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
        device = self.img_in.weight.device
        zeros = lambda n: torch.zeros(batch_size, n, device=device)
        return {"deter": zeros(self.cfg.deter), "stoch": zeros(self.cfg.stoch), "mean": zeros(self.cfg.stoch), "std": zeros(self.cfg.stoch)}

    def observe(self, obs, action, is_first, state=None, sample=True):
        """Filter a sequence: obs (B, T, *obs_shape), action (B, T, A) = a_{t-1}, is_first (B, T) bool,
        state (B, .) the latent before index 0 (zeros if None) -> post, prior: dicts of (B, T, .) tensors.
        sample=False: the posterior's means instead of samples (a deterministic filter, for the fidelity benchmark).

        The time loop is the cost of an RSSM, so it holds only what depends on the previous step: the encoder,
        the action's and the embedding's share of the layers that read them, the noise and the prior head all
        run once for the whole (B, T) batch outside it (the same math as img_step, regrouped)."""
        B, T = action.shape[:2]
        cfg = self.cfg
        assert obs.shape == (B, T) + self.obs_shape and action.shape == (B, T, self.action_dim) and is_first.shape == (B, T)
        embed = self.encode(obs)  # (B, T, E)
        keep = (~is_first).to(embed.dtype).unsqueeze(-1)  # (B, T, 1): 0 where an episode starts
        w_z, w_a = self.img_in.weight.split([cfg.stoch, self.action_dim], 1)
        w_h, w_e = self.post_in.weight.split([cfg.deter, embed.shape[-1]], 1)
        # per-step slices by unbind, not [:, t]: indexing a tensor that needs grad costs a full-size zero gradient
        # per step in backward; unbind's backward is one stack
        action_in = F.linear(action * keep, w_a, self.img_in.bias).unbind(1)  # T x (B, hidden): W_a a_{t-1} + b, a = 0 at a start
        embed_in = F.linear(embed, w_e, self.post_in.bias).unbind(1)  # T x (B, hidden): W_e e_t + b
        noise = (torch.randn(B, T, cfg.stoch, device=embed.device) * sample).unbind(1)  # T x (B, Z)
        keep = keep.unbind(1)  # T x (B, 1)
        w_z, w_h = w_z.t(), w_h.t()
        resets = is_first.any(0).tolist()
        state = state or self.initial_state(B)
        h, z = state["deter"], state["stoch"]
        deters, stochs, stats = [], [], []
        for t in range(T):
            if resets[t]:
                h, z = h * keep[t], z * keep[t]
            h = self.cell(F.silu(torch.addmm(action_in[t], z, w_z)), h)  # h_t = GRU(h_{t-1}, [z_{t-1}, a_{t-1}])
            out = self.post_out(F.silu(torch.addmm(embed_in[t], h, w_h)))  # q(z_t | h_t, e_t)
            mean, std = self._gaussian(out)
            z = mean + std * noise[t]  # reparameterised sample
            deters.append(h)
            stochs.append(z)
            stats.append(out)
        deter = torch.stack(deters, 1)  # (B, T, H)
        mean, std = self._gaussian(torch.stack(stats, 1))  # (B, T, Z)
        post = {"deter": deter, "stoch": torch.stack(stochs, 1), "mean": mean, "std": std}
        prior_mean, prior_std = self._gaussian(self.prior_net(deter))  # p(z_t | h_t) for all (B, T) at once
        prior_stoch = prior_mean + prior_std * torch.randn_like(prior_std)
        prior = {"deter": deter, "stoch": prior_stoch, "mean": prior_mean, "std": prior_std}
        return post, prior

    def img_step(self, state, action, sample=True):
        """One prior step p_theta(s_t | s_{t-1}, a_{t-1}): state dict of (N, .), action (N, A) -> state dict of (N, .)."""
        x = F.silu(self.img_in(torch.cat([state["stoch"], action], -1)))
        h = self.cell(x, state["deter"])
        mean, std = self._gaussian(self.prior_net(h))
        z = mean + std * torch.randn_like(std) if sample else mean
        return {"deter": h, "stoch": z, "mean": mean, "std": std}

    def imagine(self, start, policy_fn, horizon):
        """Roll the prior forward with actions from policy_fn(feat (N, F)) -> (N, A).
        start: state dict of (N, .) -> states dict of (N, horizon + 1, .) (index 0 = start), actions (N, horizon, A)."""
        state = {k: start[k] for k in STATE_KEYS}
        assert state["deter"].dim() == 2, "flatten start states to (N, .)"
        states, actions = [state], []
        for _ in range(horizon):
            action = policy_fn(feat(state))
            state = self.img_step(state, action)
            states.append(state)
            actions.append(action)
        return {k: torch.stack([s[k] for s in states], 1) for k in STATE_KEYS}, torch.stack(actions, 1)

    def loss(self, batch):  # Eq. 2
        """Negative ELBO of a batch (module docstring) -> (loss, metrics of floats, post dict of (B, T, .))."""
        cfg = self.cfg
        obs = batch[cfg.obs]
        post, prior = self.observe(obs, batch["action"], batch["is_first"])
        # -log p(o_t | s_t) as Dreamer V3: squared error summed over dimensions (a Gaussian with variance 1/2, constant
        # dropped), on symlog(o) for vectors; V3's scale, so that its KL weights below keep their meaning
        err = self._decode_raw(feat(post)) - self._target(obs)
        recon = err.pow(2).flatten(2).sum(-1)  # (B, T)
        # KL[q_phi || p_theta] with Dreamer V3's balancing: the same KL, once with the posterior fixed (trains the prior)
        # and once with the prior fixed (trains the posterior), each clipped below free_nats per step
        kl_dyn = gaussian_kl(post["mean"].detach(), post["std"].detach(), prior["mean"], prior["std"])  # (B, T)
        kl_rep = gaussian_kl(post["mean"], post["std"], prior["mean"].detach(), prior["std"].detach())  # (B, T)
        dyn = kl_dyn.clamp(min=cfg.free_nats).mean()
        rep = kl_rep.clamp(min=cfg.free_nats).mean()
        loss = recon.mean() + cfg.kl_dyn * dyn + cfg.kl_rep * rep
        metrics = {"wm_loss": loss.item(), "recon": recon.mean().item(), "kl": kl_dyn.mean().item(),
                   "post_std": post["std"].mean().item(), "prior_std": prior["std"].mean().item()}
        return loss, metrics, post

    @torch.no_grad()
    def open_loop(self, batch, context):
        """Observe steps [0, context), imagine [context, T) with the recorded actions from the last posterior state
        (prior means, no sampling) -> imagined feats (B, T - context, F) and keep (B,): False for segments with an
        episode start inside the imagined part."""
        obs, action, is_first = batch[self.cfg.obs], batch["action"], batch["is_first"]
        T = action.shape[1]
        assert 0 < context < T
        post, _ = self.observe(obs[:, :context], action[:, :context], is_first[:, :context])
        state = {k: v[:, -1] for k, v in post.items()}
        feats = []
        for t in range(context, T):
            state = self.img_step(state, action[:, t], sample=False)
            feats.append(feat(state))
        return torch.stack(feats, 1), ~is_first[:, context:].any(1)

    def open_loop_error(self, batch, context, imagined=None):
        """The decoder's mean squared error per observation element on the open-loop imagined steps (open_loop,
        or `imagined`, its output for this batch when already computed), in the decoder's target space (symlog
        for states, [-0.5, 0.5] for pixels); NaN if no segment is kept."""
        feats, keep = imagined or self.open_loop(batch, context)
        err = self._decode_raw(feats) - self._target(batch[self.cfg.obs][:, context:])
        return err[keep].pow(2).mean().item() if keep.any() else float("nan")


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
