"""Training: InfoNCE known answers, sampler radii, augmentation geometry, checkpoint/resume determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reradar_core.model import ModelConfig
from reradar_core.training.data import CachedSequence, TrainingSet, TupleSampler, crop_view
from reradar_core.training.loss import info_nce, info_nce_in_batch
from reradar_core.training.trainer import TrainConfig, Trainer, recall_at_1_from_descriptors


def test_info_nce_known_answer():
    q = torch.tensor([[1.0, 0.0]])
    p = torch.tensor([[0.8, 0.6]])
    n = torch.tensor([[[0.6, 0.8], [0.0, 1.0]]])
    # cosines (0.8, 0.6, 0) / 0.1 -> logits (8, 6, 0) -> loss = log(1 + e^-2 + e^-8)
    expected = math.log(1 + math.exp(-2) + math.exp(-8))
    assert float(info_nce(q, p, n, tau=0.1)) == pytest.approx(expected, rel=1e-5)
    # a negative identical to the query and an orthogonal positive: loss = log(1 + e^10)
    assert float(info_nce(q, torch.tensor([[0.0, 1.0]]), q[:, None], tau=0.1)) == pytest.approx(
        math.log(1 + math.exp(10)), rel=1e-5)


def test_in_batch_info_nce_equals_explicit_negatives():
    torch.manual_seed(0)
    a = torch.nn.functional.normalize(torch.randn(4, 8), dim=1)
    p = torch.nn.functional.normalize(torch.randn(4, 8), dim=1)
    allv = torch.cat([a, p])
    explicit = []
    for i in range(4):
        negs = torch.cat([allv[j:j + 1] for j in range(8) if j not in (i, i + 4)])
        explicit.append(info_nce(a[i:i + 1], p[i:i + 1], negs[None], tau=0.1))
    got = info_nce_in_batch(a, p, tau=0.1, symmetric=False)
    assert float(got) == pytest.approx(float(torch.stack(explicit).mean()), rel=1e-5)
    assert info_nce_in_batch(a, p).shape == ()


def _fake_sequences(side: int = 61, n: int = 120, seed: int = 0) -> list[CachedSequence]:
    """Two traversals of one straight route (4 m spacing, 1 m lateral offset) plus an unrelated route."""
    rng = np.random.default_rng(seed)
    seqs = []
    for k, (group, dy) in enumerate((("route-a", 0.0), ("route-a", 1.0), ("route-b", 0.0))):
        x = np.arange(n) * 4.0
        poses = np.stack([x, np.full(n, dy), np.zeros(n)], axis=1)
        imgs = rng.random((n, side, side)).astype(np.float16)
        seqs.append(CachedSequence(f"seq{k}", group, imgs, poses, 0.64))
    return seqs


def test_sampler_respects_radii():
    data = TrainingSet(_fake_sequences())
    sampler = TupleSampler(data, pos_radius_m=5.0, neg_radius_m=25.0, batch_pairs=8)
    for s in range(30):
        a, p = sampler.sample(np.random.default_rng(s))
        assert len(a) == 8 and len(p) == 8
        items = np.concatenate([a, p])
        for i in range(8):
            assert p[i] != a[i] and data.group[p[i]] == data.group[a[i]]
            assert np.hypot(*(data.xy[p[i]] - data.xy[a[i]])) <= 5.0
            for j in items:
                if j in (a[i], p[i]) or data.group[j] != data.group[a[i]]:
                    continue
                assert np.hypot(*(data.xy[j] - data.xy[a[i]])) > 25.0
        assert len(set(data.group[a])) == 1  # a group with room for 8 anchors fills the batch alone


def test_crop_view_moves_a_point_target_as_the_pose_says():
    res, big_side, w = 0.5, 101, 61
    big = np.zeros((big_side, big_side), np.float32)
    cb = (big_side - 1) / 2
    p_orig = np.array([6.0, -4.0])  # metres, original sensor frame
    big[int(cb - p_orig[0] / res), int(cb - p_orig[1] / res)] = 1.0
    T = np.array([2.0, 1.0, np.deg2rad(90.0)])  # new sensor 2 m forward, 1 m left, turned 90 deg left
    out = crop_view(big, w, res, T)
    # p_new = R(-yaw) (p_orig - t) = R(-90)(4, -5) = (-5, -4)
    c = (w - 1) / 2
    i, j = np.unravel_index(np.argmax(out), out.shape)
    assert (i, j) == (int(c + 5 / res), int(c + 4 / res))
    # identity pose = centre crop
    o = (big_side - w) // 2
    np.testing.assert_array_equal(crop_view(big, w, res, np.zeros(3)), big[o:o + w, o:o + w])


def test_recall_at_1_known_answer():
    db_xy = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]])
    db = np.eye(3, dtype=np.float32)
    q_xy = np.array([[1.0, 0.0], [101.0, 0.0], [500.0, 0.0]])
    q = np.array([[1, 0, 0], [0, 0, 1], [0, 1, 0]], np.float32)  # second query retrieves the wrong place
    r, n = recall_at_1_from_descriptors(db, db_xy, q, q_xy, radius_m=25.0)
    assert n == 2 and r == pytest.approx(0.5)


def _tiny_config(**kw) -> TrainConfig:
    model = ModelConfig(width=0.125, num_clusters=4, output_dim=8, cartesian_width_px=41)
    base = dict(model=model, max_steps=3, num_negatives=6, kmeans_images=8, whiten_images=16,
                checkpoint_every=1, val_every=2, val_max_database=20, val_max_queries=10, num_threads=1)
    base.update(kw)
    return TrainConfig(**base)


def test_checkpoint_resume_gives_the_same_state(tmp_path):
    seqs = _fake_sequences(side=61, n=60)
    val = [(seqs[0], seqs[1])]
    straight = Trainer(_tiny_config(max_steps=3), seqs, val, run_dir=tmp_path / "a", progress=False)
    net_a, summary_a = straight.run()
    first = Trainer(_tiny_config(max_steps=2), seqs, val, run_dir=tmp_path / "b", progress=False)
    first.run()
    resumed = Trainer(_tiny_config(max_steps=3), seqs, val, run_dir=tmp_path / "b", progress=False)
    net_b, summary_b = resumed.run()
    assert summary_a["steps"] == summary_b["steps"] == 3
    sa, sb = net_a.state_dict(), net_b.state_dict()
    for k in sa:
        torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=1e-6, msg=k)
    assert 0.0 <= summary_a["val_recall_at_1"] <= 1.0


def test_training_reduces_the_loss_on_a_fixed_batch():
    """A few optimisation steps on one batch lower InfoNCE: the gradient path through e2cnn works."""
    seqs = _fake_sequences(side=61, n=60)
    tr = Trainer(_tiny_config(lr=3e-3), seqs, progress=False)
    tr.initialise_heads()
    rng = np.random.default_rng(0)
    a, p = tr.sampler.sample(rng)
    x = tr._views(np.concatenate([a, p]), rng, augment=False)
    losses = []
    for _ in range(8):
        tr.net.train()
        g, _ = tr.net(x)
        loss = info_nce_in_batch(g[:len(a)], g[len(a):])
        tr.opt.zero_grad()
        loss.backward()
        tr.opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] - 0.1


def test_train_main_writes_loadable_weights_and_adapts_from_them(tmp_path):
    """End to end: train from Cartesian cache folders, save, load for inference, and adapt with --init."""
    from reradar_core.model import DescriptorExtractor
    from reradar_core.training.cli import train_main

    specs, kw = _tiny_cache_specs(tmp_path)
    kw["steps"] = 1
    path = train_main("tiny", specs, [(specs[0], specs[1])], run_dir=tmp_path / "run1", **kw)
    ex = DescriptorExtractor.from_file(path)
    assert ex.model_id == "reresnet-c8-w0.125-k4-d8-in201" and ex.metadata["steps"] == 1
    assert 0.0 <= ex.metadata["val_recall_at_1"] <= 1.0
    path2 = train_main("tiny-adapted", specs, [], run_dir=tmp_path / "run2", init=str(path), **kw)
    ex2 = DescriptorExtractor.from_file(path2)
    assert ex2.metadata["init"] == str(path) and ex2.metadata["train_config"]["lr"] == pytest.approx(1e-5)


def test_device_resolution_and_clear_error_without_cuda():
    from reradar_core.errors import ConfigError
    from reradar_core.training.trainer import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ConfigError, match="unknown device"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            resolve_device("cuda")
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            Trainer(_tiny_config(device="cuda"), _fake_sequences(side=61, n=60), progress=False)


def test_two_identical_runs_give_identical_weights(tmp_path):
    """Same command, same weights (CPU): the claim `reradar train` reproduces the shipped weights rests on it."""
    seqs = _fake_sequences(side=61, n=60)
    val = [(seqs[0], seqs[1])]
    runs = [Trainer(_tiny_config(max_steps=3, device="cpu"), seqs, val, run_dir=tmp_path / name, progress=False).run()
            for name in ("a", "b")]
    (net_a, sum_a), (net_b, sum_b) = runs
    sa, sb = net_a.state_dict(), net_b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
    assert sum_a["history"][-1]["loss"] == sum_b["history"][-1]["loss"]


def test_hard_negative_sampler_mines_near_descriptors_of_far_places():
    """With a memory bank, mined anchors are the nearest bank descriptors among places > neg + pos radius
    from every anchor already in the batch; the rest of the batch is random; same rng -> same batch."""
    data = TrainingSet(_fake_sequences())
    sampler = TupleSampler(data, pos_radius_m=5.0, neg_radius_m=25.0, batch_pairs=8)
    n = len(data)
    # bank: descriptor = position along the route on a circle, so "nearest descriptor" = a place at a known
    # distance; route-b gets orthogonal descriptors
    ang = data.xy[:, 0] / 1000.0
    bank = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=1).astype(np.float32)
    bank[data.group == 1] = [0.0, 0.0, 1.0]
    for s in range(20):
        a, p = sampler.sample(np.random.default_rng(s), bank=bank, hard_pairs=3, hard_pool=1)
        a2, p2 = sampler.sample(np.random.default_rng(s), bank=bank, hard_pairs=3, hard_pool=1)
        np.testing.assert_array_equal(a, a2)
        np.testing.assert_array_equal(p, p2)
        assert len(a) == 8 and len(set(data.group[a])) == 1
        for i in range(8):
            for j in range(i):
                assert np.hypot(*(data.xy[a[i]] - data.xy[a[j]])) > 30.0
        # each mined anchor (slots 1..3) is the nearest-descriptor valid candidate of some earlier anchor:
        # with descriptors monotone in x, it lies just beyond 30 m from an earlier anchor (route-a batches;
        # route-b descriptors are all equal)
        for k in range(1, 4 if data.group[a[0]] == 0 else 1):
            d = np.abs(data.xy[a[:k], 0] - data.xy[a[k], 0])
            assert d.min() <= 30.0 + 4.0 + 1e-6, (k, d)
    # without a bank (or with hard_pairs = 0) the sampler is unchanged
    ref = sampler.sample(np.random.default_rng(5))
    same = sampler.sample(np.random.default_rng(5), bank=bank, hard_pairs=0)
    np.testing.assert_array_equal(ref[0], same[0])


def test_hard_negative_training_resumes_exactly(tmp_path):
    """Memory-bank refreshes (every 2 steps) are saved with the checkpoint: 2 + 2 resumed steps = 4 straight."""
    seqs = _fake_sequences(side=61, n=60)
    kw = dict(hard_negatives=4, hard_refresh_every=2, device="cpu")
    straight = Trainer(_tiny_config(max_steps=4, **kw), seqs, run_dir=tmp_path / "a", progress=False)
    net_a, _ = straight.run()
    assert straight.bank is not None and straight.bank_step == 2
    Trainer(_tiny_config(max_steps=3, **kw), seqs, run_dir=tmp_path / "b", progress=False).run()
    net_b, _ = Trainer(_tiny_config(max_steps=4, **kw), seqs, run_dir=tmp_path / "b", progress=False).run()
    sa, sb = net_a.state_dict(), net_b.state_dict()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


def test_hard_negatives_must_be_even_and_at_most_num_negatives():
    from reradar_core.errors import ConfigError

    with pytest.raises(ConfigError, match="hard_negatives"):
        TrainConfig(hard_negatives=3)
    with pytest.raises(ConfigError, match="hard_negatives"):
        TrainConfig(hard_negatives=16)
    assert TrainConfig(hard_negatives=8).hard_pairs == 4


def test_target_split_plan_never_reads_its_confidence_sessions(monkeypatch, tmp_path):
    """The sessions kept for the confidence / floor fit train no weights: not in the plan's train or val."""
    import reradar_core.sim.suites as suites
    from reradar_core.sim.suites import SuiteData
    from reradar_core.training.suites import suite_training_data

    split = SuiteData("train-target-loop", tmp_path / "split", "mulran", "mulran", 20.0,
                      training=[tmp_path / "session2", tmp_path / "session3"],
                      confidence=[tmp_path / "session4-confidence"], purpose="training")
    bench = SuiteData("loop-sim", tmp_path / "bench", "mulran", "mulran", 20.0, database=[tmp_path / "lap1"],
                      queries=[tmp_path / "laps2-3"])
    monkeypatch.setattr(suites, "build_suite", lambda name, progress=True: split if name.startswith("train") else bench)
    plan = suite_training_data("train-target-loop", progress=False)
    read = {s.path for s in plan.train} | {s.path for pair in plan.val for s in pair}
    assert read == {tmp_path / "session2", tmp_path / "session3", tmp_path / "lap1"}


