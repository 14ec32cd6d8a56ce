"""Legal returns on measured shots: the held-out split of Google DeepMind's post-hit ball states
(D'Ambrosio et al., ICRA 2025, arXiv:2408.03906; CC-BY-4.0; :mod:`ttsim_jax.data.post_hit_states`)
against the synthetic bank, per shot type, for the "intercept" task's scripted tracker alone (action
0), the bundled policy and any other policies given (e.g. one trained on the measured train split).

One episode per environment, mean actions; shots the opponent missed are left out of the rates.
The synthetic bank is drawn with another seed than the one the policies trained on (``--bank-seed``),
so that both columns are held out.

    TTSIM_REAL_DATA=../shared/data/real python benchmarks/real_shots.py --real ../shared/data/real/deepmind_states \
        --episodes 2048 [--policy NAME=runs/ppo_real/checkpoint.msgpack ...] --out benchmarks/results/real_shots.json

(``TTSIM_REAL_DATA`` for a policy trained on ``return_ball_real``, whose task names the folder by it.)
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp


def policies(args):
    """[(name, checkpoint path)]: the bundled policy first, then ``--policy NAME=PATH``."""
    from ttsim_jax.rl.checkpoint import BUNDLED_POLICY

    out = [("bundled policy", Path(BUNDLED_POLICY))]
    for item in args.policy:
        name, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"--policy {item!r}: give NAME=PATH")
        out.append((name, Path(path)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, default=Path("../shared/data/real/deepmind_states"),
                    help="folder of DeepMind's serves.json and rallies.json (default ../shared/data/real/deepmind_states)")
    ap.add_argument("--episodes", type=int, default=2048, help="episodes per bank and player (default 2048)")
    ap.add_argument("--policy", action="append", default=[], metavar="NAME=CKPT",
                    help="a further policy to play (a 'ttsim train ppo' checkpoint); repeatable")
    ap.add_argument("--bank-seed", type=int, default=1, help="seed of the synthetic bank played (default 1; the "
                    "bundled task trains on seed 0)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the episodes (default 0)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/real_shots.json"), help="JSON to write")
    args = ap.parse_args(argv)

    from ttsim_jax.rl import ppo
    from ttsim_jax.rl.checkpoint import read_checkpoint, restore_runner
    from ttsim_jax.rl.config import parse_ppo_config
    from ttsim_jax.rl.training import build

    from ttsim_jax.env.config import ShotsConfig

    # the default task's synthetic shots, whichever task a policy trained on
    banks = {"synthetic (held-out seed)": dict(source="sampled", seed=args.bank_seed, types=list(ShotsConfig().types)),
             "measured (held-out split)": dict(source="measured", measured=str(args.real.resolve()), split="test",
                                               types=["serve", "rally"])}
    result = dict(args={k: str(v) for k, v in vars(args).items()}, load_before=os.getloadavg(), rows=[])
    key = jax.random.PRNGKey(args.seed)
    for name, path in [("scripted tracker (action 0)", None)] + policies(args):
        payload = read_checkpoint(path or policies(args)[0][1])  # the tracker plays the bundled task's shapes
        config = parse_ppo_config(payload["config"], payload["config_source"])
        train_env, train_params = build(config, config.ppo.num_envs)
        runner = restore_runner(jax.eval_shape(lambda k: ppo.init_runner(train_env, train_params, config, k),
                                               jax.random.PRNGKey(0)), payload, path) if path else None
        for bank, shots in banks.items():
            env, params = build(config, args.episodes, shots=shots)
            t0 = time.perf_counter()
            if runner is None:
                play = jax.jit(ppo.episode_runner(env, lambda a, obs: jnp.zeros((obs.shape[0], env.action_dim))))
                out = play(None, params, key)
            else:
                out = ppo.make_evaluate(env, config)(runner.params, runner.stats, params, key)
            s = ppo.summarise(out, env.config.shots.types)
            row = dict(player=name, bank=bank, seconds=time.perf_counter() - t0, **s)
            result["rows"].append(row)
            print(f"{name:32s} {bank:28s} legal {s['legal_rate']:.3f} ({s['episodes']}); " + ", ".join(
                f"{k} {v['legal_rate']:.3f} ({v['episodes']})" for k, v in s["by_type"].items() if v["episodes"]),
                flush=True)
    result["load_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
