"""Eq. 1's two levels share one phase-1 run: its configs and models, its data, and the checked optimiser step.

Below train.py (phase 1), imitate.py (phase 2) and the baselines (genrl.py, aime_nob.py), which import it and never
each other:
  TrainConfig, COMPONENTS  the configs of a run, one dataclass per component, and each one's flag prefix
  build_models, load_run   a run's models, fresh or from runs/<name>/checkpoint.pt (rundir.run_checkpoint checks it)
  default_run_dir, resolve_run   where train.py writes a run, and which one phase 2 uses when none is named
  body_segments, demo_folder     the run's D_body as segments, and a demo folder (collected first where missing)
  checked_step             one optimiser step, refused when the loss diverged or its gradient is not finite
"""
import dataclasses
import fcntl
import math
import os

import torch

import collect
import distance
import envs
import goal_vae
import policy
import rundir
import world_model
from presets import PRESETS


@dataclasses.dataclass
class TrainConfig:
    env: str = "walker"  # the agent's body
    preset: str = "cpu"  # smoke | cpu | paper: sizes of every component and of D_body
    seed: int = 0
    steps: int = 3000  # updates (ours: a CPU budget, docs/results.md; Dreamer-scale runs use ~1e5 and more)
    policy_start: int = 1000  # updates of the models before the actor-critic starts (ours)
    holdout_every: int = 20  # every 20th D_body episode is held out of training, for evaluate.evaluate_imagination (ours)
    eval_episodes: int = 3  # goal-reaching benchmark (evaluate.py, ours): episodes per own-body demo goal
    eval_steps: int = 500  # agent steps per goal-reaching episode (a whole episode)
    act_temperature: float = 0.0  # how the benchmark's policy acts, policy.Actor.act: 0 = tanh of the mean (Dreamer; more: ours, not kept)
    eval_seed: int = 30_000  # the benchmark's first environment seed; another gives fresh start poses, to confirm a choice made on it
    log_every: int = 100
    checkpoint_every: int = 250
    data: str = "data"  # the datasets' folder (presets.DATA)
    encoder: str = "default"  # video encoder of the features p_t (video_encoder.py)
    cover_edges: int = 0  # 1: D_body segments cover an episode's first steps at least as often as its middle (collect.Segments; ours, not kept)
    threads: int = 1  # torch CPU threads (ours: these small models ran faster on 1 than on 2 with the cores shared, docs/results.md, Speed)


# every component's config class and flag prefix ('' = no prefix); their presets are presets.PRESETS[<component>]
COMPONENTS = {
    "train": (TrainConfig, ""),
    "wm": (world_model.WorldModelConfig, "wm-"),
    "goal": (goal_vae.GoalVAEConfig, "goal-"),
    "dist": (distance.DistanceConfig, "dist-"),
    "ac": (policy.ActorCriticConfig, "ac-"),
}
DIVERGED = 1e10  # |loss| above this is divergence (ours: the smoke preset's losses are below 100; a learning rate of 1e3 on
# the goal VAE, distance or critic gave losses of 1e20 and more within 4 updates)


def build_models(cfgs, obs_shape, action_dim, p_dim, device):
    """A run's models, freshly initialised: {name: module} on `device`."""
    wm = world_model.WorldModel(cfgs["wm"], obs_shape, action_dim)
    if cfgs["dist"].input == "obs" and cfgs["wm"].obs != "state":
        raise ValueError("--dist-input obs reads decoded state vectors: with --obs pixels pass --dist-input feat")
    if cfgs["ac"].actor_input == "obs" and cfgs["wm"].obs != "state":
        raise ValueError("--ac-actor-input obs reads decoded state vectors: with --obs pixels pass --ac-actor-input feat")
    models = {
        "world_model": wm,
        "goal_vae": goal_vae.GoalVAE(cfgs["goal"], p_dim, cfgs["wm"].deter, cfgs["wm"].stoch),
        "dist_net": distance.DistanceNet(cfgs["dist"], wm.feat_dim, wm.decoder if cfgs["dist"].input == "obs" else None),
        "actor": policy.Actor(cfgs["ac"], wm.feat_dim, wm.feat_dim, action_dim, wm.decoder),
        "return_norm": policy.ReturnNorm(cfgs["ac"].return_norm_decay),
    }
    models["critic"], models["slow_critic"] = policy.make_critics(cfgs["ac"], wm.feat_dim, wm.feat_dim)
    if cfgs["ac"].uncertainty:  # only then: runs and agents without it keep their set of models
        models["ensemble"] = world_model.Disagreement.of(wm)
    return {k: m.to(device) for k, m in models.items()}


