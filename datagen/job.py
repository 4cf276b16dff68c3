"""The renderer boundary: the job datagen hands to the Blender process, and the events it prints back.

Blender runs as its own process (`python -m ragsplat.blender_scenes.render JOB.json`): datagen builds a
`RenderJob` (`ragsplat.datagen.build.render_job`), writes it with `to_json()` and reads the events; the
renderer reads the job with `RenderJob.from_json` and prints `Ready` and `Done`. Both sides import this
module, which imports no bpy (and no torch): the arrow goes from blender_scenes to datagen, never back.

All geometry comes ready-made in one .npz (`RenderJob.geometry`): object `name`'s mesh is `{name}_verts`
[V, 3], `{name}_tris` [F, 3] and optionally `{name}_uv` [V, 2]; a rippled water mesh also has `water_weight`
[V]. Values are frozen (tuples, not lists or arrays), so two jobs compare equal when they render the same.
Fields that are None and default to None (a lens, ripples, a task's phases, a slope) are left out of the JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields, is_dataclass
from typing import ClassVar

import numpy as np

from ragsplat.datagen.spec import LightSpec
from ragsplat.errors import RagsplatError

PROTOCOL = "@@ragsplat "  # prefix of the renderer's event lines on stdout; every other line is Blender's log


def _frozen(values) -> tuple:
    """A list or array of floats (any nesting) as nested tuples of Python floats."""
    def tuples(v):
        return tuple(tuples(x) for x in v) if isinstance(v, list) else v
    return tuples(np.asarray(values, np.float64).tolist())


def _freeze(obj, *names: str) -> None:
    """Set the frozen dataclass `obj`'s fields `names` (those not None) to nested tuples of floats."""
    for name in names:
        if getattr(obj, name) is not None:
            object.__setattr__(obj, name, _frozen(getattr(obj, name)))


def _encode(value):
    """A job part as JSON values (dataclasses as objects, a material with its "kind")."""
    if not is_dataclass(value):
        return [_encode(v) for v in value] if isinstance(value, tuple) else value
    out = {"kind": value.kind} if isinstance(value, MATERIALS) else {}
    for f in fields(value):
        v = getattr(value, f.name)
        if v is None and f.default is None:
            continue
        out[f.name] = _encode(v)
    return out


# Materials: the renderer builds one Cycles node tree per kind (`ragsplat.blender_scenes.render._material`).

@dataclass(frozen=True)
class Texture:
    """Diffuse albedo from an image, repeating (the floor repeats the periodic border texture)."""
    kind: ClassVar[str] = "texture"
    image: str  # PNG path


@dataclass(frozen=True)
class Emission:
    kind: ClassVar[str] = "emission"
    strength: float


@dataclass(frozen=True)
class Diffuse:
    kind: ClassVar[str] = "diffuse"
    color: float  # grey albedo (linear)


@dataclass(frozen=True)
class Refraction:
    """The water surface: pure refraction, visible to camera rays only; with `reflect`, Fresnel reflection
    of sky and sun. `color` carries the 1/n^2 radiance drop that Cycles does not apply itself (1: none)."""
    kind: ClassVar[str] = "refraction"
    ior: float
    color: float
    reflect: bool = False


@dataclass(frozen=True)
class Volume:
    """The water body: homogeneous absorption and scattering (1/m, linear RGB) without a surface."""
    kind: ClassVar[str] = "volume"
    absorption: tuple[float, float, float]
    scattering: tuple[float, float, float]

    def __post_init__(self):
        _freeze(self, "absorption", "scattering")


Material = Texture | Emission | Diffuse | Refraction | Volume
MATERIALS = (Texture, Emission, Diffuse, Refraction, Volume)


def material_from_json(d: dict) -> Material:
    kinds = {m.kind: m for m in MATERIALS}
    if d.get("kind") not in kinds:
        raise RagsplatError(f"unknown material kind {d.get('kind')!r}; one of {', '.join(kinds)}")
    return kinds[d["kind"]](**{k: v for k, v in d.items() if k != "kind"})


@dataclass(frozen=True)
class SceneObject:
    """A mesh of the geometry file (`{name}_verts`, ...) with its material. A `wet_only` object is hidden in
    the dry and depth passes, as the water surface is."""
    name: str
    material: Material
    wet_only: bool = False

    @classmethod
    def from_json(cls, d: dict) -> SceneObject:
        return cls(d["name"], material_from_json(d["material"]), d.get("wet_only", False))


@dataclass(frozen=True)
class RenderSettings:
    """Cycles' settings for every task of a job (`ragsplat.datagen.spec.RenderSpec` with the dataset's
    seed)."""
    samples: int  # per pixel, colour passes
    device: str  # "CPU", "GPU" or "auto"
    threads: int  # 0: all cores
    seed: int
    filter_width: float  # px, colour passes (Blackman-Harris)
    depth_filter: float  # px, the depth pass (tiny: the exact surface at the pixel centre)
    exposure: float  # stops


