"""Sec. 2 and 5: the embodiment dataset D_body and the demonstration dataset D_demo, one .npz per episode.

D_body (data/<body>/), unlabelled experience of the agent's own body, the paper's recipe at our scale:
  explore_NNNN.npz  exploration: random actions held for a random 1-10 agent steps each (correlated
                    noise reaches more varied states than i.i.d. actions; the paper used Plan2Explore)
  <task>_NNNN.npz   for task in stand/walk/run: a snapshot drawn uniformly from that expert's learning
                    history (experts/history) acting with Gaussian action noise (the paper replays the
                    buffers of Dreamer agents trained on these tasks). Jump is held out of D_body.
  Proportion exploration : task episodes = 1 : 6 at the cpu preset (80 : 3 x 160; paper: ~2000 : 3 x 1000, 2 : 3).
D_demo (data/demos/<body>_<task>_<view>/NN.npz): the final expert of each (body, task), deterministic;
  each episode is simulated once and rendered from both cameras, so the side and diagonal folders show
  the same motion.

Episode keys, index t = 0..L (Dreamer alignment, see world_model.py):
  state   (L+1, obs_dim) float32  proprioceptive observation o_t
  pixels  (L+1, 64, 64, 3) uint8  the frame of o_t from `view`
  action  (L+1, A) float32        a_{t-1}, the action that led into o_t (zeros at t = 0)
  reward  (L+1,) float32          r_t, received on arriving in o_t (0 at t = 0); sum = `return`
  is_first (L+1,) bool            True at t = 0
  p       (L+1, D) float32        video features p_t of frames t-k+1..t (video_encoder.py)
  encoder, body, task, view, source (str), return (float): metadata; `task` is kept for auditing only,
  phase 1 never reads it (D_body is unlabelled).
Features are a second pass over stored pixels (`--features`), so a new encoder needs no re-simulation.
"""
import argparse
import contextlib
import glob
import json
import math
import multiprocessing
import os
import signal
import zipfile
from dataclasses import asdict, replace

import numpy as np
import torch
from tqdm import tqdm

import envs
import experts
import rundir
from configs import DATA, PRESETS, CollectConfig
from envs import BODY_TASKS
from video_encoder import check_same_encoder, load_encoder

KEYS = {"state": np.float32, "pixels": np.uint8, "action": np.float32, "reward": np.float32, "is_first": np.bool_, "p": np.float32}
META = ("encoder", "body", "task", "view", "source", "return")
COMPLETE = "collection.json"  # written into data/<body>/ once all of D_body is on disk: its CollectConfig and episodes


def preset_config(preset):
    """The CollectConfig of a preset (configs.py), for D_body and D_demo alike."""
    return CollectConfig(**PRESETS["collect"][preset])


def episode_jobs(body, cfg, data):
    """D_body episodes as (path, job) pairs; the seed of each episode is fixed by its name."""
    jobs = []
    for k in range(cfg.explore_episodes):
        jobs.append(dict(kind="explore", body=body, task="stand", index=k, snapshot=None))
    for t, task in enumerate(BODY_TASKS):
        snapshots = experts.history_steps(body, task)
        if not snapshots:
            raise FileNotFoundError(f"no learning history for the {body} {task} expert in experts/history: train it with `python -m experts --body {body}`")
        snapshots = [s for s in snapshots if s >= cfg.history_from * snapshots[-1]]
        rng = np.random.default_rng([cfg.seed, 1 + t])
        for k in range(cfg.task_episodes):
            jobs.append(dict(kind=task, body=body, task=task, index=k, snapshot=int(rng.choice(snapshots))))
    out = []
    for job in jobs:
        job.update(steps=cfg.episode_steps, noise=cfg.action_noise, seed=[cfg.seed, envs.BODIES.index(body), len(out)], views=("side",))
        out.append(([os.path.join(data, body, f"{job['kind']}_{job['index']:04d}.npz")], job))
    return out


def demo_jobs(cfg, data, demos=None):
    """D_demo: one simulation per (body, task, index), written to both views' folders; `demos` limits the (body, task)
    pairs (default: all)."""
    out = []
    for body, task in demos or [(b, t) for b in envs.BODIES for t in envs.TASKS]:
        if not os.path.exists(experts.expert_path(body, task)):
            raise FileNotFoundError(f"no final {body} {task} expert at {experts.expert_path(body, task)}: train it with `python -m experts --body {body}`")
        for k in range(cfg.demo_episodes):
            paths = [os.path.join(data, "demos", f"{body}_{task}_{view}", f"{k:02d}.npz") for view in envs.VIEWS]
            job = dict(kind="demo", body=body, task=task, index=k, snapshot=None, steps=cfg.episode_steps, noise=0.0,
                       seed=[cfg.seed, 7, envs.BODIES.index(body), envs.TASKS.index(task), k], views=envs.VIEWS)
            out.append((paths, job))
    return out


