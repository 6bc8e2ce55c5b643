"""A skill as a chain that starts and ends standing: stand (balance) → go → task → balance.

An export folder holds the task policy (policy.onnx + policy.json), the balance policy in `balance/`
(its own export) and `chain.json`, the handoff rule:

    {"balance": "balance", "handoff_phase": 1.0, "stand_s": 2.0, "after_s": 3.0}

The balance policy holds the robot at the stance; on the go the task policy runs from phase 0 with a
fresh observation history; when the task's phase reaches `handoff_phase` the balance policy takes
over, again with a fresh history. `ChainRunner` runs that chain in MuJoCo from the stance at rest (the
robot where `adamimic deploy` puts it before the go) with only the ONNX files and the metadata, like
`Sim2Sim`, and judges it:

  success       the paper's test on the task stretch (every keyframe within 1 m, no fall);
  standing      `after_s` after the handoff, with the balance policy in charge, no fall check fired
                since the go and `pipeline.envs.falls.STANDING` holds (upright, pelvis high above the
                ground under it, base still, on the ground the reference ends on);
  rest_to_rest  both.

The evaluation, `adamimic sim2sim` and `adamimic rehearse` all judge with `judge_standing` below.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.envs.falls import STANDING, fall_flags
from pipeline.export.policy_step import METADATA_NAME, PolicyStepper, projected_gravity, rotate_z, yaw_of

CHAIN_NAME = "chain.json"
BALANCE_DIR = "balance"
DEFAULT_CHAIN = {"balance": BALANCE_DIR, "handoff_phase": 1.0, "stand_s": 2.0, "after_s": 3.0}


# ------------------------------------------------------------------------------ the folder
def write_chain(export_dir: str | Path, balance_export: str | Path, **overrides) -> dict:
    """Copies the balance export into `export_dir/balance` and writes chain.json (inside a staging
    folder the caller makes atomic)."""
    balance_export = Path(balance_export)
    for name in ("policy.onnx", METADATA_NAME):
        if not (balance_export / name).is_file():
            raise PipelineInputError(balance_export / name, None,
                                     "the balance policy's export is missing (stages/train_balance.py writes it)")
    chain = dict(DEFAULT_CHAIN, **overrides)
    target = Path(export_dir) / chain["balance"]
    shutil.copytree(balance_export, target, dirs_exist_ok=True)
    (Path(export_dir) / CHAIN_NAME).write_text(json.dumps(chain, indent=1))
    return chain


def handoff_phase(data, after_landing_s: float | None) -> float:
    """The phase a task's chain hands over at: `after_landing_s` after its last landing keyframe (clip
    `handoff_after_landing_s`), or the end of the phase (None, or a task without a landing)."""
    if after_landing_s is None:
        return 1.0
    frames = [f for f, label in zip(data.keyframe_frames, data.keyframe_labels) if str(label).startswith("landing")]
    if not frames:
        raise PipelineInputError(f"task {data.task}", "clip.handoff_after_landing_s",
                                 "the task has no keyframe labelled landing to count from")
    last = data.motion.num_frames - 1
    return float(min(1.0, (frames[-1] + after_landing_s * data.motion.fps) / last))


def read_chain(export_dir: str | Path) -> dict:
    """chain.json of an export, checked: its balance folder exists, the handoff lies within the task."""
    export_dir = Path(export_dir)
    path = export_dir / CHAIN_NAME
    if not path.is_file():
        raise PipelineInputError(path, None, "this export has no balance policy to start and end standing with "
                                 "(re-run the export stage, which adds the balance policy of params.yaml balance.out)")
    try:
        chain = dict(DEFAULT_CHAIN, **json.loads(path.read_text()))
    except json.JSONDecodeError as error:
        raise PipelineInputError(path, None, f"not valid JSON ({error})") from None
    if not (export_dir / chain["balance"] / "policy.onnx").is_file():
        raise PipelineInputError(path, "balance", f"{export_dir / chain['balance']} holds no balance policy.onnx")
    if not 0.0 < float(chain["handoff_phase"]) <= 1.0:
        raise PipelineInputError(path, "handoff_phase", f"{chain['handoff_phase']} is past the end of the task (phase 1)"
                                 if float(chain["handoff_phase"]) > 1.0 else "must be in (0, 1]")
    for key in ("stand_s", "after_s"):
        if not float(chain[key]) >= 0.0:
            raise PipelineInputError(path, key, "must be >= 0 seconds")
    return chain


# ------------------------------------------------------------------------------ the judge
def ground_height_under(model: mujoco.MjModel, x: float, y: float) -> float:
    """Top of the highest world geom under (x, y): planes everywhere, boxes within their extent."""
    top = -np.inf
    for g in np.flatnonzero(model.geom_bodyid == 0):
        kind, pos, size = model.geom_type[g], model.geom_pos[g], model.geom_size[g]
        if kind == mujoco.mjtGeom.mjGEOM_PLANE:
            top = max(top, float(pos[2]))
        elif kind == mujoco.mjtGeom.mjGEOM_BOX and abs(x - pos[0]) <= size[0] and abs(y - pos[1]) <= size[1]:
            top = max(top, float(pos[2] + size[2]))
    return top if np.isfinite(top) else 0.0


def end_ground(model: mujoco.MjModel, keyframe_targets: np.ndarray) -> float:
    """The ground the reference ends on: under its last keyframe's tracked bodies (their mean x, y) at this ψ."""
    x, y = np.asarray(keyframe_targets)[-1, :, 0:2].mean(0)
    return ground_height_under(model, float(x), float(y))


