import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch
from conftest import WATER, render_dataset

from ragsplat import rendering
from ragsplat.bench.synthetic import bed_scene, render_views, ring_cameras, write_dataset
from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.dataset import BedInfo, load_dataset
from ragsplat.errors import OutputError, TrainingDiverged
from ragsplat.gaussians import activated, colors_for_view
from ragsplat.ply import load_ply
from ragsplat.rasterize import rasterize
from ragsplat.rasterize_surfels import rasterize_surfels
from ragsplat.snell import footprint
from ragsplat.train import VARIANTS, TrainConfig, Trainer, preset_config
from ragsplat.train import trainer as train_mod
from ragsplat.train.strategy import PAPER_ITERATIONS, DensifyConfig
from ragsplat.water_surface import WaterSurface

REGION = {"xmin": -0.8, "xmax": 0.8, "ymin": -0.8, "ymax": 0.8}


def _tiny(root, water=WATER, size=20):
    cams = ring_cameras(5, size, 1.5, 0.8, target=(0, 0, -1))
    return render_dataset(root, bed_scene(300, 1.0, 1.0, seed=2), cams, water, 1, REGION)


@pytest.fixture(scope="module")
def wet(tmp_path_factory):
    return load_dataset(_tiny(tmp_path_factory.mktemp("wet")))


def _cfg(**kw):
    base = {"iterations": 12, "init_depth": 1.0, "init_count": 120, "checkpoint_every": 0}
    base.update(kw)
    return preset_config("smoke", **base)


def test_variants_and_config_errors():
    assert list(VARIANTS) == ["3dgs", "position", "position+scale", "position+opacity", "full",
                              "full+anisotropic", "full+color", "2dgs", "2dgs+full", "2dgs+full+attenuation",
                              "2dgs+full+backscatter", "2dgs+full+reflection", "2dgs+full+water"]
    assert VARIANTS["2dgs"] is None and VARIANTS["2dgs+full"]["scale"] == "anisotropic"
    assert _cfg(variant="2dgs").surfels and not _cfg(variant="full").surfels
    assert VARIANTS["3dgs"] is None
    assert VARIANTS["full"] == {"position": True, "scale": "isotropic", "opacity": True, "color": False}
    assert VARIANTS["full+anisotropic"]["scale"] == "anisotropic" and VARIANTS["full+color"]["color"]
    with pytest.raises(ValueError, match="unknown variant"):
        _cfg(variant="nope")
    with pytest.raises(ValueError, match="unknown preset"):
        preset_config("huge")
    with pytest.raises(ValueError, match="init_points"):
        _cfg(init="points")


def test_schedules_scale_with_iterations():
    cfg = preset_config("small", iterations=3000)
    assert cfg.schedule.refine_start_iter == 50 and cfg.schedule.reset_every == 300 and cfg.sh_every == 100
    tr_lr = Trainer.means_lr

    class Fake:  # means_lr only reads cfg and scene_scale
        scene_scale = 2.0

    Fake.cfg = cfg
    assert tr_lr(Fake, 0) == pytest.approx(2.0 * cfg.lr_means)
    assert tr_lr(Fake, 3000) == pytest.approx(2.0 * cfg.lr_means_final)
    assert tr_lr(Fake, 1500) == pytest.approx(2.0 * math.sqrt(cfg.lr_means * cfg.lr_means_final))


def test_a_given_scene_scale_replaces_the_cameras_extent(wet):
    """`scene_scale` (m) is what the position rate and the densification's thresholds scale with; None: the
    training cameras' extent, as 3DGS. A scale that is not a positive length is refused."""
    assert Trainer(_cfg(), wet).scene_scale == pytest.approx(wet.camera_extent(), rel=1e-12)
    given = Trainer(_cfg(scene_scale=7.5), wet)
    assert given.scene_scale == 7.5 and given.strat_state["scene_scale"] == 7.5
    assert given.means_lr(0) == pytest.approx(7.5 * given.cfg.lr_means, rel=1e-12)
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(ValueError, match="scene_scale"):
            _cfg(scene_scale=bad)


