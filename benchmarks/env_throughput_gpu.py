"""MuJoCo Warp on a GPU: tracking-environment steps/s over the same backend's physics alone.

The gpu profile's setting: TrackingEnv with its tensors and its Warp worlds on CUDA, random actions,
domain randomisation and auto-resets on, on env_throughput.py's synthetic clip. For each world count:

  * env: `env.step` end to end (the substeps as one CUDA graph, observations, rewards, resets);
  * compiled: the same with `env.compile` (rewards, terminations and observations fused by
    torch.compile; the first steps, which compile, are not timed);
  * physics: the time spent inside `backend.step` during a second pass of the same env steps
    (synchronised around each call, so it is the physics alone; that pass is not the env figure);
  * standing: a bare WarpBackend holding the home pose on the shared model (sim/benchmark.py's raw),
    an upper bound for the physics with no falls, no per-world models and no resets.

Needs a CUDA GPU with mujoco-warp and warp-lang. Run:
    python benchmarks/env_throughput_gpu.py [--worlds 1024 4096 8192] [--steps 100]
Last line: worlds=<N> env_steps_per_s=<n> compiled_env_steps_per_s=<c> physics_steps_per_s=<m> ratio=<r>
    compiled_ratio=<c/m>  (for the gpu profile's 4096)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from env_throughput import synthetic_tracking_data  # noqa: E402

from pipeline.envs.config import EnvConfig  # noqa: E402
from pipeline.envs.tracking_env import TrackingEnv  # noqa: E402
from pipeline.robot.g1 import load_robot_config  # noqa: E402
from pipeline.sim.backend import make_backend  # noqa: E402
from pipeline.sim.model import default_state_qpos  # noqa: E402

PROFILE_WORLDS = 4096


def timed(fn, steps: int) -> float:
    torch.cuda.synchronize()
    start = time.perf_counter()
    for i in range(steps):
        fn(i)
    torch.cuda.synchronize()
    return time.perf_counter() - start


def env_seconds(num_worlds: int, steps: int, data, actions, compile_step: bool) -> tuple[float, TrackingEnv]:
    env = TrackingEnv(EnvConfig(compile=compile_step), data, num_envs=num_worlds, backend="warp", device="cuda",
                      seed=0)
    env.reset()
    timed(lambda i: env.step(actions[i % 10]), 10)  # records the CUDA graphs, loads or compiles the kernels
    return timed(lambda i: env.step(actions[i % 10]), steps), env


def measure(num_worlds: int, steps: int, data) -> dict:
    gen = torch.Generator(device="cuda").manual_seed(0)
    num_joints = load_robot_config().num_joints
    actions = [0.3 * torch.randn(num_worlds, num_joints, generator=gen, device="cuda") for _ in range(10)]
    compiled_time, _ = env_seconds(num_worlds, steps, data, actions, compile_step=True)
    env_time, env = env_seconds(num_worlds, steps, data, actions, compile_step=False)

    backend, inner_step, physics = env.backend, env.backend.step, [0.0]

    def step_and_time(ctrl):
        torch.cuda.synchronize()
        start = time.perf_counter()
        inner_step(ctrl)
        torch.cuda.synchronize()
        physics[0] += time.perf_counter() - start

    backend.step = step_and_time
    timed(lambda i: env.step(actions[i % 10]), steps)
    backend.step = inner_step

    model = backend.model
    bare = make_backend("warp", model, num_worlds)
    home = default_state_qpos(model)
    bare.set_state(np.arange(num_worlds), np.tile(home, (num_worlds, 1)), np.zeros((num_worlds, model.nv)))
    targets = torch.tensor(home[model.jnt_qposadr[model.actuator_trnid[:, 0]]], dtype=torch.float32,
                           device="cuda").expand(num_worlds, -1).contiguous()
    timed(lambda i: bare.step(targets), 10)
    standing_time = timed(lambda i: bare.step(targets), steps)
    overflow = backend.contact_overflow() or bare.contact_overflow()
    free, total = torch.cuda.mem_get_info()
    samples = steps * num_worlds
    return {"worlds": num_worlds, "env": samples / env_time, "compiled": samples / compiled_time,
            "physics": samples / physics[0],
            "standing": samples / standing_time, "overflow": overflow, "gpu_mem_gib": (total - free) / 2**30}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, nargs="+", default=[1024, PROFILE_WORLDS, 8192])
    parser.add_argument("--steps", type=int, default=100, help="timed control steps per measurement")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("env_throughput_gpu.py needs a CUDA GPU")
    data = synthetic_tracking_data()
    rows = [measure(n, args.steps, data) for n in args.worlds]
    print(f"{torch.cuda.get_device_name()}; {args.steps} timed control steps (4 substeps each) per figure; "
          f"random actions, domain randomisation and resets on")
    print(f"{'worlds':>7} {'env steps/s':>12} {'compiled':>10} {'physics':>10} {'env/physics':>11} "
          f"{'compiled/physics':>16} {'standing':>10} {'GPU GiB':>8} overflow")
    for r in rows:
        print(f"{r['worlds']:7d} {r['env']:12.0f} {r['compiled']:10.0f} {r['physics']:10.0f} "
              f"{r['env'] / r['physics']:11.3f} {r['compiled'] / r['physics']:16.3f} {r['standing']:10.0f} "
              f"{r['gpu_mem_gib']:8.1f} {r['overflow']}")
    main_row = next((r for r in rows if r["worlds"] == PROFILE_WORLDS), rows[-1])
    print(f"worlds={main_row['worlds']} env_steps_per_s={main_row['env']:.0f} "
          f"compiled_env_steps_per_s={main_row['compiled']:.0f} physics_steps_per_s={main_row['physics']:.0f} "
          f"ratio={main_row['env'] / main_row['physics']:.3f} compiled_ratio={main_row['compiled'] / main_row['physics']:.3f}")


if __name__ == "__main__":
    main()
