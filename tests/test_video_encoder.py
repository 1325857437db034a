"""video_encoder.py: unit rows, window alignment, determinism, the cues on rendered motion, the TorchScript plug-in, bad input."""
import numpy as np
import pytest
import torch

import envs
import video_encoder as ve

torch.set_num_threads(1)
# torch 2.13 marks torch.jit deprecated (in favour of torch.export); TorchScript files still save and load
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")


def render(body, view, steps, dx=0.0, dz=None, swing=0.0):
    """Frames of a body moved kinematically (qpos written, no dynamics): rootx += dx per frame, rootz = dz[t],
    hips swinging +-swing rad in antiphase. A stand-in for expert motion at 0.05 s per agent step."""
    env = envs.make_env(body, "stand", view)
    qpos = env.physics.named.data.qpos
    frames = []
    for t in range(steps):
        qpos["rootx"] = dx * t
        qpos["rootz"] = 0.0 if dz is None else dz[t]
        qpos["right_hip"], qpos["left_hip"] = swing * np.sin(0.6 * t), -swing * np.sin(0.6 * t)
        qpos["right_knee"] = qpos["left_knee"] = -swing * (1 + np.cos(0.6 * t)) / 2
        env.physics.forward()
        frames.append(env.render(view))
    env.close()
    return np.stack(frames)


def hop(steps, height=0.4, period=14):
    """rootz of a body hopping in place: parabolas of `height` m every `period` frames."""
    u = (np.arange(steps) % period) / period
    return height * 4 * u * (1 - u)


def scene(steps, stripe_step=0, floor_step=0, bar_step=0):
    """Synthetic frames with hand-computable cues: black sky; from row 40 + floor_step*t down, a checker of
    8 px squares in two blues 25 grey levels apart (B - R = 50: floorness 1), moved stripe_step px right
    per frame; an orange bar, columns 32-39 + bar_step*t, rows 10-50."""
    frames = np.zeros((steps, 64, 64, 3), np.uint8)
    rows, cols = np.mgrid[:64, :64]
    for t in range(steps):
        top = 40 + floor_step * t
        square = ((rows - top) // 8 + (cols - stripe_step * t) // 8) % 2
        floor = np.where(square[..., None] == 1, [45, 65, 95], [20, 40, 70])  # grey 68.3 vs 43.3
        frames[t] = np.where((rows >= top)[..., None], floor, 0)
        left = 32 + bar_step * t
        frames[t, 10:51, left : left + 8] = [180, 130, 80]
    return frames


def test_cues_by_hand():
    """Each cue against its value worked out on paper for the synthetic scene."""
    cues = lambda frames: ve.frame_cues(frames)[0][1:].mean(0)  # [speed, lift, limbs, reach]
    # a 2 px shift of 8 px squares recolours 2 of every 8 floor columns, each by one contrast unit
    assert cues(scene(4, stripe_step=2)) == pytest.approx([0.25, 0.0, 0.0, 1 - 10 / 64])
    # the floor moves down 1 px per frame: the edge says so, and undoing it leaves no texture change
    assert cues(scene(4, floor_step=1)) == pytest.approx([0.0, 1.0, 0.0, 1 - 10 / 64])
    # the bar moves 1 px: 2 of its 9 columns' worth of pixels differ (XOR 2 x 41, union 9 x 41)
    assert cues(scene(4, bar_step=1))[2] == pytest.approx(2 / 9)
    weights = ve.frame_cues(scene(3))[1]
    assert weights[0].tolist() == [0, 0, 0, 1] and weights[1:].all()  # frame 0 has no motion cues


@pytest.fixture(scope="module")
def walking():
    return render("walker", "side", 20, dx=0.06, swing=0.4)


def test_unit_rows_and_determinism(walking):
    p = ve.load_encoder()(walking)
    assert p.shape == (20, ve.DEFAULT_DIM) and p.dtype == np.float32
    assert np.allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-5)
    assert np.array_equal(p, ve.load_encoder("default")(walking))  # a fresh encoder: the same projection
    assert ve.DefaultEncoder().projection[0, 0] == 1.764052345967664  # RandomState(0)'s first normal: the frozen stream
    single = ve.load_encoder()(walking[:1])
    assert single.shape == (1, ve.DEFAULT_DIM)