def test_footprint_through_water():
    cam = Camera.look_at([0.0, 0.0, 2.0], [0.0, 0.0, -1.0], 10, 10, 90.0)  # corner rays at 54.7 deg
    theta = math.atan(math.sqrt(2))  # corner ray angle from the vertical
    for water, expect in [(None, 3.0 * math.tan(theta)),
                          (WATER, 2.0 * math.tan(theta) + math.tan(math.asin(math.sin(theta) / 1.33)))]:
        box = footprint([cam], water, -1.0)
        assert np.allclose(box, [-expect / math.sqrt(2), expect / math.sqrt(2)] * 2, atol=1e-9)


def test_grid_init_at_bed_depth(wet):
    tr = Trainer(_cfg(init_depth=0.7), wet)
    m = tr.splats["means"].detach()
    assert torch.allclose(m[:, 2], torch.tensor(-0.7))
    # a regular grid filling what the training views see of the plane z = -0.7
    box = footprint([v.camera for v in wet.train], wet.water, -0.7)
    step_x, step_y = (float(m[:, k].unique().diff().mean()) for k in (0, 1))
    assert float(m[:, 0].min()) == pytest.approx(box[0] + step_x / 2, rel=1e-4)
    assert float(m[:, 1].max()) == pytest.approx(box[3] - step_y / 2, rel=1e-4)
    assert abs(tr.num_gaussians - 120) <= 30
    with pytest.raises(ValueError, match="bed depth"):
        Trainer(_cfg(init_depth=None), wet)
    # as datagen writes it: the depth, and a bed size that clips the grid
    generated = dataclasses.replace(wet, bed=BedInfo(depth=0.6, size=1.0))
    m = Trainer(_cfg(init_depth=None), generated).splats["means"].detach()
    assert torch.allclose(m[:, 2], torch.tensor(-0.6)) and float(m[:, :2].abs().max()) < 0.5


def test_points_init(wet, tmp_path):
    pts = np.array([[0.0, 0.0, -0.5, 1, 0, 0], [0.2, 0.0, -0.6, 0, 1, 0], [0.0, 0.3, -0.4, 0, 0, 1]])
    np.save(tmp_path / "pc.npy", pts)
    tr = Trainer(_cfg(init="points", init_points=str(tmp_path / "pc.npy")), wet)
    assert torch.allclose(tr.splats["means"][:, 2].detach(),
                          torch.tensor(pts[:, 2] * 1.33, dtype=torch.float32))


def test_points_init_fills_the_gaps_of_the_points(wet, tmp_path):
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (3000, 2))
    xy = xy[np.abs(xy[:, 0]) > 0.15]  # a 0.3 m strip without points
    np.save(tmp_path / "pc.npy", np.column_stack([xy, np.full(len(xy), -0.5), np.full((len(xy), 3), 0.5)]))
    plain = Trainer(_cfg(init="points", init_points=str(tmp_path / "pc.npy"), init_count=5000), wet)
    filled = Trainer(_cfg(init="points", init_points=str(tmp_path / "pc.npy"), init_count=5000,
                          init_fill=0.08), wet)
    extra = filled.splats["means"].detach()[plain.num_gaussians:]
    assert plain.num_gaussians == len(xy) and len(extra) > 0
    assert float(extra[:, 0].abs().max()) < 0.15 and torch.allclose(extra[:, 2], torch.tensor(-0.5 * 1.33))
    with pytest.raises(ValueError, match="init_fill"):
        _cfg(init_fill=0.1)  # the grid start has no gaps to fill
    with pytest.raises(ValueError, match="init_fill"):
        _cfg(init="points", init_points="x.npy", init_fill=-1.0)


def test_points_init_keeps_a_seeded_subset_of_a_large_cloud(wet, tmp_path):
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(-0.6, -0.4, 50),
                           rng.uniform(0, 1, (50, 3))])
    np.save(tmp_path / "pc.npy", pts)
    runs = [Trainer(_cfg(init="points", init_points=str(tmp_path / "pc.npy"), init_count=20, seed=s), wet)
            for s in (0, 0, 1)]
    means = [tr.splats["means"].detach() for tr in runs]
    assert (means[0].shape == (20, 3) and torch.equal(means[0], means[1])
            and not torch.equal(means[0], means[2]))
    known = {tuple(np.round(p, 5)) for p in pts[:, :2]}
    # points of the cloud
    assert all(tuple(np.round(m, 5)) in known for m in means[0][:, :2].double().numpy())


