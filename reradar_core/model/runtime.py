"""Where the descriptor network runs: ONNX Runtime when an exported graph lies beside the weights, torch otherwise.

The shipped weights are a torch state dict (``<name>.pt``, written by ``reradar train``). Beside it,
``<name>.onnx`` holds the same fused network (``fuse_batchnorm``) as an ONNX graph with a free batch axis, written
by ``export_onnx`` (``reradar train`` writes it with the weights; ``reradar export-onnx`` writes it for existing
weights). ONNX Runtime runs it about 2x faster than torch on CPU at one thread (docs/BENCHMARKS.md, "Session 18"),
with the same outputs to float rounding (descriptor within ~2e-7, F' within ~5e-7 relative of torch's).

The graph records the sha256 of the ``.pt`` it was exported from (model property ``reradar.weights_sha256``);
``OnnxNetwork`` refuses a graph whose record differs from the weights being loaded, so a stale ``.onnx`` left beside
retrained weights is never run. Which runtime a ``DescriptorExtractor`` uses (``resolve_runtime``):

- ``auto`` (default; ``RERADAR_NETWORK_RUNTIME`` unset): ONNX Runtime when the graph is there, matches and
  ``onnxruntime`` is installed (the ``server`` extra), torch otherwise (logged once, saying why);
- ``onnx``: ONNX Runtime or a ``ConfigError`` saying what is missing;
- ``torch``: always torch (e.g. to compare the two).

Threads: a session uses as many intra-op threads as torch is set to (``torch.get_num_threads()`` when it first runs
at that setting), so the service's ``RERADAR_TORCH_THREADS`` and ``reradar bench --threads`` govern both runtimes.
Exporting needs ``onnx`` and ``onnxscript`` (the ``train`` extra); running needs only ``onnxruntime``.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import os
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from reradar_core.errors import ConfigError

__all__ = ["ONNX_SUFFIX", "RUNTIMES", "RUNTIME_ENV", "WEIGHTS_SHA_PROPERTY", "OnnxNetwork", "export_onnx",
           "onnx_path_for", "resolve_runtime"]

logger = logging.getLogger(__name__)

ONNX_SUFFIX = ".onnx"
RUNTIME_ENV = "RERADAR_NETWORK_RUNTIME"
RUNTIMES = ("auto", "onnx", "torch")
#: ONNX model property: sha256 of the ``.pt`` weights file the graph was exported from
WEIGHTS_SHA_PROPERTY = "reradar.weights_sha256"
MODEL_ID_PROPERTY = "reradar.model_id"
_INPUT, _OUTPUTS = "image", ("descriptor", "feature_map")
#: largest relative difference between the exported graph's outputs and torch's that ``export_onnx`` accepts
#: (measured: 2e-7 descriptor, 5e-7 F'; a wrong graph is off by O(1))
EXPORT_TOLERANCE = 1e-4
#: image sizes an exported graph accepts (px); the check's second size: the far view's (``FarViewConfig``)
MIN_IMAGE_PX, MAX_IMAGE_PX, CHECK_OTHER_PX = 33, 1025, 257


def onnx_path_for(weights_path: str | Path) -> Path:
    """``<name>.onnx`` beside ``<name>.pt``."""
    return Path(weights_path).with_suffix(ONNX_SUFFIX)


def resolve_runtime(runtime: str | None) -> str:
    """The runtime asked for: ``runtime`` if given, else ``$RERADAR_NETWORK_RUNTIME``, else "auto"."""
    value = (runtime if runtime is not None else os.environ.get(RUNTIME_ENV, "auto")).strip().lower() or "auto"
    if value not in RUNTIMES:
        source = "runtime" if runtime is not None else RUNTIME_ENV
        raise ConfigError(f"{source}={value!r} is not a network runtime; use one of {', '.join(RUNTIMES)}")
    return value


def export_onnx(net: Any, path: str | Path, *, weights_sha256: str) -> Path:
    """Write ``net`` (a plain ``DescriptorNet``) as an ONNX graph (opset 20, free batch axis and image size) to
    ``path``.

    Input ``image``: (B, 1, W, W) float32 Cartesian images of any odd or even size W in [``MIN_IMAGE_PX``,
    ``MAX_IMAGE_PX``] (the trained view's 201 px, the far view's 257 px: ``OnnxNetwork.free_size``); outputs
    ``descriptor`` (B, D) float32 and ``feature_map`` (B, C, h, h) float32, as ``DescriptorNet.forward`` (the
    sensor-disc masks are computed in the graph from W). BatchNorm is folded first, as the extractor runs it. The
    graph is checked against torch on random batches at the trained size and at ``CHECK_OTHER_PX`` before it is
    written (atomically: a temporary file renamed into place). Deterministic: the same weights and package versions
    give the same bytes.
    """
    import onnx
    import torch

    from reradar_core.model.network import fuse_batchnorm

    path = Path(path)
    fused = fuse_batchnorm(net)  # a copy of ``net``, BatchNorm folded
    w = fused.config.cartesian_width_px
    batch = torch.export.Dim("batch", min=1, max=4096)
    side = torch.export.Dim("side", min=MIN_IMAGE_PX, max=MAX_IMAGE_PX)
    with warnings.catch_warnings(), _quiet_loggers("onnx_ir", "onnxscript", "torch.onnx", "torch.export"):
        warnings.simplefilter("ignore")  # the exporter's notices about torch internals and its graph passes
        # a copy again, so that tracing leaves nothing behind on ``fused``, which still has to run the check below
        program = torch.onnx.export(copy.deepcopy(fused), (torch.zeros(2, 1, w, w),), dynamo=True,
                                    dynamic_shapes=({0: batch, 2: side, 3: side},), input_names=[_INPUT],
                                    output_names=list(_OUTPUTS), optimize=True, verbose=False)
    if program is None:  # only when exporting to a file path, which this does not
        raise RuntimeError("torch.onnx.export returned no program")
    model = program.model_proto
    _strip_node_metadata(model)
    onnx.helper.set_model_props(model, {WEIGHTS_SHA_PROPERTY: weights_sha256,
                                        MODEL_ID_PROPERTY: fused.config.model_id})
    data = model.SerializeToString()
    session = _session(data, 1)
    for size in (w, CHECK_OTHER_PX):
        images = torch.rand(3, 1, size, size, generator=torch.Generator().manual_seed(0))
        with torch.inference_mode():
            expected = [t.numpy() for t in fused(images)]
        got = session.run(None, {_INPUT: images.numpy()})
        for name, a, b in zip(_OUTPUTS, got, expected, strict=True):
            err = float(np.abs(a - b).max() / max(float(np.abs(b).max()), 1e-12))
            if a.shape != b.shape or not err <= EXPORT_TOLERANCE:
                raise RuntimeError(f"exported ONNX graph differs from the torch network on {name} at {size} px: "
                                   f"shape {a.shape} vs {b.shape}, relative difference {err:.2e}")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


def _strip_node_metadata(model: Any) -> None:
    """Drop the exporter's per-node debug records (source locations, FX node names) from ``model`` in place.

    With a free image size they name Python objects by memory address (``<function sym_min at 0x...>``), so two
    exports of the same weights would differ in bytes; the graph's computation does not read them."""
    graphs = [model.graph] + [f for f in model.functions]
    while graphs:
        g = graphs.pop()
        for node in g.node:
            del node.metadata_props[:]
            for a in node.attribute:  # subgraphs (If / Loop bodies)
                if a.HasField("g"):
                    graphs.append(a.g)
                graphs.extend(a.graphs)
    for vi in list(model.graph.value_info) + list(model.graph.input) + list(model.graph.output):
        del vi.metadata_props[:]


