"""Bad input to the ``reradar`` commands is one line naming what to fix and a non-zero exit (2: usage or settings, 3:
unreachable resources), never a traceback, and never echoes a secret; ``localize --preset`` reaches the API."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_cli import app

SECRET = "SuperSecretOperatorKey-XYZ"


def _run(args: list[str], env: dict[str, str] | None = None):
    res = CliRunner().invoke(app, args, env=env)
    assert "Traceback" not in res.output
    return res


def _help(command: str) -> str:
    """``reradar COMMAND --help`` as one line of words (the rich panel's borders and wrapping removed)."""
    return " ".join(_run([command, "--help"]).output.replace("│", " ").split())


@pytest.mark.parametrize("args, what", [(["--log-level", "nosuch"], "--log-level"), (["--port", "99999"], "--port"),
                                        (["--port", "0"], "--port")])
def test_serve_refuses_bad_options(args, what):
    res = _run(["serve", *args])
    assert res.exit_code == 2 and what in res.output


def test_serve_checks_settings_before_starting(tmp_path, monkeypatch):
    monkeypatch.delenv("RERADAR_MAPS_DIR", raising=False)
    a_file = tmp_path / "traj.csv"
    a_file.write_text("t,x,y,yaw\n")
    res = _run(["serve", "--maps-dir", str(a_file)])
    assert res.exit_code == 2 and "is a file" in res.output
    res = _run(["worker"], env={"RERADAR_MAPS_DIR": str(a_file)})  # the worker reads maps too: the same refusal
    assert res.exit_code == 2 and "RERADAR_MAPS_DIR" in res.output and "is a file" in res.output
    res = _run(["serve", "--maps-dir", str(tmp_path / "maps")], env={"RERADAR_MODEL": "nosuch"})
    assert res.exit_code == 2 and "RERADAR_MODEL" in res.output and "unknown model 'nosuch'" in res.output


@pytest.mark.parametrize("command", [["serve"], ["worker"]])
def test_settings_errors_name_the_field_never_the_keys(command, tmp_path):
    env = {"RERADAR_API_KEY": SECRET, "RERADAR_VEHICLE_KEYS": "short", "RERADAR_MAPS_DIR": str(tmp_path)}
    res = _run(command, env=env)
    assert res.exit_code == 2 and "RERADAR_VEHICLE_KEYS" in res.output and "at least 16 characters" in res.output
    assert SECRET[:6] not in res.output and "short" not in res.output and "input_value" not in res.output
    res = _run(command, env={"RERADAR_API_KEY": "short", "RERADAR_MAPS_DIR": str(tmp_path)})
    assert res.exit_code == 2 and "RERADAR_API_KEY" in res.output and "'short'" not in res.output


def test_worker_redis_url_errors(tmp_path):
    env = {"RERADAR_MAPS_DIR": str(tmp_path)}
    res = _run(["worker"], env={**env, "RERADAR_REDIS_URL": "notaurl"})
    assert res.exit_code == 2 and "not a Redis URL" in res.output
    res = _run(["worker"], env={**env, "RERADAR_REDIS_URL": "redis://:pass-word@127.0.0.1:1/0"})
    assert res.exit_code == 3 and "cannot reach Redis" in res.output and "pass-word" not in res.output
    res = _run(["worker", "--check"], env={**env, "RERADAR_REDIS_URL": "redis://127.0.0.1:1/0"})
    assert res.exit_code == 1 and "cannot reach Redis" in res.output
    res = _run(["worker", "--check"], env={**env, "RERADAR_REDIS_URL": ""})
    assert res.exit_code == 2 and "RERADAR_REDIS_URL" in res.output
    assert "2 if the settings are invalid" in _help("worker")


def _fake_server(monkeypatch) -> list[httpx.Request]:
    """Every request the CLI's client sends, answered 400 by a fake server (no network)."""
    from service import client

    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(400, json={"detail": "fake server: refused"})

    init = client.ReRadarClient.__init__
    monkeypatch.setattr(client.ReRadarClient, "__init__",
                        lambda self, base_url, **kw: init(self, base_url, transport=httpx.MockTransport(handler)))
    return seen


def test_localize_sends_the_preset_and_refuses_ambiguous_npy(tmp_path, monkeypatch):
    seen = _fake_server(monkeypatch)
    scan = tmp_path / "b0.npy"
    np.save(scan, np.zeros((400, 3360), np.uint8))
    res = _run(["localize", str(scan), "--server", "http://x"])
    assert res.exit_code == 2 and "fit several radar presets" in res.output and "--preset" in res.output
    assert seen == []  # refused before anything is sent
    res = _run(["localize", str(scan), "--server", "http://x", "--preset", "mulran"])
    assert res.exit_code == 2 and "fake server: refused" in res.output
    assert b'name="preset"\r\n\r\nmulran\r\n' in seen[-1].read()
    np.save(tmp_path / "o.npy", np.zeros((400, 3768), np.uint8))  # unambiguous: the inferred preset is sent
    _run(["localize", str(tmp_path / "o.npy"), "--server", "http://x"])
    assert b'name="preset"\r\n\r\noxford\r\n' in seen[-1].read()
    np.save(tmp_path / "t.npy", np.zeros((3360, 400), np.uint8))
    res = _run(["localize", str(tmp_path / "t.npy"), "--server", "http://x", "--preset", "boreas"])
    assert res.exit_code == 2  # the server checks an explicit preset (same check, io.scan.check_polar_shape)
    res = _run(["localize", str(tmp_path / "t.npy"), "--server", "http://x"])
    assert res.exit_code == 2 and "cannot infer the radar preset from 400 range bins" in res.output
    res = _run(["localize", str(scan), "--top-k", "-3"])
    assert res.exit_code == 2 and "--top-k" in res.output and "greater than or equal to 1" in res.output


def test_localize_help_shows_the_extras_name():
    text = _help("localize")
    assert "Needs the optional bench extras" in text and "--preset" in text and "--scan-layout" in text


def test_cache_dir_that_is_a_file_and_foreign_sim_folders(tmp_path):
    a_file = tmp_path / "f"
    a_file.write_text("x")
    res = _run(["cache"], env={"RERADAR_CACHE_DIR": str(a_file)})
    assert res.exit_code == 2 and "RERADAR_CACHE_DIR" in res.output and "is a file" in res.output
    (tmp_path / "c" / "sim" / "smoke" / "database").mkdir(parents=True)
    (tmp_path / "c" / "sim" / "smoke" / "database" / "0.png").write_bytes(b"x")
    res = _run(["cache", "--prune"], env={"RERADAR_CACHE_DIR": str(tmp_path / "c")})
    assert res.exit_code == 0 and "nothing stale" in res.output
    assert (tmp_path / "c" / "sim" / "smoke" / "database" / "0.png").is_file()
    text = _help("cache")
    assert "source folder no longer exists" in text


def test_corrupt_weights_are_a_config_error_naming_the_file(tmp_path):
    from reradar_core.model.registry import available_models, resolve_weights

    _, meta = resolve_weights(available_models()[0])
    bad = tmp_path / "models" / "bad2.pt"
    bad.parent.mkdir()
    bad.write_bytes(b"\x80\x04not a torch zip file" * 10)
    bad.with_suffix(".json").write_text(json.dumps(meta))
    res = _run(["export-onnx", str(bad)])  # the JSON records the real file's sha256: checked first
    assert res.exit_code == 2 and "bad2.pt does not match its metadata" in res.output
    assert str(tmp_path) not in res.output  # the file by its name, no internal path
    bad.with_suffix(".json").write_text(json.dumps({k: v for k, v in meta.items() if k != "sha256"}))
    res = _run(["export-onnx", str(bad)])
    assert res.exit_code == 2 and "bad2.pt is not a readable ReRadar weights file" in res.output
    assert str(tmp_path) not in res.output


class _PickledObject:  # torch's safe loader refuses any class it does not allow
    pass


def test_weights_holding_other_objects_are_refused_without_unsafe_advice(tmp_path):
    """torch's refusal text offers ``weights_only=False`` (running the file's pickled code): never passed on
    (QA, session 25)."""
    import torch

    from reradar_core.model.registry import available_models, resolve_weights

    _, meta = resolve_weights(available_models()[0])
    bad = tmp_path / "models" / "pickled.pt"
    bad.parent.mkdir()
    torch.save({"state_dict": {}, "extra": _PickledObject()}, bad)
    bad.with_suffix(".json").write_text(json.dumps({k: v for k, v in meta.items() if k != "sha256"}))
    res = _run(["export-onnx", str(bad)])
    assert res.exit_code == 2 and "pickled.pt is not a readable ReRadar weights file" in res.output
    assert "holds objects other than tensors" in res.output
    assert "weights_only" not in res.output and "code execution" not in res.output


@pytest.mark.parametrize("args, what", [(["--radius", "-5"], "--radius"), (["--limit", "0"], "--limit"),
                                        (["--every", "0"], "--every")])
def test_bench_numbers_are_checked(tmp_path, args, what):
    res = _run(["bench", "--database", str(tmp_path), "--query", str(tmp_path), *args])
    assert res.exit_code == 2 and what in res.output


def test_help_text_has_no_swallowed_brackets():
    """Rich markup takes ``[word]`` for a style and drops it ("Needs the  extras"): no help text may hold one."""
    import re

    from reradar_cli import COMMANDS
    from reradar_cli.main import load_command

    for name in COMMANDS:
        cmd = load_command(name)
        for text in [cmd.help or ""] + [getattr(p, "help", None) or "" for p in cmd.params]:
            assert not re.search(r"(?<!\\)\[[A-Za-z][\w-]*\]", text), (name, text)


def test_readme_lists_every_command():
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    from reradar_cli import COMMANDS

    for name in COMMANDS:
        assert f"`reradar {name}" in readme, name


def test_fit_confidence_refuses_unknown_splits_bad_spacings_and_a_reuse_without_runs(tmp_path, monkeypatch):
    """Each refused before anything is rendered or localized (the cache stays empty)."""
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    res = _run(["fit-confidence", "--splits", "nosuch", "--reuse"])
    assert res.exit_code == 2 and "unknown training split" in res.output and "train-target-boreas" in res.output
    res = _run(["fit-confidence", "--splits", ",", "--reuse"])
    assert res.exit_code == 2 and "no training split" in res.output
    res = _run(["fit-confidence", "--map-spacings-m", "0,-3", "--reuse"])
    assert res.exit_code == 2 and "--map-spacings-m" in res.output
    res = _run(["fit-confidence", "--reuse", "--out", str(tmp_path / "m.json")])
    assert res.exit_code == 2 and "no saved runs" in res.output and "without --reuse" in res.output
    assert not (tmp_path / "m.json").exists()
    assert not any((tmp_path / "cache").rglob("*.npz"))


@pytest.mark.parametrize("args, message", [
    (["--out", "{tmp}/m.txt"], "must end in .json"), (["--out", "{tmp}"], "is a folder"),
    (["--out", "{tmp}/a_file/m.json"], "a file is in the way"), (["--plot", "{tmp}/r.txt"], "must end in .png"),
    (["--plot", "{tmp}"], "is a folder"),
])
def test_fit_confidence_checks_its_outputs_before_collecting(tmp_path, monkeypatch, args, message):
    """QA (session 20): a bad --out or --plot was found only after the hour of localization (a traceback, or the
    model written and the plot not; a folder as --plot wrote <folder>.png beside it)."""
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "a_file").write_text("")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    res = _run(["fit-confidence", "--splits", "train-target-boreas", *args])
    assert res.exit_code == 2 and message in res.output
    assert not (tmp_path / "cache" / "confidence").exists() or not any((tmp_path / "cache").rglob("*.npz"))


