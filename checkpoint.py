"""Eq. 1's two levels share one phase-1 run: its configs (configs.COMPONENTS) and models, and its data.

Below train.py (phase 1), goal_inference.py (phase 2) and the baselines (baselines/), which import it and never each
other:
  build_models, load_run   a run's models, fresh or from runs/<name>/checkpoint.pt (rundir.run_checkpoint checks it)
  stored_configs, check_weights  a checkpoint's configs and weights, checked before any model is built
  resume_from, save, stop_hint   phase 1's checkpoint: where a run goes on from (--resume), what it keeps, what a
                           diverged update says of it
  default_run_dir, resolve_run   where train.py writes a run, and which one phase 2 uses when none is named
  work_folder              where phase 2 writes for a run: the run's folder, runs/agent_<body> for a shipped agent
  prepare_data             the run's D_body (collected first where incomplete) as training segments and held-out episodes
  body_segments, demo_folder     the run's D_body as segments, and a demo folder (collected first where missing)
  export_agent             a trained run as a shipped agent, agents/<body>/checkpoint.pt: weights only (train.py --export)
"""
import dataclasses
import fcntl
import json
import os

import numpy as np
import torch

import collect
import configs
import distance
import envs
import goal_vae
import policy
import rundir
import world_model
from configs import COMPONENTS, DATA, PRESETS
from video_encoder import check_same_encoder, load_encoder


# Switches measured worse and deleted, at the value that turned each off (docs/ablations.md names each one's result and
# the commit that had it): a stored config that holds one at that value loads as before, one trained with it on is refused
REMOVED = {"train": dict(act_temperature=0.0, cover_edges=0, fidelity_every=0, wm_steps=0),
           "wm": dict(overshoot=0, overshoot_starts=4),
           "ac": dict(reward="distance", mixture=1, actor_input="feat", uncertainty=0.0),
           "dist": dict(reading="eq7", gamma=0.99, tau=0.95, td_n=10, slow_rate=0.02),
           "cloning": dict(bc_awr=0.0, bc_polish_ema=0.0, bc_polish_fresh=0, bc_advantage=0.0)}


def build_models(cfgs, obs_shape, action_dim, p_dim, device):
    """A run's models, freshly initialised: {name: module} on `device`."""
    wm = world_model.WorldModel(cfgs["wm"], obs_shape, action_dim)
    if cfgs["dist"].input == "obs" and cfgs["wm"].obs != "state":
        raise ValueError("--dist-input obs reads decoded state vectors: with --obs pixels pass --dist-input feat")
    make_dist = lambda: distance.DistanceNet(cfgs["dist"], wm.feat_dim, wm.decoder if cfgs["dist"].input == "obs" else None)  # noqa: E731
    models = {
        "world_model": wm,
        "goal_vae": goal_vae.GoalVAE(cfgs["goal"], p_dim, cfgs["wm"].deter, wm.latent),
        "dist_net": make_dist(),
        "actor": policy.Actor(cfgs["ac"], wm.feat_dim, wm.feat_dim, action_dim),
        "return_norm": policy.ReturnNorm(cfgs["ac"].return_norm_decay),
    }
    models["critic"], models["slow_critic"] = policy.make_critics(cfgs["ac"], wm.feat_dim, wm.feat_dim)
    return {k: m.to(device) for k, m in models.items()}