def test_train_takes_several_splits_and_merges_their_plans(monkeypatch, tmp_path):
    """`reradar train --split a,b` trains on both splits' sequences and validates on both splits' pairs."""
    import json

    from typer.testing import CliRunner

    import reradar_core.training.cli as tcli
    import reradar_core.training.suites as tsuites
    from reradar_cli import app
    from reradar_core.training.suites import SeqSpec, TrainingPlan

    def plan(split, progress=True):
        p = tmp_path / split
        radius = 25.0 if split == "far" else 20.0
        return TrainingPlan(train=[SeqSpec(p / "t", f"world:{split}")], val=[(SeqSpec(p / "db", "v"), SeqSpec(p / "q", "v"))],
                            note=f"plan {split}", radius_m=radius)

    seen = {}

    def fake_train_main(name, seqs, vals, **kw):
        seen.update(seqs=seqs, vals=vals, kw=kw)
        out = tmp_path / f"{name}.pt"
        out.write_bytes(b"")
        out.with_suffix(".json").write_text(json.dumps({"model_id": "m", "steps": 1, "train_time_s": 0.0}))
        return out

    monkeypatch.setattr(tsuites, "suite_training_data", plan)
    monkeypatch.setattr(tcli, "train_main", fake_train_main)
    r = CliRunner().invoke(app, ["train", "--name", "x", "--split", "a,b"])
    assert r.exit_code == 0, r.output
    assert [s.path for s in seen["seqs"]] == [tmp_path / "a" / "t", tmp_path / "b" / "t"]
    assert len(seen["vals"]) == 2 and seen["kw"]["data_note"] == "plan a; plan b"
    assert seen["kw"]["recall_radius_m"] == 20.0
    bad = CliRunner().invoke(app, ["train", "--name", "x", "--split", "a,far"])
    assert bad.exit_code != 0 and "recall radii" in bad.output


