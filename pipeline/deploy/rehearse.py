"""`adamimic rehearse`: `deploy` against `sim-bridge` over loopback, the way the robot will run it.

For each ψ: a bridge process starts the G1 on its virtual gantry (real time, 500 Hz motor law), and
`deploy` runs with its real default timings (damping, ramp, the balance policy standing, the go after
`stand_s`), the task, and the balance policy for `after_s` more. The bridge's trace is then judged
with the chain's definitions (export/chain.py): the paper's success on the task stretch from the
tracked sites at each policy step, `standing` at the chain's `after_s` after the handoff with no fall
check fired before, and `rest_to_rest`. One JSON line per ψ.

The watchdog's joint check runs with `SIM_JOINT_MARGIN_RAD`: MuJoCo's joint limits are soft, and the
landings the policies trained on press an ankle up to 0.32 rad past its range (sim2sim chains of the
step down that stand), where a robot's mechanical stop holds it. Each line reports that excursion
(`joint_past_limit_rad`) so a policy that leans on it is seen before it meets the robot.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.deploy.safety import SafetyConfig
from pipeline.deploy.transport import ODOMETRY_TOPIC

SIM_JOINT_MARGIN_RAD = 0.4


def _bridge(export_dir: Path, psi: float, domain: int, trace: Path, gantry_s: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", "sim-bridge", str(export_dir), "--psi", str(psi),
                             "--interface", "lo", "--domain", str(domain), "--trace", str(trace),
                             "--gantry-s", str(gantry_s)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def judge_trace(export_dir: Path, psi: float, report, trace: dict, chain: dict) -> dict:
    """The chain's verdicts from the bridge's trace and the controller's report."""
    from pipeline.export.chain import balance_fallen, end_ground, judge_standing, read_chain
    from pipeline.export.policy_step import projected_gravity
    from pipeline.export.sim2sim import EpisodeJudge, Sim2Sim, build_scene

    task = Sim2Sim(export_dir)
    meta = task.meta
    balance_meta = json.loads((export_dir / read_chain(export_dir)["balance"] / "policy.json").read_text())
    model = build_scene(meta, psi)
    ticks = np.asarray(trace["tick"])
    control_ms = int(round(1000 * float(meta["control_dt"])))
    targets = task.keyframe_targets(psi)
    judge = EpisodeJudge(meta, psi, targets)

    def after(state_tick: int) -> int:  # the trace row just after the command acted on `state_tick`
        return int(min(np.searchsorted(ticks, state_tick + control_ms), len(ticks) - 1))

    fell = None
    for phase, tick in zip(report.phases, report.state_ticks):
        row = after(tick)
        qpos = trace["qpos"][row]
        fell = judge.update(phase, trace["site_xpos"][row], projected_gravity(qpos[3:7]), float(qpos[2]))
        if fell not in (None, "done"):
            break
    handed_over = bool(report.phases) and report.phases[-1] >= float(chain["handoff_phase"]) - 1e-6 and fell in (None, "done")
    success = handed_over and judge.success_through(float(chain["handoff_phase"]))  # the chain's rule (export/chain.py)
    standing = False
    if handed_over:
        start = after(report.state_ticks[-1])
        stop = int(np.searchsorted(ticks, ticks[start] + int(round(1000 * float(chain["after_s"])))))
        if stop < len(ticks) and report.end != "fault":
            fallen = any(balance_fallen(model, trace["qpos"][r], balance_meta["terminations"]) is not None
                         for r in range(start, stop + 1))
            qpos = trace["qpos"][stop]
            speed = float(np.linalg.norm(trace["qpos"][stop][0:3] - trace["qpos"][stop - 1][0:3])) / (control_ms / 1000.0)
            standing = not fallen and judge_standing(model, qpos, speed, end_ground(model, targets))
    return {"psi": float(psi), "keyframe_errors": [round(e, 4) for e in judge.errors], "success": bool(success),
            "standing": bool(standing), "rest_to_rest": bool(success and standing), "deploy_end": report.end,
            "deploy_message": report.message, "joint_past_limit_rad": round(float(report.joint_past_limit_rad), 3),
            "modes": [mode for _, mode in report.modes],
            "stood_before_go_s": _stood_before_go(report.modes, float(meta["control_dt"]))}


def _stood_before_go(modes: list[tuple[int, str]], control_dt: float) -> float | None:
    """Seconds the balance policy held the robot before the go (None: no go)."""
    ticks = {}
    for tick, mode in modes:
        ticks.setdefault(mode, tick)
    return round((ticks["policy"] - ticks["stand"]) * control_dt, 3) if {"stand", "policy"} <= set(ticks) else None


def rehearse(export_dir: str | Path, psi_values, *, safety: SafetyConfig | None = None, keep_s: float = 5.0,
             log=lambda line: print(line, file=sys.stderr, flush=True)) -> list[dict]:
    """One rehearsal per ψ (module docstring); `keep_s`: how long deploy keeps the balance policy after the task."""
    from pipeline.deploy.controller import run_deploy
    from pipeline.export.chain import read_chain

    export_dir = Path(export_dir)
    chain = read_chain(export_dir)  # an export without its balance policy is refused before anything starts
    safety = safety or SafetyConfig(joint_margin_rad=SIM_JOINT_MARGIN_RAD)
    safety = dataclasses.replace(safety, hold_after_s=keep_s)
    results = []
    for psi in psi_values:
        domain = random.Random(os.getpid() + int(time.time() * 1000)).randrange(100, 230)
        with tempfile.TemporaryDirectory(prefix="adamimic-rehearse-") as scratch:
            trace_path = Path(scratch) / "trace.npz"
            bridge = _bridge(export_dir, float(psi), domain, trace_path, safety.damping_s + safety.ramp_s)
            try:
                report = run_deploy(export_dir, float(psi), interface="lo", domain_id=domain, go_flag=True,
                                    safety=safety, odometry_topic=ODOMETRY_TOPIC)
            finally:
                bridge.terminate()
                _, err = bridge.communicate(timeout=30)
            if not trace_path.is_file():
                raise RuntimeError(f"sim-bridge wrote no trace (exit {bridge.returncode}): {err.strip()[-400:]}")
            with np.load(trace_path) as npz:
                trace = {k: npz[k] for k in npz.files}
        result = judge_trace(export_dir, float(psi), report, trace, chain)
        log(f"rehearse: ψ {psi:g}: {result['deploy_end']}, rest_to_rest {result['rest_to_rest']}")
        results.append(result)
    return results
