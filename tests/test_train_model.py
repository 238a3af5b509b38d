"""The network's parts against their oracles: chunked BEV pooling vs the lifted tensor,
pillar picking vs a loop, EfficientNet-B0 vs torchvision's layout, the micro crop vs
positions in metres, the ONNX graph vs torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import run_cli
from gtgen.config import load_config
from gtgen.errors import TrainError
from test_train import SMALL_TRAIN


def test_chunked_bev_pool_equals_the_lifted_tensor_forward_and_backward():
    from gtgen.train.bev_pool import _BevPool, bev_pool, bev_pool_naive

    g = torch.Generator().manual_seed(0)
    N, Dd, P, C, n_cells = 3, 7, 11, 5, 20
    depth = torch.rand(N, Dd, P, generator=g, dtype=torch.float64)
    feat = torch.randn(N, P, C, generator=g, dtype=torch.float64)
    cell = torch.randint(0, n_cells + 6, (N, Dd, P), generator=g)  # some outside the grid (>= n_cells)
    w = torch.randn(n_cells, C, generator=g, dtype=torch.float64)

    def run(fn):
        d, f = depth.clone().requires_grad_(), feat.clone().requires_grad_()
        out = fn(d, f)
        (out * w).sum().backward()
        return out.detach(), d.grad, f.grad

    want = run(lambda d, f: bev_pool_naive(d, f, cell, n_cells))
    for chunk in (1, 3, Dd):
        got = run(lambda d, f, chunk=chunk: _BevPool.apply(d, f, cell, n_cells, chunk))
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    got = run(lambda d, f: bev_pool(d, f, cell, n_cells, chunk_mb=2 * N * P * C * 8 / 2**20))  # 2 bins a chunk
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with torch.no_grad():
        torch.testing.assert_close(bev_pool(depth, feat, cell, n_cells, 1e-6), want[0], rtol=1e-12, atol=1e-12)


def _pillars_by_loop(points, n_points, size, res, max_pillars, per_pillar, priority):
    """The oracle: per sample, points in priority order into their cells, then the pillars."""
    out = set()
    L = size * res
    for b in range(points.shape[0]):
        n = int(n_points[b])
        order = sorted(range(n), key=lambda i: (float(priority[b, i]), i)) if priority is not None else range(n)
        pillars: dict[int, list[int]] = {}
        for i in order:
            x, y = float(points[b, i, 0]), float(points[b, i, 1])
            ix, iy = int(np.floor((x + L / 2) / res)), int(np.floor((y + L / 2) / res))
            if 0 <= ix < size and 0 <= iy < size:
                pillars.setdefault(ix * size + iy, []).append(i)
        for c in list(pillars)[:max_pillars]:  # dicts keep the order of each pillar's first point
            out |= {(b * size * size + c, tuple(points[b, i].tolist())) for i in pillars[c][:per_pillar]}
    return out


def test_pillarize_keeps_the_first_points_and_pillars_by_priority():
    from gtgen.train.pillars import pillarize

    g = torch.Generator().manual_seed(1)
    B, P, size, res = 2, 300, 6, 1.0
    points = torch.rand(B, P, 3, generator=g) * 8 - 4  # some beyond the +-3 m grid
    n_points = torch.tensor([300, 170])
    for priority in (None, torch.rand(B, P, generator=g)):
        for max_pillars, per_pillar in ((100, 16), (7, 3), (20, 1)):
            pts, cells = pillarize(points, n_points, size, res, max_pillars, per_pillar, priority)
            got = {(int(c), tuple(p.tolist())) for c, p in zip(cells, pts)}
            assert len(got) == len(cells)
            assert got == _pillars_by_loop(points, n_points, size, res, max_pillars, per_pillar, priority)


def test_efficientnet_b0_has_torchvision_layout_and_loads_strictly(tmp_path):
    from gtgen.train.backbones import B0_CLASSIFIER, EfficientNetB0
    from gtgen.train.trainer import build_model

    net = EfficientNetB0()
    own = net.state_dict()
    # torchvision's efficientnet_b0: 5,288,548 parameters with its 1000-class classifier
    n = sum(p.numel() for p in net.parameters()) + sum(v.numel() for v in B0_CLASSIFIER.values())
    assert n == 5_288_548
    for key, shape in (("features.0.0.weight", (32, 3, 3, 3)), ("features.1.0.block.1.fc1.weight", (8, 32, 1, 1)),
                       ("features.2.0.block.0.0.weight", (96, 16, 1, 1)), ("features.6.3.block.3.1.weight", (192,)),
                       ("features.8.1.running_var", (1280,)), ("features.4.2.block.2.fc2.bias", (480,))):
        assert tuple(own[key].shape) == shape, key
    # a torchvision-format file (features and classifier, other values than the fresh net's)
    g = torch.Generator().manual_seed(2)
    state = {k: (torch.randn(v.shape, generator=g) if v.is_floating_point() else v.clone()) for k, v in own.items()}
    state.update({k: torch.randn(v.shape, generator=g) for k, v in B0_CLASSIFIER.items()})
    good = tmp_path / "efficientnet_b0.pth"
    torch.save(state, good)
    cfg = load_config(None, SMALL_TRAIN, {"train": {"image_backbone": "efficientnet_b0", "fpn_channels": 16, "backbone_weights": str(good)}})
    model = build_model(cfg.train, cfg)
    loaded = model.lift.backbone.net.state_dict()
    assert all(torch.equal(loaded[k], state[k]) for k in own)
    partial = dict(state)
    del partial["features.3.1.block.1.0.weight"], partial["classifier.1.bias"]
    torch.save(partial, tmp_path / "partial.pth")
    wrong = {**state, "features.0.0.weight": torch.zeros(16, 3, 3, 3), "head.fc.weight": torch.zeros(3)}
    torch.save(wrong, tmp_path / "wrong.pth")
    for name, msg in (("partial.pth", "2 missing keys \\(features.3.1.block.1.0.weight, classifier.1.bias\\)"),
                      ("wrong.pth", "1 unexpected keys \\(head.fc.weight\\); 1 keys of another shape \\(features.0.0.weight \\(16, 3, 3, 3\\) \\(expected \\(32, 3, 3, 3\\)\\)")):
        bad = cfg.model_copy(update={"train": cfg.train.model_copy(update={"backbone_weights": str(tmp_path / name)})})
        with pytest.raises(TrainError, match=msg):
            build_model(bad.train, bad)


def test_weights_that_are_no_state_dict_say_so(tmp_path):
    """A text file, or a whole pickled module, is no state dict: the error says what to save,
    not torch's advice to load with weights_only=False."""
    from gtgen.train.backbones import EfficientNetB0, load_backbone_weights

    (tmp_path / "notes.pth").write_text("not weights")
    torch.save(torch.nn.Linear(2, 2), tmp_path / "module.pth")
    for name in ("notes.pth", "module.pth"):
        with pytest.raises(TrainError, match="not a state dict of tensors saved by torch.save") as err:
            load_backbone_weights(EfficientNetB0(), tmp_path / name)
        assert "weights_only" not in str(err.value) and "\n" not in str(err.value)