def test_window_alignment(walking):
    """Row t depends on frames t-k+1..t only: later frames and frames before the window change nothing."""
    encoder, k, t = ve.load_encoder(), ve.WINDOW, 12
    p = encoder(walking)
    later = walking.copy()
    later[t + 1 :] = walking[::-1][: len(walking) - t - 1]
    assert np.array_equal(encoder(later)[: t + 1], p[: t + 1])
    assert not np.allclose(encoder(later)[t + 1 :], p[t + 1 :])
    earlier = walking.copy()
    earlier[: t - k + 1] = walking[0]
    assert np.array_equal(encoder(earlier)[t], p[t])
    assert np.array_equal(encoder(walking[t - k + 1 : t + 1])[-1], p[t])  # the window alone gives the same row


@pytest.mark.parametrize("body,view", [("walker", "side"), ("stickman", "diagonal")])
def test_cues_measure_motion(body, view):
    """The texture is its own ruler: 0.1 m per frame reads as ~0.1 checker squares (1 m) in both views;
    a hop moves the floor's edge, not its texture; a still body moves nothing."""
    cues = lambda frames: ve.frame_cues(frames)[0][1:].mean(0)  # [speed, lift, limbs, reach]
    still, walk, jump = render(body, view, 10), render(body, view, 10, dx=0.1), render(body, view, 14, dz=hop(14))
    assert np.allclose(cues(still)[:3], 0.0)
    assert 0.08 < cues(walk)[0] < 0.12 and cues(walk)[1] < 0.05
    assert cues(jump)[1] > 0.5 and cues(jump)[0] < 0.03
    assert cues(still)[3] > 0.85  # upright: the silhouette reaches near the top of the image


def test_tasks_separate_across_bodies_and_views():
    """Kinematic stand-ins of the four tasks: centroids from walker/side classify stickman/diagonal (CE-CV)."""
    steps = 24
    tasks = {
        "stand": dict(),
        "walk": dict(dx=0.06, swing=0.4),
        "run": dict(dx=0.3, swing=0.9),
        "jump": dict(dz=hop(steps), swing=0.1),
    }
    encoder = ve.load_encoder()
    describe = lambda frames: ve.descriptor(encoder(frames), "mean")
    centroids = np.stack([describe(render("walker", "side", steps, **kw)) for kw in tasks.values()])
    for i, kw in enumerate(tasks.values()):
        assert np.argmax(centroids @ describe(render("stickman", "diagonal", steps, **kw))) == i


class Tiny(torch.nn.Module):
    """A stand-in video model: the mean of each frame of the window, oldest first, and a constant."""

    def __init__(self):
        super().__init__()
        self.window = 3
        self.input_size = 16

    def forward(self, x):  # (N, k, 3, S, S) -> (N, k + 1)
        return torch.cat([x.mean(dim=(2, 3, 4)), torch.full((x.shape[0], 1), 2.0)], 1)


class WrongShape(torch.nn.Module):
    def forward(self, x):
        return x.mean(dim=(3, 4))  # (N, k, 3): not (N, D)


def test_a_window_of_no_frames_is_refused(tmp_path):
    tiny = Tiny()
    tiny.window = 0
    path = str(tmp_path / "empty_window.pt")
    torch.jit.save(torch.jit.script(tiny), path)
    with pytest.raises(ValueError, match=r"empty_window.pt says window 0, input_size 16: both must be >= 1"):
        ve.load_encoder(path)


def test_torchscript_plugin(tmp_path):
    """Resize, ImageNet normalisation and windows (frame 0 repeated at the start) are done by us, batched."""
    path = str(tmp_path / "tiny.pt")
    torch.jit.save(torch.jit.script(Tiny()), path)
    encoder = ve.load_encoder(path)
    assert encoder.name.startswith("torchscript:tiny.pt:") and len(encoder.name.split(":")[2]) == 12
    assert encoder.dim == 4 and encoder.window == 3 and encoder.size == 16
    levels = np.array([0, 40, 80, 120, 160, 200, 240], np.uint8)  # frame t is uniformly grey `levels[t]`
    frames = np.broadcast_to(levels[:, None, None, None], (7, 64, 64, 3)).copy()
    encoder.batch = 2  # several batches
    p = encoder(frames)
    normalised = lambda v: np.mean((v / 255 - np.array(ve.IMAGENET_MEAN)) / np.array(ve.IMAGENET_STD))
    for t in range(7):
        window = [levels[max(s, 0)] for s in range(t - 2, t + 1)]
        expected = np.array([normalised(v) for v in window] + [2.0])
        assert np.allclose(p[t], expected / np.linalg.norm(expected), atol=1e-5)
    assert p.dtype == np.float32 and p.shape == (7, 4)


