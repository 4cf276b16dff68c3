"""Generate a dataset: bed assets, Blender job, one render process, resume/shard, metadata merge.

`generate(spec, out, shard=(i, N))` is idempotent: it writes what is missing and never deletes. Views are
split round-robin between shards (view k belongs to shard k mod N); whichever run finds every file present
writes the merged metadata (transforms.json, COLMAP model, scene.json).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ragsplat.camera import Camera
from ragsplat.datagen import conditions, flight
from ragsplat.datagen.assets import write_bed_assets
from ragsplat.datagen.job import (
    Diffuse,
    Done,
    Intrinsics,
    Ready,
    Refraction,
    RenderJob,
    RenderSettings,
    Ripples,
    SceneObject,
    Task,
    Texture,
    Volume,
    event_json,
    parse_event,
)
from ragsplat.datagen.spec import CAMERAS, SceneSpec, validate
from ragsplat.datagen.survey import LENS, lens_polynomial, write_survey
from ragsplat.dataset import layout, rasters
from ragsplat.errors import ConfigError, OutputError, RagsplatError
from ragsplat.outputs import atomic_path, versions, write_json
from ragsplat.scoring import geometry_metrics, plane_scores, thresholds


@dataclass
class RenderStats:
    build_s: float = 0.0  # Blender start-up to scene ready (bed mesh, materials, device)
    device: str = ""
    done: list[Done] = field(default_factory=list)  # one per finished image

    @property
    def images(self) -> int:
        return len(self.done)

    @property
    def render_s(self) -> float:
        """Inside bpy.ops.render.render: Cycles sync + path tracing + Blender's file write."""
        return sum(e.render_s for e in self.done)

    def add(self, other: RenderStats) -> RenderStats:
        """Two renders' stats as one (two Blender start-ups; the device the first's)."""
        return RenderStats(self.build_s + other.build_s, self.device or other.device, self.done + other.done)


def passes_for(spec: SceneSpec) -> tuple[str, ...]:
    return layout.PASSES if spec.water is not None else ("dry", "depth")


def surveyed(spec: SceneSpec) -> bool:
    """Whether the dataset gets a survey (`ragsplat.datagen.survey`): wet photos of water."""
    return spec.water is not None and "wet" in passes_for(spec)


def radiance_factor(spec: SceneSpec) -> float:
    """Colour of the refraction BSDF: 1/n^2 (etendue: L_air = L_water / n^2) or 1 when switched off."""
    w = spec.water
    return 1.0 / w.n**2 if (w is not None and w.radiance_scale) else 1.0