@pytest.mark.parametrize("name", ["../../etc/x", "a/b", ".hidden", "..", ""])
def test_train_name_must_be_a_plain_file_stem(tmp_path, name):
    """L3: ``--name ../../etc/x`` once wrote outside --out-dir; refused before anything is read or written."""
    from typer.testing import CliRunner

    from reradar_cli import app

    res = CliRunner().invoke(app, ["train", "--name", name, "--sequence", str(tmp_path), "--steps", "0",
                                   "--out-dir", str(tmp_path / "out")])
    assert res.exit_code == 2 and "--name" in res.output
    assert not (tmp_path / "out").exists() and not (tmp_path.parent / "etc").exists()


@pytest.mark.parametrize("args, message", [(["--split", "nosuch"], "unknown training split 'nosuch'"),
                                           (["--sequence", "nosuch"], "nosuch: sequence folder does not exist")])
def test_train_bad_data_is_a_one_line_error(tmp_path, args, message):
    from typer.testing import CliRunner

    from reradar_cli import app

    res = CliRunner().invoke(app, ["train", "--name", "x", *args, "--out-dir", str(tmp_path)])
    assert res.exit_code == 2 and message in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("args, message", [
    (["--lr", "-1"], "--lr"), (["--lr", "nan"], "--lr"), (["--minutes", "0"], "--minutes"),
    (["--minutes", "nan"], "--minutes"), (["--threads", "0"], "--threads"),
    (["--val-db", "."], "--val-db and --val-query go together"),
    (["--seed", "-1"], "--seed"), (["--seed", str(2**64)], "--seed"),  # QA session 37: tracebacks after the data
    (["--rotation-consistency", "inf"], "must be a finite number >= 0"),
    (["--rotation-consistency", "nan"], "must be a finite number >= 0"),
    (["--init", "our-3-offroad-w05", "--width", "0.25", "--clusters", "5"], "fixes the network's shape"),
    (["--split", "smoke, smoke"], "--split names smoke more than once"),
])
def test_train_refuses_bad_options_before_any_work(tmp_path, args, message):
    """QA (session 20): ``--lr -1`` ended in the optimiser's traceback after the data was prepared, ``--minutes -1``
    wrote untrained weights and reported success, a lone ``--val-db`` was dropped without a word."""
    from typer.testing import CliRunner

    from reradar_cli import app

    res = CliRunner().invoke(app, ["train", "--name", "x", "--sequence", str(tmp_path), "--steps", "0",
                                   "--out-dir", str(tmp_path / "out"), *args])
    assert res.exit_code == 2 and message in res.output and "Traceback" not in res.output
    assert not (tmp_path / "out" / "x.pt").exists()


