"""The paper's metrics on hand-made trajectories whose answers are known."""

import math

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.config import EvalConfig
from pipeline.evaluation.metrics import (
    EpisodeRecord,
    aggregate,
    aggregate_ranges,
    bin_by_psi,
    episode_metrics,
    episode_success,
    keyframe_funnel,
)


def _record(world, local=None, crossed=None, acc=None, psi=0.0, num_keyframes=None):
    world = np.asarray(world, float)
    t, b = world.shape
    crossed = np.zeros(t, bool) if crossed is None else np.asarray(crossed, bool)
    return EpisodeRecord(
        body_error_world=world,
        body_error_local=np.zeros((t, b)) if local is None else local,
        keyframe_crossed=crossed,
        joint_acc=np.zeros((t, 2)) if acc is None else acc,
        psi=psi,
        num_keyframes=int(crossed.sum()) if num_keyframes is None else num_keyframes,
    )


def test_success_uses_body_mean_at_keyframes_only():
    # Two bodies; step 1 is a keyframe with errors (0.5, 1.4): mean 0.95 <= 1 -> success,
    # although one body is above 1 m. Step 2 is far off (3 m) but is no keyframe.
    world = [[0.1, 0.1], [0.5, 1.4], [3.0, 3.0], [0.2, 0.2]]
    crossed = [False, True, False, True]
    assert episode_success(world, crossed, num_keyframes=2)
    # Same keyframe with (0.7, 1.4): mean 1.05 > 1 -> failure.
    world[1] = [0.7, 1.4]
    assert not episode_success(world, crossed, num_keyframes=2)


def test_episode_that_misses_keyframes_fails():
    world = np.full((5, 3), 0.05)
    crossed = [False, True, False, False, False]  # fell after the first of three keyframes
    assert not episode_success(world, crossed, num_keyframes=3)
    assert episode_success(world, crossed, num_keyframes=1)


def test_errors_and_smoothness_known_values():
    world = np.array([[9.0, 9.0], [0.1, 0.3], [9.0, 9.0], [0.2, 0.4]])  # keyframes at steps 1, 3
    local = np.array([[0.01, 0.03], [0.02, 0.02], [0.0, 0.04], [0.01, 0.01]])
    acc = np.array([[1.0, -3.0], [2.0, 2.0], [-4.0, 0.0], [0.0, 0.0]])
    m = episode_metrics(_record(world, local, [0, 1, 0, 1], acc))
    out = aggregate([m])
    assert out["e_g_bpe"] == pytest.approx(1000 * (0.1 + 0.3 + 0.2 + 0.4) / 4)  # 250 mm
    assert out["e_l_bpe"] == pytest.approx(1000 * 0.14 / 8)  # 17.5 mm
    assert out["e_smth"] == pytest.approx(12.0 / 8)  # 1.5 rad/s^2
    assert out["success"] == 100.0


def test_pooled_over_episodes_and_ranges():
    ok = episode_metrics(_record(np.full((2, 1), 0.1), crossed=[0, 1], psi=0.5))
    bad = episode_metrics(_record(np.full((2, 1), 2.0), crossed=[0, 1], psi=1.5))
    other_ok = episode_metrics(_record(np.full((2, 1), 0.3), crossed=[1, 1], psi=1.6))
    # Pooled global error: samples 0.1, 2.0, 0.3, 0.3 -> 675 mm
    assert aggregate([ok, bad, other_ok])["e_g_bpe"] == pytest.approx(675.0)
    run1 = {"easy": [ok], "hard": [bad, other_ok]}
    run2 = {"easy": [ok], "hard": [other_ok, other_ok]}
    out = aggregate_ranges([run1, run2])
    assert out["easy"]["success"] == {"mean": 100.0, "std": 0.0}
    assert out["hard"]["success"]["mean"] == pytest.approx(75.0)
    assert out["hard"]["success"]["std"] == pytest.approx(25.0)
    assert out["overall"]["success"]["mean"] == pytest.approx((200 / 3 + 100) / 2)
    assert out["overall"]["episodes"]["total"] == 6
    rows = bin_by_psi([ok, bad, other_ok], np.array([0.0, 1.0, 2.0]))
    assert [r["success"] for r in rows] == [100.0, 50.0]
    assert rows[1]["psi"] == 1.5