def _prepare_out(spec: SceneSpec, out: Path) -> None:
    """Create `out` or check it holds this very spec; refuse anything else (nothing is ever deleted)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create output directory {out}: {err.strerror}") from None
    if not out.is_dir() or not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"output directory {out} is not writable")
    saved = out / "scene" / "spec.json"
    if saved.exists():
        if json.loads(saved.read_text()) != json.loads(json.dumps(spec.to_dict())):  # tuples -> lists
            raise OutputError(f"{out} holds a dataset made with another spec or seed "
                              f"(see {saved}); choose another --out")
    elif any(out.iterdir()):
        raise OutputError(f"{out} is not empty and holds no ragsplat generate; choose an empty or new --out")
    (out / "scene").mkdir(exist_ok=True)
    (out / "gt").mkdir(exist_ok=True)
    write_json(saved, spec.to_dict())


# Signals of a crash inside the renderer, not of a kill (the OOM killer's SIGKILL, the user's SIGINT /
# SIGTERM).
CRASH_SIGNALS = frozenset({signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT, signal.SIGILL, signal.SIGFPE})


class RendererCrashed(RagsplatError):
    """The Blender process died of a crash signal: worth a new process, which resumes from the kept images."""

    def __init__(self, message: str, signum: int, log: Path):
        super().__init__(message)
        self.signum, self.log = signum, log


def run_blender(job: RenderJob, workdir: Path, progress: Callable[[dict], None] | None = None) -> RenderStats:
    """Render `job` in one Blender (bpy) process; `progress(event)` is called after each finished image with
    the `Done` event as a dict (`ragsplat.datagen.job.event_json`)."""
    jobfile = workdir / f"job.{os.getpid()}.json"
    write_json(jobfile, job.to_json())
    stats = RenderStats()
    log_path = workdir / "blender.log"
    with open(log_path, "a") as log:
        proc = subprocess.Popen([sys.executable, "-m", "ragsplat.blender_scenes.render", str(jobfile)],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        try:
            for line in proc.stdout:
                event = parse_event(line)
                if event is None:
                    log.write(line)
                elif isinstance(event, Ready):
                    stats.device, stats.build_s = event.device, event.build_s
                else:
                    stats.done.append(event)
                    if progress is not None:
                        progress(event_json(event))
            code = proc.wait()
        finally:  # interrupted: stop the renderer too (its finished images are complete files) and tidy up
            if proc.poll() is None:
                proc.terminate()
                proc.wait()
            for stale in (jobfile, *workdir.parent.glob(f"**/.*.{proc.pid}.render")):  # this renderer's only
                stale.unlink(missing_ok=True)
    if code != 0:
        why = (f"killed by signal {-code}{' (out of memory?)' if code == -9 else ''}" if code < 0
               else f"exit {code}")
        message = (f"Blender render process failed ({why}); finished images are kept, rerun to resume; see "
                   f"{log_path}")
        if code < 0 and -code in CRASH_SIGNALS:
            raise RendererCrashed(message, -code, log_path)
        raise RagsplatError(message)
    return stats


def render_job(spec: SceneSpec, out: Path, cam: Camera, tasks: list[Task],
               lens: tuple[float, float] | None = None, ortho_scale: float | None = None) -> RenderJob:
    """The renderer's job for `tasks` seen by `cam`, through a lens with radial distortion `lens` (k1, k2)
    when given, or by an orthographic camera `ortho_scale` metres across (`Intrinsics`)."""
    texture = Texture(str(out / "scene" / "albedo.png"))
    objects = [SceneObject("bed", texture), SceneObject("floor", texture)]
    c = spec.conditions
    if spec.water is not None:
        reflect = c is not None and c.reflection
        objects.append(SceneObject("water", Refraction(spec.water.n, radiance_factor(spec), reflect)))
    ripples = None
    if c is not None:
        if c.turbid:
            objects.append(SceneObject("volume", Volume(*conditions.attenuation(c)), wet_only=True))
        if c.targets:
            objects += [SceneObject(f"target_{colour}", Diffuse(albedo))
                        for colour, albedo in zip(("black", "white"), conditions.TARGET_ALBEDO)]
        if c.rippled:
            k, amplitude = conditions.ripple_waves(c, spec.seed)
            # the mean surface the ripples ride on: level + sx x + sy y
            ripples = Ripples(k, amplitude, spec.level, spec.water.slope if spec.water.sloping else None)
    r = spec.render
    return RenderJob(
        geometry=str(out / "scene" / "geometry.npz"), objects=tuple(objects),
        water="water" if spec.water is not None else None, light=spec.light,
        render=RenderSettings(r.samples, r.device, r.threads, spec.seed, r.filter_width, r.depth_filter,
                              r.exposure),
        camera=Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                          lens_polynomial(cam, *lens) if lens else None, ortho_scale),
        tasks=tuple(tasks), ripples=ripples,
        glossy_bounces=1 if c is not None and c.reflection else 0)  # the mirror ray that sees sky and sun


def _task(spec: SceneSpec, kind: str, pose, out: Path) -> Task:
    """The renderer's task: pass `kind` of the view `pose`, written to `out`; a wet task of a rippled scene
    with its ripple phases (its own surface: the view's index seeds them)."""
    c = spec.conditions
    rippled = kind == "wet" and c is not None and c.rippled
    return Task(kind, pose.name, pose.camera.c2w_gl, str(out),
                conditions.ripple_phases(c, spec.seed, int(pose.name)) if rippled else None)


def ortho_grid(spec: SceneSpec) -> tuple[float, float, int, int]:
    """(west, north, width, height) of the orthographic truth (`layout.GT_ORTHO`): `layout.GT_GRID_STEP`
    pixels over the evaluated region, their centres on the step's multiples (the export grid's nodes in a
    dataset's own frame)."""
    step, region = layout.GT_GRID_STEP, flight.eval_region(spec)
    j0, j1 = math.ceil(region["xmin"] / step), math.floor(region["xmax"] / step)
    i0, i1 = math.ceil(region["ymin"] / step), math.floor(region["ymax"] / step)
    return (j0 - 0.5) * step, (i1 + 0.5) * step, j1 - j0 + 1, i1 - i0 + 1


# the orthographic camera's height above the water level: above every object of a scene, its clipping far off
ORTHO_ABOVE = 50.0


def ortho_job(spec: SceneSpec, out: Path) -> RenderJob:
    """The renderer's job for the orthographic truth: the dry pass straight down over `ortho_grid`."""
    west, north, width, height = ortho_grid(spec)
    step = layout.GT_GRID_STEP
    x, y = west + width * step / 2, north - height * step / 2
    c2w = ((1.0, 0.0, 0.0, x), (0.0, 1.0, 0.0, y), (0.0, 0.0, 1.0, spec.level + ORTHO_ABOVE),
           (0.0, 0.0, 0.0, 1.0))  # OpenGL axes: looking down -z, image up = north
    cam = Camera(width, height, 1.0, 1.0, width / 2, height / 2, np.eye(3), np.zeros(3))  # the size only
    task = Task("dry", "ortho", c2w, str(out / layout.GT_ORTHO))
    return render_job(spec, out, cam, [task], ortho_scale=max(width, height) * step)


def max_depth(spec: SceneSpec) -> float:
    """The depth that scale-free thresholds refer to: the reach's deepest pool, or the gravel bed's depth."""
    return spec.reach.max_depth if spec.reach is not None else spec.bed.depth


def null_models(spec: SceneSpec, gt: np.ndarray) -> dict:
    """Scores of trivial answers against the ground-truth grid [N, 3]: a flat plane at its median height, and
    at the wet region's mean depth. A benchmark on which these score well cannot tell bathymetries apart.
    Under a sloping surface the planes lie parallel to it, at the median and the mean depth below it ("z":
    their height at x = y = 0)."""
    depth = max_depth(spec)
    return {"max_depth_m": depth, "thresholds_m": thresholds(depth),
            "median_plane": _plane_scores(spec, gt, np.median, depth),
            "mean_depth_plane": _plane_scores(spec, gt, np.mean, depth)}


def _plane_scores(spec: SceneSpec, gt: np.ndarray, statistic, depth: float) -> dict:
    w = spec.water
    if w is None or not w.sloping:
        return plane_scores(gt, float(statistic(gt[:, 2])), depth)
    tilt = w.height(gt[:, :2]) - w.level  # the surface's rise above its height at x = y = 0
    z = float(statistic(gt[:, 2] - tilt))
    named = thresholds(depth)
    m = geometry_metrics(np.column_stack([gt[:, :2], z + tilt]), gt, tuple(named.values()))
    scores = {f"{k}_{name}": m[f"{k}@{t:g}"] for name, t in named.items()
              for k in ("precision", "recall", "f1")}
    return {"z": z, "chamfer": m["chamfer"], **scores}


def scene_metadata(spec: SceneSpec, poses, gt: np.ndarray) -> dict:
    region = flight.eval_region(spec)
    corners = np.array([[region[a], region[b]] for a in ("xmin", "xmax") for b in ("ymin", "ymax")])
    extra = {} if spec.conditions is None else {"conditions": conditions.figures(spec)}
    return layout.scene_json(
        spec.to_dict(), region,
        scene="bed" if spec.reach is None else "reach",
        null_models=null_models(spec, gt),
        seed=spec.seed,
        versions=versions("bpy"),
        water=layout.water_json(spec.water),
        radiance={"refraction_color": radiance_factor(spec),
                  "model": "1/n^2 (etendue)" if radiance_factor(spec) != 1.0 else "none"},
        flight={"footprint_m": list(flight.footprint(spec)), "spacing_m": list(flight.spacing(spec)),
                **({"camera": CAMERAS[spec.flight.camera].record(spec.flight.width)} if spec.flight.camera
                   else {}),
                "gsd_m": flight.gsd(spec), "nadir_views_at_eval_corners": int(
                    flight.nadir_views_covering(spec, corners).min()),
                "train_views": sum(p.split == "train" for p in poses),
                "test_views": sum(p.split == "test" for p in poses)},
        passes=list(passes_for(spec)),
        depth={"channel": layout.DEPTH_CHANNEL, "meaning": "z-depth (m) along the optical axis, dry scene",
               "no_hit": layout.NO_HIT},
        bed_grid_step_m=layout.GT_GRID_STEP,
        **extra,
    )


def _keep_stamp(path: Path, scene: dict) -> dict:
    """`scene` with the version stamp already in `path` when nothing else differs: a rerun that renders
    nothing leaves the dataset's content, and so its fingerprint and every result keyed on it, unchanged."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return scene
    new = json.loads(json.dumps(scene))  # as it reads back (tuples become lists)
    same = ({k: v for k, v in old.items() if k != "versions"}
            == {k: v for k, v in new.items() if k != "versions"})
    return {**scene, "versions": old.get("versions")} if same else scene


def _merge(spec: SceneSpec, out: Path, poses) -> None:
    kinds = passes_for(spec)
    image = "wet" if "wet" in kinds else "dry"
    frames = [layout.frame(p.name, p.camera, p.split, p.kind, layout.relative_path(image, p.name),
                           layout.relative_path("dry", p.name), layout.relative_path("depth", p.name))
              for p in poses]
    write_json(out / layout.TRANSFORMS, layout.transforms_json(poses[0].camera, frames, spec.water))
    layout.write_colmap(out / layout.COLMAP, poses, image)
    write_json(out / layout.SCENE, _keep_stamp(out / layout.SCENE,
                                               scene_metadata(spec, poses, np.load(out / layout.GT_GRID))))
    files = [layout.relative_path(kind, p.name) for kind in kinds for p in poses]
    write_json(out / layout.MANIFEST, {f: layout.file_digest(out / f) for f in files}, indent=0)
    for p in poses:  # derived from the EXR, outside the manifest and the fingerprint (which read the EXR)
        tiff = layout.depth_tiff(out, p.name)
        if not tiff.is_file():
            layout.write_depth_tiff(tiff, layout.read_depth(layout.output_path(out, "depth", p.name)))
    if surveyed(spec):  # what a surveyor would hand over (`ragsplat survey`)
        banks = np.load(out / layout.GT_BANKS) if (out / layout.GT_BANKS).is_file() else None
        targets = np.load(out / layout.GT_TARGETS) if (out / layout.GT_TARGETS).is_file() else None
        write_survey(out, poses, spec.water, seed=spec.seed, banks=banks, targets=targets,
                     waterline=_waterline_xy(out),
                     region=flight.eval_region(spec))


def _waterline_xy(out: Path) -> list[np.ndarray] | None:
    """The dataset's waterline polylines as [K, 2] horizontal points (None: a scene without one)."""
    if not (out / layout.GT_WATERLINE).is_file():
        return None
    lines = json.loads((out / layout.GT_WATERLINE).read_text())["geometry"]["coordinates"]
    return [np.asarray(line, np.float64)[:, :2] for line in lines]


def generate(spec: SceneSpec, out: Path, shard: tuple[int, int] = (0, 1),
             progress: Callable[[dict], None] | None = None, retries: int = 1,
             share: Path | None = None) -> dict:
    """Render the missing images of this shard, then merge metadata if the whole dataset is present.

    `share`: a dataset of the same scene under other water (`shares_dry_passes`): its dry and depth images,
    which never see the water, are hard-linked (or copied) here instead of rendered again (the turbidity
    sweep renders one reach at several turbidities).

    `progress(event)` gets {"event": "plan", "images", "views", "passes"} before rendering starts and the
    renderer's {"event": "done", ...} after each image. A renderer that crashes (a signal in CRASH_SIGNALS) is
    started again up to `retries` times, from the images it finished, after {"event": "retry", "signal",
    "log"} (then "plan" again): Cycles once died of SIGSEGV before its first image in CI and rendered the
    same job in seven later tries."""
    t0 = time.perf_counter()
    validate(spec)
    index, count = shard
    out = Path(out)
    _prepare_out(spec, out)
    poses = flight.plan(spec)
    write_bed_assets(spec, out)
    kinds = passes_for(spec)
    mine = [p for k, p in enumerate(poses) if k % count == index]
    if share is not None:
        _link_dry_passes(spec, Path(share), out, mine)
    # Files present are checked before they are skipped (against the manifest once there is one, else by
    # decoding them): a damaged one is rendered again.
    manifest = json.loads((out / layout.MANIFEST).read_text()) if (out / layout.MANIFEST).is_file() else {}
    damaged = [layout.relative_path(kind, p.name) for kind in kinds for p in mine
               if layout.output_path(out, kind, p.name).exists()
               and not layout.intact(layout.output_path(out, kind, p.name),
                                     manifest.get(layout.relative_path(kind, p.name)))]
    tasks = [_task(spec, kind, p, layout.output_path(out, kind, p.name)) for kind in kinds for p in mine
             if not layout.output_path(out, kind, p.name).exists()
             or layout.relative_path(kind, p.name) in damaged]
    # the survey's photos through a lens (`LENS`, where the spec asks for them): the training views' wet pass
    # again, through Cycles' polynomial lens; outside the manifest and the fingerprint, as the survey is
    lensed = surveyed(spec) and spec.render.lens
    lens = [_task(spec, "wet", p, layout.output_path(out, "lens", p.name)) for p in mine if lensed
            and p.split == "train" and not layout.intact(layout.output_path(out, "lens", p.name), None)]
    # the orthographic truth, once per dataset (the first shard's), one view
    ortho = index == 0 and not layout.intact(out / layout.GT_ORTHO, None)
    stats = RenderStats()
    if tasks or lens or ortho:
        if progress is not None:
            progress({"event": "plan", "images": len(tasks) + len(lens) + ortho, "views": len(mine),
                      "passes": len(kinds) + bool(lens)})
        try:
            for job in ([render_job(spec, out, poses[0].camera, tasks)] if tasks else []) + \
                    ([render_job(spec, out, poses[0].camera, lens, LENS)] if lens else []) + \
                    ([ortho_job(spec, out)] if ortho else []):
                stats = stats.add(run_blender(job, out / "scene", progress))
        except RendererCrashed as crash:
            if retries <= 0:
                raise
            if progress is not None:
                progress({"event": "retry", "signal": crash.signum, "log": str(crash.log)})
            return generate(spec, out, shard, progress, retries - 1)
    if ortho:
        west, north, _, _ = ortho_grid(spec)
        rasters.write_world_file(out / layout.GT_ORTHO_WORLD, layout.GT_GRID_STEP, west, north)
    complete = all(layout.output_path(out, k, p.name).exists() for k in kinds for p in poses) and \
        all(layout.output_path(out, "lens", p.name).exists() for p in poses if lensed and p.split == "train")
    if complete:
        _merge(spec, out, poses)
    summary = {"rendered": stats.images, "skipped": len(mine) * len(kinds) - len(tasks), "damaged": damaged,
               "render_s": stats.render_s, "build_s": stats.build_s, "wall_s": time.perf_counter() - t0,
               "device": stats.device,
               "complete": complete, "views": len(poses), "gsd_m": flight.gsd(spec)}
    if stats.images:
        runs = out / "scene" / f"timing-{index}-{count}.json"  # one file per shard: no write races
        history = json.loads(runs.read_text()) if runs.exists() else []
        history.append({**summary, "shard": f"{index}/{count}",
                        "per_image": [event_json(e) for e in stats.done]})
        write_json(runs, history)
    return summary


DRY_PASSES = ("dry", "depth")  # the passes rendered with the water hidden (blender_scenes.render)


def shares_dry_passes(a: SceneSpec, b: SceneSpec) -> bool:
    """Whether two specs render the same dry and depth images: the same spec but for the water body's
    turbidity (the body is hidden in those passes; tests/test_blender_sweep.py compares Cycles' images) and
    the survey's lens photos. The ripples and the reflection belong to the hidden surface too, but no render
    has compared them, so they must agree."""
    def scene(spec: SceneSpec) -> dict:
        d = spec.to_dict()
        d["render"].pop("lens", None)
        (d.get("conditions") or {}).pop("turbidity", None)
        return d
    return a.water is not None and b.water is not None and scene(a) == scene(b)


def _link_dry_passes(spec: SceneSpec, source: Path, out: Path, poses) -> None:
    saved = source / "scene" / "spec.json"
    if not saved.is_file():
        raise OutputError(f"{source} holds no ragsplat generate to share dry images from")
    if not shares_dry_passes(spec, SceneSpec.from_dict(json.loads(saved.read_text()))):
        raise OutputError(f"{source} holds another scene (see {saved}): its dry images are not this one's")
    pairs = [(layout.output_path(source, kind, p.name), layout.output_path(out, kind, p.name))
             for kind in DRY_PASSES for p in poses]
    # the orthographic truth is a dry render too (its world file with it)
    pairs += [(source / name, out / name) for name in (layout.GT_ORTHO, layout.GT_ORTHO_WORLD)]
    for src, dst in pairs:
        if dst.exists() or not src.is_file():  # a damaged one is found and rendered again by generate
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src, dst)
        except OSError:  # another file system
            with atomic_path(dst) as tmp:
                tmp.write_bytes(src.read_bytes())