def test_train_never_replaces_weights_without_overwrite_and_checks_the_folder_first(tmp_path):
    from typer.testing import CliRunner

    from reradar_cli import app

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "x.pt").write_bytes(b"earlier weights")
    res = CliRunner().invoke(app, ["train", "--name", "x", "--sequence", str(tmp_path), "--steps", "0",
                                   "--out-dir", str(tmp_path / "out")])
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert (tmp_path / "out" / "x.pt").read_bytes() == b"earlier weights"
    (tmp_path / "file").write_text("")
    res = CliRunner().invoke(app, ["train", "--name", "x", "--sequence", str(tmp_path), "--steps", "0",
                                   "--out-dir", str(tmp_path / "file" / "w")])
    assert res.exit_code == 2 and "a file is in the way" in res.output and "Traceback" not in res.output


# ------------------------------------------------------------------ resume only what gives the same weights
def test_resume_refuses_a_checkpoint_of_other_settings(tmp_path):
    """QA: a leftover checkpoint (looked up by --name) was resumed under another --seed / --lr / --steps and its
    weights written as if trained with the new settings; now refused, naming old -> new."""
    from reradar_core.errors import ConfigError

    seqs = _fake_sequences(side=61, n=60)
    run = tmp_path / "run"
    Trainer(_tiny_config(max_steps=2), seqs, run_dir=run, progress=False).run()
    for kw, named in [({"seed": 1}, "--seed 0 -> 1"), ({"lr": 5e-3}, "--lr 0.0001 -> 0.005"),
                      ({"max_steps": 1}, "past --steps 1"), ({"num_threads": 2}, "--threads 1 -> 2")]:
        with pytest.raises(ConfigError, match="--no-resume") as err:
            Trainer(_tiny_config(**{"max_steps": 2, **kw}), seqs, run_dir=run, progress=False).run()
        assert named in str(err.value)
    with pytest.raises(ConfigError, match="training data"):  # other data under the same name
        Trainer(_tiny_config(max_steps=2), _fake_sequences(side=61, n=60, seed=3), run_dir=run, progress=False).run()
    # what provably leaves the weights alone may differ: a longer budget, more steps, validation settings
    tr = Trainer(_tiny_config(max_steps=3, max_minutes=5.0, val_every=1), seqs, run_dir=run, progress=False)
    assert tr.load_checkpoint() and tr.step == 2
    # a checkpoint without recorded settings (older versions) cannot be checked: refused the same way
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    del ck["settings"]
    torch.save(ck, run / "checkpoint.pt")
    with pytest.raises(ConfigError, match="records no training settings.*--no-resume"):
        Trainer(_tiny_config(max_steps=2), seqs, run_dir=run, progress=False).run()
    Trainer(_tiny_config(max_steps=2, seed=1), seqs, run_dir=run, progress=False).run(resume=False)  # --no-resume