def test_build_map_out_a_folder_is_one_line(tmp_path):
    res = _run(["build-map", "--dataset", str(tmp_path), "--out", str(tmp_path), "--overwrite"])
    assert res.exit_code == 2 and "is a folder" in res.output and "map.h5" in res.output


def test_map_info_checks_the_arrays_and_build_map_checks_its_output_first(tmp_path):
    """QA (session 20): map-info said a map without /poses was fine (it read the attributes only); build-map wrote an
    HDF5 map under any name and failed on an unwritable --out only after the network ran."""
    import shutil

    import h5py

    from maps import DEMO_MAP_PATH

    good = tmp_path / "good.h5"
    shutil.copy(DEMO_MAP_PATH, good)
    res = _run(["map-info", str(good)])
    assert res.exit_code == 0 and json.loads(res.output)["num_keyframes"] == 80
    # an ordinary street: the stored place repetition (default settings) marks no keyframe
    assert json.loads(res.output)["place_repetition"] == {"default_settings": True, "keyframes_marked": 0,
                                                          "keyframes_unjudged": 0, "max_ratio": 0.6667}
    broken = tmp_path / "broken.h5"
    shutil.copy(DEMO_MAP_PATH, broken)
    with h5py.File(broken, "a") as f:
        del f["poses"]
    res = _run(["map-info", str(broken)])
    assert res.exit_code == 2 and "poses" in res.output
    res = _run(["map-info", str(tmp_path)])
    assert res.exit_code == 2 and "is a folder" in res.output
    (tmp_path / "a_file").write_text("")
    for out, message in ((tmp_path / "m.json", "must end in .h5"), (tmp_path / "a_file" / "m.h5", "a file is in the way")):
        res = _run(["build-map", "--dataset", str(tmp_path), "--out", str(out)])
        assert res.exit_code == 2 and message in res.output


