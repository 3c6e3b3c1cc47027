"""``reradar localize --follow``'s pose-accuracy summary: answers within 2 m / 2 deg next to the paper's
20 m / 10 deg success, with the localized answers' median and largest error (rows with known errors)."""

from __future__ import annotations

from typing import Any

from service.follow import _accuracy_line


def _row(err: tuple[float, float] | None) -> dict[str, Any]:
    if err is None:
        return {"err": None, "accurate": False, "pose": None}
    return {"err": err, "accurate": err[0] <= 2.0 and err[1] <= 2.0, "pose": (0.0, 0.0)}


def test_accuracy_line_counts_answers_outside_2_m_2_deg() -> None:
    # the QA drive at 8 m/s tracked without odometry: right place (within 20 m), wrong pose
    rows = [_row((0.10, 0.15)), _row((0.36, 0.24)), _row((1.02, 0.05)), _row((1.91, 0.08)), _row((3.13, 0.14)),
            _row((7.38, 0.01)), _row((0.2, 2.5)), _row(None)]
    line = _accuracy_line(rows)
    assert line.startswith("pose accuracy (<= 2 m and <= 2 deg): 4/8 (50.0 %); localized outside it: 3/8")
    assert "error over the 7 localized: median 1.02 m / 0.14 deg, max 7.38 m / 2.50 deg" in line
    assert _accuracy_line([_row(None)]) == "pose accuracy (<= 2 m and <= 2 deg): 0/1 (0.0 %); localized outside it: 0/1"