@pytest.mark.parametrize("whitening", [False, True])
def test_resuming_a_finished_run_keeps_one_final_history_entry(tmp_path, whitening):
    """QA: each resume of a finished run appended another ``{"final": true, "loss": null}`` entry."""
    seqs = _fake_sequences(side=61, n=60)
    cfg = _tiny_config(max_steps=2, learned_whitening=whitening)
    _, first = Trainer(cfg, seqs, run_dir=tmp_path, progress=False).run()
    _, again = Trainer(cfg, seqs, run_dir=tmp_path, progress=False).run()
    finals = [h for h in again["history"] if h.get("final")]
    assert len(finals) == 1 and finals[0]["loss"] is not None
    assert finals[0]["loss"] == [h for h in first["history"] if h.get("final")][0]["loss"]


def _tiny_cache_specs(tmp_path):
    from reradar_core.training.suites import SeqSpec

    rng = np.random.default_rng(0)
    specs = []
    for k in range(2):
        d = tmp_path / f"cache{k}"
        d.mkdir()
        np.save(d / "images.npy", rng.random((24, 361, 361)).astype(np.float16))
        np.save(d / "poses.npy", np.stack([np.arange(24) * 4.0, np.full(24, k * 1.0), np.zeros(24)], axis=1))
        specs.append(SeqSpec(d, "route"))
    kw = dict(width=0.125, clusters=4, dim=8, threads=1, out_dir=tmp_path / "w", progress=False,
              num_negatives=2, kmeans_images=4, whiten_images=8, val_max_database=8, val_max_queries=4)
    return specs, kw


