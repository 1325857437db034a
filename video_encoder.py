"""Sec. 4 "The Generalizable Goal Space": p_t = f(o_{t-k+1:t}), unit feature vectors of frame windows.

The paper's f is InternVideo2 (8-frame windows, stride 1, 512-d, L2-normalised; GenRL, Mazzaglia et al. 2024). Its
weights are gated on a model hub, so the default here is a training-free encoder built for our scene,
and a real pretrained video model plugs in from a local TorchScript file (`--encoder path.pt`).

Both share one interface: frames (T, 64, 64, 3) uint8 -> p (T, D) float32 unit rows, where row t
describes frames t-k+1..t (k = WINDOW). At the start of an episode the window is cut at frame 0: the
TorchScript plug-in repeats frame 0 to fill its fixed-length input, the default encoder averages its cues
over the frames that exist (row 0 sees one frame, so no motion). GenRL instead writes zero vectors for
the first k-1 rows (envs/main.py, process_episode); here every row is a unit vector, as cosine costs need.

Default encoder ("default-v1"). The tasks differ in how the body moves (DMC rewards: forward speed of
the centre of mass, torso height, uprightness), and both cameras track the centre of mass in x and z
(mode trackcom), so the body stays near the image centre while the world moves past it. Four cues per
frame, read from colour alone (blue checker floor, black sky, orange body; envs.py):
  speed    forward translation. The floor strip is invariant to motion along x, so only its checker
           texture moves; after undoing the vertical shift (below), the mean absolute grey change of
           floor pixels, in units of the checker contrast, is the fraction of the floor that changed
           colour: d / (1 m checker square) for a shift of d metres, whatever the perspective. The texture
           is its own ruler, so the cue reads metres per step for the side and the diagonal camera and
           for both bodies alike (measured: 0.1 m per frame reads 0.10-0.11), with no optical flow; it
           saturates at one square per step (20 m/s), far above a run (8 m/s). The vertical shift is
           undone for the far edge only, and near rows move more: a hop in place reads ~0.3 m/s.
  lift     vertical translation: the floor's top edge (its far side) moves only when the camera moves in
           z, by the same number of pixels in both views (~15-20 px per metre, measured); median over
           columns of its sub-pixel shift (columns where the body crosses the edge are skipped).
  limbs    limb motion: the fraction of the body silhouette that changes between frames (XOR / union).
  reach    posture: how far the silhouette reaches above the centre of mass, which the camera holds at a
           fixed row: 1 - (its top row) / 64; upright ~0.9, lying ~0.65 in both views (measured). Without
           it a body lying still would look like one standing still.
Speed, lift and limbs come from consecutive frames; each is averaged over the k - 1 frame pairs of the
window, reach over its k frames. The four window cues are squashed (logarithms of the motion cues over a
noise floor, reach linear) into units where 1 is a clear difference, then mapped by fixed random Fourier
features (Rahimi & Recht 2007) to DEFAULT_DIM unit vectors, cos(W x + b) with W ~ N(0, 1) drawn once from
a frozen NumPy stream. The cosine of two features then approximates the Gaussian kernel
exp(-|x - x'|^2 / 2), so the OT cost 1 - cos (App. C) is a smooth, bounded distance between behaviours.
It is a function of pixels only: no simulator state, no training, no download. What it cannot see: the
direction of travel (walking backwards reads as walking), and anything the four cues do not measure.
Change any constant of it and bump DEFAULT_NAME, so stored features are never mixed with new ones.

TorchScript plug-in contract (what the file must hold; `torch.jit.save(torch.jit.script(model), path)`):
  forward(x) with x float32 (N, k, 3, S, S): N windows of k RGB frames, oldest first, each frame
  resized from 64x64 to S x S (bilinear) and normalised with ImageNet mean/std -> (N, D) float features.
  S = 224 and k = WINDOW unless the module has int attributes `input_size` / `window` that say otherwise
  (torch.jit.script keeps such attributes, torch.jit.trace does not).
  Outputs are L2-normalised here, so the module need not do it.

Run `python video_encoder.py --eval` to measure how well the features tell the four tasks apart on
D_demo (nearest task centroid, the four settings) and how much the camera moves them; the frames/s of the default
encoder against rendering: `python bench.py --only features`.
"""
import argparse
import glob
import hashlib
import itertools
import os