@contextlib.contextmanager
def _quiet_loggers(*names: str) -> Iterator[None]:
    """Raise the named loggers to ERROR for the block (the exporter logs every graph pass at INFO)."""
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(max(lg.getEffectiveLevel(), logging.ERROR))
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def _session(model: str | bytes, threads: int) -> Any:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, int(threads))
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.log_severity_level = 3  # errors only
    # no busy-waiting pool threads on a shared machine (they would spin between requests)
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])


class OnnxNetwork:
    """The exported network run by ONNX Runtime: (B, 1, W, W) float32 -> ((B, D) descriptors, (B, C, h, h) F').

    ``free_size``: the graph takes any image size W (exported since session 34), so a view of another size
    (``DescriptorExtractor.with_view``) runs it too; False for an older graph fixed at the trained size.

    Raises ``ConfigError`` when onnxruntime is missing, the file is not a readable graph, or it was exported from
    other weights than ``weights_sha256``. Thread-safe (ONNX Runtime sessions are); picklable (sessions are
    re-created after unpickling).
    """

    def __init__(self, path: str | Path, weights_sha256: str) -> None:
        self.path = Path(path)
        self.weights_sha256 = weights_sha256
        self._lock = threading.Lock()
        self._sessions: dict[int, Any] = {}
        try:
            import onnxruntime  # noqa: F401
        except ModuleNotFoundError as exc:
            raise ConfigError("onnxruntime is not installed (pip install 'reradar[server]')") from exc
        threads = self._threads()
        try:
            session = _session(str(self.path), threads)
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable graphs
            raise ConfigError(f"{self.path.name} is not a readable ONNX graph: {exc}") from exc
        props = session.get_modelmeta().custom_metadata_map
        recorded = props.get(WEIGHTS_SHA_PROPERTY, "")
        if recorded != weights_sha256:
            raise ConfigError(f"{self.path.name} was exported from other weights (sha256 {recorded[:12] or 'none'}…, "
                              f"the weights are {weights_sha256[:12]}…); re-export it with `reradar export-onnx`")
        self.model_id = props.get(MODEL_ID_PROPERTY, "")
        # graphs exported before session 34 fix the trained image size (dims 2, 3 are numbers, not names)
        shape = session.get_inputs()[0].shape
        self.free_size = len(shape) == 4 and not isinstance(shape[2], int) and not isinstance(shape[3], int)
        #: the image sides (px, smallest and largest) the graph was exported for: ``MIN_IMAGE_PX`` to
        #: ``MAX_IMAGE_PX`` for a graph with a free size, the trained size for an older one
        self.image_px = (MIN_IMAGE_PX, MAX_IMAGE_PX)
        if not self.free_size and len(shape) == 4 and isinstance(shape[3], int):
            self.image_px = (int(shape[3]), int(shape[3]))
        self._sessions[threads] = session

    @staticmethod
    def _threads() -> int:
        import torch

        return max(1, torch.get_num_threads())

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, 1, W, W) float32 images -> ((B, D) descriptors, (B, C, h, h) F').

        Raises:
            ValueError: the images are not (B, 1, W, W) with W within ``image_px``: the graph was exported for those
                sides only, and its outputs at others were never checked against torch's.
        """
        shape = np.shape(images)
        low, high = self.image_px
        if len(shape) != 4 or shape[1] != 1 or shape[2] != shape[3]:
            raise ValueError(f"{self.path.name} takes (batch, 1, W, W) images, got shape {tuple(shape)}")
        if not low <= shape[3] <= high:
            sides = f"{low} px" if low == high else f"{low}-{high} px"
            raise ValueError(f"{self.path.name} takes images of {sides} a side (the sizes it was exported for), got "
                             f"{shape[3]} px; use a Cartesian view within that, or run the network in torch "
                             f"({RUNTIME_ENV}=torch)")
        threads = self._threads()
        session = self._sessions.get(threads)
        if session is None:
            with self._lock:
                session = self._sessions.get(threads) or _session(str(self.path), threads)
                self._sessions[threads] = session
        x = np.ascontiguousarray(images, dtype=np.float32)
        g, f = session.run(None, {_INPUT: x})
        return g, f

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_sessions"] = {}
        del state["_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