def test_steps_0_only_validates_and_writes_nothing(tmp_path):
    """docs/MODEL.md: ``--steps 0`` only validates; it wrote .pt/.json/.onnx of an untrained model."""
    from reradar_core.training.cli import train_main

    specs, kw = _tiny_cache_specs(tmp_path)
    summary: dict = {}
    assert train_main("v", specs, [(specs[0], specs[1])], steps=0, run_dir=tmp_path / "run", summary_out=summary,
                      **kw) is None
    assert not (tmp_path / "w").exists() and not (tmp_path / "run").exists()
    assert summary["steps"] == 0 and 0.0 <= summary["val_recall_at_1"] <= 1.0


def test_ctrl_c_names_the_last_checkpoint_and_exits_130(tmp_path, monkeypatch):
    """QA: Ctrl-C exited 130 without a word."""
    from typer.testing import CliRunner

    import reradar_core.training.cli as tcli
    from reradar_cli import app
    from reradar_core.training.cli import TrainingInterrupted, train_main

    specs, kw = _tiny_cache_specs(tmp_path)
    real_step = Trainer.train_step

    def step(self):
        if self.step == 3:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", step)
    with pytest.raises(TrainingInterrupted, match=r"interrupted at step 3; the last checkpoint .* is at step 2: "
                                                  "the same command resumes"):
        train_main("c", specs, [], steps=5, run_dir=tmp_path / "run", checkpoint_every=2, **kw)

    def interrupted(*a, **k):
        raise TrainingInterrupted("interrupted at step 3; the last checkpoint (x) is at step 2: the same command "
                                  "resumes from it")

    monkeypatch.setattr(tcli, "train_main", interrupted)
    res = CliRunner().invoke(app, ["train", "--name", "c", "--sequence", str(specs[0].path),
                                   "--out-dir", str(tmp_path / "o")])
    assert res.exit_code == 130 and "last checkpoint (x) is at step 2" in res.output


@pytest.mark.parametrize("args", [["--split", "nosuch"], ["--sequence", "{tmp}/cache0", "--init", "nope.pt"]])
def test_failed_train_leaves_no_empty_out_dir(tmp_path, args):
    """QA: ``--split nosuch`` / ``--init nope.pt`` failed but left the empty --out-dir behind."""
    from typer.testing import CliRunner

    from reradar_cli import app

    _tiny_cache_specs(tmp_path)
    res = CliRunner().invoke(app, ["train", "--name", "x", *[a.format(tmp=tmp_path) for a in args],
                                   "--out-dir", str(tmp_path / "out" / "w")])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ rotation consistency (issue 11)
