"""How well the flight detector (`pipeline/motion/feet.py`) reads an estimator's hop-step-jump.

Clips: `pipeline/keyframes/synthetic.py synthetic_hop_step_jump`, a standing start, two walking steps
whose contacts abut (one foot lands on the frame the other leaves: no flight), then a hop, a step and a
jump, each foot rolling from heel strike to toe-off, with `EstimatorNoise` (feet jittering by 1 cm at
30 fps, standing feet creeping at 0.15 m/s, a floor sloping 4 % up or 5 % down), one jitter per seed.
Two sets: flights of 0.16, 0.2 and 0.24 s with stances of 0.2 s, and flights of 0.1, 0.12 and 0.16 s with
stances of 0.16 s. For each: in how many clips the detector finds exactly the three flights, and how far
(frames at 50 fps) their take-offs and landings are from the truth.

Run: .venv/bin/python benchmarks/flight_detection.py [clips per set, default 16]   (~30 s)
Last line: three_found=<n>/<clips> within_2_frames=<share> worst_frames=<n>
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.keyframes.synthetic import EstimatorNoise, hop_step_jump_supports, synthetic_hop_step_jump  # noqa: E402
from pipeline.motion.feet import detect_foot_contacts, find_flights  # noqa: E402

SETS = {"flights 0.16-0.24 s": hop_step_jump_supports(),
        "flights 0.10-0.16 s": hop_step_jump_supports(flights=(0.1, 0.12, 0.16), stance=0.16)}


def main(clips: int) -> None:
    total_found, total, errors = 0, 0, []
    for name, supports in SETS.items():
        found_three, set_errors = 0, []
        for seed in range(clips):
            noise = EstimatorNoise(seed=seed, slope=(0.04, -0.05)[seed % 2])
            motion, _, truth = synthetic_hop_step_jump(supports, noise)
            found = find_flights(detect_foot_contacts(motion), motion.fps)
            if len(found) == len(truth):
                found_three += 1
                set_errors += list(np.abs(np.array(found) - np.array(truth)).ravel())
        set_errors = np.array(set_errors)
        print(f"{name}: three flights found in {found_three}/{clips} clips; take-off and landing frames off by "
              + ", ".join(f"{k}: {np.mean(set_errors == k):.0%}" for k in range(int(set_errors.max()) + 1)))
        total_found, total = total_found + found_three, total + clips
        errors += list(set_errors)
    errors = np.array(errors)
    print(f"three_found={total_found}/{total} within_2_frames={np.mean(errors <= 2):.3f} worst_frames={errors.max()}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 16)
