"""The training loop against the env contract (docs/INTERFACES.md); the stages built on it are in
`pipeline/rl/training.py`.

    Trainer(env, policy, critic, cfg, run_dir, ...).run(iters)     -> the loop itself, for any env

Each iteration: collect `steps_per_iteration` steps from every env, run the PPO update, update the
termination curriculum, log, and every `save_interval` iterations write an atomic checkpoint.

The trainer reads the env through its contract only (pipeline/envs/spec.py: `spec()`, `reset`, `step`,
`update_curriculum`, `curriculum_stats`, `pinned_observation_stats`, `state_dict`).

Resuming is bit-exact: a checkpoint holds the parameters, optimiser, RNG states and (when the env's spec
says `resumable`) the env state and current observation. Other envs are reset at every checkpoint
boundary, in the uninterrupted run as in the resumed one, so both see the same next iteration as long as
the env draws its randomness from torch's global RNG.
"""

from __future__ import annotations

import copy
import itertools
import json
import math
import shutil
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from pipeline.common.atomic import atomic_file, write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.rl.amp import AMPDiscriminator, JointWindow
from pipeline.rl.averaging import WeightAverage
from pipeline.rl.checkpoint import CheckpointManager, check_compatible, load_policy, read_meta, rng_state, save_policy, set_rng_state
from pipeline.rl.config import TrainConfig
from pipeline.rl.episode_stats import EpisodeStats
from pipeline.rl.exploration import CorrelatedNoise
from pipeline.rl.ppo import GROUPS, PPO, Rollout

