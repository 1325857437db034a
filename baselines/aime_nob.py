"""Sec. 5, baseline AIME-NoB (Zhang et al. 2025) with its AIME loss off: online imitation from video features, with
the pretrained world model learning on, an OT reward and Dreamer's actor-critic. The only method here that acts in
the environment during imitation.

AIME-NoB's recipe in the paper's cross-domain setup (the AIME loss, kinematic imitation of the demo through the
world model, is off: it needs the demonstrator's body), written with this project's models:
  start     the phase-1 run's world model and its Adam state (AIME-NoB starts from a pretrained world model);
            a fresh actor pi(a | s), critic V(s) and reward head r(s) (policy.py's networks, the run's sizes).
  interact  a round starts with one episode of episode_steps agent steps in the agent's own env (envs.make_env,
            side camera), actions sampled from pi(a | s_t), s_t filtered by the world model's posterior. Its frames
            are rendered and encoded by the run's video encoder (video_encoder.load_encoder, as collect.py does for
            D_body and D_demo). The env's task reward is never shown to the agent (only logged).
  reward    the OT reward (ot_reward.py; App. C: cosine distance of video features, Sinkhorn) of the whole episode
            against each whole demo, the best-matching demo counting (ROT, Haldar et al. 2022; AIME-NoB), one label
            r_t per frame o_t; scaled once, after the first episode, so that its labels sum to -reward_sum (ROT's
            automatic reward scale), and that scale kept for every later episode. AIME-NoB compares its world
            model's encoder embeddings of agent and demo frames; ours reads states (the cpu default), which a demo
            video does not give, so the features are the video encoder's (those GIIL's goals come from). On the
            walker's stand cell this reward ranks the agent's own episodes backwards (docs/baselines.md).
  model     then `updates` updates, each: Eq. 2 (world_model.py) on a batch of which body_ratio are D_body segments
            and the rest segments of this seed's episodes (AIME-NoB mixes its embodiment dataset in, ratio 0.5),
            plus the reward head regressed to the OT labels on the new episodes' posterior states (its gradient
            reaches the world model, as a Dreamer reward head); and Dreamer's actor-critic in imagination
            (policy.rollout, lambda_return, actor_loss, critic_loss) from the batch's posterior states with the
            reward head's r(s_{k+1}).
Interaction budget: env_steps agent steps per seed (env_steps / episode_steps episodes; each agent step is 2 control
steps, action repeat), written in every result row. Evaluation, rows, resuming and --eval-at (score against budget,
here in env steps) as genrl.py (its plumbing).

    python baselines/aime_nob.py --demo stickman_run --view side --run runs/<name> [--seeds 3] [--preset smoke|cpu]
"""
import copy
import os
import sys

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the project's modules, run as a script too
import checkpoint  # noqa: E402
import collect  # noqa: E402
import envs  # noqa: E402
import ot_reward  # noqa: E402
import policy  # noqa: E402
import rundir  # noqa: E402
from baselines import genrl  # noqa: E402
from configs import PRESETS, AIMENoBConfig, OTConfig, budgets  # noqa: E402
from video_encoder import check_same_encoder, load_encoder  # noqa: E402
from world_model import mlp  # noqa: E402

METHOD = "AIME-NoB"


def episode_rewards(p, demo_p, ot_cfg):
    """The OT reward labels of one episode: p (T, D) its video features, demo_p (K, M, D) -> (T,) float32 array, the
    index of the best-matching demo (whole episode against whole demos, ot_reward.ot_reward)."""
    reward, best = ot_reward.ot_reward(torch.as_tensor(p, device=demo_p.device)[None], demo_p, ot_cfg)
    return reward[0].cpu().numpy().astype(np.float32), int(best[0])


@torch.no_grad()
def collect_episode(env, world_model, actor, steps, obs_key, seed):
    """One episode with actions sampled from pi(a | s_t), s_t the world model's posterior -> the episode in collect.py's
    layout (state, pixels, action = a_{t-1}, is_first) and its task return (for the log only)."""
    device = next(world_model.parameters()).device
    goal = genrl.no_goal(1, device)
    obs, _ = env.reset(seed=seed)
    action, state, task_return = np.zeros(env.action_dim, np.float32), None, 0.0
    states, frames, actions = [obs], [env.render()], [action]
    for t in range(steps):
        o = torch.as_tensor(frames[-1] if obs_key == "pixels" else obs, device=device)[None, None]
        post, _ = world_model.observe(o, torch.as_tensor(action, device=device)[None, None], torch.full((1, 1), t == 0, device=device), state)
        state = {k: v[:, -1] for k, v in post.items()}
        action = actor(world_model.feat(state), goal)[0][0].cpu().numpy()
        obs, reward, _, _, _ = env.step(action)
        task_return += reward
        states.append(obs)
        frames.append(env.render())
        actions.append(action)
    episode = {"state": np.array(states, np.float32), "pixels": np.array(frames), "action": np.array(actions, np.float32),
               "is_first": np.arange(steps + 1) == 0}
    return episode, task_return


