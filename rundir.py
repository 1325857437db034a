"""What every run checks and keeps safe (train.py, imitate.py, the experts): its numeric flags, checked at start-up, and
its run directory (runs/<name>/): one writer at a time, and logs that a killed run leaves usable.

check_flags   a one-line error naming the flag of a number out of its range (--steps 0, --holdout-every 1, --goal-lr 1e3,
              --seeds 1e20: a count is at most MAX_COUNT)
lock          runs/<name>/lock (O_EXCL, the writer's pid): a second trainer stops in one line; a dead one's is taken over
run_checkpoint  a run's checkpoint, refused when it is not what the command expects (--env, agents/<body>, runs/<name>)
work_path     where a run's results go (runs/agent_<body> for a shipped agent)
run_main      an entry point's main(): bad input, Ctrl-C and SIGTERM each end in one line (the run's lock released)
trim_jsonl    on resume, metrics.jsonl keeps only the rows up to the checkpoint's update (a killed run logged past it)
read_jsonl    the rows of a .jsonl log; a last line cut short by a kill is dropped, any other bad line is an error
append_jsonl  one row, on a line of its own after such a cut line
fast_matmul   fp32 matmuls through oneDNN where that is faster and still fp32 (checked on this CPU)
threads_flag  --threads of imitate.py and the baselines: this process's torch threads, not the run's training ones
atomic_write  every file the project writes, videos too: a temporary file per writer (created anew, under a name no one
              can guess), renamed onto the path (never half a file)
load_checkpoint, plain, generator   checkpoints that load with torch.load(weights_only=True), and only so
weights_id    the identity of a checkpoint's agent, which every result row carries
checked_step  every optimiser step of the project: refused in one line, weights untouched, when a loss diverged
"""
import contextlib
import dataclasses
import fcntl
import glob
import hashlib
import json
import math
import os
import pickle
import re
import signal
import sys
import tempfile

import numpy as np
import torch

import envs

UMASK = os.umask(0o022)  # the process's umask, read once (os.umask sets it as it reads it) and put back
os.umask(UMASK)


MAX_COUNT = 10**6  # the most any int flag takes where its range has no top (ours: the presets' largest is 500 000 expert
# steps; --seeds 99999999999999999999 was accepted and ran for hours)


def check_flags(config, prefix=""):
    """One-line ValueError naming the flag (--<prefix><field>) of a numeric field of the dataclass `config` out of range:
    its class's `ranges` ((low, high) inclusive, None unbounded, or "> 0"), else a learning rate (a field ending in lr)
    in (0, 1), a count (an int) >= 1, any other float >= 0; an int unbounded there is at most MAX_COUNT."""
    ranges = getattr(type(config), "ranges", {})
    for field in dataclasses.fields(config):
        name, value = field.name, getattr(config, field.name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if name in ranges and ranges[name] == "> 0":
            ok, want = 0 < value < math.inf, "> 0"
        elif name.endswith("lr"):
            ok, want = 0 < value < 1, "a learning rate in (0, 1)"
        else:
            low, high = ranges.get(name, (1 if isinstance(value, int) else 0, None))
            top = MAX_COUNT if high is None and isinstance(value, int) else high
            ok = math.isfinite(value) and low <= value <= (math.inf if top is None else top)
            want = f"in [{low}, {high}]" if high is not None else f">= {low}" if value < low or top is None else f"<= {top}"
        if not ok:
            raise ValueError(f"--{prefix}{name.replace('_', '-')} {value}: must be {want}")


@contextlib.contextmanager
def claim(path):
    """Yields None while this process holds the lock file `path` (created with O_EXCL, holding its pid; removed at the
    end), or the pid of the live process that holds it (then nothing is taken). A lock file whose process is gone (a
    killed run) is stale and taken over; one holding this process's own pid is an outer block's, and left to it."""
    os.makedirs(os.path.dirname(no_link(path)) or ".", exist_ok=True)
    fd = holder = None
    for attempt in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            try:
                with open(path) as f:
                    holder = f.read().strip()
            except FileNotFoundError:  # released meanwhile: try again
                continue
            if holder == str(os.getpid()) or (holder.isdigit() and alive(int(holder))):
                break
            holder = None
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)  # stale: its process was killed
    if fd is None:
        if holder is None:
            raise ValueError(f"could not take the lock file {path} (other processes are starting on it); try again")
        yield None if holder == str(os.getpid()) else int(holder)
        return
    with os.fdopen(fd, "w") as f:
        f.write(str(os.getpid()))
    try:
        yield None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)


