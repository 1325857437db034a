"""Sec. 5's scale and ours: every command's presets side by side, one entry per config dataclass.

cpu    each dataclass's defaults, so what `python train.py --env walker` trains is what its dataclasses read (each
       field's comment names its source: the paper, Dreamer, LEXA, GenRL or ours); the shipped agents are cpu runs
smoke  every command end to end in seconds, the cpu recipe at toy sizes (the tests)
paper  the paper's sizes and Eq. 4 as it is written (no cloning), for a GPU
Each line below says where its values come from.
"""
import dataclasses
import inspect
import io
import os
import re
import tokenize

PRESETS = {
    # phase 1 (train.py; checkpoint.COMPONENTS): TrainConfig, WorldModelConfig, GoalVAEConfig, DistanceConfig, ActorCriticConfig, CloningConfig
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
    # phase 2 (goal_inference.py): ImitateConfig, and ot_reward.OTConfig
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
