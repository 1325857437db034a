"""Eq. 1, upper level, and Eq. 5: freeze the policy, infer the goal from a demonstration of another body or camera.

GIIL-ZS  g = goal encoder(p_T), p_T the last video feature of a demo (Sec. 4); each of the 10 demos
         gives a goal, each goal eval_episodes episodes in the agent's own env with the task's true reward.
GIIL-ZS (demo 0)  the first demo's zero-shot goal, the goal every goal search starts from, evaluated with the search's
         evaluation seeds: a search minus this column is what the search itself adds.
GIIL-FT  from the first demo's zero-shot goal, g is optimised by L_GI (Eq. 5): imagined rollouts of the
         frozen policy pi(a | s, g), per-step OT reward between the goal decoder's features of the imagined
         states and the demos (ot_reward.py), a value V_ot(s) trained on TD(lambda) targets of that reward,
         and the lambda-returns maximised through the dynamics with respect to g only. `seeds` seeds.
GIIL-online  ours, after Sec. 6 (online.py): the goal chosen on real rollouts scored by the same OT reward.
GIIL-retrieve  ours: demo 0's zero-shot goal where the body's own experience holds it; where it lies outside every final
         goal of D_body, the goal of the agent's own D_body episode whose recorded video matches the demos best by the
         same OT reward: a candidate from the body's own experience, scored on a real trajectory (giil_retrieve).

The goal searches (GIIL-FT, GIIL-online) share one interface, SEARCHES: a search is a function (cell, seed) -> goal,
and its entry says how many seeds it runs and which settings its rows depend on (a row's identity, result_config).

Deviation (docs/ablations.md, Phase 2): psi stays frozen. Sec. 4's joint finetuning of psi by L_MG did not help over
the shipped agents' SE-SV and SE-CV columns, paired seed by seed, and was removed.

Choices where the paper is silent:
* start states of the goal-inference imagination: demo features mapped into the latent space by the goal encoder
  q(s | p_t), Eq. 5's D_demo o q_phi read as embodiment-agnostic start states; the imagined steps are matched against
  the demo frames that follow (ot_reward's windowed matching).
* a segment against a 500-step demo: each imagined step is matched by OT against the window of demo frames that follow
  its start frame (ot_reward.py's windowed matching), against every demo, the best one counting (ROT).

The harness that runs a demo folder (rows, resume, videos, plots) is runner.py, under imitate.py (one demo folder) and
tables.py (every cell, with the baselines).
"""
import dataclasses
import json
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

import configs
import envs
import online
import ot_reward
import policy
import rundir
from video_encoder import load_encoder


CHOICES = {"preset": tuple(configs.PRESETS["imitate"])}
FINETUNE_FIELDS = ("steps", "starts", "goal_lr", "critic_lr", "seeds")  # what GIIL-FT alone reads
EVALUATION_FIELDS = ("eval_episodes", "eval_steps")  # what every row depends on
RETRIEVE_STRIDE = 10  # ours: GIIL-retrieve compares episodes on every 10th frame (50 of 500 steps), OT's cost / 100


def goal_inference_loss(models, critic_ot, slow_ot, goal, start, demo_p, cfgs, ot_cfg, offsets=None):  # Eq. 5
    """L_GI: -lambda-returns of the OT reward of the frozen policy's imagined rollouts, differentiable in g only.
    goal (F,) the parameter; start dict of (N, .). -> (L_GI, V_ot critic loss, metrics)."""
    ac = cfgs["ac"]
    wm, vae, actor = models["world_model"], models["goal_vae"], models["actor"]
    N = len(start["deter"])
    with policy.freeze(wm, vae, actor, slow_ot):  # psi*, the world model and the goal decoder are constants here
        feat, _, _ = policy.rollout(wm, actor, start, goal.expand(N, -1), ac.horizon)  # (N, H + 1, F)
        with torch.no_grad():  # (N, H): r^ot on arrival, a constant for g (Eq. 5 differentiates V_ot only)
            reward, _ = ot_reward.ot_reward(vae.decode(feat[:, 1:]), demo_p, ot_cfg, offsets)
        value = slow_ot(feat, None)  # (N, H + 1): V_ot(s), differentiable in feat
        returns = policy.lambda_return(reward, value, ac.gamma, ac.lambda_)  # (N, H)
    # Eq. 5: -E[sum V], the lambda-returns standing for the values as in Dreamer V1; g's gradient flows through V_ot of
    # the imagined states
    loss = -returns.mean()
    c_loss, c_metrics = policy.critic_loss(critic_ot, feat, None, returns)
    return loss, c_loss, {"L_GI": loss.item(), "ot_reward": reward.mean().item(), **{"ot_" + k: v for k, v in c_metrics.items()}}


