"""The network runtime: the exported ONNX graph gives torch's outputs, a stale graph is never run, the switch works."""

from __future__ import annotations

import logging
import pickle

import numpy as np
import pytest
import torch

from reradar_core.errors import ConfigError
from reradar_core.model import DescriptorExtractor, DescriptorNet, ModelConfig, available_models, save_weights
from reradar_core.model.extractor import file_sha256
from reradar_core.model.registry import WEIGHTS_DIR, export_weights_onnx
from reradar_core.model.runtime import RUNTIME_ENV, WEIGHTS_SHA_PROPERTY, onnx_path_for, resolve_runtime

ort = pytest.importorskip("onnxruntime")

# the plain ResNet layout with group pooling switched off: a small network whose export needs no e2cnn
TINY = ModelConfig(backbone="resnet", width=0.25, num_clusters=4, output_dim=16)


def _net(seed: int) -> DescriptorNet:
    torch.manual_seed(seed)
    net = DescriptorNet(TINY).eval()
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():  # non-trivial BatchNorm statistics, so folding them must be right
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.randn(m.running_mean.shape, generator=g) * 0.1)
            m.running_var.copy_(torch.rand(m.running_var.shape, generator=g) + 0.5)
    return net


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny network saved with its ONNX graph: (weights path, the network)."""
    net = _net(0)
    path = save_weights(net, tmp_path_factory.mktemp("w") / "tiny.pt", {"note": "test"})
    return path, net


def _images(n: int, seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 201, 201), dtype=np.float32)


def test_save_weights_writes_a_graph_that_records_the_weights(saved):
    path, _ = saved
    graph = onnx_path_for(path)
    assert graph.is_file()
    meta = ort.InferenceSession(str(graph), providers=["CPUExecutionProvider"]).get_modelmeta()
    assert meta.custom_metadata_map[WEIGHTS_SHA_PROPERTY] == file_sha256(path)


@pytest.mark.parametrize("batch", [1, 3])
def test_onnx_runtime_gives_torch_outputs_at_any_batch_size(saved, batch):
    path, _ = saved
    fast = DescriptorExtractor.from_file(path, runtime="onnx")
    ref = DescriptorExtractor.from_file(path, runtime="torch")
    assert (fast.runtime, ref.runtime) == ("onnx", "torch")
    x = _images(batch)
    g, f = fast.run_images(x)
    g0, f0 = ref.run_images(x)
    assert g.shape == g0.shape == (batch, 16) and f.shape == f0.shape
    np.testing.assert_allclose(g, g0, atol=1e-5)
    np.testing.assert_allclose(f, f0, atol=1e-5 * float(np.abs(f0).max()))
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-5)


def test_auto_is_the_default_and_the_environment_switches_it(saved, monkeypatch):
    path, _ = saved
    monkeypatch.delenv(RUNTIME_ENV, raising=False)
    assert resolve_runtime(None) == "auto"
    assert DescriptorExtractor.from_file(path).runtime == "onnx"
    monkeypatch.setenv(RUNTIME_ENV, "torch")
    assert DescriptorExtractor.from_file(path).runtime == "torch"
    monkeypatch.setenv(RUNTIME_ENV, "tensorrt")
    with pytest.raises(ConfigError, match="RERADAR_NETWORK_RUNTIME='tensorrt'.*auto, onnx, torch"):
        DescriptorExtractor.from_file(path)


def test_a_stale_graph_is_never_run(tmp_path, caplog):
    """Weights retrained in place but the old graph left beside them: auto falls back to torch and warns, onnx
    refuses, and the answers are the new weights' answers."""
    path = save_weights(_net(0), tmp_path / "m.pt", {})
    old_graph = onnx_path_for(path).read_bytes()
    save_weights(_net(1), path, {}, onnx=False)
    onnx_path_for(path).write_bytes(old_graph)
    with caplog.at_level(logging.WARNING, logger="reradar_core.model.extractor"):
        ex = DescriptorExtractor.from_file(path)
    assert ex.runtime == "torch"
    assert "exported from other weights" in caplog.text and "reradar export-onnx" in caplog.text
    with pytest.raises(ConfigError, match="runtime 'onnx' asked for, but .*other weights"):
        DescriptorExtractor.from_file(path, runtime="onnx")
    x = _images(1)
    with torch.no_grad():
        g_new, _ = _net(1)(torch.from_numpy(x)[:, None])
    np.testing.assert_allclose(ex.run_images(x)[0], g_new.numpy(), atol=1e-5)
    # re-exporting makes it fast again
    export_weights_onnx(path)
    assert DescriptorExtractor.from_file(path).runtime == "onnx"