def stored_configs(ckpt, path):
    """A checkpoint's configs {component: dataclass}. A field it lacks came after it was written and reads as today's
    default; a field since deleted (REMOVED) is dropped at its off value, and a one-line error otherwise."""
    damaged = f"{path} is damaged or not this project's checkpoint"
    config = ckpt.get("config")
    if isinstance(config, dict) and "cloning" not in config and isinstance(config.get("ac"), dict):
        # written before the cloning had a config of its own (the shipped agents): its fields were the actor-critic's
        config = {**config, "ac": {k: v for k, v in config["ac"].items() if not k.startswith("bc")},
                  "cloning": {k: v for k, v in config["ac"].items() if k.startswith("bc")}}
    if not isinstance(config, dict) or set(config) != set(COMPONENTS):
        raise ValueError(f"{damaged}: its config names {sorted(config or [])}, not {sorted(COMPONENTS)}")
    cfgs = {}
    for name, fields in config.items():
        cls, prefix = COMPONENTS[name]
        known = {f.name: f.default for f in dataclasses.fields(cls)}
        for field, value in fields.items():
            if field not in known and REMOVED.get(name, {}).get(field, object()) != value:
                raise ValueError(f"{path} was trained with --{prefix}{field.replace('_', '-')} {value}, a variant measured worse and deleted "
                                 f"(docs/ablations.md names the commit that had it): load it with that commit's code")
            kind = type(known.get(field, value))
            if not isinstance(value, (int, float) if kind is float else kind) or isinstance(value, bool) != (kind is bool):
                raise ValueError(f"{damaged}: its config {name}.{field} is {value!r}, not of type {kind.__name__}")
        cfgs[name] = cls(**{k: v for k, v in fields.items() if k in known})
        for field, allowed in getattr(cls, "choices", {}).items():
            if getattr(cfgs[name], field) not in allowed:
                raise ValueError(f"{damaged}: its config {name}.{field} is {getattr(cfgs[name], field)!r}, not one of {', '.join(allowed)}")
        try:  # the ranges the flags are held to (a stored deter -1 or horizon 0 is no model to build)
            rundir.check_flags(cfgs[name], prefix)
        except ValueError as error:
            raise ValueError(f"{damaged}: its config holds {error}") from None
    if cfgs["train"].preset not in PRESETS["train"]:
        raise ValueError(f"{damaged}: its preset {cfgs['train'].preset!r} is not one of {', '.join(PRESETS['train'])}")
    return cfgs


def check_weights(ckpt, models, path):
    """A checkpoint's weights have the names and shapes of `models` (built from its config, on the meta device where
    only this is asked: no memory), or a one-line error naming the file and the first difference."""
    for name, model in models.items():
        want, has = model.state_dict(), ckpt["models"].get(name)
        if not isinstance(has, dict):
            raise ValueError(f"{path} is damaged or not this project's checkpoint: it has no weights of the {name}")
        for key in sorted(want.keys() | has.keys()):
            shapes = [tuple(d[key].shape) if key in d and hasattr(d[key], "shape") else None for d in (want, has)]
            if shapes[0] != shapes[1]:
                raise ValueError(f"{path} is damaged or not this project's checkpoint: {name}.{key} is {shapes[1]} where its config "
                                 f"makes {shapes[0]}")


def load_run(run_dir, device="cpu", env=None):
    """A trained run: (configs, models, checkpoint metadata), checked against --env and its folder's name
    (rundir.run_checkpoint). Errors name the command that makes one."""
    ckpt = rundir.run_checkpoint(run_dir, device, env)
    path = os.path.join(run_dir, "checkpoint.pt")
    cfgs = stored_configs(ckpt, path)
    shapes = (ckpt.get("obs_shape"), ckpt.get("action_dim"), ckpt.get("p_dim"))
    obs_ok = shapes[0] == (64, 64, 3) or list(shapes[0] or ()) == [64, 64, 3] if cfgs["wm"].obs == "pixels" else isinstance(shapes[0], int) and shapes[0] >= 1
    if not (obs_ok and all(isinstance(n, int) and n >= 1 for n in shapes[1:]) and isinstance(ckpt.get("step"), int) and ckpt["step"] >= 0):
        raise ValueError(f"{path} is damaged or not this project's checkpoint: its step {ckpt.get('step')!r} or shapes (observation "
                         f"{shapes[0]!r}, action {shapes[1]!r}, p {shapes[2]!r}) are not counts; delete it or restore it from a copy")
    with torch.device("meta"):  # names and shapes checked before any memory is taken
        check_weights(ckpt, build_models(cfgs, *shapes, "meta"), path)
    models = build_models(cfgs, *shapes, device)
    for name, model in models.items():
        model.load_state_dict(ckpt["models"][name])
    return cfgs, models, ckpt


