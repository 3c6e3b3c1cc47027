"""Answer confidence: cues with known values, a monotone fitted model, JSON round-trip, calibration helpers,
the pipeline's decision and the service's ``confidence`` field."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import httpx
import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.localization import (
    REASON_LOW_CONFIDENCE,
    Candidate,
    CandidateVerification,
    LocalizationConfig,
    localize,
)
from reradar_core.localization.confidence import (
    CUE_NAMES,
    ConfidenceCues,
    ConfidenceModel,
    choose_min_confidence,
    choose_min_confidence_by_cost,
    confidence_cues,
    default_confidence_model,
    expected_calibration_error,
    fit_confidence_model,
    landmark_spread_m,
    reliability_bins,
)


def _cand(rank: int, xy: tuple[float, float], screen: float | None, *, rel: np.ndarray | None = None,
          inliers: int = 0, ratio: float = 0.0, dist: float = 0.5, ambiguity: float | None = None,
          spread: float | None = None) -> CandidateVerification:
    return CandidateVerification(keyframe_id=10 + rank, rank=rank, descriptor_distance=dist, timestamp_us=rank,
                                 T_map_keyframe=np.array([xy[0], xy[1], 0.0]), num_matches=100,
                                 num_inliers=inliers, inlier_ratio=ratio, T_keyframe_query=rel,
                                 screen_score=screen, ambiguity=ambiguity, inlier_spread_m=spread)


def test_landmark_spread_known_values() -> None:
    # four corners (+-a, +-b): np.cov (ddof 1) gives var_y = 4 b^2 / 3 < var_x
    a, b = 10.0, 3.0
    pts = np.array([[a, b], [a, -b], [-a, b], [-a, -b]])
    assert landmark_spread_m(pts) == pytest.approx(math.sqrt(4 * b * b / 3))
    line = np.column_stack([np.linspace(0, 50, 20), 2.0 * np.linspace(0, 50, 20) + 1.0])
    assert landmark_spread_m(line) == pytest.approx(0.0, abs=1e-6)  # one façade: no spread across it
    assert landmark_spread_m(pts[:2]) == 0.0


def test_cues_on_a_constructed_result() -> None:
    # winner: keyframe at (0, 0) facing +x, query 1 m ahead -> answer at (1, 0)
    best = _cand(0, (0.0, 0.0), 0.7, rel=np.array([1.0, 0.0, 0.0]), inliers=99, ratio=0.6, dist=0.3,
                 ambiguity=0.4, spread=7.5)
    near = _cand(1, (5.0, 0.0), 0.4)  # same place (within 20 m of the answer)
    far1 = _cand(2, (100.0, 0.0), 0.3)  # different places
    far2 = _cand(3, (-50.0, 0.0), 0.35)
    unscreened = _cand(4, (0.0, 200.0), None, ratio=0.1)  # no screen score: its inlier ratio counts
    cues = confidence_cues(best, [best, near, far1, far2, unscreened], place_radius_m=20.0, top_n=2)
    assert cues is not None
    assert cues.aligned_ratio == pytest.approx(0.6)
    assert cues.log_aligned == pytest.approx(math.log(100.0))
    assert cues.margin == pytest.approx(0.7 - 0.35)  # best different-place rival is rank 3
    assert cues.descriptor_distance == pytest.approx(0.3)
    assert cues.spread_m == pytest.approx(7.5)
    assert cues.agreement == pytest.approx(0.5)  # top-2 others by score: rank 1 (near), rank 3 (far)
    assert cues.ambiguity == pytest.approx(0.4)
    np.testing.assert_allclose(cues.as_array(), [cues.as_dict()[n] for n in CUE_NAMES])
    # the place radius decides what counts as "different": with 1 m every other keyframe is a rival
    assert confidence_cues(best, [best, near, far1, far2], place_radius_m=1.0).margin == pytest.approx(0.3)
    # alone: no rival (margin = own score), no agreement; infinite ambiguity is clipped
    alone = confidence_cues(replace(best, ambiguity=math.inf, inlier_spread_m=None), [best])
    assert alone is not None and alone.margin == pytest.approx(0.7) and alone.agreement == 0.0
    assert alone.ambiguity == 2.0 and alone.spread_m == 0.0
    assert confidence_cues(None, []) is None
    assert confidence_cues(_cand(0, (0.0, 0.0), 0.7), [best]) is None  # no pose: nothing to judge


def _constructed_fit(seed: int = 0, n: int = 4000) -> ConfidenceModel:
    """Labels drawn from a known logistic law in the aligned ratio; the other cues are noise."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, len(CUE_NAMES)))
    x[:, 0] = rng.uniform(0.0, 1.0, n)
    p_true = 1.0 / (1.0 + np.exp(-(12.0 * (x[:, 0] - 0.5))))
    y = rng.uniform(size=n) < p_true
    return fit_confidence_model(x, y, l2=1.0)


