"""Every command's configuration in one place, as DreamerV3's configs.yaml holds its: one dataclass per component, whose
defaults are the cpu preset and whose field comments say what each field is and where its value comes from (the paper,
Dreamer, LEXA, GenRL or ours; they become the flags' --help), then the presets that override them, side by side.

cpu    each dataclass's defaults, so what `python train.py --env walker` trains is what its dataclasses read; the shipped
       agents are cpu runs
smoke  every command end to end in seconds, the cpu recipe at toy sizes (the tests)
paper  the paper's sizes and Eq. 4 as it is written (no cloning), for a GPU

rundir.check_flags checks every field of a config (a count >= 1, a learning rate in (0, 1), a float >= 0), and a class's
`ranges` and `choices` where a field takes other values.
"""
import dataclasses
import inspect
import io
import os
import re
import tokenize
from typing import ClassVar

import envs
import rundir

# phase 1 (train.py): one config per component, COMPONENTS below

@dataclasses.dataclass
class TrainConfig:
    ranges: ClassVar[dict] = {"seed": (0, None), "policy_start": (0, None), "holdout_every": (2, None)}
    env: str = "walker"  # the agent's body
    preset: str = "cpu"  # smoke | cpu | paper: sizes of every component and of D_body
    seed: int = 0  # the training seed: torch's and the batches' draws
    steps: int = 3000  # updates (ours: a CPU budget, docs/results.md; Dreamer-scale runs use ~1e5 and more)
    policy_start: int = 1000  # updates of phase 1 before the actor-critic starts (ours)
    holdout_every: int = 20  # every 20th D_body episode is held out of training, for evaluate.evaluate_imagination (ours)
    eval_episodes: int = 3  # goal-reaching benchmark (evaluate.py, ours): episodes per own-body demo goal
    eval_steps: int = 500  # agent steps per goal-reaching episode (a whole episode)
    eval_seed: int = 30_000  # the benchmark's first environment seed; another gives fresh start poses, to confirm a choice made on it
    log_every: int = 100  # updates between rows of metrics.jsonl
    checkpoint_every: int = 250  # updates between checkpoints (--resume goes on from the last)
    data: str = "data"  # the datasets' folder (DATA below)
    encoder: str = "default"  # video encoder of the features p_t (video_encoder.py)
    threads: int = 1  # torch CPU threads (ours: these small models ran faster on 1 than on 2 with the cores shared, docs/results.md, Speed)


@dataclasses.dataclass
class WorldModelConfig:
    ranges: ClassVar[dict] = {"discrete": (0, None), "unimix": (0, 1), "grad_clip": "> 0", "min_std": "> 0"}
    choices: ClassVar[dict] = {"obs": ("state", "pixels")}  # train.py's --obs accepts these alone
    obs: str = "state"  # 'state': proprioception (ours, a CPU budget; deviation) or 'pixels': 64x64x3 (the paper)
    deter: int = 200  # GRU state h_t, Dreamer V1
    stoch: int = 30  # z_t: Gaussian units (Dreamer V1), or categorical variables when discrete > 0 (DreamerV2; GenRL: 32)
    discrete: int = 0  # classes per categorical variable of z_t (DreamerV2; GenRL: 32); 0: a Gaussian z_t (Dreamer V1)
    unimix: float = 0.01  # DreamerV3: the categorical's probabilities mixed with 1 % uniform (unused by a Gaussian z_t)
    hidden: int = 256  # width of the RSSM's input and head layers (ours; Dreamer V1: 200)
    units: int = 256  # width of the state encoder/decoder MLPs (ours; Dreamer V1's MLP size: 400)
    layers: int = 2  # hidden layers of the state encoder/decoder MLPs (ours: a 24-36-d vector needs little)
    cnn_depth: int = 32  # channels of the first conv layer of the pixel encoder/decoder, doubled per layer (Dreamer V1: 32, 64, 128, 256)
    min_std: float = 0.1  # Dreamer V1: std = softplus(x) + 0.1 of a Gaussian z_t
    free_nats: float = 1.0  # Dreamer V3: each KL term is clipped below 1 nat per step
    kl_dyn: float = 0.5  # Dreamer V3 KL balancing: weight of KL(sg(post) || prior), trains the prior
    kl_rep: float = 0.1  # Dreamer V3 KL balancing: weight of KL(post || sg(prior)), trains the posterior
    batch: int = 16  # sequences per batch (ours, a CPU budget; Dreamer V1: 50)
    seq_len: int = 50  # steps per sequence, Dreamer V1
    lr: float = 6e-4  # Adam, Dreamer V1
    grad_clip: float = 100.0  # global gradient norm, Dreamer V1


