"""One ONNX graph for the deployed policy, its metadata, parity check and the hub-format folder.

The graph is the whole deployed controller: observation history (raw, as the robot measures it)
→ normalisation → stage-1 actor + adapters → (joint position targets, raw action, Δφ^Δ).
The raw action is an output too because the next observation contains it (previous action).
Metadata lives inside the ONNX (`metadata_props`, one key per entry, JSON values) and beside it
as `policy.json`, so a deployment script needs nothing else.
"""

from __future__ import annotations

import json
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pipeline.common.atomic import atomic_dir
from pipeline.common.errors import PipelineInputError

ONNX_NAME = "policy.onnx"
METADATA_NAME = "policy.json"
HUB_FILES = ("config.json", "model.safetensors")
INPUT_NAME = "obs"
OUTPUT_NAMES = ("joint_targets", "action", "phase_rate_offset")
# rad (joint targets) and action units, of a sample's largest output where it passes 1: float32 rounding through the
# network on the parity check's wide random inputs reaches 2e-5 at outputs of order 1 and grows with them (7e-7 of a
# balance policy's raw action of 156 there); 1e-4 rad is below a G1 joint encoder's step (2π / 2^14 ≈ 3.8e-4 rad)
PARITY_TOLERANCE = 1e-4
OPSET = 17


class DeployedPolicy(nn.Module):
    """Wraps a policy module (stage 1 alone, or stage 1 + adapters) into the deployed interface.

    `policy(obs)` returns the joint action a, or a tuple (a, Δφ^Δ) — the composed stage-2 module.
    `normalizer`, when given, maps raw observations to the policy's input (else the policy
    normalises itself). Joint targets = offset + action_scale · a, where the offset is the default
    pose, or — for a policy trained with `env.action_offset: reference` or `feedforward` — that
    offset's per-frame table (envs/feedforward.py: `zero_action_targets`) at the frame the step ends
    on: round(φ'·(T − 1)) with φ' = φ + rate + clamp(Δφ^Δ, −0.75·rate, rate) and φ read from the
    newest step of the raw observation, exactly as the env steps. With a push prior
    (priors/push_prior.py) the offset also carries w(ψ) · push[frame], ψ read from the same step.
    """

    def __init__(self, policy: nn.Module, default_joint_pos, action_scale, normalizer: nn.Module | None = None,
                 reference: "ReferenceOffset | None" = None):
        super().__init__()
        self.policy = policy
        self.normalizer = normalizer
        self.register_buffer("default_joint_pos", torch.as_tensor(np.asarray(default_joint_pos), dtype=torch.float32))
        self.register_buffer("action_scale", torch.as_tensor(np.asarray(action_scale), dtype=torch.float32))
        self.reference = reference
        if reference is not None:
            self.register_buffer("reference_joint_targets", torch.as_tensor(np.asarray(reference.joint_targets), dtype=torch.float32))
        if reference is not None and reference.push_offsets is not None:
            as_f32 = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
            psi, w = np.asarray(reference.psi_anchors, np.float64), np.asarray(reference.weight_anchors, np.float64)
            self.register_buffer("push_offsets", as_f32(reference.push_offsets))
            # w(ψ) as the first anchor's weight plus one clamped ramp per anchor interval: ops ONNX has
            self.register_buffer("psi_knots", as_f32(psi[:-1]))
            self.register_buffer("psi_spans", as_f32(np.diff(psi)))
            self.register_buffer("weight_slopes", as_f32(np.diff(w) / np.diff(psi)))
            self.register_buffer("weight_first", as_f32(w[:1]))

    def _offset(self, obs: torch.Tensor, phase_rate_offset: torch.Tensor) -> torch.Tensor:
        if self.reference is None:
            return self.default_joint_pos
        rate = self.reference.phase_rate
        phase = obs[:, self.reference.phase_index: self.reference.phase_index + 1]
        phase = phase + rate + phase_rate_offset.clamp(-0.75 * rate, rate)
        last = self.reference_joint_targets.shape[0] - 1
        frame = torch.round(phase * last).clamp(0, last).long().reshape(-1)
        if self.reference.push_offsets is None:
            return self.reference_joint_targets[frame]
        return self.reference_joint_targets[frame] + self._push_weight(obs) * self.push_offsets[frame]

    def _push_weight(self, obs: torch.Tensor) -> torch.Tensor:
        """(N, 1) w(ψ) of the push prior at the observed ψ: `PushPrior.weight`, as clamped ramps."""
        index = self.reference.psi_index
        psi = obs[:, index: index + 1]
        ramps = torch.minimum(torch.relu(psi - self.psi_knots), self.psi_spans)  # (N, A - 1)
        return self.weight_first + (ramps * self.weight_slopes).sum(-1, keepdim=True)

    def forward(self, obs: torch.Tensor):
        x = self.normalizer(obs) if self.normalizer is not None else obs
        out = self.policy(x)
        if isinstance(out, (tuple, list)):
            action, phase_rate_offset = out[0], out[1]
        else:
            action, phase_rate_offset = out, torch.zeros_like(out[..., :1])
        phase_rate_offset = phase_rate_offset.reshape(action.shape[0], 1)
        targets = self._offset(obs, phase_rate_offset) + self.action_scale * action
        return targets, action, phase_rate_offset