def judge_standing(model: mujoco.MjModel, qpos: np.ndarray, speed: float, ground: float | None = None) -> bool:
    """`STANDING` of one robot state: upright, high above the ground under the pelvis, moving at `speed`
    (m/s), on `ground` (the height `end_ground` gives; None: whatever ground it is on)."""
    under = ground_height_under(model, float(qpos[0]), float(qpos[1]))
    return STANDING(projected_gravity(qpos[3:7])[:2], float(qpos[2]) - under, speed,
                    0.0 if ground is None else under - ground)


def balance_fallen(model, qpos: np.ndarray, terminations: dict) -> str | None:
    """The balance policy's fall checks (absolute, height above the ground under the pelvis)."""
    height = float(qpos[2]) - ground_height_under(model, float(qpos[0]), float(qpos[1]))
    by_tilt, by_height = fall_flags(projected_gravity(qpos[3:7])[:2], height, float(terminations["max_tilt"]),
                                    terminations.get("min_base_height"))
    return "tilt" if by_tilt else "height" if by_height else None


# ------------------------------------------------------------------------------ the run
@dataclass
class ChainResult:
    psi: float
    success: bool  # the paper's test on the task stretch
    standing: bool
    rest_to_rest: bool
    end: str  # "standing", "not_standing", or the check that ended it: "tilt", "height", "keyframe_error", "max_steps"
    ended_in: str  # "stand", "task" or "balance"
    keyframe_errors: list[float]
    steps: dict = field(default_factory=dict)  # control steps of each stretch
    final_base_pos: list[float] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"psi": self.psi, "success": self.success, "standing": self.standing, "rest_to_rest": self.rest_to_rest,
                "end": self.end, "ended_in": self.ended_in, "keyframe_errors": self.keyframe_errors, "steps": self.steps}