def test_dry_scene_never_calls_refraction(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("refract_gaussians called for a scene without water")

    monkeypatch.setattr(rendering, "refract_gaussians", boom)
    dry = load_dataset(_tiny(tmp_path / "dry", water=None))
    tr = Trainer(_cfg(variant="full", iterations=3), dry)
    assert tr.flags is None
    tr.train()
    identity = load_dataset(_tiny(tmp_path / "n1", water=WaterSurface(0.0, 1.0)))
    Trainer(_cfg(variant="full", iterations=2), identity).train()


def test_variant_3dgs_skips_refraction(wet, monkeypatch):
    calls = []
    real = rendering.refract_gaussians
    monkeypatch.setattr(rendering, "refract_gaussians", lambda *a, **k: calls.append(k) or real(*a, **k))
    Trainer(_cfg(variant="3dgs", iterations=2), wet).train()
    assert calls == []
    Trainer(_cfg(variant="position+opacity", iterations=2), wet).train()
    # the trainer checks its cameras above the water itself, at the start and after each move of it
    assert calls == [{**VARIANTS["position+opacity"], "covariances": True, "check_camera": False}] * 2
    calls.clear()  # surfels take the refracted tangents, never apparent covariances
    Trainer(_cfg(variant="2dgs+full", iterations=1), wet).train()
    assert calls == [{**VARIANTS["2dgs+full"], "covariances": False, "check_camera": False}]


@pytest.mark.parametrize("variant", ["full", "full+color", "full+anisotropic"])
def test_render_without_interface_is_the_true_scene(wet, variant):
    tr = Trainer(_cfg(variant=variant, iterations=2), wet)
    tr.train()
    cam = wet.test[0].camera
    center = torch.tensor(cam.camera_center, dtype=torch.float32)
    scales, quats, opac = activated(tr.splats)
    with torch.no_grad():
        want, _, _, _ = rasterize(tr.splats["means"], quats, scales, opac,
                                  colors_for_view(tr.splats, center, tr.active_sh_degree), cam, tr.background)
    img, _, _ = tr.render(cam, interface=False)
    assert torch.allclose(img, want.clamp(0, 1))
    wet_img, _, _ = tr.render(cam, interface=True)
    assert (wet_img - img).abs().max() > 1e-3
    if variant == "full+color":  # darkened through the water on top of opacity (1 / n^2 in linear light)
        assert float(wet_img.mean()) < float(img.mean())


def test_surfels_keep_no_thickness_through_splits(wet):
    # grow_scale3d 0: every Gaussian with a gradient counts as large and is split at the refinement (step 10)
    densify = DensifyConfig(refine_start_iter=0, refine_stop_iter=PAPER_ITERATIONS,
                            reset_every=PAPER_ITERATIONS, grow_grad2d=0.0, grow_scale3d=0.0)
    tr = Trainer(_cfg(variant="2dgs+full", densify=densify), wet)
    n0 = tr.num_gaussians
    tr.train()
    assert tr.num_gaussians > n0  # splits happened (a split divides all three scales by 1.6)
    assert torch.allclose(tr.splats["scales"][:, 2].exp(), torch.tensor(train_mod.SURFEL_THICKNESS))


def test_surfel_variants_render_surfels_and_map_their_tangents(wet):
    tr = Trainer(_cfg(variant="2dgs+full", iterations=2), wet)
    assert float(tr.splats["scales"][:, 2].detach().exp().max()) == pytest.approx(train_mod.SURFEL_THICKNESS)
    tr.train()
    cam = wet.test[0].camera
    center = torch.tensor(cam.camera_center, dtype=torch.float32)
    scales, quats, opac = activated(tr.splats)
    colors = colors_for_view(tr.splats, center, tr.active_sh_degree)
    with torch.no_grad():
        want, _, _, _ = rasterize_surfels(tr.splats["means"], quats, scales[:, :2], opac, colors, cam,
                                          tr.background)
    img, _, _ = tr.render(cam, interface=False)  # the true surfels
    assert torch.allclose(img, want.clamp(0, 1))
    # Through water of n = 1 the apparent surfels are the true ones (J = I): the pinhole render
    args = (tr.splats, cam, center, tr.active_sh_degree, WaterSurface(level=WATER.level, n=1.0), tr.flags,
            True, tr.background, "cpu")
    with torch.no_grad():
        torch.testing.assert_close(rendering.render_splats(*args)[0], want)
        wet_img = rendering.render_splats(*args[:4], WATER, *args[5:])[0]
    assert (wet_img - want).abs().max() > 1e-3


def test_surfel_geometry_terms_switch_on_after_their_fractions(wet):
    cfg = _cfg(variant="2dgs+full", iterations=10, distortion_from=0.3, normal_from=0.6)
    tr = Trainer(cfg, wet)
    cam, center = tr.views[0].camera, tr.centers[0]
    with torch.no_grad():
        _, _, depth, meta = tr._render(cam, center, True, tr.water)
        terms = [float(train_mod.surfel_loss(cfg, cam, depth, meta, None, step)) for step in (3, 4, 7)]
    assert terms[0] == 0 and terms[1] > 0 and terms[2] > terms[1]


def test_outputs_resume_and_determinism(wet, tmp_path):
    cfg = _cfg(variant="full", iterations=14, checkpoint_every=5)
    a = Trainer(cfg, wet, tmp_path / "a")
    stats = a.train()
    assert stats["iterations"] == 14 and stats["num_gaussians"] == a.num_gaussians
    meta = json.loads((tmp_path / "a/config.json").read_text())
    assert meta["config"]["seed"] == 0 and meta["config"]["variant"] == "full"
    assert meta["refraction_applied"] == VARIANTS["full"] and "torch" in meta["versions"]
    assert TrainConfig.from_dict(meta["config"]) == cfg
    ply = load_ply(tmp_path / "a/point_cloud.ply")
    for k, v in ply.items():
        assert torch.equal(v, a.splats[k].detach()), k  # float32 written and read back: lossless
    # interrupted after 9 steps (checkpoint at 5 plus 4 lost steps), rerun from the checkpoint
    b = Trainer(cfg, wet, tmp_path / "b")
    for _ in range(9):
        b.train_step()
        if b.step % 5 == 0:
            b.save_checkpoint()
    c = Trainer(cfg, wet, tmp_path / "b")
    assert c.step == 5
    c.train()
    for k in a.splats:  # resumed: the same steps on the same state (checkpoint lossless), one process
        assert torch.equal(a.splats[k], c.splats[k]), k
    with pytest.raises(OutputError, match="different settings .*seed"):
        Trainer(_cfg(variant="full", iterations=14, checkpoint_every=5, seed=1), wet, tmp_path / "a")
    # how the run executes is not what it computes: those settings resume
    assert (Trainer(dataclasses.replace(cfg, checkpoint_every=7, compile_refraction=True), wet,
                    tmp_path / "a").step == 14)


def test_callbacks_at_eval_steps(wet):
    seen = []
    tr = Trainer(_cfg(iterations=9), wet)
    tr.train(callbacks=[lambda t, s: seen.append((s, t.elapsed, t.num_gaussians))], eval_steps=[3, 6, 50])
    assert [s for s, _, _ in seen] == [3, 6, 9]
    assert seen[0][1] > 0 and seen[0][1] <= seen[1][1] <= seen[2][1] == tr.elapsed


def test_nan_is_reported_with_iteration_and_parameter(wet):
    tr = Trainer(_cfg(iterations=5), wet)
    tr.train_step()
    tr.splats["scales"].register_hook(lambda g: g * float("nan") if tr.step == 2 else g)
    with pytest.raises(TrainingDiverged, match=r"iteration 2: non-finite gradient of parameter 'scales'"):
        tr.train_step()
    tr = Trainer(_cfg(iterations=5), wet)
    tr.train_step()
    with torch.no_grad():
        tr.splats["sh0"][:, 0, 0] = float("inf")  # every Gaussian: whichever the next view sees
    with pytest.raises(TrainingDiverged, match=r"iteration 2: loss is .* parameter 'sh0' \(\d+ of"):
        tr.train_step()
    tr = Trainer(_cfg(iterations=5), wet)
    with torch.no_grad():
        tr.splats["quats"][0] = float("nan")  # off screen or not: caught after the step
    with pytest.raises(TrainingDiverged, match=r"iteration 1: .*parameter 'quats'"):
        tr.train_step()


def test_cli_train(wet, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--data", str(wet.root), "--out", str(out), "--preset", "smoke", "--iterations", "3",
            "--variant", "position", "--init-depth", "1.0", "--no-progress", "--seed", "3"]
    assert main(args) == 0
    assert json.loads((out / "config.json").read_text())["config"]["seed"] == 3
    assert (out / "point_cloud.ply").exists() and (out / "ckpt.pt").exists()
    assert main(args) == 0  # finished run: resumes at the end, nothing to do
    assert main(["train", "--data", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert main(args[:-2] + ["--seed", "4"]) == 2  # the checkpoint was written with other settings
    few = tmp_path / "few"  # a start thinned to a seeded subset of the points
    points = tmp_path / "points.npy"
    np.save(points, np.random.default_rng(0).uniform(-0.5, 0.5, (300, 3)) - [0, 0, 1.0])
    assert main(["train", "--data", str(wet.root), "--out", str(few), "--preset", "smoke", "--iterations",
                 "1",
                 "--init", "points", "--init-points", str(points), "--init-count", "50",
                 "--no-progress"]) == 0
    assert json.loads((few / "config.json").read_text())["config"]["init_count"] == 50
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == f"resumed from step 3 of 3 ({out})"
    assert len(err) == 3 and "does not exist" in err[1] and "different settings" in err[2]


def test_refraction_aware_training_recovers_depth(tmp_path):
    """End to end: a textured bed 2 m under water, 10 oblique views; every run starts from a flat grid half
    way between the apparent depth (d / n) and the true depth, 24.8 cm above the bed. The refraction-aware
    variants must bring the bed to its true depth (the mean absolute height error falls below a third of the
    start's), the unaware ones must rise towards the apparent bed instead, and all must fit the images better
    than at the start.

    The run isolates the geometry from the 3DGS schedule, which squeezed into a short run cannot move a bed
    24.8 cm (`smoke` at 120 steps: `full` ended at +22.4 cm, `2dgs+full` at +24.6): its position rate decays
    1000x (at most about 8 cm of travel in 120 steps), opacities are reset every 12 steps while densification
    runs, and the faint grey start (opacity 0.1, colour rate 2.5e-3) builds slowly the texture that the depth
    gradient locks on to. Here: a constant position rate, no densification, a denser and more opaque start, a
    faster colour rate. Measured (seed 0), bias / mean |error| after 100 steps from +24.8 / 24.8 cm: `full`
    +0.9 / 4.6, `2dgs+full` +1.7 / 3.5, `3dgs` +40.0 / 43.1, `2dgs` +42.2 / 42.6; with `smoke`'s position
    rate instead (1.6e-3 decaying to 1.6e-6) `full` ends at +21.8."""
    d, half = 2.0, 1.5
    views = render_views(bed_scene(1500, half, d, seed=0), ring_cameras(10, 64, 1.5, 2.5, target=(0, 0, -d)),
                         WATER)
    for i, v in enumerate(views):
        v["split"] = "test" if i % 4 == 3 else "train"
    region = {"xmin": -1, "xmax": 1, "ymin": -1, "ymax": 1}
    ds = load_dataset(write_dataset(tmp_path / "e2e", views, WATER, region,
                                    bed={"depth": d, "size": 2 * half}))

    def bed_error(tr):  # opacity-weighted (signed mean, mean absolute) height error over the central region
        m = tr.splats["means"].detach()
        dz = m[:, 2] - (-d + 0.1 * d * torch.sin(2.0 * m[:, 0] / half) * torch.cos(1.5 * m[:, 1] / half))
        w = torch.sigmoid(tr.splats["opacities"].detach()) * ((m[:, 0].abs() < 1) & (m[:, 1].abs() < 1))
        return float((dz * w).sum() / w.sum()), float((dz.abs() * w).sum() / w.sum())

    apparent = d - d / WATER.n  # the apparent bed's height above the true one (0.496 m)
    err, fit = {}, {}
    for variant in ("3dgs", "full", "2dgs", "2dgs+full"):
        cfg = preset_config("smoke", variant=variant, iterations=100, init_depth=(d + d / WATER.n) / 2,
                            init_count=1000, init_opacity=0.5, lr_means=5e-3, lr_means_final=5e-3,
                            lr_sh0=1e-2,
                            densify=DensifyConfig(refine_stop_iter=0))  # no growth, pruning or resets
        tr = Trainer(cfg, ds)
        start = bed_error(tr)
        hist = []
        tr.train(on_step=lambda t, hist=hist: hist.append(t.last["psnr"]))  # the loss has geometry terms too
        err[variant] = bed_error(tr)
        fit[variant] = (np.mean(hist[:10]), np.mean(hist[-10:]))
        assert fit[variant][1] > fit[variant][0] + 1.0, (variant, fit)
    assert start[0] == pytest.approx(apparent / 2, abs=0.02)  # above the bed to begin with
    for variant in ("full", "2dgs+full"):  # recovered: the bias and the bed's shape (|bias| <= mean |dz|)
        assert err[variant][1] < start[1] / 3, (start, err)
    for variant in ("3dgs", "2dgs"):  # pulled up towards the apparent bed, a third of the way at least
        assert (err[variant][0] > start[0] + (apparent - start[0]) / 3
                and err[variant][1] > start[1]), (start, err)


def test_sigint_checkpoints_finished_steps_and_resume_says_so(evaluable_dataset, tmp_path):
    """A real Ctrl-C to a training process: one line, exit 130, a checkpoint of whole steps; the rerun
    resumes from it and says so."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "ragsplat.cli.main", "train", "--data", str(evaluable_dataset), "--out",
           str(out), "--preset", "smoke", "--iterations", "100000", "--checkpoint-every", "0",
           "--no-progress"]

    log = tmp_path / "stderr.txt"

    def interrupt_after(condition):
        with open(log, "w") as err:
            proc = subprocess.Popen(cmd, stderr=err, stdout=subprocess.DEVNULL)
            deadline = time.time() + 120
            while not condition() and time.time() < deadline and proc.poll() is None:
                time.sleep(0.2)
            time.sleep(1.0)  # some steps
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=120)
        return proc.returncode, log.read_text().strip().splitlines()

    code, err = interrupt_after(lambda: (out / "config.json").exists())
    assert code == 130 and len(err) == 1 and "interrupted" in err[0], err
    step = torch.load(out / "ckpt.pt", weights_only=True)["step"]
    assert 0 < step < 100000
    code, err = interrupt_after(lambda: "resumed" in log.read_text())
    assert code == 130 and err[0] == f"resumed from step {step} of 100000 ({out})", err
    assert torch.load(out / "ckpt.pt", weights_only=True)["step"] > step


def test_outputs_are_never_overwritten_or_mixed(wet, evaluable_dataset, tmp_path, capsys):
    args = ["--preset", "smoke", "--iterations", "2", "--init-depth", "1.0", "--no-progress"]
    foreign = tmp_path / "theirs"
    foreign.mkdir()
    (foreign / "config.json").write_text("someone else's")
    assert main(["train", "--data", str(wet.root), "--out", str(foreign), *args]) == 2
    assert ([p.name for p in foreign.iterdir()] == ["config.json"]
            and (foreign / "config.json").read_text() == "someone else's")
    run = tmp_path / "run"
    assert main(["train", "--data", str(wet.root), "--out", str(run), *args]) == 0
    before = (run / "config.json").read_text()
    assert main(["train", "--data", str(evaluable_dataset), "--out", str(run), *args]) == 2  # another dataset
    assert (run / "config.json").read_text() == before
    (run / "ckpt.pt").write_bytes(b"not a checkpoint")
    assert main(["train", "--data", str(wet.root), "--out", str(run), *args]) == 2
    assert (main(["ablation", "--data", str(evaluable_dataset), "--out", str(foreign), "--preset", "smoke"])
            == 2)
    assert (main(["train", "--data", str(wet.root), "--out", str(tmp_path / "new"), "--device", "tpu9",
                  *args]) == 2)
    assert (main(["train", "--data", str(wet.root), "--out", str(tmp_path / "g"), "--backend", "gsplat",
                  *args]) == 2)
    assert main(["ablation", "--data", str(evaluable_dataset), "--out", str(tmp_path / "a"), "--vgg16",
                 str(tmp_path / "nowhere.pth")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 7 and all(line.startswith("ragsplat ") for line in err)
    assert "not written by ragsplat" in err[0] and "another dataset" in err[1]
    assert "not a readable checkpoint" in err[2] and "not written by ragsplat" in err[3]
    assert ("unknown torch device 'tpu9'" in err[4] and "gsplat" in err[5]
            and "nowhere.pth: no such file" in err[6])
    assert not (tmp_path / "g" / "config.json").exists()  # refused before any work


def test_more_iterations_extend_a_finished_run(wet, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--data", str(wet.root), "--out", str(run), "--preset", "smoke", "--init-depth", "1.0",
            "--no-progress"]
    assert main([*args, "--iterations", "3"]) == 0
    capsys.readouterr()
    assert main([*args, "--iterations", "5"]) == 0
    assert "resumed from step 3 of 5, extended from 3 iterations" in capsys.readouterr().err
    assert torch.load(run / "ckpt.pt", weights_only=True)["step"] == 5
    assert main([*args, "--iterations", "4"]) == 2  # shorter than what is done: refused, named
    assert "different settings (iterations)" in capsys.readouterr().err


def test_a_checkpoint_is_refused_when_one_image_changed(wet, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(wet.root, data)
    run = tmp_path / "run"
    args = ["train", "--data", str(data), "--out", str(run), "--preset", "smoke", "--init-depth", "1.0",
            "--iterations", "2", "--no-progress"]
    assert main(args) == 0
    image = data / json.loads((data / "transforms.json").read_text())["frames"][0]["file_path"]
    image.write_bytes(image.read_bytes() + b"\0")  # same cameras and spec, other content
    capsys.readouterr()
    assert main(args) == 2
    assert "checkpoint of another dataset" in capsys.readouterr().err


def test_an_implausible_init_depth_is_refused_before_training(wet, tmp_path, capsys):
    args = ["train", "--data", str(wet.root), "--out", str(tmp_path / "run"), "--preset", "smoke",
            "--iterations", "2", "--no-progress"]
    assert main([*args, "--init-depth", "1e6"]) == 2  # e.g. millimetres typed as metres
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "init depth 1e+06 m is more than 10x the cameras' height" in err[0]
    assert not (tmp_path / "run" / "ckpt.pt").exists()


def test_pruning_sees_the_rendered_opacity_of_variants_that_fade_it(wet):
    """The trainer hands the strategy the water's opacity factor exactly when the variant renders submerged
    Gaussians fainter (the dead-zone fix, tested in test_strategy)."""
    for variant, fades in (("3dgs", False), ("position", False), ("full", True), ("position+opacity", True)):
        tr = Trainer(_cfg(variant=variant), wet)
        factor = tr.strategy.opacity_factor
        assert (factor is not None) == fades, variant
        if fades:
            deep = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
            torch.testing.assert_close(factor(deep), torch.tensor([1 / 1.33**2, 1.0]))


def test_triangulated_init_is_computed_once_per_dataset_content(tmp_path, monkeypatch):
    """init="triangulated" starts from `colmap.triangulate` of the training images (submerged depths x n),
    cached in the dataset with its fingerprint: a second run reuses it, changed content recomputes it."""
    from ragsplat.dataset import colmap

    calls = []

    def fake(root, work):
        calls.append(root)
        return np.array([[0.0, 0.0, -0.5, 1, 0, 0], [0.2, 0.0, -0.6, 0, 1, 0], [0.0, 0.3, 0.1, 0, 0, 1]]), \
            np.zeros((0, 4)), []

    monkeypatch.setattr(colmap, "triangulate", fake)
    ds = load_dataset(_tiny(tmp_path / "data"))
    m = [Trainer(_cfg(init="triangulated"), ds).splats["means"][:, 2].detach() for _ in range(2)]
    assert len(calls) == 1 and torch.equal(m[0], m[1])
    torch.testing.assert_close(m[0], torch.tensor([-0.5 * 1.33, -0.6 * 1.33, 0.1]))  # above the water: as is
    Trainer(_cfg(init="triangulated"), dataclasses.replace(ds, fingerprint="other"))
    assert len(calls) == 2


def test_refracted_init_intersects_the_tracks_through_the_water(tmp_path, monkeypatch):
    """init="refracted": the cached tracks' pixels, bent at the water, meet at the true points (the pixels
    here are exact: each true point seen through the water by every training camera); a point above the
    level keeps its straight-ray position."""
    from ragsplat.dataset import colmap
    from ragsplat.refraction import apparent_points

    ds = load_dataset(_tiny(tmp_path / "data"))
    true = np.array([[0.1, -0.2, -0.7], [-0.3, 0.25, -1.2], [0.2, 0.1, -0.05]])
    names = sorted(v.file_path for v in ds.train)
    obs = []
    for k, name in enumerate(names):
        cam = next(v.camera for v in ds.train if v.file_path == name)
        seen = apparent_points(torch.from_numpy(true), torch.from_numpy(cam.camera_center), WATER).numpy()
        px, _ = cam.project(seen)
        obs += [(i, k, *px[i]) for i in range(len(true))]
    straight = np.concatenate([true * [1, 1, 1 / WATER.n], np.full((3, 3), 0.5)], 1)  # apparent: z / n
    dry = np.array([[0.0, 0.0, 0.1, 0.5, 0.5, 0.5]])
    monkeypatch.setattr(colmap, "triangulate",
                        lambda root, work: (np.concatenate([straight, dry]), np.array(obs), names))
    for robust in (False, True):  # exact rays: the robust intersection meets them there too
        means = Trainer(_cfg(init="refracted", init_robust=robust), ds).splats["means"]
        means = means.detach().double().numpy()
        np.testing.assert_allclose(means, np.concatenate([true, dry[:, :3]]), atol=1e-5)
    with pytest.raises(ValueError, match="init_robust"):
        _cfg(init="triangulated", init_robust=True)


class _HostReads(torch.overrides.TorchFunctionMode):
    """Where the code reads a value back from the tensors' device or copies one there from the host: on a
    GPU each of these waits for every kernel queued before it. Counted by (what, file:line) of the innermost
    ragsplat frame; the rasterizer's reference kernels (which gsplat replaces on a GPU) are left out."""

    READS = frozenset({"__bool__", "__float__", "__int__", "__index__", "item", "tolist", "numpy", "cpu",
                       "nonzero"})

    def __init__(self):
        super().__init__()
        self.sites: dict[tuple[str, str], int] = {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        copy = name in ("tensor", "as_tensor") and "device" in kwargs and not torch.is_tensor(args[0])
        if name in self.READS or copy:
            import traceback

            frames = [f for f in traceback.extract_stack()[:-1] if "ragsplat" in f.filename
                      and "/tests/" not in f.filename]
            # the view order is drawn on the host on every device (a CPU generator)
            if frames and frames[-1].name != "_next_view" and not any(
                    k in frames[-1].filename for k in ("reference/project", "reference/composite",
                                                       "reference/surfel_composite")):
                key = (name, f"{frames[-1].filename.rsplit('/', 1)[-1]}:{frames[-1].name}")
                self.sites[key] = self.sites.get(key, 0) + 1
        return func(*args, **kwargs)


@pytest.mark.parametrize("variant", ["full", "2dgs+full"])
def test_a_training_step_reads_the_device_twice(wet, variant):
    """A step between refinements waits for the device at two places only: the one read of its loss,
    PSNR and finiteness checks, and the search of the submerged rows; the views' matrices are copied to the
    device once, not per step (`Camera.tensor`)."""
    tr = Trainer(_cfg(variant=variant, iterations=20, backend="torch"), wet)
    for _ in range(len(tr.views)):  # every view once: its matrices made on the device
        tr.train_step()
    reads = _HostReads()
    with reads:
        for _ in range(4):
            tr.train_step()
    assert reads.sites == {("tolist", "trainer.py:_check_before_step"): 4,
                           ("__bool__", "refraction.py:_wet_rows"): 4}