def test_bench_refuses_the_database_as_a_query_and_an_unwritable_out_before_running(tmp_path):
    """QA (session 20): ``--query`` = ``--database`` reported Recall@1 100 % without a word; an --out under a file
    ended in a traceback after the whole benchmark had run."""
    db = tmp_path / "db"
    db.mkdir()
    res = _run(["bench", "--database", str(db), "--query", str(tmp_path / "." / "db"), "-m", "ringkey"])
    assert res.exit_code == 2 and "is the --database folder" in res.output
    (tmp_path / "a_file").write_text("")
    res = _run(["bench", "--database", str(db), "--query", str(tmp_path), "-m", "ringkey",
                "--out", str(tmp_path / "a_file" / "out")])
    assert res.exit_code == 2 and "a file is in the way" in res.output


def test_export_onnx_names_a_missing_weights_file_as_missing(tmp_path):
    """QA (session 20): a .pt path that does not exist was answered 'unknown model ... (or give a .pt path)'."""
    res = _run(["export-onnx", str(tmp_path / "nonexist.pt")])
    assert res.exit_code == 2 and "no such weights file" in res.output and "unknown model" not in res.output
    (tmp_path / "x.pt").mkdir()
    res = _run(["export-onnx", str(tmp_path / "x.pt")])
    assert res.exit_code == 2 and "is a folder" in res.output


