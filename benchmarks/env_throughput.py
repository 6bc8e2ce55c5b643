"""Full tracking-environment steps/s over raw `mujoco.rollout` stepping of the same model, and the
physics preset's speed-up over the baseline physics (robots/g1/robot.yaml `physics`, docs/physics.md).

Same model (the env's scene), same worlds (256), same physics threads (2). The env step includes
everything training pays for: delayed per-substep control, observations with history, both reward
groups, terminations, auto-resets with domain randomisation, random actions.

"raw" replays through bare `mujoco.rollout` exactly the physics calls the env made (its per-world
randomised models, start states and controls), so the ratio is the env's own cost and not a
difference in what is simulated: random actions topple robots (more contacts) and per-world model
copies cost cache, which a robot standing on one shared model does not pay. That second figure
(sim/benchmark.py's definition) is printed too. The 2 cores are shared with other work, so all
sides are measured interleaved in short alternating blocks and each side's time summed.

Two envs run side by side, the same actions and seeds: one on the physics preset `--physics` (default
"fast") and one on "baseline", the settings every earlier figure was measured with; their env steps/s
give speedup_vs_baseline. For each, where a substep goes, at the states the env's physics calls started
from: CPU µs of one mj_step, with and without contacts, and the contacts and constraint rows (nefc).

It also counts the torch operators one env step dispatches outside the physics. On a GPU each one
that is not a view is a kernel launch with its host cost, and that count, not the worlds, sets the
env's own time there (RESULTS.md, *GPU*).

Run: .venv/bin/python benchmarks/env_throughput.py [--physics fast]   (about a minute)
Last line: env_steps_per_s=<n> raw_steps_per_s=<m> ratio=<r> speedup_vs_baseline=<x>   (n, m, r: the --physics preset)
"""

from __future__ import annotations

import argparse
import dataclasses
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


