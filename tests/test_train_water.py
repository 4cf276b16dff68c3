"""Masked loss, water overrides and water calibration in the trainer, on tiny scenes rendered in memory."""

import json
import math
from pathlib import Path

import pytest
import torch

from ragsplat.bench.synthetic import bed_scene, render_views, ring_cameras, write_dataset
from ragsplat.cli.main import main
from ragsplat.dataset import BedInfo, Dataset
from ragsplat.dataset.load import View
from ragsplat.errors import ConfigError
from ragsplat.gaussians import PARAM_NAMES, activated, colors_for_view
from ragsplat.rasterize import rasterize
from ragsplat.refraction import refract_gaussians
from ragsplat.train import Trainer, preset_config
from ragsplat.train.strategy import DensifyConfig
from ragsplat.train.trainer import rippled
from ragsplat.water_surface import WaterSurface

LEVEL, N, DEPTH = 0.2, 1.33, 1.0  # a level off zero, so nothing passes by reading 0 for it
NO_DENSIFY = DensifyConfig(refine_start_iter=10**6, refine_stop_iter=10**6, reset_every=10**6)


def _dataset(water, size=24, views=5, count=300, level=LEVEL) -> Dataset:
    """A textured bed DEPTH below `level`, seen by a nadir and a ring of oblique cameras, in memory."""
    scene = bed_scene(count, 1.0, DEPTH, seed=0)
    scene["means"][:, 2] += level
    cams = ring_cameras(views, size, level + 1.5, 1.0, target=(0, 0, level - DEPTH))
    out = []
    for i, v in enumerate(render_views(scene, cams, water)):
        rgb = (v["image"] * 255).round().to(torch.uint8)
        out.append(View(f"{i:04d}", "train", "nadir", v["camera"], rgb, None, "", None, None))
    return Dataset(Path("mem"), water, out, BedInfo(depth=DEPTH, size=2.0))


@pytest.fixture(scope="module")
def wet():
    return _dataset(WaterSurface(LEVEL, N))


def _cfg(**kw):
    base = {"iterations": 10, "init_depth": DEPTH, "init_count": 150, "checkpoint_every": 0}
    return preset_config("smoke", **{**base, **kw})


# ---- masked loss
# --------------------------------------------------------------------------------------------
def _grads(ds: Dataset, **kw) -> tuple[dict, float]:
    """The gradient of every Gaussian parameter in the first training step, and that step's loss (`kw`: the
    Trainer's)."""
    tr = Trainer(_cfg(), ds, **kw)
    grads = {}
    for name in PARAM_NAMES:
        tr.splats[name].register_hook(lambda g, name=name: grads.__setitem__(name, g.clone()))
    loss = tr.train_step()["loss"]
    return grads, loss


def _one_view(ds: Dataset, rgb: torch.Tensor, mask) -> Dataset:
    v = ds.views[3]  # an oblique view
    return Dataset(ds.root, ds.water,
                   [View(v.name, "train", v.kind, v.camera, rgb, None, "", None, None, mask)], ds.bed)


def test_pixels_outside_the_mask_do_not_reach_the_loss(wet):
    rgb = wet.views[3].rgb
    h, w = rgb.shape[:2]
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[4:18, 2:15] = True  # SSIM windows straddle its edges
    base, loss = _grads(_one_view(wet, rgb, mask))
    assert set(base) == set(PARAM_NAMES)  # quats' is zero: a rotation changes nothing of the isotropic start
    assert all(bool(base[k].abs().sum() > 0) for k in ("means", "scales", "opacities", "sh0"))
    noise = torch.randint(0, 256, rgb.shape, generator=torch.Generator().manual_seed(1), dtype=torch.uint8)
    other, other_loss = _grads(_one_view(wet, torch.where(mask[..., None], rgb, noise), mask))
    # bit-identical: the loss zeroes (torch.where) and drops everything outside the mask, so both runs do the
    # same operations on the same numbers
    assert other_loss == loss
    for name in PARAM_NAMES:
        assert torch.equal(other[name], base[name]), name
    # one used pixel changed: the gradients change
    moved = rgb.clone()
    moved[10, 8] = 255 - moved[10, 8]
    changed, _ = _grads(_one_view(wet, moved, mask))
    assert not torch.equal(changed["means"], base["means"]) and not torch.equal(changed["sh0"], base["sh0"])
    # without the mask the noise is fitted too
    unmasked, _ = _grads(_one_view(wet, torch.where(mask[..., None], rgb, noise), None))
    assert not torch.equal(unmasked["means"], base["means"])