@contextlib.contextmanager
def lock(run_dir):
    """Hold run_dir/lock while the block runs; ValueError naming the other process if a live one holds it."""
    path = os.path.join(run_dir, "lock")
    with claim(path) as holder:
        if holder:
            raise ValueError(f"{run_dir} is in use by process {holder} (its lock file {path}): wait for that run to end, "
                             f"or train into another --run-dir; delete {path} only if no such process runs")
        yield


def read_jsonl(path):
    """The rows of a .jsonl file, [] if there is none (a last line cut by a kill is dropped)."""
    if not os.path.exists(path):
        return []
    with open(path) as f:
        lines = f.read().split("\n")
    rows = []
    for number, line in enumerate(lines, 1):
        try:
            if line.strip():
                rows.append(json.loads(line))
        except json.JSONDecodeError as error:
            if number < len(lines):  # not the last line: not a kill's doing
                raise ValueError(f"{path}: line {number} is not a JSON row ({error}); delete that line") from None
    return rows


def trim_jsonl(path, step):
    """Keep the rows of `path` logged at update <= step; rewritten atomically."""
    rows = [r for r in read_jsonl(path) if r["step"] <= step]
    atomic_write(path, lambda f: f.write("".join(json.dumps(r) + "\n" for r in rows).encode()))


def no_link(path):
    """path, refused where it or the folder it is written into is a symbolic link (a run folder's baselines/, a demo
    folder): a run or data folder from elsewhere never makes this project write outside it."""
    for link in (path, os.path.dirname(path)):
        if link and os.path.islink(link):
            raise ValueError(f"{link} is a symbolic link (to {os.readlink(link)}): nothing is written through a link; remove it")
    return path


def append_jsonl(path, row):
    """Append one row. A last line without its newline (a kill) is completed if it is a whole row, as read_jsonl
    counts it, and dropped otherwise, so that the new row starts on a line of its own."""
    with open(no_link(path), "a+b") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # one appender at a time (table shards in parallel processes), released on close
        f.seek(0)
        text = f.read()
        last = text[text.rfind(b"\n") + 1 :]
        if last:
            try:
                json.loads(last)
                f.write(b"\n")
            except json.JSONDecodeError:
                f.truncate(len(text) - len(last))
        f.write((json.dumps(row) + "\n").encode())


def not_training(run_dir):
    """A one-line ValueError while another live process trains run_dir (holds its lock): its checkpoint is a
    mid-training one, not the agent."""
    path = os.path.join(run_dir, "lock")
    try:
        pid = int(open(path).read().strip() or 0)
    except (FileNotFoundError, ValueError):
        return
    if pid != os.getpid() and alive(pid):
        raise ValueError(f"{run_dir} is being trained now by process {pid} ({path}): its checkpoint is not the final agent; "
                         f"wait for the training to end, then run this again")


def fast_matmul():
    """Routes fp32 matmuls through oneDNN instead of MKL's sgemm (faster on AMD EPYC cores: docs/results.md, Speed) where
    that still computes in fp32; returns whether it did. PyTorch's switch, mkldnn's fp32_precision 'bf16', really rounds
    to bf16 on a CPU with bf16 matmul (AMX): a probe matmul and its backward are checked against float64 first."""
    matmul = torch.backends.mkldnn.matmul
    if not torch.backends.mkldnn.is_available():
        return False
    matmul.fp32_precision = "bf16"
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(256, 460, generator=g, requires_grad=True), torch.randn(256, 460, generator=g)
    out = torch.nn.functional.linear(a, b)  # (256, 256), the shape of an actor layer on 256 imagination starts
    out.backward(torch.ones_like(out))
    with torch.no_grad():
        exact = a.double() @ b.double().t()
        error = max(((out.double() - exact).abs().max() / exact.abs().max()).item(),
                    ((a.grad.double() - b.double().sum(0)).abs().max() / b.double().sum(0).abs().max()).item())
    if error > 1e-5:  # fp32 gives ~1e-6 here, bf16 ~1e-3
        matmul.fp32_precision = "none"
    return error <= 1e-5


def threads_flag(parser):
    """--threads: torch CPU threads of a phase-2 or baseline process, default 1, not the run's: 2 threads in each of two
    table shards on two cores slowed GIIL-FT many times over (docs/results.md, Speed)."""
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1; one per table shard)")


def use_threads(threads):
    """torch.set_num_threads(--threads), checked like every count."""
    if not 1 <= threads <= MAX_COUNT:
        raise ValueError(f"--threads {threads}: must be {'>= 1' if threads < 1 else f'<= {MAX_COUNT}'}")
    torch.set_num_threads(threads)