# fields that may differ when a run is resumed: they do not change what the models are
RESUMABLE = {"steps", "log_every", "checkpoint_every", "eval_episodes", "eval_steps", "eval_seed", "data", "threads",
             "bc_polish", "bc_polish_batches"}  # the polish starts from the training actor, kept apart in the checkpoint
LR_FLAGS = {"world_model": ("wm", "lr"), "goal_vae": ("goal", "lr"), "dist_net": ("dist", "lr"), "actor": ("ac", "actor_lr"), "critic": ("ac", "critic_lr")}


def resume_from(ckpt_path, resume, cfgs, models, optims, encoder, device, rng):
    """Where a run starts: (0, rng) for a new run; with --resume, its checkpoint's weights, optimisers and RNGs after
    checking that it is the same run -> (update, numpy Generator)."""
    if not os.path.exists(ckpt_path):
        return 0, rng
    if not resume:
        raise ValueError(f"{ckpt_path} exists: pass --resume to continue that run, or another --seed for a new one")
    ckpt, config = rundir.load_checkpoint(ckpt_path, device), {n: dataclasses.asdict(c) for n, c in cfgs.items()}
    saved = {n: dataclasses.asdict(c) for n, c in stored_configs(ckpt, ckpt_path).items()}  # a deleted switch left on: an error
    changed = [f"{n}.{k}" for n in config for k in config[n] if k not in RESUMABLE and saved[n].get(k) != config[n][k]]
    if changed:
        raise ValueError(f"{ckpt_path} was trained with other {', '.join(changed)}: pass the same flags to resume, or start a new run")
    if config["train"]["steps"] < ckpt["step"]:
        raise ValueError(f"--steps {config['train']['steps']} is below the update {ckpt['step']} of {ckpt_path}: pass --steps {ckpt['step']} or more")
    check_same_encoder(ckpt["encoder"], encoder.name, ckpt_path)
    check_weights(ckpt, models, ckpt_path)
    for name, model in models.items():
        model.load_state_dict(ckpt["models"][name])
    models["actor"].load_state_dict(ckpt.get("actor_unpolished", ckpt["models"]["actor"]))  # training goes on from the unpolished actor
    if "optims" not in ckpt:  # a shipped agent (checkpoint.export_agent: weights only) copied into run_dir: trained on from its
        # weights (its polished actor) with fresh Adam moments and RNGs seeded from (seed, update) (ours; training longer
        # than it was shipped, docs/ablations.md)
        print(f"resumed {ckpt_path} at update {ckpt['step']} from its weights alone (an exported agent): fresh optimisers")
        torch.manual_seed(config["train"]["seed"] * 1_000_003 + ckpt["step"])
        return ckpt["step"], np.random.default_rng([config["train"]["seed"], ckpt["step"]])
    for name, opt in optims.items():
        opt.load_state_dict(ckpt["optims"][name])
    torch.set_rng_state(ckpt["torch_rng"].cpu())  # load_checkpoint maps every tensor to `device`; the CPU generator needs a CPU tensor
    print(f"resumed {ckpt_path} at update {ckpt['step']}")
    return ckpt["step"], rundir.generator(ckpt["rng"])


def save(ckpt_path, cfgs, step, rng, encoder, shapes, models, optims, **actors):
    """runs/<name>/checkpoint.pt: what checkpoint.load_run reads and what --resume needs (optimisers, RNGs); `actors`:
    actor state_dicts kept beside the models (actor_unpolished). Returns the update it holds."""
    state = {"config": {n: dataclasses.asdict(c) for n, c in cfgs.items()}, "step": step, "rng": rng.bit_generator.state,
             "torch_rng": torch.get_rng_state(), "encoder": encoder.name, "obs_shape": shapes[0], "action_dim": shapes[1], "p_dim": shapes[2],
             "models": {k: m.state_dict() for k, m in models.items()}, "optims": {k: o.state_dict() for k, o in optims.items()},
             **actors}
    rundir.atomic_write(ckpt_path, lambda f: torch.save(state, f))
    return step