@dataclasses.dataclass
class GoalVAEConfig:
    ranges: ClassVar[dict] = {"grad_clip": "> 0", "min_std": "> 0", "kappa": "> 0"}
    units: int = 256  # MLP width, the world model's (ours; Dreamer V1's MLP size: 400)
    layers: int = 2  # hidden layers of the encoder and of the decoder (ours)
    min_std: float = 0.1  # std = softplus(x) + 0.1, as the world model (Dreamer V1)
    kappa: float = 10.0  # vMF concentration of p(p_t | s) (ours: recon kappa * (1 - cos) on the scale of the z KL)
    posterior_recon: float = 1.0  # weight of the decoder's fit on world-model posterior states (ours, `loss`; 0 = Eq. 3 alone)
    lr: float = 6e-4  # Adam, the world model's rate (Dreamer V1)
    grad_clip: float = 100.0  # global gradient norm, Dreamer V1


@dataclasses.dataclass
class DistanceConfig:
    choices: ClassVar[dict] = {"input": ("obs", "feat")}  # train.py's flags accept these alone
    ranges: ClassVar[dict] = {"encoder_goals": (0, 1), "grad_clip": "> 0"}
    units: int = 128  # width of d's MLP (LEXA: 4 x 128)
    layers: int = 4  # hidden layers of d's MLP (LEXA)
    pairs: int = 1024  # candidate pairs of each kind (same / different trajectory) per batch (ours)
    contrastive_weight: float = 0.1  # weight of Eq. 7's contrastive term (LEXA's 10% negatives ~ 0.11; Eq. 7: 1, equal weights)
    encoder_goals: int = 1  # 1: also fit d(s_i, g_j) with g_j the goal encoder's goal of frame j (ours); 0: Eq. 7 alone
    input: str = "obs"  # 'obs': d on decoded observations (ours, LEXA's embedding; state obs only); 'feat': on [h, z] (Eq. 7)
    lr: float = 3e-4  # Adam (ours: the usual rate for a small MLP)
    grad_clip: float = 100.0  # global gradient norm, as the world model (Dreamer V1)


@dataclasses.dataclass
class ActorCriticConfig:
    ranges: ClassVar[dict] = {"goal_near": (0, 1), "gamma": (0, 1), "lambda_": (0, 1), "goal_mix": (0, 1),
                              "slow_critic_rate": (0, 1), "return_norm_decay": (0, 1), "grad_clip": "> 0", "min_std": "> 0", "max_std": "> 0",
                              "mean_scale": "> 0"}
    units: int = 256  # MLP width (ours, a CPU budget; Dreamer V1: 400)
    actor_layers: int = 2  # hidden layers of the actor's MLP (ours, a CPU budget; Dreamer V1: 4)
    critic_layers: int = 2  # hidden layers of the critic's MLP (ours, a CPU budget; Dreamer V1: 3)
    horizon: int = 15  # imagined steps H, Dreamer V1 (GenRL: 16)
    gamma: float = 0.99  # discount of Eq. 4's imagined returns (Dreamer V1)
    lambda_: float = 0.95  # TD(lambda), Dreamer V1
    actor_lr: float = 3e-4  # Adam (ours; Dreamer V1: 8e-5)
    critic_lr: float = 3e-4  # Adam (ours; Dreamer V1: 8e-5)
    grad_clip: float = 100.0  # global gradient norm, Dreamer V1
    mean_scale: float = 5.0  # pre-tanh mean = 5 tanh(x / 5), Dreamer V1's tanh-normal
    min_std: float = 0.1  # lower bound of the actor's std (Dreamer V3)
    max_std: float = 1.0  # upper bound of the actor's std (Dreamer V3)
    entropy: float = 3e-4  # entropy bonus scale, Dreamer V3
    slow_critic_rate: float = 0.02  # EMA rate of the slow critic that computes the targets, Dreamer V3
    return_norm_decay: float = 0.99  # EMA decay of the 5-95 percentile range of returns, Dreamer V3
    starts: int = 32  # imagination start states per update (ours: an update's time is linear in them; Dreamer V1: all 50x50 states)
    goal_mix: float = 0.5  # share of goals from the goal encoder, the rest D_body posterior states (ours; sample_goals)
    goal_near: float = 0.5  # share of goals from a later frame of the start state's own segment, reachable in the horizon (ours; sample_goals)


