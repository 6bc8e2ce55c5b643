"""`adamimic sim-bridge`: a MuJoCo G1 (our model, the export's scene at ψ) behind the G1's DDS interface.

Publishes `unitree_hg` LowState_ on rt/lowstate and applies LowCmd_ from rt/lowcmd with the robot's
motor law τ = τ_ff + kp (q* − q) + kd (dq* − dq), clipped to the effort limits, evaluated by MuJoCo at
every physics step (500 Hz by default, as the robot's motor drivers run it) through the actuators'
gain and bias terms. The pelvis pose goes out as nav_msgs Odometry_ (a lidar-odometry stand-in).
The robot starts where a real one does: in the default pose hanging on a virtual gantry (gantry.py),
at the task's start position, its feet off the ground; the physics runs from the first LowCmd, and
the gantry lowers it onto its feet and lets go `gantry.release_s` later (after deploy's damping and
ramp). With no gantry it starts standing on its feet in the default pose.

Real time (default): the simulation follows the wall clock, like the robot. `lockstep`: one control
period (`control_dt`) of physics per LowCmd received, then one LowState, so the controller and this
bridge run the same sequence as `sim2sim` whatever the load of the machine (for tests).
The accelerometer is not simulated (zeros); the policy does not observe it.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.deploy.crc import low_state_crc
from pipeline.deploy.gantry import Gantry
from pipeline.deploy.motors import NUM_MOTORS, MotorMap
from pipeline.deploy.transport import (LOW_CMD_TOPIC, LOW_STATE_TOPIC, ODOMETRY_TOPIC, CheckedReader, check_low_cmd)

REPUBLISH_S = 0.02  # lockstep: the last state again while no command comes


class SimBridge:
    def __init__(self, export_dir: str | Path, psi: float, *, link, lockstep: bool = False,
                 sim_dt: float = 0.002, odometry_hz: float = 10.0, gantry: Gantry | None = Gantry()):
        from pipeline.export.chain import stance_state
        from pipeline.export.sim2sim import build_scene
        from pipeline.robot.g1 import load_robot_config

        meta_path = Path(export_dir) / "policy.json"
        if not meta_path.is_file():
            raise PipelineInputError(meta_path, None, "policy metadata json not found")
        self.meta = meta = json.loads(meta_path.read_text())
        if not sim_dt > 0:
            raise PipelineInputError("sim-bridge", "--sim-dt", f"must be > 0, got {sim_dt}")
        self.model = model = build_scene(meta, float(psi))
        model.opt.timestep = sim_dt
        self.data = mujoco.MjData(model)
        self.stance_z = load_robot_config().default_root_height
        self.data.qpos[:], self.data.qvel[:] = stance_state(meta, model, self.stance_z)
        self.stance_z = float(self.data.qpos[2])  # with the ground under the start
        self.gantry, self.pelvis = gantry, model.body("pelvis").id
        self.anchor_xy = self.data.qpos[0:2].copy()
        if gantry is not None:
            self.data.qpos[2] += gantry.lift_m
        mujoco.mj_forward(model, self.data)
        names = meta["joint_names"]
        self.motors = MotorMap.from_joint_names(names, str(meta_path))
        self.actuators = np.array([model.actuator(n).id for n in names])
        self.qpos_adr = np.array([model.jnt_qposadr[model.joint(n).id] for n in names])
        self.dof_adr = np.array([model.jnt_dofadr[model.joint(n).id] for n in names])
        self.sites = np.array([model.site(n).id for n in meta["tracked_site_names"]])
        self._unpowered()
        self.lockstep, self.odometry_every = lockstep, max(1, int(round(1.0 / (odometry_hz * sim_dt))))
        self.steps_per_command = max(1, int(round(float(meta["control_dt"]) / sim_dt)))
        self.link = link
        self.cmd_reader = CheckedReader(link.reader(LOW_CMD_TOPIC, link.types.LowCmd), check_low_cmd)
        self.state_writer = link.writer(LOW_STATE_TOPIC, link.types.LowState)
        self.odometry_writer = link.writer(ODOMETRY_TOPIC, link.types.Odometry)
        self.state = link.types.new_low_state()
        self.odometry = link.types.new_odometry()
        self.steps = 0
        self.commands = 0
        self.trace: dict[str, list] = {"tick": [], "qpos": [], "site_xpos": []}
        self.stop = False

    def _unpowered(self) -> None:
        self.model.actuator_gainprm[self.actuators, 0] = 0.0
        self.model.actuator_biasprm[self.actuators, 0:3] = 0.0

    def apply(self, cmd) -> None:
        """The motor law of each driven joint from one LowCmd (locked waist motors have no joint here)."""
        m = self.motors.motor_of_joint
        mc = cmd.motor_cmd
        kp = np.array([mc[i].kp for i in m]) * np.array([mc[i].mode == 1 for i in m])
        kd = np.array([mc[i].kd for i in m]) * np.array([mc[i].mode == 1 for i in m])
        q = np.array([mc[i].q for i in m])
        dq = np.array([mc[i].dq for i in m])
        tau = np.array([mc[i].tau for i in m]) * np.array([mc[i].mode == 1 for i in m])
        a = self.actuators
        # force = gain·ctrl + b0 + b1·q + b2·q̇ = kp q* + (τ_ff + kd dq*) − kp q − kd q̇
        self.model.actuator_gainprm[a, 0] = kp
        self.model.actuator_biasprm[a, 0] = tau + kd * dq
        self.model.actuator_biasprm[a, 1] = -kp
        self.model.actuator_biasprm[a, 2] = -kd
        self.data.ctrl[a] = q
        self.commands += 1

    def publish(self) -> None:
        d, s = self.data, self.state
        s.tick = int(round(self.steps * self.model.opt.timestep * 1000)) & 0xFFFFFFFF  # simulated ms
        quat = d.qpos[3:7]
        s.imu_state.quaternion = [float(v) for v in quat]
        s.imu_state.gyroscope = [float(v) for v in d.qvel[3:6]]
        w, x, y, z = quat
        s.imu_state.rpy = [float(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))),
                           float(np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))),
                           float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))]
        q29 = self.motors.to_motors(d.qpos[self.qpos_adr], 0.0)
        dq29 = self.motors.to_motors(d.qvel[self.dof_adr], 0.0)
        tau29 = self.motors.to_motors(d.actuator_force[self.actuators], 0.0)
        for i in range(NUM_MOTORS):
            ms = s.motor_state[i]
            ms.mode, ms.q, ms.dq, ms.tau_est = 1, float(q29[i]), float(dq29[i]), float(tau29[i])
        s.crc = low_state_crc(s)
        self.state_writer.write(s)

    def publish_odometry(self) -> None:
        pose = self.odometry.pose.pose
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in self.data.qpos[0:3])
        w, x, y, z = (float(v) for v in self.data.qpos[3:7])
        pose.orientation.w, pose.orientation.x, pose.orientation.y, pose.orientation.z = w, x, y, z
        self.odometry_writer.write(self.odometry)

    def _record(self) -> None:
        self.trace["tick"].append(int(self.state.tick))
        self.trace["qpos"].append(self.data.qpos[0:7].copy())
        self.trace["site_xpos"].append(self.data.site_xpos[self.sites].copy())

    def _physics(self, steps: int) -> None:
        for _ in range(steps):
            if self.gantry is not None:
                self.gantry.apply(self.model, self.data, self.pelvis, self.anchor_xy, self.stance_z,
                                  self.steps * self.model.opt.timestep)
            mujoco.mj_step(self.model, self.data)
            self.steps += 1

    def run(self, duration_s: float | None = None) -> None:
        signal.signal(signal.SIGTERM, lambda *_: setattr(self, "stop", True))
        start = time.monotonic()
        dt = self.model.opt.timestep
        last_cmd = None
        self.publish_odometry()
        self.publish()
        last_publish = time.monotonic()
        try:
            while not self.stop and (duration_s is None or time.monotonic() - start < duration_s):
                received = self.cmd_reader.poll()
                fresh = received is not None and received is not last_cmd
                if fresh:
                    last_cmd = received
                    self.apply(received.message)
                if self.lockstep:
                    if fresh:
                        self._physics(self.steps_per_command)
                        self.publish_odometry()
                        self.publish()
                        self._record()
                        last_publish = time.monotonic()
                    else:
                        if time.monotonic() - last_publish > REPUBLISH_S:
                            self.publish()
                            last_publish = time.monotonic()
                        time.sleep(0.0002)
                    continue
                wall = time.monotonic()
                if last_cmd is not None:  # hanging on the gantry until the first command
                    self._physics(1)
                    if self.steps % self.odometry_every == 0:
                        self.publish_odometry()
                    if self.steps % self.steps_per_command == 0:
                        self._record()
                self.publish()
                delay = dt - (time.monotonic() - wall)
                if delay > 0:
                    time.sleep(delay)
        except KeyboardInterrupt:
            pass

    def save_trace(self, path: str | Path) -> None:
        """Per control period: the LowState tick, pelvis pose (7) and tracked sites (B, 3), as .npz."""
        from pipeline.common.atomic import atomic_file

        with atomic_file(path) as handle:
            np.savez(handle, tick=np.asarray(self.trace["tick"], dtype=np.int64),
                     qpos=np.asarray(self.trace["qpos"]).reshape(-1, 7),
                     site_xpos=np.asarray(self.trace["site_xpos"]).reshape(-1, len(self.sites), 3))
