"""Physics presets (robots/g1/robot.yaml `physics`, docs/physics.md): the baseline is today's settings, bad
presets are named errors, and the cheaper presets stay within a stated tolerance of the baseline on landings.

The landing: the G1 drops from 25 cm above its standing height at 1 m/s downward (2.4 m/s at touch-down, as the
far jump's landing) with some forward or sideways speed, and a fixed PD-target sequence crouches it after
touch-down to absorb the impact and raises it again. Both presets run it through the CPU backend (the env's
stepping path) and are compared at every control step (50 Hz: the only times the env reads the state under
either preset) over the flight, the touch-down and 0.36 s of absorption, before the leaning landing starts to
tip forward and chaos decides.

Tolerance (docs/physics.md): base position 3 cm, base orientation 3°, joint RMS 0.03 rad, each foot's
touch-down at the same control step or one later or earlier. Why these: 3 cm and 3° are small against what the env
scores — the lower body's tracking kernel pays exp(-0.03² / 0.1) = 0.99 of its reward for a 3 cm error,
and an episode succeeds within 1 m mean body error — and they sit well above the baseline's own
discretisation error (halving its timestep moves the same landings by at most 0.4 cm / 0.6°). Measured for
`fast`: at most 1.4 cm, 1.5°, 0.022 rad, touch-down one step apart; for `light` at most 0.4 cm, 0.4°, 0.008 rad,
same touch-down step.

A tighter tier, the size of the baseline's own timestep error (1 cm, 1°, 0.015 rad, same touch-down step), is
what a preset must also meet before it may replace the baseline where results are compared: `light` meets it,
`fast` does not, and a policy's falls after a landing came out differently under `fast` but not under `light`
(docs/physics.md). One 20 ms substep per control step breaks
the tolerance (6 cm, 6°, 0.07 rad), which shows the check can tell.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig
from pipeline.robot.assets import ROBOT_DIR
from pipeline.robot.g1 import PhysicsConfig, default_qpos, load_robot_config
from pipeline.sim.backend import make_backend
from pipeline.sim.model import build_sim_model

CONTROL_DT = 0.02
LANDING_STEPS = 25  # 0.5 s: 0.14 s of flight, then 0.36 s of absorption
TOLERANCE = {"base_pos_m": 0.03, "base_rot_deg": 3.0, "joint_rms_rad": 0.03, "touchdown_steps": 1}
AS_BASELINE = {"base_pos_m": 0.01, "base_rot_deg": 1.0, "joint_rms_rad": 0.015, "touchdown_steps": 0}
# (forward m/s, sideways m/s, forward pitch rad) at the start: straight at walking pace; faster and leaning
# forward; drifting sideways (rolls onto the outer edge of one foot)
LANDINGS = [(0.5, 0.0, 0.0), (0.8, 0.0, 0.05), (0.3, 0.3, 0.0)]


def _crouch_targets(robot, steps: int) -> np.ndarray:
    """PD targets per control step: the default pose, into a crouch right after touch-down, back up."""
    t = np.arange(steps) * CONTROL_DT
    crouch = np.zeros(robot.num_joints)
    for side in ("left", "right"):
        crouch[robot.joint_names.index(f"{side}_hip_pitch_joint")] = -0.35
        crouch[robot.joint_names.index(f"{side}_knee_joint")] = 0.6
        crouch[robot.joint_names.index(f"{side}_ankle_pitch_joint")] = -0.3
    weight = np.clip(np.minimum((t - 0.04) / 0.15, (0.6 - t) / 0.3), 0.0, 1.0)
    return robot.default_joint_pos + weight[:, None] * crouch


def land(physics, forward_speed: float, side_speed: float, pitch: float) -> dict[str, np.ndarray]:
    """The landing under `physics`, read after every control step: base position, orientation (wxyz),
    joints, and the control step at which each foot first touches (-1: never)."""
    robot = load_robot_config()
    backend = make_backend("cpu", build_sim_model(physics=physics), 1, nthread=0)
    qpos = default_qpos(robot)
    qpos[2] += 0.25
    qpos[3:7] = [np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0]
    qvel = np.zeros(backend.nv)
    qvel[0], qvel[1], qvel[2] = forward_speed, side_speed, -1.0
    backend.set_state([0], qpos[None], qvel[None])
    targets = torch.tensor(_crouch_targets(robot, LANDING_STEPS), dtype=torch.float32)
    qpos_rows, touchdown = [], np.full(2, -1)
    for k in range(LANDING_STEPS):
        backend.step(targets[k][None])
        qpos_rows.append(backend.get_state()[0][0])
        contact = backend.foot_contact[0].numpy()
        touchdown[(touchdown < 0) & contact] = k
    backend.close()
    q = np.array(qpos_rows)
    return {"pos": q[:, :3], "quat": q[:, 3:7], "joints": q[:, 7:], "touchdown": touchdown}


def deviation(run: dict, reference: dict) -> dict[str, float]:
    """The largest deviation of `run` from `reference` over the landing, in TOLERANCE's terms."""
    dot = np.clip(np.abs(np.sum(run["quat"] * reference["quat"], axis=1)), 0.0, 1.0)
    return {
        "base_pos_m": float(np.linalg.norm(run["pos"] - reference["pos"], axis=1).max()),
        "base_rot_deg": float(np.degrees(2.0 * np.arccos(dot)).max()),
        "joint_rms_rad": float(np.sqrt(np.mean((run["joints"] - reference["joints"]) ** 2, axis=1)).max()),
        "touchdown_steps": int(np.abs(run["touchdown"] - reference["touchdown"]).max()),
    }


