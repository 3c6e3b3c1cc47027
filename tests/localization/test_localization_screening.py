"""The vectorised screen gives ``screen_alignment``'s score for every candidate, and ranks the true keyframe
first."""

from __future__ import annotations

import numpy as np

from reradar_core.geometry.se2 import inverse, transform_points
from reradar_core.localization.screening import build_screen_grid, screen_candidates, screen_keyframe
from reradar_core.matching import AlignmentConfig, build_landmark_grid, screen_alignment


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_batched_scores_equal_single_candidate_scores() -> None:
    rng = np.random.default_rng(0)
    cfg = AlignmentConfig()
    kfs = [(rng.uniform(-60, 60, (m, 2)), _unit(rng.normal(size=(m, 16)))) for m in (300, 120, 3, 250, 1)]
    # the query sees keyframe 3 from a known offset, plus clutter
    sel = rng.choice(250, 180, replace=False)
    q_pts = np.vstack([transform_points(inverse(np.array([2.0, -3.0, 0.7])), kfs[3][0][sel]),
                       rng.uniform(-60, 60, (60, 2))])
    q_desc = _unit(np.vstack([kfs[3][1][sel] + 0.05 * rng.normal(size=(180, 16)), rng.normal(size=(60, 16))]))
    batched = screen_candidates(q_pts, q_desc, [screen_keyframe(p, d, cfg) for p, d in kfs], cfg)
    single = [screen_alignment(q_pts, q_desc, p, d, cfg) for p, d in kfs]
    np.testing.assert_array_equal(batched, single)
    assert int(np.argmax(batched)) == 3 and batched[3] > 0.6 and batched[4] == 0.0  # one landmark: no pair


def test_screen_grid_marks_cells_within_the_threshold() -> None:
    cfg = AlignmentConfig()
    pts = np.array([[0.0, 0.0], [10.0, -4.0]])
    g = build_screen_grid(pts, cfg)
    full = build_landmark_grid(pts, cfg.grid_cell_m)
    assert g.near.dtype == np.uint8 and g.near.size == g.n * g.n
    np.testing.assert_array_equal(g.near.reshape(g.n, g.n), full.distance_m < cfg.score_threshold_m)
    assert g.near.sum() > 0 and g.near.reshape(g.n, g.n)[0, 0] == 0  # the margin is never near


def test_degenerate_query_scores_zero() -> None:
    cfg = AlignmentConfig()
    kf = screen_keyframe(np.zeros((10, 2)), _unit(np.ones((10, 4))), cfg)
    assert screen_candidates(np.zeros((1, 2)), np.ones((1, 4)), [kf], cfg).tolist() == [0.0]
    assert screen_candidates(np.zeros((5, 2)), np.ones((5, 4)), [], cfg).shape == (0,)


def test_scores_do_not_depend_on_the_scoring_block(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import reradar_core.localization.screening as screening

    rng = np.random.default_rng(3)
    cfg = AlignmentConfig()
    kfs = [screen_keyframe(rng.uniform(-60, 60, (m, 2)), _unit(rng.normal(size=(m, 16))), cfg) for m in (200, 90, 150)]
    q_pts, q_desc = rng.uniform(-60, 60, (220, 2)), _unit(rng.normal(size=(220, 16)))
    default = screen_candidates(q_pts, q_desc, kfs, cfg)
    monkeypatch.setattr(screening, "_SCORE_BLOCK", 7)  # many blocks, a ragged last one
    np.testing.assert_array_equal(screen_candidates(q_pts, q_desc, kfs, cfg), default)


def test_scores_do_not_depend_on_the_similarity_block(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # the descriptor similarities are computed in blocks of candidates (bounded temporaries): 1 per block, two
    # blocks with a ragged last one, and all at once give the same scores
    import reradar_core.localization.screening as screening

    rng = np.random.default_rng(5)
    cfg = AlignmentConfig()
    kfs = [screen_keyframe(rng.uniform(-60, 60, (m, 2)), _unit(rng.normal(size=(m, 16))), cfg)
           for m in (400, 330, 350, 380, 420)]
    q_pts, q_desc = rng.uniform(-60, 60, (260, 2)), _unit(rng.normal(size=(260, 16)))
    results = []
    for block in (1, 3, 100):
        monkeypatch.setattr(screening, "_SIM_BLOCK", block)
        results.append(screen_candidates(q_pts, q_desc, kfs, cfg))
    np.testing.assert_array_equal(results[0], results[2])
    np.testing.assert_array_equal(results[1], results[2])


def test_batched_scores_equal_single_candidate_scores_for_other_cells_and_many_scored_landmarks() -> None:
    """A cell that is not a power of two (divided, not multiplied by its inverse) and 300 scored landmarks
    (summed in int64, not uint8): still the single-candidate scores. (Every keyframe has >= 64 k landmarks, so
    the single-candidate top-k orders its pairs as the batched one does.)"""
    rng = np.random.default_rng(4)
    for cfg in (AlignmentConfig(grid_cell_m=0.3), AlignmentConfig(score_points=300),
                AlignmentConfig(grid_cell_m=0.25, top_k_matches=3)):
        kfs = [(rng.uniform(-60, 60, (m, 2)), _unit(rng.normal(size=(m, 16)))) for m in (400, 330, 350)]
        sel = rng.choice(350, 300, replace=False)
        q_pts = np.vstack([transform_points(inverse(np.array([-4.0, 1.0, 2.5])), kfs[2][0][sel]),
                           rng.uniform(-60, 60, (40, 2))])
        q_desc = _unit(np.vstack([kfs[2][1][sel] + 0.05 * rng.normal(size=(300, 16)), rng.normal(size=(40, 16))]))
        batched = screen_candidates(q_pts, q_desc, [screen_keyframe(p, d, cfg) for p, d in kfs], cfg)
        single = [screen_alignment(q_pts, q_desc, p, d, cfg) for p, d in kfs]
        np.testing.assert_array_equal(batched, single)
        assert int(np.argmax(batched)) == 2 and batched[2] > 0.6
