"""Sec. 5 and App. D: Walker and Stickman, the four tasks, two viewpoints, score normalisation (Eq. 8).

Both bodies are planar MuJoCo models driven like dm_control's walker: control step 0.025 s
(10 physics steps of 0.0025 s), action repeat 2, so an episode is 1000 control steps = 500 agent
steps and the agent's reward is the sum over the repeat (as in Dreamer and GenRL).

* Walker is dm_control's walker XML unchanged, plus our diagonal camera (a camera does not change
  the dynamics, so stand/walk/run rewards equal `dm_control.suite.walker` step for step).
* Stickman follows the public GenRL model (Mazzaglia et al. 2024): walker with a shorter torso, arms
  (shoulder, elbow) and a head; 10 motors. Written here from those facts.

One reward definition per task, shared by both bodies (the paper's R^S = R^A). The only per-body
constant is the standing height of the torso (walker 1.2 as in dm_control, stickman 1.15 as in
GenRL), because the torsos differ in length:
  stand = (3 * standing + upright) / 4,  standing = tolerance(torso_z, [H, inf), margin H/2),
                                          upright  = (1 + torso_zz) / 2
  walk, run = stand * (5 * move + 1) / 6, move = tolerance(com_vx, [v, inf), margin v/2, 0.5, linear)
  jump (ours, no public definition exists) = stand * (5 * lift + 1) / 6, lift = clip((torso_z - H) /
        JUMP_RISE, 0, 1) while no part of the body touches the floor, else 0; JUMP_RISE = 0.4 m.
Height alone is not enough: our first jump (lift from torso height alone) was maximised by standing still
on tiptoe with straight legs (torso 0.33 m above H, airborne 4% of the time: experts.jump_stats). With
lift counted only in the air, standing earns stand / 6 whatever the posture, and the rest of the
reward needs the body to leave the ground upright, high, again and again. (Our SAC experts learnt a
wind-up of their own: they drop low, then spring up into the air with the torso upright.)

Rendering bypasses dm_control's renderer: one `mujoco.Renderer` per env with shadows, reflections
and the skybox turned off (they are most of the cost of a 64x64 frame on a software GL).
"""
import argparse
import atexit
import os
import weakref

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering on CPU (Mesa); OSMesa is not installed

try:  # MuJoCo loads its GL backend on import: another MUJOCO_GL may be missing here (OSMesa: an AttributeError)
    import mujoco
    from dm_control import mujoco as dm_mujoco
except (AttributeError, ImportError, RuntimeError) as error:
    raise SystemExit(f"error: MuJoCo does not load with MUJOCO_GL={os.environ['MUJOCO_GL']} ({type(error).__name__}: {error}); "
                     "unset it or set MUJOCO_GL=egl (headless Mesa, what this project renders with)") from None
import numpy as np
from dm_control.suite import common
from dm_control.suite.utils import randomizers
from dm_control.utils import rewards

BODIES = ("walker", "stickman")
TASKS = ("stand", "walk", "run", "jump")
BODY_TASKS = ("stand", "walk", "run")  # the tasks of D_body (collect.py) and of the benchmark's average (evaluate.py); jump is held out
VIEWS = ("side", "diagonal")
SETTINGS = ("SE-SV", "SE-CV", "CE-SV", "CE-CV")  # Sec. 5: the demo's body and camera, same as/cross to the agent's

CONTROL_TIMESTEP = 0.025  # dm_control walker: 10 physics steps of 0.0025 s
ACTION_REPEAT = 2  # Dreamer / GenRL on DMC
EPISODE_STEPS = 500  # agent steps: 1000 control steps = 25 s
STAND_HEIGHT = {"walker": 1.2, "stickman": 1.15}  # dm_control walker / GenRL stickman
MOVE_SPEED = {"stand": 0.0, "walk": 1.0, "run": 8.0, "jump": 0.0}  # m/s, dm_control walker
JUMP_RISE = 0.4  # m above the standing height for the full jump reward (our definition)

# App. D, Table 3: (min, max) return used by Eq. 8. Jump has no public definition; ours differs from the
# paper's, so its bounds are measured on our task, like Table 3's, over both bodies: min = the random policy's
# mean return (`python -m experts --bounds`: walker 24.3, stickman 22.7), max = our final jump experts' mean
# return (`python -m experts --eval --tasks jump`: walker 425.4, stickman 460.4).
SCORE_BOUNDS = {"stand": (150.0, 970.0), "walk": (45.0, 960.0), "run": (30.0, 800.0), "jump": (23.5, 442.9)}