def test_a_mask_of_every_pixel_is_the_unmasked_loss(wet):
    rgb = wet.views[3].rgb
    every = torch.ones(rgb.shape[:2], dtype=torch.bool)
    (g_all, loss_all), (g_none, loss_none) = (_grads(_one_view(wet, rgb, m)) for m in (every, None))
    assert loss_all == pytest.approx(loss_none, rel=1e-6)
    for name in PARAM_NAMES:
        assert torch.allclose(g_all[name], g_none[name], rtol=1e-4, atol=1e-9), name


def test_masked_psnr_counts_used_pixels_only(wet):
    rgb = wet.views[3].rgb
    mask = torch.zeros(rgb.shape[:2], dtype=torch.bool)
    mask[:, :12] = True
    tr = Trainer(_cfg(), _one_view(wet, rgb, mask))
    with torch.no_grad():
        img = tr.render(tr.views[0].camera)[0]
    mse = float(((img - tr.targets[0])[mask] ** 2).mean())
    assert tr.train_step()["psnr"] == pytest.approx(-10 * torch.log10(torch.tensor(mse)).item(), rel=1e-4)


# ---- configuration
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kw, match", [
    ({"water_n": 0.99}, "water_n"), ({"water_n": float("nan")}, "water_n"),
                                       ({"water_level": float("inf")}, "finite"),
    ({"optimize_water": "n"}, "optimize_water"),
                                       ({"optimize_water": "level", "variant": "3dgs"}, "never refracts"),
    ({"lr_water_level": 0.0}, "lr_water_level"), ({"lr_water_n": -1e-4}, "lr_water_n"),
    ({"water_warmup": 1.0}, "water_warmup"), ({"water_warmup": -0.1}, "water_warmup")])
def test_config_refuses(kw, match):
    with pytest.raises(ConfigError, match=match):
        _cfg(**kw)


def test_the_dataset_decides_what_can_be_overridden(wet):
    dry = Dataset(wet.root, None, wet.views, wet.bed)
    with pytest.raises(ConfigError, match="no water; give its level .* to calibrate"):
        Trainer(_cfg(optimize_water="level"), dry)
    with pytest.raises(ConfigError, match="no water; give its level .* to set n"):
        Trainer(_cfg(water_n=1.34), dry)
    with pytest.raises(ConfigError, match="not below every training camera"):
        Trainer(_cfg(water_level=LEVEL + 1.5), wet)
    # a level given to a dry dataset adds the water (n: 1.33 unless given), and the transform with it
    tr = Trainer(_cfg(water_level=LEVEL), dry)
    assert tr.water == WaterSurface(LEVEL, 1.33) and tr.flags is not None
    assert Trainer(_cfg(), dry).flags is None


def test_overridden_water_is_the_one_used_everywhere(wet):
    level, n = LEVEL - 0.3, 1.2
    tr = Trainer(_cfg(water_level=level, water_n=n), wet)
    assert tr.water == WaterSurface(level, n)
    # the grid lies init_depth below the overridden level ...
    assert torch.allclose(tr.splats["means"][:, 2].detach(), torch.tensor(level - DEPTH))
    # ... and the render goes through the overridden water
    cam = wet.views[2].camera
    center = torch.tensor(cam.camera_center, dtype=torch.float32)
    s = tr.splats
    with torch.no_grad():
        scales, quats, opac = activated(s)
        a = refract_gaussians(s["means"], scales, quats, opac,
                              colors_for_view(s, center, tr.active_sh_degree), center, WaterSurface(level, n))
        want, _, _, _ = rasterize(a.means, a.quats, a.scales, a.opacities, a.colors, cam, tr.background)
    # the same operations as tr.render (degree 0: no SH kernel; full's flags are the defaults): bit-identical
    assert torch.equal(tr.render(cam)[0], want.clamp(0, 1))