def test_fitted_model_is_monotone_in_aligned_ratio_and_recovers_the_law() -> None:
    model = _constructed_fit()
    grid = np.tile(model.mean, (21, 1))
    grid[:, 0] = np.linspace(0.0, 1.0, 21)
    p = model.predict(grid)
    assert np.all(np.diff(p) > 0)
    assert p[0] < 0.05 and p[-1] > 0.95 and p[10] == pytest.approx(0.5, abs=0.08)
    # the noise cues get small weights next to the ratio's
    assert model.coef[0] > 5 * np.abs(model.coef[1:]).max()
    # deterministic: the same data gives the same coefficients
    np.testing.assert_array_equal(_constructed_fit().coef, model.coef)


def test_predict_accepts_cues_and_arrays() -> None:
    model = _constructed_fit()
    cues = ConfidenceCues(*model.mean)
    one = model.predict(cues)
    assert isinstance(one, float) and 0.0 <= one <= 1.0
    assert model.predict(cues.as_array()) == pytest.approx(one)
    assert model.predict(np.full(len(CUE_NAMES), 1e6)) <= 1.0  # no overflow


def test_json_round_trip(tmp_path: Path) -> None:
    model = replace(_constructed_fit(), min_confidence=0.83, meta={"splits": ["train-target-loop"]})
    path = tmp_path / "conf.json"
    model.save(path)
    back = ConfidenceModel.load(path)
    for name in ("mean", "scale", "coef"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))
    assert back.intercept == model.intercept and back.min_confidence == 0.83
    assert back.meta == {"splits": ["train-target-loop"]} and back.cue_names == CUE_NAMES
    x = np.random.default_rng(1).normal(size=(5, len(CUE_NAMES)))
    np.testing.assert_array_equal(back.predict(x), model.predict(x))


def test_bad_model_files_are_refused(tmp_path: Path) -> None:
    d = _constructed_fit().to_dict()
    with pytest.raises(ConfigError, match="format"):
        ConfidenceModel.from_dict({**d, "format_version": 99})
    with pytest.raises(ConfigError, match="cues"):
        ConfidenceModel.from_dict({**d, "cue_names": ["aligned_ratio"]})
    with pytest.raises(ConfigError, match="lacks"):
        ConfidenceModel.from_dict({k: v for k, v in d.items() if k != "coef"})
    with pytest.raises(ConfigError, match="not found"):
        ConfidenceModel.load(tmp_path / "missing.json")
    with pytest.raises(ConfigError):
        fit_confidence_model(np.zeros((4, len(CUE_NAMES))), np.ones(4))  # one class only


def test_shipped_model_loads() -> None:
    model = default_confidence_model()
    assert 0.0 <= model.min_confidence <= 1.0
    assert 0.0 <= model.predict(model.mean) <= 1.0


def test_calibration_helpers_known_answers() -> None:
    # p = 0.25 for four answers of which one is right: perfectly calibrated
    assert expected_calibration_error(np.full(4, 0.25), np.array([1, 0, 0, 0])) == pytest.approx(0.0)
    # always 0.9 sure, always wrong: ECE 0.9
    assert expected_calibration_error(np.full(10, 0.9), np.zeros(10)) == pytest.approx(0.9)
    t = reliability_bins(np.array([0.05, 0.95, 0.95]), np.array([0, 1, 0]), bins=10)
    assert t["count"][0] == 1 and t["count"][9] == 2 and t["frac_pos"][9] == pytest.approx(0.5)
    assert np.isnan(t["mean_p"][5])


