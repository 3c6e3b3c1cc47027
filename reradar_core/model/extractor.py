"""``DescriptorExtractor``: one radar scan -> ``ScanFeatures`` (global descriptor + landmark local descriptors).

Pipeline (paper, Sec. "Method"): polar scan -> Cartesian image (``polar_to_cartesian``, the model's own
``CartesianConfig``) -> exported network -> global descriptor (NetVLAD + PCA-whitening, L2) and F'. The network
runs in ONNX Runtime when its exported graph lies beside the weights, in torch otherwise (``reradar_core.model.runtime``). Cen 2018
landmarks found on the polar scan are mapped to Cartesian pixels; those inside the image are kept (the
strongest ``max_keypoints``), F' is sampled bilinearly at each (F' cell k is centred on input pixel
``stride * k``, so pixel (r, c) is F' coordinate (r / stride, c / stride)), and the vectors are
L2-normalised and stored as float16.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from reradar_core.errors import ConfigError, ModelMismatchError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig, metric_to_pixel, polar_to_cartesian
from reradar_core.geometry.heading import canonical_turn, turn_scan
from reradar_core.geometry.se2 import transform_points
from reradar_core.io.scan import RadarScan, require_scan
from reradar_core.model.config import ModelConfig
from reradar_core.model.network import DescriptorNet, fuse_batchnorm
from reradar_core.model.runtime import OnnxNetwork, onnx_path_for, resolve_runtime

__all__ = ["DescriptorExtractor", "sample_feature_map", "DEFAULT_MAX_KEYPOINTS", "check_weights_sha256",
           "file_sha256", "read_weights_blob"]

logger = logging.getLogger(__name__)

DEFAULT_MAX_KEYPOINTS = 512  # strongest landmarks kept per scan: enough for RANSAC, keeps maps small


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_weights_sha256(path: str | Path, meta: dict[str, Any], sha256: str | None = None) -> str:
    """The weights file's sha256 (``sha256``: already computed), checked against the ``sha256`` its JSON records
    (``save_weights`` writes it); a ``ConfigError`` (one line) when they differ: the file was corrupted or
    replaced after it was written. Metadata without ``sha256`` is not checked."""
    path = Path(path)
    sha = sha256 or file_sha256(path)
    want = meta.get("sha256")
    if isinstance(want, str) and want and want.lower() != sha:
        raise ConfigError(f"model weights file {path.name} does not match its metadata (sha256 {sha[:12]}... where "
                          f"{path.with_suffix('.json').name} records {want[:12]}...): the file is corrupt or was "
                          "replaced; restore it or re-train the model")
    return sha


def read_weights_blob(path: str | Path, meta: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The ``.pt`` at ``path`` as torch saved it (``state_dict``, and ``train_state_dict`` where training wrote
    one) and its sha256, checked against ``meta``'s (``check_weights_sha256``).

    Raises:
        ConfigError: one line: the file differs from its metadata's hash, or is not a readable weights file.
    """
    path = Path(path)
    sha = check_weights_sha256(path, meta)  # once per load: a few ms per 10 MB
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(blob, dict) or not isinstance(blob.get("state_dict"), dict):
            raise ValueError("no state_dict")
    except Exception as exc:  # noqa: BLE001 - torch raises pickle, zip, EOF and runtime errors on a bad file
        detail = str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__
        if "weights only load failed" in detail.lower():
            # torch's text goes on to offer weights_only=False, i.e. running the file's pickled code: never advised
            detail = "it holds objects other than tensors and plain containers, which the safe loader refuses"
        raise ConfigError(f"model weights file {path.name} is not a readable ReRadar weights file (corrupt or "
                          f"truncated .pt: {detail}); re-export or re-train it") from None
    return blob, sha


def _mismatch_summary(exc: RuntimeError) -> str:
    """torch's ``load_state_dict`` error (one line per tensor, often over a hundred) as its first mismatch and a
    count."""
    lines = [ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()]
    if not lines:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    more = f" (and {len(lines) - 1} more)" if len(lines) > 1 else ""
    return f"{lines[0].rstrip('.')}{more}"


_logged_fallbacks: set[str] = set()