def test_rotation_consistency_adds_one_minus_cosine_of_turned_anchors(monkeypatch):
    """With weight w the step's loss is InfoNCE + w * mean(1 - cos(anchor, anchor turned)); the turned copies share
    the anchors' shift and only their heading differs; the batch itself is drawn exactly as without the term."""
    from reradar_core.training.loss import info_nce_in_batch

    seqs = _fake_sequences(side=61, n=60)
    render = Trainer._render_views
    seen: list[tuple[np.ndarray, np.ndarray]] = []

    def recording(self, items, T):
        seen.append((np.asarray(items).copy(), np.asarray(T).copy()))
        return render(self, items, T)

    monkeypatch.setattr(Trainer, "_render_views", recording)
    batches, losses = {}, {}
    for w in (0.0, 5.0):
        tr = Trainer(_tiny_config(rotation_consistency=w), seqs, progress=False)
        tr.initialise_heads()
        seen.clear()
        losses[w] = tr.train_step()
        batches[w] = seen[-1]
    b = _tiny_config().batch_pairs
    (items0, T0), (items, T) = batches[0.0], batches[5.0]
    assert len(items0) == 2 * b and len(items) == 3 * b
    np.testing.assert_array_equal(items[:2 * b], items0)  # the InfoNCE batch is unchanged by the option
    np.testing.assert_array_equal(T[:2 * b], T0)
    np.testing.assert_array_equal(items[2 * b:], items[:b])  # then the anchors again
    np.testing.assert_array_equal(T[2 * b:, :2], T[:b, :2])  # same shift
    assert np.all(np.abs(np.angle(np.exp(1j * (T[2 * b:, 2] - T[:b, 2])))) > 1e-6)  # another heading
    # the loss by hand, on the same views and the same initial weights
    tr = Trainer(_tiny_config(rotation_consistency=5.0), seqs, progress=False)
    tr.initialise_heads()
    tr.net.train()
    g, _ = tr.net(render(tr, items, T))
    term = (1 - (g[:b] * g[2 * b:]).sum(1)).mean()
    assert 0 < float(term.detach()) < 2
    assert losses[5.0] == pytest.approx(float(info_nce_in_batch(g[:b], g[b:2 * b], tau=0.1) + 5.0 * term), rel=1e-4)


def test_rotation_consistency_weight_is_checked_and_recorded_for_resume(tmp_path):
    from reradar_core.errors import ConfigError

    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="rotation_consistency"):
            _tiny_config(rotation_consistency=bad)
    seqs = _fake_sequences(side=61, n=60)
    run = tmp_path / "run"
    Trainer(_tiny_config(max_steps=2), seqs, run_dir=run, progress=False).run()
    # off (the default) is what checkpoints written before the option did: they stay resumable
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert "rotation_consistency" not in ck["settings"]
    with pytest.raises(ConfigError, match=r"--rotation-consistency 0\.0 -> 2\.0"):
        Trainer(_tiny_config(max_steps=2, rotation_consistency=2.0), seqs, run_dir=run, progress=False).run()
    Trainer(_tiny_config(max_steps=2, rotation_consistency=2.0), seqs, run_dir=run, progress=False).run(resume=False)
    with pytest.raises(ConfigError, match=r"--rotation-consistency 2\.0 -> 0\.0"):  # and back: named, not "<not ...>"
        Trainer(_tiny_config(max_steps=2), seqs, run_dir=run, progress=False).run()


# ---- QA session 37: a diverged run, drives of one world, validation without overlap --------------------------------
def test_a_diverged_run_stops_with_one_line_and_writes_no_weights(tmp_path):
    """QA: `--rotation-consistency 1e300` (or `--lr 1e30`) wrote NaN weights and NaN into the .json, then the ONNX
    export failed with a traceback."""
    from reradar_core.training.cli import train_main
    from reradar_core.training.trainer import TrainingDivergedError

    specs, kw = _tiny_cache_specs(tmp_path)
    with pytest.raises(TrainingDivergedError, match=r"diverged at step 1: the loss is (nan|inf).*--rotation-consistency"):
        train_main("nan", specs, [(specs[0], specs[1])], steps=2, run_dir=tmp_path / "run", rotation_consistency=1e300,
                   **kw)
    assert not (tmp_path / "w" / "nan.pt").exists() and not (tmp_path / "w" / "nan.json").exists()