@dataclasses.dataclass
class CloningConfig:
    ranges: ClassVar[dict] = {"bc_final": (0, 1), "bc_polish": (0, None)}
    bc: float = 1.0  # weight of hindsight behaviour cloning beside Eq. 4's actor loss (ours, a deviation, bc_loss; 0 = Eq. 4 alone)
    bc_final: float = 0.5  # share of bc_loss's goals from the episode's last frame, what the benchmark and GIIL-ZS give (ours)
    bc_steps: int = 10  # actor steps on bc_loss per update: the first with Eq. 4's loss, the rest on bc_loss alone, each with fresh goals (ours)
    bc_polish: int = 5000  # bc_loss steps of the actor alone on the frozen final world model and goal VAE, after the last update (ours; polish)
    bc_polish_batches: int = 250  # D_body batches whose posterior states the polish computes once and cycles (ours; polish)


# every phase-1 component's config class and flag prefix ('' = no prefix); their presets are PRESETS[<component>]
COMPONENTS = {
    "train": (TrainConfig, ""),
    "wm": (WorldModelConfig, "wm-"),
    "goal": (GoalVAEConfig, "goal-"),
    "dist": (DistanceConfig, "dist-"),
    "ac": (ActorCriticConfig, "ac-"),
    "cloning": (CloningConfig, "ac-"),  # a term of the actor's loss: --ac-bc, --ac-bc-final, ...
}


# the datasets (collect.py)

@dataclasses.dataclass
class CollectConfig:
    ranges: ClassVar[dict] = {"seed": (0, None), "history_from": (0, 1)}
    explore_episodes: int = 80  # D_body exploration episodes (ours; the paper: ~2000)
    # D_body episodes per task in envs.BODY_TASKS (ours: each doubling from 40 raised goal reaching, docs/ablations.md,
    # Phase 1; the paper: 1000, which makes exploration : task episodes 2 : 3 there, 1 : 6 here)
    task_episodes: int = 160
    demo_episodes: int = 10  # per (body, task, view): paper Sec. 5
    episode_steps: int = envs.EPISODE_STEPS  # agent steps per episode
    action_noise: float = 0.3  # std of the Gaussian noise on snapshot actions in D_body (ours)
    # task episodes come from the snapshots at or after this fraction of each expert's last history step (ours; 0 = the whole
    # history, kept: the later half alone did not raise the stickman's goal reaching, docs/ablations.md, Phase 1)
    history_from: float = 0.0
    seed: int = 0  # the collection's seed: every episode's own seed is derived from it and the episode's name


# phase 2 (imitate.py, tables.py): the goal searches, the OT reward, GIIL-online

@dataclasses.dataclass
class ImitateConfig:
    ranges: ClassVar[dict] = {"video": (0, 1)}
    preset: str = "cpu"  # smoke | cpu | paper: the overrides in PRESETS["imitate"] and PRESETS["ot"]
    steps: int = 300  # goal-finetuning updates (ours, a CPU budget)
    starts: int = 64  # imagined trajectories per L_GI update (ours)
    goal_lr: float = 3e-4  # Adam on g (ours; chosen on same-body cells, docs/ablations.md)
    critic_lr: float = 8e-5  # V_ot, as the phase-1 critic (Dreamer V1)
    seeds: int = 5  # GIIL-FT seeds (the paper: 3; 5 so that FT vs ZS(demo 0) is measured beyond the noise)
    eval_episodes: int = 3  # episodes per GIIL-ZS goal and per goal search's seed
    eval_steps: int = envs.EPISODE_STEPS  # agent steps per evaluation episode
    video: int = 1  # write demo | agent side-by-side videos