@dataclass(frozen=True)
class Intrinsics:
    """The pinhole every task renders through (square pixels, principal point centred); with
    `fisheye_polynomial` [k0..k4], Cycles' polynomial lens instead: a lens with radial distortion
    (`ragsplat.datagen.survey.lens_polynomial`); with `ortho_scale`, Cycles' orthographic camera, its view
    `ortho_scale` metres across the image's larger side (fx and fy unused)."""
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    fisheye_polynomial: tuple[float, ...] | None = None
    ortho_scale: float | None = None

    def __post_init__(self):
        _freeze(self, "fisheye_polynomial")


@dataclass(frozen=True)
class Ripples:
    """The water mesh of a wet task with `phases` is moved to that photo's surface before it renders: the
    mean surface level + sx x + sy y (`slope`, None: flat) plus `water_weight` times the ripples
    (`ragsplat.datagen.conditions.ripple_height`)."""
    k: tuple[tuple[float, float], ...]  # [K, 2] wave vectors (rad/m)
    amplitude: tuple[float, ...]  # [K] (m)
    level: float
    slope: tuple[float, float] | None = None  # (dz/dx, dz/dy)

    def __post_init__(self):
        _freeze(self, "k", "amplitude", "slope")


@dataclass(frozen=True)
class Task:
    """One image: pass `kind` ("wet" with the water objects, "dry" without, "depth": Cycles' z-depth of
    the dry scene) seen from `c2w_gl` (4 x 4, OpenGL camera axes), written to `out`; `phases` [K]: its own
    rippled surface (wet tasks of a rippled job)."""
    kind: str
    name: str
    c2w_gl: tuple[tuple[float, ...], ...]
    out: str
    phases: tuple[float, ...] | None = None

    def __post_init__(self):
        _freeze(self, "c2w_gl", "phases")


@dataclass(frozen=True)
class RenderJob:
    """What one Blender process renders, in order, from one scene built once (persistent data)."""
    geometry: str  # the .npz of every object's mesh
    objects: tuple[SceneObject, ...]
    water: str | None  # the water surface's object (camera rays only, hidden in dry and depth), or none
    light: LightSpec | None  # sun and sky; None: a black world (emitters only)
    render: RenderSettings
    camera: Intrinsics
    tasks: tuple[Task, ...]
    ripples: Ripples | None = None
    glossy_bounces: int = 0  # 1 for a reflecting surface: the mirror ray that sees sky and sun

    def __post_init__(self):
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "tasks", tuple(self.tasks))

    def to_json(self) -> dict:
        return _encode(self)

    @classmethod
    def from_json(cls, d: dict) -> RenderJob:
        return cls(geometry=d["geometry"], objects=tuple(SceneObject.from_json(o) for o in d["objects"]),
                   water=d["water"], light=None if d["light"] is None else LightSpec(**d["light"]),
                   render=RenderSettings(**d["render"]), camera=Intrinsics(**d["camera"]),
                   tasks=tuple(Task(**t) for t in d["tasks"]),
                   ripples=Ripples(**d["ripples"]) if d.get("ripples") is not None else None,
                   glossy_bounces=d.get("glossy_bounces", 0))


# Events: one line each on the renderer's stdout, PROTOCOL followed by the event's JSON.

@dataclass(frozen=True)
class Ready:
    """The scene is built (start-up, meshes, materials, device)."""
    event: ClassVar[str] = "ready"
    build_s: float
    device: str  # the device Cycles uses, e.g. "CPU" or "GPU (OPTIX: ...)"


@dataclass(frozen=True)
class Done:
    """One task's image is written (complete: atomically renamed)."""
    event: ClassVar[str] = "done"
    name: str
    kind: str  # the task's pass
    render_s: float  # inside bpy.ops.render.render: Cycles sync + path tracing + Blender's file write
    cycles_s: float | None  # Cycles' own render and sync stamps (colour passes; None for depth)
    total_s: float  # the whole task, file conversion included


Event = Ready | Done
EVENTS = {e.event: e for e in (Ready, Done)}


def event_json(event: Event) -> dict:
    """The event as a dict, {"event": "ready" | "done", **fields} (what `ragsplat.datagen.build.generate`
    reports)."""
    return {"event": event.event, **{f.name: getattr(event, f.name) for f in fields(event)}}


def event_line(event: Event) -> str:
    return PROTOCOL + json.dumps(event_json(event))


def parse_event(line: str) -> Event | None:
    """The event on a renderer's stdout `line`, or None for a line of Blender's own log."""
    if not line.startswith(PROTOCOL):
        return None
    try:
        d = json.loads(line.removeprefix(PROTOCOL))
        return EVENTS[d.pop("event")](**d)
    except (ValueError, KeyError, TypeError, AttributeError):
        raise RagsplatError(f"renderer event not understood: {line.strip()!r}") from None