def substep_cost(model: mujoco.MjModel, calls, max_states: int = 512) -> dict[str, float]:
    """Where one substep goes, at the states the recorded physics calls started from (at most
    `max_states`, spread over the calls), each on its world's own model: CPU µs of one mj_step (this
    thread's time, so other load on the cores barely moves it), the same with contacts switched off (the
    rest is what contacts cost: collision, their constraint rows, the solver), contacts and constraint rows."""
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
    data = mujoco.MjData(model)
    picks = [(models[w], state0[w], ctrl[w, 0]) for models, state0, ctrl, _ in calls for w in range(len(models))]
    picks = picks[:: max(1, len(picks) // max_states)]
    ncon = nefc = 0
    seconds = {"with": 0.0, "without": 0.0}
    for world_model, state, ctrl in picks:
        for contacts in ("with", "without"):
            flags = world_model.opt.disableflags
            if contacts == "without":
                world_model.opt.disableflags = flags | mujoco.mjtDisableBit.mjDSBL_CONTACT.value
            mujoco.mj_setState(world_model, data, state, spec)
            data.ctrl[:] = ctrl
            start = time.thread_time()
            mujoco.mj_step(world_model, data)
            seconds[contacts] += time.thread_time() - start
            world_model.opt.disableflags = flags
            if contacts == "with":
                ncon, nefc = ncon + data.ncon, nefc + data.nefc
    n = len(picks)
    return {"us_step": 1e6 * seconds["with"] / n, "us_step_no_contacts": 1e6 * seconds["without"] / n,
            "ncon": ncon / n, "nefc": nefc / n}


class PresetRun:
    """One env on one physics preset, with its recorder and raw replayer; timings summed over blocks."""

    def __init__(self, physics: str, data: TrackingData):
        torch.manual_seed(0)  # the env draws its randomisation from torch's global RNG: same draws for each preset
        self.name = physics
        self.env = TrackingEnv(dataclasses.replace(EnvConfig(), physics=physics), data, num_envs=NUM_WORLDS, seed=0)
        self.recorder = RecordingPool(self.env.backend._pool)  # the CPU backend's pool (private: benchmark only)
        self.env.backend._pool = self.recorder
        self.model, robot = self.env.backend.model, self.env.robot
        self.raw = RawRollout(self.model, self.env.decimation)
        home = np.concatenate([[0.0, 0.0, robot.default_root_height, 1.0, 0.0, 0.0, 0.0], robot.default_joint_pos])
        self.stand_state, self.stand_ctrl = home_state(self.model, home, robot.default_joint_pos, self.env.decimation)
        self.env_time = self.replay_time = self.standing_time = 0.0
        self.resets, self.calls = 0, []
        self.env.reset()

    def run_env(self, actions, steps: int) -> tuple[float, int]:
        resets = 0
        start = time.perf_counter()
        for i in range(steps):
            _, _, terminated, truncated, _ = self.env.step(actions[i % len(actions)])
            resets += int((terminated | truncated).sum())
        return time.perf_counter() - start, resets

    def warm_up(self, actions) -> None:
        self.run_env(actions, WARMUP)
        self.raw.replay(self.recorder.calls)
        self.raw.standing(self.stand_state, self.stand_ctrl, WARMUP)

    def block(self, actions) -> None:
        self.recorder.calls.clear()
        t, r = self.run_env(actions, BLOCK)
        self.env_time, self.resets = self.env_time + t, self.resets + r
        self.replay_time += self.raw.replay(self.recorder.calls)
        self.standing_time += self.raw.standing(self.stand_state, self.stand_ctrl, BLOCK)
        self.calls.extend(self.recorder.calls[:: max(1, BLOCK // 2)])  # a few per block for the contact counts

    def report(self, steps: int) -> dict:
        return {"env": steps / self.env_time, "raw": steps / self.replay_time, "standing": steps / self.standing_time,
                **substep_cost(self.model, self.calls)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--physics", default="fast",
                        help="physics preset to measure (robots/g1/robot.yaml physics.presets), against baseline")
    args = parser.parse_args()
    data = synthetic_tracking_data()
    runs = {"baseline": PresetRun("baseline", data)}
    if args.physics != "baseline":
        runs[args.physics] = PresetRun(args.physics, data)
    measured = runs[args.physics]
    gen = torch.Generator().manual_seed(0)
    actions = [0.3 * torch.randn(NUM_WORLDS, measured.env.action_dim, generator=gen) for _ in range(BLOCK)]
    for run in runs.values():
        run.warm_up(actions)
    for _ in range(ROUNDS):  # alternate short blocks so shared-core load hits every side alike
        for run in runs.values():
            run.block(actions)
    steps = ROUNDS * BLOCK * NUM_WORLDS
    reports = {name: run.report(steps) for name, run in runs.items()}
    env = measured.env
    print(f"worlds={NUM_WORLDS} threads={THREADS} torch_threads(env)={env.cfg.torch_threads} "
          f"control_steps={ROUNDS * BLOCK} resets={measured.resets} (interleaved blocks of {BLOCK}; random actions, "
          f"domain randomisation on)")
    for name, rep in reports.items():
        phys = runs[name].env.robot.physics(name)
        print(f"physics {name}: timestep {phys.timestep * 1e3:g} ms x {runs[name].env.decimation} substeps, "
              f"foot capsules {list(phys.foot_capsules)}, collisions {phys.collisions}: "
              f"mj_step {rep['us_step']:.0f} us CPU ({rep['us_step_no_contacts']:.0f} without contacts), "
              f"{rep['ncon']:.1f} contacts and {rep['nefc']:.1f} constraint rows per substep; "
              f"env {rep['env']:.0f} steps/s, raw {rep['raw']:.0f}, "
              f"raw standing on the shared model {rep['standing']:.0f} (env/standing={rep['env'] / rep['standing']:.3f})")
    print("raw is the env's own physics replayed (same per-world models, states, controls)")
    operators, kernels = operators_per_step(env, actions)
    print(f"torch operators per env step outside the physics: {operators:.0f} ({kernels:.0f} not views: "
          f"kernel launches on a GPU)")
    rep, base = reports[args.physics], reports["baseline"]
    print(f"env_steps_per_s={rep['env']:.0f} raw_steps_per_s={rep['raw']:.0f} ratio={rep['env'] / rep['raw']:.3f} "
          f"speedup_vs_baseline={rep['env'] / base['env']:.2f}")


if __name__ == "__main__":
    main()