def test_missing_graph_means_torch_unless_onnx_is_required(tmp_path):
    path = save_weights(_net(2), tmp_path / "n.pt", {}, onnx=False)
    assert not onnx_path_for(path).exists()
    assert DescriptorExtractor.from_file(path).runtime == "torch"
    with pytest.raises(ConfigError, match="no exported graph n.onnx.*reradar export-onnx"):
        DescriptorExtractor.from_file(path, runtime="onnx")


def test_an_unreadable_graph_is_a_clear_error_not_a_crash(tmp_path):
    path = save_weights(_net(2), tmp_path / "u.pt", {}, onnx=False)
    onnx_path_for(path).write_bytes(b"not a graph")
    assert DescriptorExtractor.from_file(path).runtime == "torch"
    with pytest.raises(ConfigError, match="u.onnx is not a readable ONNX graph"):
        DescriptorExtractor.from_file(path, runtime="onnx")


def test_onnx_extractor_survives_pickling_and_a_thread_change(saved):
    path, _ = saved
    ex = DescriptorExtractor.from_file(path, runtime="onnx")
    x = _images(2)
    g, _ = ex.run_images(x)
    copy = pickle.loads(pickle.dumps(ex))
    assert copy.runtime == "onnx"
    np.testing.assert_array_equal(copy.run_images(x)[0], g)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        np.testing.assert_allclose(ex.run_images(x)[0], g, atol=1e-6)
    finally:
        torch.set_num_threads(before)


def test_every_shipped_model_has_its_current_graph():
    """A retrained shipped model must come with its re-exported graph (``reradar train`` writes both;
    ``reradar export-onnx NAME`` re-writes one), or the service silently runs at half speed."""
    names = available_models()
    assert names
    for name in names:
        pt = WEIGHTS_DIR / f"{name}.pt"
        graph = onnx_path_for(pt)
        assert graph.is_file(), f"{name}: no {graph.name}; run `reradar export-onnx {name}`"
        meta = ort.InferenceSession(str(graph), providers=["CPUExecutionProvider"]).get_modelmeta()
        assert meta.custom_metadata_map.get(WEIGHTS_SHA_PROPERTY) == file_sha256(pt), \
            f"{name}: {graph.name} is stale; run `reradar export-onnx {name}`"


def test_shipped_default_model_runs_in_onnx_runtime_with_torch_outputs():
    fast = DescriptorExtractor.from_pretrained()
    ref = DescriptorExtractor.from_pretrained(runtime="torch")
    assert fast.runtime == "onnx"
    x = _images(2, seed=5)
    g, f = fast.run_images(x)
    g0, f0 = ref.run_images(x)
    np.testing.assert_allclose(g, g0, atol=1e-5)
    np.testing.assert_allclose(f, f0, atol=1e-5 * float(np.abs(f0).max()))


def test_graph_takes_any_image_size_with_torch_outputs(saved):
    """Since session 34 the graph's image size is free: the far view's 257 px (and any other size) runs in ONNX
    Runtime with torch's outputs, the sensor-disc masks computed from the image it is given."""
    path, _ = saved
    fast = DescriptorExtractor.from_file(path, runtime="onnx")
    ref = DescriptorExtractor.from_file(path, runtime="torch")
    assert fast.onnx_network is not None and fast.onnx_network.free_size
    for size in (257, 121):
        x = np.random.default_rng(size).random((2, size, size), dtype=np.float32)
        g, f = fast.run_images(x)
        g0, f0 = ref.run_images(x)
        assert f.shape == f0.shape and f.shape[-1] == f0.shape[-1] > 0
        np.testing.assert_allclose(g, g0, atol=1e-5)
        np.testing.assert_allclose(f, f0, atol=1e-5 * float(np.abs(f0).max()))