def test_choose_min_confidence_known_answer() -> None:
    p = np.array([0.99, 0.95, 0.9, 0.8, 0.7, 0.6])
    correct = np.array([True, False, True, False, True, False])
    eligible = np.ones(6, bool)
    # 200 queries, 0.5 % -> one wrong answer allowed: the bar sits just above the second-highest wrong (0.8)
    bar = choose_min_confidence(p, correct, eligible, 200, 0.005)
    assert 0.8 < bar <= 0.9
    assert int(((p >= bar) & ~correct).sum()) == 1
    # 100 queries -> none allowed: just above 0.95
    assert 0.95 < choose_min_confidence(p, correct, eligible, 100, 0.005) <= 0.99
    # ineligible wrong answers (below the floor) never count
    assert choose_min_confidence(p, correct, correct, 100, 0.005) == 0.0


def test_choose_min_confidence_by_cost_known_answer() -> None:
    p = np.array([0.99, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5])
    correct = np.array([True, True, True, False, True, True, False])
    eligible = np.ones(7, bool)
    # cost 10: refusing the 0.8 wrong costs two correct answers (0.7, 0.6) -> bar just above 0.8 (cost 2)
    bar = choose_min_confidence_by_cost(p, correct, eligible, 10.0)
    assert 0.8 < bar <= 0.9
    # cost 1.5: one wrong is cheaper than two refusals -> only the 0.5 wrong is refused (cost 1.5)
    bar = choose_min_confidence_by_cost(p, correct, eligible, 1.5)
    assert 0.5 < bar <= 0.6
    # no wrong answers -> no bar; ineligible answers never count
    assert choose_min_confidence_by_cost(p, np.ones(7, bool), eligible, 10.0) == 0.0
    assert choose_min_confidence_by_cost(p, correct, correct, 10.0) == 0.0
    # equal confidences cannot be split by a bar: the tie is refused or admitted together
    bar = choose_min_confidence_by_cost(np.array([0.9, 0.5, 0.5]), np.array([True, True, False]),
                                        np.ones(3, bool), 10.0)
    assert 0.5 < bar <= 0.9
    with pytest.raises(ConfigError):
        choose_min_confidence_by_cost(p, correct, eligible, 0.0)