def stop_hint(ckpt_path, saved, cfgs, name):
    """What a diverged update says after 'stopped; ': the checkpoint kept, and the learning rate of the model `name`."""
    kept = f"the last good checkpoint is {ckpt_path} (update {saved}), untouched" if os.path.exists(ckpt_path) else \
        f"no checkpoint was written yet (the first comes at update {cfgs['train'].checkpoint_every})"
    component, field = LR_FLAGS[name]
    return f"{kept}. A learning rate too high? --{COMPONENTS[component][1]}{field.replace('_', '-')} is {getattr(cfgs[component], field)}"


def default_run_dir(env, preset, seed=0, obs=None):
    """runs/<env>_<obs>_<preset>_s<seed> (obs: the preset's unless given): where train.py writes and imitate.py reads."""
    obs = obs or PRESETS["wm"][preset].get("obs", configs.WorldModelConfig.obs)
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


def work_folder(run_dir):
    """Where phase 2 and the benchmark write for run_dir (rows, videos, tables, baselines' states; rundir.work_path): the
    run's own folder, but for a shipped agent (agents/<body>: committed weights only) runs/agent_<body> beside agents/,
    made here with a checkpoint.pt that links to the agent's (read, never written through: rundir.no_link); says so."""
    work = rundir.work_path(run_dir)
    if work == run_dir:
        return run_dir
    os.makedirs(work, exist_ok=True)
    link, weights = os.path.join(work, "checkpoint.pt"), os.path.abspath(os.path.join(run_dir, "checkpoint.pt"))
    if os.path.exists(link) and not os.path.islink(link):
        raise ValueError(f"{link} is a checkpoint of its own: move that run elsewhere, so that the shipped agent's results can go to {work}")
    if os.path.realpath(link) != os.path.realpath(weights):  # none yet, or a link to an agents/ folder since moved
        if os.path.islink(link):
            os.remove(link)
        os.symlink(weights, link)
    print(f"the shipped agent {run_dir}: its results go to {work}")
    return work


def body_episodes(cfgs, keys):
    """D_body's episodes in the run's data folder, for the commands that read it without collecting (the baselines,
    fidelity.py): refused in one line where its collection.json lists episodes no longer on disk (train.py collects them)."""
    tc = cfgs["train"]
    folder = os.path.join(tc.data, tc.env)
    complete = os.path.join(folder, collect.COMPLETE)
    listed = json.load(open(complete)).get("episodes", []) if os.path.exists(complete) else []
    if lost := [n for n in listed if not os.path.exists(os.path.join(folder, n))]:
        raise ValueError(f"D_body at {folder} lacks {len(lost)} of the {len(listed)} episodes its {collect.COMPLETE} lists ({lost[0]}, ...): "
                         f"collect them again (python collect.py --env {tc.env} --data {tc.data} --preset {tc.preset})")
    return collect.load_folder(folder, keys)


def body_features(cfgs, stride):
    """D_body's episodes as GIIL-retrieve reads them: their file names, video features every stride-th frame (N, T', D)
    and last features (N, D)."""
    episodes = body_episodes(cfgs, ("p",))
    return ([os.path.basename(e["path"]) for e in episodes], np.stack([e["p"][::stride] for e in episodes]),
            np.stack([e["p"][-1] for e in episodes]))


def body_segments(cfgs):
    """D_body as collect.Segments (the run's data folder and segment length): what L_MG keeps training on."""
    wc = cfgs["wm"]
    keys = (wc.obs, "action", "is_first", "p")
    return collect.Segments(body_episodes(cfgs, keys), keys, wc.seq_len)