def test_validation_without_a_single_overlapping_query_is_refused(tmp_path):
    """QA: a validation pair with no common place gave "val Recall@1 nan (0 queries)" and NaN in the .json."""
    from reradar_core.errors import ConfigError
    from reradar_core.training.cli import train_main
    from reradar_core.training.suites import SeqSpec

    specs, kw = _tiny_cache_specs(tmp_path)
    far = tmp_path / "far"
    far.mkdir()
    np.save(far / "images.npy", np.load(specs[1].path / "images.npy"))
    np.save(far / "poses.npy", np.load(specs[1].path / "poses.npy") + [5000.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match="no query lies within 25 m of a database scan"):
        train_main("v", specs, [(specs[0], SeqSpec(far, "route"))], steps=0, **kw)


def test_weights_json_is_strict_json(tmp_path):
    import json

    from reradar_core.model.registry import _finite_or_none

    meta = {"a": float("nan"), "b": [1.0, float("inf"), {"c": -float("inf")}], "d": (2.0,), "e": "x"}
    assert json.loads(json.dumps(_finite_or_none(meta), allow_nan=False)) == {"a": None, "b": [1.0, None, {"c": None}],
                                                                              "d": [2.0], "e": "x"}


def test_sequence_folders_of_one_simulated_world_are_one_place_group(tmp_path):
    """QA: `--sequence A --sequence B` (two drives of one simulated route) made each folder its own place: no
    positive across the drives and same-place scans used as negatives. Folders rendered in one world share it;
    recorded folders share a frame only with --shared-frame."""
    import json

    from reradar_core.training.cli import _place_group

    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "reradar_sim.json").write_text(json.dumps({"suite": "smoke", "world_seed": seed}))
    (tmp_path / "real").mkdir()
    groups = {n: _place_group(tmp_path / n, False) for n in ("a", "b", "c", "real")}
    assert groups["a"] == groups["b"] != groups["c"]
    assert groups["real"] not in (groups["a"], groups["c"])
    assert {_place_group(tmp_path / n, True) for n in ("a", "c", "real")} == {"shared-frame"}


def test_train_preset_and_time_unit_reach_the_folders(tmp_path, monkeypatch):
    """QA session 37: a recorded Boreas folder must name its preset (3,360 bins fit two bin sizes), and ``train``
    had no ``--preset``; the folders' reader now gets it, and the pose-time unit, for training and validation."""
    from typer.testing import CliRunner

    import reradar_core.training.cli as tcli
    from reradar_cli import app

    seen: dict = {}

    def fake_train_main(name, seqs, vals, **kw):
        seen.update(seqs=seqs, vals=vals)
        return None

    monkeypatch.setattr(tcli, "train_main", fake_train_main)
    args = ["train", "--name", "x", "--sequence", str(tmp_path), "--val-db", str(tmp_path), "--val-query",
            str(tmp_path), "--steps", "0", "--out-dir", str(tmp_path / "o")]
    res = CliRunner().invoke(app, [*args, "--preset", "boreas-2021", "--time-unit", "ms"])
    assert res.exit_code == 0, res.output
    specs = [*seen["seqs"], *seen["vals"][0]]
    assert [(s.preset, s.time_unit) for s in specs] == [("boreas-2021", "ms")] * 3
    res = CliRunner().invoke(app, [*args, "--preset", "navtech9"])
    assert res.exit_code == 2 and "unknown radar preset 'navtech9'" in res.output
    res = CliRunner().invoke(app, ["train", "--name", "x", "--split", "smoke", "--preset", "boreas"])
    assert res.exit_code == 2 and "--preset applies to --sequence" in res.output


def test_cartesian_cache_tells_presets_and_poses_apart(tmp_path):
    """The same folder read with another preset (bin size) or pose-time unit is another cache entry."""
    from types import SimpleNamespace

    from reradar_core.geometry.cartesian import CartesianConfig
    from reradar_core.io.presets import get_preset
    from reradar_core.training.data import _cache_key

    scan = tmp_path / "1.png"
    scan.write_bytes(b"x")
    poses = SimpleNamespace(poses=np.zeros((1, 3)))

    class Seq(SimpleNamespace):
        def __len__(self):
            return 1

    big = CartesianConfig(361, 0.64)
    a = _cache_key(Seq(scan_paths=[scan], root=tmp_path, preset=get_preset("boreas"), poses=poses), big)
    b = _cache_key(Seq(scan_paths=[scan], root=tmp_path, preset=get_preset("boreas-2021"), poses=poses), big)
    c = _cache_key(Seq(scan_paths=[scan], root=tmp_path, preset=get_preset("boreas"),
                       poses=SimpleNamespace(poses=np.ones((1, 3)))), big)
    assert len({a, b, c}) == 3
    assert a == _cache_key(Seq(scan_paths=[scan], root=tmp_path, preset=get_preset("boreas"), poses=poses), big)