class Trainer:
    def __init__(self, env, policy, critic, cfg: TrainConfig, run_dir: str | Path, *, stage: int, meta: dict,
                 l2c2: bool = False, amp: AMPDiscriminator | None = None, amp_reference: torch.Tensor | None = None,
                 use_phase_offset: bool = False, tensorboard: bool = True, progress: bool = True, log=print):
        self.env, self.policy, self.critic, self.cfg = env, policy, critic, cfg
        self.spec = env.spec()
        self.run_dir = Path(run_dir)
        self.stage, self.meta, self.log = stage, meta, log
        self.device = torch.device(cfg.device if cfg.device != "cuda" or torch.cuda.is_available() else "cpu")
        policy.to(self.device)
        critic.to(self.device)
        if amp is not None:
            amp.to(self.device)
            amp_reference = amp_reference.to(self.device)
        self.amp, self.amp_reference = amp, amp_reference
        self.use_phase_offset = use_phase_offset
        self.checkpoints = CheckpointManager(self.run_dir, cfg.keep_checkpoints)
        self.average = WeightAverage() if cfg.average_tail > 0 else None
        self.stats = EpisodeStats(self.spec.num_envs, self.device)
        self.warm_started = False  # warm_start: this run began from another run's networks
        self.noise = None
        self._setup_algorithm(l2c2)
        self.history: list[dict] = []
        self.tensorboard, self.progress = tensorboard, progress
        self.joint_window = None
        if amp is not None:
            self.joint_window = JointWindow(self.spec.num_envs, self.spec.action_dim, cfg.amp.window, self.device)

    def _setup_algorithm(self, l2c2: bool) -> None:
        """PPO here; the off-policy trainer (fast_td3.FastTD3Trainer) sets up its own."""
        self.algorithm = "ppo"
        self.steps_per_iteration = self.cfg.ppo.steps_per_iteration
        self.ppo = PPO(self.policy, self.critic, self.cfg.ppo, l2c2=l2c2)
        # White noise (the paper's) is drawn inside policy.sample; correlated noise needs a state per world.
        if self.cfg.ppo.noise_correlation > 0:
            self.noise = CorrelatedNoise(self.spec.num_envs, self.policy.raw_dim, self.cfg.ppo.noise_correlation, self.device)

    # -- env helpers ------------------------------------------------------------------------
    @staticmethod
    def _joint_pos(info: dict) -> torch.Tensor:
        if "joint_pos" not in info:
            raise RuntimeError("AMP needs the robot's joint positions: the env's step gives no info['joint_pos']")
        return info["joint_pos"]

    # -- one iteration ----------------------------------------------------------------------
    def collect(self, obs: dict) -> tuple[Rollout, dict, dict]:
        steps, n = self.steps_per_iteration, self.spec.num_envs
        raw_dim = self.policy.raw_dim
        ro = Rollout.allocate(steps, n, obs["actor"].shape[-1], obs["critic"].shape[-1], raw_dim, self.device)
        amp_windows = []
        for t in range(steps):
            rec = self.ppo.act(obs["actor"], obs["critic"], self.noise.next() if self.noise is not None else None)
            offset = rec["phase_offset"] if self.use_phase_offset else None
            next_obs, rewards, terminated, truncated, info = self.env.step(rec["action"], offset)
            terminated, truncated = terminated.bool(), truncated.bool()
            if self.noise is not None:
                self.noise.restart(terminated | truncated)
            self.stats.step(rewards, terminated, truncated, info)
            if self.amp is not None:
                self.joint_window.push(self._joint_pos(info))
                windows = self.joint_window.flat(info.get("phase") if self.cfg.variant_spec.amp == "mimic" else None)
                amp_windows.append(windows)
                rewards = self.amp.combine(rewards, self.amp.style_reward(windows))
                self.joint_window.filled &= ~(terminated | truncated)
            ro.actor_obs[t], ro.critic_obs[t] = obs["actor"], obs["critic"]
            ro.raw_actions[t], ro.log_probs[t] = rec["raw"], rec["log_prob"]
            ro.means[t], ro.stds[t] = rec["mean"], rec["std"]
            for g in GROUPS:
                ro.values[g][t] = rec[g]
                ro.rewards[g][t] = rewards[g]
            ro.terminated[t], ro.truncated[t] = terminated, truncated
            # Timeouts bootstrap from the state they reached when the env reports it (before its
            # auto-reset); otherwise from the state the last action was taken in. Valued for every
            # world and used where truncated: asking first whether any world timed out is a GPU sync.
            final = info.get("final_obs")
            v = self.ppo.values(final["critic"]) if final is not None else {g: rec[g] for g in GROUPS}
            for g in GROUPS:
                ro.timeout_values[g][t] = v[g]
            obs = next_obs
        ro.last_values = self.ppo.values(obs["critic"])
        amp_batch = torch.cat(amp_windows) if amp_windows else None
        return ro, obs, {"amp_windows": amp_batch}

    def _boundary(self, iteration: int, obs: dict | None) -> dict:
        """At checkpoint boundaries of envs without state, restart episodes (see module docstring)."""
        if obs is None or (not self.spec.resumable and iteration % self.cfg.save_interval == 0):
            self.stats.reset()
            if self.joint_window is not None:
                self.joint_window.filled.zero_()
            if self.noise is not None:
                self.noise.restart()
            return self.env.reset()
        return obs

    def _sync(self) -> None:
        """Waits for queued GPU work, so that wall-clock splits of an iteration are true."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    # -- the loop ---------------------------------------------------------------------------
    def run(self, iterations: int, resume: bool = False, time_limit_s: float | None = None,
            chunk_s: float | None = None) -> dict:
        """Trains `iterations` (0: until `time_limit_s` of wall time), saving as it goes.

        The curricula follow the iteration count, so the same config trains the same policy on any
        machine, however busy; a time limit only stops a slow run early, and the run says so. A run
        sized by time alone (`iterations` 0) has no count to follow: its curricula follow wall time.

        `chunk_s`: a long run spread over several invocations. This one stops at the first checkpoint
        after `chunk_s` seconds of its own and returns {"paused": True, ...} without writing the final
        policy; `resume=True` continues from there. A chunk ends only at a save boundary, so the chunks
        train what one uninterrupted run trains, and the time limit counts the chunks' time together."""
        by_time = iterations <= 0
        if by_time and not (time_limit_s and time_limit_s > 0):
            raise ValueError("a run with 0 iterations trains until its time limit: give time_limit_s > 0")
        start, obs = 0, None
        if resume:
            start, obs = self._restore()
        else:
            # a new run where another ran: a later --resume must not take that run's checkpoints or finished
            # stage (metrics.json: the stages skip a finished stage 1) for this one's, nor TensorBoard its curves
            self.checkpoints.clear()
            (self.run_dir / "metrics.json").unlink(missing_ok=True)
            shutil.rmtree(self.run_dir / "tensorboard", ignore_errors=True)
        if start == 0 and not self.warm_started:
            self._warm_up_normalizers()
        writer = self._writer()
        # Wall time counts across resumes, so a time limit caps the whole run.
        t0 = time.time() - (self.history[-1]["seconds"] if self.history else 0.0)
        steps = itertools.count(start) if by_time else range(start, iterations)
        bar = tqdm(steps, initial=start, total=None if by_time else iterations, desc=f"stage {self.stage}",
                   disable=not self.progress, mininterval=2.0, file=sys.stderr)
        stopped_early = False
        chunk_start = time.time()

        def fraction_done(iterations_done: int) -> float:
            """How far through the stage: by the clock for a run sized by time, else by the count."""
            return min((time.time() - t0) / time_limit_s, 1.0) if by_time else iterations_done / iterations

        for it in bar:
            obs = self._boundary(it, obs)
            progress = fraction_done(it)
            self.env.update_curriculum(progress)
            self.policy.train()
            stats, obs = self._iteration(obs)
            stats.update(self.stats.summary())
            stats.update({"iteration": it + 1, "env_steps": (it + 1) * self.spec.num_envs * self.steps_per_iteration,
                          "seconds": time.time() - t0})
            stats.update(self.env.curriculum_stats())
            self.history.append(stats)
            if writer is not None:
                for k, v in stats.items():
                    if isinstance(v, (int, float)) and math.isfinite(v):
                        writer.add_scalar(f"stage{self.stage}/{k}", v, it + 1)
            bar.set_postfix(success=f"{stats.get('success_rate', float('nan')):.2f}", ret=f"{stats.get('return_sparse', float('nan')):.1f}")
            if self.average is not None and (it + 1) % self.cfg.average_every == 0:
                if fraction_done(it + 1) >= 1.0 - self.cfg.average_tail:
                    self.average.add(self.policy.state_dict())
            out_of_time = time_limit_s is not None and time_limit_s > 0 and time.time() - t0 > time_limit_s
            at_boundary = (it + 1) % self.cfg.save_interval == 0
            if at_boundary or it + 1 == iterations or out_of_time:
                self._save(it + 1, obs)
            finished = out_of_time or it + 1 == iterations
            if chunk_s is not None and at_boundary and not finished and time.time() - chunk_start >= chunk_s:
                bar.close()
                if writer is not None:
                    writer.close()
                self.log(f"[train] stage {self.stage}: chunk of {chunk_s:.0f} s done at iteration {it + 1}; "
                         f"resume to continue ({self.checkpoints.latest()})")
                return {"stage": self.stage, "paused": True, "iteration": it + 1,
                        "train_seconds": self.history[-1]["seconds"], "checkpoint": str(self.checkpoints.latest())}
            if out_of_time:
                if not by_time and it + 1 < iterations:
                    stopped_early = True
                    self.log(f"[train] stage {self.stage}: the {time_limit_s:.0f} s time limit stopped it at iteration "
                             f"{it + 1} of {iterations}, its curricula {progress:.0%} through; a longer limit (or a "
                             f"quieter machine) trains what the config asks")
                iterations = it + 1
                break
        bar.close()
        if writer is not None:
            writer.close()
        return self._finish(iterations, stopped_early)

    def _iteration(self, obs: dict) -> tuple[dict, dict]:
        """One PPO iteration: a rollout, then the update. Returns (figures to log, next observation)."""
        collect_start = time.perf_counter()
        rollout, obs, extra = self.collect(obs)
        self._sync()
        update_start = time.perf_counter()
        stats = self.ppo.update(rollout)
        if self.amp is not None:
            stats.update(self.amp.update(self.amp_reference, extra["amp_windows"]))
        self._sync()
        # Where an iteration's time goes (on a GPU the env's small kernels, not the physics, were
        # the larger part: benchmarks/RESULTS.md).
        stats.update({"collect_seconds": update_start - collect_start, "update_seconds": time.perf_counter() - update_start,
                      "reward_sparse": rollout.rewards["sparse"].mean().item(),
                      "reward_dense": rollout.rewards["dense"].mean().item()})
        return stats, obs

    @torch.no_grad()
    def _warm_up_normalizers(self) -> None:
        """Fits the observation normalisers on one rollout of the initial policy before the first
        update. Without it the first rollout and update see raw observations (joint velocities of
        ~10 rad/s): the first Adam steps then move the policy so far (KL ≈ 2× target on average)
        that the adaptive rule cuts the learning rate to its floor. The statistics are then frozen
        for that rollout and its update like every later one (see PPO.act)."""
        if not self.cfg.ppo.normalize_obs:
            return
        obs = self.env.reset()
        actor, critic = [], []
        for _ in range(self.steps_per_iteration):
            actor.append(obs["actor"])
            critic.append(obs["critic"])
            raw, _ = self.policy.sample(obs["actor"])
            action, phase_offset = self.policy.to_env(obs["actor"], raw)
            obs = self.env.step(action, phase_offset if self.use_phase_offset else None)[0]
        self.policy.update_normalizers(torch.stack(actor))
        self.critic.update_normalizers(torch.stack(critic))

    # -- saving / resuming ------------------------------------------------------------------
    def _training_state(self, obs: dict) -> dict:
        state = {**self._algorithm_state(), "rng": rng_state(), "history": self.history,
                 "stats": self.stats.state_dict(), "stage": self.stage}
        if self.spec.resumable:
            state["env"] = self.env.state_dict()
            state["obs"] = {k: v.clone() for k, v in obs.items()}
        if self.noise is not None:
            state["noise"] = self.noise.state_dict()
        if self.average is not None:
            state["weight_average"] = self.average.state_dict()
        if self.amp is not None:
            state["amp"] = {"net": self.amp.state_dict(), "optimizer": self.amp.optimizer.state_dict(),
                            "window": self.joint_window.frames.clone(), "filled": self.joint_window.filled.clone()}
        return state

    def _algorithm_state(self) -> dict:
        return {"ppo": self.ppo.state_dict()}

    def _load_algorithm_state(self, state: dict, path: Path) -> None:
        self.ppo.load_state_dict(state["ppo"])

    def _load_critic(self, path: Path) -> None:
        _, critic, _ = load_policy(path, with_critic=True)
        self.critic.load_state_dict(critic.state_dict())

    def _save(self, iteration: int, obs: dict) -> None:
        self.checkpoints.save(iteration, self.policy, self.critic, self.meta, self._training_state(obs))

    def warm_start(self, path: str | Path) -> None:
        """Starts this run from a checkpoint's networks (normalisers included) and optimiser, with its own
        iteration count, history, curricula and env: a fine-tune. Before `run`, which then leaves the
        normalisers' statistics as they came. A committed run (its `policy/` kept, its checkpoints not)
        gives its networks alone, and the optimiser starts afresh."""
        path = Path(path)
        if (path / "checkpoints").is_dir():  # a run folder: its latest checkpoint
            path = path / "checkpoints"
        if (path / "latest").is_file():  # a checkpoints folder: the one its pointer names
            path = CheckpointManager(path.parent, 1).latest() or path
        if not (path / "training_state.pt").is_file() and (path / "policy" / "config.json").is_file():
            path = path / "policy"  # a committed run: its final networks
        with_state = (path / "training_state.pt").is_file()
        if not with_state and not (path / "config.json").is_file():
            raise PipelineInputError(path, "training_state.pt", "not a training checkpoint nor a policy (init_from "
                                     "names a run, its checkpoints folder, one checkpoint or a policy folder)")
        check_compatible(read_meta(path), self.meta, path)
        policy, _ = load_policy(path)
        self.policy.load_state_dict(policy.state_dict())
        self._load_critic(path)
        if with_state:
            self._load_algorithm_state(CheckpointManager.load_state(path), path)
        self.warm_started = True
        self.log(f"[train] warm start from {path}")

    def _restore(self) -> tuple[int, dict | None]:
        path = self.checkpoints.latest()
        if path is None:
            self.log(f"[train] no checkpoint under {self.checkpoints.root}: starting from scratch")
            return 0, None
        meta = read_meta(path)
        check_compatible(meta, self.meta, path)
        if int(meta.get("stage", self.stage)) != self.stage:
            raise PipelineInputError(path, "stage", f"checkpoint is stage {meta.get('stage')}, this run is stage {self.stage}")
        if meta.get("algorithm", "ppo") != self.algorithm:
            raise PipelineInputError(path, "algorithm", f"checkpoint was trained with {meta.get('algorithm', 'ppo')!r}, this "
                                     f"run asks for {self.algorithm!r} (train.algorithm); resume with the same "
                                     f"algorithm, or start a new run directory")
        policy, _ = load_policy(path)
        self.policy.load_state_dict(policy.state_dict())
        self._load_critic(path)
        state = CheckpointManager.load_state(path)
        self._load_algorithm_state(state, path)
        self.history = list(state["history"])
        self.stats.load_state_dict(state["stats"])
        obs = None
        if "env" in state and self.spec.resumable:
            self.env.load_state_dict(state["env"])
            obs = state["obs"]
        if self.noise is not None and "noise" in state:
            self.noise.load_state_dict(state["noise"])
        if self.average is not None and "weight_average" in state:
            self.average.load_state_dict(state["weight_average"])
        if self.amp is not None and "amp" in state:
            self.amp.load_state_dict(state["amp"]["net"])
            self.amp.optimizer.load_state_dict(state["amp"]["optimizer"])
            self.joint_window.frames.copy_(state["amp"]["window"])
            self.joint_window.filled.copy_(state["amp"]["filled"])
        set_rng_state(state["rng"])
        self.log(f"[train] resumed stage {self.stage} from {path.name} (iteration {state['iteration']})")
        return int(state["iteration"]), obs

    def _writer(self):
        if not self.tensorboard:
            return None
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(str(self.run_dir / "tensorboard"))

    def _finish(self, iterations: int, stopped_by_time_limit: bool = False) -> dict:
        policy, meta = self.policy, dict(self.meta, iteration=iterations)
        if self.average is not None and self.average.count:
            policy = copy.deepcopy(self.policy)
            policy.load_state_dict(self.average.mean())
            meta["averaged_snapshots"] = self.average.count
            self.log(f"[train] stage {self.stage}: the policy written is the mean of {self.average.count} snapshots, "
                     f"every {self.cfg.average_every} iterations over the last {self.cfg.average_tail:.0%} of the stage")
        save_policy(self.run_dir / "policy", policy, self.critic, meta)
        last = self.history[-1] if self.history else {}
        metrics = {"stage": self.stage, "variant": self.cfg.variant, "iterations": iterations,
                   "success_rate": last.get("success_rate"), "return_sparse": last.get("return_sparse"),
                   "return_dense": last.get("return_dense"), "episodes_in_window": last.get("episodes"),
                   "env_steps": last.get("env_steps"), "train_seconds": last.get("seconds"),
                   "stopped_by_time_limit": stopped_by_time_limit}
        write_text_atomic(self.run_dir / "metrics.json", json.dumps(metrics, indent=2))
        write_text_atomic(self.run_dir / "history.json", json.dumps(self.history))
        plot_curve(self.history, self.run_dir / "training_curve.png", f"stage {self.stage} ({self.cfg.variant})")
        return metrics


def plot_curve(history: list[dict], path: Path, title: str) -> None:
    if not history:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [h["iteration"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    for ax, key in zip(axes, ("success_rate", "return_sparse", "return_dense")):
        ax.plot(it, [h.get(key, float("nan")) for h in history])
        ax.set_xlabel("iteration")
        ax.set_title(key)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_file(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=90)
    plt.close(fig)