def test_record_shape_mismatch_is_rejected():
    with pytest.raises(ValueError):
        EpisodeRecord(np.zeros((3, 2)), np.zeros((4, 2)), np.zeros(3, bool), np.zeros((3, 2)), 0.0, 1)


def test_eval_config_from_dict():
    cfg = EvalConfig.from_dict({"episodes_per_range": 10, "runs": 2, "video": {"psi": [1.2, 2]}})
    assert cfg.episodes_per_range == 10 and cfg.video.psi == (1.2, 2.0)
    assert EvalConfig.from_dict(None) == EvalConfig()
    with pytest.raises(PipelineInputError, match="evaluate: episodes"):
        EvalConfig.from_dict({"episodes": 3})
    with pytest.raises(PipelineInputError, match="runs"):
        EvalConfig.from_dict({"runs": 0})
    with pytest.raises(PipelineInputError, match="evaluate.video: fps"):
        EvalConfig.from_dict({"video": {"fps": "fast"}})


# ------------------------------------------------------------------------------ ψ reached
def test_psi_reach_fit_and_read_by_hand():
    from pipeline.evaluation.metrics import PsiReach

    psi = np.linspace(0.2, 2.0, 7)
    far = np.zeros((7, 4, 3))
    far[:, 2:, 0] = (psi - 1.1)[:, None]  # the landing (keyframe 2) and after move along x by ψ − ψ_raw
    reach = PsiReach.fit(psi, far)
    assert reach.keyframe == 2 and reach.axis == pytest.approx([1.0, 0.0, 0.0]) and reach.slope == pytest.approx(1.0)
    misses = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [-0.2, 0.05, 0.3], [0.0, 0.0, 0.0]])
    assert reach.reached(1.5, misses) == pytest.approx(1.3)  # landed 0.2 m short of its 1.5 m target
    assert math.isnan(reach.reached(1.5, misses[:2]))  # fell before the landing keyframe

    triple = np.zeros((7, 3, 3))  # cumulative: landing k carries k/3 of ψ − ψ_raw; the last moves most
    triple[:, :, 0] = (psi - 2.4)[:, None] * np.array([1, 2, 3]) / 3
    assert PsiReach.fit(psi, triple).keyframe == 2
    high = np.zeros((7, 3, 3))
    high[:, 1, 2] = 0.5 * (psi - 0.2)  # an apex along z at half a metre per unit ψ
    r = PsiReach.fit(psi, high)
    assert r.keyframe == 1 and r.axis == pytest.approx([0, 0, 1]) and r.slope == pytest.approx(0.5)
    assert r.reached(1.0, np.array([[0, 0, 0], [0, 0, -0.1], [0, 0, 0]])) == pytest.approx(0.8)

    assert PsiReach.fit(psi, np.zeros((7, 3, 3))) is None  # nothing edited (the original motion)
    turn = np.zeros((7, 2, 3))
    turn[:, 1, 0], turn[:, 1, 1] = np.cos(psi) - 1, np.sin(psi)  # a heading edit: not a line
    assert PsiReach.fit(psi, turn) is None
    assert PsiReach.fit(psi[:1], far[:1]) is None