import numpy as np
import torch
from tqdm import tqdm

from envs import BODIES, EPISODE_STEPS, SETTINGS, TASKS, VIEWS, cross_body

WINDOW = 8  # k: InternVideo2 in GenRL, 8-frame windows at stride 1 (Mazzaglia et al. 2024)
SIZE = 64  # renders are 64x64 (envs.py)
DEFAULT_NAME = "default-v1"  # recorded in every dataset; bump it when anything below changes the features
DEFAULT_DIM = 512  # as InternVideo2 in GenRL (Mazzaglia et al. 2024); random Fourier features estimate the kernel within ~1/sqrt(DIM)
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)  # torchvision's ImageNet statistics

# Colours of our renders (dm_control's materials, lit): both checker colours of the floor have B - R ~ 48
# grey levels and differ from each other by ~25 in grey (measured: 49 vs 74); the body (rgba .7 .5 .3)
# has R - B ~ 100; the sky is black (skybox off).
FLOOR_BLUE = 48.0  # B - R of a floor pixel: floorness = clip((B - R) / FLOOR_BLUE, 0, 1)
FLOOR_CONTRAST = 25.0  # grey-level difference of the two checker colours
BODY_RED = 30  # a body pixel has R - B above this (and R above 60)
MIN_EDGE_COLUMNS = 8  # fewer columns showing the floor's top edge: no vertical shift is measured
MIN_FLOOR_PIXELS = 50  # fewer floor pixels in both frames: no speed is measured
# Squashing of the window cues into units where 1 is a clear difference. Translation is what the rewards
# measure, so speed and lift get log2(1 + cue / floor): a factor of 2 is one unit; limbs, which also change
# with body and view, get log1p(cue / floor): a factor of e; reach is linear.
SPEED_FLOOR = 0.02  # metres per step (0.4 m/s); a walk (1 m/s) is 2.5 floors, a run (8 m/s) 20
LIFT_FLOOR = 0.1  # pixels per step (~0.1 m/s vertically); a hop or a bouncing gait moves ~1 px per step
LIMBS_FLOOR = 0.05  # fraction of the silhouette changing per step; a still body ~0.05, a gait ~0.4
REACH_UNIT = 0.1  # reach of an upright body ~0.9-0.95, of a lying one ~0.6-0.7 (measured, both views)
PROJECTION_SEED = 0  # RandomState stream: frozen by NumPy (NEP 19), the same on every machine


def check_frames(frames):
    """frames must be (T, 64, 64, 3) uint8 with T >= 1; ValueError naming what was expected otherwise."""
    if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8:
        got = frames.dtype if isinstance(frames, np.ndarray) else type(frames).__name__
        raise ValueError(f"video encoder expects frames as a uint8 numpy array (T, {SIZE}, {SIZE}, 3), got {got}")
    if frames.ndim != 4 or frames.shape[1:] != (SIZE, SIZE, 3):
        raise ValueError(f"video encoder expects frames of shape (T, {SIZE}, {SIZE}, 3), got {frames.shape}")
    if len(frames) == 0:
        raise ValueError(f"video encoder got an empty episode (0 frames); expected (T >= 1, {SIZE}, {SIZE}, 3)")