@contextlib.contextmanager
def default_matmul():
    """fp32 matmuls on PyTorch's default route inside the block, whatever the process set before: an episode must not
    depend on which process simulates it. train.py and imitate.py route them through oneDNN (rundir.fast_matmul),
    whose sums differ from MKL's in the last bit, and 500 steps of a falling body grow that into another episode."""
    matmul = torch.backends.mkldnn.matmul
    before, matmul.fp32_precision = matmul.fp32_precision, "none"
    try:
        yield
    finally:
        matmul.fp32_precision = before


def simulate(job):
    """Run one episode; returns the keys of every view's file (without features)."""
    torch.set_num_threads(1)
    rng = np.random.default_rng(job["seed"])
    env = _worker_env(job["body"], job["task"])
    obs, _ = env.reset(seed=int(rng.integers(2**31)))  # what a fresh make_env(..., seed) and reset() would start from
    actor = None
    if job["kind"] == "demo":
        actor = experts.load_expert(job["body"], job["task"])
    elif job["kind"] != "explore":
        actor = experts.load_expert(job["body"], job["task"], job["snapshot"])
    states, actions, rewards = [obs], [np.zeros(env.action_dim, np.float32)], [0.0]
    frames = {view: [env.render(view)] for view in job["views"]}
    held, hold = None, 0
    for _ in range(job["steps"]):
        if actor is None:  # exploration: a uniform random action held for 1-10 steps
            if hold == 0:
                held, hold = rng.uniform(-1, 1, env.action_dim), int(rng.integers(1, 11))
            action, hold = held, hold - 1
        else:
            with torch.no_grad(), default_matmul():
                mean = actor(torch.as_tensor(obs)[None, None], deterministic=True)[0][0, 0].double().numpy()
            action = np.clip(mean + job["noise"] * rng.standard_normal(env.action_dim), -1, 1)
        obs, reward, _, _, _ = env.step(action)
        states.append(obs)
        actions.append(np.asarray(action, np.float32))
        rewards.append(reward)
        for view in job["views"]:
            frames[view].append(env.render(view))
    source = "explore" if job["kind"] == "explore" else f"{job['task']}@{job['snapshot'] or 'final'}"
    common = dict(
        state=np.array(states, np.float32), action=np.array(actions), reward=np.array(rewards, np.float32),
        is_first=np.arange(len(states)) == 0, body=job["body"], task="explore" if job["kind"] == "explore" else job["task"],
        source=source, **{"return": float(np.sum(rewards))},
    )
    return [dict(common, pixels=np.array(frames[view]), view=view) for view in job["views"]]


def save_episode(path, episode):
    rundir.atomic_write(path, lambda f: np.savez_compressed(f, **episode))