AGENTS = "agents"  # the shipped phase-1 agents: agents/<body>/checkpoint.pt, weights only (checkpoint.export_agent)


def work_path(run_dir):
    """Where results of run_dir go: the folder itself, but runs/agent_<body> beside agents/ for a shipped agent."""
    parent, name = os.path.split(os.path.normpath(run_dir))
    return os.path.join(os.path.dirname(parent), "runs", f"agent_{name}") if os.path.basename(parent) == AGENTS else run_dir


RUN_NAME = re.compile(r"(?P<env>[a-z]+)_(?P<obs>state|pixels)_(?P<preset>[a-z]+)_s(?P<seed>\d+)")  # checkpoint.default_run_dir's


def run_checkpoint(run_dir, device="cpu", env=None):
    """The checkpoint of a trained run, checked against what the command expects of it before anything runs: the body
    `env` where the command names one (--env), and what the folder's name says: agents/<body> holds that body's agent,
    runs/<env>_<obs>_<preset>_s<seed> that run (checkpoint.default_run_dir). A folder of another name may hold any agent;
    phase 2 then tags its rows with the checkpoint's body. A run still in training is refused (not_training): every
    command and probe that reads a run reads it here (checkpoint.load_run). Errors name the file and the fix."""
    not_training(run_dir)
    path, folder = os.path.join(run_dir, "checkpoint.pt"), os.path.normpath(run_dir)
    name, shipped = os.path.basename(folder), os.path.basename(os.path.dirname(folder)) == AGENTS
    named = RUN_NAME.fullmatch(name)
    want = named.groupdict() if named else {}
    if not os.path.exists(path):
        if shipped:
            raise FileNotFoundError(f"no checkpoint at {path}: restore the shipped agent with `git checkout {path}`")
        # the flags that train into this folder: those its name encodes (--obs always: its default is the preset's)
        body = env or want.get("env", "walker")
        flags = [f"--env {body}"] + [f"--{k} {want[k]}" for k, usual in (("obs", None), ("preset", "cpu"), ("seed", "0")) if want.get(k, usual) != usual]
        if not named or folder != os.path.join("runs", "{}_{obs}_{preset}_s{seed}".format(body, **want)):
            flags.append(f"--run-dir {run_dir}")
        raise FileNotFoundError(f"no checkpoint at {path}: train one with `python train.py {' '.join(flags)}`")
    ckpt = load_checkpoint(path, device)
    config = ckpt.get("config") if isinstance(ckpt, dict) else None
    if not (isinstance(config, dict) and all(isinstance(config.get(k), dict) for k in ("train", "wm")) and isinstance(ckpt.get("models"), dict)):
        raise ValueError(f"{path} is damaged or not this project's checkpoint: it holds no run config and models; delete it or restore it from a copy")
    tc = ckpt["config"]["train"]
    has = {"env": tc["env"], "obs": ckpt["config"]["wm"]["obs"], "preset": tc["preset"], "seed": str(tc["seed"])}
    if env and env != has["env"]:
        raise ValueError(f"--env {env}, but {path} holds a {has['env']} agent: pass --env {has['env']}, or a --run of a {env} agent")
    if shipped and name in envs.BODIES and name != has["env"]:
        raise ValueError(f"{path} holds a {has['env']} agent, but {folder} is the shipped {name} agent's folder: put the {name} "
                         f"agent back (`git checkout {path}`) and keep the {has['env']} one in a folder of its own, passed by --run")
    if any(want[k] != has[k] for k in want):
        true = "{env}_{obs}_{preset}_s{seed}".format(**has)
        raise ValueError(f"{path} holds the run {true} (body, observations, preset, seed), not the {name} that its folder is named: "
                         f"move the folder to {os.path.join(os.path.dirname(folder), true)}")
    return ckpt