def mixed_batch(body, online, cfgs, ratio, rng, device):
    """A world-model batch: round(ratio * B) D_body segments, then the new episodes' segments (with their 'reward')."""
    wc = cfgs["wm"]
    n_body = round(ratio * wc.batch)
    parts = ([body.sample(n_body, rng, device)] if n_body else []) + [online.sample(wc.batch - n_body, rng, device)]
    batch = {k: torch.cat([part[k] for part in parts]) for k in (wc.obs, "action", "is_first")}
    return batch, n_body, parts[-1]["reward"]


def train_seed(cell, nc, body, encoder, demo_p, seed, on_budget=None, resume=None):
    """AIME-NoB for one seed (module docstring) -> the actor, the world model trained on, and a log of the episodes.
    on_budget(env_steps, actor, world_model, state) after each budget of budgets(nc), state() the seed's training
    state (its episodes too); resume: such a state, to go on from its env steps."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    cfgs, device, models = cell["cfgs"], cell["device"], cell["models"]
    ac, wc = cfgs["ac"], cfgs["wm"]
    wm = models["world_model"]
    wm.load_state_dict(cell["ckpt"]["models"]["world_model"])  # every seed starts from the phase-1 world model
    actor = policy.Actor(ac, wm.feat_dim, 1, wm.action_dim).to(device)  # the baseline's own actor, the run's sizes
    critic, slow_critic = (m.to(device) for m in policy.make_critics(ac, wm.feat_dim, 0))
    reward_head = mlp(wm.feat_dim, ac.units, 1, ac.critic_layers).to(device)  # r(s_t) of the OT label of o_t
    return_norm = policy.ReturnNorm(ac.return_norm_decay).to(device)
    opt_wm = torch.optim.Adam(wm.parameters(), lr=wc.lr)
    if "optims" in cell["ckpt"]:  # a deep copy: Adam steps its state in place, and every seed starts from the checkpoint's
        opt_wm.load_state_dict(copy.deepcopy(cell["ckpt"]["optims"]["world_model"]))
    optims = [(opt_wm, wm, wc.grad_clip), (torch.optim.Adam(reward_head.parameters(), lr=wc.lr), reward_head, wc.grad_clip),
              (torch.optim.Adam(actor.parameters(), lr=ac.actor_lr), actor, ac.grad_clip),
              (torch.optim.Adam(critic.parameters(), lr=ac.critic_lr), critic, ac.grad_clip)]
    parts = {"world_model": wm, "reward_head": reward_head, "actor": actor, "critic": critic, "slow_critic": slow_critic,
             "return_norm": return_norm, **{f"optim_{i}": opt for i, (opt, _, _) in enumerate(optims)}}
    env = envs.make_env(cfgs["train"].env, cell["task"])
    ot_cfg = OTConfig(**PRESETS["ot"][nc.preset])  # the solver's settings, unit scale: the labels are scaled below
    goal, episodes, log, scale, first = genrl.no_goal(1, device), [], [], None, 0
    if resume:
        done, rng = genrl.load_state(parts, resume)
        first, scale, log = done // nc.episode_steps, resume["scale"], resume["log"]
        episodes = [{k: v.numpy() for k, v in episode.items()} for episode in resume["episodes"]]
    state = lambda: {**genrl.save_state(parts, (e + 1) * nc.episode_steps, rng), "episodes": rundir.plain(episodes), "scale": scale, "log": log}
    n_episodes, marks = nc.env_steps // nc.episode_steps, budgets(nc)
    bar = tqdm(total=n_episodes * nc.updates, initial=first * nc.updates, desc=f"{METHOD} seed {seed} updates ({n_episodes} episodes)", leave=False)
    for e in range(first, n_episodes):
        episode, task_return = collect_episode(env, wm, actor, nc.episode_steps, wc.obs, 10_000 + 1000 * seed + e)
        reward, best = episode_rewards(encoder(episode["pixels"]), demo_p, ot_cfg)
        scale = scale or nc.reward_sum / max(abs(float(reward.sum())), 1e-12)  # ROT: fixed once, on the first episode
        episodes.append({k: episode[k] for k in (wc.obs, "action", "is_first")} | {"reward": reward * scale})
        online = collect.Segments(episodes, (wc.obs, "action", "is_first", "reward"), wc.seq_len)
        for _ in range(nc.updates):
            batch, n_body, labels = mixed_batch(body, online, cfgs, nc.body_ratio, rng, device)
            wm_loss, metrics, post = wm.loss(batch)  # Eq. 2
            predicted = reward_head(wm.feat(post)[n_body:]).squeeze(-1)  # (B - n_body, T)
            reward_loss = 0.5 * (predicted - labels).pow(2).mean()  # a unit Gaussian, as Dreamer's reward head
            start, _ = policy.sample_starts(post, nc.starts)
            with policy.freeze(wm, reward_head, slow_critic):
                feat, _, log_prob = policy.rollout(wm, actor, start, goal, ac.horizon)  # (N, H + 1, F)
                imagined = reward_head(feat[:, 1:]).squeeze(-1)  # (N, H): r(s_{k+1}) on arrival
                returns = policy.lambda_return(imagined, slow_critic(feat, None), ac.gamma, ac.lambda_)  # (N, H)
            a_loss, a_metrics = policy.actor_loss(returns, log_prob, return_norm, ac.entropy)
            c_loss, _ = policy.critic_loss(critic, feat, None, returns)
            loss = wm_loss + reward_loss + a_loss + c_loss  # one backward: freeze and the detached starts keep each term to its modules
            for opt, _, _ in optims:
                opt.zero_grad(set_to_none=True)
            loss.backward()
            for opt, module, clip in optims:
                torch.nn.utils.clip_grad_norm_(module.parameters(), clip)
                opt.step()
            policy.ema_update(slow_critic, critic, ac.slow_critic_rate)
            bar.update(1)
        log.append({"episode": e, "task_return": round(task_return, 2), "ot_sum": round(float(reward.sum() * scale), 3), "best_demo": best,
                    "wm_loss": round(metrics["wm_loss"], 3), "reward_loss": round(reward_loss.item(), 5), "imagined_return": round(a_metrics["return"], 3)})
        bar.set_postfix(episode=e, ot=log[-1]["ot_sum"], task=log[-1]["task_return"])
        if on_budget and (e + 1) * nc.episode_steps in marks:
            on_budget((e + 1) * nc.episode_steps, actor, wm, state)
    bar.close()
    env.close()
    return actor, wm, log


def run_cell(run_dir, demo, view, nc, data=None):
    """AIME-NoB on one demo folder for seeds 0..nc.seeds-1, at each budget of budgets(nc), skipping what has a row
    already -> the new rows."""
    cell = genrl.load_cell(run_dir, demo, view, data)
    inputs = {}

    def train(seed, on_budget, resume):
        if not inputs:  # once per cell, and only when a seed runs
            inputs["encoder"] = load_encoder(cell["cfgs"]["train"].encoder)
            check_same_encoder(cell["ckpt"]["encoder"], inputs["encoder"].name, f"{run_dir}/checkpoint.pt and its --encoder {cell['cfgs']['train'].encoder!r}")
            demos = [d["p"] for d in cell["demos"]]
            inputs["demo_p"] = torch.as_tensor(np.stack([p[: min(len(q) for q in demos)] for p in demos]), device=cell["device"])  # (K, M, D)
            inputs["body"] = checkpoint.body_segments(cell["cfgs"]) if round(nc.body_ratio * cell["cfgs"]["wm"].batch) else None
        train_seed(cell, nc, inputs["body"], inputs["encoder"], inputs["demo_p"], seed, on_budget, resume)

    return genrl.run_seeds(cell, METHOD, nc, train, env_steps="budget")


def main():
    genrl.run_cells(genrl.cell_parser("Baseline AIME-NoB (AIME loss off): online imitation with an OT reward on video features, world "
                                      "model learning on.", AIMENoBConfig, PRESETS["aime_nob"]), run_cell, METHOD, AIMENoBConfig, PRESETS["aime_nob"])


if __name__ == "__main__":
    rundir.run_main(main, "the finished seeds are in the run's results.jsonl: the same command runs the others")
