"""Domain randomisation of the paper's table, sampled per world at reset and written into the
backend's per-world model with `set_model_field(name, world_ids, values)`, values being the whole
field for each of those worlds, shape (n, *model.<name>.shape).

Mapping to MuJoCo fields (why each is what it is):
  trunk mass +U(−2,5) kg and link masses ×U(0.9,1.1) → body_mass, with body_inertia scaled by the
      same ratio so each link keeps its radius of gyration;
  base CoM offset U(−0.1,0.1) m per axis → body_ipos of the base body;
  friction U(0.1,1.1) → sliding friction of the robot's collision geoms (the feet have contact
      priority, so theirs is the one MuJoCo uses against the ground). The paper's ranges were
      tuned in Isaac Gym, whose PhysX contacts average the two materials' friction: against its
      ground of friction 1 a sample of 0.1 gives a contact of 0.55. With `friction_combine:
      average` (default) the feet get (sample + ground)/2 so the contact sees what it saw there;
      `robot` uses the sample itself (0.1: no far jump can push off that floor);
  restitution e ∈ U(0,0.1) → the feet's contact damping ratio ζ = −ln e / sqrt(π² + ln² e)
      (a damped-spring contact bounces back with e = exp(−ζπ/sqrt(1−ζ²))), ζ = 1 at e = 0;
  P gain ×U, D gain ×U, motor strength ×U → actuator_gainprm[0] = s·p·Kp, biasprm[1] = −s·p·Kp,
      biasprm[2] = −s·d·Kd (strength scales the whole PD torque; the effort limit stays);
  control delay U(0,100) ms → returned to the env, which feeds per-substep delayed targets.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import torch

from pipeline.envs.config import Range, RandomizationConfig


def restitution_to_dampratio(e: np.ndarray) -> np.ndarray:
    e = np.asarray(e, dtype=np.float64)
    log_e = np.log(np.clip(e, 1e-300, 1.0))
    zeta = -log_e / np.sqrt(math.pi**2 + log_e**2)
    return np.where(e <= 0.0, 1.0, np.minimum(zeta, 1.0))  # no bounce: critically damped


class DomainRandomizer:
    def __init__(self, cfg: RandomizationConfig, model: mujoco.MjModel, backend):
        self.cfg, self.backend = cfg, backend
        self.rng = np.random.default_rng(0)
        self.base = {name: np.array(getattr(model, name), dtype=np.float64) for name in (
            "body_mass", "body_inertia", "body_ipos", "geom_friction", "geom_solref",
            "actuator_gainprm", "actuator_biasprm")}
        self.trunk = model.body(cfg.trunk_body).id
        self.base_body = model.body(cfg.base_body).id
        world_body = model.geom_bodyid == 0
        self.robot_geoms = np.flatnonzero(~world_body)
        self.feet_geoms = np.flatnonzero((model.geom_priority > 0) & ~world_body)
        ground = [g for g in np.flatnonzero(world_body) if model.geom(g).name == "ground"]
        self.ground_friction = float(model.geom_friction[ground[0], 0]) if ground else 1.0
        self.links = np.array([b for b in range(1, model.nbody) if b != self.trunk])

    def _on(self, r: Range) -> bool:
        return self.cfg.enabled and r.enabled

    @property
    def delay_enabled(self) -> bool:
        return self._on(self.cfg.control_delay_ms) and self.cfg.control_delay_ms.high > 0

    @property
    def max_delay_s(self) -> float:
        return self.cfg.control_delay_ms.high / 1000.0 if self.delay_enabled else 0.0

    def _u(self, r: Range, size) -> np.ndarray:
        return self.rng.uniform(r.low, r.high, size)

    def _write(self, name: str, world_ids: np.ndarray, values: np.ndarray) -> None:
        self.backend.set_model_field(name, world_ids, values)  # read back: backend.get_model_field

    def apply(self, world_ids: np.ndarray) -> np.ndarray:
        """Samples and writes every enabled term for `world_ids`; returns their control delays (s)."""
        c, n = self.cfg, len(world_ids)
        # seeded from torch's global RNG so the whole env replays from one RNG state
        self.rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,))))
        tile = lambda name: np.repeat(self.base[name][None], n, 0)  # noqa: E731
        if self._on(c.trunk_mass_add) or self._on(c.link_mass_scale):
            mass, inertia = tile("body_mass"), tile("body_inertia")
            if self._on(c.link_mass_scale):
                mass[:, self.links] *= self._u(c.link_mass_scale, (n, len(self.links)))
            if self._on(c.trunk_mass_add):
                mass[:, self.trunk] += self._u(c.trunk_mass_add, n)
            inertia *= (mass / np.maximum(self.base["body_mass"], 1e-12))[..., None]
            self._write("body_mass", world_ids, mass)
            self._write("body_inertia", world_ids, inertia)
        if self._on(c.base_com_offset):
            ipos = tile("body_ipos")
            ipos[:, self.base_body] += self._u(c.base_com_offset, (n, 3))
            self._write("body_ipos", world_ids, ipos)
        if self._on(c.friction):
            friction = tile("geom_friction")
            sample = self._u(c.friction, n)
            if c.friction_combine == "average":
                sample = 0.5 * (sample + self.ground_friction)
            friction[:, self.robot_geoms, 0] = sample[:, None]
            self._write("geom_friction", world_ids, friction)
        if self._on(c.restitution):
            solref = tile("geom_solref")
            solref[:, self.feet_geoms, 1] = restitution_to_dampratio(self._u(c.restitution, n))[:, None]
            self._write("geom_solref", world_ids, solref)
        gains = [self._on(c.p_gain_scale), self._on(c.d_gain_scale), self._on(c.motor_strength)]
        if any(gains):
            nu = self.base["actuator_gainprm"].shape[0]
            p = self._u(c.p_gain_scale, (n, nu)) if gains[0] else np.ones((n, nu))
            d = self._u(c.d_gain_scale, (n, nu)) if gains[1] else np.ones((n, nu))
            s = self._u(c.motor_strength, (n, nu)) if gains[2] else np.ones((n, nu))
            gain, bias = tile("actuator_gainprm"), tile("actuator_biasprm")
            gain[:, :, 0] *= s * p
            bias[:, :, 1] *= s * p
            bias[:, :, 2] *= s * d
            self._write("actuator_gainprm", world_ids, gain)
            self._write("actuator_biasprm", world_ids, bias)
        if self.delay_enabled:
            return self._u(c.control_delay_ms, n) / 1000.0
        return np.zeros(n)
