"""The push prior (priors/push_prior.py): built on the bundled sample with a tiny search, its table lines up
with the rollouts it was measured by, it round-trips through its files, bad files are named, and a policy
trained without it is refused where the task has one."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline import REPO_ROOT
from pipeline.common.errors import PipelineInputError
from pipeline.priors.push_prior import (FILE_ARRAYS, FILE_JSON, PushPrior, PushPriorConfig, build_push_prior,
                                        load_push_prior, monotone_anchors, write_push_prior)
from pipeline.robot.g1 import load_robot_config


@pytest.fixture(scope="module")
def sample_data():
    """D_edit of the bundled sample (params.yaml's far_jump_sample), 8 samples."""
    from pipeline.config import load_params
    from pipeline.human.importers import load_human_motion
    from pipeline.keyframes.edit import build_tracking_data
    from pipeline.keyframes.select import select_keyframes
    from pipeline.retarget.core import retarget

    params = load_params(REPO_ROOT / "params.yaml")
    task = params.tasks["far_jump_sample"]
    motion, _ = retarget(load_human_motion(task.input_path(REPO_ROOT)), params.retarget, progress=False)
    return build_tracking_data(motion, task, select_keyframes(motion, task), "edit", 8, 0)


@pytest.fixture(scope="module")
def sample_prior(sample_data):
    return build_push_prior(sample_data, PushPriorConfig(enabled=True, iterations=3, population=16), log=None)


def test_weight_reads_the_anchors_and_holds_their_ends():
    prior = PushPrior(np.zeros((3, 2)), np.array([0.4, 1.0, 1.6]), np.array([0.0, 0.2, 1.0]), ("a", "b"))
    np.testing.assert_allclose(prior.weight([0.1, 0.4, 0.7, 1.0, 1.3, 1.6, 2.0]), [0.0, 0.0, 0.1, 0.2, 0.6, 1.0, 1.0])


def test_monotone_anchors_keep_the_smallest_weight_reaching_each_psi():
    psi = np.array([0.39, 0.80, 1.05, 1.01, 0.97, 1.07, 1.28, 1.275])
    w = np.arange(len(psi)) * 0.1
    kept_psi, kept_w = monotone_anchors(psi, w)
    np.testing.assert_allclose(kept_psi, [0.39, 0.80, 1.05, 1.07, 1.28])
    np.testing.assert_allclose(kept_w, [0.0, 0.1, 0.2, 0.5, 0.6])


class _StubJumps:
    """Jumps as a function of the offsets alone: the feet travel 1 m plus their mean, past 1 m the pelvis dips
    a millimetre under the flight limit (a penalty of 0.005, which a farther jump outscores), and below
    0.9 m there is no flight (None), as a rollout that never leaves the ground."""

    knots = 12

    def __init__(self, landable_up_to_m: float = 1.0):
        self.landable_up_to_m = landable_up_to_m

    def jumps(self, offsets):
        from pipeline.priors.open_loop import MIN_FLIGHT_PELVIS_M, Jump

        out = []
        for o in offsets:
            feet = 1.0 + float(o.mean())
            if feet < 0.9:
                out.append(None)
                continue
            out.append(Jump(feet_m=feet, landing_x=feet, pelvis_m=feet, takeoff_s=0.3, landing_s=0.6, tilt=0.1, pitch_rate=0.0,
                            lowest_pelvis_m=MIN_FLIGHT_PELVIS_M - (0.001 if feet > self.landable_up_to_m else 0.0),
                            apex_pelvis_m=0.8, capture_outside_m=0.0, fall_check_excess=0.0,
                            feet_ahead_m=0.5 * (feet - 0.9)))  # a farther landing reaches further forward
        return out


def test_the_search_can_insist_on_a_landable_jump():
    from pipeline.priors.open_loop import cross_entropy_search

    def search(**kw):
        return cross_entropy_search(_StubJumps(), 1.0, 0.0, 4, 32, np.random.default_rng(0), log=None, **kw)[1]

    best = search()
    assert best.feet_m > 1.0 and not best.landable(1.0, 0.0)  # by score, the hair-breadth violation wins
    best = search(landable_only=True)
    assert best.landable(1.0, 0.0) and best.feet_m <= 1.0
    # nothing landable, some rollouts never flew: no jump, rather than the best of the unusable ones
    nothing = cross_entropy_search(_StubJumps(landable_up_to_m=0.0), 1.0, 0.0, 4, 32, np.random.default_rng(0),
                                   log=None, landable_only=True)
    assert nothing[1] is None


def test_a_posture_limit_keeps_the_search_from_reaching_its_feet_forward():
    from pipeline.priors.open_loop import LandingPosture, cross_entropy_search

    posture = LandingPosture(max_feet_ahead_m=0.025, min_lean=-1.0, min_pitch_rate=-10.0)
    free = cross_entropy_search(_StubJumps(), 1.0, 0.0, 4, 32, np.random.default_rng(0), log=None, landable_only=True)[1]
    held = cross_entropy_search(_StubJumps(), 1.0, 0.0, 4, 32, np.random.default_rng(0), log=None, landable_only=True,
                                posture=posture)[1]
    assert free.feet_m > 0.95 and not free.landable(1.0, 0.0, posture=posture)
    assert held.feet_m <= 0.95 and held.feet_ahead_m <= 0.025 and held.landable(1.0, 0.0, posture=posture)
    # each limit by hand: 0.1 m too far ahead, leaning back 0.2 past its limit, pitching back 1 rad/s too fast
    jump = dataclasses.replace(held, feet_ahead_m=0.125, lean=-0.3, pitch_rate=-2.0)
    limits = LandingPosture(max_feet_ahead_m=0.025, min_lean=-0.1, min_pitch_rate=-1.0)
    assert limits.excess(jump) == pytest.approx(0.1 + 0.2 + 0.2 * 1.0)


def test_the_reference_posture_is_read_at_the_landing_frame(sample_data):
    from pipeline.common import quat
    from pipeline.priors.open_loop import DOWN, OpenLoopJumps
    from pipeline.priors.push_prior import flight_frames

    _, landing = flight_frames(sample_data)
    jumps = OpenLoopJumps(sample_data.motion, load_robot_config(), 0, 31)
    limits = jumps.reference_posture(landing, feet_margin_m=0.1, lean_margin=0.3, pitch_rate_margin=0.6)
    segment = jumps.segment
    qpos, qvel = segment.qpos()[landing], segment.qvel()[landing]
    rear_ankle_x = min(segment.body_pos[landing, segment.body_index(name), 0] for name in ("left_ankle", "right_ankle"))
    assert limits.max_feet_ahead_m == pytest.approx(rear_ankle_x - qpos[0] + 0.1)
    assert limits.min_lean == pytest.approx(quat.inverse_rotate(qpos[3:7], DOWN)[0] - 0.3)
    assert limits.min_pitch_rate == pytest.approx(qvel[4] - 0.6)


def test_the_push_curves_are_linear_between_the_configured_knots(sample_data):
    from pipeline.priors.open_loop import CHANNELS, OpenLoopJumps

    jumps = OpenLoopJumps(sample_data.motion, load_robot_config(), 0, 31, knots=7)  # a knot every 5 steps
    offsets = np.random.default_rng(0).normal(size=(2, len(CHANNELS), 7))
    curves = jumps.curves(offsets)
    knee = jumps.channel_joints[1]
    np.testing.assert_allclose(curves[:, ::5, knee[0]], offsets[:, 1])  # each knot's value at its step ...
    np.testing.assert_allclose(curves[:, ::5, knee[1]], offsets[:, 1])  # ... on both sides
    np.testing.assert_allclose(curves[:, 2, knee[0]], 0.6 * offsets[:, 1, 0] + 0.4 * offsets[:, 1, 1])  # linear between
    with pytest.raises(ValueError, match="at least 2 knots"):
        OpenLoopJumps(sample_data.motion, load_robot_config(), 0, 31, knots=1)


def test_a_search_that_lands_nothing_is_an_input_error(sample_data, monkeypatch):
    from pipeline.priors import open_loop

    monkeypatch.setattr(open_loop, "cross_entropy_search", lambda *a, **k: (np.zeros((1, 1)), None))
    with pytest.raises(PipelineInputError, match="push_prior: none of the search's 1 x 2 rollouts landed"):
        build_push_prior(sample_data, PushPriorConfig(enabled=True, iterations=1, population=2), log=None)


def test_the_table_is_the_searched_push_in_its_window_and_fades_after_touch_down(sample_data, sample_prior):
    prior, s = sample_prior, sample_prior.summary
    start, stop = s["window_frames"]
    table = prior.joint_offsets
    assert table.shape == (sample_data.motion.num_frames, len(load_robot_config().joint_names))
    assert not table[: start + 1].any() and not table[stop + 1:].any()  # control step k aims at start + k + 1
    assert np.abs(table[start + 1: stop + 1]).max() > 0
    touch = s["touchdown_frame"]
    assert start < touch <= stop and np.abs(table[touch]).max() > 0
    assert not table[touch + 10 + 1:].any()  # 0.2 s of fade at 50 fps
    np.testing.assert_allclose(np.abs(table).max(), s["max_abs_offset_rad"])
    # The anchors: a table w(ψ) can be read from, each one a rollout that passed the env's fall checks.
    assert np.all(np.diff(prior.psi_anchors) > 0) and np.all(np.diff(prior.weight_anchors) >= 0)
    passed = {round(m["w"], 6): m["psi"] for m in s["measured"] if m["passes_fall_checks"]}
    for p, w in zip(prior.psi_anchors, prior.weight_anchors):
        assert passed[round(float(w), 6)] == pytest.approx(p)
    # The w = 1 rollout of the stored (faded) table is the searched jump: the fade starts at its touch-down,
    # so the flight is the same rollout, and the table lines up with the search's control steps.
    at_one = next(m for m in s["measured"] if m["w"] == 1.0)
    assert at_one["psi"] == pytest.approx(s["psi_reached"], abs=1e-9)


def test_prior_round_trips_and_bad_files_are_named(tmp_path, sample_data, sample_prior):
    robot = load_robot_config()
    frames = sample_data.motion.num_frames
    write_push_prior(tmp_path / "on", sample_prior)
    back = load_push_prior(tmp_path / "on", frames, robot.joint_names)
    np.testing.assert_array_equal(back.joint_offsets, sample_prior.joint_offsets)
    np.testing.assert_array_equal(back.weight([0.0, 0.2, 0.5]), sample_prior.weight([0.0, 0.2, 0.5]))
    write_push_prior(tmp_path / "off", None)
    assert load_push_prior(tmp_path / "off", frames, robot.joint_names) is None
    assert not (tmp_path / "off" / FILE_ARRAYS).exists()

    with pytest.raises(PipelineInputError, match="joint_offsets"):
        load_push_prior(tmp_path / "on", frames + 1, robot.joint_names)
    with pytest.raises(PipelineInputError, match="joint_names"):
        load_push_prior(tmp_path / "on", frames, tuple(reversed(robot.joint_names)))
    bad = PushPrior(sample_prior.joint_offsets, np.array([0.3, 0.2]), np.array([0.0, 1.0]), sample_prior.joint_names)
    write_push_prior(tmp_path / "bad", bad)
    with pytest.raises(PipelineInputError, match=f"{FILE_ARRAYS}: psi_anchors"):
        load_push_prior(tmp_path / "bad", frames, robot.joint_names)
    (tmp_path / "on" / FILE_ARRAYS).unlink()
    with pytest.raises(PipelineInputError, match="missing"):
        load_push_prior(tmp_path / "on", frames, robot.joint_names)
    (tmp_path / "off" / FILE_JSON).write_text('{"enabled": "yes"}')
    with pytest.raises(PipelineInputError, match=f"{FILE_JSON}: enabled"):
        load_push_prior(tmp_path / "off", frames, robot.joint_names)
    with pytest.raises(PipelineInputError, match="run the push_prior stage"):
        load_push_prior(tmp_path / "nowhere", frames, robot.joint_names)


def test_a_task_without_a_flight_is_refused(sample_data):
    no_flight = dataclasses.replace(sample_data, keyframe_labels=tuple("" for _ in sample_data.keyframe_labels))
    with pytest.raises(PipelineInputError, match="push_prior: needs a take-off"):
        build_push_prior(no_flight, PushPriorConfig(enabled=True, iterations=1, population=2), log=None)


def test_env_adds_the_push_to_the_zero_action_per_sample(sample_data, sample_prior):
    import torch

    from pipeline.envs.config import EnvConfig
    from pipeline.envs.tracking_env import TrackingEnv

    data = dataclasses.replace(sample_data, push_prior=sample_prior)
    cfg = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0, "sampling": {"mode": "sweep"}})
    plain, pushed = TrackingEnv(cfg, sample_data, num_envs=8), TrackingEnv(cfg, data, num_envs=8)
    plain.reset(), pushed.reset()
    frame = torch.full((8,), sample_prior.summary["window_frames"][0] + 20)
    weight = torch.as_tensor(sample_prior.weight(sample_data.psi[pushed.sample.numpy()]), dtype=torch.float32)
    expected = plain._action_offset(frame) + weight[:, None] * torch.as_tensor(sample_prior.joint_offsets[frame.numpy()],
                                                                                dtype=torch.float32)
    torch.testing.assert_close(pushed._action_offset(frame), expected)
    assert float((pushed._action_offset(frame) - plain._action_offset(frame)).abs().max()) > 0.01

    with pytest.raises(PipelineInputError, match="env.action_offset"):
        TrackingEnv(EnvConfig.from_dict({"action_offset": "reference"}), data, num_envs=2)