EPS_MIN = 0.004  # float64: exp(-2/eps) = exp(-500) ~ 7e-218 stays above the smallest normal 2e-308, with room for u, v


@dataclasses.dataclass
class OTConfig:
    eps: float = 0.01  # Sinkhorn entropic regularisation, absolute on the cosine cost in [0, 2] (ROT: epsilon 0.01 with POT)
    iters: int = 100  # Sinkhorn iterations, a fixed count without early stop (ROT: niter=100)
    scale: float = 1.0  # reward scale: sum_t r_t = -scale * <P, C> in [-2 scale, 0] (ROT: sinkhorn_rew_scale)
    cpu_chunk_bytes: int = 2**20  # CPU: trajectories solved together so their float64 kernels fit the L2 cache (faster than one batch, `python bench.py --only ot`); GPU: one batch

    def __post_init__(self):
        if not self.eps >= EPS_MIN:
            raise ValueError(f"OTConfig.eps={self.eps} is below {EPS_MIN}: exp(-C/eps) underflows float64 for cosine costs near 2")
        if self.iters < 1:
            raise ValueError(f"OTConfig.iters={self.iters}: Sinkhorn needs at least one iteration")


@dataclasses.dataclass
class OnlineConfig:
    # (candidates kept, episodes each) per round (ours): 10 x 2, 4 x 3, 2 x 9 = 50 episodes, AIME-NoB's 50,000 env steps
    schedule: tuple = ((10, 2), (4, 3), (2, 9))
    seed_base: int = 50_000  # refinement env seeds: seed_base + 1000 seed + i, apart from the evaluation's 20000 + 100 seed + e
    seeds: int = 3  # GIIL-online seeds (as the paper's non-zero-shot methods), each paired with GIIL-ZS (demo 0)


# the baselines (baselines/genrl.py, baselines/aime_nob.py)

@dataclasses.dataclass
class GenRLConfig:
    preset: str = "cpu"  # smoke | cpu: the overrides in PRESETS["genrl"]
    steps: int = 1000  # actor-critic updates per seed (ours: the time per seed and cell set for GenRL here; more updates help,
    # docs/ablations.md, Baselines' budgets; GenRL trains far longer)
    starts: int = 128  # imagination start states per update, D_body posterior states (ours: half the shipped agents' 256, for time)
    target_len: int = 15  # L: target states, q(s | p) of the first demo's last L features (GenRL: as long as the imagination, H = 15 here)
    align_window: int = 8  # k: imagined steps matched to the target's start (GenRL: n_frames 8, the video model's window)
    seeds: int = 3  # Sec. 5: baselines run with 3 seeds
    eval_episodes: int = 2  # episodes in the agent's own env per seed
    eval_steps: int = envs.EPISODE_STEPS  # agent steps per evaluation episode
    eval_at: str = ""  # also evaluate after these updates, comma-separated, each below --steps (ours: the score against budget)
    budget_field: ClassVar[str] = "steps"  # the field a budget of eval_at counts in

    def __post_init__(self):
        rundir.check_flags(self)
        budgets(self)  # a malformed --eval-at fails here, before anything runs
        if self.align_window > self.target_len:
            raise ValueError(f"--align-window {self.align_window} is longer than --target-len {self.target_len}: pass a window <= the target")