def test_psi_reached_in_episode_metrics_and_aggregate():
    from pipeline.evaluation.metrics import PsiReach

    reach = PsiReach(keyframe=1, axis=np.array([1.0, 0.0, 0.0]), slope=1.0)
    crossed = np.array([False, True, False, True])
    miss = np.zeros((4, 3))
    miss[3, 0] = -0.3  # the second crossing is keyframe 1
    records = [EpisodeRecord(body_error_world=np.full((4, 2), e), body_error_local=np.zeros((4, 2)),
                             keyframe_crossed=crossed, joint_acc=np.zeros((4, 1)), psi=p, num_keyframes=2,
                             keyframe_miss=miss) for p, e in ((1.0, 0.1), (1.4, 2.0))]
    eps = [episode_metrics(r, reach=reach) for r in records]
    assert [e.psi_reached for e in eps] == pytest.approx([0.7, 1.1])
    assert [e.success for e in eps] == [True, False]
    out = aggregate(eps)
    assert out["psi_reached"] == pytest.approx(0.9) and out["psi_reached_max"] == pytest.approx(0.7)
    assert math.isnan(episode_metrics(records[0]).psi_reached)  # no PsiReach: not measured


def test_keyframe_funnel_counts_by_hand():
    """Three episodes over three keyframes: one succeeds, one drifts past 1 m at the second keyframe
    and keeps going, one falls after the first. The funnel's last on-track value is the success rate."""
    kf = [False, True, False, True, False, True]
    good = episode_metrics(_record(np.full((6, 2), 0.1), crossed=kf))
    drift = np.full((6, 2), 0.2)
    drift[3] = 1.5  # second keyframe 1.5 m off, third back to 0.2
    drifting = episode_metrics(_record(drift, crossed=kf))
    fallen = episode_metrics(_record(np.full((3, 2), 0.3), crossed=[False, True, False], num_keyframes=3))
    assert fallen.keyframe_errors == pytest.approx((0.3,))
    rows = keyframe_funnel([good, drifting, fallen], num_keyframes=3)
    assert [r["reached"] for r in rows] == pytest.approx([100.0, 200 / 3, 200 / 3])
    assert [r["on_track"] for r in rows] == pytest.approx([100.0, 100 / 3, 100 / 3])
    assert [r["e_g_bpe"] for r in rows] == pytest.approx([200.0, 800.0, 150.0])  # means over who reached k
    assert rows[-1]["on_track"] == pytest.approx(aggregate([good, drifting, fallen])["success"])
    assert math.isnan(keyframe_funnel([fallen], num_keyframes=3)[2]["e_g_bpe"])


def test_endings_classify_and_count():
    """How an episode ended, from the checks that fired and its last tilt error against the reference."""
    from pipeline.evaluation.metrics import classify_ending, endings

    assert classify_ending((), None) == "completed"  # ran to the motion's end
    assert classify_ending(None, None) == "unknown"  # cut short, or an env that does not say
    assert classify_ending(("tilt",), np.array([0.9, 0.1])) == "forward"
    assert classify_ending(("tilt", "base_height"), np.array([-0.5, 0.2])) == "backward"
    assert classify_ending(("tilt",), np.array([0.3, -0.6])) == "sideways"
    assert classify_ending(("base_height",), np.array([0.2, 0.1])) == "sank"  # 0.22 from the reference's lean
    assert classify_ending(("base_height",), None) == "unknown"

    def ended(by, tilt):
        record = _record(np.full((3, 2), 0.1), crossed=[False, True, True])
        record.ended_by, record.end_tilt_error = by, None if tilt is None else np.array(tilt)
        return episode_metrics(record)

    episodes = [ended((), None), ended(("tilt",), [0.9, 0.0]), ended(("tilt", "base_height"), [-0.8, 0.0]),
                ended(("base_height",), [0.1, 0.0])]
    assert [e.ending for e in episodes] == ["completed", "forward", "backward", "sank"]
    out = endings(episodes)
    assert out["episodes"] == 4
    assert out["ending"] == {"completed": 25.0, "forward": 25.0, "backward": 25.0, "sideways": 0.0, "sank": 25.0,
                             "unknown": 0.0}
    assert out["check"] == {"tilt": 50.0, "base_height": 50.0, "keyframe_error": 0.0}
    assert sum(out["ending"].values()) == pytest.approx(100.0)
