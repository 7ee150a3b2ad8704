"""Training: schedule, loss, batches, no collapse, exact resume, the model's render paths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cubecloud_cli.cunerf.model import CubeModel, CubeOutput, render_many
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels, holdout_slices, voxel_centres
from cubecloud_cli.cunerf.training import Trainer, adaptive_mse, learning_rate
from cubecloud_cli.numerics.metrics import psnr


def _settings(**changes) -> CunerfSettings:
    base = dict(iterations=60, batch_size=512, lr=0.05, lr_final=5e-3, warmup=5, holdout=2, val_every=30)
    return CunerfSettings(**{**base, **changes})


def _trainer(volume: np.ndarray, settings: CunerfSettings) -> Trainer:
    size = volume.shape[0]
    torch.manual_seed(settings.seed)
    model = CubeModel(settings.field_config(size), settings.render_config(size))
    held = holdout_slices(volume, settings.holdout, settings.train_scale)
    voxels = TrainingVoxels(torch.from_numpy(volume), settings.train_scale, held, settings.body_fraction)
    return Trainer(model, voxels, settings, torch.Generator().manual_seed(settings.seed))


def _ball(size=16, radius=0.35, value=0.8) -> np.ndarray:
    axis = (2 * np.arange(size) + 1) / size - 1
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    return np.where(x**2 + y**2 + z**2 < radius**2, value, 0.0).astype(np.float32)


def test_learning_rate_warms_up_then_decays_log_linearly():
    s = CunerfSettings(iterations=1000, lr=1e-2, lr_final=1e-4, warmup=100)
    assert learning_rate(0, s) == pytest.approx(1e-4)  # 1% of lr
    at_warm = learning_rate(100, s)
    assert at_warm == pytest.approx(math.exp(0.9 * math.log(1e-2) + 0.1 * math.log(1e-4)))
    assert learning_rate(1000, s) == pytest.approx(1e-4)
    after = [learning_rate(t, s) for t in range(100, 1001, 50)]
    assert all(a > b for a, b in zip(after, after[1:]))
    assert learning_rate(500, CunerfSettings(iterations=1000, lr=1e-2, lr_final=1e-2, warmup=0)) == pytest.approx(1e-2)


def test_adaptive_loss_is_the_papers_and_stops_its_weight_gradient():
    target = torch.tensor([0.5, 0.2])
    fine = torch.tensor([0.9, 0.2], requires_grad=True)
    coarse = torch.tensor([0.1, 0.6], requires_grad=True)
    loss = adaptive_mse(CubeOutput(fine, coarse, True), target)
    expected = ((0.4**2 + 0) / 2) + ((math.sqrt(0.4) * 0.4**2 + 0 * 0.4**2) / 2)
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    loss.backward()
    # d/dfine only through the MSE term: 2·(fine − C)/2.
    assert fine.grad.tolist() == pytest.approx([0.4, 0.0], rel=1e-6)
    plain = adaptive_mse(CubeOutput(fine.detach(), fine.detach(), False), target)
    assert plain.item() == pytest.approx(0.08, rel=1e-6)


def test_batches_skip_held_out_slices_and_follow_the_lattice():
    volume = _ball(16)
    held = holdout_slices(volume, 3, 2)
    assert held and all(k % 2 == 1 for k in held)
    voxels = TrainingVoxels(torch.from_numpy(volume), 2, held, 0.5)
    centres, targets = voxels.batch(4000, torch.Generator().manual_seed(0))
    index = torch.round((centres + 1) * 8 - 0.5).long()
    assert (index % 2 == 0).all()
    assert not set(index[:, 2].tolist()) & set(held)
    np.testing.assert_array_equal(targets.numpy(), volume[index[:, 0], index[:, 1], index[:, 2]])
    assert 0.45 < (targets > 0).float().mean() < 0.7  # half from the body, the rest uniform


def test_holdout_slices_avoid_the_ends_and_empty_slices():
    volume = np.zeros((40, 40, 40), np.float32)
    volume[5:35, 5:35, 4:36] = 0.5
    picks = holdout_slices(volume, 4, 1)
    assert len(picks) == 4 and min(picks) > 4 and max(picks) < 35
    assert holdout_slices(np.zeros((16, 16, 16), np.float32), 2, 1) == [5, 10]


def test_a_thin_body_keeps_most_of_its_slices_for_training():
    volume = np.zeros((64, 64, 64), np.float32)
    volume[:, :, 20:34] = 0.5  # 14 slices of body
    assert len(holdout_slices(volume, 8, 1)) == 1


def test_a_mostly_air_scan_still_learns_its_body():
    # 0.5% of the voxels are body: without body sampling a batch holds ~3 of them.
    volume = _ball(24, radius=0.2, value=0.8)
    assert (volume > 0).mean() < 0.01
    trainer = _trainer(volume, _settings(iterations=150, holdout=0))
    for _ in range(150):
        trainer.step()
    inside = torch.from_numpy(np.argwhere(volume > 0))
    rendered = render_many(trainer.model, voxel_centres(inside, 24))
    assert rendered.mean() > 0.6
    assert torch.isfinite(rendered).all() and (rendered <= 1).all()


@pytest.mark.parametrize("model", ["fast", "cunerf"])
def test_all_air_batches_and_cubes_reaching_outside_stay_finite(model):
    settings = _settings(
        model=model,
        lr=2e-3 if model == "cunerf" else 0.05,
        batch_size=64,
        importance=8,
        cube_radius=4.0,
        samples_per_axis=2,
    )
    trainer = _trainer(np.zeros((8, 8, 8), np.float32), settings)
    for _ in range(3):
        assert math.isfinite(trainer.step())
    corners = torch.tensor([[-1.0, -1.0, -1.0], [0.99, 0.99, 0.99], [5.0, 0.0, 0.0]])
    for train in (True, False):
        out = trainer.model.render(corners, train=train, generator=torch.Generator().manual_seed(0))
        assert torch.isfinite(out.value).all() and torch.isfinite(out.coarse).all()
        assert (out.value >= 0).all() and (out.value <= 1).all()


@pytest.mark.parametrize("official", [False, True])
def test_the_official_switch_picks_the_official_samplers(official, monkeypatch):
    import cubecloud_cli.cunerf.model as model_module

    layouts, directions = [], []
    original_offsets, original_directions = model_module.cube_offsets, model_module.sphere_directions
    monkeypatch.setattr(model_module, "cube_offsets", lambda *a, **k: layouts.append(a[2]) or original_offsets(*a, **k))
    monkeypatch.setattr(
        model_module, "sphere_directions", lambda *a, **k: directions.append(a[1]) or original_directions(*a, **k)
    )
    trainer = _trainer(_ball(8), _settings(official=official, importance=8, samples_per_axis=4))
    generator = torch.Generator().manual_seed(0)
    for train in (True, False):
        out = trainer.model.render(torch.zeros(5, 3), train=train, generator=generator)
        assert out.has_fine and torch.isfinite(out.value).all()
    if official:
        assert layouts == ["official-train", "official-lattice"] and directions == ["official", "official"]
    else:
        assert layouts == ["stratified", "lattice"] and directions == ["uniform", "fibonacci"]


def test_test_time_fine_points_are_centred_on_the_cube():
    # Radii come sorted; directions must not be, or long radii would all point one way.
    from cubecloud_cli.cunerf.sampling import sphere_directions

    for count in (7, 16, 32, 59, 64):
        radii = torch.linspace(0.1, 1.0, count)[:, None]
        centroid = (radii * sphere_directions((count,), "fibonacci")).mean(0)
        # Paired in spiral order the z offset would be about −(1.0 − 0.1)/6 = −0.15.
        assert centroid.abs().max() < 0.03, (count, centroid)


def test_resume_continues_exactly_like_an_uninterrupted_run(tmp_path):
    volume = _ball(16)
    settings = _settings(iterations=40, val_every=10)
    straight = _trainer(volume, settings)
    for _ in range(40):
        straight.step()

    first = _trainer(volume, settings)
    for _ in range(17):
        first.step()
    first.save(tmp_path / "checkpoint.pt")
    second = _trainer(volume, settings)
    second.model.coarse.table.data.add_(1.0)  # a fresh process would start from other values
    second.restore(torch.load(tmp_path / "checkpoint.pt", weights_only=False))
    for _ in range(23):
        second.step()

    for a, b in zip(straight.model.state_dict().values(), second.model.state_dict().values()):
        assert torch.equal(a, b)
    assert second.iteration == 40


def test_fitting_a_small_volume_reaches_a_useful_psnr():
    # A smooth blob: held-out slices between training slices are predictable from them.
    axis = (2 * np.arange(32) + 1) / 32 - 1
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    volume = (0.8 * np.exp(-(x**2 + 2 * y**2 + z**2) / 0.2)).astype(np.float32)
    trainer = _trainer(volume, _settings(iterations=300, batch_size=1024, holdout=2))
    for _ in range(300):
        trainer.step()
    assert trainer.held_out_scores()["val_psnr"] > 30
    everything = torch.from_numpy(np.argwhere(np.ones_like(volume, dtype=bool)))
    rendered = render_many(trainer.model, voxel_centres(everything, 32)).reshape(32, 32, 32).numpy()
    assert psnr(volume, rendered) > 30


@pytest.mark.parametrize("train_scale", [1, 2, 3])
def test_body_voxels_listed_slab_by_slab_are_every_training_voxel_in_x_y_z_order(monkeypatch, train_scale):
    import cubecloud_cli.cunerf.supervision as supervision

    monkeypatch.setattr(supervision, "BODY_SLAB", 3)  # slabs that cut the lattice unevenly
    rng = np.random.default_rng(train_scale)
    volume = torch.from_numpy(
        np.where(rng.random((17, 17, 17)) < 0.4, rng.random((17, 17, 17)), 0.0).astype(np.float32)
    )
    voxels = supervision.TrainingVoxels(volume, train_scale, held_out=[4, 9], body_fraction=0.8)
    lattice, slices = range(0, 17, train_scale), [k for k in range(0, 17, train_scale) if k not in (4, 9)]
    expected = [(i, j, k) for i in lattice for j in lattice for k in slices if volume[i, j, k] > 0]
    # Counted without being listed: a start that trains no iteration never holds the list.
    assert voxels.body_voxels == len(expected) and "_body" not in voxels.__dict__
    assert [tuple(row) for row in voxels.body.tolist()] == expected and voxels.body.dtype == torch.int32
