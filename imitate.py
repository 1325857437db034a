"""Eq. 1, upper level, and Eq. 5: freeze the policy, infer the goal from a demonstration of another body or camera.

GIIL-ZS  g = goal encoder(p_T), p_T the last video feature of a demo (Sec. 4); each of the 10 demos
         gives a goal, each goal eval_episodes episodes in the agent's own env with the task's true reward.
GIIL-ZS (demo 0)  the first demo's zero-shot goal, the goal GIIL-FT starts from, evaluated with GIIL-FT's evaluation
         seeds: GIIL-FT minus this column is what finetuning itself adds.
GIIL-FT  from the first demo's zero-shot goal, g is optimised by L_GI (Eq. 5): imagined rollouts of the
         frozen policy pi(a | s, g), per-step OT reward between the goal decoder's features of the imagined
         states and the demos (ot_reward.py), a value V_ot(s) trained on TD(lambda) targets of that reward,
         and the lambda-returns maximised through the dynamics with respect to g only. With
         `--finetune-policy 1`, psi is finetuned jointly by L_MG (Eq. 4) with g among its goals (Sec. 4, last
         paragraph): stop-gradients keep g out of L_MG and psi out of L_GI. `seeds` seeds.

Deviation (measured in docs/ablations.md, Phase 2): psi stays frozen by default (joint finetuning did not help over
the shipped agents' whole SE-SV and SE-CV columns, paired seed by seed). Two variants of ours were measured equal to
Eq. 5 as written on same-body cells and removed: g's gradient through the OT rewards of the lambda-returns too, and
V_ot alone for the first 100 updates.

Choices where the paper is silent:
* start states of the goal-inference imagination: demo features mapped into the latent space by the goal encoder
  q(s | p_t), Eq. 5's D_demo o q_phi read as embodiment-agnostic start states; the imagined steps are matched against
  the demo frames that follow (ot_reward's windowed matching). Two other choices measured worse and were removed
  (docs/ablations.md): D_body posterior start states, and optimising a video feature p with g = q(s | p).
* a segment against a 500-step demo: whole-demo OT (ot_reward.py) against every demo, the best one counting (ROT).

    python imitate.py --demo stickman_run [--view side|diagonal] [--run runs/<name> | --env walker|stickman] [--preset P] [--finetune]
    python imitate.py --table [--run runs/<name>] [--methods giil,genrl,aime-nob] [--budgets genrl=2000]   (tables.py)
Missing demos of the one body x task imitated are collected first (collect.py, the run's preset and data folder).
"""
import argparse
import contextlib
import copy
import dataclasses
import os
import time

import numpy as np
import torch
from tqdm import tqdm

import aime_nob
import checkpoint
import cloning
import collect
import envs
import evaluate
import genrl
import online
import ot_reward
import policy
import rundir
import tables
from presets import PRESETS
from video_encoder import check_same_encoder, load_encoder


@dataclasses.dataclass
class ImitateConfig:
    preset: str = "cpu"
    steps: int = 300  # goal-finetuning updates (ours, a CPU budget)
    starts: int = 64  # imagined trajectories per L_GI update (ours)
    goal_lr: float = 3e-4  # Adam on g (ours; chosen on same-body cells, docs/ablations.md)
    critic_lr: float = 8e-5  # V_ot, as the phase-1 critic (Dreamer V1)
    finetune_policy: int = 0  # 0: the policy stays exactly psi* (ours: joint finetuning did not help on same-body cells, docs/ablations.md); 1: psi jointly finetuned by L_MG (Sec. 4)
    seeds: int = 5  # GIIL-FT seeds (the paper: 3; 5 so that FT vs ZS(demo 0) is measured beyond the noise)
    eval_episodes: int = 3  # episodes per GIIL-ZS goal and per GIIL-FT seed
    eval_steps: int = envs.EPISODE_STEPS
    video: int = 1  # write demo | agent side-by-side videos


CHOICES = {"preset": tuple(PRESETS["imitate"])}
FINETUNE_FIELDS = ("steps", "starts", "goal_lr", "critic_lr", "finetune_policy", "seeds")  # what GIIL-FT alone reads