# ---- calibration
# ------------------------------------------------------------------------------------------------
def test_frozen_water_trains_as_without_calibration(wet):
    """During the warm-up the run is the uncalibrated one, bit for bit; after it the water moves."""
    def run(**kw):
        tr = Trainer(_cfg(iterations=20, **kw), wet)
        losses = [tr.train_step()["loss"] for _ in range(8)]
        return tr, losses

    plain, plain_losses = run()
    frozen, frozen_losses = run(optimize_water="level+n", water_warmup=0.5)  # water frozen to step 10
    # bit for bit: while frozen the water is the same Python floats (a float64 round trip), the same graph
    assert frozen_losses == plain_losses
    for k in plain.splats:
        assert torch.equal(frozen.splats[k], plain.splats[k]), k
    assert frozen.water == plain.water == wet.water
    moving, moving_losses = run(optimize_water="level+n", water_warmup=0.0)
    # step 1 renders the start water, but as float64 leaves: round-off: different graphs
    assert moving_losses[0] == pytest.approx(plain_losses[0], rel=1e-6, abs=0)
    assert moving_losses[1:] != plain_losses[1:]
    assert moving.water.level != LEVEL and moving.water.n != N


def test_index_stays_at_or_above_one():
    # clear water (n = 1 in the images) and a start just above it with a large step: Adam overshoots 1
    ds = _dataset(WaterSurface(LEVEL, 1.0))
    tr = Trainer(_cfg(optimize_water="level+n", water_n=1.02, lr_water_n=0.05, water_warmup=0.0), ds)
    seen = []
    for _ in range(10):
        tr.train_step()
        seen.append(tr.water.n)
    assert min(seen) == 1.0  # clamp_(min=1.0): exactly 1


def test_checkpoint_restores_the_water_and_its_optimiser(wet, tmp_path):
    cfg = _cfg(iterations=12, checkpoint_every=4, optimize_water="level+n", water_level=LEVEL + 0.05,
               water_n=1.3, water_warmup=0.25)
    a = Trainer(cfg, wet, tmp_path / "a")
    stats = a.train()
    assert stats["water"] == {"level": a.water.level, "n": a.water.n}
    assert a.water.level != LEVEL + 0.05 and a.water.n != 1.3  # it moved
    meta = json.loads((tmp_path / "a/config.json").read_text())
    assert meta["water"] == {"level": LEVEL + 0.05, "n": 1.3} and meta["water_final"] == stats["water"]
    assert meta["config"]["optimize_water"] == "level+n" and meta["config"]["water_start_scaled"] == 3
    assert json.loads((tmp_path / "a/train_stats.json").read_text())["water"] == stats["water"]
    # interrupted after 10 steps, resumed from the checkpoint at 8
    b = Trainer(cfg, wet, tmp_path / "b")
    for _ in range(10):
        b.train_step()
        if b.step % 4 == 0:
            b.save_checkpoint()
    c = Trainer(cfg, wet, tmp_path / "b")
    assert c.step == 8 and c.water != Trainer(cfg, wet).water  # not the start: the checkpoint's water
    c.train()
    # resumed: the same steps on the same state (checkpoint lossless), one process: bit-identical
    assert c.water == a.water
    for k in a.splats:
        assert torch.equal(a.splats[k], c.splats[k]), k


@pytest.mark.parametrize("offset", [0.05, -0.05])
def test_calibration_moves_a_wrong_level_towards_the_truth(offset):
    """A bed rendered under water at a known level; training starts with the level 5 cm off (either side).
    Once the Gaussians have settled (warm-up, half the run) the level must close most of the gap. Measured:
    +5 cm ends at -1.2 cm, -5 cm at +1.5 cm after 300 steps (the level overshoots while the bed, fitted to
    the wrong level during the warm-up, re-settles). Densification is off: in this 400-Gaussian toy its
    clones follow the level along the level-depth trade-off (raising the level by dz and lowering the bed by
    (n - 1) dz leaves a nadir image unchanged) and the level drifts."""
    ds = _dataset(WaterSurface(LEVEL, N), size=48, views=8, count=400)
    cfg = _cfg(iterations=300, init_count=400, water_level=LEVEL + offset, optimize_water="level",
               water_warmup=0.5, densify=NO_DENSIFY)
    tr = Trainer(cfg, ds)
    tr.train()
    assert abs(tr.water.level - LEVEL) < 0.5 * abs(offset), tr.water