def test_bad_backbone_weights_through_the_cli_are_one_line(dataset, tmp_path):
    import yaml

    torch.save({"features.0.0.weight": torch.zeros(32, 3, 3, 3)}, tmp_path / "few.pth")
    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump({"train": {**SMALL_TRAIN["train"], "image_backbone": "efficientnet_b0", "backbone_weights": str(tmp_path / "few.pth")}}))
    p = run_cli("train", dataset, "--steps", "1", "--run-dir", tmp_path / "run", "--config", c, cwd=tmp_path)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "missing keys (features.0.1.weight" in p.stderr and not (tmp_path / "run").exists()


def test_paper_network_parameters_per_block():
    from gtgen.train.trainer import build_model, parameter_counts, preset_overrides

    cfg = load_config(None, preset_overrides("paper"))
    with torch.device("meta"):  # the shapes only
        counts = parameter_counts(build_model(cfg.train, cfg))
    assert counts["image backbone"] == 5_288_548 - 1_281_000  # EfficientNet-B0 without its classifier
    assert sum(v for k, v in counts.items() if k != "total") == counts["total"]
    assert abs(counts["total"] / 19.5e6 - 1) < 0.15, counts  # the paper: 19.5 M


@pytest.mark.parametrize("n_s", [250, 80, 126])
def test_micro_view_takes_exactly_the_centre_half(n_s):
    from gtgen.train.data import micro_view

    res, m = 0.8, 128
    L = n_s * res
    raw = np.full((n_s, n_s), np.nan)
    spots = [(0.3 * L / 4 * 3, -0.9 * L / 4), (-0.88 * L / 4, 0.47 * L / 4), (0.1, 0.1)]  # metres, inside +-L/4
    for k, (x, y) in enumerate(spots):
        raw[int(np.floor((x + L / 2) / res)), int(np.floor((y + L / 2) / res))] = k + 1.0
    view = micro_view(raw, m)
    centres = -L / 4 + (np.arange(m) + 0.5) * (L / 2 / m)  # the micro cells' centres [m]
    for k, (x, y) in enumerate(spots):
        # the micro cells whose centres lie in the short cell that holds the spot
        cx0 = np.floor((x + L / 2) / res) * res - L / 2
        cy0 = np.floor((y + L / 2) / res) * res - L / 2
        want = ((centres >= cx0) & (centres < cx0 + res))[:, None] & ((centres >= cy0) & (centres < cy0 + res))[None, :]
        assert np.array_equal(view == k + 1.0, want), (n_s, k)