def frame_cues(frames):
    """Per-frame cues of the default encoder (module docstring) and where they could be measured.

    frames (T, 64, 64, 3) uint8 -> cues (T, 4) [speed, lift, limbs, reach] and weights (T, 4) in {0, 1}.
    The motion cues of frame t compare frames t-1 and t, so frame 0 has none (weight 0).
    """
    T = len(frames)
    rgb = frames.astype(np.int16)
    red, blue = rgb[..., 0], rgb[..., 2]
    floor = np.clip((blue - red) / FLOOR_BLUE, 0.0, 1.0).astype(np.float32)  # (T, H, W) floorness
    body = (red - blue > BODY_RED) & (red > 60)  # (T, H, W)
    grey = rgb.mean(-1, dtype=np.float32)  # (T, H, W)
    rows = np.arange(SIZE)[None, :, None]  # (1, H, 1)

    # lift: per column, the sub-pixel row where floorness first reaches 0.5 (the floor's top edge)
    solid = floor >= 0.5
    first = np.argmax(solid, axis=1)  # (T, W), 0 where the column shows no floor
    below = np.take_along_axis(floor, first[:, None], 1)[:, 0]
    above = np.take_along_axis(floor, np.maximum(first - 1, 0)[:, None], 1)[:, 0]
    edge = first - (below - 0.5) / np.maximum(below - above, 1e-3)  # linear crossing between rows first-1, first
    body_at_edge = (body & (np.abs(rows - first[:, None]) <= 3)).any(1)  # (T, W): a limb hides the edge
    edge = np.where(solid.any(1) & (first > 0) & ~body_at_edge, edge, np.nan)
    step = edge[1:] - edge[:-1]  # (T-1, W), nan where either frame has no clean edge in that column
    lift_ok = np.isfinite(step).sum(1) >= MIN_EDGE_COLUMNS  # (T-1,)
    shift = np.zeros(T - 1)  # pixels the floor moved down from frame t-1 to t
    if lift_ok.any():
        shift[lift_ok] = np.nanmedian(step[lift_ok], axis=1)

    # speed: frame t-1 moved down by shift (linear interpolation between rows), compared with frame t
    whole = np.floor(shift)
    frac = (shift - whole)[:, None, None]  # (T-1, 1, 1)
    whole = whole.astype(int)[:, None, None]
    src, src_up = np.clip(rows - whole, 0, SIZE - 1), np.clip(rows - whole - 1, 0, SIZE - 1)  # (T-1, H, 1)

    def moved(x):  # x[t-1] shifted down by shift[t]: (T-1, H, W)
        return (1 - frac) * np.take_along_axis(x[:-1], src, 1) + frac * np.take_along_axis(x[:-1], src_up, 1)

    inside = (rows - whole - 1 >= 0) & (rows - whole < SIZE)  # the source rows exist in frame t-1
    both_floor = (floor[1:] >= 0.9) & (moved(floor) >= 0.9) & inside  # (T-1, H, W), 0.9: no body or sky mixed in
    n_floor = both_floor.sum((1, 2))
    speed = (np.abs(grey[1:] - moved(grey)) * both_floor).sum((1, 2)) / np.maximum(n_floor, 1) / FLOOR_CONTRAST

    union = (body[1:] | body[:-1]).sum((1, 2))
    limbs = (body[1:] ^ body[:-1]).sum((1, 2)) / np.maximum(union, 1)

    occupied = body.any(2)  # (T, H): rows holding body pixels
    reach = 1 - np.argmax(occupied, 1) / SIZE

    cues, weights = np.zeros((T, 4)), np.zeros((T, 4))
    cues[1:, :3] = np.stack([speed, np.abs(shift), limbs], 1)
    weights[1:, :3] = np.stack([n_floor >= MIN_FLOOR_PIXELS, lift_ok, union > 0], 1)
    cues[:, 3], weights[:, 3] = reach, occupied.any(1)
    return cues, weights


def window_mean(values, weights, k):
    """Row t: the weighted mean of rows t-k+1..t (cut at 0), 0 where the weights sum to 0. (T, C) -> (T, C)."""
    pad = np.zeros((1, values.shape[1]))
    cum_w = np.cumsum(np.concatenate([pad, weights]), 0)  # (T+1, C)
    cum_v = np.cumsum(np.concatenate([pad, values * weights]), 0)
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - k, 0)
    total = cum_w[end] - cum_w[start]
    return np.where(total > 0, (cum_v[end] - cum_v[start]) / np.maximum(total, 1e-12), 0.0)


