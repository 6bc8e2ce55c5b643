"""How well the balance policy stands: many worlds at once in the balance env, deterministic actions.

`standing_rate(policy, cfg, starts=...)`: worlds start at the stance at rest (`starts="stance"`) or in
the recorded end states of the task policies (`starts="recorded"`), under the paper's domain
randomisation and the pushes of `balance.env.randomization.push`, for `eval_seconds`. A world counts
as **upright** when no fall check fired and its pelvis leans less than `STANDING.max_tilt` at the end,
and as **standing** when it also passes the rest of `STANDING` (height, speed) then.
"""

from __future__ import annotations

import copy

import torch

from pipeline.balance.config import BalanceConfig
from pipeline.envs.falls import STANDING
from pipeline.envs.torch_math import projected_gravity


@torch.no_grad()
def standing_rate(policy, cfg: BalanceConfig, *, root, starts: str = "stance", episodes: int | None = None,
                  seconds: float | None = None, seed: int = 0) -> dict:
    from pipeline.balance.train import make_balance_env

    episodes = episodes or cfg.eval_episodes
    seconds = seconds or cfg.eval_seconds
    env_cfg = copy.deepcopy(cfg.env)
    env_cfg.episode_s = seconds + 1.0  # no time-out inside the test: the last state is read before any reset
    st = env_cfg.starts
    st.drop_prob = 0.0
    if starts == "stance":
        st.states_prob, st.joint_pos_noise, st.lin_vel_noise, st.ang_vel_noise = 0.0, 0.0, 0.0, 0.0
    elif starts == "recorded":
        st.states_prob, st.state_vel_scale = 1.0, [1.0, 1.0]
    else:
        raise ValueError(f"starts must be 'stance' or 'recorded', got {starts!r}")
    torch.manual_seed(seed)
    env = make_balance_env(cfg, root, num_envs=episodes, env_cfg=env_cfg)
    if starts == "recorded" and env.start_states is None:
        raise FileNotFoundError(f"no recorded start states at {cfg.start_states_path(root)}")
    policy.eval()
    obs = env.reset()
    fell = torch.zeros(episodes, dtype=torch.bool)
    for _ in range(int(round(seconds / env.control_dt))):
        action, _ = policy(obs["actor"])
        obs, _, terminated, _, _ = env.step(action)
        fell |= terminated.cpu()
    qpos, qvel = env.backend.qpos.cpu(), env.backend.qvel.cpu()
    tilt = projected_gravity(qpos[:, 3:7])[:, :2].norm(dim=-1)
    upright = ~fell & (tilt < STANDING.max_tilt)
    standing = upright & (qpos[:, 2] >= STANDING.min_height) & (qvel[:, 0:3].norm(dim=-1) < STANDING.max_speed)
    return {"starts": starts, "episodes": episodes, "seconds": seconds, "seed": seed,
            "upright": 100.0 * float(upright.float().mean()), "standing": 100.0 * float(standing.float().mean()),
            "fell": 100.0 * float(fell.float().mean()),
            "pushes": {"interval_s": list(env_cfg.randomization.push.interval_s),
                       "max_vel_xy": env_cfg.randomization.push.max_vel_xy},
            "randomization": bool(env_cfg.randomization.enabled)}
