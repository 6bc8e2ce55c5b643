"""Full tracking-environment steps/s over raw `mujoco.rollout` stepping of the same model.

Same model (the env's scene), same worlds (256), same physics threads (2). The env step includes
everything training pays for: delayed per-substep control, observations with history, both reward
groups, terminations, auto-resets with domain randomisation, random actions. The 2 cores are
shared with other work, so raw and env are measured interleaved in short alternating blocks and
each side's time is summed: load changes hit both sides alike.

Run: .venv/bin/python benchmarks/env_throughput.py   (no arguments, < 1 minute)
Last line: env_steps_per_s=<n> raw_steps_per_s=<m> ratio=<r>
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.envs.config import EnvConfig  # noqa: E402
from pipeline.envs.tracking_env import TrackingEnv  # noqa: E402
from pipeline.keyframes.tracking_data import TrackingData  # noqa: E402
from pipeline.motion.motion import RobotKinematics  # noqa: E402

NUM_WORLDS, THREADS, BLOCK, ROUNDS, WARMUP = 256, 2, 10, 8, 5


def synthetic_tracking_data(seconds: float = 4.0, num_samples: int = 16) -> TrackingData:
    """A standing clip with swinging arms and a slight squat: keyframes every second."""
    kin = RobotKinematics()
    cfg = kin.config
    frames = int(seconds * 50) + 1
    t = np.arange(frames) / 50.0
    joints = np.tile(cfg.default_joint_pos, (frames, 1))
    for name, amp in (("left_shoulder_pitch_joint", 0.4), ("right_shoulder_pitch_joint", -0.4)):
        joints[:, cfg.joint_names.index(name)] += amp * np.sin(2 * np.pi * 0.5 * t)
    root = np.tile([0.0, 0.0, cfg.default_root_height], (frames, 1))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (frames, 1))
    motion = kin.motion(50.0, root, quat, joints, name="bench")
    keyframes = np.arange(50, frames, 50)
    k = len(keyframes)
    psi = np.linspace(0.0, 0.2, num_samples)
    offsets = np.zeros((num_samples, k, 3))
    offsets[:, :, 0] = psi[:, None] * np.linspace(0.0, 1.0, k)[None]
    return TrackingData(task="bench", motion=motion, keyframe_frames=keyframes,
                        keyframe_labels=("",) * k, sparse_scale=np.ones(k), edited=np.ones(k, bool),
                        psi=psi, keyframe_offsets=offsets)


class RawRollout:
    """Bare rollout of the env's model: one call of `decimation` substeps per control step."""

    def __init__(self, model: mujoco.MjModel, qpos: np.ndarray, ctrl: np.ndarray, decimation: int):
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
        data = mujoco.MjData(model)
        data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        row = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, row, spec)
        self.model, self.decimation = model, decimation
        self.state0 = np.tile(row, (NUM_WORLDS, 1))
        self.ctrl = np.tile(ctrl, (NUM_WORLDS, decimation, 1))
        self.states = np.empty((NUM_WORLDS, decimation, row.size))
        self.sensors = np.empty((NUM_WORLDS, decimation, model.nsensordata))
        self.models = [model] * NUM_WORLDS
        self.datas = [mujoco.MjData(model) for _ in range(THREADS)]
        self.pool = mj_rollout.Rollout(nthread=THREADS)

    def run(self, steps: int) -> float:
        start = time.perf_counter()
        for _ in range(steps):
            self.pool.rollout(self.models, self.datas, self.state0, self.ctrl, skip_checks=True,
                              nstep=self.decimation, control_spec=mujoco.mjtState.mjSTATE_CTRL.value,
                              state=self.states, sensordata=self.sensors)
            np.copyto(self.state0, self.states[:, -1])
        return time.perf_counter() - start


def main() -> None:
    data = synthetic_tracking_data()
    env = TrackingEnv(EnvConfig(), data, num_envs=NUM_WORLDS, seed=0)
    model = env.backend.model
    home = np.concatenate([[0.0, 0.0, env.robot.default_root_height, 1.0, 0.0, 0.0, 0.0], env.robot.default_joint_pos])
    raw = RawRollout(model, home, env.robot.default_joint_pos, env.decimation)
    gen = torch.Generator().manual_seed(0)
    actions = [0.3 * torch.randn(NUM_WORLDS, env.action_dim, generator=gen) for _ in range(BLOCK)]

    def run_env(steps: int) -> tuple[float, int]:
        resets = 0
        start = time.perf_counter()
        for i in range(steps):
            _, _, terminated, truncated, _ = env.step(actions[i % BLOCK])
            resets += int((terminated | truncated).sum())
        return time.perf_counter() - start, resets

    env.reset()
    run_env(WARMUP)
    raw.run(WARMUP)
    env_time = raw_time = 0.0
    resets = 0
    for _ in range(ROUNDS):
        t, r = run_env(BLOCK)
        env_time, resets = env_time + t, resets + r
        raw_time += raw.run(BLOCK)
    steps = ROUNDS * BLOCK * NUM_WORLDS
    env_rate, raw_rate = steps / env_time, steps / raw_time
    print(f"worlds={NUM_WORLDS} threads={THREADS} torch_threads={torch.get_num_threads()} "
          f"control_steps={ROUNDS * BLOCK} resets={resets} (interleaved blocks of {BLOCK})")
    print(f"env_steps_per_s={env_rate:.0f} raw_steps_per_s={raw_rate:.0f} ratio={env_rate / raw_rate:.3f}")


if __name__ == "__main__":
    main()