def overhead_fraction(summary: dict) -> float:
    """Time outside Cycles' render calls as a fraction of the time inside them."""
    return ((summary["wall_s"] - summary["render_s"]) / summary["render_s"] if summary["render_s"]
            else math.nan)


def stretch(spec: SceneSpec, out: Path, core: tuple[float, float], margin: float | None = None,
            progress: Callable[[dict], None] | None = None) -> Path:
    """A stretch of a reach as its own small dataset, for development work that cannot wait for the whole
    reach (the `long` reach renders in over an hour; a stretch of it in minutes): the wet pass of the
    training views whose camera centre lies within `margin` (default: half a nadir footprint along x) of the
    core x-range `core` (m), rendered into `out`'s own paths (a later `generate` renders only the rest), and
    out/stretch_X0_X1/ holding those views (transforms.json), their survey (survey/, as `generate` writes it,
    the edge points along the flown x-range), and the ground truth cut to the core (gt/, scene.json: scored
    by `ragsplat score --truth`, at the whole reach's maximum depth). Resumes. Returns the stretch's
    folder."""
    validate(spec)
    if spec.water is None or spec.reach is None:
        raise ConfigError("a stretch is part of a reach under water: this spec has no reach or no water")
    x0, x1 = core
    region = flight.eval_region(spec)
    if not region["xmin"] <= x0 < x1 <= region["xmax"]:
        raise ConfigError(f"the core x {x0:g} to {x1:g} m must lie inside the evaluated region's x "
                          f"{region['xmin']:.2f} to {region['xmax']:.2f} m")
    margin = flight.footprint(spec)[0] / 2 if margin is None else margin
    out = Path(out)
    _prepare_out(spec, out)
    write_bed_assets(spec, out)
    poses = flight.plan(spec)
    views = [p for p in poses
             if p.split == "train" and x0 - margin <= p.camera.camera_center[0] <= x1 + margin]
    if len(views) < 3:
        raise ConfigError(f"{len(views)} training photos within {margin:g} m of x {x0:g} to {x1:g}: a survey "
                          "needs 3 at least; widen the stretch")
    tasks = [_task(spec, "wet", p, layout.output_path(out, "wet", p.name)) for p in views
             if not layout.intact(layout.output_path(out, "wet", p.name), None)]
    if tasks:
        if progress is not None:
            progress({"event": "plan", "images": len(tasks), "views": len(views), "passes": 1})
        run_blender(render_job(spec, out, poses[0].camera, tasks), out / "scene", progress)
    root = out / f"stretch_{x0:g}_{x1:g}"
    (root / "gt").mkdir(parents=True, exist_ok=True)
    if not (root / "images").exists():
        os.symlink(os.path.relpath(out / "images", root), root / "images")
    inside = {"xmin": x0, "xmax": x1, "ymin": region["ymin"], "ymax": region["ymax"]}
    for name in (layout.GT_GRID, layout.GT_BANKS):
        nodes = np.load(out / name)
        layout.write_npy(root / name, nodes[(nodes[:, 0] >= x0) & (nodes[:, 0] < x1)])
    for name in (layout.GT_SURFACE, layout.GT_MESH, layout.GT_WATERLINE):  # the whole reach's: exact anywhere
        (root / name).write_bytes((out / name).read_bytes())
    frames = [layout.frame(p.name, p.camera, p.split, p.kind, layout.relative_path("wet", p.name))
              for p in views]
    write_json(root / layout.TRANSFORMS, layout.transforms_json(views[0].camera, frames, spec.water))
    scene = scene_metadata(spec, views, np.load(root / layout.GT_GRID))
    write_json(root / layout.SCENE, {**scene, "eval_region": inside, "passes": ["wet"],
                                     "stretch": {"core_x": [x0, x1], "margin_m": margin, "of": str(out)}})
    write_survey(root, views, spec.water, seed=spec.seed, banks=np.load(root / layout.GT_BANKS),
                 waterline=_waterline_xy(out),
                 region={**inside, "xmin": x0 - margin, "xmax": x1 + margin})
    return root