def test_a_policy_trained_without_the_prior_is_refused_where_the_task_has_one():
    from pipeline.rl.checkpoint import check_compatible

    check_compatible({"push_prior": False}, {"push_prior": False}, "policy")
    with pytest.raises(PipelineInputError, match="policy: push_prior"):
        check_compatible({"push_prior": False}, {"push_prior": True}, Path("policy"))


def test_the_stage_writes_the_prior_and_the_edited_variants_train_with_it(tmp_path, monkeypatch, sample_data):
    """`push_prior` stage on the sample's D_edit (a tiny search), then what train/evaluate/export load:
    the prior for variants that track the edit, none for the one that tracks the unedited clip, which is
    still judged on the edited keyframes."""
    import argparse
    from pipeline import paths
    from pipeline.config import load_params
    from pipeline.keyframes.datasets import write_tracking_dataset
    from pipeline.stages import _evaluation_data, _tracking_data, run_push_prior

    params = load_params(REPO_ROOT / "params.yaml")
    task = params.tasks["far_jump_sample"]
    monkeypatch.chdir(tmp_path)
    write_tracking_dataset(paths.keyframes_dir("far_jump_sample") / "d_edit", sample_data)
    args = argparse.Namespace(task="far_jump_sample")

    run_push_prior(params, args)  # the sample's default: no prior, and a file that says so
    assert not _tracking_data(params, "far_jump_sample", "adamimic").push_prior

    tiny = dataclasses.replace(task, push_prior=PushPriorConfig(enabled=True, iterations=3, population=16))
    params = dataclasses.replace(params, tasks={**params.tasks, "far_jump_sample": tiny})
    run_push_prior(params, args)
    assert (paths.push_prior_dir("far_jump_sample") / FILE_ARRAYS).is_file()
    edited = _tracking_data(params, "far_jump_sample", "adamimic")
    assert edited.push_prior is not None and edited.push_prior.joint_offsets.shape[0] == edited.motion.num_frames
    assert _tracking_data(params, "far_jump_sample", "deepmimic_noadapt").push_prior is None
    # Evaluation judges every variant on the edited keyframes, with the zero action it trained with.
    judged = _evaluation_data(params, "far_jump_sample", "deepmimic_noadapt")
    assert judged.push_prior is None
    np.testing.assert_array_equal(judged.keyframe_offsets, edited.keyframe_offsets)
    assert np.abs(judged.keyframe_offsets).max() > 0
    assert _evaluation_data(params, "far_jump_sample", "deepmimic_adapt").push_prior is not None


