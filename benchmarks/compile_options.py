"""XLA compile options: compile time of a run's programs and the speed of what they compile.

halfcheetah, paper configuration. For each set of `XLA_FLAGS`, in a fresh process: `init` and
the two phases of a generation compiled side by side as the CLI does (seconds until the
phases, and until all three, are ready), then
`init` run and generations timed from its state (median of 3 after one untimed; T = 400, the
first generations' episode limit, before Q-filtering starts).

    python benchmarks/compile_options.py [--variants ...] [--out FILE] [--smoke]
"""

import argparse
import json
import os
import subprocess
import sys
import time

_AUTOTUNE_OFF = "--xla_gpu_autotune_level=0"
_PARALLEL = "--xla_gpu_force_compilation_parallelism=16"
VARIANTS = {
    "default": "",
    "autotune_off": _AUTOTUNE_OFF,
    "parallel_16": _PARALLEL,
    "autotune_off+parallel_16": f"{_AUTOTUNE_OFF} {_PARALLEL}",
}


def child() -> dict:
    """Compile and time in this process, under the XLA_FLAGS it was started with."""
    import jax

    from pgps_jax.envs import make_env
    sys.path.insert(0, os.path.dirname(__file__))
    from throughput import bench_config, compile_run  # sibling benchmark; reads --smoke itself

    config = bench_config("halfcheetah")
    env = make_env("halfcheetah")
    keys = (jax.random.PRNGKey(0), jax.random.PRNGKey(100))
    compiled, _, step_s, both_s = compile_run(config, env, *keys, vmapped=False,
                                              end_of_run=False)
    init, play, learn = (compiled[name].result() for name in ("init", "play", "learn"))
    state = init(*keys)
    state, _ = learn(*play(state))
    times = []
    for _ in range(3):
        t = time.perf_counter()
        state, metrics = learn(*play(state))
        jax.block_until_ready(metrics)
        times.append(time.perf_counter() - t)
    return {"generation_phases_compile_s": step_s, "init_and_phases_compile_s": both_s,
            "generation_ms": sorted(times)[1] * 1e3,
            "episode_limit": int(metrics["gen/episode_limit"])}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", default="benchmarks/results/compile_options.json")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child()))
        return
    import jax
    out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "variants": {}}
    for name in args.variants:
        env = {**os.environ, "XLA_FLAGS": VARIANTS[name]}
        command = [sys.executable, __file__, "--child"] + (["--smoke"] if args.smoke else [])
        result = subprocess.run(command, env=env, capture_output=True, text=True)
        row = {"xla_flags": VARIANTS[name]}
        if result.returncode == 0:
            row.update(json.loads(result.stdout.strip().splitlines()[-1]))
        else:
            row["error"] = result.stderr.strip().splitlines()[-3:]
        out["variants"][name] = row
        print(name, json.dumps(row), flush=True)
    json.dump(out, open(args.out, "w"), indent=1)


if __name__ == "__main__":
    main()
