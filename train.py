"""Eq. 1, lower level: phase 1 learns psi* = argmin L_MG on D_body alone, with no task labels.

One update, in the order of Sec. 4:
  Eq. 2  world model (RSSM) on a batch of D_body segments            -> posterior states s_t
  Eq. 3  goal VAE q(s | p_t), p(p_t | s) against sg(posterior)
  Eq. 7  temporal distance network on pairs of posterior states (and of states and encoder goals, ours)
  Eq. 4  goal-conditioned actor-critic in imagination, reward -d(s, g)   (after `policy_start` updates,
         once the world model and distance give a meaningful reward)
  ours   hindsight behaviour cloning beside Eq. 4's actor loss, and a cloning polish after the last update (cloning.py)
Ends with the learning curve (learning_curve.png) and the goal-reaching benchmark (evaluate.py): the multi-task
policy in the real environment with its own body's side-view demos as goals, against random actions.

    python train.py --env walker [--obs state|pixels] [--preset smoke|cpu|paper] [--seed N] [--resume]
    python train.py --env walker --evaluate [--run-dir runs/<name>]   # the benchmark alone, of a trained run
"""
import argparse
import copy
import dataclasses
import json
import os
import time

import numpy as np
import torch
from tqdm import tqdm

import checkpoint
import cloning
import distance
import envs
import evaluate
import policy
import rundir
from checkpoint import default_run_dir, load_run, prepare_data
from configs import COMPONENTS, PRESETS, TrainConfig, config_flags


def add_config_flags(parser):
    """One flag per field of each component's config (configs.config_flags: its help the field's comment)."""
    for name, (cls, prefix) in COMPONENTS.items():
        config_flags(parser, cls, prefix, f"{name}.", {"preset": tuple(PRESETS["train"])} if name == "train" else getattr(cls, "choices", None),
                     bare=("obs",) if name == "wm" else ())


def resolve_configs(args, preset):
    """dataclass defaults (the cpu preset) < the preset's overrides (configs.py) < explicit flags -> {component: config}."""
    out = {}
    for name, (cls, _) in COMPONENTS.items():
        given = {f.name: getattr(args, f"{name}.{f.name}") for f in dataclasses.fields(cls)}
        out[name] = cls(**{**PRESETS[name][preset], **{k: v for k, v in given.items() if v is not None}})
    out["train"].preset = preset  # the preset these sizes come from, whichever way it was passed
    return out


def gradient_norms(module, **losses):
    """{'grad_<name>': the L2 norm of d loss / d module's parameters} for each named loss, without touching .grad:
    how much of the actor's update each term of its loss makes (logged: Eq. 4's against the cloning's)."""
    params = [p for p in module.parameters() if p.requires_grad]
    out = {}
    for name, loss in losses.items():
        grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
        out["grad_" + name] = torch.sqrt(sum((g ** 2).sum() for g in grads if g is not None)).item()
    return out


def log_line(m):
    """One line per log step, grouped by equation; the actor-critic's part only once it has started."""
    line = (f"{m['step']}: Eq.2 wm {m['wm_loss']:.2f} (recon {m['recon']:.2f} kl {m['kl']:.2f} open-loop {m['open_loop']:.3f}, "
            f"p cos {m['open_loop_p_cos']:.2f}) | Eq.3 goal {m['goal_loss']:.2f} (cos {m['goal_cos']:.2f}) | Eq.7 dist {m['dist_loss']:.3f}")
    if "d_enc" in m:
        line += " (d of encoder goals 1/5/15/30 ahead, other: " + " ".join(f"{d:.2f}" for d in m["d_enc"]) + ")"
    if "actor_loss" in m:
        line += f" | Eq.4 actor {m['actor_loss']:.3f} critic {m['critic_loss']:.3f} reward {m['reward']:.3f}" + (f" bc {m['bc_loss']:.2f}" if "bc_loss" in m else "")
    return line + f" | {m['updates_per_s']:.1f} upd/s"