FAR_JUMP = REPO_ROOT.parent / "shared" / "data" / "adamimic_smpl" / "far_jump.npz"


def zero_action_landings(data, prior, num_envs: int = 8):
    """Rolls out the pushed zero action (no randomisation, episodes from t = 0), one world per swept ψ
    sample. Returns (ψ, where each world's rear ankle touched down after its first flight of at least
    0.1 s (NaN: it never did), where the reference's rear ankle lands unedited)."""
    import torch

    from pipeline.envs.config import EnvConfig
    from pipeline.envs.tracking_env import TrackingEnv
    from pipeline.priors.push_prior import flight_frames

    data = dataclasses.replace(data, push_prior=prior)
    cfg = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0, "sampling": {"mode": "sweep"}})
    env = TrackingEnv(cfg, data, num_envs=num_envs)
    env.reset()
    psi = data.psi[env.sample.numpy()]
    _, landing = flight_frames(data)
    ankles = [data.motion.body_index("left_ankle"), data.motion.body_index("right_ankle")]
    airborne_steps = np.zeros(num_envs, dtype=int)
    landed_x = np.full(num_envs, np.nan)
    ended = np.zeros(num_envs, dtype=bool)
    zero = torch.zeros(num_envs, env.action_dim)
    for _ in range(data.motion.num_frames):
        _, _, terminated, truncated, _ = env.step(zero)
        contact = np.asarray(env.backend.foot_contact).any(-1)
        rear_x = np.asarray(env.backend.site_pos)[:, env.feet_idx.numpy(), 0].min(-1)
        touched = ~ended & np.isnan(landed_x) & contact & (airborne_steps * env.control_dt >= 0.1)
        landed_x[touched] = rear_x[touched]
        airborne_steps = np.where(contact, 0, airborne_steps + 1)
        ended |= (terminated | truncated).numpy()
        if (ended | ~np.isnan(landed_x)).all():
            break
    return psi, landed_x, float(data.motion.body_pos[landing, ankles, 0].min())


