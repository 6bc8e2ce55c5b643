"""`RobotEnv`: what every G1 environment of the pipeline shares, whatever its task.

The robot and its physics backend, the domain randomisation, the control delay, the pushes, the
proprioceptive observation, the regularising penalties, the fall checks, the penalty curriculum,
the CPU thread scope and the resume machinery. A task env (`TrackingEnv`, `BalanceEnv`) subclasses
it and adds its own reference, rewards, observations and resets; neither copies the other.

Trainers read it through `pipeline.envs.spec` (`spec()`, `update_curriculum`, `curriculum_stats`, ...).

A subclass provides:
  `_dense_term_names()`   the dense group's terms in the order its score stacks them;
  `_reset_worlds(ids)`    start new episodes in worlds `ids`;
  `_step(action, phase_rate_offset)` one control step of every world;
  `_STATE_BUFFERS`        its per-world tensors (added to `RobotEnv.SHARED_BUFFERS`) for resume;
  `_task_state()` / `_load_task_state(state)` whatever else decides its future steps.
"""

from __future__ import annotations

import contextlib

import mujoco
import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs import rewards as R
from pipeline.envs.falls import fall_flags
from pipeline.envs.randomization import DomainRandomizer
from pipeline.envs.scene import make_physics
from pipeline.envs.spec import EnvSpec
from pipeline.robot.g1 import joint_limits, load_robot_config

# The regularisers every task pays in its dense group, in the order `penalty_terms` returns them.
PENALTY_TERMS = ("feet_orientation", "joint_acc", "joint_vel", "action_rate", "smoothness", "torques", "torque_limits",
                 "joint_pos_limits", "joint_vel_limits")


def proprio_dim(num_joints: int) -> int:
    """One step of proprioception: base angular velocity, projected gravity, joint positions (from the
    default pose), joint velocities and the last action — what `adamimic deploy` measures on the robot."""
    return 3 + 3 + 3 * num_joints


def proprio_frame(qpos, qvel, gravity, prev_action, default_joint_pos) -> torch.Tensor:
    """One step of proprioception (`proprio_dim`), in the order the exported layouts name it."""
    return torch.cat([qvel[:, 3:6], gravity, qpos[:, 7:] - default_joint_pos, qvel[:, 6:], prev_action], dim=-1)


