"""Step latency of `adamimic deploy` against the MuJoCo sim bridge over DDS, on 2 cores.

Runs from the repository root with no arguments. A policy of the trained architecture (the default
NetworkConfig: actor 512-256-128, adapters 256-128; random weights, as only the cost matters) is
exported for a 10 s standing clip; `adamimic sim-bridge` runs the G1 in real time at 500 Hz in a
second process and the controller runs one episode at 50 Hz, both pinned to the same 2 cores.
Latency per policy step: from taking the LowState (CRC and motor-count check) through the
observation, the ONNX run, the clamps and the signed LowCmd until it is written to DDS. Prints one
summary line with p50/p99/max. The watchdog's tilt and joint checks are widened so that the random
policy's fall does not end the run early; everything else is the deploy path as shipped.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CORES = 2
SECONDS = 10.0


def _standing_data(seconds: float):
    from pipeline.keyframes.tracking_data import TrackingData
    from pipeline.motion.motion import RobotKinematics
    from pipeline.robot.g1 import default_qpos, load_robot_config

    q = default_qpos(load_robot_config())
    frames = int(seconds * 50)
    motion = RobotKinematics().motion(50.0, np.tile(q[:3], (frames, 1)), np.tile(q[3:7], (frames, 1)),
                                      np.tile(q[7:], (frames, 1)))
    psi = np.linspace(1.0, 2.0, 11)
    offsets = np.zeros((11, 2, 3))
    offsets[:, 1, 0] = psi - 1.0
    return TrackingData(task="far_jump", motion=motion, keyframe_frames=np.array([frames // 4, frames - 10]),
                        keyframe_labels=("", "landing"), sparse_scale=np.array([1.0, 50.0]),
                        edited=np.array([False, True]), psi=psi, keyframe_offsets=offsets, psi_raw=1.0,
                        psi_ranges={"easy": [(1.0, 1.5)], "hard": [(1.5, 2.0)]})


def _export(tmp: Path) -> Path:
    import torch

    from pipeline.envs.config import EnvConfig
    from pipeline.export.metadata import observation_layout
    from pipeline.export.onnx_export import export_variant
    from pipeline.rl.checkpoint import save_policy
    from pipeline.rl.config import NetworkConfig
    from pipeline.rl.networks import DoubleCritic, Stage1Policy
    from pipeline.rl.stage2 import Stage2Policy
    from pipeline.robot.g1 import load_robot_config

    torch.manual_seed(0)
    cfg, net = load_robot_config(), NetworkConfig()
    obs_dim = observation_layout(cfg, history=EnvConfig().observations.history)["dim"]
    data = _standing_data(SECONDS)
    rate = cfg.control_dt / data.motion.duration
    policy = Stage2Policy(Stage1Policy(obs_dim, 27, net.actor_hidden, phase_rate=rate), net.adapter_hidden,
                          phase_rate=rate)
    meta = {"robot": cfg.name, "task": "far_jump", "variant": "adamimic", "stage": 2,
            "joint_names": list(cfg.joint_names), "action_dim": 27, "actor_obs_dim": obs_dim,
            "critic_obs_dim": obs_dim, "phase_rate": rate,
            "architecture": {"actor_hidden": net.actor_hidden, "critic_hidden": [16],
                             "adapter_hidden": net.adapter_hidden, "activation": "elu", "freeze_base": True,
                             "normalize_obs": True}}
    save_policy(tmp / "final", policy, DoubleCritic(obs_dim, [16]), meta)
    return export_variant(task="far_jump", variant="adamimic", data=data, policy_dir=tmp / "final",
                          out_dir=tmp / "export", env_cfg=EnvConfig()).folder


def main() -> None:
    from pipeline.deploy.controller import run_deploy
    from pipeline.deploy.safety import SafetyConfig

    cores = sorted(os.sched_getaffinity(0))[:CORES]
    os.sched_setaffinity(0, cores)
    domain = random.randint(1, 230)
    with tempfile.TemporaryDirectory() as tmp:
        export = _export(Path(tmp))
        bridge = subprocess.Popen(["taskset", "-c", ",".join(map(str, cores)), sys.executable, "-m", "pipeline.cli",
                                   "sim-bridge", str(export), "--psi", "1.4", "--interface", "lo",
                                   "--domain", str(domain)], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                                  stderr=subprocess.DEVNULL)
        try:
            report = run_deploy(export, 1.4, interface="lo", domain_id=domain, go_flag=True,
                                odometry_topic="rt/adamimic/odometry",
                                safety=SafetyConfig(damping_s=0.2, ramp_s=0.5, hold_after_s=0.1, max_tilt_rad=3.1,
                                                    joint_margin_rad=10.0, first_state_timeout_s=30.0))
        finally:
            bridge.send_signal(signal.SIGTERM)
            bridge.wait(timeout=30)
    ms = 1000 * np.asarray(report.step_latency_s)
    if report.end not in ("done", "max_steps") or ms.size < 100:
        sys.exit(f"deploy_latency: run ended early ({report.end}: {report.message}), {ms.size} steps")
    print(f"deploy_latency: controller step p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
          f"max {ms.max():.2f} ms over {ms.size} policy steps at 50 Hz (budget 20 ms; {len(cores)} cores shared "
          f"with the 500 Hz sim bridge)")


if __name__ == "__main__":
    main()