def test_the_graph_refuses_image_sizes_it_was_not_exported_for(saved, monkeypatch):
    """Session 34's review: the graph ran at image sides outside the 33-1025 px it was exported for (whose outputs
    were never checked against torch's) without a word. Outside that range it is a ValueError saying what to do; the
    range's ends run, with torch's outputs."""
    path, _ = saved
    fast = DescriptorExtractor.from_file(path, runtime="onnx")
    ref = DescriptorExtractor.from_file(path, runtime="torch")
    assert fast.onnx_network is not None and fast.onnx_network.image_px == (33, 1025)
    for side in (32, 1026):
        with pytest.raises(ValueError, match=rf"33-1025 px a side .*got {side} px.*{RUNTIME_ENV}=torch"):
            fast.run_images(np.zeros((1, side, side), np.float32))
    x = np.random.default_rng(33).random((1, 33, 33), dtype=np.float32)
    g, f = fast.run_images(x)
    g0, f0 = ref.run_images(x)
    np.testing.assert_allclose(g, g0, atol=1e-5)
    np.testing.assert_allclose(f, f0, atol=1e-5 * float(np.abs(f0).max()))
    with pytest.raises(ValueError, match=r"takes \(batch, 1, W, W\) images, got shape \(1, 1, 40, 41\)"):
        fast.onnx_network(np.zeros((1, 1, 40, 41), np.float32))
    # a graph exported before session 34 takes its trained size only
    monkeypatch.setattr(fast.onnx_network, "image_px", (201, 201))
    with pytest.raises(ValueError, match="201 px a side .*got 257 px"):
        fast.run_images(np.zeros((1, 257, 257), np.float32))


def test_export_is_byte_identical_on_a_rerun(saved, tmp_path):
    """The same weights export to the same bytes (the exporter's debug records, which name objects by memory
    address, are dropped), so a re-export of unchanged weights changes no shipped file."""
    path, _ = saved
    a = tmp_path / "a.pt"
    a.write_bytes(path.read_bytes())
    a.with_suffix(".json").write_bytes(path.with_suffix(".json").read_bytes())
    assert export_weights_onnx(a).read_bytes() == onnx_path_for(path).read_bytes()  # the fixture's export


def test_far_view_of_the_default_model_runs_in_onnx_runtime_with_torch_outputs():
    from reradar_core.geometry.cartesian import CartesianConfig

    far = CartesianConfig(257, 1.28)
    fast = DescriptorExtractor.from_pretrained().with_view(far)
    ref = DescriptorExtractor.from_pretrained(runtime="torch").with_view(far)
    assert (fast.runtime, ref.runtime) == ("onnx", "torch")
    assert fast.model_id == ref.model_id and fast.model_id.endswith("-in257")
    x = np.random.default_rng(7).random((2, 257, 257), dtype=np.float32)
    g, f = fast.run_images(x)
    g0, f0 = ref.run_images(x)
    np.testing.assert_allclose(g, g0, atol=1e-5)
    np.testing.assert_allclose(f, f0, atol=1e-5 * float(np.abs(f0).max()))


def test_a_fixed_size_graph_leaves_the_other_view_to_torch(saved, monkeypatch):
    """A graph exported before session 34 fixes the trained size: ``with_view`` then runs the view in torch."""
    from reradar_core.geometry.cartesian import CartesianConfig

    path, _ = saved
    ex = DescriptorExtractor.from_file(path, runtime="onnx")
    monkeypatch.setattr(ex.onnx_network, "free_size", False)
    assert ex.with_view(CartesianConfig(257, 1.28)).runtime == "torch"
    assert ex.runtime == "onnx"