def test_fit_bar_holds_the_wrong_rate_on_every_split() -> None:
    from reradar_core.localization.confidence_fit import FitData, fit_from_data

    rng = np.random.default_rng(7)
    n = 2000
    x = rng.normal(size=(n, len(CUE_NAMES)))
    x[:, 0] = rng.uniform(0.0, 1.0, n)
    correct = rng.uniform(size=n) < 1.0 / (1.0 + np.exp(-(12.0 * (x[:, 0] - 0.5))))
    split = np.where(np.arange(n) < n // 2, "train-target-loop", "train-target-boreas")
    # the second split has no wrong answers above the floor: pooled, the first could have twice its share
    correct[n // 2:] = True
    data = FitData(x, np.ones(n, bool), correct, x[:, 0] >= 0.3, np.ones(n, bool), np.zeros(n, bool), split,
                   np.zeros(n, bool))
    model, report = fit_from_data(data, max_wrong_fraction=0.005, wrong_cost=None, floors=(0.3,))
    p = model.predict(x)
    for s in ("train-target-loop", "train-target-boreas"):
        k = split == s
        assert (k & data.eligible & (p >= model.min_confidence) & ~correct).sum() <= 0.005 * k.sum()
    assert report["bar_cost"] == 0.0 and model.min_confidence == max(report["bar_max_wrong_per_group"].values())
    # with a cost the bar can only rise
    model_c, report_c = fit_from_data(data, max_wrong_fraction=0.005, wrong_cost=10.0, floors=(0.3,))
    assert model_c.min_confidence == max(report_c["bar_cost"], model.min_confidence)


# ------------------------------------------------------------------ the pipeline's decision
def _features(rng: np.random.Generator, n: int = 150):
    from reradar_core.features import ScanFeatures

    kps = rng.uniform(-60, 60, size=(n, 2))
    desc = rng.normal(size=(n, 32))
    g = rng.normal(size=16)
    return ScanFeatures(g / np.linalg.norm(g), kps, desc / np.linalg.norm(desc, axis=1, keepdims=True), 0)


def test_pipeline_reports_confidence_and_applies_the_bar(monkeypatch: pytest.MonkeyPatch) -> None:
    import reradar_core.localization.pipeline as pipeline

    # a known model: p = sigmoid(10 * aligned_ratio - 6), bar 0.99 (the shipped coefficients may change)
    c = len(CUE_NAMES)
    coef = np.zeros(c)
    coef[0] = 10.0
    known = ConfidenceModel(CUE_NAMES, np.zeros(c), np.ones(c), coef, -6.0, min_confidence=0.99)
    monkeypatch.setattr(pipeline, "default_confidence_model", lambda: known)
    rng = np.random.default_rng(3)
    kfs = [_features(rng) for _ in range(4)]
    poses = np.column_stack([np.arange(4) * 100.0, np.zeros(4), np.zeros(4)])
    query = kfs[1]  # the keyframe itself: every landmark aligns at the identity

    def cands() -> list[Candidate]:
        return [Candidate(i, poses[i], kfs[i], 0.1 * r, r) for r, i in enumerate([1, 0, 2, 3])]

    expected = 1.0 / (1.0 + math.exp(-4.0))  # aligned ratio 1
    floor_only = localize(query, cands(), LocalizationConfig(min_confidence=0.0))
    assert floor_only.status == "localized" and floor_only.cues is not None
    assert floor_only.cues.aligned_ratio == pytest.approx(1.0)
    assert floor_only.confidence == pytest.approx(expected)
    assert floor_only.best is not None and floor_only.best.inlier_spread_m is not None
    assert floor_only.best.inlier_spread_m > 20.0  # landmarks spread over a 120 m square
    # None = the model's own bar (0.99 > 0.982): refused, with the confidence still reported
    strict = localize(query, cands(), LocalizationConfig())
    assert strict.status == "not_localized" and strict.reason == REASON_LOW_CONFIDENCE
    assert strict.T_map_query is None and strict.confidence == pytest.approx(expected)
    assert localize(query, cands(), LocalizationConfig(min_confidence=0.98)).status == "localized"
    # mutual_nn is not what the model was fitted on: the bar does not apply there
    assert localize(query, cands(), LocalizationConfig(pose_method="mutual_nn")).status == "localized"
    with pytest.raises(ConfigError):
        LocalizationConfig(min_confidence=1.5)


# ------------------------------------------------------------------ the service's field
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))


@pytest.fixture(scope="module")
def service_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time, make_scan

    from maps.build import build_map
    from service.core.config import Settings
    from service.demo import serve_in_thread

    extractor = FakeExtractor()
    built = build_map(tmp_path_factory.mktemp("built") / "fake.h5", extractor,
                      lambda i: make_scan(i, keyframe_time(i)), keyframe_poses(), radar_preset="boreas",
                      name="fake", batch_size=4)
    settings = Settings(maps_dir=tmp_path_factory.mktemp("maps"), load_demo_map=False, api_key=API_KEY,
                        torch_threads=1)
    with serve_in_thread(settings, extractor) as url, httpx.Client(base_url=url, timeout=60) as c:
        with built.open("rb") as fh:
            r = c.post("/maps", data={"map_id": "route-a"}, files={"map_file": ("fake.h5", fh)},
                       headers={"X-API-Key": API_KEY})
        assert r.status_code == 201, r.text
        yield c