def prepare_data(cfgs):
    """D_body of the run (collected first where incomplete) and the body's own demos (the benchmark's goals):
    -> encoder, training Segments, held-out episodes, (obs_shape, action_dim, p_dim)."""
    tc, wc = cfgs["train"], cfgs["wm"]
    folder, want = os.path.join(tc.data, tc.env), collect.preset_config(tc.preset)
    complete = os.path.join(folder, collect.COMPLETE)
    has = json.load(open(complete)) if os.path.exists(complete) else {}  # missing, or a collection killed half-way
    if has:  # a field added to CollectConfig since that collection reads as its default
        has = {**dataclasses.asdict(configs.CollectConfig()), **has}
    counts = ("explore_episodes", "task_episodes")
    same_kind = all(has.get(k) == v for k, v in dataclasses.asdict(want).items() if k not in counts)
    # a smaller D_body of the same recipe (the preset's older, smaller default) grows; another kind passed by --data
    # (e.g. shorter episodes) is used as it is
    fewer = [f"{k} {has.get(k, 0)} < {getattr(want, k)}" for k in counts if has.get(k, 0) < getattr(want, k)] if same_kind or not has else []
    if lost := [n for n in has.get("episodes", []) if not os.path.exists(os.path.join(folder, n))]:  # deleted since
        if not same_kind:
            raise ValueError(f"D_body at {folder} lacks {len(lost)} of the episodes its {collect.COMPLETE} lists ({lost[0]}, ...): "
                             f"collect them again with the settings that file names (python collect.py --env {tc.env} --data ...)")
        fewer.append(f"{len(lost)} of its episodes deleted")
    if has and not same_kind:
        other = [f"{k} {has.get(k)} (preset {v})" for k, v in dataclasses.asdict(want).items() if k not in counts and has.get(k) != v]
        print(f"D_body at {folder} was collected with {', '.join(other)}: used as it is; `python collect.py --env {tc.env} "
              f"--data <another folder>` collects the preset's")
    if fewer:
        print(f"D_body at {folder} is not complete ({', '.join(fewer)}): "
              f"collecting what is missing (python collect.py --env {tc.env} --preset {tc.preset})")
        collect.collect_body(tc.env, want, tc.data, os.cpu_count(), tc.encoder)
    if not all(os.path.isdir(os.path.join(tc.data, "demos", f"{tc.env}_{task}_side")) for task in envs.TASKS):
        print(f"{tc.env}'s own demos (the goals of the goal-reaching benchmark, evaluate.py) missing: collecting them")
        collect.collect_demos(want, tc.data, os.cpu_count(), tc.encoder, demos=[(tc.env, task) for task in envs.TASKS])
    encoder = load_encoder(tc.encoder)
    episodes = collect.load_folder(folder, (wc.obs, "action", "is_first", "p"), encoder=encoder.name)
    held_out = episodes[:: tc.holdout_every]
    train_eps = [e for k, e in enumerate(episodes) if k % tc.holdout_every]
    data = collect.Segments(train_eps, (wc.obs, "action", "is_first", "p"), wc.seq_len)
    obs_shape = episodes[0][wc.obs].shape[1] if wc.obs == "state" else (64, 64, 3)
    print(f"D_body {folder}: {len(train_eps)} training + {len(held_out)} held-out episodes, {sum(data.lengths)} steps, features {encoder.name}")
    return encoder, data, held_out, (obs_shape, episodes[0]["action"].shape[1], episodes[0]["p"].shape[1])


