"""The ``reradar`` command line and the package boundaries it relies on: every sub-command is listed without
importing any of them, the vehicle client and the serving path import nothing they do not use, and the
library never imports the map store, the service or the CLI."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from reradar_cli import COMMANDS, app

ROOT = Path(__file__).resolve().parents[2]

#: heavy or unrelated modules that must stay out of the light paths
HEAVY = ("torch", "e2cnn", "faiss", "matplotlib", "scipy", "cv2", "h5py", "fastapi")
NOT_SERVING = ("reradar_core.sim", "reradar_core.training", "reradar_core.baselines", "reradar_core.benchmark",
               "matplotlib", "onnx", "onnxscript", "onnx_ir")  # the ONNX exporter: serving only runs the graph


def _loaded_after(code: str) -> list[str]:
    """Run ``code`` in a fresh interpreter (repository root) and return the modules it loaded."""
    out = subprocess.run([sys.executable, "-c", code + "\nimport json, sys; print(json.dumps(sorted(sys.modules)))"],
                         cwd=ROOT, capture_output=True, text=True, check=True, timeout=300)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _offending(modules: list[str], prefixes: tuple[str, ...]) -> list[str]:
    return [m for m in modules if any(m == p or m.startswith(p + ".") for p in prefixes)]


def test_help_lists_every_command_without_importing_them() -> None:
    res = CliRunner().invoke(app, ["--help"])
    assert res.exit_code == 0, res.output
    for name in ("info", "sim", "train", "build-map", "bench", "serve", "localize", "demo"):
        assert name in COMMANDS and name in res.output
    loaded = _loaded_after("from typer.testing import CliRunner\nfrom reradar_cli import app\n"
                           "assert CliRunner().invoke(app, ['--help']).exit_code == 0")
    assert _offending(loaded, HEAVY + ("reradar_core", "maps", "service")) == []


def test_every_command_resolves_to_its_module() -> None:
    for name in COMMANDS:
        res = CliRunner().invoke(app, [name, "--help"])
        assert res.exit_code == 0, (name, res.output)
        assert "Usage" in res.output
        # an on/off flag is not labelled with a type (typer 0.29 writes <bool>, read as "takes a value")
        assert "<bool>" not in res.output, name
    assert CliRunner().invoke(app, ["no-such-command"]).exit_code != 0
    assert "<int>" in CliRunner().invoke(app, ["bench", "--help"]).output  # options with values keep theirs


def test_vehicle_client_imports_no_server_dependency() -> None:
    loaded = _loaded_after("import service.client, service.cli\nfrom typer.testing import CliRunner\n"
                           "from reradar_cli import app\n"
                           "assert CliRunner().invoke(app, ['localize', '--help']).exit_code == 0")
    assert _offending(loaded, HEAVY + ("reradar_core.localization", "maps", "reradar_core.model")) == []


def test_serving_path_never_imports_simulator_training_baselines_or_benchmark() -> None:
    """A real localization over HTTP (TestClient, shipped model, demo map) loads none of them."""
    code = f"""
import tempfile
from pathlib import Path
from fastapi.testclient import TestClient
from service.core.config import Settings
from service.main import create_app
q = sorted(Path({str(ROOT / 'maps' / 'demo' / 'queries')!r}).glob('*.png'))[0]
s = Settings(maps_dir=Path(tempfile.mkdtemp()) / 'maps', load_demo_map=True, vehicle_keys='v' * 20)
with TestClient(create_app(s)) as c:
    r = c.post('/localize', data={{'map_id': 'demo'}}, files={{'scan': (q.name, q.read_bytes(), 'image/png')}},
               headers={{'X-API-Key': 'v' * 20}})
    assert r.status_code == 200, r.text
"""
    loaded = _loaded_after(code)
    assert "reradar_core.localization.localizer" in loaded and "torch" in loaded  # it really served a request
    assert "onnxruntime" in loaded  # the shipped model's network ran in ONNX Runtime
    assert _offending(loaded, NOT_SERVING) == []


def test_export_onnx_refuses_an_unknown_model_with_the_known_ones() -> None:
    res = CliRunner().invoke(app, ["export-onnx", "no-such-model"])
    assert res.exit_code == 2
    assert "unknown model 'no-such-model'" in res.output and "our-3-boreas-w05" in res.output


def test_library_never_imports_maps_service_or_cli() -> None:
    bad = []
    for path in (ROOT / "reradar_core").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            bad += [f"{path.relative_to(ROOT)}: {n}" for n in names
                    if n.split(".")[0] in ("maps", "service", "reradar_cli")]
    assert bad == []


def test_missing_optional_dependency_is_an_actionable_error(monkeypatch) -> None:  # noqa: ANN001
    """A client-only install has no uvicorn: `reradar serve` says which extra to install (exit 2)."""
    monkeypatch.setitem(sys.modules, "uvicorn", None)  # `import uvicorn` now raises ModuleNotFoundError
    res = CliRunner().invoke(app, ["serve", "--port", "1"])
    assert res.exit_code == 2
    assert "uvicorn" in res.output and "reradar[server]" in res.output