def test_service_response_carries_confidence(service_client: httpx.Client) -> None:
    from service_test_fakes import make_scan

    from reradar_core.io.scan import encode_navtech_png_bytes

    for seed in (3, 999):  # a mapped place and an unknown one
        files = {"scan": ("q.png", encode_navtech_png_bytes(make_scan(seed, 5)), "image/png")}
        r = service_client.post("/localize", data={"map_id": "route-a"}, files=files)
        assert r.status_code == 200, r.text
        res = r.json()
        assert isinstance(res["confidence"], float) and 0.0 <= res["confidence"] <= 1.0
        if res["status"] == "not_localized" and res["reason"] != REASON_LOW_CONFIDENCE:
            assert res["pose"] is None
    schema = service_client.get("/openapi.json").json()["components"]["schemas"]["LocalizeResponse"]
    field = schema["properties"]["confidence"]
    assert field["minimum"] == 0 and field["maximum"] == 1 and "Probability" in field["description"]


def test_fit_from_data_chooses_the_bar_on_fit_runs_and_reports_held_out(tmp_path: Path) -> None:
    from reradar_core.localization.confidence_fit import FitData, fit_from_data

    rng = np.random.default_rng(5)
    n = 3000
    x = rng.normal(size=(n, len(CUE_NAMES)))
    x[:, 0] = rng.uniform(0.0, 1.0, n)
    correct = rng.uniform(size=n) < 1.0 / (1.0 + np.exp(-(12.0 * (x[:, 0] - 0.5))))
    data = FitData(x, np.ones(n, bool), correct, x[:, 0] >= 0.3, np.ones(n, bool),
                   np.arange(n) >= int(0.8 * n), np.array(["train-target-loop"] * n), np.arange(n) % 3 == 0)
    path = tmp_path / "runs.npz"
    data.save(path)
    back = FitData.load(path)
    np.testing.assert_array_equal(back.cues, data.cues)
    np.testing.assert_array_equal(back.unseen, data.unseen)
    model, report = fit_from_data(back, max_wrong_fraction=0.005, floors=(0.3,))
    assert model.min_confidence == report["min_confidence"] and model.meta["report"] == report
    fit = ~data.heldout
    p = model.predict(x)
    wrong_fit = (fit & data.eligible & (p >= model.min_confidence) & ~correct).sum()
    assert wrong_fit <= 0.005 * fit.sum()
    assert report["fit"]["wrong_pct_with_bar"] <= 0.5 < report["fit"]["wrong_pct_floor_only"]
    assert report["heldout"]["runs"] == int(data.heldout.sum())
    assert 0.0 <= report["ece_heldout"] < 0.1  # labels follow the model's own law


def _floor_data(rng: np.random.Generator, n: int, low_aligned_correct: bool):
    """Runs at a probe floor of 0.25: cue 1 (log_aligned) decides correctness above aligned 0.5; below it the
    answers are right as often (``low_aligned_correct``) or always wrong, with the same cue-1 law."""
    from reradar_core.localization.confidence_fit import FitData

    x = rng.normal(size=(n, len(CUE_NAMES)))
    x[:, 0] = rng.uniform(0.25, 1.0, n)
    correct = x[:, 1] > 0.0
    if not low_aligned_correct:
        correct &= x[:, 0] >= 0.5
    return FitData(x, np.ones(n, bool), correct, np.ones(n, bool), np.ones(n, bool), np.arange(n) >= int(0.8 * n),
                   np.array(["train-target-loop"] * n), np.ones(n, bool))


def test_fit_chooses_the_floor_on_the_unseen_sessions() -> None:
    from reradar_core.localization.confidence_fit import FLOOR_GRID, fit_from_data

    rng = np.random.default_rng(11)
    # right answers below 0.5 aligned that the other cues recognise: the lowest floor answers them
    model, report = fit_from_data(_floor_data(rng, 3000, True), max_wrong_fraction=0.005)
    assert model.min_aligned_ratio == report["min_aligned_ratio"] == min(FLOOR_GRID)
    assert [r["floor"] for r in report["floors"]] == sorted(FLOOR_GRID, reverse=True)
    costs = {r["floor"]: r["judged_cost"] for r in report["floors"]}
    assert costs[min(FLOOR_GRID)] < costs[0.5]
    # below 0.5 every answer is wrong: a lower floor can only add wrong answers, so the floor stays at 0.5
    model, report = fit_from_data(_floor_data(rng, 3000, False), max_wrong_fraction=0.005)
    assert model.min_aligned_ratio == 0.5
    # the fitted floor is what the guided pipeline uses when the config leaves it open
    back = ConfidenceModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back.min_aligned_ratio == 0.5