def test_torchscript_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no video model at"):
        ve.load_encoder(str(tmp_path / "missing.pt"))
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="does not load as TorchScript"):
        ve.load_encoder(str(junk))
    wrong = str(tmp_path / "wrong.pt")
    torch.jit.save(torch.jit.script(WrongShape()), wrong)
    with pytest.raises(ValueError, match=r"returned \(1, 8, 3\) for N = 1; expected \(N, D\)"):
        ve.load_encoder(wrong)


@pytest.mark.parametrize(
    "frames,message",
    [
        (np.zeros((4, 64, 64, 3), np.float32), "uint8 numpy array"),
        (np.zeros((4, 32, 32, 3), np.uint8), r"shape \(T, 64, 64, 3\), got \(4, 32, 32, 3\)"),
        (np.zeros((0, 64, 64, 3), np.uint8), "empty episode"),
        ([[0]], "uint8 numpy array"),
    ],
)
def test_bad_frames(frames, message):
    with pytest.raises(ValueError, match=message):
        ve.load_encoder()(frames)


def write_demos(root, encoder_of=lambda body, task, view: "default-v1", demos=3, steps=5):
    """A synthetic D_demo: p of task i points near axis i (no rendering), so the right answer is known."""
    rng = np.random.default_rng(0)
    for body in ve.BODIES:
        for i, task in enumerate(ve.TASKS):
            for view in ve.VIEWS:
                folder = root / "demos" / f"{body}_{task}_{view}"
                folder.mkdir(parents=True)
                for n in range(demos):
                    p = np.eye(8)[i] + 0.1 * rng.standard_normal((steps, 8))
                    p /= np.linalg.norm(p, axis=1, keepdims=True)
                    pixels = np.zeros((steps, 64, 64, 3), np.uint8)
                    np.savez(folder / f"{n:02d}.npz", pixels=pixels, p=p.astype(np.float32), encoder=np.array(encoder_of(body, task, view)))


def test_eval_report(tmp_path, capsys):
    write_demos(tmp_path)
    accuracy = ve.evaluate(str(tmp_path))
    assert set(accuracy) == {(a, k, s) for a in ve.BODIES for k in ve.DESCRIPTORS for s in ve.SETTINGS}
    assert all(a == 100.0 for a in accuracy.values())
    out = capsys.readouterr().out
    assert "| walker | last | 100 | 100 | 100 | 100 |" in out and "| CE-CV | jump | 0 | 0 | 0 | 3 |" in out


def test_mixing_encoders_is_an_error(tmp_path):
    ve.check_same_encoder("default-v1", np.array("default-v1"), "here")
    with pytest.raises(ValueError, match=r"here: video features from two encoders, 'default-v1' and 'torchscript:m.pt:0123456789ab'.*collect.py --features"):
        ve.check_same_encoder("default-v1", "torchscript:m.pt:0123456789ab", "here")
    write_demos(tmp_path, encoder_of=lambda body, task, view: "torchscript:m.pt:0123456789ab" if view == "diagonal" else "default-v1")
    with pytest.raises(ValueError, match="two encoders"):
        ve.evaluate(str(tmp_path))


def test_eval_missing_data_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr("sys.argv", ["video_encoder.py", "--eval", "--data", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"^error: no demos in .*walker_stand_side: make D_demo with `python collect.py --demos`$"):
        ve.main()


def test_view_gap_by_hand():
    """A camera that changes nothing reads 1 / 1; features that turn at the last row read it there; the second
    pair compares consecutive side demos of each task."""
    side = [np.array([[1.0, 0.0], [1.0, 0.0]]), np.array([[0.0, 1.0], [0.0, 1.0]])]
    turned = [np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([[0.0, 1.0], [-1.0, 0.0]])]
    features = {(b, t, v): [p.copy() for p in (side if v == "side" or b == "walker" else turned)]
                for b in ve.BODIES for t in ve.TASKS for v in ve.VIEWS}
    gap = ve.view_gap(features)
    assert gap["walker"] == ((1.0, 1.0), (0.0, 0.0))
    assert gap["stickman"] == ((0.5, 0.0), (0.0, 0.0))
