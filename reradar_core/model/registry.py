"""Shipped model weights: ``reradar_core/model/weights/<name>.pt`` + ``<name>.json`` (config, provenance).

The ``.pt`` file holds ``{"state_dict": ...}`` of the exported plain-torch ``DescriptorNet`` (float32), so
loading needs neither e2cnn nor training code. The JSON holds the ``ModelConfig``, training data, command,
time, validation Recall@1 and the weights' sha256. ``<name>.onnx`` beside them is the same network as an ONNX graph
(``reradar_core.model.runtime``), which inference runs in ONNX Runtime when it is there.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import torch

from reradar_core.errors import ConfigError
from reradar_core.model.network import DescriptorNet

__all__ = ["WEIGHTS_DIR", "DEFAULT_MODEL", "available_models", "export_weights_onnx", "resolve_weights",
           "save_weights"]

logger = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
# Stage-2 ReResNet adapted on simulated Boreas-like target data (never a query sequence): "Our (3)"; width 0.5 since
# session 16 (docs/MODEL.md, "Width 0.5, measured": the descriptor alone within 0.7 points of the pipeline)
DEFAULT_MODEL = "our-3-boreas-w05"


def available_models(weights_dir: Path = WEIGHTS_DIR) -> list[str]:
    """Names of the shipped models (a ``.pt`` with its ``.json``), sorted."""
    if not weights_dir.is_dir():
        return []
    return sorted(p.stem for p in weights_dir.glob("*.pt") if p.with_suffix(".json").is_file())


def resolve_weights(name: str = "default", weights_dir: Path = WEIGHTS_DIR) -> tuple[Path, dict[str, Any]]:
    """Registry name, "default", or a path to a ``.pt`` file -> (weights path, metadata dict)."""
    candidate = Path(name)
    if candidate.suffix == ".pt" and candidate.is_file():
        pt = candidate
    elif candidate.suffix == ".pt" or len(candidate.parts) > 1:  # a path, not a registry name
        why = ("is a folder, not a weights file" if candidate.is_dir() else
               "is not a weights file (.pt)" if candidate.is_file() else "no such weights file")
        raise ConfigError(f"{candidate}: {why} (a .pt written by `reradar train`)")
    else:
        names = available_models(weights_dir)
        if name == "default":
            if DEFAULT_MODEL in names:
                name = DEFAULT_MODEL
            elif names:
                logger.warning("default model %s is not shipped; using %s", DEFAULT_MODEL, names[0])
                name = names[0]
            else:
                raise ConfigError(f"no model weights in {weights_dir}; run `reradar train` first")
        if name not in names:
            raise ConfigError(f"unknown model {name!r}; available: {names or 'none'} (or give a .pt path)")
        pt = weights_dir / f"{name}.pt"
    jpath = pt.with_suffix(".json")
    if not jpath.is_file():
        raise ConfigError(f"model metadata {jpath} is missing next to {pt}")
    try:
        meta = json.loads(jpath.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(f"model metadata {jpath} is not valid JSON: {exc}") from exc
    return pt, meta


def _finite_or_none(value: Any) -> Any:
    """``value`` with every NaN or infinite float (nested in dicts, lists, tuples) replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def save_weights(net: DescriptorNet, path: str | Path, metadata: dict[str, Any],
                 train_state_dict: dict[str, torch.Tensor] | None = None, onnx: bool = True) -> Path:
    """Write ``net`` (a plain, exported ``DescriptorNet``) to ``path`` (.pt), its metadata to .json and, with
    ``onnx``, the network as an ONNX graph to .onnx (``export_weights_onnx``; skipped with a warning when the
    exporter's packages, the ``train`` extra, are missing: inference then runs in torch).

    ``train_state_dict`` (the e2cnn training network's state) is stored alongside so that a later training
    stage can start from these weights (``reradar train --init NAME``); inference ignores it.
    The metadata gains ``config``, ``model_id``, ``name`` and ``sha256`` (of the .pt file).
    """
    from reradar_core.model.extractor import file_sha256

    path = Path(path).with_suffix(".pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    blob: dict[str, Any] = {"state_dict": state}
    if train_state_dict is not None:
        blob["train_state_dict"] = {k: v.detach().cpu().contiguous() for k, v in train_state_dict.items()}
    torch.save(blob, path)
    meta = dict(metadata)
    meta.update(name=path.stem, config=net.config.to_dict(), model_id=net.config.model_id,
                sha256=file_sha256(path))
    # strict JSON: a NaN (e.g. a validation Recall@1 over no query) is written as null, not as a bare NaN
    path.with_suffix(".json").write_text(json.dumps(_finite_or_none(meta), indent=2, sort_keys=True,
                                                    allow_nan=False) + "\n")
    if onnx:
        try:
            export_weights_onnx(path, net=net)
        except ModuleNotFoundError as exc:
            logger.warning("no ONNX graph written for %s (%s is not installed): inference runs in torch",
                           path.name, exc.name)
    return path


def export_weights_onnx(path: str | Path, net: DescriptorNet | None = None) -> Path:
    """Write ``<name>.onnx`` beside the weights file ``path`` (``<name>.pt``): its network as an ONNX graph that
    records the file's sha256 (``reradar_core.model.runtime.export_onnx``). ``net``: the network already in memory
    (else loaded from ``path``). Any stale graph there is removed first. Returns the graph's path."""
    from reradar_core.model.extractor import DescriptorExtractor, file_sha256
    from reradar_core.model.runtime import export_onnx, onnx_path_for

    path = Path(path)
    graph = onnx_path_for(path)
    graph.unlink(missing_ok=True)
    if net is None:
        net = DescriptorExtractor.from_file(path, runtime="torch", fuse=False).net
    return export_onnx(net, graph, weights_sha256=file_sha256(path))