def test_periodic_runs_choose_the_tie_margin_only() -> None:
    """Runs in periodic worlds (``SPLIT-periodic``) leave the coefficients, floor and bar as the other runs fit them
    and choose the tie margin: of those that refuse at most 0.5 % of the right answers of the unseen sessions
    elsewhere, the smallest that leaves the fewest periodic wrong answers (known margins: right answers elsewhere at
    0.3 but 4 at 0.035; periodic wrong answers at 0.025 and 0.08, right ones at 0.2)."""
    from reradar_core.localization.confidence_fit import (
        PLACE_MARGIN_GRID,
        FitData,
        choose_place_margin,
        fit_from_data,
    )

    rng = np.random.default_rng(3)
    plain = _floor_data(rng, 3000, True)
    k = CUE_NAMES.index("margin")
    plain.cues[:, k] = 0.3
    first_right = np.flatnonzero(plain.correct & ~plain.heldout)[:4]
    plain.cues[first_right, k] = 0.035  # 4 right answers elsewhere that a margin above 0.035 would refuse
    m = 400
    per = FitData(np.tile(plain.cues[:1], (m, 1)), np.ones(m, bool), np.arange(m) % 2 == 0, np.ones(m, bool),
                  np.ones(m, bool), np.zeros(m, bool), np.array(["train-target-loop-periodic"] * m), np.ones(m, bool))
    per.cues[:, 0] = 0.9  # well aligned: above any floor and bar
    per.cues[:, 1] = 3.0
    per.cues[:, k] = np.where(per.correct, 0.2, np.where(np.arange(m) % 4 == 1, 0.025, 0.08))
    both = FitData.concat([plain, per])
    assert both.periodic.tolist() == [False] * 3000 + [True] * m
    alone, _ = fit_from_data(plain, max_wrong_fraction=0.005)
    model, report = fit_from_data(both, max_wrong_fraction=0.005)
    np.testing.assert_array_equal(model.coef, alone.coef)
    assert (model.min_aligned_ratio, model.min_confidence) == (alone.min_aligned_ratio, alone.min_confidence)
    base = int((plain.correct & ~plain.heldout & plain.unseen & (alone.predict(plain.cues) >= alone.min_confidence)
                & (plain.cues[:, 0] >= alone.min_aligned_ratio)).sum())
    assert 4 <= 0.005 * base  # the 4 refused right answers fit the budget: the first margin above 0.08 wins
    chosen, table = choose_place_margin(both, model)
    assert report["place_margin"]["chosen"] == chosen == min(t for t in PLACE_MARGIN_GRID if t > 0.08)
    rows = {r["margin"]: r for r in table}
    assert rows[0.02]["periodic_wrong"] == m // 2 and rows[0.03]["periodic_wrong"] == m // 4
    assert rows[0.09]["periodic_wrong"] == 0 and rows[0.09]["periodic_correct"] == m // 2
    assert rows[0.03]["other_refused"] == 0 and rows[0.04]["other_refused"] == 4
    # a budget too small for the 4: the margin stays below 0.035
    assert choose_place_margin(both, model, max_refused_fraction=1.0 / (10 * base))[0] == 0.03


def test_shipped_place_margin_is_the_fitted_one() -> None:
    """``LocalizationConfig.min_place_margin`` is the margin the shipped fit chose (``reradar fit-confidence``
    reports it; a re-fit that chooses another must update the default)."""
    from reradar_core.localization.confidence import DEFAULT_MODEL_PATH
    from reradar_core.localization.pipeline import LocalizationConfig

    report = json.loads(DEFAULT_MODEL_PATH.read_text())["meta"]["report"]
    assert LocalizationConfig().min_place_margin == report["place_margin"]["chosen"]
    assert report["place_margin"]["periodic_runs"] > 0