def report_goal_reaching(run_dir, models, cfgs, device, name="goal_reaching.json"):
    """evaluate.goal_reaching, printed as a table and written to runs/<name>/goal_reaching.json (or `name`)."""
    tc = cfgs["train"]
    scores = evaluate.goal_reaching(models, cfgs, tc.eval_episodes, tc.eval_steps, device=device)
    print(f"goal reaching, {tc.env}: own side-view demos as goals (g = q(s | p_T)), {tc.eval_episodes} episodes per demo, "
          f"{tc.eval_steps} steps, normalised score (Eq. 8) mean +- s.e.")
    print("\n".join(evaluate.summary(scores)))
    weights = rundir.weights_id(rundir.load_checkpoint(os.path.join(run_dir, "checkpoint.pt")))  # the agent scored, as saved
    print("wrote", evaluate.write_goal_reaching(run_dir, scores, tc, weights, name))
    return scores


def train(cfgs, run_dir, resume):
    """Phase 1 into run_dir, which no other process writes meanwhile (rundir.lock); flags are checked first."""
    for name, config in cfgs.items():
        rundir.check_flags(config, COMPONENTS[name][1])
    ckpt_path = os.path.join(run_dir, "checkpoint.pt")
    if resume and not os.path.exists(ckpt_path):
        raise ValueError(f"--resume: no checkpoint at {ckpt_path}; drop --resume to start a new run there")
    with rundir.lock(run_dir):
        return pretrain(cfgs, run_dir, resume)


def make_optimizers(models, cfgs):
    """One Adam per trained model, and its gradient-norm clip."""
    wc, ac, gc, dc = cfgs["wm"], cfgs["ac"], cfgs["goal"], cfgs["dist"]
    lrs = {"world_model": wc.lr, "goal_vae": gc.lr, "dist_net": dc.lr, "actor": ac.actor_lr, "critic": ac.critic_lr}
    clip = {"world_model": wc.grad_clip, "goal_vae": gc.grad_clip, "dist_net": dc.grad_clip, "actor": ac.grad_clip, "critic": ac.grad_clip}
    return {name: torch.optim.Adam(models[name].parameters(), lr=lr) for name, lr in lrs.items()}, clip