def test_micro_prior_of_a_ramp_is_the_ramp_at_the_micro_cells(dataset):
    from gtgen.train.data import ShardDataset

    cfg = load_config(None, SMALL_TRAIN, {"train": {"micro_size": 128}})
    ds = ShardDataset(dataset, cfg.train)
    n_s, res = 250, 0.8  # the paper's short grid: its centre half starts mid-cell
    x = -n_s * res / 2 + (np.arange(n_s) + 0.5) * res
    ramp = np.repeat(0.2 * x[:, None], n_s, 1).astype(np.float32)  # elevation = x / 5 [m], within the +-25 m clip
    prior = ds._micro_prior(ramp)
    centres = -50 + (np.arange(128) + 0.5) * (100 / 128)
    inner = slice(8, -8)  # away from the slab's edges, where the smoothing window is cut
    np.testing.assert_allclose(prior[0][inner, inner] * cfg.train.elevation_clip_m, np.repeat(0.2 * centres[inner, None], 128 - 16, 1), atol=1e-4)


def test_onnx_export_matches_torch(dataset, tmp_path):
    import onnxruntime as ort

    from gtgen.train.checkpoint import load_checkpoint
    from gtgen.train.data import ShardDataset
    from gtgen.train.evaluation import trained_model as _trained_model
    from gtgen.train.onnx import INPUTS, Deployable, deploy_inputs
    from gtgen.train.trainer import _collate, train

    cfg = load_config(None, SMALL_TRAIN)
    train(dataset, tmp_path / "run", cfg, max_steps=2)
    p = run_cli("export", "onnx", "--ckpt", tmp_path / "run" / "ckpt.pt", "-o", tmp_path / "m.onnx", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    # a folder as the output, even with --overwrite: one line saying so (was "Is a directory: 'myout.partial'")
    (tmp_path / "myout").mkdir()
    p = run_cli("export", "onnx", "--ckpt", tmp_path / "run" / "ckpt.pt", "-o", "myout/", "--overwrite", cwd=tmp_path)
    assert p.returncode == 1 and p.stderr.strip() == ("error: output 'myout' is a folder, and this output is one file: "
                                                      "give the file's path (a name inside the folder, say)"), p.stderr
    assert list((tmp_path / "myout").iterdir()) == [] and sorted(x.name for x in tmp_path.iterdir()) == ["latest", "m.onnx", "myout", "run"]
    state, tc, data_cfg = load_checkpoint(tmp_path / "run" / "ckpt.pt")
    model = _trained_model(state, tc, data_cfg)
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == list(INPUTS)
    ds = ShardDataset(dataset, tc)
    for i in (3, len(ds) - 1):  # two samples, two numbers of pillar points
        batch = _collate([ds[i]])
        args = deploy_inputs(model, batch)
        with torch.no_grad():
            want = Deployable(model)(*args)
            full = model(batch)
        torch.testing.assert_close(want[0], full["micro/elevation"])  # the graph is the whole network
        got = sess.run(None, {n: a.numpy() for n, a in zip(INPUTS, args)})
        for w, g in zip(want, got):
            assert np.max(np.abs(w.numpy() - g)) < 1e-3
