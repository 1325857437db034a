"""envs.py: bodies, shared rewards (against dm_control), cameras, seeding, bad input, Eq. 8."""
import numpy as np
import pytest
from dm_control import suite

import envs


@pytest.mark.parametrize("task", ["stand", "walk", "run"])
def test_walker_rewards_equal_dm_control(task):
    """Same seed, same random actions: our reward per agent step = dm_control's over the 2 repeated steps."""
    ours = envs.make_env("walker", task, seed=3)
    theirs = suite.load("walker", task, task_kwargs={"random": 3})
    ours.reset()
    theirs.reset()
    rng = np.random.default_rng(0)
    for _ in range(envs.EPISODE_STEPS):
        action = rng.uniform(-1, 1, 6)
        _, reward, _, truncated, _ = ours.step(action)
        expected = theirs.step(action).reward + theirs.step(action).reward
        assert reward == pytest.approx(expected, abs=1e-9)
    assert truncated and theirs.step(action).first()  # both episodes end after 1000 control steps


def test_stickman_structure():
    env = envs.make_env("stickman", "stand")
    model = env.physics.model
    names = lambda kind, n: {model.id2name(i, kind) for i in range(n)}
    assert {"head", "neck", "right_hand", "left_hand"} <= names("geom", model.ngeom)
    assert {"right_shoulder", "left_elbow"} <= names("joint", model.njnt)
    assert model.nu == 10 and env.action_dim == 10 and model.nv == 13
    assert np.allclose(model.jnt_axis[3:], [0, -1, 0])  # every limb hinge is about -y: planar
    assert model.jnt_type[0] == model.jnt_type[1] == 2  # root slides z, x (mjJNT_SLIDE)
    total_mass = model.body_mass.sum()
    assert 34 < total_mass < 36  # GenRL's stickman (Mazzaglia et al. 2024) at MuJoCo's default density: ~34.9 kg


@pytest.mark.parametrize("body", envs.BODIES)
def test_posture_from_an_observation_equals_the_stand_reward(body):
    """envs.posture of a stored state's torso height (obs[-1 - nv]) and zz (obs[0]) = the stand reward of the physics."""
    env = envs.make_env(body, "stand", seed=1)
    env.reset()
    rng = np.random.default_rng(0)
    postures = []
    for _ in range(30):
        obs, *_ = env.step(rng.uniform(-1, 1, env.action_dim))
        postures.append(envs.task_reward(env.physics, body, "stand"))
        assert envs.posture(body, obs[-1 - env.physics.model.nv], obs[0]) == pytest.approx(postures[-1], abs=1e-6)
    assert np.ptp(postures) > 0.05  # the body moved: the check compared different postures


def test_stickman_stands_and_falls():
    """Zero torque from upright: it collapses to the floor; it never sinks through it."""
    env = envs.make_env("stickman", "stand")
    env.reset()
    with env.physics.reset_context():
        env.physics.data.qpos[:] = 0
    heights = []
    for _ in range(100):
        obs, *_ = env.step(np.zeros(10))
        heights.append(obs[22])  # torso height follows the 11 bodies' orientations
    assert heights[0] > 1.0 and 0.05 < min(heights) < 0.5


def test_views_differ_and_frames_are_64px():
    env = envs.make_env("walker", "walk")
    env.reset()
    side, diagonal = env.render("side"), env.render("diagonal")
    assert side.shape == (64, 64, 3) and side.dtype == np.uint8
    assert np.abs(side.astype(int) - diagonal.astype(int)).mean() > 10


def test_same_seed_same_episode():
    def episode(seed):
        env = envs.make_env("stickman", "run", seed=seed)
        obs = [env.reset()[0]]
        rng = np.random.default_rng(1)
        for _ in range(50):
            obs.append(env.step(rng.uniform(-1, 1, 10))[0])
        return np.array(obs), env.render()

    (a, fa), (b, fb), (c, _) = episode(7), episode(7), episode(8)
    assert np.array_equal(a, b) and np.array_equal(fa, fb)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("kwargs, listed", [
    ({"body": "humanoid"}, "walker, stickman"),
    ({"task": "hop"}, "stand, walk, run, jump"),
    ({"view": "top"}, "side, diagonal"),
])
def test_unknown_names_list_valid_ones(kwargs, listed):
    args = {"body": "walker", "task": "stand", "view": "side", **kwargs}
    with pytest.raises(ValueError, match=listed):
        envs.make_env(**args)


def test_bad_actions():
    env = envs.make_env("walker", "stand")
    env.reset()
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        env.step(np.zeros(10))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([0, 0, np.nan, 0, 0, 0]))


def test_jump_rewards_height():
    """The jump reward grows with torso height above the standing height, saturates JUMP_RISE above it, and counts
    height only in the air: feet on the floor earn stand / 6."""
    env = envs.make_env("walker", "jump")
    rewards = []
    for z in (-0.05, 0.0, 0.1, 0.3, 0.5):  # rootz offset from the initial torso height 1.3 m, upright; at -0.05 the feet touch
        with env.physics.reset_context():
            env.physics.data.qpos[:] = 0
            env.physics.data.qpos[0] = z
        rewards.append(envs.task_reward(env.physics, "walker", "jump"))
    lift = np.clip((1.3 + np.array([-0.05, 0.0, 0.1, 0.3, 0.5]) - 1.2) / envs.JUMP_RISE, 0, 1) * [0, 1, 1, 1, 1]
    assert np.allclose(rewards, (5 * lift + 1) / 6)


def test_normalized_score_eq8():
    assert envs.normalized_score("walk", 45) == 0 and envs.normalized_score("walk", 960) == 100
    assert envs.normalized_score("run", 415) == pytest.approx(50)


def test_observed_reward_reads_the_task_reward_from_observations():
    """stand: exactly task_reward; walk, run, jump (approximations: rootx velocity, no airborne test): in [0, 1], and
    a body moving forward at running speed earns more of run than one standing still."""
    env = envs.make_env("walker", "run")
    obs, _ = env.reset(seed=3)
    assert np.isclose(envs.observed_reward("walker", "stand", obs), envs.task_reward(env.physics, "walker", "stand"))
    batch = np.stack([obs, obs])
    batch[1, -env.physics.model.nv + 1] = 10.0  # rootx velocity
    for task in ("walk", "run", "jump"):
        r = envs.observed_reward("walker", task, batch)
        assert r.shape == (2,) and np.all((0 <= r) & (r <= 1))
    run = envs.observed_reward("walker", "run", batch)
    assert run[1] > run[0]