def load_run(run_dir, device="cpu", env=None):
    """A trained run: (configs, models, checkpoint metadata), checked against --env and its folder's name
    (rundir.run_checkpoint). Errors name the command that makes one."""
    ckpt = rundir.run_checkpoint(run_dir, device, env)
    cfgs = {name: COMPONENTS[name][0](**fields) for name, fields in ckpt["config"].items()}
    models = build_models(cfgs, ckpt["obs_shape"], ckpt["action_dim"], ckpt["p_dim"], device)
    for name, model in models.items():
        model.load_state_dict(ckpt["models"][name])
    return cfgs, models, ckpt


def default_run_dir(env, preset, seed=0, obs=None):
    """runs/<env>_<obs>_<preset>_s<seed> (obs: the preset's unless given): where train.py writes and imitate.py reads."""
    obs = obs or PRESETS["wm"][preset].get("obs", world_model.WorldModelConfig.obs)
    return os.path.join("runs", f"{env}_{obs}_{preset}_s{seed}")


def resolve_run(env, preset):
    """The run phase 2 uses when none is named: the user's own (runs/<env>_<obs>_<preset>_s0) when it exists, else the
    shipped agent of that body (cpu preset only); says which."""
    own = default_run_dir(env, preset)
    shipped = os.path.join(rundir.AGENTS, env)
    if not os.path.exists(os.path.join(own, "checkpoint.pt")) and preset == "cpu" and os.path.exists(os.path.join(shipped, "checkpoint.pt")):
        print(f"using the shipped {env} agent {shipped} (no run of your own at {own}; `python train.py --env {env}` makes one)")
        return shipped
    print(f"using the run {own}")
    return own


def body_segments(cfgs):
    """D_body as collect.Segments (the run's data folder and segment length): what L_MG keeps training on."""
    wc, tc = cfgs["wm"], cfgs["train"]
    keys = (wc.obs, "action", "is_first", "p")
    return collect.Segments(collect.load_folder(os.path.join(tc.data, tc.env), keys), keys, wc.seq_len)


def demo_folder(cfgs, demo, view):
    """<data>/demos/<demo>_<view> of the run's data folder, its episodes collected first (both views of that body and
    task, the run's preset) where any is missing; an unknown demo lists the valid names."""
    tc = cfgs["train"]
    body, _, task = demo.rpartition("_")
    if body not in envs.BODIES or task not in envs.TASKS:
        raise ValueError(f"unknown demo {demo!r}: valid demos are {', '.join(b + '_' + t for b in envs.BODIES for t in envs.TASKS)}")
    os.makedirs(os.path.join(tc.data, "demos"), exist_ok=True)
    lock = os.open(os.path.join(tc.data, "demos"), os.O_RDONLY)
    try:  # table shards in parallel: one collects, the others wait on the folder's lock, then find the episodes on disk
        fcntl.flock(lock, fcntl.LOCK_EX)
        collect.collect_demos(collect.preset_config(tc.preset), tc.data, os.cpu_count(), tc.encoder, [(body, task)])
    finally:
        os.close(lock)
    return os.path.join(tc.data, "demos", f"{demo}_{view}")


def checked_step(opt, loss, what, update, stop, clip=math.inf):
    """opt.step() on `loss`, its gradient's global norm clipped at `clip`; unless the loss diverged (DIVERGED) or is
    not finite, or its gradient is not: then a one-line ValueError '<what> is <loss> at update <update>: stopped;
    <stop()>' (or '... has a non-finite gradient ...'), the weights untouched. stop: what was kept and what to try."""
    opt.zero_grad(set_to_none=True)
    bad = "" if abs(loss.item()) < DIVERGED else f"is {loss.item():.3g}"  # False for nan and inf too
    if not bad:
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_([p for group in opt.param_groups for p in group["params"]], clip)
        bad = "" if torch.isfinite(norm) else f"has a non-finite gradient (norm {norm.item()})"
    if bad:
        raise ValueError(f"{what} {bad} at update {update}: stopped; {stop()}")
    opt.step()