def stance_state(meta: dict, model: mujoco.MjModel, stance_height: float) -> tuple[np.ndarray, np.ndarray]:
    """The default pose at rest on the ground, where and facing as the task's first frame starts."""
    start = np.asarray(meta["initial_state"]["qpos"], dtype=np.float64)
    yaw = yaw_of(start[3:7])
    qpos = np.zeros(model.nq)
    qpos[0:2] = start[0:2]
    qpos[2] = stance_height + ground_height_under(model, start[0], start[1])
    qpos[3:7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    qpos[7:] = meta["default_joint_pos"]
    return qpos, np.zeros(model.nv)


class DelayedTargets:
    """Joint targets as the motors see them `delay_s` after they were sent, substep by substep."""

    def __init__(self, delay_s: float, sim_dt: float):
        self.lag = int(round(delay_s / sim_dt))  # substeps
        self.substep = 0
        self.sent: list[tuple[int, np.ndarray]] = []  # (substep sent at, targets)

    def hold(self, targets) -> None:
        """What the motors hold before anything was sent."""
        self.sent = [(-(10**9), np.asarray(targets, dtype=np.float64).copy())]

    def send(self, targets) -> None:
        self.sent.append((self.substep, np.asarray(targets, dtype=np.float64).copy()))

    def applied(self) -> np.ndarray:
        due = self.substep - self.lag
        while len(self.sent) > 1 and self.sent[1][0] <= due:
            self.sent.pop(0)
        self.substep += 1
        return self.sent[0][1]


def control_step(stepper, state, delay: DelayedTargets, actuators, decimation: int, **extra):
    """One control step in MuJoCo: `stepper`'s policy on the measured `state` (a sim2sim RobotState), its joint
    targets through the motors' `delay`, `decimation` physics substeps. Returns the policy's output."""
    out = stepper.step(base_ang_vel=state.base_ang_vel(), projected_gravity=state.projected_gravity(),
                       joint_pos=state.joint_pos(), joint_vel=state.joint_vel(), **extra)
    delay.send(out.joint_targets)
    for _ in range(decimation):
        state.data.ctrl[actuators] = delay.applied()
        mujoco.mj_step(state.model, state.data)
    return out


class ChainRunner:
    """The chain of one export in MuJoCo (see the module docstring)."""

    def __init__(self, export_dir: str | Path, **chain_overrides):
        from pipeline.export.sim2sim import Sim2Sim, load_exported

        export_dir = Path(export_dir)
        self.chain = dict(read_chain(export_dir), **chain_overrides)
        self.task = Sim2Sim(export_dir)
        self.balance_session, self.balance_meta = load_exported(export_dir / self.chain["balance"])
        if self.balance_meta.get("kind") != "balance":
            raise PipelineInputError(export_dir / self.chain["balance"] / METADATA_NAME, "kind", "is not a balance policy")
        if self.balance_meta["joint_names"] != self.task.meta["joint_names"]:
            raise PipelineInputError(export_dir / self.chain["balance"] / METADATA_NAME, "joint_names",
                                     "differ from the task policy's")
        self.balance = PolicyStepper(self.balance_session, self.balance_meta)
        self.control_dt = self.task.control_dt

    def run(self, psi: float, *, on_step: Callable | None = None, visual: bool = False,
            randomize: Callable[[mujoco.MjModel], float] | None = None) -> ChainResult:
        """One chain at ψ. `randomize(model)` may change the model (domain randomisation) and returns a
        control delay in seconds: each substep then applies the joint targets sent that long before."""
        from pipeline.export.sim2sim import EpisodeJudge, RobotState, build_scene, check_psi

        m, chain = self.task.meta, self.chain
        check_psi(m, psi)
        model = build_scene(m, psi, visual=visual)
        delay = DelayedTargets(randomize(model) if randomize is not None else 0.0, model.opt.timestep)
        data = mujoco.MjData(model)
        joints = [model.joint(n).id for n in m["joint_names"]]
        state = RobotState(model, data, model.jnt_qposadr[joints], model.jnt_dofadr[joints])
        actuators = np.array([model.actuator(n).id for n in m["joint_names"]])
        sites = np.array([model.site(n).id for n in m["tracked_site_names"]])
        data.qpos[:], data.qvel[:] = stance_state(m, model, float(self.balance_meta["stance"]["root_height"]))
        mujoco.mj_forward(model, data)
        delay.hold(data.qpos[7:])
        targets = self.task.keyframe_targets(psi)
        judge = EpisodeJudge(m, psi, targets)
        stand_steps, after_steps = int(round(chain["stand_s"] / self.control_dt)), int(round(chain["after_s"] / self.control_dt))
        steps = {"stand": 0, "task": 0, "balance": 0}  # control steps each stretch ran
        counter = {"step": 0}

        def advance(stepper, stretch: str, **extra) -> object:
            out = control_step(stepper, state, delay, actuators, self.task.decimation, **extra)
            counter["step"] += 1
            steps[stretch] += 1
            if on_step is not None:
                on_step(model, data, {"stretch": stretch, "phase": out.phase if stretch == "task" else None,
                                      "psi": psi, "keyframe_targets": targets, "step": counter["step"],
                                      "reached": len(judge.errors)})
            return out

        def finish(end: str, ended_in: str, standing: bool = False) -> ChainResult:
            # the task stretch succeeded when it handed over with every keyframe up to the handoff within the threshold
            success = ended_in == "balance" and judge.success_through(float(chain["handoff_phase"]))
            return ChainResult(float(psi), bool(success), bool(standing), bool(success and standing), end, ended_in,
                               list(judge.errors), dict(steps), data.qpos[0:3].tolist())

        def hold(count: int, stretch: str) -> str | None:
            """`count` control steps of the balance policy from a fresh history: the fall that ended them, or None."""
            self.balance.reset()
            for _ in range(count):
                advance(self.balance, stretch, psi=0.0)
                fallen = balance_fallen(model, data.qpos, self.balance_meta["terminations"])
                if fallen is not None:
                    return fallen
            return None

        fallen = hold(stand_steps, "stand")
        if fallen is not None:
            return finish(fallen, "stand")

        task = self.task.stepper
        task.reset()
        origin, origin_yaw = data.qpos[0:3].copy(), yaw_of(data.qpos[3:7])
        while True:
            odometry = rotate_z(data.qpos[0:3] - origin, -origin_yaw) if task.odometry_due() else None
            out = advance(task, "task", psi=psi, odometry=odometry)
            verdict = judge.update(out.phase, data.site_xpos[sites], state.projected_gravity(), float(data.qpos[2]))
            if verdict not in (None, "done"):
                return finish(verdict, "task")
            if out.phase >= float(chain["handoff_phase"]) - 1e-9:
                break
            if steps["task"] >= task.max_steps:
                return finish("max_steps", "task")

        fallen = hold(after_steps, "balance")
        if fallen is not None:
            return finish(fallen, "balance")
        standing = judge_standing(model, data.qpos, float(np.linalg.norm(data.qvel[0:3])), end_ground(model, targets))
        return finish("standing" if standing else "not_standing", "balance", standing)


def run_chain(export_dir: str | Path, psi_values, **chain_overrides) -> dict:
    """Chains at the given ψ values: the success and rest_to_rest rates (%) and each episode."""
    runner = ChainRunner(export_dir, **chain_overrides)
    results = [runner.run(float(psi)) for psi in psi_values]
    rate = lambda key: 100.0 * float(np.mean([getattr(r, key) for r in results])) if results else float("nan")  # noqa: E731
    return {"task": runner.task.meta["task"], "chain": runner.chain, "success": rate("success"),
            "standing": rate("standing"), "rest_to_rest": rate("rest_to_rest"),
            "episodes": [r.to_json() for r in results]}


class LiveChain:
    """The chain one control step at a time, for a viewer: the balance policy holds the robot until `go()`
    (counted after `stand_s`), the task runs to its handoff (or a fall), then the balance policy again.
    `restart(psi)` puts the robot back at the stance and moves the terrain to ψ, in the same model."""

    def __init__(self, runner: ChainRunner, psi: float):
        from pipeline.export.sim2sim import RobotState, build_scene

        m = runner.task.meta
        self.runner, self.meta = runner, m
        self.model = build_scene(m, psi, visual=True)
        self.data = mujoco.MjData(self.model)
        joints = [self.model.joint(n).id for n in m["joint_names"]]
        self.state = RobotState(self.model, self.data, self.model.jnt_qposadr[joints], self.model.jnt_dofadr[joints])
        self.actuators = np.array([self.model.actuator(n).id for n in m["joint_names"]])
        self.sites = np.array([self.model.site(n).id for n in m["tracked_site_names"]])
        self.restart(psi)

    def restart(self, psi: float) -> None:
        from pipeline.export.sim2sim import EpisodeJudge, terrain_layout_at

        self.psi = float(psi)
        for name, (pos, size) in terrain_layout_at(self.meta, self.psi).items():
            self.model.geom_pos[self.model.geom(name).id], self.model.geom_size[self.model.geom(name).id] = pos, size
        self.data.qpos[:], self.data.qvel[:] = stance_state(self.meta, self.model,
                                                            float(self.runner.balance_meta["stance"]["root_height"]))
        mujoco.mj_forward(self.model, self.data)
        self.judge = EpisodeJudge(self.meta, self.psi, self.runner.task.keyframe_targets(self.psi))
        self.stretch, self.substep, self.control_steps, self.go_asked, self.end = "stand", 0, 0, False, None
        self.runner.balance.reset()

    def go(self) -> None:
        self.go_asked = True

    def status(self) -> str:
        text = {"stand": "standing on the balance policy" + (" (go pressed)" if self.go_asked else ": press go"),
                "task": f"the task, phase {self.runner.task.stepper.phase:.2f}",
                "balance": "the balance policy took over"}[self.stretch]
        return f"ψ {self.psi:.2f} m: {text}" + (f"; {self.end}" if self.end else "")

    def _control(self) -> None:
        s, chain, task = self.state, self.runner.chain, self.runner.task.stepper
        measured = dict(base_ang_vel=s.base_ang_vel(), projected_gravity=s.projected_gravity(),
                        joint_pos=s.joint_pos(), joint_vel=s.joint_vel())
        if self.stretch == "stand" and self.go_asked and self.control_steps * self.runner.control_dt >= chain["stand_s"]:
            self.stretch, self.origin = "task", (self.data.qpos[0:3].copy(), yaw_of(self.data.qpos[3:7]))
            task.reset()
        if self.stretch == "task":
            odometry = rotate_z(self.data.qpos[0:3] - self.origin[0], -self.origin[1]) if task.odometry_due() else None
            out = task.step(psi=self.psi, odometry=odometry, **measured)
            verdict = self.judge.update(out.phase, self.data.site_xpos[self.sites], s.projected_gravity(),
                                        float(self.data.qpos[2]))
            if verdict not in (None, "done") or out.phase >= float(chain["handoff_phase"]) - 1e-9:
                self.end = f"the task ended: {verdict or 'handed over'}"
                self.stretch = "balance"
                self.runner.balance.reset()
        else:
            out = self.runner.balance.step(psi=0.0, **measured)
        self.data.ctrl[self.actuators] = out.joint_targets
        self.control_steps += 1

    def step(self) -> None:
        """One physics substep; a control step every `decimation` of them."""
        if self.substep % self.runner.task.decimation == 0:
            self._control()
        mujoco.mj_step(self.model, self.data)
        self.substep += 1