def within_tolerance(dev: dict, tolerance: dict = TOLERANCE) -> bool:
    return all(dev[key] <= limit for key, limit in tolerance.items())


@pytest.fixture(scope="module")
def baseline_landings():
    return {landing: land("baseline", *landing) for landing in LANDINGS}


def test_baseline_preset_is_todays_physics():
    robot = load_robot_config()
    base = robot.physics("baseline")
    assert robot.default_physics == "baseline" and robot.sim_dt == 0.005 and robot.decimation == 4
    assert (base.timestep, base.integrator, base.cone, base.collisions) == (0.005, "implicitfast", "pyramidal", "all")
    assert base.foot_capsules == (1, 2, 3, 4, 5, 6, 7)
    model = build_sim_model()
    assert model.opt.timestep == 0.005 and int((model.geom_conaffinity > 0).sum()) == 34  # 33 robot collision geoms + ground
    for name, substeps in (("light", 4), ("fast", 2)):
        cheaper = build_sim_model(physics=name)
        assert int(round(CONTROL_DT / cheaper.opt.timestep)) == substeps
        assert int((cheaper.geom_conaffinity > 0).sum()) == 34 - 2 * (7 - len(robot.physics(name).foot_capsules))
        # every preset keeps every geom (drawing, Warp's model) and differs only in flags and options
        assert (cheaper.ngeom, cheaper.nbody, cheaper.nsensor) == (model.ngeom, model.nbody, model.nsensor)


def test_landing_has_a_flight_and_a_touchdown(baseline_landings):
    for reference in baseline_landings.values():
        assert ((reference["touchdown"] >= 5) & (reference["touchdown"] <= 12)).all()  # 0.1-0.24 s
        assert reference["pos"][:, 2].min() > 0.55 and reference["pos"][-1, 2] > 0.6  # no fall inside the window


@pytest.mark.parametrize("preset", ["light", "fast"])
@pytest.mark.parametrize("landing", LANDINGS)
def test_cheaper_presets_land_within_tolerance_of_baseline(baseline_landings, landing, preset):
    dev = deviation(land(preset, *landing), baseline_landings[landing])
    assert within_tolerance(dev), f"{preset} vs baseline on landing {landing}: {dev}, tolerance {TOLERANCE}"


def test_light_preset_is_as_close_as_the_baselines_own_timestep_error(baseline_landings):
    refined = PhysicsConfig("baseline_half_timestep", timestep=0.0025)
    for landing in LANDINGS:
        reference = baseline_landings[landing]
        assert within_tolerance(deviation(land(refined, *landing), reference), AS_BASELINE)  # the tier's yardstick
        dev = deviation(land("light", *landing), reference)
        assert within_tolerance(dev, AS_BASELINE), f"light vs baseline on landing {landing}: {dev}, tier {AS_BASELINE}"
    fast = [deviation(land("fast", *landing), baseline_landings[landing]) for landing in LANDINGS]
    assert not all(within_tolerance(dev, AS_BASELINE) for dev in fast), fast


def test_a_too_coarse_preset_breaks_the_tolerance(baseline_landings):
    one_substep = PhysicsConfig("one_substep", timestep=CONTROL_DT)
    devs = [deviation(land(one_substep, *landing), baseline_landings[landing]) for landing in LANDINGS]
    assert not all(within_tolerance(dev) for dev in devs), devs


def test_unknown_preset_is_named_error():
    with pytest.raises(PipelineInputError, match="env: physics: unknown physics preset 'warp_speed'"):
        EnvConfig.from_dict({"physics": "warp_speed"})
    with pytest.raises(PipelineInputError, match="unknown physics preset"):
        build_sim_model(physics="warp_speed")


@pytest.mark.parametrize("edit, bad, field", [
    ("timestep: 0.005", "timestep: -1", "physics.presets.baseline.timestep"),
    ("timestep: 0.005", "timestep: 0.003", "physics.presets.baseline.timestep"),  # 0.02 s is no whole number of it
    ("cone: pyramidal", "cone: round", "physics.presets.baseline.cone"),
    ("foot_capsules: [1, 2, 3, 4, 5, 6, 7]", "foot_capsules: [0, 9]", "physics.presets.baseline.foot_capsules"),
    ("default: baseline", "default: turbo", "physics.default"),
])
def test_bad_physics_block_names_the_key(tmp_path: Path, edit: str, bad: str, field: str):
    text = (ROBOT_DIR / "robot.yaml").read_text()
    assert edit in text
    path = tmp_path / "robot.yaml"
    path.write_text(text.replace(edit, bad, 1))
    with pytest.raises(PipelineInputError, match=field.replace(".", r"\.")):
        load_robot_config(path)