# Side camera: dm_control's walker camera. Diagonal camera (new, paper Fig. 2): behind the body at 45
# degrees in the horizontal plane, same distance (2 m) and the same 30 degree downward tilt, tracking
# the COM. Stickman's cameras sit 0.2 m higher (relative to its torso) so that its head is in frame.
_CAMERAS = """
      <camera name="side" pos="0 -2 {z}" euler="60 0 0" mode="trackcom"/>
      <camera name="diagonal" pos="-1.414 -1.414 {z}" xyaxes="0.707 -0.707 0 0.354 0.354 0.866" mode="trackcom"/>"""

_STICKMAN_LEG = """
      <body name="{s}_thigh" pos="0 {y} -0.25">
        <joint name="{s}_hip" range="-20 100"/>
        <geom name="{s}_thigh" pos="0 0 -0.225" size="0.05 0.225"/>
        <body name="{s}_leg" pos="0 0 -0.7">
          <joint name="{s}_knee" pos="0 0 0.25" range="-150 0"/>
          <geom name="{s}_leg" size="0.04 0.25"/>
          <body name="{s}_foot" pos="0.06 0 -0.25">
            <joint name="{s}_ankle" pos="-0.06 0 0" range="-45 45"/>
            <geom name="{s}_foot" zaxis="1 0 0" size="0.04 0.1"/>
          </body>
        </body>
      </body>"""

_STICKMAN_ARM = """
      <body name="{s}_upper_arm" pos="0 {y} 0.2">
        <joint name="{s}_shoulder" range="-20 100"/>
        <geom name="{s}_upper_arm" pos="0 0 -0.135" size="0.04 0.135"/>
        <body name="{s}_forearm" pos="0 0 -0.27">
          <joint name="{s}_elbow" range="0 150"/>
          <geom name="{s}_forearm" pos="0 0 -0.15" size="0.035 0.15"/>
          <geom name="{s}_hand" type="sphere" pos="0 0 -0.35" size="0.05"/>
        </body>
      </body>"""


def parse_demo(demo):
    """A demo's name, <demonstrator body>_<task> (stickman_run), -> (body, task); an unknown one lists the valid names."""
    body, _, task = str(demo).rpartition("_")
    if body not in BODIES or task not in TASKS:
        raise ValueError(f"unknown demo {demo!r}: valid demos are {', '.join(b + '_' + t for b in BODIES for t in TASKS)}")
    return body, task


def setting(agent_body, demo_body, view):
    """The setting of a demo for an agent: SE or CE (same or cross embodiment), SV or CV (same or cross view)."""
    return ("SE" if demo_body == agent_body else "CE") + "-" + ("SV" if view == "side" else "CV")


def cross_body(agent):
    """The demonstrator of an agent's cross-embodiment (CE) cells: the next body in BODIES (the paper's two: each other)."""
    return BODIES[(BODIES.index(agent) + 1) % len(BODIES)]


def demo_of(agent, task, where):
    """(demo name, view) of a setting: SE/CE picks the demonstrator's body, SV/CV its camera."""
    return f"{agent if where.startswith('SE') else cross_body(agent)}_{task}", "side" if where.endswith("SV") else "diagonal"


def cells(agent):
    """Every (task, setting) of an agent's table, in a fixed order (what --shard splits)."""
    return [(task, where) for task in TASKS for where in SETTINGS]


def _stickman_xml(walker_xml):
    """The walker XML with its torso subtree replaced by the stickman's (GenRL's stickman, Mazzaglia et al. 2024)."""
    head, rest = walker_xml.split('<body name="torso"', 1)
    tail = rest.split("</worldbody>", 1)[1]
    limbs = "".join(_STICKMAN_LEG.format(s=s, y=y) for s, y in (("right", -0.05), ("left", 0.05)))
    limbs += "".join(_STICKMAN_ARM.format(s=s, y=y) for s, y in (("right", -0.1), ("left", 0.1)))
    torso = f"""<body name="torso" pos="0 0 1.25" childclass="walker">
      <light name="light" pos="0 0 2" mode="trackcom"/>{_CAMERAS.format(z=0.9)}
      <joint name="rootz" axis="0 0 1" type="slide" limited="false" armature="0" damping="0"/>
      <joint name="rootx" axis="1 0 0" type="slide" limited="false" armature="0" damping="0"/>
      <joint name="rooty" axis="0 1 0" type="hinge" limited="false" armature="0" damping="0"/>
      <geom name="torso" size="0.06 0.25"/>
      <geom name="neck" pos="0 0 0.3" size="0.045 0.045"/>
      <geom name="head" type="sphere" pos="0 0 0.445" size="0.1"/>{limbs}
    </body>
  </worldbody>"""
    motors = "".join(
        f'\n    <motor name="{s}_{j}" joint="{s}_{j}" gear="{g}"/>'
        for s in ("right", "left")
        for j, g in (("hip", 100), ("knee", 50), ("ankle", 20), ("shoulder", 100), ("elbow", 50))
    )
    tail = tail.split("<actuator>", 1)[0] + f"<actuator>{motors}\n  </actuator>\n</mujoco>\n"
    return head + torso + tail