def diagnostics(models, cfgs, data, rng, device, post, post_feat, goal_feat, is_first, step):
    """What a log row adds to the losses: open-loop imagination (evaluate.open_loop_metrics), d of encoder goals 1, 5, 15
    and 30 steps ahead (evaluate.distance_profile), Eq. 4's reward on reachable goals (evaluate.reachable_goal_reward)."""
    wc, ac, wm = cfgs["wm"], cfgs["ac"], models["world_model"]
    out = evaluate.open_loop_metrics(wm, models["goal_vae"], data.sample(wc.batch, rng, device), wc.seq_len // 2)
    if wc.seq_len > 40:
        out.update(evaluate.distance_profile(models["dist_net"], post_feat, goal_feat, is_first))
    if step >= cfgs["train"].policy_start and wc.seq_len > ac.horizon:  # from the fresh actor's row on
        out.update(evaluate.reachable_goal_reward(wm, models["dist_net"], models["actor"], post, goal_feat, is_first, ac.horizon, seed=step))
    return out


def final_report(run_dir, models, cfgs, held_out, device):
    """After training: imagination on held-out D_body, the learning curve, the goal-reaching benchmark."""
    wc = cfgs["wm"]
    imagination = evaluate.evaluate_imagination(models, cfgs, held_out, device)
    rundir.atomic_write(os.path.join(run_dir, "imagination.json"), lambda f: f.write(json.dumps(imagination, indent=1).encode()))
    print(f"held-out D_body: goal decoder's cosine to the true p_t {imagination['posterior_p_cos']:.2f} on posterior states, "
          f"{imagination['open_loop_p_cos']:.2f} on {wc.seq_len - wc.seq_len // 2} open-loop imagined steps (world-model error {imagination['open_loop']:.3f})")
    print("wrote", evaluate.learning_curve(run_dir))
    report_goal_reaching(run_dir, models, cfgs, device)


def pretrain(cfgs, run_dir, resume):
    """Phase 1 into run_dir (module docstring): every update Eq. 2, 3 and 7 on one batch of D_body segments, then Eq. 4
    with the hindsight cloning beside it; the log, checkpoints and, after the last update, the polish and the report."""
    tc, wc, dc, ac, cc = cfgs["train"], cfgs["wm"], cfgs["dist"], cfgs["ac"], cfgs["cloning"]
    device = "cuda" if torch.cuda.is_available() else "cpu"
    torch.set_num_threads(tc.threads)
    rundir.fast_matmul()  # oneDNN where it is faster and still fp32 (rundir.py)
    torch.manual_seed(tc.seed)  # seeding: one block, everything from the run seed
    rng = np.random.default_rng(tc.seed)
    encoder, data, held_out, shapes = prepare_data(cfgs)
    models = checkpoint.build_models(cfgs, *shapes, device)
    wm, vae, dist_net, actor, critic, slow_critic = (models[k] for k in ("world_model", "goal_vae", "dist_net", "actor", "critic", "slow_critic"))
    optims, clips = make_optimizers(models, cfgs)
    ckpt_path, log_path = (os.path.join(run_dir, n) for n in ("checkpoint.pt", "metrics.jsonl"))
    first, rng = checkpoint.resume_from(ckpt_path, resume, cfgs, models, optims, encoder, device, rng)
    rundir.trim_jsonl(log_path, first)  # rows a killed run logged after its checkpoint
    keep = lambda done, **actors: checkpoint.save(ckpt_path, cfgs, done, rng, encoder, shapes, models, optims, **actors)
    update = lambda name, loss, term: rundir.checked_step(optims[name], loss, term, step, lambda: checkpoint.stop_hint(ckpt_path, saved, cfgs, name), clips[name])
    saved, t0, metrics, total = first, time.time(), {}, tc.steps
    for step in (bar := tqdm(range(first, total), initial=first, total=total, desc=f"train {os.path.basename(run_dir)}")):
        batch = data.sample(wc.batch, rng, device)
        logged = (step + 1) % tc.log_every == 0 or step + 1 == total  # the update whose metrics the log row keeps
        # Eq. 2: the world model (RSSM) on the segments -> posterior states s_t
        loss, m2, post = wm.loss(batch)
        update("world_model", loss, "Eq. 2 world-model loss")
        # Eq. 3: the goal VAE, q(s | p_t) and p(p_t | s), against sg(posterior)
        loss, m3 = vae.loss(batch["p"], post)
        update("goal_vae", loss, "Eq. 3 goal-VAE loss")
        metrics.update(m2 | m3)
        post_feat = wm.feat(post).detach()  # (B, T, F)
        # Eq. 7: the temporal distance on pairs of posterior states, and of states and encoder goals (ours)
        with torch.no_grad():  # the goal encoder's g of every frame (B, T, F), what GIIL-ZS feeds the policy, and of the last (B, F)
            goal_feat, final_goal = vae.goal(batch["p"]), vae.goal(batch["p_last"])
        pairs = distance.sample_pairs(batch["episode"], batch["is_first"], dc.pairs)
        loss, m7 = distance.distance_loss(dist_net, post_feat, pairs, wc.seq_len, dc.contrastive_weight, goal_feat if dc.encoder_goals else None)
        update("dist_net", loss, "Eq. 7 distance loss")
        metrics.update(m7)
        # Eq. 4 after policy_start updates, once d gives a meaningful reward: the actor-critic in imagination, reward -d(s, g)
        if step >= tc.policy_start:
            start, index = policy.sample_starts(post, ac.starts)
            goals = policy.sample_goals(post_feat, goal_feat, index, batch["is_first"], ac.goal_mix, ac.goal_near)
            a_loss, c_loss, m4 = policy.policy_losses(wm, dist_net, actor, critic, slow_critic, models["return_norm"], start, goals, ac)
            # ours, beside Eq. 4: hindsight behaviour cloning of D_body's actions (cloning.py), in cc.bc_steps actor steps
            clone = lambda: cloning.bc_loss(actor, post_feat, goal_feat, batch["action"], final_goal, cc.bc_final)
            bc, m_bc = clone() if cc.bc else (0.0, {})
            if logged and cc.bc:  # Eq. 4's share of the actor's step against the cloning's (evaluate.gradient_share)
                m4.update(gradient_norms(actor, eq4=a_loss, bc=cc.bc * bc))
            update("actor", a_loss + cc.bc * bc, "Eq. 4 actor loss")
            update("critic", c_loss, "Eq. 4 critic loss")
            policy.ema_update(slow_critic, critic, ac.slow_critic_rate)
            for _ in range(cc.bc_steps - 1 if cc.bc else 0):  # more cloning steps on this batch, each with fresh goals
                bc, m_bc = clone()
                update("actor", cc.bc * bc, "behaviour-cloning loss")
            metrics.update(m4 | m_bc)
        if logged:
            metrics.update(step=step + 1, updates_per_s=tc.log_every / (time.time() - t0))
            metrics.update(diagnostics(models, cfgs, data, rng, device, post, post_feat, goal_feat, batch["is_first"], step + 1))
            rundir.append_jsonl(log_path, metrics)
            bar.write(log_line(metrics))
            t0 = time.time()
        if (step + 1) % tc.checkpoint_every == 0 or step + 1 == total:
            saved = keep(step + 1)
    if cc.bc and cc.bc_polish:  # ours: cloning on the final world model; the checkpoint keeps the unpolished actor to resume from
        unpolished = copy.deepcopy(actor.state_dict())
        cloning.polish(models, cfgs, data, device)
        keep(total, actor_unpolished=unpolished)
    final_report(run_dir, models, cfgs, held_out, device)
    print(f"wrote {ckpt_path}, {log_path}")
    return run_dir


def main():
    parser = argparse.ArgumentParser(description="Phase 1: pretrain the world model, goal VAE, distance and multi-task policy on D_body.", allow_abbrev=False)
    parser.add_argument("--resume", action="store_true", help="continue runs/<name>/checkpoint.pt (in a copy of a shipped agent: train on from its weights, fresh optimisers)")
    parser.add_argument("--evaluate", action="store_true", help="only the goal-reaching benchmark (evaluate.py) of the trained run")
    parser.add_argument("--allow-cpu", action="store_true", help="train --preset paper without a GPU (it is sized for one)")
    parser.add_argument("--run-dir", default=None, help="default runs/<env>_<obs>_<preset>_s<seed>")
    parser.add_argument("--export", metavar="DIR", help="write the trained run (--run-dir) as a shipped agent DIR/checkpoint.pt "
                        "(weights only, float32), then exit; e.g. agents/walker")
    parser.add_argument("--force", action="store_true", help="with --export: replace the agent already there (kept in DIR/previous_<n>/)")
    add_config_flags(parser)
    args = parser.parse_args()
    envs._check_name("body", getattr(args, "train.env") or TrainConfig.env, envs.BODIES)
    cfgs = resolve_configs(args, getattr(args, "train.preset") or "cpu")
    tc = cfgs["train"]
    run_dir = args.run_dir or default_run_dir(tc.env, tc.preset, tc.seed, cfgs["wm"].obs)
    if args.force and not args.export:
        parser.error("--force replaces an exported agent: it goes with --export DIR")
    if (args.export or args.evaluate) and (args.resume or args.allow_cpu):
        parser.error(f"--{'resume' if args.resume else 'allow-cpu'} is for training: it does nothing with --export or --evaluate")
    if args.export:
        print("wrote", checkpoint.export_agent(run_dir, args.export, args.force))
    elif args.evaluate:
        device = "cuda" if torch.cuda.is_available() else "cpu"
        run_cfgs, models, _ = load_run(run_dir, device, getattr(args, "train.env"))
        run_dir = checkpoint.work_folder(run_dir)
        torch.set_num_threads(tc.threads)
        rundir.fast_matmul()  # oneDNN where it is faster and still fp32 (rundir.py)
        asked = {k: getattr(tc, k) for k in evaluate.BENCHMARK}
        data = getattr(args, "train.data") or run_cfgs["train"].data  # the demos under the run's own data, unless --data names others
        # the run's own benchmark is goal_reaching.json; one with other settings or demos is written beside it, named by
        # them, and the kept one stays (what evaluate.py compares across seeds)
        tag = "" if data == run_cfgs["train"].data else "_data-" + os.path.normpath(data).strip(os.sep).replace(os.sep, "-")
        own = asked == {k: getattr(run_cfgs["train"], k) for k in evaluate.BENCHMARK} and not tag
        name = "goal_reaching.json" if own else "goal_reaching_" + "_".join(f"{k.removeprefix('eval_')}{v}" for k, v in asked.items()) + tag + ".json"
        run_cfgs["train"] = dataclasses.replace(run_cfgs["train"], **asked, data=data)
        report_goal_reaching(run_dir, models, run_cfgs, device, name)
    else:
        rundir.check_gpu(tc.preset, args.allow_cpu)
        train(cfgs, run_dir, args.resume)


if __name__ == "__main__":
    rundir.run_main(main, "the run folder keeps its last checkpoint: the same command with --resume goes on from it")