@dataclass(frozen=True)
class ReferenceOffset:
    """What the graph needs to add the per-frame joint targets to the action (see `DeployedPolicy`)."""

    joint_targets: np.ndarray  # (T, J) joint targets at a zero action (`zero_action_targets`), action order
    phase_rate: float  # Δφ per control step
    phase_index: int  # where the newest step's phase sits in the raw observation
    # The push prior (priors/push_prior.py), None without one: (T, J) push at w = 1, w(ψ)'s anchors,
    # and where the newest step's ψ sits in the raw observation
    push_offsets: np.ndarray | None = None
    psi_anchors: np.ndarray | None = None
    weight_anchors: np.ndarray | None = None
    psi_index: int | None = None

    @classmethod
    def for_layout(cls, joint_targets, phase_rate: float, layout: dict, push_prior=None) -> "ReferenceOffset":
        newest = (int(layout["history"]) - 1) * int(layout["step_dim"])  # history is oldest first
        push = {}
        if push_prior is not None:
            push = {"push_offsets": np.asarray(push_prior.joint_offsets, dtype=np.float32),
                    "psi_anchors": np.asarray(push_prior.psi_anchors), "weight_anchors": np.asarray(push_prior.weight_anchors),
                    "psi_index": newest + _term_start(layout, "psi")}
        return cls(np.asarray(joint_targets, dtype=np.float32), float(phase_rate), newest + _term_start(layout, "phase"),
                   **push)


def _term_start(layout: dict, name: str) -> int:
    """Where term `name` starts within one step of the observation layout."""
    start = 0
    for term in layout["terms"]:
        if term["name"] == name:
            return start
        start += int(term["dim"])
    raise ValueError(f"the observation layout has no {name} term")


def export_onnx(module: DeployedPolicy, obs_dim: int, path: str | Path, metadata: dict | None = None) -> Path:
    """Writes the graph (batch dimension dynamic) with `metadata` in its metadata_props."""
    import onnx

    path = Path(path)
    module = module.eval().cpu()
    example = torch.zeros(1, obs_dim)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter announces its deprecation
        torch.onnx.export(
            module, (example,), str(tmp), dynamo=False, opset_version=OPSET,
            input_names=[INPUT_NAME], output_names=list(OUTPUT_NAMES),
            dynamic_axes={INPUT_NAME: {0: "batch"}} | {n: {0: "batch"} for n in OUTPUT_NAMES},
        )
    model = onnx.load(str(tmp))
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, json.dumps(value)
    onnx.checker.check_model(model)
    onnx.save(model, str(tmp))
    tmp.replace(path)
    return path


def onnx_session(path: str | Path):
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise PipelineInputError(path, None, "ONNX policy file not found (run the export stage first)")
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # single-robot inference: threads only add latency
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def read_onnx_metadata(path: str | Path) -> dict:
    meta = onnx_session(path).get_modelmeta().custom_metadata_map
    return {k: json.loads(v) for k, v in meta.items()}


def parity_errors(module: DeployedPolicy, onnx_path: str | Path, obs_dim: int, num: int = 256,
                  seed: int = 0) -> tuple[float, float]:
    """Torch against onnxruntime on random observations, over all outputs: (the max abs difference, the max of
    each sample's differences over max(1, its largest torch output), the size float32 rounds at)."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(0.0, 2.0, size=(num, obs_dim)).astype(np.float32)
    with torch.no_grad():
        ref = [t.numpy() for t in module.eval().cpu()(torch.from_numpy(obs))]
    got = onnx_session(onnx_path).run(list(OUTPUT_NAMES), {INPUT_NAME: obs})
    per_sample = [(np.abs(a - b).reshape(num, -1).max(-1), np.maximum(1.0, np.abs(a).reshape(num, -1).max(-1)))
                  for a, b in zip(ref, got)]
    return float(max(d.max() for d, _ in per_sample)), float(max((d / size).max() for d, size in per_sample))


def parity(module: DeployedPolicy, onnx_path: str | Path, obs_dim: int, num: int = 256, seed: int = 0,
           scaled: bool = False) -> float:
    """One of `parity_errors`: the max abs difference, or with `scaled` the difference at the output's size."""
    return parity_errors(module, onnx_path, obs_dim, num, seed)[int(scaled)]


@dataclass(frozen=True)
class ExportResult:
    folder: Path
    onnx: Path
    metadata: Path
    parity_max_abs_diff: float