def test_pipeline_floor_comes_from_the_confidence_model(monkeypatch: pytest.MonkeyPatch) -> None:
    import reradar_core.localization.pipeline as pipeline
    from reradar_core.localization.pipeline import LocalizationConfig

    c = len(CUE_NAMES)
    known = ConfidenceModel(CUE_NAMES, np.zeros(c), np.ones(c), np.zeros(c), 0.0, min_aligned_ratio=0.35)
    monkeypatch.setattr(pipeline, "default_confidence_model", lambda: known)
    assert LocalizationConfig().effective_min_inlier_ratio == 0.35
    assert LocalizationConfig(min_inlier_ratio=0.6).effective_min_inlier_ratio == 0.6
    assert LocalizationConfig(pose_method="mutual_nn").effective_min_inlier_ratio == 0.0
    # files fitted before the floor was fitted keep the fixed floor of then
    d = known.to_dict()
    del d["min_aligned_ratio"]
    assert ConfidenceModel.from_dict(d).min_aligned_ratio == 0.5
    with pytest.raises(ConfigError):
        ConfidenceModel(CUE_NAMES, np.zeros(c), np.ones(c), np.zeros(c), 0.0, min_aligned_ratio=1.5)


def test_split_models_applies_overrides_and_refuses_bad_ones() -> None:
    from reradar_core.localization.confidence_fit import SPLIT_MODELS, split_models

    assert split_models() == SPLIT_MODELS
    got = split_models("train-target-boreas=our-3-boreas, train-target-loop = our-3-loop",
                       ["train-target-boreas", "train-target-loop", "train-target-offroad"])
    assert got == {"train-target-boreas": "our-3-boreas", "train-target-loop": "our-3-loop",
                   "train-target-offroad": "our-3-offroad-w05"}
    # QA session 36: an unknown model was reported by --reuse as a cache miss; a split named twice, the last won
    with pytest.raises(ConfigError, match="unknown model 'nosuch'"):
        split_models("train-target-boreas=nosuch")
    with pytest.raises(ConfigError, match="no such weights file"):
        split_models("train-target-loop=x.pt")
    with pytest.raises(ConfigError, match="for 'train-target-boreas' twice"):
        split_models("train-target-boreas=our-3-boreas,train-target-boreas=our-1")
    with pytest.raises(ConfigError, match="not SPLIT=MODEL"):
        split_models("train-target-boreas")
    with pytest.raises(ConfigError, match="unknown split"):
        split_models("smoke=our-1")
    with pytest.raises(ConfigError, match="which --splits does not fit"):  # QA (session 20): was ignored
        split_models("train-target-loop=our-1", ["train-target-boreas"])
    with pytest.raises(ConfigError, match="more than once"):  # would be localized twice and weigh double
        split_models("", ["train-target-boreas", "train-target-boreas"])


def _patch_split_runs(monkeypatch: pytest.MonkeyPatch, runs: list, flag: str, plain: int) -> dict[str, object]:
    """``confidence_fit.split_runs`` replaced by one yielding ``runs`` when its ``flag`` argument (``lookalike`` or
    ``periodic``) is true, else their first ``plain``; returns the dict in which each call records the flag."""
    import reradar_core.baselines.ours as ours
    from reradar_core.localization import confidence_fit as cf

    seen: dict[str, object] = {}

    def fake_split_runs(split: str, method: object, config: object, query_step: int, progress: bool,
                        map_spacing_m: float, lookalike: bool,
                        periodic: bool = False) -> tuple[float, Iterator[cf.SplitRun]]:
        seen[flag] = {"lookalike": lookalike, "periodic": periodic}[flag]
        return 20.0, iter(runs if seen[flag] else runs[:plain])

    monkeypatch.setattr(cf, "split_runs", fake_split_runs)
    monkeypatch.setattr(ours, "Ours", lambda *a, **k: None)
    return seen