class DefaultEncoder:
    """The training-free encoder (module docstring): four motion and posture cues -> random Fourier features."""

    name = DEFAULT_NAME
    dim = DEFAULT_DIM
    window = WINDOW

    def __init__(self):
        stream = np.random.RandomState(PROJECTION_SEED)
        self.projection = stream.standard_normal((4, DEFAULT_DIM))  # W: lengthscale 1 in squashed-cue units
        self.phase = stream.uniform(0, 2 * np.pi, DEFAULT_DIM)  # b

    def cues(self, frames):
        """Squashed window cues x (T, 4): row t is the point in cue space that p_t embeds."""
        check_frames(frames)
        cues, weights = frame_cues(frames)
        # a window of k frames holds k-1 frame pairs: motion cues of frames t-k+2..t, reach of t-k+1..t
        motion = window_mean(cues[:, :3], weights[:, :3], self.window - 1)
        reach = window_mean(cues[:, 3:], weights[:, 3:], self.window)
        speed, lift, limbs = motion.T
        x = np.stack([np.log2(1 + speed / SPEED_FLOOR), np.log2(1 + lift / LIFT_FLOOR), np.log1p(limbs / LIMBS_FLOOR), reach[:, 0] / REACH_UNIT], 1)
        assert x.shape == (len(frames), 4)
        return x

    def __call__(self, frames):
        x = self.cues(frames)
        p = np.cos(x @ self.projection + self.phase)  # (T, D) random Fourier features
        p = p / np.linalg.norm(p, axis=1, keepdims=True)
        assert p.shape == (len(frames), self.dim)
        return p.astype(np.float32)