@dataclasses.dataclass
class AIMENoBConfig:
    ranges: ClassVar[dict] = {"body_ratio": (0, 1), "reward_sum": "> 0"}
    preset: str = "cpu"  # smoke | cpu: the overrides in PRESETS["aime_nob"], and the OT solver's preset of the same name
    env_steps: int = 5000  # interaction budget per seed in agent steps: 10 episodes (ours, cpu time; AIME-NoB interacts far longer)
    episode_steps: int = envs.EPISODE_STEPS  # agent steps per collected episode (a whole episode)
    updates: int = 50  # world-model and actor-critic updates after each episode (ours: a cpu seed in minutes, docs/ablations.md, Baselines' budgets)
    starts: int = 128  # imagination start states per update, posterior states of the batch (as genrl.py)
    body_ratio: float = 0.5  # share of D_body segments in each world-model batch (AIME-NoB: embodiment data at ratio 0.5)
    reward_sum: float = 10.0  # the first episode's OT labels are scaled to sum to -reward_sum (ROT: auto_rew_scale_factor 10)
    seeds: int = 3  # Sec. 5: baselines run with 3 seeds
    eval_episodes: int = 2  # episodes in the agent's own env per seed
    eval_steps: int = envs.EPISODE_STEPS  # agent steps per evaluation episode
    eval_at: str = ""  # also evaluate after these env steps, comma-separated whole episodes below --env-steps (ours, as genrl.py)
    budget_field: ClassVar[str] = "env_steps"

    def __post_init__(self):
        rundir.check_flags(self)
        if self.env_steps % self.episode_steps:
            raise ValueError(f"--env-steps {self.env_steps} is not a multiple of --episode-steps {self.episode_steps}: the budget is whole episodes")
        if self.body_ratio == 1:
            raise ValueError("--body-ratio 1: must be below 1, the rest of each batch is the new episodes, which train the reward")
        budgets(self)  # a malformed --eval-at fails here


def budgets(cfg):
    """The budgets a baseline's seed is evaluated at, ascending: those of cfg.eval_at and the whole cfg.<budget_field>."""
    final, flag = getattr(cfg, cfg.budget_field), "--" + cfg.budget_field.replace("_", "-")
    try:
        marks = sorted({int(b) for b in cfg.eval_at.split(",") if b.strip()})
    except ValueError:
        raise ValueError(f"--eval-at {cfg.eval_at!r}: pass budgets as comma-separated integers, e.g. 1000,2000") from None
    bad = [b for b in marks if not 0 < b < final or b % getattr(cfg, "episode_steps", 1)]
    if bad:
        whole = f", whole episodes of --episode-steps {cfg.episode_steps}" if hasattr(cfg, "episode_steps") else ""
        raise ValueError(f"--eval-at {bad[0]}: each budget must be between 0 and {flag} {final}{whole}")
    return marks + [final]


PRESETS = {
    # phase 1 (train.py; COMPONENTS): TrainConfig, WorldModelConfig, GoalVAEConfig, DistanceConfig, ActorCriticConfig, CloningConfig
    "train": {
        "smoke": dict(steps=6, policy_start=2, holdout_every=3, eval_episodes=1, eval_steps=10, log_every=2, checkpoint_every=3,
                      data=os.path.join("data", "smoke")),  # ours: toy
        "cpu": {},
        "paper": dict(steps=100_000, policy_start=5_000, log_every=1000, checkpoint_every=5000),  # ours: Dreamer-scale updates
    },
    "wm": {
        "smoke": dict(deter=16, stoch=4, hidden=16, units=16, cnn_depth=4, batch=4, seq_len=8),  # ours: toy
        "cpu": {},
        # GenRL's sizes and latent (Mazzaglia et al. 2024) on the paper's pixels: z 32 categoricals of 32 classes (DreamerV2)
        "paper": dict(obs="pixels", deter=1024, stoch=32, discrete=32, hidden=1024, units=1024, cnn_depth=48, batch=48, seq_len=48),
    },
    "goal": {"smoke": dict(units=16), "cpu": {}, "paper": dict(units=1024)},  # ours: toy; paper: the world model's width (GenRL)
    "dist": {
        "smoke": dict(units=16, layers=2, pairs=64),  # ours: toy
        "cpu": {},
        "paper": dict(contrastive_weight=1.0, input="feat"),  # Eq. 7 as written: both expectations weighed equally, d on [h, z]
    },
    "ac": {
        "smoke": dict(units=16, horizon=5),  # ours: toy
        "cpu": {},
        # GenRL: width 1024, horizon 16, all states of a 48x48 batch as starts; Dreamer V1: the layers and rates
        "paper": dict(units=1024, horizon=16, starts=48 * 48, actor_layers=4, critic_layers=3, actor_lr=8e-5, critic_lr=8e-5, goal_near=0.0),
    },
    "cloning": {"smoke": dict(bc_polish=4), "cpu": {}, "paper": dict(bc=0.0, bc_final=0.0, bc_steps=1, bc_polish=0)},  # ours: toy; paper: Eq. 4 alone
    # the datasets (collect.py): CollectConfig
    "collect": {
        "smoke": dict(explore_episodes=2, task_episodes=1, demo_episodes=2, episode_steps=20),  # ours: toy
        "cpu": {},
        "paper": dict(explore_episodes=2000, task_episodes=1000),  # the paper's D_body: ~2000 exploration, 1000 per task
    },
    # phase 2 (imitate.py, tables.py): ImitateConfig, OTConfig
    "imitate": {
        "smoke": dict(steps=3, starts=8, seeds=2, eval_episodes=1, eval_steps=10),  # ours: toy
        "cpu": {},
        "paper": dict(steps=2000, starts=256),  # ours: longer finetuning on more starts, for a GPU
    },
    "ot": {"smoke": dict(iters=20), "cpu": {}, "paper": {}},  # ours: toy
    # GIIL-online (online.py, ours after Sec. 6): OnlineConfig
    "online": {"smoke": dict(schedule=((2, 1), (1, 1)), seeds=1), "cpu": {}, "paper": {}},  # ours: toy
    # the baselines (baselines/genrl.py, baselines/aime_nob.py): GenRLConfig, AIMENoBConfig; no paper preset (tables.py --run runs their cpu one)
    "genrl": {"smoke": dict(steps=3, starts=8, target_len=5, align_window=3, seeds=2, eval_steps=10), "cpu": {}},  # ours: toy
    "aime_nob": {"smoke": dict(env_steps=20, episode_steps=10, updates=2, starts=8, seeds=2, eval_steps=10), "cpu": {}},  # ours: toy
}