def check_gpu(preset, allow_cpu):
    """train.py --preset paper without a GPU: a one-line error naming the time it would take and --allow-cpu."""
    if preset == "paper" and not allow_cpu and not torch.cuda.is_available():
        raise ValueError("--preset paper is sized for a GPU and this machine has none: its 100 000 updates of the paper's pixel models "
                         "take ~6 h on one (docs/results.md) and far longer on CPU cores, after a 5000-episode D_body (~3 h to "
                         "collect on 2 cores); pass --preset cpu, or --allow-cpu to run it here anyway")


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run_main(main, kept):
    """An entry point's main(): bad input ends in one line 'error: ...' (exit 1); Ctrl-C, or the SIGTERM of `timeout`
    or a scheduler, in one line 'interrupted: <kept>', what is kept and how to go on (exit 130), once the `finally`
    blocks of the run ran (its lock file released): Python's default SIGTERM ends the process without them."""
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        main()
    except (ValueError, FileNotFoundError) as error:  # bad input: one line naming the problem, no traceback
        raise SystemExit(f"error: {error}")
    except OSError as error:  # a full disk, a read-only folder, a path too long or naming a file: the path, and what is kept
        raise SystemExit(f"error: {error.strerror or error}: {error.filename or ''} ({kept})")
    except KeyboardInterrupt:
        sys.stdout.flush()
        print(f"\ninterrupted: {kept}", file=sys.stderr, flush=True)
        os._exit(130)  # not SystemExit: the interpreter's exit runs the finalizers of open renderers and pools, which print
        # errors ('Exception ignored', EGL) after this line


def alive(pid):
    """Whether process `pid` still runs."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True


def atomic_write(path, write, by_name=False):
    """Every file this project writes goes through here: write(f) fills a temporary file, which is then renamed onto
    `path`, so a killed run leaves the old file or the new one, never half of one. The temporary file is named after
    the writer's pid, so two processes writing the same file (two runs side by side collecting one D_demo) each rename
    a whole file of their own; a killed writer's leftover temporary file goes at the next write of `path`. by_name:
    write(name) gets the temporary file's name instead, ending in path's extension (cv2.VideoWriter picks the format by it).
    The temporary file is created anew (O_EXCL) under a name no one can guess beside the pid, so a link planted at a
    predictable name is never written through."""
    folder = os.path.dirname(no_link(path)) or "."
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f"{os.path.basename(path)}.{os.getpid()}.", suffix=".tmp" + (os.path.splitext(path)[1] if by_name else ""), dir=folder)
    try:
        os.fchmod(fd, 0o666 & ~UMASK)  # what open() would have made: mkstemp's file is the owner's alone
        if by_name:
            os.close(fd)
            write(tmp)
        else:
            with os.fdopen(fd, "wb") as f:
                write(f)
    except BaseException as error:  # an error or Ctrl-C half-way: the old file stays, and no temporary one
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        if isinstance(error, OSError) and not error.filename:  # a full disk met inside write(f): name the file it was for
            raise OSError(error.errno, error.strerror or str(error), path) from None
        raise
    os.replace(tmp, path)
    for left in glob.glob(glob.escape(path) + ".*.tmp*"):
        pid = left[len(path) + 1:].split(".")[0]
        if pid.isdigit() and not alive(int(pid)):
            with contextlib.suppress(FileNotFoundError):
                os.remove(left)


DIVERGED = 1e10  # |loss| above this is divergence (ours: the smoke preset's losses are below 100; a learning rate of 1e3 on
# the goal VAE, distance or critic gave losses of 1e20 and more within 4 updates)


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


def weights_id(ckpt):
    """The identity of a checkpoint's agent, '<update>:<hash of every weight>': every result row carries it, so that a
    retrained or replaced agent is evaluated again, never credited with another agent's rows."""
    digest = hashlib.sha256()
    for name in sorted(ckpt["models"]):
        for key, tensor in sorted(ckpt["models"][name].items()):
            digest.update(f"{name}.{key}".encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return f"{ckpt['step']}:{digest.hexdigest()[:16]}"


def load_checkpoint(path, device="cpu"):
    """A checkpoint read with torch.load(weights_only=True): tensors and plain values only, no code runs (a pickle, the
    older format, is never unpickled). One-line ValueError for a corrupt or pickled file."""
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError:
        raise ValueError(f"{path} holds pickled Python objects (the format before checkpoints became weights-only), which are not "
                         f"loaded: train it again") from None
    except (RuntimeError, EOFError, OSError) as error:
        raise ValueError(f"{path}: not a readable checkpoint ({str(error).splitlines()[0]}); delete it or restore it from a copy") from None


def plain(obj):
    """obj with numpy generators as their state dicts, arrays as tensors and numpy scalars as Python numbers: what
    torch.load(weights_only=True) reads back."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(plain(v) for v in obj)
    if isinstance(obj, np.random.Generator):
        return obj.bit_generator.state
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj.copy())
    return obj.item() if isinstance(obj, np.generic) else obj


def generator(state):
    """The numpy Generator of a checkpoint's plain `bit_generator.state` dict (plain)."""
    rng = np.random.Generator(getattr(np.random, state["bit_generator"])())
    rng.bit_generator.state = state
    return rng
