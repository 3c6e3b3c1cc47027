"""``reradar localize --follow SEQUENCE_DIR``: replay a recorded drive through a running service in tracking
mode, print a per-scan table against the folder's ground truth and draw the trajectory (PNG).

Each scan is sent with one session id and the odometry since the previous scan; odometry is the ground-truth
relative motion with seeded multiplicative noise (``odometry_noise`` x step length / turn), standing in for
a vehicle's wheel odometry, or none at all (the server then localizes each scan globally, docs/SERVICE.md).

Two bars: the paper's success (20 m, 10 degrees: the right place) and pose accuracy (2 m, 2 degrees: a pose a
vehicle can use; the service's own pose target, README "Pose on real scans"). A ``localized`` answer beyond the
first is ``WRONG``, one beyond the second ``OFF``; the replay fails (exit 1) on either, since a tracking
answer 5 m behind the vehicle is the right place but the wrong pose.
"""

from __future__ import annotations

import math
import os
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["INTERRUPTED_EXIT", "answer_errors", "follow_sequence", "interrupted_line", "noisy_odometry",
           "trajectory_path"]

#: pose accuracy a vehicle needs (metres, degrees); success is the paper's rule (``evaluation.localization_success``:
#: e_t < R of the radar's dataset, 20 m Boreas / MulRan, 25 m OORD / Oxford, and e_r < 10 degrees)
POSE_TRANSLATION_M = 2.0
POSE_ROTATION_DEG = 2.0