class RobotEnv:
    SHARED_BUFFERS = ("episode_step", "prev_action", "prev_action2", "prev_joint_vel", "obs_history", "privileged",
                      "target_history", "delay_lag", "delay_substeps", "push_timer")
    _STATE_BUFFERS: tuple[str, ...] = SHARED_BUFFERS

    def __init__(self, cfg, model: mujoco.MjModel, *, num_envs: int, backend, device, source: str):
        self.cfg = cfg
        self.robot = load_robot_config()
        self.device = torch.device(device)
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs <= 0:
            raise PipelineInputError(source, "num_envs", f"must be a positive integer, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.backend = make_physics(backend, model, self.num_envs, cfg.physics_threads, device, source)
        self.model = self.backend.model  # the compiled scene with the backend's sensors
        self.decimation = int(self.backend.decimation)
        self.control_dt = self.robot.control_dt
        self.sim_dt = self.control_dt / self.decimation
        self.num_joints = self.robot.num_joints
        self.action_dim = self.num_joints
        self.delay_scale = self.push_scale = 1.0  # curricula may scale the randomised delays and the pushes

    # ------------------------------------------------------------------------------------ set-up
    def _tensor(self, x, dtype=torch.float32):
        return torch.as_tensor(np.array(x), dtype=dtype, device=self.device)  # a copy: dataset arrays are read-only

    def _precompute_robot(self) -> None:
        """Joint layout, limits, gains and the feet: what the penalties, actions and falls read."""
        cfg, rc = self.cfg.rewards, self.robot
        # Steps read joints as the contiguous qpos[7:] / qvel[6:] slices (no gather): check the layout.
        qadr = [self.model.jnt_qposadr[self.model.joint(n).id] for n in rc.joint_names]
        if qadr != list(range(7, 7 + rc.num_joints)) or self.model.nq != 7 + rc.num_joints:
            raise PipelineInputError("robot", "joints", "the model's qpos is not free joint + the 27 joints in action order")
        names = rc.tracked_body_names
        unknown = [b for b in cfg.feet if b not in names]
        if unknown:
            raise PipelineInputError("env", "rewards.feet", f"unknown tracked bodies {unknown}")
        self.feet_idx = torch.as_tensor([names.index(f) for f in cfg.feet], device=self.device)
        self.default_joint_pos = self._tensor(rc.default_joint_pos)
        self.action_scale = self._tensor(rc.action_scale)
        lim = joint_limits(self.model, rc.joint_names)
        self.joint_pos_low, self.joint_pos_high = self._tensor(lim[:, 0]), self._tensor(lim[:, 1])
        lo, hi = R.soft_range(lim[:, 0], lim[:, 1], cfg.soft_joint_pos_limit)
        self.soft_pos_low, self.soft_pos_high = self._tensor(lo), self._tensor(hi)
        self.soft_vel_limit = self._tensor(rc.velocity_limit * cfg.soft_joint_vel_limit)
        self.soft_torque_limit = self._tensor(rc.effort_limit * cfg.soft_torque_limit)

    def _start_randomizer(self) -> None:
        self.randomizer = DomainRandomizer(self.cfg.randomization, self.model, self.backend)

    def _alloc_shared_state(self, frame_dim: int, privileged_dim: int) -> None:
        n, j, dev = self.num_envs, self.num_joints, self.device
        z = lambda *shape: torch.zeros(*shape, device=dev)  # noqa: E731
        self.episode_step = torch.zeros(n, dtype=torch.long, device=dev)
        self.prev_action, self.prev_action2 = z(n, j), z(n, j)
        self.prev_joint_vel = z(n, j)
        self.obs_history = z(n, self.cfg.observations.history, frame_dim)
        self.privileged = z(n, privileged_dim)
        self.arange = torch.arange(n, device=dev)
        # Control delay: ring buffer of joint targets; lag[i, s] = control steps back used at substep s.
        max_delay = int(round(self.randomizer.max_delay_s / self.sim_dt))
        self.target_slots = max_delay // self.decimation + 2
        self.target_history = z(self.target_slots, n, j)
        self.target_ptr = 0
        self.delay_lag = torch.zeros(n, self.decimation, dtype=torch.long, device=dev)
        self.delay_substeps = torch.zeros(n, dtype=torch.long, device=dev)
        self.push_timer = z(n)

    # ------------------------------------------------------------------------------------ API
    def reset(self) -> dict[str, torch.Tensor]:
        with self._torch_threads():
            self._reset_worlds(self.arange)
            return self._obs_dict()

    def step(self, action: torch.Tensor, phase_rate_offset: torch.Tensor | None = None):
        """One control step of every world: (obs, {"sparse", "dense"} rewards, terminated, truncated, info);
        see docs/INTERFACES.md."""
        with self._torch_threads():
            return self._step(action, phase_rate_offset)

    @contextlib.contextmanager
    def _torch_threads(self):
        """Runs the env's torch work on `cfg.torch_threads` threads and restores the caller's count.
        Per-step tensors are small; torch's OpenMP workers beside the physics threads on 2 cores
        cost ~40 % of the env's throughput (benchmarks/env_throughput.py), and a scoped switch
        (sub-microsecond) leaves the trainer's own setting alone."""
        wanted = self.cfg.torch_threads
        if wanted <= 0 or self.device.type != "cpu":
            yield
            return
        previous = torch.get_num_threads()
        if previous != wanted:
            torch.set_num_threads(wanted)
        try:
            yield
        finally:
            if previous != wanted:
                torch.set_num_threads(previous)

    # ------------------------------------------------------------------ the trainer's contract (envs/spec.py)
    def spec(self) -> EnvSpec:
        return EnvSpec(num_envs=self.num_envs, action_dim=self.action_dim, actor_obs_dim=self.actor_obs_dim,
                       critic_obs_dim=self.critic_obs_dim, joint_names=tuple(self.robot.joint_names),
                       obs_layout=self.obs_layout(), phase_rate=self._phase_rate(),
                       action_offset=self._action_offset_kind(), push_prior=self._push_prior())

    def _phase_rate(self) -> float | None:
        return None

    def _action_offset_kind(self) -> str:
        return "default"

    def _push_prior(self) -> bool:
        return False

    def update_curriculum(self, progress: float) -> float:
        """Once per training iteration: the penalty curriculum; a subclass adds its own."""
        self._update_penalty_curriculum()
        return progress

    def curriculum_stats(self) -> dict:
        return {"penalty_scale": float(self.penalty_scale)}

    def pinned_observation_stats(self) -> list[tuple[list[int], float, float]]:
        return []

    def _obs_dict(self) -> dict[str, torch.Tensor]:
        actor = self.obs_history.reshape(self.num_envs, -1)
        return {"actor": actor, "critic": torch.cat([actor, self.privileged], dim=-1)}

    # ------------------------------------------------------------------------------------ penalty curriculum
    @property
    def penalty_scale(self) -> float:
        """Factor on the dense penalties' weights (the penalty curriculum's; 1: the configured weights)."""
        return self._penalty_scale

    @penalty_scale.setter
    def penalty_scale(self, value: float) -> None:
        self._penalty_scale = value = float(value)
        w, dt = self.cfg.rewards.weights, self.control_dt if self.cfg.rewards.scale_by_dt else 1.0
        weights = [getattr(w, name) * (value if getattr(w, name) < 0 else 1.0) * dt for name in self._dense_term_names()]
        self._dense_weights = torch.tensor(weights, device=self.device)

    def _dense_term_names(self) -> tuple[str, ...]:
        raise NotImplementedError

    def _update_penalty_curriculum(self) -> None:
        """The dense penalty scale from the share of episodes that fell since the last call (`PenaltyCurriculum`)."""
        pc = self.cfg.rewards.penalty_curriculum
        if pc.enabled:
            if not self.penalty_curriculum_started:
                self.penalty_scale, self.penalty_curriculum_started = pc.initial, True
            elif int(self.episodes_finished) > 0:
                fall_rate = int(self.episodes_terminated) / int(self.episodes_finished)
                self.penalty_scale = pc.next_scale(self.penalty_scale, fall_rate)
        self._clear_episode_counts()

    def _clear_episode_counts(self) -> None:
        # kept as device tensors so counting them costs no host sync per step
        self.episodes_finished = torch.zeros((), dtype=torch.long, device=self.device)
        self.episodes_terminated = torch.zeros((), dtype=torch.long, device=self.device)

    def _count_episodes(self, done: torch.Tensor, terminated: torch.Tensor) -> None:
        self.episodes_finished = self.episodes_finished + done.sum()
        self.episodes_terminated = self.episodes_terminated + terminated.sum()

    # ------------------------------------------------------------------------------------ pure per-step pieces
    def _proprio(self, qpos, qvel, gravity, prev_action) -> torch.Tensor:
        return proprio_frame(qpos, qvel, gravity, prev_action, self.default_joint_pos)

    def _penalty_terms(self, joint_pos, joint_vel, joint_acc, torque, feet_quat, foot_contact, action) -> dict:
        """The regularisers of `PENALTY_TERMS` (each weighted by a negative `rewards.weights` entry)."""
        return {
            "feet_orientation": R.feet_orientation(feet_quat, foot_contact.to(torch.float32)),
            "joint_acc": R.sum_sq(joint_acc),
            "joint_vel": R.sum_sq(joint_vel),
            "action_rate": R.sum_sq(action - self.prev_action),
            "smoothness": R.smoothness(action, self.prev_action, self.prev_action2),
            "torques": R.sum_sq(torque),
            "torque_limits": R.over_limit(torque, self.soft_torque_limit),
            "joint_pos_limits": R.outside_range(joint_pos, self.soft_pos_low, self.soft_pos_high),
            "joint_vel_limits": R.over_limit(joint_vel, self.soft_vel_limit),
        }

    @staticmethod
    def _falls(tilt_xy, base_height, max_tilt, min_height):
        """(by_tilt, by_height) of `falls.fall_flags`, the one definition every judge uses."""
        return fall_flags(tilt_xy, base_height, max_tilt, min_height)

    # ------------------------------------------------------------------------------------ actuation
    def _delayed_control(self, target: torch.Tensor) -> torch.Tensor:
        if not self.randomizer.delay_enabled:
            return target
        self.target_ptr = (self.target_ptr + 1) % self.target_slots
        self.target_history[self.target_ptr] = target
        slots = (self.target_ptr - self.delay_lag) % self.target_slots  # (N, decimation)
        return self.target_history[slots, self.arange[:, None]]  # (N, decimation, J)

    def _apply_pushes(self) -> None:
        push = self.cfg.randomization.push
        if not (self.cfg.randomization.enabled and push.enabled):
            return
        self.push_timer -= self.control_dt
        due = self.push_timer <= 0
        if not bool(due.any()):
            return
        ids = due.nonzero().squeeze(-1)
        qvel = self.backend.qvel[ids].clone()
        kick = torch.rand(ids.numel(), 3, device=self.device) * 2 - 1
        if self.push_scale != 1.0:  # a curriculum's share of the configured kicks
            kick = kick * self.push_scale
        qvel[:, 0:2] += push.max_vel_xy * kick[:, :2]
        qvel[:, 5] += push.max_vel_yaw * kick[:, 2]
        self.backend.set_state(ids, self.backend.qpos[ids].clone(), qvel, forward=False)  # the step's views: after it
        self.push_timer[ids] = self._push_interval(ids.numel())

    def _push_interval(self, n: int) -> torch.Tensor:
        lo, hi = self.cfg.randomization.push.interval_s
        return lo + (hi - lo) * torch.rand(n, device=self.device)

    def _randomize_worlds(self, ids: torch.Tensor, initial_target: torch.Tensor) -> None:
        """Draws the domain randomisation and control delay of worlds `ids`; their delay ring starts
        at `initial_target` (n, J) or (J,)."""
        ids_np = ids.cpu().numpy()
        delay = self.randomizer.apply(ids_np)  # (n,) seconds of control delay
        if self.delay_scale != 1.0:  # a curriculum's share of the configured delays
            delay = delay * self.delay_scale
        d = torch.as_tensor(np.round(delay / self.sim_dt), dtype=torch.long, device=self.device)
        self.delay_substeps[ids] = d
        sub = torch.arange(self.decimation, device=self.device)
        self.delay_lag[ids] = torch.clamp(torch.div(d[:, None] - sub + self.decimation - 1, self.decimation,
                                                    rounding_mode="floor"), min=0)
        self.target_history[:, ids] = initial_target

    def _restart_episodes(self, ids: torch.Tensor, joint_vel: torch.Tensor) -> None:
        """The shared per-episode state of worlds `ids` at a reset (draws their next push's time)."""
        self.episode_step[ids] = 0
        self.prev_action[ids] = 0.0
        self.prev_action2[ids] = 0.0
        self.prev_joint_vel[ids] = joint_vel
        self.push_timer[ids] = self._push_interval(ids.numel())

    def _restart_observations(self, ids: torch.Tensor, frame_obs: torch.Tensor, privileged: torch.Tensor) -> None:
        """Worlds `ids` start their history filled with their first frame (new tensors: callers hold the old)."""
        hist = self.obs_history.clone()
        hist[ids] = frame_obs[:, None].expand(-1, self.cfg.observations.history, -1)
        self.obs_history = hist
        priv = self.privileged.clone()
        priv[ids] = privileged
        self.privileged = priv

    # ------------------------------------------------------------------------------------ resume
    def _model_fields(self) -> list[str]:
        """The MjModel fields this env writes per world (the randomiser's; a task adds its own)."""
        return list(self.randomizer.base)

    def state_dict(self) -> dict:
        """Everything that determines future steps, on the CPU, for a bit-exact resume (the trainer
        saves it with its checkpoint). Randomness is drawn from torch's global RNG, which the caller
        owns and restores itself (the trainer does); the randomiser's numpy RNG is re-seeded from it
        at every reset but is saved anyway."""
        ids = np.arange(self.num_envs)
        qpos, qvel = self.backend.get_state()
        return {
            "num_envs": self.num_envs,
            "qpos": torch.from_numpy(np.array(qpos, dtype=np.float64)),
            "qvel": torch.from_numpy(np.array(qvel, dtype=np.float64)),
            "model_fields": {name: np.array(self.backend.get_model_field(name, ids)) for name in self._model_fields()},
            "buffers": {name: getattr(self, name).detach().cpu().clone() for name in self._STATE_BUFFERS},
            "target_ptr": int(self.target_ptr),
            "penalty_scale": float(self.penalty_scale),
            "penalty_curriculum": [self.penalty_curriculum_started, int(self.episodes_finished),
                                   int(self.episodes_terminated)],
            "randomizer_rng": self.randomizer.rng.bit_generator.state,
            **self._task_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restores `state_dict()` of an env built with the same config, data and number of worlds."""
        if int(state.get("num_envs", -1)) != self.num_envs:
            raise PipelineInputError("env state", "num_envs",
                                     f"checkpoint has {state.get('num_envs')} worlds, this env {self.num_envs}")
        ids = np.arange(self.num_envs)
        # model first: set_state's forward pass then sees each world's own masses and terrain
        for name, values in state["model_fields"].items():
            self.backend.set_model_field(name, ids, np.asarray(values))
        buffers = self._upgrade_buffers(dict(state["buffers"]))
        for name in self._STATE_BUFFERS:
            saved = buffers[name]
            current = getattr(self, name)
            if saved.shape != current.shape or saved.dtype != current.dtype:
                raise PipelineInputError("env state", name,
                                         f"expected {tuple(current.shape)} {current.dtype}, got {tuple(saved.shape)} {saved.dtype}")
            setattr(self, name, saved.to(self.device).clone())
        self.target_ptr = int(state["target_ptr"])
        self.penalty_scale = float(state["penalty_scale"])
        started, finished, terminated = state["penalty_curriculum"]
        self.penalty_curriculum_started = bool(started)
        self._clear_episode_counts()
        self.episodes_finished += int(finished)
        self.episodes_terminated += int(terminated)
        self.randomizer.rng.bit_generator.state = state["randomizer_rng"]
        self._load_task_state(state)
        self.backend.set_state(ids, state["qpos"].numpy(), state["qvel"].numpy())

    def _upgrade_buffers(self, buffers: dict) -> dict:
        """Buffers of states saved by older versions, completed (none for the shared ones)."""
        return buffers

    def _task_state(self) -> dict:
        return {}

    def _load_task_state(self, state: dict) -> None:
        pass


__all__ = ["RobotEnv", "PENALTY_TERMS", "proprio_dim"]