def test_collect_split_labels_lookalike_runs_wrong_and_groups_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """A look-alike session's query (the map's road, other surroundings) is never a revisit: an answer at its
    ground-truth position is still wrong there, and its rows form a group of their own (``SPLIT-lookalike``) for
    the bar's per-group rule; the split's own sessions keep their labels."""
    from reradar_core.localization import confidence_fit as cf
    from reradar_core.localization.pipeline import LocalizationResult

    gt = np.array([3.0, 4.0, 0.2])
    best = _cand(0, (0.0, 0.0), 0.7, rel=gt.copy(), inliers=99, ratio=0.6, ambiguity=0.4, spread=7.5)

    class Loc:  # every query answered at its ground truth from a keyframe at the origin
        def localize(self, features: object, config: object) -> LocalizationResult:
            return LocalizationResult("localized", None, best, gt.copy(), [best])

    runs = [cf.SplitRun(None, gt, True, "full", Loc(), 0, 10, False),
            cf.SplitRun(None, gt, True, "full", Loc(), 9, 10, True),
            cf.SplitRun(None, gt, False, "full", Loc(), 9, 10, True, True)]
    seen = _patch_split_runs(monkeypatch, runs, "lookalike", 2)
    d = cf.collect_split("train-target-loop", progress=False, lookalike=True)
    assert seen["lookalike"] is True
    assert d.split.tolist() == ["train-target-loop", "train-target-loop", "train-target-loop-lookalike"]
    assert d.correct.tolist() == [True, True, False] and d.eligible.all() and d.has_pose.all()
    assert d.revisit.tolist() == [True, True, False] and d.unseen.tolist() == [False, True, True]
    assert d.heldout.tolist() == [False, True, True]
    plain = cf.collect_split("train-target-loop", progress=False)
    assert seen["lookalike"] is False and plain.split.tolist() == ["train-target-loop"] * 2


def test_collect_split_labels_periodic_runs_by_ground_truth_and_groups_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """A periodic world's runs (map and session in a world whose streets repeat every tile) are labelled by ground
    truth like the split's own: an answer one 40 m period off is wrong, one at the query's place right; their rows
    form a group of their own (``SPLIT-periodic``)."""
    from reradar_core.localization import confidence_fit as cf
    from reradar_core.localization.pipeline import LocalizationResult

    gt = np.array([3.0, 4.0, 0.2])

    class Loc:  # answered from a keyframe at the origin, ``off`` metres along x from the query's ground truth
        def __init__(self, off: float) -> None:
            rel = gt + [off, 0.0, 0.0]
            self.best = _cand(0, (0.0, 0.0), 0.7, rel=rel, inliers=99, ratio=0.6, ambiguity=0.9, spread=7.5)

        def localize(self, features: object, config: object) -> LocalizationResult:
            return LocalizationResult("localized", None, self.best, gt.copy(), [self.best])

    runs = [cf.SplitRun(None, gt, True, "full", Loc(0.0), 0, 10, False),
            cf.SplitRun(None, gt, True, "full", Loc(0.0), 1, 10, True, periodic=True),
            cf.SplitRun(None, gt, True, "full", Loc(40.0), 2, 10, True, periodic=True)]
    seen = _patch_split_runs(monkeypatch, runs, "periodic", 1)
    d = cf.collect_split("train-target-loop", progress=False, periodic=True)
    assert seen["periodic"] is True
    assert d.split.tolist() == ["train-target-loop", "train-target-loop-periodic", "train-target-loop-periodic"]
    assert d.correct.tolist() == [True, True, False] and d.unseen.tolist() == [False, True, True]
    assert [r.group for r in runs] == ["", "-periodic", "-periodic"]
    assert cf.SplitRun(None, gt, False, "full", None, 0, 1, True, True).group == "-lookalike"
    assert cf.collect_split("train-target-loop", progress=False).split.tolist() == ["train-target-loop"]
    assert seen["periodic"] is False