def noisy_odometry(T_prev_curr: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """(dx m, dy m, dyaw rad) with zero-mean Gaussian noise of ``noise`` x the step length on each axis and
    ``noise`` x the turn (plus 0.1 degrees) on the heading."""
    step = float(np.hypot(T_prev_curr[0], T_prev_curr[1]))
    out = np.asarray(T_prev_curr, np.float64).copy()
    out[:2] += rng.normal(scale=noise * step, size=2)
    out[2] += rng.normal(scale=noise * abs(out[2]) + math.radians(0.1))
    return out


def answer_errors(pose: Any, T_map_gt: Any) -> tuple[float, float]:
    """(translation error m, heading error deg) of an answer's ``pose`` (``x_m``, ``y_m``, ``yaw_deg``, as the API
    returns it) against the (3,) ground truth (x m, y m, yaw rad): ``evaluation.localization_errors``."""
    from reradar_core.evaluation import localization_errors

    est = np.array([[pose.x_m, pose.y_m, math.radians(pose.yaw_deg)]])
    e_t, e_r = localization_errors(est, np.asarray(T_map_gt, np.float64).reshape(1, 3))
    return float(e_t[0]), float(e_r[0])


def trajectory_path(out: Path | None, folder: Path) -> Path:
    """Where the replay of ``folder`` writes its trajectory PNG: ``out`` itself (a ``.png`` file), or
    ``<folder>-follow.png`` inside ``out`` when it is an existing folder, or beside ``folder`` when ``out`` is None.

    ValueError when that name does not end in ``.png`` (the plot is a PNG) or its folder does not exist (it is
    not created: a mistyped path should not make folders) or cannot be written. Checked before the replay: it
    would otherwise fail, or write under another name, after the whole drive.
    """
    # "." and ".." have no usable name of their own: name the PNG after the folder they stand for
    src = folder.resolve() if folder.name in ("", ".", "..") else folder
    name = f"{src.name}-follow.png"
    png = src.with_name(name) if out is None else out / name if out.is_dir() else out
    if png.suffix.lower() != ".png":
        raise ValueError(f"--out {out}: the trajectory is written as a PNG; give a file name ending in .png "
                         "(or an existing folder)")
    parent = png.parent
    if parent.exists() and not parent.is_dir():
        raise ValueError(f"cannot write the trajectory PNG {png}: {parent} is a file, not a folder (give another "
                         "--out)")
    if not parent.is_dir():
        raise ValueError(f"cannot write the trajectory PNG {png}: folder {parent} does not exist (it is not "
                         "created; make it, or give another --out)")
    if not os.access(parent, os.W_OK):
        raise ValueError(f"cannot write the trajectory PNG {png}: folder {parent} is not writable (give another "
                         "--out)")
    return png


#: Exit status of a replay stopped with Ctrl-C (KeyboardInterrupt): 128 + SIGINT (2), the shell's convention
INTERRUPTED_EXIT = 130


def interrupted_line(answered: int, planned: int) -> str:
    """The line a replay stopped with Ctrl-C prints above its summary: how many of the ``planned`` scans were
    ``answered`` (a row each; the scan in flight when the key was pressed is not counted)."""
    return f"interrupted after {answered} of {planned} scans (Ctrl-C): the summary below covers the {answered} answered"


#: Tries of one scan the server refused as busy (429 / 503) before the replay records it as an error, and the wait
#: before each further try (seconds; the server's Retry-After is 1-2 s)
BUSY_RETRIES = 3
BUSY_WAIT_S = 1.0


def follow_sequence(client: Any, folder: Path, map_id: str, echo: Callable[[str], None] = print,
                    echo_err: Callable[[str], None] | None = None, top_k: int | None = None,
                    odometry: str = "ground-truth", odometry_noise: float = 0.05,
                    every: int = 1, limit: int | None = None, tracking: bool = True, out: Path | None = None,
                    seed: int = 0, session: str | None = None, preset: str | None = None,
                    time_unit: str | None = None) -> int:
    """Replay ``folder`` on map ``map_id`` with ``client`` (``service.client.ReRadarClient``).

    ``preset`` (None: the folder's own) is the radar the folder was recorded with, given to the sequence loader
    and sent with every scan; ``time_unit`` (``s``, ``ms``, ``us``, ``ns``; None: absolute UTC times or the
    format's unit, never a guess) is the unit of the folder's pose-file timestamps (``load_sequence``'s
    ``pose_time_unit``, as ``reradar build-map --time-unit``).

    A scan the service answers with an error about the scan (``_scan_error``: 400 / 413 / 415 / 422) is an ``error``
    row and the replay goes on; one it refuses as busy (429 / 503) is tried again ``BUSY_RETRIES`` times,
    ``BUSY_WAIT_S`` apart and longer each time; any other error answer (key, map, not the ReRadar API) or a lost
    server ends the replay there. The summary and the trajectory are written either way. Errors go to
    ``echo_err`` (default ``echo``). Ctrl-C (KeyboardInterrupt) during the replay stops sending too: the line
    ``interrupted_line`` prints, then the summary and the trajectory of the scans answered so far; a second
    Ctrl-C while they are written propagates (the caller, ``reradar localize``, exits 130 at once).

    Returns 0 when at least one scan was localized and every ``localized`` answer is within ``POSE_TRANSLATION_M``
    and ``POSE_ROTATION_DEG`` of the ground truth and no scan failed; 1 when an answer was off, no scan was
    localized or a scan failed; 3 when the server was lost mid-replay; ``INTERRUPTED_EXIT`` (130) when Ctrl-C
    stopped the replay, whatever the answers so far; 2 for an error answer that ends the replay,
    an unreadable folder, or ``out`` refused by ``trajectory_path`` before any scan is sent. The trajectory goes to
    ``trajectory_path(out, folder)``, printed as ``trajectory: PATH``.
    """
    import httpx

    from service.client import ReRadarAPIError

    say_err = echo_err or echo
    from reradar_core.errors import ReRadarError
    from reradar_core.evaluation import localization_success, radius_for
    from reradar_core.geometry.se2 import relative_pose
    from reradar_core.io.datasets import load_sequence, read_sequence_meta

    try:
        seq = load_sequence(folder, preset=preset, pose_time_unit=time_unit)
    except ReRadarError as exc:
        say_err(f"error: {exc}")
        return 2
    try:
        png = trajectory_path(out, folder)
    except ValueError as exc:
        say_err(f"error: {exc}")
        return 2
    idx = np.arange(0, len(seq), every)
    if limit is not None:
        idx = idx[:limit]
    if seq.layout == "oxford" and "oxford_T_world_origin" not in read_sequence_meta(folder):
        # real Oxford odometry starts at the identity: its frame is the map's only for a map built from this drive
        echo("note: this folder's ground truth is its own odometry (it starts at the identity); the errors below "
             "mean something only on a map built from this same drive (e.g. `reradar build-map --dataset` of it)")
    gt = seq.mid_sweep_poses()  # the service answers mid-sweep poses (docs/CONVENTIONS.md)
    radius_m = radius_for(seq.preset.name)
    rng = np.random.default_rng(seed)
    session_id = (session or f"follow-{uuid.uuid4().hex[:12]}") if tracking else None
    head = (f"{'#':>4} {'scan':<22} {'mode':<16} {'status':<13} {'x_m':>8} {'y_m':>8} {'yaw_deg':>8} | "
            f"{'gt_x_m':>8} {'gt_y_m':>8} {'gt_yaw':>8} | {'err_m':>6} {'err_deg':>7} {'score':>5} {'ms':>5}")
    echo(head)
    echo("-" * len(head))
    rows: list[dict[str, Any]] = []
    prev = None
    lost = fatal = interrupted = False
    try:
        for n, i in enumerate(idx):
            odo = None
            if tracking and odometry == "ground-truth" and prev is not None:
                T = noisy_odometry(relative_pose(gt[prev], gt[i]), odometry_noise, rng)
                odo = (float(T[0]), float(T[1]), math.degrees(float(T[2])))
            name = seq.scan_paths[i].name
            g = gt[i]
            gts = f"{g[0]:8.2f} {g[1]:8.2f} {math.degrees(g[2]):8.2f}"
            t0 = time.perf_counter()
            try:
                res = _localize_patiently(client, map_id, seq.scan_paths[i], top_k, session_id, odo, preset)
            except ReRadarAPIError as exc:
                if not _scan_error(exc):  # the server, the key or the map: every next scan would get the same
                    say_err(f"error: scan {name}: {exc}; the replay stops here")
                    fatal = True
                    break
                # this scan's answer (a corrupt or refused file): the replay goes on, the next scan without odometry
                rows.append({"i": int(i), "mode": "-", "status": "error", "ms": (time.perf_counter() - t0) * 1e3,
                             "server_ms": float("nan"), "gt": g, "pose": None, "ok": False, "wrong": False,
                             "accurate": False, "err": None, "error": True})
                echo(f"{n:4d} {name:<22} {'-':<16} {'error':<13} {'-':>8} {'-':>8} {'-':>8} | {gts} |  (see stderr)")
                say_err(f"error: scan {name}: {exc}")
                prev = None
                continue
            except httpx.TransportError as exc:
                say_err(f"error: scan {name}: the server was lost ({exc}); the replay stops here")
                lost = True
                break
            ms = (time.perf_counter() - t0) * 1e3
            prev = i
            row: dict[str, Any] = {"i": int(i), "mode": res.mode + ("*" if res.tracking_lost else "")
                                   + ("+far" if res.view == "far" else "")
                                   + ("+dense" if res.registration == "dense" else ""),
                                   "status": res.status, "ms": ms, "server_ms": res.timings_ms.get("total_ms", ms),
                                   "gt": g, "pose": None, "ok": False, "wrong": False, "accurate": False,
                                   "err": None}
            rows.append(row)  # answered: counted even when Ctrl-C comes before its line is printed
            if res.status == "localized" and res.pose is not None:
                et, er = answer_errors(res.pose, g)
                row.update(pose=(res.pose.x_m, res.pose.y_m), ok=bool(localization_success(et, er, radius_m)),
                           accurate=et <= POSE_TRANSLATION_M and er <= POSE_ROTATION_DEG, err=(et, er))
                row["wrong"] = not row["ok"]
                flag = "  WRONG" if row["wrong"] else ("" if row["accurate"] else "  OFF")
                echo(f"{n:4d} {name:<22} {row['mode']:<16} {res.status:<13} {res.pose.x_m:8.2f} {res.pose.y_m:8.2f} "
                     f"{res.pose.yaw_deg:8.2f} | {gts} | {et:6.2f} {er:7.2f} {res.alignment_score:5.2f} {ms:5.0f}"
                     + flag)
            else:
                echo(f"{n:4d} {name:<22} {row['mode']:<16} {res.status:<13} {'-':>8} {'-':>8} {'-':>8} | {gts} | "
                     f"{'-':>6} {'-':>7} {res.alignment_score:5.2f} {ms:5.0f}  ({res.reason})")
    except KeyboardInterrupt:  # Ctrl-C: stop sending; the scan in flight, unanswered, is not counted
        interrupted = True
        echo("")
        echo(interrupted_line(len(rows), len(idx)))
    _summary(rows, echo, radius_m)
    if rows:
        try:
            _plot(rows, gt[idx[:len(rows)]], png, f"{folder.name} on map {map_id}")
            echo(f"trajectory: {png}")
        except ModuleNotFoundError:
            echo("trajectory PNG skipped: matplotlib is not installed (pip install 'reradar[plot]')")
    if interrupted:
        return INTERRUPTED_EXIT
    if lost:
        return 3
    if fatal:
        return 2
    off = any(r["pose"] is not None and not r["accurate"] for r in rows)
    failed = any(r.get("error") for r in rows)
    # a replay that localized nothing is no success, whatever else it printed (QA session 38: exit 0 at 0/12)
    return 1 if off or failed or not any(r["pose"] is not None for r in rows) else 0


def _scan_error(exc: Any) -> bool:
    """True for an error answer about the scan itself (400 / 413 / 415 / 422: unreadable, too large, another
    layout), after which a replay goes on; the others (a key refused, an unknown or unready map, an answer that is
    not the ReRadar API's, a server error) would repeat for every scan and end it."""
    from service.client import ReRadarResponseError

    return not isinstance(exc, ReRadarResponseError) and exc.status_code in (400, 413, 415, 422)


def _localize_patiently(client: Any, map_id: str, scan: Path, top_k: int | None, session_id: str | None,
                        odometry: Any, preset: str | None) -> Any:
    """``client.localize`` of one scan, tried again while the server answers busy (429 / 503): ``BUSY_RETRIES``
    more tries, ``BUSY_WAIT_S`` x 1, 2, 3 apart (a replay is one request at a time, so it never hammers)."""
    from service.client import ReRadarAPIError

    for attempt in range(BUSY_RETRIES + 1):
        try:
            return client.localize(map_id, scan_path=scan, top_k=top_k, session_id=session_id, odometry=odometry,
                                   preset=preset)
        except ReRadarAPIError as exc:
            if exc.status_code not in (429, 503) or attempt == BUSY_RETRIES:
                raise
            time.sleep(BUSY_WAIT_S * (attempt + 1))
    raise AssertionError("unreachable")  # pragma: no cover


def _summary(rows: list[dict[str, Any]], echo: Callable[[str], None], radius_m: float) -> None:
    from reradar_core.evaluation import MAX_ROTATION_ERROR_DEG

    n = len(rows)
    if not n:
        echo("no scans")
        return
    ok = sum(r["ok"] for r in rows)
    wrong = sum(r["wrong"] for r in rows)
    failed = sum(bool(r.get("error")) for r in rows)
    echo("")
    echo(f"success (< {radius_m:g} m and < {MAX_ROTATION_ERROR_DEG:g} deg): {ok}/{n} ({100 * ok / n:.1f} %); "
         f"localized at a wrong pose: {wrong}/{n}; not localized: {n - ok - wrong - failed}/{n}"
         + (f"; failed (an error answer, on stderr): {failed}/{n}" if failed else ""))
    echo(_accuracy_line(rows))
    for mode in sorted({r["mode"] for r in rows if not r.get("error")}):
        sel = [r for r in rows if r["mode"] == mode]
        echo(f"mode {mode:<16} {len(sel):4d} scans: server p50 {np.percentile([r['server_ms'] for r in sel], 50):.0f} ms, "
             f"client p50 {np.percentile([r['ms'] for r in sel], 50):.0f} ms")
    echo("(mode global* = tracking was lost and the scan was localized globally; +far = answered by the map's far "
         "view, its own view having refused; +dense = placed by the far view's dense registration)")


def _accuracy_line(rows: list[dict[str, Any]]) -> str:
    """The pose-accuracy summary: answers within ``POSE_TRANSLATION_M`` / ``POSE_ROTATION_DEG`` of all scans,
    localized answers outside it, and the median and largest error of the localized answers."""
    n = len(rows)
    errs = np.array([r["err"] for r in rows if r["err"] is not None], np.float64).reshape(-1, 2)
    good = sum(bool(r["accurate"]) for r in rows)
    head = (f"pose accuracy (<= {POSE_TRANSLATION_M:g} m and <= {POSE_ROTATION_DEG:g} deg): {good}/{n} "
            f"({100 * good / n:.1f} %); localized outside it: {len(errs) - good}/{n}")
    if not len(errs):
        return head
    med, top = np.median(errs, axis=0), errs.max(axis=0)
    return (f"{head}; error over the {len(errs)} localized: median {med[0]:.2f} m / {med[1]:.2f} deg, "
            f"max {top[0]:.2f} m / {top[1]:.2f} deg")


def _plot(rows: list[dict[str, Any]], gt: np.ndarray, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    o = gt[0, :2]  # plot relative to the first ground-truth pose: map coordinates may be UTM (1e6 m)
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(gt[:, 0] - o[0], gt[:, 1] - o[1], "-", color="0.6", lw=1.5, label="ground truth")
    styles = {"tracking": ("tab:blue", "o"), "global": ("tab:green", "s"), "global*": ("tab:orange", "^")}
    for mode, (color, marker) in styles.items():
        pts = np.array([r["pose"] for r in rows if r["pose"] is not None and r["mode"] == mode and r["accurate"]]).reshape(-1, 2) - o
        if len(pts):
            ax.scatter(pts[:, 0], pts[:, 1], s=10, c=color, marker=marker, label=f"{mode} ({len(pts)})")
    off = np.array([r["pose"] for r in rows if r["pose"] is not None and not r["accurate"] and not r["wrong"]]).reshape(-1, 2) - o
    if len(off):
        ax.scatter(off[:, 0], off[:, 1], s=30, c="tab:purple", marker="d",
                   label=f"outside {POSE_TRANSLATION_M:g} m / {POSE_ROTATION_DEG:g} deg ({len(off)})")
    bad = np.array([r["pose"] for r in rows if r["wrong"]]).reshape(-1, 2) - o
    if len(bad):
        ax.scatter(bad[:, 0], bad[:, 1], s=40, c="tab:red", marker="x", label=f"wrong pose ({len(bad)})")
    lost = np.array([r["gt"][:2] for r in rows if r["pose"] is None and not r.get("error")]).reshape(-1, 2) - o
    if len(lost):
        ax.scatter(lost[:, 0], lost[:, 1], s=12, facecolors="none", edgecolors="k", lw=0.6,
                   label=f"not localized ({len(lost)}, at ground truth)")
    # a square window round everything drawn, at least 20 m a side: with equal axes a straight drive collapsed
    # one axis into overlapping ticks under the legend (QA session 38)
    drawn = np.vstack([gt[:, :2] - o] + [np.array([r["pose"]]) - o for r in rows if r["pose"] is not None])
    centre = (drawn.min(axis=0) + drawn.max(axis=0)) / 2
    half = max(float(np.ptp(drawn, axis=0).max()) / 2, 10.0) * 1.15
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x - {o[0]:.1f} (m, map frame)")
    ax.set_ylabel(f"y - {o[1]:.1f} (m, map frame)")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120, format="png")  # trajectory_path checked the name and its folder
    plt.close(fig)