def finetune_goal(models, cfgs, ic, ot_cfg, p_goal, demo_p, seed, device):
    """GIIL-FT: optimise g for ic.steps updates of Eq. 5 from the zero-shot goal q(s | p_goal), p_goal (D,) the first
    demo's last feature, demo_p the demos' features [(M, D)]. Returns the final g (F,)."""
    torch.manual_seed(seed)
    ac = cfgs["ac"]
    critic_ot, slow_ot = policy.make_critics(ac, models["world_model"].feat_dim, 0)
    critic_ot, slow_ot = critic_ot.to(device), slow_ot.to(device)
    with torch.no_grad():
        goal = torch.nn.Parameter(models["goal_vae"].goal(p_goal).clone())  # g0 = q(s | p_T): GIIL-ZS's goal
    opt_goal = torch.optim.Adam([goal], lr=ic.goal_lr)
    opt_ot = torch.optim.Adam(critic_ot.parameters(), lr=ic.critic_lr)
    stop = lambda: "nothing more is appended to results.jsonl (a learning rate too high? --goal-lr, --critic-lr)"
    # (K, M, D): one collection, every demo of one length; float64 once here, not in every ot_reward call (exact either way)
    demo_p = torch.as_tensor(np.stack(demo_p), device=device, dtype=torch.float64)
    K, M = demo_p.shape[:2]
    bar = tqdm(range(ic.steps), desc=f"GIIL-FT seed {seed}", leave=False)
    for step in bar:
        # Eq. 5's start states: goal-encoder states of demo frames t0, matched against the frames that follow
        t0 = torch.randint(M - ac.horizon - 1, (ic.starts,), device=device)
        with torch.no_grad():
            start = models["goal_vae"].encode(demo_p[torch.randint(K, (ic.starts,), device=device), t0].float())
        start = {k: start[k] for k in models["world_model"].state_keys}
        gi_loss, ot_loss, metrics = goal_inference_loss(models, critic_ot, slow_ot, goal, start, demo_p, cfgs, ot_cfg, t0 + 1)
        for opt, loss, what in ((opt_goal, gi_loss, "Eq. 5 L_GI"), (opt_ot, ot_loss, "V_ot loss")):
            rundir.checked_step(opt, loss, f"GIIL-FT seed {seed}: {what}", step, stop)
        policy.ema_update(slow_ot, critic_ot, ac.slow_critic_rate)
        bar.set_postfix(ot=f"{metrics['ot_reward']:.4f}")
    return goal.detach()


# --- the goal searches: one interface, registered in SEARCHES ---

@dataclasses.dataclass
class Cell:
    """What a goal search sees of one demo folder: the frozen agent, the settings, the demos and their zero-shot goals."""
    models: dict
    cfgs: dict
    ic: configs.ImitateConfig
    oc: configs.OnlineConfig
    ot_cfg: configs.OTConfig
    task: str
    demos: list  # the folder's episodes (collect.load_folder): "p" (T + 1, D) video features, "pixels"
    goals: list  # GIIL-ZS's goals q(s | p_T), one (F,) per demo
    device: str
    body: Callable  # () -> D_body's episode names, their features every RETRIEVE_STRIDE-th frame (N, T', D), last features (N, D)
    memo: dict = dataclasses.field(default_factory=dict, init=False)  # what a search computes once per cell, not per seed


def giil_ft(cell, seed):
    """the goal finetuned by Eq. 5 from demo 0's zero-shot goal, --seeds seeds (5)."""
    goal = finetune_goal(cell.models, cell.cfgs, cell.ic, cell.ot_cfg, torch.as_tensor(cell.demos[0]["p"][-1], device=cell.device),
                         [d["p"] for d in cell.demos], seed, cell.device)
    # how far finetuning moved g: beside the distance between the demos' zero-shot goals (docs/results.md)
    return goal, 0, {"goal_shift": round((goal - cell.goals[0]).norm().item(), 3)}