def demo_folder(cfgs, demo, view):
    """<data>/demos/<demo>_<view> of the run's data folder, its episodes collected first (both views of that body and
    task, the run's preset) where any is missing; an unknown demo lists the valid names."""
    tc = cfgs["train"]
    body, task = envs.parse_demo(demo)
    # the folder a checkpoint names is followed only where it is the preset's or a data folder of this project (the
    # run's D_body or demos in it): a run folder from elsewhere never makes this project write at a place of its choosing
    ours = (os.path.join(tc.data, tc.env, collect.COMPLETE), os.path.join(tc.data, "demos"))
    if os.path.normpath(tc.data) != os.path.normpath(DATA[tc.preset]) and not any(os.path.exists(p) for p in ours):
        raise ValueError(f"the run's checkpoint names the data folder {tc.data}, which holds neither D_body nor demos: not followed; "
                         f"put the run's data back there, or train a run on yours")
    if tc.encoder != "default" and not os.path.isdir(os.path.join(tc.data, "demos", f"{demo}_{view}")):  # said, not followed silently
        print(f"{demo}'s demos are collected with the run's video encoder {tc.encoder} (the file its checkpoint names)")
    os.makedirs(os.path.join(tc.data, "demos"), exist_ok=True)
    lock = os.open(os.path.join(tc.data, "demos"), os.O_RDONLY)
    try:  # table shards in parallel: one collects, the others wait on the folder's lock, then find the episodes on disk
        fcntl.flock(lock, fcntl.LOCK_EX)
        collect.collect_demos(collect.preset_config(tc.preset), tc.data, os.cpu_count(), tc.encoder, [(body, task)])
    finally:
        os.close(lock)
    return os.path.join(tc.data, "demos", f"{demo}_{view}")


def export_agent(run_dir, out_dir, force=False):
    """A trained run as a shipped agent: its models' float32 weights, config and shapes; no optimiser state or RNG.
    An agent already at out_dir is replaced only with force, and kept (with what was written for it) in previous_<n>/.
    Loadable by checkpoint.load_run like any run (float16 files of earlier exports are cast back to float32 on loading).
    float32, not float16 (ours): the walker exported in float16 scored lower on the benchmark than its run, paired over
    the same episodes (docs/ablations.md, Training length and export), and float32 fits in 7.5 MB."""
    rundir.not_training(run_dir)  # a checkpoint mid-training is not the agent
    path = os.path.join(out_dir, "checkpoint.pt")
    if os.path.exists(path) and not force:
        raise ValueError(f"--export {out_dir}: {path} holds an agent already: pass --force to replace it (the old one is kept in "
                         f"{out_dir}/previous_<n>/), or export elsewhere")
    ckpt = rundir.load_checkpoint(os.path.join(run_dir, "checkpoint.pt"))
    agent = {k: ckpt[k] for k in ("config", "step", "encoder", "obs_shape", "action_dim", "p_dim")}
    # D_body is not shipped: the agent reads (and collects) demos in its preset's default data folder, wherever it was
    # trained; that folder is kept as trained_data
    train_cfg = agent["config"]["train"]
    body = os.path.basename(os.path.normpath(out_dir))
    if os.path.basename(os.path.dirname(os.path.normpath(out_dir))) == rundir.AGENTS and body in envs.BODIES and body != train_cfg["env"]:
        raise ValueError(f"--export {out_dir}: {run_dir} trained a {train_cfg['env']} agent; export it to agents/{train_cfg['env']}")
    agent["config"] = {**agent["config"], "train": {**train_cfg, "data": DATA[train_cfg["preset"]]}}
    agent["trained_data"] = train_cfg["data"]
    agent["models"] = ckpt["models"]
    os.makedirs(out_dir, exist_ok=True)
    # what phase 2 and the benchmark wrote for the agent replaced here would mix with the new agent's (tables.py matches
    # rows by demo and settings, not by weights): moved, never deleted, to <out_dir>/previous_<n>/
    made = [f for f in ("checkpoint.pt", "results.jsonl", "tables.md", "goal_reaching.json", "imitate") if os.path.exists(os.path.join(out_dir, f))]
    if made:
        old = next(p for n in range(10**6) if not os.path.exists(p := os.path.join(out_dir, f"previous_{n}")))  # the first free
        os.makedirs(old)
        for f in made:
            os.replace(os.path.join(out_dir, f), os.path.join(old, f))
        print(f"moved the replaced agent's {', '.join(made)} to {old}")
    rundir.atomic_write(path, lambda f: torch.save(agent, f))
    return path