@pytest.mark.parametrize("damage", ["truncated", "empty", "architecture", "bit-flip"])
def test_serve_refuses_an_unreadable_model_file_in_one_line(tmp_path, damage):
    """QA: ``RERADAR_MODEL=<truncated|empty|wrong-architecture>.pt reradar serve`` logged a start-up traceback and
    exited 3; now the same one-line ``error: RERADAR_MODEL: ...`` and exit 2 as an unknown name, before the server
    starts."""
    import torch

    from reradar_core.model import DescriptorNet, ModelConfig, save_weights

    torch.manual_seed(0)
    width = 0.5 if damage == "architecture" else 0.25
    net = DescriptorNet(ModelConfig(backbone="resnet", width=width, num_clusters=4, output_dim=16)).eval()
    pt = save_weights(net, tmp_path / "m.pt", {}, onnx=False)
    meta = json.loads(pt.with_suffix(".json").read_text())
    raw = pt.read_bytes()
    if damage == "bit-flip":
        pt.write_bytes(raw[:1000] + bytes([raw[1000] ^ 1]) + raw[1001:])
    else:  # without a recorded sha256, so that loading itself must fail
        del meta["sha256"]
        if damage == "architecture":
            meta["config"]["width"] = 0.25
        else:
            pt.write_bytes(raw[: len(raw) // 2] if damage == "truncated" else b"")
    pt.with_suffix(".json").write_text(json.dumps(meta))
    res = _run(["serve", "--maps-dir", str(tmp_path / "maps")], env={"RERADAR_MODEL": str(pt)})
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: RERADAR_MODEL: ") and "m.pt" in lines[0], res.output


def test_fit_confidence_warns_when_too_few_wrong_answers_to_fit_a_bar(caplog):
    """QA: a tiny fit set (86 runs, no wrong answer above the floor) wrote ``min_confidence: 0.0`` without a word.
    (Library-level: ``reradar fit-confidence`` logs this warning; its own tests live in tests/localization.)"""
    import logging

    from reradar_core.localization.confidence import CUE_NAMES
    from reradar_core.localization.confidence_fit import MIN_WRONG_FOR_BAR, FitData, fit_from_data

    rng = np.random.default_rng(5)

    def data(n: int, wrong_rate: float) -> FitData:
        x = rng.normal(size=(n, len(CUE_NAMES)))
        x[:, 0] = rng.uniform(0.5, 1.0, n)
        correct = rng.uniform(size=n) >= wrong_rate
        if wrong_rate == 0.0:  # wrong answers only below the aligned-landmark floor (the QA's fit set)
            correct[:10] = False
            x[:10, 0] = 0.1
        return FitData(x, np.ones(n, bool), correct, x[:, 0] >= 0.3, np.ones(n, bool), np.zeros(n, bool),
                       np.array(["train-target-loop"] * n), np.zeros(n, bool))

    with caplog.at_level(logging.WARNING, logger="reradar_core.localization.confidence_fit"):
        model, report = fit_from_data(data(86, 0.0), floors=(0.3,))
    assert "too few wrong answers to fit a confidence bar" in caplog.text
    assert report["warnings"] and "only 0 wrong answer(s)" in report["warnings"][0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="reradar_core.localization.confidence_fit"):
        _, report = fit_from_data(data(2000, 0.2), floors=(0.3,))  # hundreds of wrong answers: no warning
    assert "warnings" not in report and "too few" not in caplog.text and MIN_WRONG_FOR_BAR <= 400


def test_serve_on_a_port_in_use_says_so_before_loading_anything(tmp_path, monkeypatch):
    """A second server on a busy port is one line before the model and maps load (QA session 36: a uvicorn log line
    after the whole start-up), and the first server is untouched."""
    import socket

    monkeypatch.setattr("service.cli.served_model_or_exit", lambda *a, **k: pytest.fail("loaded the model"))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = _run(["serve", "--port", str(port), "--maps-dir", str(tmp_path / "maps")])
        assert res.exit_code == 2 and f"127.0.0.1:{port} is in use" in res.output and "--port" in res.output
    from service.cli import address_free_or_exit

    with socket.socket() as busy:  # uvicorn binds IPv6 only for an IPv6 host: an IPv4 server there is no conflict
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        if socket.has_ipv6:
            try:
                address_free_or_exit("::1", port)
            except OSError:  # no IPv6 on this machine's loopback: nothing to check
                pass
    with socket.socket() as probe:  # a port the system just handed out and took back: free
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    address_free_or_exit("", free)  # "" is every interface, as uvicorn reads it, not a refusal


def test_a_folder_or_another_file_named_as_a_pose_or_weights_file_is_said_to_be_one(tmp_path):
    folder = tmp_path / "adir"
    folder.mkdir()
    res = _run(["sim", "--trajectory", str(folder), "--time-unit", "s", "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "is a folder, not a pose file" in res.output
    text = tmp_path / "traj.csv"
    text.write_text("t,x,y,yaw\n")
    res = _run(["export-onnx", str(text)])
    assert res.exit_code != 0 and "is not a weights file (.pt)" in res.output and "no such" not in res.output


def test_replay_options_without_follow_are_refused(tmp_path):
    """QA session 36: `localize --every 2 SCAN` ignored --every without a word."""
    scan = tmp_path / "1600000000000000.png"
    scan.write_bytes(b"\x89PNG\r\n\x1a\n")
    res = _run(["localize", str(scan), "--every", "2", "--no-tracking"])
    assert res.exit_code == 2 and "--every, --no-tracking apply to a replay with --follow" in res.output


def test_train_refuses_an_unknown_device_before_making_its_run_folder(tmp_path, monkeypatch):
    """QA session 36: `--device tpu` was refused clearly but left an empty run folder in the cache."""
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    seq = tmp_path / "seq"
    seq.mkdir()
    res = _run(["train", "--name", "e1", "--sequence", str(seq), "--device", "tpu", "--out-dir", str(tmp_path / "o"),
                "--steps", "1"])
    assert res.exit_code != 0 and "unknown device 'tpu'" in res.output
    assert not (tmp_path / "cache" / "training" / "runs" / "e1").exists()


def test_a_closed_stdout_ends_a_command_quietly():
    """QA session 38: `reradar localize --follow ... | head -3` ended with "error: Broken pipe" (exit 2)."""
    import subprocess
    import sys

    script = ("import typer\nfrom reradar_cli.main import _guarded\n"
              "def long():\n    for i in range(200000):\n        typer.echo(f'row {i}')\n"
              "app = typer.Typer()\napp.command()(_guarded('x', long))\napp()\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline() == b"row 0\n"
    proc.stdout.close()  # the reader goes away, as `head` does
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 141 and b"Broken pipe" not in err and b"Traceback" not in err, err