def model_xml(body):
    """MJCF string of a body, with both cameras."""
    walker = common.read_model("walker.xml").decode()
    cams = '<camera name="side" pos="0 -2 .7" euler="60 0 0" mode="trackcom"/>\n      <camera name="back" pos="-2 0 .5" xyaxes="0 -1 0 1 0 3" mode="trackcom"/>'
    assert cams in walker, "dm_control's walker.xml changed: update envs.py"
    walker = walker.replace(cams, _CAMERAS.format(z=0.7).strip())
    return walker if body == "walker" else _stickman_xml(walker)


# Renderers still open at exit are closed before MuJoCo terminates the EGL display (else each prints an
# EGLError at exit): mujoco registers that at its first context, so ours is registered after it (atexit is LIFO).
_RENDERERS = weakref.WeakSet()


def _new_renderer(model, size):
    renderer = mujoco.Renderer(model, size, size)
    if not _RENDERERS:
        atexit.register(lambda: [r.close() for r in list(_RENDERERS)])
    _RENDERERS.add(renderer)
    return renderer


def _check_name(kind, value, valid):
    if value not in valid:
        raise ValueError(f"unknown {kind} {value!r}: valid {kind} names are {', '.join(valid)}")


def airborne(physics):
    """True when no geom of the body touches the floor (MuJoCo's contact list of the last step)."""
    contacts = physics.data.contact[: physics.data.ncon]
    floor = physics.model.geom("floor").id
    return not np.any((contacts.geom1 == floor) | (contacts.geom2 == floor))


def posture(body, torso_z, torso_zz):
    """The stand reward (3 standing + upright) / 4 of a torso height and its zz orientation (arrays too): 1 upright at
    stand height. In an observation (Env._observation) torso_zz is obs[0] (torso xx = zz for a planar body) and torso_z
    obs[-1 - nv]."""
    stand_height = STAND_HEIGHT[body]
    standing = rewards.tolerance(torso_z, bounds=(stand_height, float("inf")), margin=stand_height / 2)
    return (3 * standing + (1 + torso_zz) / 2) / 4



def observed_posture(body, obs):
    """posture of state observations (..., obs_dim): torso zz at obs[0], the torso height at obs[-1 - nv]."""
    height = -1 - make_env(body, "stand").physics.model.nv
    return posture(body, obs[..., height], obs[..., 0])

def observed_reward(body, task, obs):
    """task_reward read from state observations alone (..., obs_dim), for decoded imagined states (fidelity.py): the
    torso's x velocity (qvel of rootx, at obs[-nv + 1]) stands for the centre of mass's, and jump's lift counts without
    its airborne test (no contacts in an observation). An approximation of the reward, not the environment's."""
    nv = make_env(body, "stand").physics.model.nv
    height, stand = obs[..., -1 - nv], observed_posture(body, obs)
    if task == "stand":
        return stand
    if task == "jump":
        return stand * (5 * np.clip((height - STAND_HEIGHT[body]) / JUMP_RISE, 0.0, 1.0) + 1) / 6
    speed = MOVE_SPEED[task]
    move = rewards.tolerance(obs[..., -nv + 1], bounds=(speed, float("inf")), margin=speed / 2, value_at_margin=0.5, sigmoid="linear")
    return stand * (5 * move + 1) / 6