def _onnx_network(weights: Path, sha256: str, runtime: str) -> OnnxNetwork | None:
    """The ONNX Runtime network for ``weights`` under ``runtime`` ("auto" / "onnx" / "torch"), None for torch.

    "auto" falls back to torch when the graph is missing, stale or onnxruntime is not installed, and says why once
    per weights file (a stale graph is a warning: someone retrained without re-exporting)."""
    if runtime == "torch":
        return None
    graph = onnx_path_for(weights)
    try:
        if not graph.is_file():
            raise ConfigError(f"{weights.stem} has no exported graph {graph.name} beside its weights "
                              "(`reradar export-onnx` writes it)")
        return OnnxNetwork(graph, sha256)
    except ConfigError as exc:
        if runtime == "onnx":
            raise ConfigError(f"network runtime 'onnx' asked for, but {exc}") from exc
        if sha256 not in _logged_fallbacks:
            _logged_fallbacks.add(sha256)
            # a graph that is there but cannot run (stale, unreadable, no onnxruntime) is worth a warning
            (logger.warning if graph.is_file() else logger.info)("descriptor network runs in torch: %s", exc)
        return None


def _landmark_xy(points: Any) -> np.ndarray:
    """Landmarks as (N, 2) float64 sensor-frame x, y metres; ``ConfigError`` for another shape ((2, N) or (N, 3),
    which a reshape would interleave into other points) or non-finite values."""
    try:
        xy = np.asarray(points, np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"landmarks must be an (N, 2) array of sensor-frame x, y in metres: {exc}") from None
    if xy.size == 0:
        return xy.reshape(0, 2)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ConfigError(f"landmarks must be an (N, 2) array of sensor-frame x, y in metres, got shape {xy.shape}")
    if not np.isfinite(xy).all():
        raise ConfigError("landmarks hold NaN or infinite coordinates")
    return xy


def _turned_points(xy: np.ndarray, turn: float) -> np.ndarray:
    """(N, 2) sensor-frame points (metres) in the frame of the sensor yawed counter-clockwise by ``turn`` (rad):
    ``R(-turn) xy`` (``geometry.heading.turn_scan``'s image of them)."""
    if not turn:
        return xy
    return transform_points(np.array([0.0, 0.0, -turn]), xy)  # T_turned_sensor: the sensor turned back by -turn


def sample_feature_map(fmap: torch.Tensor | np.ndarray, rc_px: np.ndarray, stride: int) -> np.ndarray:
    """Bilinearly sample F' at input-image pixel positions.

    Args:
        fmap: (C, h, w) feature map; cell (k, l) is centred on input pixel (stride * k, stride * l).
        rc_px: (N, 2) float (row, col) input-image pixel coordinates.
        stride: input pixels per F' cell.

    Returns:
        (N, C) float32 (not normalised). Positions outside F' are clamped to its border.
    """
    f = torch.as_tensor(fmap, dtype=torch.float32)
    c, h, w = f.shape
    rc = np.asarray(rc_px, dtype=np.float64).reshape(-1, 2)
    if rc.shape[0] == 0:
        return np.zeros((0, c), np.float32)
    fr = np.clip(rc[:, 0] / stride, 0, h - 1)
    fc = np.clip(rc[:, 1] / stride, 0, w - 1)
    # grid_sample with align_corners=True: -1 / +1 are the centres of the first / last cells.
    gx = fc / max(w - 1, 1) * 2 - 1
    gy = fr / max(h - 1, 1) * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], axis=-1).astype(np.float32))[None, None]
    out = F.grid_sample(f[None], grid, mode="bilinear", align_corners=True)  # (1, C, 1, N)
    return out[0, :, 0].T.contiguous().numpy()