def export_folder(module: DeployedPolicy, obs_dim: int, metadata: dict, out_dir: str | Path,
                  source_dir: str | Path | None = None, balance_export: str | Path | None = None,
                  chain: dict | None = None) -> ExportResult:
    """The hub-format folder: config.json + model.safetensors (copied from the trained policy
    folder `source_dir`), policy.onnx and policy.json, and with `balance_export` the balance policy
    and the chain's handoff rule (export/chain.py; `chain`: chain.json's fields other than the defaults).
    Fails (nothing written) if parity fails."""
    out_dir = Path(out_dir)
    if source_dir is not None:
        missing = [n for n in HUB_FILES if not (Path(source_dir) / n).is_file()]
        if missing:
            raise PipelineInputError(source_dir, missing[0], "missing from the trained policy folder")
    with atomic_dir(out_dir) as staging:
        onnx_path = export_onnx(module, obs_dim, staging / ONNX_NAME, metadata)
        diff, scaled = parity_errors(module, onnx_path, obs_dim)
        if not scaled < PARITY_TOLERANCE:
            raise RuntimeError(f"ONNX parity failed: max difference {scaled:.3g} (of max(1, the largest output)) >= "
                               f"{PARITY_TOLERANCE}; max abs diff {diff:.3g}")
        full = metadata | {"parity_max_abs_diff": diff, "onnx": ONNX_NAME}
        (staging / METADATA_NAME).write_text(json.dumps(full, indent=1))
        if source_dir is not None:
            for name in HUB_FILES:
                shutil.copy2(Path(source_dir) / name, staging / name)
        if balance_export is not None:
            from pipeline.export.chain import write_chain

            write_chain(staging, balance_export, **(chain or {}))
    return ExportResult(out_dir, out_dir / ONNX_NAME, out_dir / METADATA_NAME, diff)


def export_variant(*, task: str, variant: str, data, policy_dir: str | Path, out_dir: str | Path,
                   env_cfg=None, balance_export: str | Path | None = None,
                   handoff_after_landing_s: float | None = None) -> ExportResult:
    """The `export` stage: trained policy folder (models/<task>/<variant>/final) → hub-format
    folder with policy.onnx + policy.json (models/<task>/<variant>/export), and the balance policy
    the chain stands with (`balance_export`, params.yaml `balance.out`/export) in its `balance/`."""
    from pipeline.export.metadata import build_metadata, observation_layout, termination_metadata, terrain_metadata
    from pipeline.rl.checkpoint import load_policy
    from pipeline.robot.g1 import load_robot_config

    robot = load_robot_config()
    policy_dir = Path(policy_dir)
    if not policy_dir.is_dir():
        raise PipelineInputError(policy_dir, None, "trained policy folder not found (run the training stages)")
    push_prior = getattr(data, "push_prior", None)
    module, meta = load_policy(policy_dir, expect={"robot": robot.name, "joint_names": list(robot.joint_names),
                                                   "push_prior": push_prior is not None})
    if meta.get("task") not in (None, task):
        raise PipelineInputError(policy_dir / "config.json", "task",
                                 f"policy was trained for task {meta['task']!r}, not {task!r}")
    history = env_cfg.observations.history if env_cfg is not None else 5
    layout = observation_layout(robot, history=history)
    if layout["dim"] != meta["actor_obs_dim"]:
        raise PipelineInputError(policy_dir / "config.json", "actor_obs_dim",
                                 f"{meta['actor_obs_dim']} does not match the deployed layout ({layout['dim']})")
    for term in layout["terms"]:
        if term["name"] == "odometry" and env_cfg is not None:
            term["rate_hz"] = env_cfg.observations.odometry_rate_hz
    terrain = None
    if data.terrain and data.terrain.get("kind", "flat") != "flat":
        from pipeline.keyframes.terrain import terrain_builder, terrain_layout

        grid = np.linspace(float(data.psi.min()), float(data.psi.max()), 41)
        terrain = terrain_metadata(terrain_builder(data.terrain), lambda p: terrain_layout(data.terrain, p), grid)
    terminations = termination_metadata(env_cfg.terminations if env_cfg is not None else None, task)
    metadata = build_metadata(task=task, variant=variant, robot=robot, data=data, obs_layout=layout,
                              terminations=terminations, terrain=terrain, action_offset=meta["action_offset"])
    metadata["policy_stage"] = meta.get("stage")
    if env_cfg is not None:  # the physics preset it trained on, so sim2sim and play replay that one
        metadata["physics"] = env_cfg.physics
        metadata["sim_dt"] = robot.physics(env_cfg.physics).timestep
    reference = None
    if meta["action_offset"] != "default":  # the table policy.json records (build_metadata)
        reference = ReferenceOffset.for_layout(metadata["reference"]["joint_target"], metadata["phase"]["rate"], layout,
                                               push_prior)
    module = DeployedPolicy(module, robot.default_joint_pos, robot.action_scale, reference=reference)
    from pipeline.export.chain import handoff_phase

    chain = {"handoff_phase": handoff_phase(data, handoff_after_landing_s)}
    return export_folder(module, layout["dim"], metadata, out_dir, source_dir=policy_dir, balance_export=balance_export,
                         chain=chain)
