"""Left-right mirror of G1 states, observations and actions (reflection through the sagittal x-z plane).

The G1 and the jumps are near symmetric, so a transition and its mirror image are both plausible
experience; the off-policy trainer can replay each sample as recorded or mirrored (fast_td3.mirror).

Under the reflection y -> −y:
  * a joint maps to its left/right partner (a joint without one, the waist's, to itself); roll and
    yaw joints turn the other way, so their angles, velocities and actions change sign;
  * polar vectors (positions, linear velocities, gravity) keep x and z and flip y;
  * axial vectors (angular velocities) flip x and z and keep y;
  * scalars (phase, ψ, base height, the time to the next keyframe) stay.
Every map is a permutation with signs, so mirror ∘ mirror is exactly the identity.
"""

from __future__ import annotations

import torch

from pipeline.common.errors import PipelineInputError

POLAR = (1.0, -1.0, 1.0)
AXIAL = (-1.0, 1.0, -1.0)
# What each named observation quantity is (TrackingEnv.obs_layout's names).
QUANTITY_KIND = {
    "base_ang_vel": "axial", "projected_gravity": "polar", "joint_pos_rel": "joints", "joint_vel": "joints",
    "prev_action": "joints", "phase": "scalar", "psi": "scalar", "odometry": "polar",
    "base_lin_vel": "polar", "ref_joint_pos": "joints", "base_height": "scalar", "phase_to_next_keyframe": "scalar",
}


def joint_mirror(joint_names: list[str] | tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """(partner index, sign) per joint: mirrored[i] = sign[i] * q[partner[i]]."""
    names = list(joint_names)
    index = {n: i for i, n in enumerate(names)}
    partner, sign = [], []
    for name in names:
        other = name.replace("left_", "\0").replace("right_", "left_").replace("\0", "right_")
        if other not in index:
            raise PipelineInputError("joint_names", name, f"its mirror partner {other!r} is not a joint of this robot")
        partner.append(index[other])
        sign.append(-1.0 if ("roll" in name or "yaw" in name) else 1.0)
    return torch.tensor(partner), torch.tensor(sign)


def qpos_mirror(qpos: torch.Tensor, joint_names) -> torch.Tensor:
    """A floating-base pose (…, 7 + J) [x y z, qw qx qy qz, joints] mirrored: position y flips, the
    base rotation R becomes M R M (M = diag(1, −1, 1)), i.e. quaternion (w, −x, y, −z)."""
    partner, sign = joint_mirror(joint_names)
    out = qpos.clone()
    out[..., 1] = -qpos[..., 1]
    out[..., 4] = -qpos[..., 4]
    out[..., 6] = -qpos[..., 6]
    out[..., 7:] = sign.to(qpos) * qpos[..., 7:][..., partner.to(qpos.device)]
    return out


class Mirror:
    """Permutation-with-signs maps of the actor observation, critic observation and raw action."""

    def __init__(self, actor_perm, actor_sign, critic_perm, critic_sign, raw_perm, raw_sign):
        self.maps = {"actor": (actor_perm, actor_sign), "critic": (critic_perm, critic_sign), "raw": (raw_perm, raw_sign)}

    def to(self, device) -> "Mirror":
        self.maps = {k: (p.to(device), s.to(device)) for k, (p, s) in self.maps.items()}
        return self

    def apply(self, kind: str, x: torch.Tensor) -> torch.Tensor:
        perm, sign = self.maps[kind]
        return x[..., perm] * sign

    def actor(self, x: torch.Tensor) -> torch.Tensor:
        return self.apply("actor", x)

    def critic(self, x: torch.Tensor) -> torch.Tensor:
        return self.apply("critic", x)

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        return self.apply("raw", x)

    @classmethod
    def from_layout(cls, layout: dict, joint_names, actor_dim: int, critic_dim: int, raw_dim: int) -> "Mirror":
        """From TrackingEnv.obs_layout(): `history` frames of `actor_frame` quantities, then the
        critic's `critic_privileged` tail ([start, stop) spans). Extra raw outputs past the joints
        (the phase-rate offset) stay."""
        partner, jsign = joint_mirror(joint_names)
        num_joints = len(partner)

        def block(name: str, size: int) -> tuple[torch.Tensor, torch.Tensor]:
            kind = QUANTITY_KIND.get(name)
            if kind is None:
                raise PipelineInputError("obs_layout", name, "no known mirror for this observation quantity")
            if kind in ("polar", "axial"):
                if size != 3:
                    raise PipelineInputError("obs_layout", name, f"a 3-vector, got {size} columns")
                return torch.arange(3), torch.tensor(POLAR if kind == "polar" else AXIAL)
            if kind == "joints":
                if size != num_joints:
                    raise PipelineInputError("obs_layout", name, f"{size} columns for {num_joints} joints")
                return partner.clone(), jsign.clone()
            return torch.arange(size), torch.ones(size)

        def spans(items: dict, total: int, offset: int) -> tuple[torch.Tensor, torch.Tensor]:
            perm, sign = torch.arange(total) + offset, torch.ones(total)  # absolute column indices
            for name, (start, stop) in items.items():
                p, s = block(name, stop - start)
                perm[start - offset : stop - offset] = p + start
                sign[start - offset : stop - offset] = s
            return perm, sign

        frame_dim, history = int(layout["frame_dim"]), int(layout["history"])
        if frame_dim * history != actor_dim:
            raise PipelineInputError("obs_layout", "frame_dim", f"{history} x {frame_dim} != actor observation {actor_dim}")
        frame_perm, frame_sign = spans(layout["actor_frame"], frame_dim, 0)
        actor_perm = torch.cat([frame_perm + h * frame_dim for h in range(history)])
        actor_sign = frame_sign.repeat(history)
        priv_perm, priv_sign = spans(layout.get("critic_privileged", {}), critic_dim - actor_dim, actor_dim)
        critic_perm, critic_sign = torch.cat([actor_perm, priv_perm]), torch.cat([actor_sign, priv_sign])
        raw_perm, raw_sign = torch.arange(raw_dim), torch.ones(raw_dim)
        raw_perm[:num_joints], raw_sign[:num_joints] = partner, jsign
        return cls(actor_perm, actor_sign, critic_perm, critic_sign, raw_perm, raw_sign)


def mirror_for_env(env, raw_dim: int) -> Mirror:
    """The env's mirror, from its observation layout and joint names (its spec); a clear error where it has none."""
    spec = env.spec()
    if not isinstance(spec.obs_layout, dict) or "actor_frame" not in spec.obs_layout:
        raise PipelineInputError("train.fast_td3", "mirror", "the env gives no observation layout to mirror "
                                 "(TrackingEnv.obs_layout); set fast_td3.mirror: false")
    return Mirror.from_layout(spec.obs_layout, spec.joint_names, spec.actor_obs_dim, spec.critic_obs_dim, raw_dim)
