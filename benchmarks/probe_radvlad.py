"""What RadVLAD responds to: perturb the query scans of one cached calibration subset and re-run it.

Reads a subset written by ``benchmarks/calibrate_sim.py`` (``.cache/reradar/calib/<suite>-<tag>.npz``) and prints
RadVLAD's Recall@1 with the query scans unchanged, brightened, noisier, partly flattened or shifted in range
(docs/SIMULATOR.md, "Hard suites: ablation towards simulator v5").

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_radvlad.py .cache/reradar/calib/loop-sim-hard-<tag>.npz
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibrate_sim import recall_at_1  # noqa: E402


def main(path: str, method: str = "radvlad") -> None:
    z = np.load(path)
    d: dict[str, object] = {k: z[k] for k in z.files}
    d["radius"], d["preset"] = float(z["radius"]), str(z["preset"])
    q = np.asarray(d["q_scans"]).astype(np.float32)
    rng = np.random.default_rng(0)

    def run(name: str, qq: np.ndarray) -> None:
        e = dict(d)
        e["q_scans"] = np.clip(np.round(qq), 0, 255).astype(np.uint8)
        print(f"{name:20s} {recall_at_1(method, e):.2f}", flush=True)

    quarter = q.shape[2] // 4
    run("unchanged", q)
    run("+15/255 every bin", q + 15)
    run("range roll 40 bins", np.roll(q, 40, axis=2))
    run("noise sigma 20/255", q + rng.normal(0, 20, q.shape))
    m = q.copy()
    m[:, :, :quarter] = np.median(q)
    run("near quarter flat", m)
    m = q.copy()
    m[:, :, quarter:] = np.median(q)
    run("far 3/4 flat", m)


if __name__ == "__main__":
    main(*sys.argv[1:])