def giil_online(cell, seed):
    """ours, after Sec. 6 (online.py): the goal chosen among the demos' zero-shot goals by the OT reward of real
    rollouts, 50 episodes per seed, 3 seeds."""
    tc, ic = cell.cfgs["train"], cell.ic
    goal, k, log = online.refine_goal(cell.models, cell.cfgs, lambda: envs.make_env(tc.env, cell.task), torch.stack(cell.goals),
                                      np.stack([d["p"] for d in cell.demos]), cell.oc, seed, load_encoder(tc.encoder), ic.eval_steps,
                                      cell.ot_cfg)
    return goal, k, {"env_steps": len(log) * ic.eval_steps, "ot_log": [[i, s, round(score, 4)] for i, s, score in log], "chosen_demo": k}


def support(goal, final_goals):
    """ours, GIIL-retrieve's acceptance test: (the distance from goal (F,) to the nearest of D_body's final goals
    (N, F), the support's radius: the largest distance of one of those final goals to its nearest other one). A goal
    farther out than the radius lies outside every goal the hindsight clone learnt to end an episode in."""
    apart = torch.cdist(final_goals, final_goals).fill_diagonal_(float("inf"))
    return torch.cdist(goal[None], final_goals).min().item(), apart.min(1).values.max().item()


def giil_retrieve(cell, seed):
    """ours: demo 0's zero-shot goal where it lies inside the support of D_body's final goals (support); outside it,
    the goal of the agent's own D_body episode that matches the demos best, q(s | p_T) of its last frame. Each
    episode's real trajectory is scored against the demos by App. C's OT reward (whole episode against each demo, the
    best demo counting: GIIL-online's score of a real rollout) on every RETRIEVE_STRIDE-th frame: candidates from the
    body's own experience, ranked with no imagination and no episode run; one goal, evaluated on every seed's starts."""
    if "retrieve" not in cell.memo:  # the seeds differ in their evaluation's starts only: the search runs once a cell
        names, body_p, body_last = cell.body()
        with torch.no_grad():
            final_goals = cell.models["goal_vae"].goal(torch.as_tensor(body_last, device=cell.device))
        distance, radius = support(cell.goals[0], final_goals)
        extra = {"support_distance": round(distance, 3), "support_radius": round(radius, 3)}
        if distance <= radius:  # the demo's own goal is one the body's experience holds: kept
            cell.memo["retrieve"] = cell.goals[0], {"retrieved": None, **extra}
        else:
            score = online.ot_score(body_p, np.stack([d["p"][::RETRIEVE_STRIDE] for d in cell.demos]), cell.ot_cfg)  # (N,)
            best = int(np.argmax(score))
            cell.memo["retrieve"] = final_goals[best], {"retrieved": names[best], "retrieved_ot": round(float(score[best]), 4), **extra}
    goal, extra = cell.memo["retrieve"]
    return goal, 0, dict(extra)


@dataclasses.dataclass(frozen=True)
class GoalSearch:
    search: Callable  # (cell, seed) -> (g (F,), the demo shown beside its video, more fields of its row)
    seeds: Callable  # (ImitateConfig, OnlineConfig) -> the seeds it runs, each paired with GIIL-ZS (demo 0)
    config: Callable  # (ImitateConfig, OnlineConfig) -> the settings its rows depend on: a row's identity
    flag: str  # imitate.py --<flag>, tables.py --methods <flag>


def finetune_config(ic, oc):
    return {k: v for k, v in dataclasses.asdict(ic).items() if k not in ("seeds", "video")}


def retrieve_config(ic, oc):
    return {**{k: getattr(ic, k) for k in EVALUATION_FIELDS}, "preset": ic.preset, "stride": RETRIEVE_STRIDE, "accept": "support"}


def online_config(ic, oc):  # as a row stores it: JSON has no tuples (the schedule reads back as lists)
    fields = {**{k: getattr(ic, k) for k in EVALUATION_FIELDS}, **{k: v for k, v in dataclasses.asdict(oc).items() if k != "seeds"}}
    return json.loads(json.dumps(fields))


SEARCHES = {
    "GIIL-FT": GoalSearch(giil_ft, lambda ic, oc: ic.seeds, finetune_config, "finetune"),
    "GIIL-online": GoalSearch(giil_online, lambda ic, oc: oc.seeds, online_config, "online"),
    "GIIL-retrieve": GoalSearch(giil_retrieve, lambda ic, oc: ic.seeds, retrieve_config, "retrieve"),
}
ZERO_SHOT = ("GIIL-ZS", "GIIL-ZS (demo 0)")
METHODS = ZERO_SHOT + tuple(SEARCHES)  # a cell's columns, in the tables' order