def task_reward(physics, body, task):
    """The shared reward of one control step (module docstring); equals dm_control's walker for stand/walk/run."""
    height = physics.named.data.xpos["torso", "z"]
    stand_height = STAND_HEIGHT[body]
    stand = posture(body, height, physics.named.data.xmat["torso", "zz"])
    if task == "stand":
        return stand
    if task == "jump":
        lift = np.clip((height - stand_height) / JUMP_RISE, 0.0, 1.0) * airborne(physics)
        return stand * (5 * lift + 1) / 6
    speed = MOVE_SPEED[task]
    com_vx = physics.named.data.sensordata["torso_subtreelinvel"][0]
    move = rewards.tolerance(com_vx, bounds=(speed, float("inf")), margin=speed / 2, value_at_margin=0.5, sigmoid="linear")
    return stand * (5 * move + 1) / 6


def normalized_score(task, episode_return):
    """Eq. 8, in percent: 100 (R - R_min) / (R_max - R_min) with SCORE_BOUNDS (Table 3)."""
    _check_name("task", task, TASKS)
    low, high = SCORE_BOUNDS[task]
    return 100.0 * (np.asarray(episode_return, dtype=np.float64) - low) / (high - low)


class Env:
    """One body doing one task, seen from one camera. Gymnasium-style reset()/step()."""

    def __init__(self, body, task, view="side", seed=0, size=64):
        _check_name("body", body, BODIES)
        _check_name("task", task, TASKS)
        _check_name("view", view, VIEWS)
        self.body, self.task, self.view, self.size = body, task, view, size
        self.physics = dm_mujoco.Physics.from_xml_string(model_xml(body), common.ASSETS)
        self.action_dim = self.physics.model.nu  # walker 6, stickman 10
        self.obs_dim = len(self._observation())  # walker 24, stickman 36
        self._random = np.random.RandomState(seed)
        self._renderer = None
        self._steps = 0

    def _observation(self):
        """dm_control walker's observation for either body: body orientations (xx, xz), torso height, qvel."""
        data = self.physics.named.data
        orientations = data.xmat[1:, ["xx", "xz"]].ravel()
        return np.concatenate([orientations, [data.xpos["torso", "z"]], self.physics.data.qvel]).astype(np.float32)

    def reset(self, seed=None):
        """Random joint angles (root pitch uniform in [-pi, pi]), then the body falls: dm_control walker's start."""
        if seed is not None:
            self._random = np.random.RandomState(seed)
        with self.physics.reset_context():
            randomizers.randomize_limited_and_rotational_joints(self.physics, self._random)
        self._steps = 0
        return self._observation(), {}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.action_dim,):
            raise ValueError(f"{self.body} takes actions of shape ({self.action_dim},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action contains NaN or inf: {action}")
        self.physics.set_control(np.clip(action, -1.0, 1.0))
        reward = 0.0
        for _ in range(ACTION_REPEAT):
            self.physics.step(round(CONTROL_TIMESTEP / self.physics.model.opt.timestep))
            reward += task_reward(self.physics, self.body, self.task)
        self._steps += 1
        truncated = self._steps >= EPISODE_STEPS
        return self._observation(), float(reward), False, truncated, {}

    def render(self, view=None, size=None):
        """An RGB uint8 frame (size, size, 3) from this env's camera (or `view`), default 64x64."""
        view = view or self.view
        _check_name("view", view, VIEWS)
        size = size or self.size
        if self._renderer is None or self._renderer.height != size:
            self._renderer = _new_renderer(self.physics.model.ptr, size)
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX):
                self._renderer.scene.flags[flag] = 0
        self._renderer.update_scene(self.physics.data.ptr, camera=view)
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def make_env(body, task, view="side", seed=0):
    """An Env; ValueError listing the valid names for an unknown body, task or view."""
    return Env(body, task, view, seed)


def show(path="docs/bodies.png", size=192):
    """One PNG: rows walker, stickman; columns side, diagonal view; bodies standing, limbs slightly bent."""
    import cv2

    rows = []
    for body in BODIES:
        env = make_env(body, "stand")
        qpos = env.physics.named.data.qpos
        for joint, angle in (("hip", 20), ("knee", -30), ("shoulder", 30), ("elbow", 40)):
            for side, sign in (("right", 1), ("left", -0.5)):
                if f"{side}_{joint}" in qpos.axes.row.names:
                    qpos[f"{side}_{joint}"] = np.deg2rad(angle * sign)
        env.physics.forward()
        rows.append(np.concatenate([env.render(view, size) for view in VIEWS], axis=1))
        env.close()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    cv2.imwrite(path, cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--show", action="store_true", help="write docs/bodies.png: both bodies x both views")
    args = parser.parse_args()
    if args.show:
        print("wrote", show())
    else:
        parser.print_help()