def test_the_pushed_zero_action_lands_where_the_edit_moves_the_landing(sample_data, sample_prior):
    """w(ψ) is read where the gap and the keyframes are laid out: in the env, each world whose ψ the
    prior reaches lands its rear ankle about ψ − ψ_raw past the reference's landing (the search measured
    its jumps from the reference's state, the env's episodes start earlier and arrive a little apart)."""
    psi, landed_x, reference_landing_x = zero_action_landings(sample_data, sample_prior)
    reachable = psi <= sample_prior.psi_anchors[-1]
    assert reachable.sum() >= 2
    expected = reference_landing_x + np.maximum(psi, sample_prior.psi_anchors[0]) - sample_data.psi_raw
    np.testing.assert_allclose(landed_x[reachable], expected[reachable], atol=0.08)


@pytest.mark.skipif(not FAR_JUMP.is_file(), reason="../shared/data/adamimic_smpl not present")
def test_the_far_jumps_prior_measures_its_jumps_where_the_env_lands_them():
    """On the shared far jump the robot takes off 0.15-0.2 m behind the reference's feet. A prior that
    measured ψ by the feet's flight (as it once did) read every jump that much longer than where it
    lands, so each pushed world landed at the gap's far edge, short of its target. Here each world of
    the env replays exactly one of the search's measured rollouts (w held constant, on flat ground) and
    its landing must be the ψ the prior recorded for it."""
    from pipeline.human.importers import load_human_motion
    from pipeline.common.yaml_strict import load_yaml_strict
    from pipeline.keyframes.config import TerrainConfig
    from pipeline.keyframes.task_parsing import load_tasks
    from pipeline.keyframes.edit import build_tracking_data
    from pipeline.keyframes.select import select_keyframes
    from pipeline.retarget import RetargetConfig, retarget

    task = load_tasks(load_yaml_strict(REPO_ROOT / "pipeline" / "keyframes" / "paper_tasks.yaml")["tasks"])["far_jump"]
    task = dataclasses.replace(task, terrain=TerrainConfig(kind="flat"))
    motion, _ = retarget(load_human_motion(FAR_JUMP), RetargetConfig(), fps_out=50, progress=False)
    takeoff, _ = select_keyframes(motion, task).flights[0]
    segment = motion.slice(takeoff - 25, takeoff + 51)  # 0.5 s before the take-off (the prior's window) to 1 s after
    data = build_tracking_data(segment, task, select_keyframes(segment, task), "edit", 2, 0)
    prior = build_push_prior(data, PushPriorConfig(enabled=True, iterations=4, population=32), log=None)
    zero, strongest = prior.summary["measured"][0], prior.summary["measured"][-1]
    assert zero["w"] == 0.0 and zero["psi"] is not None, "the zero action's own jump must have been measured"
    for measured in (zero, strongest) if strongest["psi"] is not None else (zero,):
        w = measured["w"]
        held = PushPrior(prior.joint_offsets, np.array([0.0, 10.0]), np.array([w, w]), prior.joint_names)
        _, landed_x, reference_landing_x = zero_action_landings(data, held, num_envs=2)
        np.testing.assert_allclose(landed_x, reference_landing_x + measured["psi"] - data.psi_raw, atol=0.03,
                                   err_msg=f"w = {w}")