class DescriptorExtractor:
    """Inference wrapper around the exported descriptor network.

    Attributes:
        config: the architecture (``ModelConfig``).
        model_id: architecture id, e.g. "reresnet-c8-w0.5-k32-d256-in201" (``ModelConfig.model_id``; ``-ch`` with the canonical heading).
        weights_sha256: sha256 of the weights file ("" for untrained/in-memory weights); maps store it and
            refuse a mismatched model.
        name: registry name ("our-3-boreas", ...) or "" when built from a network.
        cartesian: input image geometry.
        descriptor_dim: D of the global descriptor.
        max_keypoints: cap on landmarks per scan (strongest kept; None = all).

        runtime: "onnx" when the network runs in ONNX Runtime (``onnx_network``), else "torch".

    ``fuse`` folds BatchNorm into the convolutions (same function, faster); the given ``net`` is not changed.
    ``onnx_network`` (an ``OnnxNetwork`` of the same weights; ``from_file`` finds it) runs the network instead of torch.
    """

    def __init__(self, net: DescriptorNet, *, weights_sha256: str = "", name: str = "",
                 metadata: dict[str, Any] | None = None, max_keypoints: int | None = DEFAULT_MAX_KEYPOINTS,
                 landmark_config: Any = None, fuse: bool = True, onnx_network: OnnxNetwork | None = None) -> None:
        self.net = fuse_batchnorm(net) if fuse else net.eval()
        self.onnx_network = onnx_network
        self.config: ModelConfig = net.config
        self.weights_sha256 = weights_sha256
        self.name = name
        self.metadata = dict(metadata or {})
        self.max_keypoints = max_keypoints
        self.landmark_config = landmark_config
        for p in self.net.parameters():
            p.requires_grad_(False)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_pretrained(cls, name: str = "default", **kwargs: Any) -> DescriptorExtractor:
        """Load shipped weights by registry name (``available_models()``) or a path to a ``.pt`` file."""
        from reradar_core.model.registry import resolve_weights

        pt, meta = resolve_weights(name)
        return cls.from_file(pt, meta=meta, **kwargs)

    @classmethod
    def from_file(cls, path: str | Path, meta: dict[str, Any] | None = None, *, runtime: str | None = None,
                  **kwargs: Any) -> DescriptorExtractor:
        """Load a weights file written by ``save_weights`` (JSON metadata next to it, same stem).

        ``runtime``: "auto" (ONNX Runtime when ``<name>.onnx`` of these weights is beside the file and onnxruntime
        is installed, torch otherwise), "onnx" (ONNX Runtime or a ``ConfigError``) or "torch"; None reads
        ``$RERADAR_NETWORK_RUNTIME`` (default "auto"). See ``reradar_core.model.runtime``.
        """
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"model weights file {path} does not exist; run `reradar train` or pick one of "
                              "reradar_core.model.available_models()")
        if meta is None:
            jpath = path.with_suffix(".json")
            if not jpath.is_file():
                raise ConfigError(f"model metadata {jpath} is missing next to {path}")
            try:
                meta = json.loads(jpath.read_text())
            except (OSError, ValueError) as exc:
                raise ConfigError(f"model metadata {jpath.name} is not readable JSON ({exc})") from None
        try:
            config = ModelConfig.from_dict(meta["config"])
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"model metadata for {path} has no valid 'config': {exc}") from exc
        net = DescriptorNet(config)
        blob, sha = read_weights_blob(path, meta)
        state = {k: v.float() if v.is_floating_point() else v for k, v in blob["state_dict"].items()}
        try:
            net.load_state_dict(state)
        except RuntimeError as exc:
            raise ModelMismatchError(f"weights {path} do not fit model {config.model_id} (another architecture "
                                     f"than its JSON describes?): {_mismatch_summary(exc)}") from None
        return cls(net, weights_sha256=sha, name=meta.get("name", path.stem), metadata=meta,
                   onnx_network=_onnx_network(path, sha, resolve_runtime(runtime)), **kwargs)

    def with_view(self, cartesian: CartesianConfig) -> DescriptorExtractor:
        """The same weights on another Cartesian view (``CartesianConfig``: width px, metres per px).

        The network is fully convolutional up to F' and NetVLAD aggregates any number of cells, so the weights
        apply to another image size or scale without retraining (the far view of ``localization.far_view``:
        257 px at 1.28 m reach the radar's 165 m). Runs in ONNX Runtime when this extractor does and its graph
        takes any image size (``OnnxNetwork.free_size``: exported since session 34), in torch otherwise (an older
        graph fixed at the trained size). The copy shares the weights (read-only) and keeps its own disc-mask
        cache; ``model_id`` names the view (``...-in257``), so a map built with one view refuses queries of another.
        """
        import copy

        net = copy.copy(self.net)  # shallow: shares the modules (weights), owns its attributes
        net.config = replace(self.config, cartesian_width_px=int(cartesian.width_px),
                             cartesian_resolution_m=float(cartesian.resolution_m))
        net.__dict__["_disc_cache"] = {}
        out = copy.copy(self)
        onnx = self.onnx_network if getattr(self.onnx_network, "free_size", False) else None
        out.net, out.config, out.onnx_network = net, net.config, onnx
        return out

    # ---------------------------------------------------------------- properties
    @property
    def model_id(self) -> str:
        return self.config.model_id

    @property
    def cartesian(self) -> CartesianConfig:
        return self.config.cartesian

    @property
    def descriptor_dim(self) -> int:
        return self.config.descriptor_dim

    @property
    def local_dim(self) -> int:
        return self.config.feature_dim

    @property
    def runtime(self) -> str:
        """Where the network runs: "onnx" (ONNX Runtime) or "torch"."""
        return "onnx" if self.onnx_network is not None else "torch"

    # ---------------------------------------------------------------- inference
    @torch.inference_mode()
    def run_images(self, images: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """(B, W, W) Cartesian images -> ((B, D) float32 descriptors, (B, C, h, h) float32 F').

        ``images``: float, values in [0, 1] (``polar_to_cartesian``'s output), square; W is
        ``cartesian.width_px`` for this extractor's view (the network itself takes any side: the far view's 257 px);
        one (W, W) image is a batch of one. Raises ``ConfigError`` for images that are not square (e.g. a polar
        scan) or 8-bit values (0..255), which the network would describe without a word (cosine ~0.1 to the right
        descriptor).
        """
        if isinstance(images, torch.Tensor):
            images = images.detach().cpu().numpy()
        arr = np.asarray(images, dtype=np.float32)
        if arr.ndim == 2:
            arr = arr[None]
        if arr.ndim != 3 or arr.shape[1] != arr.shape[2]:
            w = self.cartesian.width_px
            raise ConfigError(f"images must be square Cartesian images, (B, {w}, {w}) or ({w}, {w}) "
                              f"(polar_to_cartesian(scan, extractor.cartesian)), got shape {np.shape(images)}")
        if arr.size:
            lo, hi = float(arr.min()), float(arr.max())
            if not (np.isfinite(lo) and np.isfinite(hi)) or lo < -1e-4 or hi > 1.0 + 1e-4:
                raise ConfigError(f"image values must be finite and in [0, 1] (polar_to_cartesian's scale), got "
                                  f"[{lo:.4g}, {hi:.4g}]" + (": 8-bit values? divide by 255" if hi > 1.5 else ""))
        if self.onnx_network is not None:
            return self.onnx_network(arr[:, None])
        g, f = self.net(torch.as_tensor(arr)[:, None])
        return g.numpy(), f.numpy()

    def heading_turn(self, scan: RadarScan) -> float:
        """The counter-clockwise turn (radians) of the sensor at which the network sees the scan: the scan's
        canonical heading (``geometry.heading.canonical_turn`` over the image's half width) when
        ``config.canonical_heading``, else 0."""
        if not self.config.canonical_heading:
            return 0.0
        cart = self.cartesian
        return canonical_turn(scan, cart.centre_px * cart.resolution_m)

    def cartesian_image(self, scan: RadarScan) -> np.ndarray:
        """(W, W) float32 network input: the scan's Cartesian image, seen at ``heading_turn(scan)``."""
        return polar_to_cartesian(turn_scan(scan, self.heading_turn(scan)), self.cartesian)

    @property
    def landmark_range_m(self) -> float:
        """Range (metres) beyond which no landmark is inside the Cartesian image (its corners, plus a pixel
        and a metre of margin): the keypoints use only the landmarks within it, so the detector need not look
        further (``detect_landmarks(..., max_range_m=...)`` returns exactly those)."""
        cart = self.cartesian
        return (cart.centre_px + 1.0) * cart.resolution_m * math.sqrt(2.0) + 1.0

    def _keypoints(self, scan: RadarScan, landmarks: Any, turn: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame keypoints (N, 2) inside the image seen at ``turn`` (rad) and their strengths (N,)."""
        if landmarks is None:
            from reradar_core.landmarks import detect_landmarks

            landmarks = detect_landmarks(scan, self.landmark_config, max_range_m=self.landmark_range_m)
        if hasattr(landmarks, "xy_m"):
            xy = _landmark_xy(landmarks.xy_m)
            strength = np.asarray(getattr(landmarks, "strength", np.ones(len(xy))), np.float64).reshape(-1)
            if len(strength) != len(xy):
                raise ConfigError(f"landmarks: {len(strength)} strengths for {len(xy)} points")
        else:
            xy = _landmark_xy(landmarks)
            strength = np.ones(len(xy))
        rc = metric_to_pixel(_turned_points(xy, turn), self.cartesian)
        w = self.cartesian.width_px
        inside = np.all((rc >= 0) & (rc <= w - 1), axis=1)
        xy, strength = xy[inside], strength[inside]
        if self.max_keypoints is not None and len(xy) > self.max_keypoints:
            keep = np.sort(np.argsort(-strength, kind="stable")[: self.max_keypoints])
            xy, strength = xy[keep], strength[keep]
        return xy, strength

    def _features(self, scan: RadarScan, g: np.ndarray, fmap: np.ndarray, landmarks: Any) -> ScanFeatures:
        turn = self.heading_turn(scan)
        xy, _ = self._keypoints(scan, landmarks, turn)
        local = sample_feature_map(fmap, metric_to_pixel(_turned_points(xy, turn), self.cartesian),
                                   self.config.stride)
        local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
        return ScanFeatures(global_descriptor=g, keypoints_xy_m=xy.astype(np.float32),
                            local_descriptors=local.astype(np.float16), timestamp_us=int(scan.timestamp_us))

    def features_from_outputs(self, scan: RadarScan, global_descriptor: np.ndarray, feature_map: np.ndarray,
                              landmarks: Any = None) -> ScanFeatures:
        """``ScanFeatures`` from one scan's network outputs (``run_images``: (D,) descriptor, (C, h, h) F')
        and its landmarks (detected when None): keypoints and local descriptors sampled from F'. Lets callers
        time the network and the landmark stage separately (``benchmark.timing``)."""
        return self._features(scan, global_descriptor, feature_map, landmarks)

    def describe(self, scan: RadarScan, landmarks: Any = None) -> ScanFeatures:
        """One scan -> ``ScanFeatures`` (landmarks detected with Cen 2018 unless given as ``Landmarks`` or
        an (N, 2) array of sensor-frame metres)."""
        require_scan(scan, "describe")
        g, f = self.run_images(self.cartesian_image(scan)[None])
        return self._features(scan, g[0], f[0], landmarks)

    def describe_batch(self, scans: Sequence[RadarScan], landmarks: Sequence[Any] | None = None,
                       batch_size: int = 16) -> list[ScanFeatures]:
        """Many scans, network batched ``batch_size`` at a time (map building)."""
        for scan in scans:
            require_scan(scan, "describe_batch")
        out: list[ScanFeatures] = []
        for start in range(0, len(scans), batch_size):
            chunk = scans[start:start + batch_size]
            imgs = np.stack([self.cartesian_image(s) for s in chunk])
            g, f = self.run_images(imgs)
            for i, s in enumerate(chunk):
                lm = None if landmarks is None else landmarks[start + i]
                out.append(self._features(s, g[i], f[i], lm))
        return out

    def global_descriptors(self, scans: Sequence[RadarScan], batch_size: int = 16) -> np.ndarray:
        """(N, D) global descriptors only (no landmarks) — for retrieval benchmarks."""
        for scan in scans:
            require_scan(scan, "DescriptorExtractor.global_descriptors")
        out = []
        for start in range(0, len(scans), batch_size):
            imgs = np.stack([self.cartesian_image(s) for s in scans[start:start + batch_size]])
            out.append(self.run_images(imgs)[0])
        return np.concatenate(out) if out else np.zeros((0, self.descriptor_dim), np.float32)
