"""Full tracking-environment steps/s over raw `mujoco.rollout` stepping of the same model.

Same model (the env's scene), same worlds (256), same physics threads (2). The env step includes
everything training pays for: delayed per-substep control, observations with history, both reward
groups, terminations, auto-resets with domain randomisation, random actions.

"raw" replays through bare `mujoco.rollout` exactly the physics calls the env made (its per-world
randomised models, start states and controls), so the ratio is the env's own cost and not a
difference in what is simulated: random actions topple robots (more contacts) and per-world model
copies cost cache, which a robot standing on one shared model does not pay. That second figure
(sim/benchmark.py's definition) is printed too. The 2 cores are shared with other work, so all
sides are measured interleaved in short alternating blocks and each side's time summed.

It also counts the torch operators one env step dispatches outside the physics. On a GPU each one
that is not a view is a kernel launch with its host cost, and that count, not the worlds, sets the
env's own time there (RESULTS.md, *GPU*).

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
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.envs.config import EnvConfig  # noqa: E402
from pipeline.envs.tracking_env import TrackingEnv  # noqa: E402
from pipeline.keyframes.tracking_data import TrackingData  # noqa: E402
from pipeline.motion.motion import RobotKinematics  # noqa: E402

NUM_WORLDS, THREADS, BLOCK, ROUNDS, WARMUP = 256, 2, 10, 6, 5


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


class RecordingPool:
    """Stands between the CPU backend and its rollout pool: records each call's inputs (the
    per-world models, start states and per-substep controls) so the raw side can replay exactly
    the physics the env asked for."""

    def __init__(self, pool):
        self.pool, self.calls = pool, []

    def rollout(self, models, datas, state0, ctrl, **kwargs):
        self.calls.append((list(models), state0.copy(), ctrl.copy(), kwargs["nstep"]))
        return self.pool.rollout(models, datas, state0, ctrl, **kwargs)


class RawRollout:
    """Bare `mujoco.rollout` on its own pool of THREADS threads and preallocated outputs."""

    def __init__(self, model: mujoco.MjModel, decimation: int):
        nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS.value)
        self.model, self.decimation = model, decimation
        self.states = np.empty((NUM_WORLDS, decimation, nstate))
        self.sensors = np.empty((NUM_WORLDS, decimation, model.nsensordata))
        self.datas = [mujoco.MjData(model) for _ in range(THREADS)]
        self.pool = mj_rollout.Rollout(nthread=THREADS)

    def _call(self, models, state0, ctrl) -> None:
        self.pool.rollout(models, self.datas, state0, ctrl, skip_checks=True, nstep=self.decimation,
                          control_spec=mujoco.mjtState.mjSTATE_CTRL.value, state=self.states,
                          sensordata=self.sensors)

    def replay(self, calls) -> float:
        """The env's own physics calls (same models, states, controls), timed without the env."""
        start = time.perf_counter()
        for models, state0, ctrl, _ in calls:
            self._call(models, state0, ctrl)
        return time.perf_counter() - start

    def standing(self, state0: np.ndarray, ctrl: np.ndarray, steps: int) -> float:
        """Closed-loop stepping of the one shared model holding the home pose (sim/benchmark.py's raw)."""
        models = [self.model] * NUM_WORLDS
        start = time.perf_counter()
        for _ in range(steps):
            self._call(models, state0, ctrl)
            np.copyto(state0, self.states[:, -1])
        return time.perf_counter() - start


def home_state(model: mujoco.MjModel, qpos: np.ndarray, targets: np.ndarray, decimation: int):
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    row = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, row, spec)
    return np.tile(row, (NUM_WORLDS, 1)), np.tile(targets, (NUM_WORLDS, decimation, 1))


class OperatorCount(TorchDispatchMode):
    """Counts the aten operators dispatched while `counting` is on, by name."""

    VIEWS = {"aten.slice", "aten.select", "aten.view", "aten.unsqueeze", "aten.squeeze", "aten.unbind",
             "aten.expand", "aten.transpose", "aten.permute", "aten.t", "aten.alias", "aten._unsafe_view",
             "aten.as_strided", "aten.detach", "aten.split", "aten.split_with_sizes", "aten.chunk"}

    def __init__(self):
        super().__init__()
        self.counts, self.counting = {}, True

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if self.counting:
            name = str(func.overloadpacket)
            self.counts[name] = self.counts.get(name, 0) + 1
        return func(*args, **(kwargs or {}))

    def kernels(self) -> int:
        return sum(n for name, n in self.counts.items() if name not in self.VIEWS)


def operators_per_step(env, actions) -> tuple[float, float]:
    """(operators, non-view operators) per env step, the backend's own stepping left out."""
    counter, inner = OperatorCount(), env.backend.step

    def physics_uncounted(*args, **kwargs):
        counter.counting = False
        try:
            return inner(*args, **kwargs)
        finally:
            counter.counting = True

    env.backend.step = physics_uncounted
    try:
        with counter:
            for action in actions:
                env.step(action)
    finally:
        env.backend.step = inner
    return sum(counter.counts.values()) / len(actions), counter.kernels() / len(actions)


def main() -> None:
    data = synthetic_tracking_data()
    env = TrackingEnv(EnvConfig(), data, num_envs=NUM_WORLDS, seed=0)
    recorder = RecordingPool(env.backend._pool)  # the CPU backend's pool (private: benchmark only)
    env.backend._pool = recorder
    model, robot = env.backend.model, env.robot
    raw = RawRollout(model, env.decimation)
    home = np.concatenate([[0.0, 0.0, robot.default_root_height, 1.0, 0.0, 0.0, 0.0], robot.default_joint_pos])
    stand_state, stand_ctrl = home_state(model, home, robot.default_joint_pos, env.decimation)
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
    raw.replay(recorder.calls)
    raw.standing(stand_state, stand_ctrl, WARMUP)
    env_time = replay_time = standing_time = 0.0
    resets = 0
    for _ in range(ROUNDS):  # alternate short blocks so shared-core load hits every side alike
        recorder.calls.clear()
        t, r = run_env(BLOCK)
        env_time, resets = env_time + t, resets + r
        replay_time += raw.replay(recorder.calls)
        standing_time += raw.standing(stand_state, stand_ctrl, BLOCK)
    steps = ROUNDS * BLOCK * NUM_WORLDS
    env_rate, raw_rate, standing_rate = steps / env_time, steps / replay_time, steps / standing_time
    print(f"worlds={NUM_WORLDS} threads={THREADS} torch_threads(env)={env.cfg.torch_threads} "
          f"control_steps={ROUNDS * BLOCK} resets={resets} (interleaved blocks of {BLOCK}; random actions, "
          f"domain randomisation on)")
    print(f"raw is the env's own physics replayed (same per-world models, states, controls); for reference, "
          f"raw standing on the shared model: {standing_rate:.0f} steps/s (env/standing={env_rate / standing_rate:.3f})")
    operators, kernels = operators_per_step(env, actions)
    print(f"torch operators per env step outside the physics: {operators:.0f} ({kernels:.0f} not views: "
          f"kernel launches on a GPU)")
    print(f"env_steps_per_s={env_rate:.0f} raw_steps_per_s={raw_rate:.0f} ratio={env_rate / raw_rate:.3f}")


if __name__ == "__main__":
    main()
