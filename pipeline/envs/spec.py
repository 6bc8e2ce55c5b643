"""What a trainer may know of an environment: `EnvSpec`, and the few calls it makes.

The trainers (pipeline/rl) read an env through this contract only, so the tracking env, the balance env
and a test's toy train alike without the trainer probing for attributes:

  env.spec() -> EnvSpec            sizes, joint order, observation layout, phase rate, action offset
  env.reset() -> obs               {"actor": (N, A), "critic": (N, C)}
  env.step(action, phase_rate_offset=None) -> obs, {"sparse", "dense"}, terminated, truncated, info
                                   info holds "final_obs" (truncated worlds' last observation) and, for AMP,
                                   "joint_pos"
  env.update_curriculum(progress)  once per iteration, progress in [0, 1]
  env.curriculum_stats() -> dict   the curricula's state, logged with each iteration
  env.pinned_observation_stats()   [(actor columns, mean, variance)] the normalisers hold fixed
  env.state_dict() / env.load_state_dict(state)   what a resumed run needs to step on bit for bit
                                   (only called where the spec says `resumable`)

`RobotEnv` implements all of it; a subclass overrides what differs.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EnvSpec:
    num_envs: int
    action_dim: int
    actor_obs_dim: int
    critic_obs_dim: int
    joint_names: tuple[str, ...]  # the action's order
    obs_layout: dict | None = None  # where each quantity sits in the observations (TrackingEnv.obs_layout)
    phase_rate: float | None = None  # Δφ per control step; None: the env has no phase
    action_offset: str = "default"  # what a zero action holds: "default" pose, or the reference's joints
    push_prior: bool = False  # the zero action carries the task's push prior (priors/push_prior.py)
    # state_dict()/load_state_dict() restore the env exactly; False: the trainer restarts every episode at each
    # checkpoint boundary instead, in a run and in its resumption alike
    resumable: bool = True
