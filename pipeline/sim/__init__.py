"""Physics behind one narrow interface: CpuBackend (MuJoCo C + rollout threads), WarpBackend (mujoco_warp).

    from pipeline.sim import make_backend, build_sim_model
    backend = make_backend("cpu", build_sim_model(terrain), num_worlds=256)
"""

from pipeline.sim.backend import PhysicsBackend, make_backend
from pipeline.sim.model import add_sim_sensors, build_sim_model

__all__ = ["PhysicsBackend", "make_backend", "build_sim_model", "add_sim_sensors"]