# Where each preset's datasets go by default (--data): the smoke preset's 20-step episodes never share a folder with the
# 500-step ones of the others (cpu and paper episodes are alike: paper's D_body extends cpu's)
DATA = {"smoke": PRESETS["train"]["smoke"]["data"], "cpu": "data", "paper": "data"}


def field_comments(cls):
    """{field: its comment in the source} of a dataclass: the comment lines right above the field and the one after it,
    which say what the field is and where its value comes from (the paper, Dreamer, GenRL, ours)."""
    lines = inspect.getsource(cls).splitlines()
    comments = {tok.start[0]: (tok.start[1], tok.string.lstrip("#").strip())
                for tok in tokenize.generate_tokens(io.StringIO("\n".join(lines) + "\n").readline) if tok.type == tokenize.COMMENT}
    names, out, above = {f.name for f in dataclasses.fields(cls)}, {}, []
    for number, line in enumerate(lines, 1):
        indent = len(line) - len(line.lstrip())
        if number in comments and comments[number][0] == indent:  # a comment line of its own: about the field below
            above.append(comments[number][1])
            continue
        name = re.match(r"\s+(\w+)\s*:", line)
        if name and name.group(1) in names:
            out[name.group(1)] = " ".join(above + ([comments[number][1]] if number in comments else []))
        above = []
    return out


def config_flags(parser, cls, prefix="", dest="", choices=None, bare=()):
    """One flag --<prefix><field> per field of the dataclass cls, stored as <dest><field>, default None ('not given': the
    preset's value applies); its help is the field's source comment. choices: {field: the values allowed}; bare: fields
    whose flag has no prefix (--obs, what every command calls the world model's input)."""
    comments, choices = field_comments(cls), choices or {}
    for field in dataclasses.fields(cls):
        kind = type(field.default)
        if kind not in (int, float, str, bool):  # a tuple (online's schedule): only a preset sets it
            continue
        parser.add_argument("--" + ("" if field.name in bare else prefix) + field.name.rstrip("_").replace("_", "-"), dest=dest + field.name, type=kind, default=None,
                            choices=choices.get(field.name), metavar=None if field.name in choices else kind.__name__.upper(),
                            help=f"{comments.get(field.name) or cls.__name__ + '.' + field.name} (default {field.default!r}"
                                 f"{'' if field.name == 'preset' else ', or the preset' + chr(39) + 's'})".replace("%", "%%"))