def load_episode(path, keys=tuple(KEYS)):
    """Read and validate one episode: the requested keys (arrays) plus metadata and its `path`. One-line ValueError
    naming the file otherwise."""
    if not zipfile.is_zipfile(path):  # np.load would read a text file as a pickle, and a .npy as one array
        raise ValueError(f"{path}: not a readable .npz episode (no zip archive: a text file, a .npy array, a truncated copy?); delete it and rerun collect.py")
    try:
        with np.load(path) as archive:
            episode = {k: archive[k] for k in tuple(keys) + META if k in archive.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as error:
        raise ValueError(f"{path}: not a readable .npz episode ({error}); delete it and rerun collect.py") from None
    missing = [k for k in tuple(keys) + META if k not in episode]
    if missing:
        raise ValueError(f"{path}: missing key(s) {', '.join(missing)}; recollect it (delete the file and rerun collect.py)")
    length = len(episode["is_first"]) if "is_first" in episode else None
    for key in keys:
        value = episode[key]
        if value.dtype != KEYS[key]:
            raise ValueError(f"{path}: key {key!r} has dtype {value.dtype}, expected {np.dtype(KEYS[key])}")
        length = length or len(value)
        if len(value) != length or len(value) < 2:
            raise ValueError(f"{path}: key {key!r} has {len(value)} steps, expected {length} (>= 2) like the other keys")
        if key == "pixels" and value.shape[1:] != (64, 64, 3):
            raise ValueError(f"{path}: key 'pixels' has shape {value.shape}, expected (T, 64, 64, 3)")
        if key == "p" and value.ndim != 2:
            raise ValueError(f"{path}: key 'p' must be a finite (T, D) array, got shape {value.shape}")
        if value.dtype == np.float32 and not np.all(np.isfinite(value)):
            bad = np.argwhere(~np.isfinite(value))[0]
            raise ValueError(f"{path}: key {key!r} must be a finite array, has {value[tuple(bad)]} at step {bad[0]}; delete the file and rerun collect.py")
        if key == "action" and np.abs(value).max() > 1:  # the environments' action bounds (envs.make_env)
            bad = np.argwhere(np.abs(value) > 1)[0]
            raise ValueError(f"{path}: key 'action' must lie in [-1, 1], has {value[tuple(bad)]:g} at step {bad[0]}; delete the file and rerun collect.py")
    for key in META[:-1]:
        episode[key] = str(episode[key])
    number = np.asarray(episode["return"]).dtype.kind in "fiu" and np.size(episode["return"]) == 1
    episode["return"] = float(episode["return"]) if number else math.nan
    if not math.isfinite(episode["return"]):  # a demo's return names its demos in every result row (runner.finished)
        raise ValueError(f"{path}: its return {episode['return']} is not a finite number; delete the file and rerun collect.py")
    episode["path"] = path
    return episode


class Segments:
    """Random (B, T) segments of whole episodes (never crossing an episode's end), as torch tensors. A segment starts
    uniformly in [0, L - T] of its episode, so step t < T of an episode lies in one only (t + 1) / T as often as a
    middle step (Dreamer's sampling)."""

    def __init__(self, episodes, keys, seq_len):
        lengths = np.array([len(e["is_first"]) for e in episodes])
        if lengths.min() < seq_len:
            raise ValueError(f"episodes of {lengths.min()} steps are shorter than the segment length {seq_len}: collect longer episodes or pass --wm-seq-len")
        self.data = {k: np.concatenate([e[k] for e in episodes]) for k in keys}
        self.starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        self.lengths, self.seq_len = lengths, seq_len

    def sample(self, batch, rng, device):
        episode = rng.integers(len(self.lengths), size=batch)
        T, L = self.seq_len, self.lengths[episode]
        start = self.starts[episode] + (rng.random(batch) * (L - T + 1)).astype(int)
        index = start[:, None] + np.arange(T)  # (B, T)
        out = {k: torch.as_tensor(v[index], device=device) for k, v in self.data.items()}
        out["episode"] = torch.as_tensor(episode, device=device)
        if "p" in self.data:  # the feature of each segment's episode's last frame: hindsight goals (cloning.bc_loss)
            out["p_last"] = torch.as_tensor(self.data["p"][self.starts[episode] + self.lengths[episode] - 1], device=device)
        return out


def folder_metadata(folder):
    """What a folder's name says its episodes are: data/<body> (D_body) their body, data/demos/<body>_<task>_<view> their
    body, task and view; {} for a folder of another name."""
    name = os.path.basename(os.path.normpath(folder))
    if name in envs.BODIES:
        return {"body": name}
    demo, _, view = name.rpartition("_")
    try:
        return dict(zip(("body", "task"), envs.parse_demo(demo)), view=view) if view in envs.VIEWS else {}
    except ValueError:  # not a demo folder's name
        return {}


def load_folder(folder, keys=tuple(KEYS), encoder=None):
    """All episodes of a folder, sorted by name. One collection only: features from two encoders, episodes of two
    lengths or arrays of two widths are an error naming both files."""
    names = sorted(n for n in os.listdir(folder) if n.endswith(".npz") and not n.endswith(".tmp.npz")) if os.path.isdir(folder) else []
    if not names:
        raise FileNotFoundError(f"no episodes in {folder}: run `python collect.py` (see --help)")
    episodes = [load_episode(os.path.join(folder, n), keys) for n in names]
    first, expected = episodes[0], folder_metadata(folder)
    for episode in episodes:
        check_same_encoder(encoder or first["encoder"], episode["encoder"], episode["path"])
        odd = [f"{k} {episode[k]!r}" for k, v in expected.items() if episode[k] != v]
        if odd:
            raise ValueError(f"{episode['path']}: an episode of {', '.join(odd)} in {folder}, which holds "
                             f"{', '.join(f'{k} {v!r}' for k, v in expected.items())}: move or delete it")
        for key in keys:
            if episode[key].shape[1:] != first[key].shape[1:]:
                raise ValueError(f"{episode['path']}: key {key!r} has shape {episode[key].shape[1:]} per step, {first['path']} has "
                                 f"{first[key].shape[1:]}: one folder holds one body's episodes; delete the odd file and rerun collect.py")
        if keys and len(episode[keys[0]]) != len(first[keys[0]]):
            raise ValueError(f"{folder} mixes episodes of {len(first[keys[0]])} and {len(episode[keys[0]])} steps ({first['path']}, "
                             f"{episode['path']}): two collections (presets?); delete the folder and collect it again")
    return episodes


def _worker(item):
    """Simulate, compute features, write the views not on disk yet (a file written whole is never replaced); returns
    the paths written (a pool worker, one episode)."""
    paths, job, encoder_spec = item
    encoder = _worker_encoder(encoder_spec)
    written = [(path, episode) for path, episode in zip(paths, simulate(job)) if not zipfile.is_zipfile(path)]
    for path, episode in written:
        save_episode(path, dict(episode, p=encoder(episode["pixels"]), encoder=encoder.name))
    return [path for path, _ in written]


_ENCODERS, _ENVS = {}, {}


def _worker_env(body, task):
    """One env per (body, task) and process, kept across its episodes: building the model and its renderer took
    ~0.3 s of a 2.4 s episode (bench.py --only collect); each episode starts with reset(seed), as a fresh env would."""
    if (body, task) not in _ENVS:
        _ENVS[body, task] = envs.make_env(body, task)
    return _ENVS[body, task]


def _worker_encoder(spec):
    """One encoder per worker process, loaded on first use."""
    if spec not in _ENCODERS:
        _ENCODERS[spec] = load_encoder(spec)
    return _ENCODERS[spec]


def check_length(jobs):
    """Episodes on disk of another length than the jobs' (another preset's) are an error: the two would mix."""
    done = [p for paths, _ in jobs for p in paths if zipfile.is_zipfile(p)]
    steps = jobs[0][1]["steps"] if jobs else None
    if done and len(load_episode(done[0], ("is_first",))["is_first"]) != steps + 1:
        raise ValueError(f"{done[0]} is not a {steps}-step episode like the ones this collection makes (another preset's?): "
                         f"pass another --data, or delete {os.path.dirname(done[0])} to collect it again")


def run_jobs(jobs, encoder_spec, workers, desc):
    """Runs the jobs whose files are not all on disk yet (resume), in `workers` processes. A file that is not a zip
    archive (empty, cut short: not written by atomic_write) is not on disk: collected again, in its place."""
    check_length(jobs)
    todo = [(paths, job, encoder_spec) for paths, job in jobs if not all(zipfile.is_zipfile(p) for p in paths)]
    broken = [p for paths, _, _ in todo for p in paths if os.path.exists(p) and not zipfile.is_zipfile(p)]
    print(f"{desc}: {len(jobs) - len(todo)} of {len(jobs)} episodes already on disk"
          + (f"; {len(broken)} unreadable file(s) collected again ({', '.join(broken[:3])})" if broken else ""))
    if not todo:
        return
    # spawn: no EGL context or torch thread pool is inherited from the parent; the workers ignore Ctrl-C, which ends
    # the parent, whose pool then ends them (terminate)
    workers = min(workers, len(todo))
    pool = multiprocessing.get_context("spawn").Pool(workers, signal.signal, (signal.SIGINT, signal.SIG_IGN)) if workers > 1 else None
    with pool or contextlib.nullcontext():
        for _ in tqdm(pool.imap_unordered(_worker, todo) if pool else map(_worker, todo), total=len(todo), desc=desc):
            pass


def recompute_features(data, encoder_spec):
    """Second pass: rewrite `p` of every episode of the collection at `data` (data/<body>/, data/demos/*/; never another
    collection nested inside it, such as data/smoke) whose encoder differs from encoder_spec's."""
    encoder = load_encoder(encoder_spec)
    folders = [os.path.join(data, body) for body in envs.BODIES] + sorted(glob.glob(os.path.join(glob.escape(data), "demos", "*")))
    paths = [os.path.join(d, n) for d in folders if os.path.isdir(d) for n in sorted(os.listdir(d)) if n.endswith(".npz") and not n.endswith(".tmp.npz")]
    for path in tqdm(paths, desc=f"features ({encoder.name})"):
        with np.load(path) as f:
            episode = {k: f[k] for k in f.files}
        if str(episode.get("encoder")) != encoder.name:
            save_episode(path, dict(episode, p=encoder(episode["pixels"]), encoder=encoder.name))
    print(f"features of {len(paths)} episodes under {data} are from {encoder.name}")


def collect_body(body, cfg, data="data", workers=2, encoder="default"):
    """Writes D_body of one body (skips what exists), then its COMPLETE file; returns its folder."""
    envs._check_name("body", body, envs.BODIES)
    folder, jobs = os.path.join(data, body), episode_jobs(body, cfg, data)
    check_length(jobs)  # first: another preset's folder is left as it was
    if os.path.exists(os.path.join(folder, COMPLETE)):  # not complete until this collection is
        os.remove(os.path.join(folder, COMPLETE))
    run_jobs(jobs, encoder, workers, f"D_body {body}")
    episodes = sorted(os.path.basename(path) for paths, _ in jobs for path in paths)  # what a complete D_body holds
    rundir.atomic_write(os.path.join(folder, COMPLETE), lambda f: f.write(json.dumps({**asdict(cfg), "episodes": episodes}).encode()))
    scores = {task: [] for task in BODY_TASKS}  # what cloning can reach: the task episodes' quality
    for paths, job in jobs:
        if job["kind"] in scores:
            with np.load(paths[0]) as f:
                scores[job["kind"]].append(envs.normalized_score(job["kind"], float(f["return"])))
    print(f"D_body {body}: {len(jobs)} episodes; the task episodes' mean normalised score (Eq. 8) "
          + ", ".join(f"{task} {np.mean(v):.1f}" for task, v in scores.items() if v))
    return folder


def collect_demos(cfg, data="data", workers=2, encoder="default", demos=None):
    """Writes D_demo (skips what exists), of the (body, task) pairs `demos` (default: all); returns its folder."""
    run_jobs(demo_jobs(cfg, data, demos), encoder, workers, "D_demo" if demos is None else "D_demo " + " ".join(f"{b}_{t}" for b, t in demos))
    return os.path.join(data, "demos")


def main():
    parser = argparse.ArgumentParser(description="Write D_body (--env BODY) and/or D_demo (--demos); recompute features (--features).", allow_abbrev=False)
    parser.add_argument("--env", choices=envs.BODIES, help="collect D_body for this body")
    parser.add_argument("--demos", action="store_true", help="collect D_demo: every body x task x view")
    parser.add_argument("--features", action="store_true", help="recompute video features of everything under --data")
    parser.add_argument("--preset", choices=PRESETS["collect"], default="cpu")
    parser.add_argument("--data", default=None, help="default: data, or data/smoke for --preset smoke (configs.DATA)")
    parser.add_argument("--workers", type=int, default=os.cpu_count())
    parser.add_argument("--encoder", default="default", help="'default' or a TorchScript video model file (video_encoder.py)")
    parser.add_argument("--task-episodes", type=int, default=None, help="D_body episodes per task (default: the preset's)")
    parser.add_argument("--history-from", type=float, default=None, help="task episodes replay the snapshots from this fraction of "
                        "each expert's learning history on (default: the preset's)")
    args = parser.parse_args()
    cfg, args.data = preset_config(args.preset), args.data or DATA[args.preset]
    cfg = replace(cfg, **{k: v for k, v in (("task_episodes", args.task_episodes), ("history_from", args.history_from)) if v is not None})
    try:
        rundir.check_flags(cfg)  # CollectConfig's ranges, as every command's config
    except ValueError as error:
        parser.error(str(error))
    if not args.env and (args.task_episodes is not None or args.history_from is not None):
        parser.error("--task-episodes and --history-from shape D_body: add --env BODY, or drop them")
    if not (args.env or args.demos or args.features):
        parser.error("nothing to do: pass --env BODY, --demos or --features")
    if args.env:
        print("wrote", collect_body(args.env, cfg, args.data, args.workers, args.encoder))
    if args.demos:
        print("wrote", collect_demos(cfg, args.data, args.workers, args.encoder))
    if args.features:
        recompute_features(args.data, args.encoder)


if __name__ == "__main__":
    rundir.run_main(main, "the episodes written are kept whole: the same command collects the others")