def test_cli_water_arguments(tmp_path, capsys):
    scene = bed_scene(200, 1.0, DEPTH, seed=0)
    views = render_views(scene, ring_cameras(3, 16, 1.5, 0.8, target=(0, 0, -DEPTH)), WaterSurface(0.0, N))
    data = write_dataset(tmp_path / "data", views, WaterSurface(0.0, N), bed={"depth": DEPTH})
    args = ["train", "--data", str(data), "--preset", "smoke", "--iterations", "3", "--no-progress"]
    out = tmp_path / "run"
    assert (main([*args, "--out", str(out), "--water-level", "-0.05", "--n", "1.34", "--optimize-water",
                  "level"]) == 0)
    meta = json.loads((out / "config.json").read_text())
    assert (meta["config"]["water_level"], meta["config"]["water_n"], meta["config"]["optimize_water"]) == \
        (-0.05, 1.34, "level")
    assert meta["water"] == {"level": -0.05, "n": 1.34} and meta["water_final"]["n"] == 1.34
    for bad in (["--n", "0.9"], ["--water-level", "nan"], ["--optimize-water", "n"]):
        with pytest.raises(SystemExit) as done:  # argparse: usage, the option named, exit 2
            main([*args, "--out", str(tmp_path / "bad"), *bad])
        assert done.value.code == 2
        assert bad[0] in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


# ---- each view through its own surface (`Trainer.view_ripples`: the ripples' bound)
# --------------------------------------------------------------------------------------------
def test_a_flat_surface_per_view_trains_as_the_shared_one(wet):
    asked = []

    def flat(name, xy):
        asked.append((name, len(xy)))
        return torch.zeros_like(xy)

    base, loss = _grads(wet)
    same, same_loss = _grads(wet, view_ripples=flat)
    # the means minus zero offsets: the same numbers rendered; the gradient reaches the means through one more
    # node (round-off at most)
    assert same_loss == loss
    for name in PARAM_NAMES:
        assert torch.allclose(same[name], base[name], rtol=1e-6, atol=1e-12), name
    assert len(asked) == 1 and asked[0][0] in {v.name for v in wet.views}  # the trained view's own surface
    assert 0 < asked[0][1] <= 150  # at the submerged Gaussians' crossings


def test_a_rippled_view_moves_what_it_shows(wet):
    def tilted(name, xy):  # one view's surface tilted, the others flat
        return torch.tensor([0.05, 0.0]).expand_as(xy) if name == "0000" else torch.zeros_like(xy)

    tr = Trainer(_cfg(), wet, view_ripples=tilted)
    flat = Trainer(_cfg(), wet)
    i = [v.name for v in wet.views].index("0000")
    water = tr.water
    shown = rippled(tr.splats, tr.centers[i], water, lambda xy: tilted("0000", xy))["means"]
    moved = (shown - tr.splats["means"]).detach()
    wet_ones = water.depth(tr.splats["means"]) > 0
    # a facet rising along +x turns the rays towards +x (an oblique ray a little across too): the photo
    # shows the bed moved by +offset, so the render moves the Gaussians back, along -x, never up or down
    assert (moved[wet_ones, 0] < 0).all() and (moved[wet_ones, 1].abs() < 0.2 * -moved[wet_ones, 0]).all()
    assert (moved[:, 2] == 0).all() and (moved[~wet_ones] == 0).all()
    # about what the facet bends a vertical ray by at their depth (d tan(a - b), a = atan 0.05, sin b = sin a
    # / n), more for an oblique ray that meets it in its plane of incidence
    a = math.atan(0.05)
    nadir = water.depth(tr.splats["means"])[wet_ones] * math.tan(a - math.asin(math.sin(a) / N))
    assert (-moved[wet_ones, 0] > 0.5 * nadir).all() and (-moved[wet_ones, 0] < 2 * nadir).all()
    j = (i + 1) % len(wet.views)
    other = rippled(tr.splats, tr.centers[j], water, lambda xy: tilted(wet.views[j].name, xy))["means"]
    assert torch.equal(other, tr.splats["means"])  # a flat view renders the Gaussians as they are
    assert torch.equal(flat.splats["means"], tr.splats["means"])


def test_a_surface_per_view_needs_a_horizontal_water(wet):
    tilted = Dataset(wet.root, WaterSurface(LEVEL, N, (0.01, 0.0)), wet.views, wet.bed)
    with pytest.raises(ConfigError, match="horizontal"):
        Trainer(_cfg(), tilted, view_ripples=lambda name, xy: torch.zeros_like(xy))
