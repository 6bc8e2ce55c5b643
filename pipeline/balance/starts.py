"""The task policies' own end states, as starts for the balance policy's training.

A chain hands the robot to the balance policy where the task policy leaves it: after a landing,
moving and leaning. `record_end_states` rolls each exported task policy out in sim2sim over its ψ
range and keeps the states from its last landing keyframe to the end of its phase (every few steps);
`--at-handoff` instead runs each export's whole chain (`ChainRunner`, from the stance at rest) and keeps
the state the balance policy is handed, nominal and under the paper's randomisation: a task's own
catches, for a balance policy fine-tuned on them. Every state is moved onto flat ground (the balance
env has no terrain): the pelvis keeps its height above the ground under it (a handoff: above the ground
the reference ends on, where a robot still in the air will land). States already past the
balance env's fall checks are left out: no policy starts there.

    python -m pipeline.balance.starts models/pretrained/far_jump/export models/pretrained/jump_step_down/export \
        --out data/balance/start_states.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.common.atomic import atomic_file
from pipeline.common.errors import PipelineInputError
from pipeline.envs.falls import fall_flags
from pipeline.export.chain import end_ground, ground_height_under
from pipeline.export.policy_step import projected_gravity


def last_landing_phase(meta: dict) -> float:
    """The phase of the last keyframe labelled as a landing, or 60 % of the phase without one."""
    labels = meta["keyframes"].get("labels") or []
    phases = [p for p, label in zip(meta["keyframes"]["phases"], labels) if str(label).startswith("landing")]
    return float(phases[-1]) if phases else 0.6


def record_end_states(export_dir: str | Path, psi_values, *, every: int = 3, max_tilt: float = 0.8,
                      min_height: float = 0.4) -> dict:
    """{"qpos" (M, nq), "qvel" (M, nv), "psi" (M,), "phase" (M,)} of one export, on flat ground."""
    from pipeline.export.sim2sim import Sim2Sim

    runner = Sim2Sim(export_dir)
    start = last_landing_phase(runner.meta)
    rows = {"qpos": [], "qvel": [], "psi": [], "phase": []}
    for psi in psi_values:
        def keep(model, data, info, psi=float(psi)):
            final = info["phase"] >= 1.0 - 1e-6
            if info["phase"] < start or (info["step"] % every and not final):
                return
            qpos = _on_flat_ground(model, data.qpos, max_tilt, min_height)  # the balance env's worlds: the origin
            if qpos is None:
                return
            rows["qpos"].append(qpos)
            rows["qvel"].append(data.qvel.copy())
            rows["psi"].append(psi)
            rows["phase"].append(info["phase"])

        runner.run_episode(float(psi), on_step=keep)
    if not rows["qpos"]:
        raise PipelineInputError(export_dir, None, "no end state of this policy passed the fall checks")
    return {k: np.asarray(v) for k, v in rows.items()}


def _on_flat_ground(model, qpos: np.ndarray, max_tilt: float, min_height: float,
                    ground: float | None = None) -> np.ndarray | None:
    """`qpos` at the origin of flat ground, the pelvis as high above it as it was above `ground` (None: the
    ground under the pelvis); None past a fall check."""
    qpos = qpos.copy()
    qpos[2] -= ground_height_under(model, qpos[0], qpos[1]) if ground is None else ground
    by_tilt, by_height = fall_flags(projected_gravity(qpos[3:7])[:2], qpos[2], max_tilt, min_height)
    if by_tilt or by_height:
        return None
    qpos[0:2] = 0.0
    return qpos


def record_handoff_states(export_dir: str | Path, psi_values, *, randomized_per_psi: int = 3, seed: int = 0,
                          max_tilt: float = 0.8, min_height: float = 0.4) -> dict:
    """{"qpos", "qvel", "psi", "phase"} where the chain hands the robot to the balance policy: once per ψ on
    the nominal model and `randomized_per_psi` times under the paper's randomisation, on flat ground."""
    import torch

    from pipeline.envs.config import RandomizationConfig
    from pipeline.evaluation.chain_eval import model_randomizer
    from pipeline.export.chain import ChainRunner

    runner = ChainRunner(export_dir)
    randomize = model_randomizer(RandomizationConfig())
    torch.manual_seed(seed)
    rows = {"qpos": [], "qvel": [], "psi": [], "phase": []}
    for psi in psi_values:
        for draw in range(1 + randomized_per_psi):
            last = {}

            def keep(model, data, info):
                if info["stretch"] == "task":
                    last.update(model=model, qpos=data.qpos.copy(), qvel=data.qvel.copy(), phase=info["phase"],
                                targets=info["keyframe_targets"])

            result = runner.run(float(psi), on_step=keep, randomize=randomize if draw else None)
            if result.ended_in != "balance" or not last:  # fell in the task: nothing was handed over
                continue
            # a handoff at the landing may come with the robot still over a gap or a ledge: it lands on the
            # ground the reference ends on, not on the floor of the gap under its pelvis
            qpos = _on_flat_ground(last["model"], last["qpos"], max_tilt, min_height,
                                   ground=end_ground(last["model"], last["targets"]))
            if qpos is not None:
                rows["qpos"].append(qpos)
                rows["qvel"].append(last["qvel"])
                rows["psi"].append(float(psi))
                rows["phase"].append(float(last["phase"]))
    if not rows["qpos"]:
        raise PipelineInputError(export_dir, None, "no chain of this export reached its handoff")
    return {k: np.asarray(v) for k, v in rows.items()}


def write_start_states(path: str | Path, exports: list[Path], episodes: int = 16, at_handoff: bool = False) -> dict:
    """Records every export's end states over an even ψ grid of its range and writes one npz."""
    import json

    parts = []
    for export in exports:
        meta = json.loads((Path(export) / "policy.json").read_text())
        lo, hi = meta["psi_limits"]
        record = record_handoff_states if at_handoff else record_end_states
        parts.append(record(export, np.linspace(lo, hi, episodes)))
    states = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    states["source"] = np.array([str(e) for e in exports])
    states["count_per_source"] = np.array([len(p["qpos"]) for p in parts])
    with atomic_file(path, "wb") as handle:
        np.savez_compressed(handle, **states)
    return states


def load_start_states(path: str | Path | None) -> dict | None:
    """The states of `write_start_states`, or None where there is no file."""
    if path is None or not Path(path).is_file():
        return None
    with np.load(path) as npz:
        for key in ("qpos", "qvel"):
            if key not in npz.files:
                raise PipelineInputError(path, key, "missing from the start-state file")
        return {"qpos": npz["qpos"], "qvel": npz["qvel"], "source": str(path)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("exports", type=Path, nargs="+", help="exported task policy folders")
    parser.add_argument("--out", type=Path, default=Path("data/balance/start_states.npz"))
    parser.add_argument("--episodes", type=int, default=16, help="ψ values per export, evenly over its range")
    parser.add_argument("--at-handoff", action="store_true",
                        help="the states each export's chain hands over, nominal and randomised (module docstring)")
    args = parser.parse_args(argv)
    states = write_start_states(args.out, args.exports, args.episodes, at_handoff=args.at_handoff)
    print(f"{args.out}: {len(states['qpos'])} states ({', '.join(map(str, states['count_per_source']))} per export)")


if __name__ == "__main__":
    main()
