"""Which task's D_body episodes does a demo folder retrieve from the agent's own experience (GIIL-retrieve's candidates)?

For every demo folder (both bodies, both cameras), the agent's D_body episodes are ranked against the demos by three
scorers of their recorded features, every goal_inference.RETRIEVE_STRIDE-th frame: App. C's OT reward (whole episode
against each demo, the best demo counting: what GIIL-retrieve ranks by), the cosine of the second halves' mean features,
and the best cosine of the last frames. A line per folder gives the first letter of the task of the top `k` episodes
(s stand, w walk, r run, e exploration; D_body has no jump).

    python probes/retrieval.py agents/walker [--top 10]
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import checkpoint  # noqa: E402
import collect  # noqa: E402
import configs  # noqa: E402
import envs  # noqa: E402
import online  # noqa: E402
from goal_inference import RETRIEVE_STRIDE  # noqa: E402


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


SCORERS = {  # name: (body_p (N, T, D), body_last (N, D), demo_p (K, M, D), demo_last (K, D)) -> (N,), higher matches better
    "OT": lambda p, last, d, d_last: online.ot_score(p, d, configs.OTConfig()),
    "mean tail": lambda p, last, d, d_last: unit(unit(p[:, p.shape[1] // 2:]).mean(1)) @ unit(unit(d[:, d.shape[1] // 2:]).mean((0, 1))),
    "last frame": lambda p, last, d, d_last: (unit(last) @ unit(d_last).T).max(1),
}


def retrieved(run, top):
    """{(demo folder, scorer): the D_body episode names of the top `top`, best first}."""
    cfgs = checkpoint.load_run(run)[0]
    names, body_p, body_last = checkpoint.body_features(cfgs, RETRIEVE_STRIDE)
    out = {}
    for body in envs.BODIES:
        for task in envs.TASKS:
            for view in envs.VIEWS:
                demos = collect.load_folder(checkpoint.demo_folder(cfgs, f"{body}_{task}", view), ("p",))
                demo_p = np.stack([d["p"][::RETRIEVE_STRIDE] for d in demos])
                demo_last = np.stack([d["p"][-1] for d in demos])
                for name, scorer in SCORERS.items():
                    score = scorer(body_p, body_last, demo_p, demo_last)
                    out[f"{body}_{task}_{view}", name] = [names[i] for i in np.argsort(-score, kind="stable")[:top]]
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("run", help="a trained run or shipped agent, e.g. agents/walker (its D_body is read)")
    parser.add_argument("--top", type=int, default=10)
    args = parser.parse_args()
    found = retrieved(args.run, args.top)
    for folder in sorted({f for f, _ in found}):
        print(folder, " | ".join(f"{name}: " + "".join(n[0] for n in found[folder, name]) for name in SCORERS))
