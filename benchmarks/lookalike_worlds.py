"""Confident answers on unmapped streets shaped like mapped ones (issue 11: "an unknown place is not_localized").

For each world profile (``--profiles``) renders (``reradar sim``, boreas preset) the 120 x 80 m loop of
``tracking_changed_scene.py``: the map drive (world seed 5, every 2nd scan), a query drive in the map's world 1 m to
the side, and query drives on the same roads in worlds of other seeds (``--lookalike-seeds``: other buildings, trees
and parked cars along the same road geometry, where every ``localized`` answer is wrong). Then localizes every scan
globally (``MapDatabase.localize``, as the benchmark does) with the shipped confidence model and, with ``--compare``,
another model JSON (e.g. the previous commit's ``confidence_model.json``), and prints per drive and model the correct
and wrong ``localized`` answers with the wrong ones' confidence and errors (m, deg).

    python benchmarks/lookalike_worlds.py --work /tmp/lw [--compare old_confidence_model.json]

Rendering takes ~1 minute per profile on two cores the first time (kept in ``--work``); localizing ~30 s a drive.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracking_changed_scene import RERADAR, loop_poses, write_trajectory  # noqa: E402


def render(work: Path, profile: str, lookalike_seeds: list[int]) -> Path:
    """The profile's map, same-world drive and look-alike drives under ``work/profile`` (kept when rendered)."""
    write_trajectory(work / "map.csv", loop_poses(0.0))
    write_trajectory(work / "rev.csv", loop_poses(0.3, reverse=True))
    d = work / profile
    common = ["--trajectory", str(work / "map.csv"), "--road", str(work / "rev.csv"), "--preset", "boreas",
              "--profile", profile]
    runs = {"map": ["--every", "2", "--seed", "5"], "same": ["--lateral", "-1.0", "--traversal-seed", "31", "--seed", "5"]}
    for s in lookalike_seeds:
        runs[f"look{s}"] = ["--lateral", "-1.0", "--traversal-seed", "31", "--seed", str(s)]
    return render_runs(d, common, runs)


def render_runs(d: Path, common: list[str], runs: dict[str, list[str]]) -> Path:
    """Render each of ``runs`` (name -> its ``reradar sim`` arguments after ``common``) into ``d/name`` unless it is
    there, and the map ``d/map.h5`` from the run ``map`` unless it is there; returns ``d``."""
    for name, extra in runs.items():
        if not (d / name).is_dir():
            subprocess.run([*RERADAR, "sim", *common, *extra, "--out", str(d / name)], check=True,
                           stdout=subprocess.DEVNULL)
    if not (d / "map.h5").is_file():
        subprocess.run([*RERADAR, "build-map", "--dataset", str(d / "map"), "--out", str(d / "map.h5")], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders and maps (kept)")
    ap.add_argument("--profiles", default="urban,suburban,urban-open,offroad")
    ap.add_argument("--lookalike-seeds", default="11,12")
    ap.add_argument("--compare", type=Path, default=None, help="another confidence model JSON to run as well")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    import torch

    from maps.database import MapDatabase
    from reradar_core.evaluation import localization_errors
    from reradar_core.io.datasets import load_sequence
    from reradar_core.localization import localizer, pipeline
    from reradar_core.localization.confidence import DEFAULT_MODEL_PATH, ConfidenceModel
    from reradar_core.model import DescriptorExtractor

    torch.set_num_threads(1)
    models = {"shipped": ConfidenceModel.load(DEFAULT_MODEL_PATH)}
    if args.compare is not None:
        models["compare"] = ConfidenceModel.load(args.compare)
    ext = DescriptorExtractor.from_pretrained("default")
    seeds = [int(s) for s in args.lookalike_seeds.split(",") if s]
    for profile in args.profiles.split(","):
        d = render(args.work, profile, seeds)
        db = MapDatabase.open(d / "map.h5", ext.model_id, ext.weights_sha256, keyframe_cache_size=None, preload=True)
        for drive in ["same", *(f"look{s}" for s in seeds)]:
            seq = load_sequence(d / drive)
            gts = seq.mid_sweep_poses()
            feats = [ext.describe(seq.load_scan(i)) for i in range(len(seq))]
            for name, model in models.items():
                # the pipeline and the localizer read the shipped model through these names
                pipeline.default_confidence_model = localizer.default_confidence_model = (lambda m=model: m)
                correct, wrong = 0, []
                for i, f in enumerate(feats):
                    res = db.localize(f)
                    if not res.localized:
                        continue
                    e_t, e_r = localization_errors(np.asarray(res.T_map_query)[None], gts[i][None])
                    if drive == "same" and e_t[0] < 20.0 and e_r[0] < 10.0:
                        correct += 1
                    else:
                        wrong.append([i, round(res.confidence, 3), round(float(e_t[0]), 1), round(float(e_r[0]), 1)])
                print(json.dumps({"profile": profile, "drive": drive, "model": name, "scans": len(seq),
                                  "correct": correct, "wrong": len(wrong), "wrong_scan_conf_m_deg": wrong}), flush=True)
        db.close()


if __name__ == "__main__":
    main()