def body_pool(models, cfgs, segments, rng, device, n=32):
    """n D_body segments filtered by the world model (no gradient): their posterior states, flattened, are where
    imagination starts and where L_MG's D_body goals come from; the segments themselves feed L_MG's
    behaviour-cloning term when the run uses one."""
    wc = cfgs["wm"]
    batch = segments.sample(n, rng, device)
    with torch.no_grad():
        post, _ = models["world_model"].observe(batch[wc.obs], batch["action"], batch["is_first"])
        bc = {"feat": models["world_model"].feat(post), "goal": models["goal_vae"].goal(batch["p"]), "action": batch["action"],
              "final": models["goal_vae"].goal(batch["p_last"])}
    return {k: v.flatten(0, 1) for k, v in post.items()}, bc


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


def multi_goal_loss(models, start, goal, body_goals, bc, cfgs):  # Eq. 4 during finetuning
    """L_MG with the current task goal sg(g) among D_body goals (plus the run's behaviour cloning on D_body
    segments, as in phase 1): gradients reach psi (actor, critic) only."""
    ac = cfgs["ac"]
    n = len(start["deter"])
    goals = torch.cat([goal.detach().expand(n // 2, -1), body_goals[torch.randint(len(body_goals), (n - n // 2,))]])
    a_loss, c_loss, metrics = policy.policy_losses(models["world_model"], models["dist_net"], models["actor"], models["critic"],
                                                   models["slow_critic"], models["return_norm"], start, goals, ac)
    if ac.bc:
        a_loss = a_loss + ac.bc * cloning.bc_loss(models["actor"], bc["feat"], bc["goal"], bc["action"], bc["final"], ac.bc_final)[0]
    return a_loss, c_loss, metrics


def finetune_goal(models, cfgs, ic, ot_cfg, p_goal, demo_p, seed, device, optim_states=None):
    """GIIL-FT: optimise g (and psi by L_MG with --finetune-policy 1) for ic.steps updates from the zero-shot goal
    q(s | p_goal), p_goal (D,) the first demo's last feature. Returns the final g (F,). optim_states: the phase-1
    checkpoint's optimiser states, from which L_MG's Adam continues (fresh Adam moments would make its first steps
    lr-sized on every weight)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    ac = cfgs["ac"]
    critic_ot, slow_ot = policy.make_critics(ac, models["world_model"].feat_dim, 0)
    critic_ot, slow_ot = critic_ot.to(device), slow_ot.to(device)
    with torch.no_grad():
        goal = torch.nn.Parameter(models["goal_vae"].goal(p_goal).clone())  # g0 = q(s | p_T): GIIL-ZS's goal
    opt_goal = torch.optim.Adam([goal], lr=ic.goal_lr)
    opt_ot = torch.optim.Adam(critic_ot.parameters(), lr=ic.critic_lr)
    if ic.finetune_policy:
        opt_actor = torch.optim.Adam(models["actor"].parameters(), lr=ac.actor_lr)
        opt_critic = torch.optim.Adam(models["critic"].parameters(), lr=ac.critic_lr)
        if optim_states:  # deep copies: Adam steps its state in place, and every seed starts from the checkpoint's
            opt_actor.load_state_dict(copy.deepcopy(optim_states["actor"]))
            opt_critic.load_state_dict(copy.deepcopy(optim_states["critic"]))
        segments = checkpoint.body_segments(cfgs)
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
            checkpoint.checked_step(opt, loss, f"GIIL-FT seed {seed}: {what}", step, stop)
        policy.ema_update(slow_ot, critic_ot, ac.slow_critic_rate)
        if ic.finetune_policy:  # fresh D_body segments every update, as in phase 1: L_MG goes on training on all of D_body
            pool, bc = body_pool(models, cfgs, segments, rng, device, cfgs["wm"].batch)
            index = torch.randint(len(pool["deter"]), (ic.starts,), device=device)
            body_start = {k: v[index] for k, v in pool.items()}
            a_loss, c_loss, _ = multi_goal_loss(models, body_start, goal, models["world_model"].feat(pool), bc, cfgs)
            for opt, loss, what in ((opt_actor, a_loss, "Eq. 4 actor loss"), (opt_critic, c_loss, "Eq. 4 critic loss")):
                checkpoint.checked_step(opt, loss, f"GIIL-FT seed {seed}: {what}", step, stop, ac.grad_clip)  # clipped as in phase 1
            policy.ema_update(models["slow_critic"], models["critic"], ac.slow_critic_rate)
        bar.set_postfix(ot=f"{metrics['ot_reward']:.4f}")
    return goal.detach()


def imitate(run_dir, demo, view, finetune, ic, zero_shot=True, done=None, online_cfg=None):
    """GIIL-ZS (unless not zero_shot), GIIL-FT (with finetune) and GIIL-online (with an online.OnlineConfig, ours after
    Sec. 6) for one demo folder; appends each evaluation
    to runs/<name>/results.jsonl and returns the rows. done: (method, seed) pairs this cell already has (table),
    not run again: a cell cut off after some seeds goes on from the first missing one. None: those results.jsonl has
    for these demos and settings, as --table finds them (a rerun after Ctrl-C goes on, appending no duplicates)."""
    rundir.check_flags(ic)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    cfgs, models, ckpt = checkpoint.load_run(run_dir, device)
    tc = cfgs["train"]
    rundir.fast_matmul()  # oneDNN where it is faster and still fp32 (rundir.py)
    folder = checkpoint.demo_folder(cfgs, demo, view)
    demo_body, task = demo.rsplit("_", 1)
    demos = collect.load_folder(folder, ("pixels", "p"))  # one collection: every demo of one length
    if finetune and len(demos[0]["p"]) < cfgs["ac"].horizon + 2:
        raise ValueError(f"{folder}: demos of {len(demos[0]['p'])} steps are too short for imagined segments of {cfgs['ac'].horizon}; collect longer ones")
    for d in demos:
        check_same_encoder(ckpt["encoder"], d["encoder"], d["path"])
    demo_returns = [round(d["return"], 3) for d in demos]  # identifies this D_demo: --table ignores rows of older demos
    where = tables.setting(tc.env, demo_body, view)
    ot_cfg = ot_reward.OTConfig(**PRESETS["ot"][ic.preset])
    out_dir = os.path.join(run_dir, "imitate")
    os.makedirs(out_dir, exist_ok=True)
    results_path = os.path.join(run_dir, "results.jsonl")
    rows = []
    if done is None:
        configs = {m: tables.result_config(ic, m, online_cfg) for m in tables.METHODS + ((tables.ONLINE,) if online_cfg else ())}
        done = {(r["method"], r["seed"]) for r in tables.finished(tables.load_results(run_dir), demo, view, demo_returns, configs)}
        if done:
            print(f"{results_path} has {len(done)} of these evaluations (these demos and settings): kept, not run again")
    done = set(done)  # grows as this call evaluates: GIIL-FT and GIIL-online share their GIIL-ZS (demo 0) seeds

    def evaluate_goal(method, seed, goal, video_demo, **extra):
        """eval_episodes episodes at once with goal (F,), environment seeds 20000 + 100 seed + e: GIIL-FT seed s and
        GIIL-ZS (demo 0) seed s meet the same start states. Seed 0's first episode is written as a video. `extra`: more
        fields of the row."""
        render = bool(ic.video) and seed == 0
        env_list = [envs.make_env(tc.env, task) for _ in range(ic.eval_episodes)]
        returns, frames = evaluate.run_episodes(env_list, models, goal[None].expand(ic.eval_episodes, -1), ic.eval_steps,
                                                cfgs["wm"].obs, 20_000 + 100 * seed, render)
        scores = [evaluate.episode_score(task, r, ic.eval_steps) for r in returns]
        if render:
            evaluate.write_video(os.path.join(out_dir, f"{demo}_{view}_{method.replace(' ', '_')}_s{seed}.mp4"), video_demo, frames[0])
        row = {"agent": tc.env, "demo": demo, "view": view, "task": task, "setting": where, "method": method, "seed": seed,
               "score": float(np.mean(scores)), "episode_scores": scores, "time": round(time.time() - t0, 1), "demo_returns": demo_returns,
               "config": tables.result_config(ic, method, online_cfg), **extra}
        rundir.append_jsonl(results_path, row)
        rows.append(row)
        done.add((method, seed))

    with torch.no_grad():
        goals = [models["goal_vae"].goal(torch.as_tensor(d["p"][-1], device=device)) for d in demos]  # GIIL-ZS: g = q(s | p_T)
    for k, goal in enumerate(tqdm(goals if zero_shot else [], desc=f"GIIL-ZS {demo} {view}")):
        if ("GIIL-ZS", k) in done:
            continue
        t0 = time.time()  # each row's own time, so a table's cost is the sum (rows before 2026-11-22 overlap)
        evaluate_goal("GIIL-ZS", k, goal, demos[k]["pixels"])
    if finetune:
        psi_star = {k: {n: t.clone() for n, t in m.state_dict().items()} for k, m in models.items()}  # clones: optimisers step in place
        for seed in range(ic.seeds):  # each seed is independent of the others: its own RNG seeds, from psi*
            t0 = time.time()
            if ("GIIL-ZS (demo 0)", seed) not in done:
                evaluate_goal("GIIL-ZS (demo 0)", seed, goals[0], demos[0]["pixels"])
            if ("GIIL-FT", seed) in done:
                continue
            t0 = time.time()  # GIIL-FT's time: finetuning and its evaluation
            goal = finetune_goal(models, cfgs, ic, ot_cfg, torch.as_tensor(demos[0]["p"][-1], device=device), [d["p"] for d in demos], seed, device,
                                 ckpt.get("optims"))
            # how far finetuning moved g: beside the distance between the demos' zero-shot goals (docs/results.md)
            evaluate_goal("GIIL-FT", seed, goal, demos[0]["pixels"], goal_shift=round((goal - goals[0]).norm().item(), 3))
            for k, m in models.items():  # psi* back (--finetune-policy 1 moved it) for the next seed and for GIIL-online
                m.load_state_dict(psi_star[k])
    if online_cfg:  # GIIL-online (online.py): the goal chosen among the demos' zero-shot goals by the OT reward of real rollouts
        encoder, demo_p = load_encoder(tc.encoder), np.stack([d["p"] for d in demos])
        for seed in range(online_cfg.seeds):
            t0 = time.time()
            if ("GIIL-ZS (demo 0)", seed) not in done:  # not again where GIIL-FT's seeds had it
                evaluate_goal("GIIL-ZS (demo 0)", seed, goals[0], demos[0]["pixels"])
            if (tables.ONLINE, seed) in done:
                continue
            t0 = time.time()  # GIIL-online's time: its real episodes, their scoring and its evaluation
            posterior = online_cfg.candidates == "posterior"
            candidates = online.posterior_goals(models["goal_vae"], demos[0]["p"][-1], len(goals), online_cfg.seed_base + seed) \
                if posterior else torch.stack(goals)
            goal, k, log = online.refine_goal(models, cfgs, lambda: envs.make_env(tc.env, task), candidates, demo_p, online_cfg,
                                              seed, encoder, ic.eval_steps, ot_cfg)
            evaluate_goal(tables.ONLINE, seed, goal, demos[0 if posterior else k]["pixels"], env_steps=len(log) * ic.eval_steps,
                          ot_log=[[i, s, round(score, 4)] for i, s, score in log], **{"chosen_candidate" if posterior else "chosen_demo": k})
    for method in tables.METHODS + (tables.ONLINE,):
        scores = [r["score"] for r in rows if r["method"] == method]
        if scores:
            print(f"{method} {tc.env} imitating {demo} ({view} view, {where}): normalised score {np.mean(scores):.1f} +- "
                  f"{evaluate.stderr(scores):.1f} over {len(scores)} {'demos' if method == 'GIIL-ZS' else 'seeds'} x {ic.eval_episodes} episodes")
    print(f"appended to {results_path}; videos in {out_dir}")
    return rows


def baseline_configs(preset, methods, budgets=None):
    """{method: (module, its config, the config its rows carry)} of the baselines named in `methods` (tables.BASELINES' keys),
    each with its own preset of that name (cpu's where it has none); budgets {name: budget} replaces a preset's (GenRL's
    updates, AIME-NoB's env steps: --budgets)."""
    out, budgets = {}, budgets or {}
    for name in methods:
        module, cls, key = {"genrl": (genrl, genrl.GenRLConfig, "genrl"), "aime-nob": (aime_nob, aime_nob.AIMENoBConfig, "aime_nob")}[name]
        given = {cls.budget_field: budgets[name]} if name in budgets else {}
        cfg = cls(**{**PRESETS[key].get(preset, {}), **given})  # a preset the baseline has not (paper): its defaults
        out[tables.BASELINES[name]] = (module, cfg, genrl.result_config(cfg))
    return out


def table(run_dir, ic, settings=envs.SETTINGS, demos_per_cell=10, shard=(0, 1), methods=("giil",), oc=None, budgets=None):
    """Tables 1-2 and 4-11 (tables.py): every setting x task for this agent, GIIL-ZS, GIIL-ZS (demo 0) and GIIL-FT
    ("giil" in `methods`) and the baselines named in `methods` (tables.BASELINES' keys: genrl.py, aime_nob.py, each with
    its preset of ic.preset); runs only what is missing from results.jsonl, and shows every finished cell of all of them.
    `settings` limits which settings run now, shard (i, N) runs only the cells i, i + N, i + 2N, ... of those (in
    tables.cells' order; N processes or machines share one table: rows are appended under a lock, one row per
    evaluation, and a cell's rows are told apart by method and seed, so shards merge without loss or duplicates); the
    tables show every finished cell. budgets {name: budget}: the baselines' columns at these budgets instead of their
    presets' (tables.parse_budgets; a budget's rows from genrl.py / aime_nob.py --eval-at count). A row counts only if it was
    made with the demos now on disk (their returns match) and with the settings asked for (tables.result_config): regenerating D_demo or changing a setting makes the cells
    run again instead of mixing old and new results."""
    unknown = [m for m in methods if m not in ("giil", "online") and m not in tables.BASELINES]
    if unknown:
        raise ValueError(f"--methods {','.join(unknown)}: choose from giil, online, {', '.join(tables.BASELINES)}")
    oc = oc or online.OnlineConfig(**PRESETS["online"][ic.preset])
    rundir.check_flags(ic)
    baselines = baseline_configs(ic.preset, tables.BASELINES, budgets)  # their finished cells are shown whichever methods run now
    cfgs = checkpoint.load_run(run_dir)[0]
    agent, shown = cfgs["train"].env, []
    configs = {**{m: tables.result_config(ic, m, oc) for m in tables.METHODS + (tables.ONLINE,)}, **{m: b[2] for m, b in baselines.items()}}
    # the shards split the cells of `settings`, so that none is left idle; a cell left out runs nothing, its finished rows still count
    runs_here = [cell for cell in tables.cells(agent) if cell[1] in settings][shard[0]::shard[1]]
    for task, where in tables.cells(agent):
        demo, view = tables.demo_of(agent, task, where)
        run_now = (task, where) in runs_here
        # one process at a time runs a cell (its lock file, rundir.claim): a second table process without --shard, or
        # with shards that overlap, skips the cells another one is running; their rows count once written
        with rundir.claim(tables.cell_lock(run_dir, demo, view)) if run_now else contextlib.nullcontext() as other:
            if other:
                print(f"{demo} ({view} view): process {other} is running this cell now ({tables.cell_lock(run_dir, demo, view)}): skipped here")
            run_now = run_now and not other
            folder = checkpoint.demo_folder(cfgs, demo, view) if run_now else os.path.join(cfgs["train"].data, "demos", f"{demo}_{view}")
            if not os.path.isdir(folder):
                continue
            returns = [round(e["return"], 3) for e in collect.load_folder(folder, ())]
            done = {(r["method"], r["seed"]) for r in tables.finished(tables.load_results(run_dir), demo, view, returns, configs)}
            count = lambda m: sum(method == m for method, _ in done)
            zs, ft = count("GIIL-ZS") < demos_per_cell, min(count("GIIL-FT"), count("GIIL-ZS (demo 0)")) < ic.seeds
            # GIIL-online's candidates are GIIL-ZS's goals: its column comes with them (and its curve is read from them)
            zs, ft = zs and ("giil" in methods or "online" in methods), ft and "giil" in methods
            on = "online" in methods and min(count(tables.ONLINE), count("GIIL-ZS (demo 0)")) < oc.seeds
            if (zs or ft or on) and run_now:  # only the seeds missing (a cell cut off goes on where it was)
                imitate(run_dir, demo, view, ft, ic, zero_shot=zs, done=done, online_cfg=oc if on else None)
            for name, method in tables.BASELINES.items():
                module, cfg, _ = baselines[method]
                if count(method) < cfg.seeds and run_now and name in methods:
                    module.run_cell(run_dir, demo, view, cfg)
            shown.append((demo, view, returns))
    rows = tables.load_results(run_dir)  # read once all cells ran: the rows other shards appended meanwhile count too
    text = tables.markdown_tables(agent, [r for cell in shown for r in tables.finished(rows, *cell, configs)])
    path = os.path.join(run_dir, "tables.md")
    rundir.atomic_write(path, lambda f: f.write(text.encode()))
    print(text)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description="Phase 2: infer the goal from a demo (GIIL-ZS, --finetune: GIIL-FT), or --table.", allow_abbrev=False)
    parser.add_argument("--demo", help="<demonstrator body>_<task>, e.g. stickman_run")
    parser.add_argument("--view", choices=envs.VIEWS, help="camera of the demo (default side)")
    parser.add_argument("--run", help="the phase-1 run (train.py) whose agent imitates (default: the --env agent's run of this --preset, "
                        "runs/<env>_<obs>_<preset>_s0, or else the shipped agents/<env>)")
    parser.add_argument("--env", choices=envs.BODIES, help="the agent's body, to pick the default --run (default walker); with --run, checked against its agent")
    parser.add_argument("--finetune", action="store_true", help="also GIIL-FT: finetune the goal (Eq. 5), --seeds seeds (default 5)")
    parser.add_argument("--online", action="store_true", help="also GIIL-online (ours, after Sec. 6; online.py): the goal chosen on real "
                        "rollouts by their OT reward, 20 episodes per seed, 3 seeds")
    parser.add_argument("--online-candidates", choices=online.CANDIDATES, default=None, help="GIIL-online's candidate goals (default "
                        "demos: the demos' zero-shot goals; posterior: demo 0's and 9 draws of q(s | p_T), online.OnlineConfig)")
    parser.add_argument("--table", action="store_true", help="all settings x tasks for this agent; keeps finished cells")
    parser.add_argument("--settings", help="with --table: the settings to run now, comma-separated (default all)")
    parser.add_argument("--shard", metavar="I/N", help="with --table: run only cells I, I + N, ... of those of --settings (N processes, one table)")
    rundir.threads_flag(parser)
    parser.add_argument("--budgets", help="with --table: the baselines' columns at these budgets instead of their presets', e.g. "
                        "genrl=2000,aime-nob=15000 (GenRL updates, AIME-NoB env steps)")
    parser.add_argument("--methods", help="with --table: comma-separated, of giil (GIIL-ZS, GIIL-FT; the default), genrl, aime-nob (the "
                        "baselines, genrl.py and aime_nob.py with their --preset); e.g. giil,genrl,aime-nob")
    for field in dataclasses.fields(ImitateConfig):
        parser.add_argument("--" + field.name.replace("_", "-"), type=type(field.default), default=None,
                            choices=CHOICES.get(field.name), help=f"default {field.default!r}, or the preset's")
    args = parser.parse_args()
    rundir.use_threads(args.threads)
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(ImitateConfig) if getattr(args, f.name) is not None}
    ic = ImitateConfig(**{**PRESETS["imitate"][given.get("preset", "cpu")], **given})
    # a flag that does nothing in the mode chosen is an error, not ignored
    demo_only = [f for f in ("demo", "view", "finetune", "online") if getattr(args, f)]
    table_only = [f for f in ("settings", "shard", "methods", "budgets") if getattr(args, f) is not None]
    if args.table and demo_only:
        parser.error(f"--{demo_only[0]} does nothing with --table (it runs every demo and view): drop it")
    if not args.table and table_only:
        parser.error(f"--{table_only[0]} works with --table only: add --table, or drop it")
    if args.online_candidates and not (args.online or "online" in (args.methods or "").split(",")):
        parser.error("--online-candidates sets GIIL-online: add --online (or --table --methods online), or drop it")
    oc = online.OnlineConfig(**{**PRESETS["online"][ic.preset], **({"candidates": args.online_candidates} if args.online_candidates else {})})
    if args.demo and not args.finetune and any(f in given for f in FINETUNE_FIELDS):
        parser.error(f"--{[f for f in FINETUNE_FIELDS if f in given][0].replace('_', '-')} sets GIIL-FT: add --finetune, or drop it")
    run = args.run or checkpoint.resolve_run(args.env or "walker", ic.preset)
    # before anything runs: the run's agent is the body --env names (with --run) and what its folder's name says
    rundir.run_checkpoint(run, env=args.env)
    if args.table:
        try:
            settings, shard = tables.parse_settings(args.settings or ",".join(envs.SETTINGS)), tables.parse_shard(args.shard)
            budgets = tables.parse_budgets(args.budgets) if args.budgets else None
        except ValueError as error:
            parser.error(str(error))
        table(run, ic, settings, shard=shard, methods=(args.methods or "giil").split(","), oc=oc, budgets=budgets)
    elif args.demo:
        view, lock = args.view or "side", tables.cell_lock(run, args.demo, args.view or "side")
        with rundir.claim(lock) as other:  # as a --table cell: one process at a time
            if other:
                raise ValueError(f"process {other} is running {args.demo} ({view} view) on {run} now ({lock}): wait for it to end; "
                                 f"the same command then goes on from its rows")
            imitate(run, args.demo, view, args.finetune, ic, online_cfg=oc if args.online else None)
    else:
        parser.error("pass --demo NAME (e.g. stickman_run) or --table")


if __name__ == "__main__":
    rundir.run_main(main, "every evaluation finished is in the run's results.jsonl: the same command goes on from there")
