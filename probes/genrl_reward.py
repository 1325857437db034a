"""Does GenRL's reward (genrl.aligned_reward) rank real behaviour as the task score does, and does its actor reach in
the real body what it reaches in imagination? For one cell, each GenRL actor saved by baselines/genrl.py (the training state
at its last budget, runs/<name>/baselines/GenRL_<demo>_<view>_s<seed>_*.pt) and, for reference, the phase-1 policy
given demo 0's zero-shot goal (the GIIL-ZS (demo 0) column):
* task score: Eq. 8's normalised score of `episodes` real episodes (evaluate.run_episodes, env seeds 30000 + ...);
* real reward: GenRL's reward of those episodes' filtered posterior states, every H-step stretch s_{t+1..t+H} (t a
  multiple of H) scored against the target as one imagined trajectory is in training;
* imagined reward: from the same episodes' posterior states (every H-th), H steps imagined with the same actor and
  goal, scored the same way: what training maximised.
If the reference scores high on the task and low on the real reward while GenRL's actors score the reverse, the reward
does not identify the task; if GenRL's imagined reward is far above its real one, the actor exploits the model.

    python probes/genrl_reward.py runs/<name> walker_stand side [--episodes 2] [--preset cpu]
"""
import argparse
import glob
import os
import re
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import configs  # noqa: E402
import envs  # noqa: E402
import evaluate  # noqa: E402
from baselines import genrl  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
from configs import PRESETS  # noqa: E402


@torch.no_grad()
def measure(cell, target, actor, goal, episodes, window):
    """-> (task scores, mean real reward, mean imagined reward) of `actor` with goal (1, G) on `episodes` episodes."""
    wm, cfgs, H = cell["models"]["world_model"], cell["cfgs"], cell["cfgs"]["ac"].horizon
    env_list = [envs.make_env(cfgs["train"].env, cell["task"]) for _ in range(episodes)]
    posts = []
    returns, _ = evaluate.run_episodes(env_list, {"world_model": wm, "actor": actor}, goal.expand(episodes, -1), envs.EPISODE_STEPS,
                                       cfgs["wm"].obs, 30_000, on_state=lambda state: posts.append({k: v.clone() for k, v in state.items()}))
    for env in env_list:
        env.close()
    post = {k: torch.stack([p[k] for p in posts], 1) for k in posts[0]}  # (N, T + 1, .)
    feat = wm.feat(post)
    stretches = feat[:, 1:1 + (feat.shape[1] - 1) // H * H].reshape(-1, H, feat.shape[-1])  # s_{t+1..t+H}, t = 0, H, 2H, ...
    real, _ = genrl.aligned_reward(genrl.decoder_input(wm, stretches), target, window)
    starts = {k: v[:, :-1:H].flatten(0, 1) for k, v in post.items()}
    imagined_feat, _, _ = policy.rollout(wm, actor, starts, goal.expand(len(starts["deter"]), -1), H)
    imagined, _ = genrl.aligned_reward(genrl.decoder_input(wm, imagined_feat[:, 1:]), target, window)
    return [evaluate.episode_score(cell["task"], r, envs.EPISODE_STEPS) for r in returns], real.mean().item(), imagined.mean().item()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("run")
    parser.add_argument("demo")
    parser.add_argument("view", choices=envs.VIEWS)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--preset", default="cpu", choices=PRESETS["genrl"], help="baselines/genrl.py's preset the actors were trained with (its target, window)")
    args = parser.parse_args()
    torch.manual_seed(0)
    cell = genrl.load_cell(args.run, args.demo, args.view)
    models, cfgs, gc = cell["models"], cell["cfgs"], configs.GenRLConfig(**PRESETS["genrl"][args.preset])
    wm = models["world_model"]
    p = torch.as_tensor(cell["demos"][0]["p"])
    target = genrl.target_states(models, p, gc.target_len)
    paths = sorted(glob.glob(os.path.join(args.run, "baselines", f"GenRL_{args.demo}_{args.view}_s*_*.pt")))
    if not paths:
        raise ValueError(f"no GenRL training state of {args.demo} ({args.view} view) in {args.run}/baselines: run baselines/genrl.py on that cell first")
    print(f"{args.demo} ({args.view} view), {args.episodes} episodes each | task score | real reward | imagined reward")
    with torch.no_grad():
        zero_shot = models["goal_vae"].goal(p[-1])[None]
    scores, real, imagined = measure(cell, target, models["actor"], zero_shot, args.episodes, gc.align_window)
    print(f"phase-1 policy, demo 0's zero-shot goal | {np.mean(scores):6.1f} | {real:.3f} | {imagined:.3f}")
    for path in paths:
        state = rundir.load_checkpoint(path)
        actor = policy.Actor(cfgs["ac"], wm.feat_dim, 1, wm.action_dim)
        actor.load_state_dict(state["actor"])
        scores, real, imagined = measure(cell, target, actor, genrl.no_goal(1, "cpu"), args.episodes, gc.align_window)
        seed = re.search(r"_s(\d+)_[0-9a-f]+\.pt$", path).group(1)
        print(f"GenRL seed {seed} after {state['done']} updates | {np.mean(scores):6.1f} | {real:.3f} | {imagined:.3f}")


if __name__ == "__main__":
    rundir.run_main(main, "nothing is written")