class TorchScriptEncoder:
    """A pretrained video model from a TorchScript file (contract in the module docstring)."""

    def __init__(self, path, batch=16, device=None):
        if not os.path.isfile(path):
            raise FileNotFoundError(f"no video model at {path}: --encoder takes 'default' or the path of a TorchScript file")
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        try:
            self.module = torch.jit.load(path, map_location=self.device).eval()
        except Exception as error:  # torch raises several types for a file that is not TorchScript
            raise ValueError(f"{path} does not load as TorchScript ({type(error).__name__}); expected a file written by torch.jit.save") from None
        self.path, self.batch = path, batch
        self.window = int(getattr(self.module, "window", WINDOW))
        self.size = int(getattr(self.module, "input_size", 224))  # InternVideo2: 224 px (Wang et al. 2024)
        if self.window < 1 or self.size < 1:
            raise ValueError(f"{path} says window {self.window}, input_size {self.size}: both must be >= 1 (frames per window, pixels)")
        if self.window > EPISODE_STEPS + 1:  # frames it would repeat, each taking (3, S, S) floats in every row's input
            raise ValueError(f"{path} says window {self.window}, more than the {EPISODE_STEPS + 1} frames of an episode (envs.EPISODE_STEPS "
                             f"steps): set the module's window to at most {EPISODE_STEPS + 1}")
        with open(path, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
        self.name = f"torchscript:{os.path.basename(path)}:{digest[:12]}"
        probe = self._forward(torch.zeros(1, self.window, 3, self.size, self.size, device=self.device))
        self.dim = probe.shape[1]
        self.mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 1, 3, 1, 1)
        self.std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 1, 3, 1, 1)

    def _forward(self, x):
        """Runs the module on (N, k, 3, S, S) and checks that it returns finite, nonzero (N, D)."""
        with torch.inference_mode():
            y = self.module(x)
        expected = f"(N, D) for input (N, {self.window}, 3, {self.size}, {self.size})"
        if not isinstance(y, torch.Tensor) or y.ndim != 2 or len(y) != len(x):
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ValueError(f"{self.path} returned {got} for N = {len(x)}; expected {expected}")
        if not torch.isfinite(y).all() or (y.norm(dim=1) == 0).any():
            raise ValueError(f"{self.path} returned NaN, inf or all-zero features; expected finite nonzero {expected}")
        return y.float()

    def __call__(self, frames):
        check_frames(frames)
        T, k = len(frames), self.window
        # row t: frames t-k+1..t oldest first; before frame 0, frame 0 is repeated (module docstring)
        index = np.maximum(np.arange(T)[:, None] - np.arange(k - 1, -1, -1)[None], 0)  # (T, k)
        video = torch.from_numpy(frames).to(self.device)
        out = []
        for rows in np.array_split(index, -(-T // self.batch)):
            x = video[torch.from_numpy(rows).to(self.device)].permute(0, 1, 4, 2, 3).float() / 255  # (n, k, 3, 64, 64)
            x = torch.nn.functional.interpolate(x.flatten(0, 1), size=(self.size, self.size), mode="bilinear", align_corners=False)
            x = (x.unflatten(0, (len(rows), k)) - self.mean) / self.std  # (n, k, 3, S, S)
            out.append(self._forward(x))
        p = torch.nn.functional.normalize(torch.cat(out), dim=1).cpu().numpy()
        assert p.shape == (T, self.dim)
        return p


def load_encoder(spec="default"):
    """The encoder behind an --encoder value: 'default' (training-free) or the path of a TorchScript file."""
    return DefaultEncoder() if spec == "default" else TorchScriptEncoder(spec)


def check_same_encoder(name_a, name_b, where):
    """Features of two encoders must never meet: ValueError naming both, and the command that recomputes them."""
    if str(name_a) != str(name_b):
        raise ValueError(
            f"{where}: video features from two encoders, {str(name_a)!r} and {str(name_b)!r}; recompute them with one: "
            "`python collect.py --features --encoder <default|model.pt>`"
        )


DESCRIPTORS = ("last", "mean")  # last: p_T, the input of the zero-shot goal (Sec. 4); mean: the normalised mean of p_t


def load_demo_features(data, encoder=None):
    """{(body, task, view): [p (T+1, D) of each demo]} from D_demo; p recomputed from pixels by `encoder` if given."""
    features, name = {}, None
    for body, task, view in tqdm(list(itertools.product(BODIES, TASKS, VIEWS)), desc="D_demo", disable=encoder is None):
        folder = os.path.join(data, "demos", f"{body}_{task}_{view}")
        paths = sorted(p for p in glob.glob(os.path.join(folder, "*.npz")) if not p.endswith(".tmp.npz"))
        if not paths:
            raise FileNotFoundError(f"no demos in {folder}: make D_demo with `python collect.py --demos`")
        features[body, task, view] = []
        for path in paths:
            with np.load(path) as episode:
                needed = ("pixels",) if encoder else ("p", "encoder")
                if not set(needed) <= set(episode.files):
                    raise ValueError(f"{path} lacks {' or '.join(needed)}: not a D_demo episode (`python collect.py --demos`)")
                p = encoder(episode["pixels"]) if encoder else episode["p"]
                stored = encoder.name if encoder else str(episode["encoder"])
            check_same_encoder(name or stored, stored, path)
            name = stored
            features[body, task, view].append(p)
    return features, name


def descriptor(p, kind):
    """One unit vector per demo: 'last' = p_T, 'mean' = the mean of its rows, renormalised."""
    d = p[-1] if kind == "last" else p.mean(0)
    return d / np.linalg.norm(d)


def confusion(features, agent, setting, kind):
    """(4, 4) counts, rows = the demo's task, columns = the task of the nearest centroid.

    Centroids: the normalised mean descriptor of each task over the agent's own side-view demos. In SE-SV a
    demo is one of those, so it is left out of its own task's centroid (leave-one-out).
    """
    demo_body = agent if setting.startswith("SE") else cross_body(agent)
    view = "side" if setting.endswith("SV") else "diagonal"
    own = {task: np.stack([descriptor(p, kind) for p in features[agent, task, "side"]]) for task in TASKS}
    if setting == "SE-SV" and min(len(d) for d in own.values()) < 2:
        raise ValueError(f"SE-SV leaves each demo out of its centroid: it needs 2 or more demos per folder of {agent}")
    counts = np.zeros((len(TASKS), len(TASKS)), int)
    for i, task in enumerate(TASKS):
        for n, p in enumerate(features[demo_body, task, view]):
            centroids = []
            for other in TASKS:
                members = np.delete(own[other], n, 0) if (setting == "SE-SV" and other == task) else own[other]
                centroid = members.mean(0)
                centroids.append(centroid / np.linalg.norm(centroid))
            counts[i, np.argmax(np.stack(centroids) @ descriptor(p, kind))] += 1
    return counts


def view_gap(features):
    """{body: (same episode, side vs diagonal camera; two episodes of one task, side camera)}, each the cosine of
    their features row by row as (mean over rows, last row), averaged over tasks and demos. D_demo films each
    episode from both cameras (collect.collect_demos), so the first pair differs in the camera only and the second,
    the scale to read it by, in the episode only."""
    def cosines(a, b):  # p's rows are unit vectors (module docstring)
        cos = (a * b).sum(-1)
        return cos.mean(), cos[-1]
    gap = {}
    for body in BODIES:
        views = [cosines(s, d) for task in TASKS for s, d in zip(features[body, task, "side"], features[body, task, "diagonal"])]
        episodes = [cosines(a, b) for task in TASKS for a, b in zip(features[body, task, "side"], features[body, task, "side"][1:])]
        gap[body] = tuple(tuple(np.mean(pairs, 0)) for pairs in (views, episodes))
    return gap


def evaluate(data="data", encoder=None):
    """Markdown report of nearest-centroid task accuracy on D_demo; returns {(agent, kind, setting): accuracy %}."""
    features, name = load_demo_features(data, encoder)
    fewest, most = min(len(v) for v in features.values()), max(len(v) for v in features.values())
    counts = {(a, k, s): confusion(features, a, s, k) for a in BODIES for k in DESCRIPTORS for s in SETTINGS}
    accuracy = {key: 100.0 * np.trace(c) / c.sum() for key, c in counts.items()}
    print(f"## Task accuracy (%) of the nearest task centroid, encoder {name}, {os.path.join(data, 'demos')}")
    print(f"{fewest if fewest == most else f'{fewest}-{most}'} demos per body/task/view; centroids from the agent's own side-view demos.\n")
    print("| agent | descriptor | " + " | ".join(SETTINGS) + " |\n|---|---|" + "---|" * len(SETTINGS))
    for agent in BODIES:
        for kind in DESCRIPTORS:
            print(f"| {agent} | {kind} | " + " | ".join(f"{accuracy[agent, kind, s]:.0f}" for s in SETTINGS) + " |")
    for agent in BODIES:
        for kind in DESCRIPTORS:
            print(f"\n### Confusion: agent {agent}, descriptor {kind} (rows: the demo's task, columns: predicted)\n")
            print("| setting | demo task | " + " | ".join(TASKS) + " |\n|---|---|" + "---|" * len(TASKS))
            for setting in SETTINGS:
                for task, row in zip(TASKS, counts[agent, kind, setting]):
                    print(f"| {setting} | {task} | " + " | ".join(str(c) for c in row) + " |")
    print("\n## How much the camera moves the features: cosine of p_t, mean over t / last t\n")
    print("| body | one episode, side vs diagonal | two episodes of one task, side |\n|---|---|---|")
    for body, pairs in view_gap(features).items():
        print(f"| {body} | " + " | ".join(f"{mean:.3f} / {last:.3f}" for mean, last in pairs) + " |")
    return accuracy


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--eval", action="store_true", help="task accuracy of the nearest task centroid on D_demo, the four settings")
    parser.add_argument("--data", default="data", help="dataset root holding demos/<body>_<task>_<view>/*.npz")
    parser.add_argument("--recompute", action="store_true", help="--eval on features recomputed from the stored pixels")
    parser.add_argument("--encoder", default="default", help="with --recompute: 'default' or a TorchScript video model file")
    args = parser.parse_args()
    if not args.eval:
        parser.error("pass --eval (the encoder's speed: python bench.py --only features)")
    if args.encoder != "default" and not args.recompute:
        parser.error("--encoder needs --recompute (without it, --eval reads the features stored in D_demo)")
    try:
        evaluate(args.data, load_encoder(args.encoder) if args.recompute else None)
    except (FileNotFoundError, ValueError) as error:
        raise SystemExit(f"error: {error}") from None


if __name__ == "__main__":
    main()
